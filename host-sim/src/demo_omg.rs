//! `host-sim demo`: the embedded default model, the trained tiny FE-OMG
//! reaching model (`models/omg/tiny_fe_r1`, compiled into the binary),
//! driven by the targets of a held-out test clip for both hands, in fixed
//! point (its int8 blob on the runtime) beside float (the f64 graph), both
//! through the controller's reaching loop. Prints reach success and frames
//! to reach, the fixed-vs-float joint error, blob size, RAM, MACs, and the
//! Cortex-M4's instructions per frame measured under QEMU when it can be;
//! draws the skeleton, the targets and the hand paths.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, Context, Result};
use exporter::net::omg::{omg_from_bytes, OmgNet};
use phasegate::blob::WeightFormat;

use crate::omg::{diff, rollout, Clips, Diff, FixedOmg, FloatOmg, Mode};
use crate::omg_reach::{median, reach_stats, TargetStats};
use crate::render::canvas::{BLUE, ORANGE};

const WEIGHTS: &[u8] = include_bytes!("../../models/omg/tiny_fe_r1/model.safetensors");
const CONFIG: &str = include_str!("../../models/omg/tiny_fe_r1/config.json");
const REFERENCES: &[u8] = include_bytes!("../../models/omg/tiny_fe_r1/references.npz");
const RIG: &str = include_str!("../../models/omg/tiny_fe_r1/rig.json");

/// Frames of the demo's clip (5 s at 60 fps).
pub const FRAMES: usize = 300;
/// Frames run on the Cortex-M4 under QEMU for the instruction count.
pub const TARGET_FRAMES: usize = 30;

/// The held-out inputs and the rollout targets of the embedded
/// `references.npz`, (clips, frames, width) each.
fn references() -> Result<(Clips, Clips)> {
    let path = Path::new("models/omg/tiny_fe_r1/references.npz (embedded)");
    let mut arrays = exporter::npz::read_npz_from(std::io::Cursor::new(REFERENCES), path)?;
    Ok((
        Clips::take(&mut arrays, "inputs", path)?,
        Clips::take(&mut arrays, "rollout_targets", path)?,
    ))
}

/// The embedded model, its rig's joint parents, the clip's first frame
/// and its per-frame target blocks.
pub struct Embedded {
    /// The imported model.
    pub omg: OmgNet,
    /// Parent of each joint (-1 for the root).
    pub parents: Vec<i32>,
    /// Frame 0 of the held-out clip.
    pub first: Vec<f64>,
    /// Its target block at every frame.
    pub targets: Vec<Vec<f64>>,
}

/// The first `n` frames of the embedded reference inputs (held-out test
/// clips, clip after clip), f32, as a matrix.
pub fn reference_frames(n: usize) -> Result<crate::npy::Matrix<f32>> {
    let (Clips { dims, data }, _) = references()?;
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
    let (inputs, targets) = references()?;
    let frames = targets.dims[1].min(FRAMES);
    Ok(Embedded {
        first: inputs.row(0, 0).to_vec(),
        targets: (0..frames).map(|f| targets.row(0, f).to_vec()).collect(),
        omg,
        parents,
    })
}

/// What the demo measured for one way of running the model.
pub struct Run {
    /// Every frame.
    pub frames: Vec<Vec<f64>>,
    /// Per hand target.
    pub stats: TargetStats,
}

/// Instructions per frame on the Cortex-M4, or why they were not measured.
pub enum Measured {
    /// Median instructions of the inference per frame, frames, bit-exact.
    Qemu {
        /// Median instructions per frame of the inference.
        instructions: u64,
        /// Frames run.
        frames: usize,
        /// Outputs that differed from the host runtime.
        mismatches: usize,
    },
    /// Not measured, and why.
    Not(String),
}

/// Everything `host-sim demo` prints.
pub struct OmgDemo {
    /// Float and fixed point.
    pub float: Run,
    /// The int8 blob.
    pub fixed: Run,
    /// Fixed vs float joints.
    pub diff: Diff,
    /// Blob bytes.
    pub blob_bytes: usize,
    /// Activation RAM of the blob, bytes.
    pub ram_bytes: usize,
    /// The controller's own state on the device (`Reach<f32, 448>`), bytes.
    pub state_bytes: usize,
    /// MACs per frame (header).
    pub macs: u32,
    /// The Cortex-M4 figure.
    pub target: Measured,
    /// The picture, if written.
    pub picture: Option<PathBuf>,
    /// Joints, key joints, frames.
    pub shape: (usize, usize, usize),
}

fn run(e: &Embedded, net: &mut impl phasegate_controller::Network<f64>) -> Result<Run> {
    let t: Vec<&[f64]> = e.targets.iter().map(Vec::as_slice).collect();
    let frames = rollout(
        &e.omg,
        &crate::omg::Start::frame(&e.first),
        &t,
        Mode::Grounded,
        net,
    )?;
    // The data's frames, for the targets: the first frame's pose with each
    // frame's target block.
    let range = e.omg.config.slice("target");
    let clip: Vec<Vec<f64>> = e
        .targets
        .iter()
        .map(|tb| {
            let mut f = e.first.clone();
            f[range.clone()].copy_from_slice(tb);
            f
        })
        .collect();
    let mut stats = TargetStats::default();
    reach_stats(&e.omg.config, &frames, &clip, usize::MAX, &mut stats);
    Ok(Run { frames, stats })
}

/// Runs the demo; the picture goes to `picture` unless `None`, QEMU runs
/// unless `skip_target`.
pub fn run_demo(picture: Option<&Path>, skip_target: bool) -> Result<OmgDemo> {
    let e = embedded()?;
    let blob = int8_blob(&e.omg)?;
    let model = phasegate::Model::from_bytes(&blob).map_err(|err| anyhow!("blob: {err}"))?;
    let float = run(&e, &mut FloatOmg(&e.omg))?;
    let fixed = run(&e, &mut FixedOmg::new(&blob)?)?;
    let d = diff(&e.omg, &fixed.frames, &float.frames);
    let target = if skip_target {
        Measured::Not("skipped (--no-target)".into())
    } else {
        measure_on_target(&blob, &fixed.frames)
    };
    let picture = match picture {
        Some(p) => {
            draw(&e, &float, &fixed, p)?;
            Some(p.to_path_buf())
        }
        None => None,
    };
    let cfg = &e.omg.config;
    Ok(OmgDemo {
        diff: d,
        blob_bytes: blob.len(),
        ram_bytes: model.ram_bytes(),
        state_bytes: phasegate_controller::Reach::<f32, 448>::STATE_RAM_BYTES,
        macs: model.macs_per_frame(),
        target,
        picture,
        shape: (cfg.joints, cfg.key, float.frames.len()),
        float,
        fixed,
    })
}

/// The blob under QEMU on the fixed rollout's own frames (inputs), bit for
/// bit against the host runtime.
fn measure_on_target(blob: &[u8], frames: &[Vec<f64>]) -> Measured {
    if !crate::target::qemu_available() {
        return Measured::Not("qemu-system-arm is not installed".into());
    }
    let go = || -> Result<Measured> {
        let dir = scratch_dir();
        std::fs::create_dir_all(&dir).with_context(|| format!("{}", dir.display()))?;
        let model = dir.join("omg-demo.blob");
        std::fs::write(&model, blob)?;
        let n = TARGET_FRAMES.min(frames.len());
        let width = frames.first().map_or(0, Vec::len);
        let x = crate::npy::Matrix {
            rows: n,
            cols: width,
            data: frames[..n]
                .iter()
                .flatten()
                .map(|&v| v as f32)
                .collect::<Vec<_>>(),
        };
        let inputs = dir.join("omg-demo-inputs.npy");
        crate::npy::write_matrix(&inputs, &x)?;
        let phases = dir.join("omg-demo-phases.npy");
        crate::npy::write_vector(&phases, &vec![0f32; n])?;
        let r = crate::target::execute(&crate::target::TargetArgs {
            model,
            frames: Some(n),
            inputs: Some(inputs),
            phases: Some(phases),
            ..Default::default()
        })?;
        Ok(Measured::Qemu {
            instructions: r.infer_instructions.median,
            frames: r.frames,
            mismatches: r.mismatches,
        })
    };
    let dir = scratch_dir();
    let m = go().unwrap_or_else(|err| Measured::Not(format!("{err:#}")));
    // Best effort: a scratch directory left behind is harmless.
    let _ = std::fs::remove_dir_all(dir);
    m
}

/// The scratch directory of the QEMU run's files.
fn scratch_dir() -> PathBuf {
    std::env::temp_dir().join(format!("phasegate-demo-{}", std::process::id()))
}

fn rate(s: &TargetStats) -> String {
    let n = s.reached.len();
    let k = s.reached.iter().filter(|&&r| r).count();
    format!("{k}/{n} ({:.0} %)", 100.0 * k as f64 / n.max(1) as f64)
}

impl OmgDemo {
    /// The text `host-sim demo` prints.
    pub fn render(&self) -> String {
        let (j, k, f) = self.shape;
        let mut s = format!(
            "embedded default model: trained tiny FE-OMG reaching model (models/omg/tiny_fe_r1; rig R1, \
             {j} joints, {k} key joints), int8 blob\n\
             {f} frames (5 s at 60 fps) of a held-out test clip's targets for both hands, through the \
             reaching controller (grounded costs), fixed point (runtime) beside float (f64):\n\n"
        );
        s += "            targets reached (within 0.1 m in time)   frames to reach (median)   final distance (mean)\n";
        for (name, r) in [("float", &self.float), ("fixed", &self.fixed)] {
            s += &format!(
                "{name:<11} {:<40} {:<26} {:.3} m\n",
                rate(&r.stats),
                median(&r.stats.frames).map_or("-".into(), |m| format!("{m:.0}")),
                r.stats.final_m.iter().sum::<f64>() / r.stats.final_m.len().max(1) as f64
            );
        }
        s += &format!(
            "\nfixed vs float joint positions: p99 {:.2} cm, max {:.2} cm, mean {:.2} cm\n",
            100.0 * self.diff.p99_joint_m,
            100.0 * self.diff.max_joint_m,
            100.0 * self.diff.mean_joint_m
        );
        s += &format!(
            "blob size        {} bytes (flash)\n\
             RAM              {} bytes of activations + {} bytes of controller state (Reach<f32, 448>)\n\
             MACs per frame   {}\n",
            self.blob_bytes, self.ram_bytes, self.state_bytes, self.macs
        );
        s += &match &self.target {
            Measured::Qemu {
                instructions,
                frames,
                mismatches,
            } => format!(
                "Cortex-M4        {instructions} instructions per frame (measured under QEMU, {frames} frames, {}), \
                 {:.1} ms at 168 MHz if one instruction per cycle\n",
                if *mismatches == 0 {
                    "bit-exact with the host".to_string()
                } else {
                    format!("{mismatches} outputs NOT bit-exact")
                },
                *instructions as f64 / 168e3
            ),
            Measured::Not(why) => format!(
                "Cortex-M4        not measured here: {why} (`host-sim target` measures it; docs/omg.md has the figures)\n"
            ),
        };
        if let Some(p) = &self.picture {
            s += &format!("picture          {}\n", p.display());
        }
        s += "(the model itself reaches poorly, in float too: models/omg/README.md; `host-sim omg-reach` for all held-out clips)\n";
        s
    }
}

/// Front view (x right, y up, root space) with the skeleton at a few
/// frames, both hands' paths (float and fixed) and the targets.
fn draw(e: &Embedded, float: &Run, fixed: &Run, path: &Path) -> Result<()> {
    use crate::omg_rollout::picture::{draw, Layer};
    use crate::omg_rollout::record::OmgRecord;
    let record = |r: &Run| OmgRecord::new(&e.omg.config, &e.parents, r.frames.clone());
    let (fixed, float) = (record(fixed)?, record(float)?);
    draw(
        &[
            Layer {
                record: &fixed,
                label: "fixed point (int8)".into(),
                colour: BLUE,
                width: 1.5,
            },
            Layer {
                record: &float,
                label: "float (f64)".into(),
                colour: ORANGE,
                width: 4.0,
            },
        ],
        "tiny FE-OMG reaching a held-out clip's targets: front view",
        5,
        path,
    )
}
