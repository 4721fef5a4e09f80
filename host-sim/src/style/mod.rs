//! Styles on the host: the styled networks behind the controller loop
//! (float reference: the base chain with its adapters as graph nodes,
//! `Net::with_adapters`, run by `FloatNet64`; and the fixed-point `Runtime`
//! with its style bank), rollouts, style metrics and pictures, and the
//! adapter-learning demonstration ([`demo`]).

pub mod demo;

use anyhow::{anyhow, Result};
use phasegate::{Mix, Model, Runtime, Style};
use phasegate_controller::layout::JOINTS;
use phasegate_controller::{Command, Locomotion, Network, Pose, Real};
use std::f64::consts::TAU;
use std::fmt::Write as _;

/// The float PFNN (cubic gating) from a weight directory or an `.npz`.
pub fn load_float(path: &std::path::Path) -> Result<exporter::net::Net> {
    exporter::cp::cli::load_dense(path, exporter::net::GatingMode::Cubic)
}

/// Activation width of host styled runtimes.
pub const WIDTH: usize = 2048;
/// Adapter scratch of host styled runtimes.
pub const SCRATCH: usize = 4096;
/// Styles a host styled runtime holds.
pub const BANK: usize = 8;

/// The fixed-point styled runtime behind the controller loop (f32 glue, as
/// on the device).
pub struct StyledFixed<'a> {
    /// The runtime.
    pub rt: Box<Runtime<'a, WIDTH, SCRATCH, BANK>>,
}

impl<'a> StyledFixed<'a> {
    /// A base blob and style blobs, all validated and attached.
    pub fn new(base: &'a [u8], styles: &[&'a [u8]]) -> Result<Self> {
        let model = Model::from_bytes(base).map_err(|e| anyhow!("base blob: {e}"))?;
        let mut rt = Box::new(Runtime::new(model).map_err(|e| anyhow!("{e}"))?);
        for (i, s) in styles.iter().enumerate() {
            let style = Style::from_bytes(s).map_err(|e| anyhow!("style {i}: {e}"))?;
            rt.add_style(style).map_err(|e| anyhow!("style {i}: {e}"))?;
        }
        Ok(StyledFixed { rt })
    }
}

impl Network<f32> for StyledFixed<'_> {
    fn input_dim(&self) -> usize {
        self.rt.input_dim()
    }

    fn output_dim(&self) -> usize {
        self.rt.output_dim()
    }

    fn predict(
        &mut self,
        phase: f32,
        x: &[f32],
        y: &mut [f32],
    ) -> phasegate_controller::Result<()> {
        self.rt.predict(phase, x, y)
    }

    fn mean_output(&self, y: &mut [f32]) -> phasegate_controller::Result<()> {
        self.rt.mean_output(y)
    }
}

/// One rollout: poses and what the network saw and said each frame.
#[derive(Clone, Debug, Default)]
pub struct Run {
    /// Poses (widened to f64).
    pub poses: Vec<Pose<f64>>,
    /// Network inputs, model units.
    pub inputs: Vec<Vec<f64>>,
    /// Network outputs, model units.
    pub outputs: Vec<Vec<f64>>,
    /// Phases, radians.
    pub phases: Vec<f64>,
}

pub(crate) fn widen<R: Real>(p: &Pose<R>) -> Pose<f64> {
    let v3 = |v: [R; 3]| v.map(Real::to_f64);
    Pose {
        frame: p.frame,
        root_position: v3(p.root_position),
        facing: p.facing.map(Real::to_f64),
        joint_positions: p.joint_positions.map(v3),
        joint_rotations: p.joint_rotations.map(|q| q.map(Real::to_f64)),
        contacts: p.contacts.map(Real::to_f64),
        phase: p.phase.to_f64(),
        gaits: p.gaits.map(Real::to_f64),
    }
}

/// Runs the controller loop over `net` for `commands` (one per frame).
pub fn rollout<R: Real, N: Network<R>>(net: &mut N, commands: &[Command]) -> Result<Run> {
    let mut state = Locomotion::<R>::new(net).map_err(|e| anyhow!("{e}"))?;
    let mut run = Run::default();
    for c in commands {
        let pose = state.step(net, c).map_err(|e| anyhow!("{e}"))?;
        let phase = pose.phase.to_f64() * TAU;
        run.poses.push(widen(pose));
        run.inputs
            .push(state.last_input().iter().map(|v| v.to_f64()).collect());
        run.outputs
            .push(state.last_output().iter().map(|v| v.to_f64()).collect());
        run.phases.push(phase);
    }
    Ok(run)
}

/// Joint positions relative to the root, in the root's frame (x right,
/// y up, z forward).
pub fn root_space(p: &Pose<f64>) -> [[f64; 3]; JOINTS] {
    let [fx, fz] = p.facing;
    p.joint_positions.map(|j| {
        let (dx, dz) = (j[0] - p.root_position[0], j[2] - p.root_position[2]);
        // Right is (fz, -fx) for facing (fx, fz) with y up.
        [dx * fz - dz * fx, j[1], dx * fx + dz * fz]
    })
}

/// Head joint.
pub const HEAD: usize = 16;
/// Hand joints (left, right).
pub const HANDS: [usize; 2] = [20, 27];

/// What a style changes, measured on a rollout (frames from `skip` on).
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct StyleMetrics {
    /// Mean head height.
    pub head_height: f64,
    /// Mean hips height.
    pub hips_height: f64,
    /// Standard deviation of the hands' forward (z) position in root space:
    /// the amplitude of the arm swing.
    pub hand_swing: f64,
    /// Distance the root travelled.
    pub distance: f64,
}

/// [`StyleMetrics`] of `poses[skip..]`.
pub fn metrics(poses: &[Pose<f64>], skip: usize) -> StyleMetrics {
    let ps = &poses[skip.min(poses.len())..];
    let n = ps.len().max(1) as f64;
    let mut m = StyleMetrics::default();
    let mut hz = [Vec::new(), Vec::new()];
    for p in ps {
        let r = root_space(p);
        m.head_height += r[HEAD][1] / n;
        m.hips_height += r[0][1] / n;
        for (h, &j) in hz.iter_mut().zip(&HANDS) {
            h.push(r[j][2]);
        }
    }
    let sd = |v: &[f64]| {
        let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
        (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / v.len().max(1) as f64).sqrt()
    };
    m.hand_swing = 0.5 * (sd(&hz[0]) + sd(&hz[1]));
    if let (Some(a), Some(b)) = (ps.first(), ps.last()) {
        m.distance = ((b.root_position[0] - a.root_position[0]).powi(2)
            + (b.root_position[2] - a.root_position[2]).powi(2))
        .sqrt();
    }
    m
}

/// RMS and max distance between the root-space joint positions of two runs.
pub fn pose_difference(a: &[Pose<f64>], b: &[Pose<f64>]) -> (f64, f64) {
    let (mut sq, mut max, mut n) = (0.0, 0.0f64, 0usize);
    for (pa, pb) in a.iter().zip(b) {
        for (ja, jb) in root_space(pa).iter().zip(root_space(pb).iter()) {
            let d = ((ja[0] - jb[0]).powi(2) + (ja[1] - jb[1]).powi(2) + (ja[2] - jb[2]).powi(2))
                .sqrt();
            sq += d * d;
            max = max.max(d);
            n += 1;
        }
    }
    ((sq / n.max(1) as f64).sqrt(), max)
}

/// Mix label.
pub fn mix_label(m: Mix, names: &[&str]) -> String {
    let n = |id: phasegate::StyleId| {
        names
            .get(usize::from(id.0))
            .copied()
            .unwrap_or("?")
            .to_string()
    };
    match m {
        Mix::Base => "base".to_string(),
        Mix::One(s) => n(s),
        Mix::Blend { from, to, weight } => {
            format!(
                "{:.0}% {} + {:.0}% {}",
                100.0 * (1.0 - weight.to_num::<f64>()),
                n(from),
                100.0 * weight.to_num::<f64>(),
                n(to)
            )
        }
    }
}

/// Side views (root space, facing right) of several runs at the same
/// frames, one row per run, as an SVG document.
pub fn svg_side_views(
    runs: &[(&str, &[Pose<f64>], &str)],
    frames: &[usize],
    title: &str,
) -> String {
    let (cell_w, cell_h, label_w) = (150.0, 230.0, 150.0);
    let w = label_w + cell_w * frames.len() as f64;
    let h = 40.0 + cell_h * runs.len() as f64;
    let mut s = String::new();
    let _ = writeln!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}" font-family="sans-serif">"#
    );
    let _ = writeln!(s, r#"<rect width="{w}" height="{h}" fill="white"/>"#);
    let _ = writeln!(s, r#"<text x="10" y="24" font-size="16">{title}</text>"#);
    let parents = phasegate_controller::layout::PARENTS;
    for (row, (name, poses, colour)) in runs.iter().enumerate() {
        let y0 = 40.0 + cell_h * row as f64;
        let _ = writeln!(
            s,
            r#"<text x="10" y="{}" font-size="13">{name}</text>"#,
            y0 + cell_h / 2.0
        );
        for (col, &f) in frames.iter().enumerate() {
            let Some(p) = poses.get(f) else { continue };
            let x0 = label_w + cell_w * col as f64 + cell_w / 2.0;
            let ground = y0 + cell_h - 20.0;
            let _ = writeln!(
                s,
                r##"<line x1="{}" y1="{ground}" x2="{}" y2="{ground}" stroke="#bbb"/>"##,
                x0 - cell_w / 2.0 + 5.0,
                x0 + cell_w / 2.0 - 5.0
            );
            if row == 0 {
                let _ = writeln!(
                    s,
                    r#"<text x="{}" y="{}" font-size="11">frame {f}</text>"#,
                    x0 - 25.0,
                    y0 + 12.0
                );
            }
            let r = root_space(p);
            // Side view: forward (z) to the right, up is up; 1 unit = 1.1 px.
            let px = |j: usize| (x0 + 1.1 * r[j][2], ground - 1.1 * r[j][1]);
            for (j, &par) in parents.iter().enumerate() {
                if par < 0 {
                    continue;
                }
                let ((ax, ay), (bx, by)) = (px(j), px(par as usize));
                let left = (1..=5).contains(&j) || (17..=23).contains(&j);
                let opacity = if left { 0.45 } else { 1.0 };
                let _ = writeln!(
                    s,
                    r#"<line x1="{ax:.1}" y1="{ay:.1}" x2="{bx:.1}" y2="{by:.1}" stroke="{colour}" stroke-width="3" stroke-opacity="{opacity}" stroke-linecap="round"/>"#
                );
            }
        }
    }
    s += "</svg>\n";
    s
}

/// The side views of [`svg_side_views`] as a PNG: the title on top, each
/// run's name above its row, frame numbers under the first row; the far
/// (left) limbs lighter.
pub fn png_side_views(
    runs: &[(&str, &[Pose<f64>], &str)],
    frames: &[usize],
    title: &str,
    path: &std::path::Path,
) -> Result<()> {
    side_views_canvas(runs, frames, title).save_png(path)
}

/// The picture [`png_side_views`] writes.
pub fn side_views_canvas(
    runs: &[(&str, &[Pose<f64>], &str)],
    frames: &[usize],
    title: &str,
) -> crate::render::canvas::Canvas {
    use crate::render::canvas::{Canvas, BLACK, WHITE};
    let (cell_w, cell_h, top) = (150.0, 230.0, 34.0);
    let mut c = Canvas::new(
        (cell_w * frames.len() as f64) as usize,
        (top + cell_h * runs.len() as f64) as usize,
        WHITE,
    );
    c.text(8.0, 10.0, title, 2, BLACK);
    let hex = |code: &str| -> [u8; 3] {
        let v = u32::from_str_radix(code.trim_start_matches('#'), 16).unwrap_or(0);
        [(v >> 16) as u8, (v >> 8) as u8, v as u8]
    };
    let lighter = |rgb: [u8; 3]| rgb.map(|v| (f64::from(v) * 0.45 + 255.0 * 0.55) as u8);
    let parents = phasegate_controller::layout::PARENTS;
    for (row, (name, poses, colour)) in runs.iter().enumerate() {
        let (near, far) = (hex(colour), lighter(hex(colour)));
        let y0 = top + cell_h * row as f64;
        c.text(8.0, y0 + 6.0, name, 2, near);
        for (col, &f) in frames.iter().enumerate() {
            let Some(p) = poses.get(f) else { continue };
            let x0 = cell_w * col as f64 + cell_w / 2.0;
            let ground = y0 + cell_h - 20.0;
            let left = cell_w * col as f64;
            c.line(
                (left + 5.0, ground),
                (left + cell_w - 5.0, ground),
                1.0,
                [190; 3],
            );
            if row == 0 {
                c.text(left + 5.0, ground + 6.0, &format!("frame {f}"), 1, [120; 3]);
            }
            let r = root_space(p);
            let px = |j: usize| (x0 + 1.1 * r[j][2], ground - 1.1 * r[j][1]);
            for (j, &par) in parents.iter().enumerate() {
                if par < 0 {
                    continue;
                }
                let is_left = (1..=5).contains(&j) || (17..=23).contains(&j);
                let colour = if is_left { far } else { near };
                c.line(px(j), px(par as usize), 3.0, colour);
            }
        }
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;
    use phasegate_controller::{Gait, PfnnController};

    /// The PNG has the layout asked for, and its title and row labels are
    /// drawn (the raster is otherwise white above the first skeletons).
    #[test]
    fn side_views_png_has_rows_columns_and_labels() {
        let model = Model::from_bytes(crate::default_model::BLOB).unwrap();
        let mut ctl: Box<PfnnController<phasegate::Runtime<'_, 512>>> =
            Box::new(PfnnController::from_model(model).unwrap());
        let poses: Vec<Pose<f64>> = (0..30)
            .map(|_| widen(ctl.step(&Command::moving([0.0, 1.5], Gait::Walk)).unwrap()))
            .collect();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("views.png");
        let rows: [(&str, &[Pose<f64>], &str); 2] =
            [("first", &poses, "#1f5fbf"), ("second", &poses, "#d9661f")];
        png_side_views(&rows, &[5, 15, 25], "title", &path).unwrap();
        let decoder = png::Decoder::new(std::fs::File::open(&path).unwrap());
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (3 * 150, 34 + 2 * 230));
        let ink = |x0: usize, y0: usize, x1: usize, y1: usize| {
            (y0..y1).any(|y| {
                (x0..x1).any(|x| buf[(y * info.width as usize + x) * 3..][..3] != [255; 3])
            })
        };
        assert!(ink(8, 10, 80, 24), "no title");
        assert!(ink(8, 40, 80, 54), "no label on the first row");
        assert!(ink(8, 270, 80, 284), "no label on the second row");
    }
}
