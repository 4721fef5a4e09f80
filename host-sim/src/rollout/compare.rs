//! Two rollouts of the same command stream, frame by frame.

use anyhow::{bail, Result};
use phasegate_controller::geom::unyaw3;
use phasegate_controller::layout::JOINTS;
use phasegate_controller::Pose;
use serde::Serialize;
use std::f64::consts::TAU;
use std::fmt::Write;

use super::metrics::{quantile, wrap_angle};
use super::record::Rollout;

/// Errors at one frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct FrameErrors {
    /// Mean over joints of the root-relative joint position error, units.
    pub joint_mean: f64,
    /// 99th percentile over the 31 joints (linear interpolation), units.
    pub joint_p99: f64,
    /// Largest over joints, units.
    pub joint_max: f64,
    /// Ground-plane distance between the roots, units.
    pub root_drift: f64,
    /// Absolute yaw difference, radians.
    pub heading_drift: f64,
    /// Absolute phase difference (wrapped), radians.
    pub phase_error: f64,
}

/// Over the whole rollout.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Summary {
    /// Frames compared.
    pub frames: usize,
    /// Mean over all (frame, joint) root-relative errors, units.
    pub joint_mean: f64,
    /// 99th percentile over all (frame, joint) errors, units.
    pub joint_p99: f64,
    /// Largest (frame, joint) error, units.
    pub joint_max: f64,
    /// Largest per-frame 99th percentile (what the fidelity bar holds
    /// "at every frame"), units.
    pub worst_frame_p99: f64,
    /// Root drift at the last frame, units.
    pub root_drift_final: f64,
    /// Largest root drift, units.
    pub root_drift_max: f64,
    /// Heading drift at the last frame, radians.
    pub heading_drift_final: f64,
    /// Largest heading drift, radians.
    pub heading_drift_max: f64,
    /// Mean phase error, radians.
    pub phase_error_mean: f64,
    /// Largest phase error, radians.
    pub phase_error_max: f64,
}

/// Per-frame errors and their summary.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Comparison {
    /// One entry per frame.
    pub frames: Vec<FrameErrors>,
    /// Over all frames.
    pub summary: Summary,
}

/// Joint positions in the pose's own root frame.
pub fn root_relative(p: &Pose<f64>) -> [[f64; 3]; JOINTS] {
    let r = p.root_position;
    p.joint_positions
        .map(|j| unyaw3(p.facing, [j[0] - r[0], j[1] - r[1], j[2] - r[2]]))
}

fn frame_errors(a: &Pose<f64>, b: &Pose<f64>, all: &mut Vec<f64>) -> FrameErrors {
    let (ra, rb) = (root_relative(a), root_relative(b));
    let mut e: Vec<f64> = ra
        .iter()
        .zip(&rb)
        .map(|(x, y)| {
            ((x[0] - y[0]).powi(2) + (x[1] - y[1]).powi(2) + (x[2] - y[2]).powi(2)).sqrt()
        })
        .collect();
    all.extend(&e);
    let mean = e.iter().sum::<f64>() / e.len() as f64;
    let max = e.iter().copied().fold(0.0, f64::max);
    let dx = a.root_position[0] - b.root_position[0];
    let dz = a.root_position[2] - b.root_position[2];
    FrameErrors {
        joint_mean: mean,
        joint_p99: quantile(&mut e, 0.99),
        joint_max: max,
        root_drift: (dx * dx + dz * dz).sqrt(),
        heading_drift: wrap_angle(a.yaw() - b.yaw()).abs(),
        phase_error: wrap_angle((a.phase - b.phase) * TAU).abs(),
    }
}

/// Compares two rollouts frame by frame. They must have the same length
/// and, to mean anything, the same commands: a mismatch is refused.
pub fn compare(a: &Rollout, b: &Rollout) -> Result<Comparison> {
    if a.len() != b.len() {
        bail!("rollouts have {} and {} frames", a.len(), b.len());
    }
    if a.is_empty() {
        bail!("rollouts are empty");
    }
    if let Some(i) = a.commands.iter().zip(&b.commands).position(|(x, y)| x != y) {
        bail!("the rollouts were driven by different commands (first difference at frame {i})");
    }
    let mut all = Vec::with_capacity(a.len() * JOINTS);
    let frames: Vec<FrameErrors> = a
        .poses
        .iter()
        .zip(&b.poses)
        .map(|(x, y)| frame_errors(x, y, &mut all))
        .collect();
    let last = frames.last().copied().unwrap_or_default();
    let fold = |f: fn(&FrameErrors) -> f64| frames.iter().map(f).fold(0.0, f64::max);
    let n = frames.len() as f64;
    let summary = Summary {
        frames: frames.len(),
        joint_mean: all.iter().sum::<f64>() / all.len() as f64,
        joint_p99: quantile(&mut all, 0.99),
        joint_max: fold(|f| f.joint_max),
        worst_frame_p99: fold(|f| f.joint_p99),
        root_drift_final: last.root_drift,
        root_drift_max: fold(|f| f.root_drift),
        heading_drift_final: last.heading_drift,
        heading_drift_max: fold(|f| f.heading_drift),
        phase_error_mean: frames.iter().map(|f| f.phase_error).sum::<f64>() / n,
        phase_error_max: fold(|f| f.phase_error),
    };
    Ok(Comparison { frames, summary })
}

impl Comparison {
    /// Per-frame table (every `every`-th frame and the last) and summary.
    pub fn table(&self, every: usize) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "{:>6} {:>10} {:>10} {:>10} {:>11} {:>12} {:>11}",
            "frame",
            "joint mean",
            "joint p99",
            "joint max",
            "root drift",
            "heading rad",
            "phase rad"
        );
        let every = every.max(1);
        for (i, f) in self.frames.iter().enumerate() {
            if i % every == every - 1 || i + 1 == self.frames.len() {
                let _ = writeln!(
                    s,
                    "{:>6} {:>10.4} {:>10.4} {:>10.4} {:>11.4} {:>12.5} {:>11.5}",
                    i,
                    f.joint_mean,
                    f.joint_p99,
                    f.joint_max,
                    f.root_drift,
                    f.heading_drift,
                    f.phase_error
                );
            }
        }
        let m = &self.summary;
        let _ = writeln!(
            s,
            "\nsummary over {} frames (positions in capture units, about 1 cm):",
            m.frames
        );
        let _ = writeln!(
            s,
            "  root-relative joint position error  mean {:.4}  p99 {:.4}  max {:.4}  (worst frame p99 {:.4})",
            m.joint_mean, m.joint_p99, m.joint_max, m.worst_frame_p99
        );
        let _ = writeln!(
            s,
            "  root position drift                 final {:.4}  max {:.4}",
            m.root_drift_final, m.root_drift_max
        );
        let _ = writeln!(
            s,
            "  heading drift (rad)                 final {:.5}  max {:.5}",
            m.heading_drift_final, m.heading_drift_max
        );
        let _ = writeln!(
            s,
            "  phase error (rad)                   mean {:.5}  max {:.5}",
            m.phase_error_mean, m.phase_error_max
        );
        s
    }
}
