//! Physical sanity metrics: is a rollout plausible, without looking at it?

use phasegate_controller::layout::{CONTACT_JOINTS, PARENTS};
use serde::Serialize;
use std::f64::consts::{PI, TAU};
use std::fmt;

use super::record::Rollout;

/// Contact values above this count as a planted foot.
pub const CONTACT_THRESHOLD: f64 = 0.5;

/// The metrics. The first four are the headline figures (compared between
/// rollouts by the fidelity bars); the rest add detail.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Sanity {
    /// Mean over frames and bones of `| |bone| - |bone in the mean pose| |`, units.
    pub bone_error_mean: f64,
    /// Mean horizontal speed of heel and toe joints while their contact
    /// value exceeds [`CONTACT_THRESHOLD`], units per second (0 if never).
    pub skate_mean: f64,
    /// Mean over frames of the depth of the lowest joint below the ground
    /// (0 where none is below), units.
    pub penetration_mean: f64,
    /// Mean phase advance, radians per second.
    pub phase_rate: f64,
    /// Largest bone length error, units.
    pub bone_error_max: f64,
    /// 95th percentile of the contact-foot speeds, units per second.
    pub skate_p95: f64,
    /// Deepest any joint went below the ground, units.
    pub penetration_max: f64,
    /// Share of foot-frames in contact.
    pub contact_share: f64,
}

impl Sanity {
    /// The headline metrics with names, for bar checks and tables.
    pub fn headline(&self) -> [(&'static str, f64); 4] {
        [
            ("bone length error (units)", self.bone_error_mean),
            ("foot skating (units/s)", self.skate_mean),
            ("ground penetration (units)", self.penetration_mean),
            ("phase advance (rad/s)", self.phase_rate),
        ]
    }
}

/// `p`-quantile by linear interpolation between order statistics (NumPy's
/// default); 0 for no values.
pub fn quantile(values: &mut [f64], p: f64) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    values.sort_by(f64::total_cmp);
    let pos = p.clamp(0.0, 1.0) * (values.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = (lo + 1).min(values.len() - 1);
    values[lo] + (values[hi] - values[lo]) * (pos - lo as f64)
}

/// Wraps an angle difference into `(-pi, pi]`.
pub fn wrap_angle(a: f64) -> f64 {
    let w = (a + PI).rem_euclid(TAU) - PI;
    if w <= -PI {
        w + TAU
    } else {
        w
    }
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Computes the metrics of a rollout.
pub fn sanity(r: &Rollout) -> Sanity {
    let bones: Vec<(usize, usize, f64)> = PARENTS
        .iter()
        .enumerate()
        .filter_map(|(j, &p)| {
            let p = usize::try_from(p).ok()?;
            Some((j, p, dist(r.mean_pose[j], r.mean_pose[p])))
        })
        .collect();
    let (mut bone_sum, mut bone_n, mut bone_max) = (0.0, 0usize, 0f64);
    let (mut pen_sum, mut pen_max) = (0.0, 0f64);
    for pose in &r.poses {
        let jp = &pose.joint_positions;
        for &(j, p, rest) in &bones {
            let e = (dist(jp[j], jp[p]) - rest).abs();
            bone_sum += e;
            bone_n += 1;
            bone_max = bone_max.max(e);
        }
        let lowest = jp.iter().map(|p| p[1]).fold(f64::INFINITY, f64::min);
        let depth = (-lowest).max(0.0);
        pen_sum += depth;
        pen_max = pen_max.max(depth);
    }
    let mut speeds = Vec::new();
    let mut foot_frames = 0usize;
    for w in r.poses.windows(2) {
        for (k, &j) in CONTACT_JOINTS.iter().enumerate() {
            foot_frames += 1;
            if w[1].contacts[k] > CONTACT_THRESHOLD {
                let (a, b) = (w[0].joint_positions[j], w[1].joint_positions[j]);
                let h = ((b[0] - a[0]).powi(2) + (b[2] - a[2]).powi(2)).sqrt();
                speeds.push(h * r.frame_rate);
            }
        }
    }
    let phase_steps: f64 = r
        .poses
        .windows(2)
        .map(|w| wrap_angle((w[1].phase - w[0].phase) * TAU))
        .sum();
    let frames = r.poses.len().max(1) as f64;
    let skate_mean = if speeds.is_empty() {
        0.0
    } else {
        speeds.iter().sum::<f64>() / speeds.len() as f64
    };
    let contact_share = speeds.len() as f64 / foot_frames.max(1) as f64;
    Sanity {
        bone_error_mean: bone_sum / bone_n.max(1) as f64,
        skate_mean,
        penetration_mean: pen_sum / frames,
        phase_rate: phase_steps / (r.poses.len().saturating_sub(1).max(1) as f64) * r.frame_rate,
        bone_error_max: bone_max,
        skate_p95: quantile(&mut speeds, 0.95),
        penetration_max: pen_max,
        contact_share,
    }
}

impl fmt::Display for Sanity {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "physical sanity:")?;
        writeln!(
            f,
            "  bone length error   mean {:8.3}  max {:8.3} units (vs the mean pose)",
            self.bone_error_mean, self.bone_error_max
        )?;
        writeln!(
            f,
            "  foot skating        mean {:8.2}  p95 {:8.2} units/s (heels and toes in contact, {:.0}% of foot-frames)",
            self.skate_mean,
            self.skate_p95,
            100.0 * self.contact_share
        )?;
        writeln!(
            f,
            "  ground penetration  mean {:8.3}  max {:8.3} units (lowest joint below y = 0)",
            self.penetration_mean, self.penetration_max
        )?;
        writeln!(
            f,
            "  phase advance            {:8.3} rad/s ({:.3} cycles/s)",
            self.phase_rate,
            self.phase_rate / TAU
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use phasegate_controller::Pose;

    #[test]
    fn quantiles_interpolate() {
        let mut v = vec![3.0, 1.0, 2.0, 4.0];
        assert_eq!(quantile(&mut v, 0.0), 1.0);
        assert_eq!(quantile(&mut v, 1.0), 4.0);
        assert_eq!(quantile(&mut v, 0.5), 2.5);
        assert_eq!(quantile(&mut [], 0.5), 0.0);
    }

    #[test]
    fn angles_wrap() {
        assert!((wrap_angle(3.0 * PI / 2.0) + PI / 2.0).abs() < 1e-12);
        assert_eq!(wrap_angle(PI), PI);
        assert_eq!(wrap_angle(-PI), PI);
    }

    #[test]
    fn a_sliding_planted_foot_skates_and_a_sunk_one_penetrates() {
        let mut mean = [[0.0; 3]; 31];
        for (j, m) in mean.iter_mut().enumerate() {
            m[1] = 10.0 + j as f64;
        }
        let mut poses = Vec::new();
        for f in 0..61 {
            let mut p = Pose::<f64>::zero();
            for (j, jp) in p.joint_positions.iter_mut().enumerate() {
                *jp = [f as f64, mean[j][1] - 11.0, 0.0];
            }
            p.contacts = [1.0; 4];
            p.phase = (f as f64 / 60.0).fract();
            poses.push(p);
        }
        let r = Rollout {
            commands: vec![Default::default(); poses.len()],
            poses,
            mean_pose: mean,
            frame_rate: 60.0,
        };
        let s = sanity(&r);
        assert!(s.bone_error_mean < 1e-12);
        assert!((s.skate_mean - 60.0).abs() < 1e-9);
        assert!((s.penetration_mean - 1.0).abs() < 1e-12);
        assert!((s.phase_rate - TAU).abs() < 1e-9);
        assert_eq!(s.contact_share, 1.0);
    }
}
