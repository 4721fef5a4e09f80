//! `host-sim demo`: the embedded default model, the trained tiny FE-OMG
//! reaching model (`models/omg/tiny_fe_r1`, compiled into the binary),
//! through the demo's target script (`host-sim/src/demo/reach-demo.json`,
//! compiled in: both hands through five targets each and back to rest,
//! 600 frames from rest), in fixed point (its int8 blob on the runtime)
//! beside float (the f64 graph), both through the controller's reaching
//! loop. Prints the reach figures of [`crate::reach_metrics`] (the
//! definitions of `tools/omg/metrics.py`), the fixed-vs-float joint
//! difference, blob size, RAM, MACs, and the Cortex-M4's instructions per
//! frame of the reaching loop itself on the reach firmware under QEMU
//! (bit for bit against the host's `Reach<f32>`) when it can be run; draws
//! the front and side views to a PNG and an animated GIF.
//!
//! A joint-velocity model (`docs/omg-joint-velocity.md`) starts from rest;
//! an absolute one from the first frame of its references (as `host-sim
//! rollout --omg` starts a script).

use std::path::{Path, PathBuf};

use anyhow::{anyhow, Context, Result};
use exporter::net::omg::{omg_from_bytes, OmgNet};
use phasegate::blob::WeightFormat;
use phasegate_controller::CostMode;

use crate::omg::{diff, rollout, Clips, Diff, FixedOmg, FloatOmg, Mode, Start};
use crate::omg_reach::block_positions;
use crate::omg_rollout::script::TargetScript;
use crate::reach_metrics::{
    script_intervals, Bones, FrameLayout, HandTarget, ReachCounts, ReachSummary, BONE_TOL_M,
    CONTACT_RADIUS_M,
};
use crate::render::canvas::{BLUE, ORANGE};
use crate::target::reach::DEVICE_WIDTH;

const WEIGHTS: &[u8] = include_bytes!("../../models/omg/tiny_fe_r1/model.safetensors");
const CONFIG: &str = include_str!("../../models/omg/tiny_fe_r1/config.json");
const REFERENCES: &[u8] = include_bytes!("../../models/omg/tiny_fe_r1/references.npz");
const RIG: &str = include_str!("../../models/omg/tiny_fe_r1/rig.json");

/// The demo's target script (written before any model was chosen).
pub const SCRIPT: &str = include_str!("demo/reach-demo.json");
/// Where [`SCRIPT`] comes from.
pub const SCRIPT_PATH: &str = "host-sim/src/demo/reach-demo.json";

/// One GIF frame every this many rollout frames.
pub const GIF_EVERY: usize = 3;

/// The share of the counted targets the int8 model must reach.
pub const DEMO_BAR: f64 = 0.75;

/// The held-out inputs of the embedded `references.npz` (clips, frames,
/// width).
fn reference_inputs() -> Result<Clips> {
    let path = Path::new("models/omg/tiny_fe_r1/references.npz (embedded)");
    let mut arrays = exporter::npz::read_npz_from(std::io::Cursor::new(REFERENCES), path)?;
    Clips::take(&mut arrays, "inputs", path)
}

/// The embedded model, its rig and the demo script's rollout plan.
pub struct Embedded {
    /// The imported model.
    pub omg: OmgNet,
    /// Parent of each joint (-1 for the root).
    pub parents: Vec<i32>,
    /// The rig's bones and rest lengths.
    pub bones: Bones,
    /// The script.
    pub script: TargetScript,
    /// Where the rollout starts (from rest for a joint-velocity model).
    pub start: Start,
    /// The target block of every frame.
    pub blocks: Vec<Vec<f64>>,
    /// The hands' target positions on every frame.
    pub targets: Vec<Vec<[f64; 3]>>,
    /// The counted hand targets.
    pub counted: Vec<HandTarget>,
}

/// The first `n` frames of the embedded reference inputs (held-out test
/// clips, clip after clip), f32, as a matrix.
pub fn reference_frames(n: usize) -> Result<crate::npy::Matrix<f32>> {
    let Clips { dims, data } = reference_inputs()?;
    let cols = dims[2];
    let rows = n.min(data.len() / cols.max(1));
    Ok(crate::npy::Matrix {
        rows,
        cols,
        // Exact: the stored values are float32.
        data: data[..rows * cols].iter().map(|&v| v as f32).collect(),
    })
}

/// The int8 blob `host-sim demo` runs (and the golden case
/// `omg-tiny-fe-r1` holds).
pub fn int8_blob(omg: &OmgNet) -> Result<Vec<u8>> {
    let opts = crate::omg::exporter_options(WeightFormat::I8);
    Ok(exporter::export::export(&omg.net, None, &opts)?.0)
}

/// Loads what `host-sim demo` runs, from the bytes compiled in.
pub fn embedded() -> Result<Embedded> {
    let omg = omg_from_bytes(WEIGHTS, CONFIG).context("embedded OMG model")?;
    let parents = crate::omg_rollout::parents_of(RIG.as_bytes()).context("embedded rig.json")?;
    let bones = match &omg.dof {
        Some(form) => Bones::new(&form.skeleton.parents, &form.skeleton.offsets),
        None => Bones::from_rig_json(RIG.as_bytes()),
    }
    .context("the embedded model's rig")?;
    let script: TargetScript =
        serde_json::from_str(SCRIPT).with_context(|| format!("{SCRIPT_PATH} (embedded)"))?;
    let n = script
        .frames
        .unwrap_or(crate::omg_rollout::script::DEFAULT_FRAMES);
    let first = reference_inputs()?.row(0, 0).to_vec();
    let (start, blocks) = crate::omg_rollout::script_start(&omg, &first, &script, n)
        .with_context(|| format!("{SCRIPT_PATH} (embedded)"))?;
    let (counted, _) = script_intervals(&script.intervals(&omg.config, n)?);
    Ok(Embedded {
        targets: block_positions(&omg.config, &blocks),
        omg,
        parents,
        bones,
        script,
        start,
        blocks,
        counted,
    })
}

/// What the demo measured for one way of running the model.
pub struct Run {
    /// Every frame.
    pub frames: Vec<Vec<f64>>,
    /// Per hand target.
    pub counts: ReachCounts,
    /// The figures.
    pub summary: ReachSummary,
}

/// The reaching loop on the Cortex-M4, or why it was not measured.
pub enum Measured {
    /// Median instructions per step on the reach firmware under QEMU.
    Qemu {
        /// Whole frame (targets set and `Reach::step`).
        frame: u64,
        /// The network (`Runtime::run`: quantise, infer, de-quantise).
        inference: u64,
        /// The controller: frame minus network.
        glue: u64,
        /// Steps run.
        steps: usize,
        /// Every frame value and target outcome equal to the host's
        /// `Reach<f32>`.
        bit_exact: bool,
        /// Frame values that differ.
        mismatches: usize,
        /// The loop state's size on the device (its log), bytes.
        state_bytes: usize,
    },
    /// Not measured, and why.
    Not(String),
}

/// Everything `host-sim demo` prints.
pub struct OmgDemo {
    /// Float (the f64 graph).
    pub float: Run,
    /// The int8 blob.
    pub fixed: Run,
    /// Fixed vs float joints.
    pub diff: Diff,
    /// Blob bytes.
    pub blob_bytes: usize,
    /// Activation RAM of the blob, bytes.
    pub ram_bytes: usize,
    /// The controller's state (`Reach<f32, DEVICE_WIDTH>`), bytes: the
    /// device's own figure when QEMU ran, else its size on this host.
    pub state_bytes: usize,
    /// MACs per frame (header).
    pub macs: u32,
    /// The Cortex-M4 figure.
    pub target: Measured,
    /// The PNG, if written.
    pub picture: Option<PathBuf>,
    /// The GIF, if written.
    pub gif: Option<PathBuf>,
    /// Joints, key joints, frames.
    pub shape: (usize, usize, usize),
    /// A joint-velocity model (from rest).
    pub dof: bool,
    /// The script's name and description.
    pub script: (String, String),
}

fn run(e: &Embedded, net: &mut impl phasegate_controller::Network<f64>) -> Result<Run> {
    let t: Vec<&[f64]> = e.blocks.iter().map(Vec::as_slice).collect();
    let frames = rollout(&e.omg, &e.start, &t, Mode::Grounded, net)?;
    let mut counts = ReachCounts::default();
    let layout = FrameLayout::of(&e.omg.config);
    counts.add_clip(&frames, &e.targets, &e.counted, &layout, &e.bones);
    Ok(Run {
        frames,
        summary: counts.summary(),
        counts,
    })
}

/// Runs the demo; the pictures go to `picture` (PNG) and `gif` unless
/// `None`, QEMU runs unless `skip_target`.
pub fn run_demo(picture: Option<&Path>, gif: Option<&Path>, skip_target: bool) -> Result<OmgDemo> {
    let e = embedded()?;
    let blob = int8_blob(&e.omg)?;
    let model = phasegate::Model::from_bytes(&blob).map_err(|err| anyhow!("blob: {err}"))?;
    let float = run(&e, &mut FloatOmg(&e.omg))?;
    let fixed = run(&e, &mut FixedOmg::new(&blob)?)?;
    let d = diff(&e.omg, &fixed.frames, &float.frames);
    let target = if skip_target {
        Measured::Not("skipped (--no-target)".into())
    } else {
        measure_on_target(&e, &blob)
    };
    let title = "tiny FE-OMG reaching the demo's targets: int8 (fixed point) and f64";
    let layers = |float: &Run, fixed: &Run| -> Result<[crate::omg_rollout::record::OmgRecord; 2]> {
        let record = |r: &Run| {
            crate::omg_rollout::record::OmgRecord::new(&e.omg.config, &e.parents, r.frames.clone())
        };
        Ok([record(fixed)?, record(float)?])
    };
    let records = layers(&float, &fixed)?;
    let layer = |i: usize| crate::omg_rollout::picture::Layer {
        record: &records[i],
        label: ["fixed point (int8)", "float (f64)"][i].into(),
        colour: [BLUE, ORANGE][i],
        width: [1.5, 4.0][i],
    };
    // Both pictures or neither; their directories are made if missing.
    let mut outputs = exporter::atomic::Outputs::new();
    for p in [picture, gif].into_iter().flatten() {
        if let Some(d) = p.parent().filter(|d| !d.as_os_str().is_empty()) {
            outputs.dir(d);
        }
    }
    if let Some(p) = picture {
        let png = crate::omg_rollout::picture::png_bytes(&[layer(0), layer(1)], title, 5, p)?;
        outputs.add(p, png);
    }
    if let Some(g) = gif {
        let bytes =
            crate::omg_rollout::picture::gif_bytes(&[layer(0), layer(1)], title, g, GIF_EVERY)?;
        outputs.add(g, bytes);
    }
    outputs.commit()?;
    let state_bytes = match &target {
        Measured::Qemu { state_bytes, .. } => *state_bytes,
        Measured::Not(_) => phasegate_controller::Reach::<f32, DEVICE_WIDTH>::STATE_RAM_BYTES,
    };
    let cfg = &e.omg.config;
    Ok(OmgDemo {
        diff: d,
        blob_bytes: blob.len(),
        ram_bytes: model.ram_bytes(),
        state_bytes,
        macs: model.macs_per_frame(),
        target,
        picture: picture.map(Path::to_path_buf),
        gif: gif.map(Path::to_path_buf),
        shape: (cfg.joints, cfg.key, float.frames.len()),
        dof: e.omg.dof.is_some(),
        script: (
            e.script.name.clone().unwrap_or_else(|| "demo".into()),
            // Its description says what it is for; the line says the rest.
            e.script
                .description
                .as_deref()
                .map(|d| d.strip_prefix("host-sim demo: ").unwrap_or(d).to_string())
                .unwrap_or_default(),
        ),
        float,
        fixed,
    })
}

/// The reaching loop itself (the int8 blob, the demo's start and every
/// step's targets) on the reach firmware under QEMU, bit for bit against
/// the host's `Reach<f32>`.
fn measure_on_target(e: &Embedded, blob: &[u8]) -> Measured {
    if !crate::target::qemu_available() {
        return Measured::Not("qemu-system-arm is not installed".into());
    }
    let dir = scratch_dir();
    let go = || -> Result<Measured> {
        std::fs::create_dir_all(&dir).with_context(|| format!("{}", dir.display()))?;
        let model = dir.join("omg-demo.blob");
        std::fs::write(&model, blob)?;
        let plan =
            crate::target::reach::plan_from_start(&e.omg, &e.start, &e.blocks, CostMode::Grounded)?;
        let r = crate::target::reach::execute_plan(&model, SCRIPT_PATH, &plan)?;
        Ok(Measured::Qemu {
            frame: r.frame_instructions.median,
            inference: r.network_instructions.median,
            glue: r.glue_instructions.median,
            steps: r.frames,
            bit_exact: r.bit_exact(),
            mismatches: r.mismatches,
            state_bytes: r.state_bytes,
        })
    };
    let m = go().unwrap_or_else(|err| Measured::Not(format!("{err:#}")));
    // Best effort: a scratch directory left behind is harmless.
    let _ = std::fs::remove_dir_all(dir);
    m
}

/// The scratch directory of the QEMU run's files.
fn scratch_dir() -> PathBuf {
    std::env::temp_dir().join(format!("phasegate-demo-{}", std::process::id()))
}

impl Run {
    /// `k/n (p %)` of the targets plausibly reached.
    fn rate(&self) -> String {
        let n = self.summary.targets;
        let k = self.counts.plausibly_reached();
        format!("{k}/{n} ({:.0} %)", 100.0 * k as f64 / n.max(1) as f64)
    }

    /// Whether at least [`DEMO_BAR`] of the counted targets were reached
    /// (plausibly).
    pub fn meets_bar(&self) -> bool {
        let n = self.summary.targets;
        n > 0 && self.counts.plausibly_reached() as f64 >= DEMO_BAR * n as f64
    }
}

impl OmgDemo {
    /// The text `host-sim demo` prints.
    pub fn render(&self) -> String {
        let (j, k, f) = self.shape;
        let (name, description) = &self.script;
        let mut s = format!(
            "embedded default model: trained tiny FE-OMG reaching model (models/omg/tiny_fe_r1; rig R1, \
             {j} joints, {k} key joints; {}), int8 blob\n\
             target script \"{name}\" ({SCRIPT_PATH}, compiled in): {description}\n\
             {f} frames ({:.1} s at 60 fps) {}, through the reaching controller (grounded costs): \
             fixed point (the int8 blob on the runtime) beside float (the f64 graph)\n\n",
            if self.dof {
                "joint-velocity output: the controller limits it, integrates the joint angles and \
                 rebuilds the pose by forward kinematics"
            } else {
                "absolute pose output"
            },
            f as f64 / 60.0,
            if self.dof {
                "from rest"
            } else {
                "from its references' first frame"
            },
        );
        s += &format!(
            "reach rule: a target counts if the hand starts more than {CONTACT_RADIUS_M} m from it; \
             reached = within {CONTACT_RADIUS_M} m with every bone within {} cm of the rig's\n\n",
            100.0 * BONE_TOL_M
        );
        s += "        reached          near start   frames to reach (median)   final distance (mean)   bone error p99\n";
        for (name, r) in [("float", &self.float), ("fixed", &self.fixed)] {
            let m = &r.summary;
            s += &format!(
                "{name:<7} {:<16} {:<12} {:<26} {:<23} {:.3} cm\n",
                r.rate(),
                m.near_start,
                m.frames_median.map_or("-".into(), |v| format!("{v:.0}")),
                format!("{:.3} m", m.final_m),
                m.bone_err_p99_cm
            );
        }
        let met = self.fixed.meets_bar();
        if !met {
            s += &format!(
                "\nthe int8 model reached fewer than three quarters of the targets away from the hands: {}\n",
                self.fixed.rate()
            );
        }
        s += &format!(
            "\ndemo bar (>= 3/4 of the targets away from the hands reached, int8): {}\n",
            if met { "met" } else { "NOT met" }
        );
        s += &format!(
            "\nfixed vs float joint positions: p99 {:.2} cm, max {:.2} cm, mean {:.2} cm\n",
            100.0 * self.diff.p99_joint_m,
            100.0 * self.diff.max_joint_m,
            100.0 * self.diff.mean_joint_m
        );
        let state = match &self.target {
            Measured::Qemu { .. } => {
                format!("Reach<f32, {DEVICE_WIDTH}> on the Cortex-M4, from its log")
            }
            Measured::Not(_) => format!("Reach<f32, {DEVICE_WIDTH}>, its size on this host"),
        };
        s += &format!(
            "blob size        {} bytes (flash)\n\
             RAM              {} bytes of activations + {} bytes of controller state ({state})\n\
             MACs per frame   {}\n",
            self.blob_bytes, self.ram_bytes, self.state_bytes, self.macs
        );
        s += &match &self.target {
            Measured::Qemu {
                frame,
                inference,
                glue,
                steps,
                bit_exact,
                mismatches,
                ..
            } => format!(
                "Cortex-M4        the reaching loop itself on the reach firmware under QEMU ({steps} steps of the script): \
                 {frame} instructions per frame (median), {inference} of them inference (Runtime::run), {glue} the controller; \
                 {}; {:.1} ms at 168 MHz if one instruction per cycle\n",
                if *bit_exact {
                    format!("bit-exact with the host's Reach<f32, {DEVICE_WIDTH}>")
                } else {
                    format!("{mismatches} frame values NOT bit-exact with the host's Reach<f32, {DEVICE_WIDTH}>")
                },
                *frame as f64 / 168e3
            ),
            Measured::Not(why) => format!(
                "Cortex-M4        not measured here: {why} (`host-sim target --reach` measures it; docs/omg-joint-velocity.md has the figures)\n"
            ),
        };
        if let Some(p) = &self.picture {
            s += &format!("picture          {} (front and side views)\n", p.display());
        }
        if let Some(p) = &self.gif {
            s += &format!(
                "animation        {} (every {GIF_EVERY}rd frame)\n",
                p.display()
            );
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run_of(plausible: usize, targets: usize) -> Run {
        let counts = ReachCounts {
            reached: vec![true; targets],
            plausible: (0..targets).map(|i| i < plausible).collect(),
            frames: vec![20; plausible],
            final_m: vec![0.05; targets],
            ..ReachCounts::default()
        };
        Run {
            frames: Vec::new(),
            summary: counts.summary(),
            counts,
        }
    }

    fn demo(fixed: Run) -> OmgDemo {
        OmgDemo {
            float: run_of(12, 12),
            fixed,
            diff: Diff::default(),
            blob_bytes: 1,
            ram_bytes: 2,
            state_bytes: 3,
            macs: 4,
            target: Measured::Not("skipped (--no-target)".into()),
            picture: None,
            gif: None,
            shape: (31, 4, 600),
            dof: true,
            script: ("demo".into(), "five targets".into()),
        }
    }

    /// Three quarters of the counted targets, plausibly reached in fixed
    /// point, meet the demo's bar; fewer are said plainly, and the rule is
    /// printed in words.
    #[test]
    fn the_demo_bar_is_three_quarters_of_the_counted_targets_in_fixed_point() {
        assert!(run_of(9, 12).meets_bar());
        assert!(!run_of(8, 12).meets_bar());
        assert!(
            !run_of(0, 0).meets_bar(),
            "no target counted: nothing shown"
        );
        let met = demo(run_of(9, 12)).render();
        assert!(
            met.contains("demo bar (>= 3/4 of the targets away from the hands reached, int8): met"),
            "{met}"
        );
        assert!(met.contains("fixed   9/12 (75 %)"), "{met}");
        assert!(met.contains(
            "reach rule: a target counts if the hand starts more than 0.1 m from it; \
             reached = within 0.1 m with every bone within 1 cm of the rig's"
        ));
        let not = demo(run_of(8, 12)).render();
        assert!(not.contains("fewer than three quarters of the targets away from the hands: 8/12"));
        assert!(not.contains("int8): NOT met"), "{not}");
    }
}
