//! `host-sim rollout-dataset`: the network inputs the float controller
//! feeds a dense PFNN over command scripts, as a data set for
//! `exporter cp --distill-data` and `exporter --calibration` (with
//! `--tours N`: random scripts, [`super::tour`]).
//!
//! The f64 float controller ([`reference_f64`], the same loop as the
//! device's) runs each script for `--frames` frames from the reset pose;
//! every frame's network input and phase is one row. The `.npz` (float32,
//! C order; names in [`exporter::cp::distill`]):
//!
//! | array | shape | meaning |
//! |---|---|---|
//! | `X` | (N, inputs) | network inputs, model units (not normalised) |
//! | `phase` | (N,) | phase of each row, radians in `[0, 2 pi)` |
//! | `script` | (N,) | index of the row's script in `--scripts` |
//! | `frame` | (N,) | frame of the row within its script |
//!
//! Rows are in script order, then frame order. With `--blob B`, the
//! fixed-point controller of blob `B` runs the same scripts too and its
//! rows follow (script indices `S..2S` for `S` scripts): the inputs the
//! quantised loop visits, which drift from the float loop's. The output
//! depends only on the model and the arguments (same bytes on every run).

use anyhow::{bail, Context, Result};
use exporter::cp::distill::{DATA_INPUTS, DATA_PHASES};
use exporter::net::{GatingMode, Net};
use std::f64::consts::TAU;
use std::path::{Path, PathBuf};

use super::{load_reference, Script};
use crate::controller::{reference_f64, Controller, FixedController};

/// The scripts `--scripts` defaults to.
pub const DEFAULT_SCRIPTS: &str = "walk,circle-left,zigzag,jog-stop-jog,crouch-walk";

/// `host-sim rollout-dataset`.
#[derive(Debug, clap::Args)]
pub struct RolloutDatasetArgs {
    /// The dense float model: a PFNN weight directory or a PFNN-shaped .npz.
    #[arg(long, required_unless_present = "omg")]
    pub pfnn: Option<PathBuf>,
    /// Instead of a PFNN: an OMG model directory (model.safetensors,
    /// config.json, references.npz). The rows are its f64 grounded
    /// rollouts of the first --clips training clips of its rig (from
    /// --data), the rows `omg-reach --calibration-clips` uses and
    /// `exporter omg --calibration` takes.
    #[arg(
        long,
        conflicts_with_all = ["pfnn", "scripts", "tours", "frames", "gating", "blob"],
        requires = "clips"
    )]
    pub omg: Option<PathBuf>,
    /// Training clips of --omg's rollouts.
    #[arg(long, requires = "omg", value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::RUNS))]
    pub clips: Option<usize>,
    /// The OMG data set (`python3 -m tools.omg.generate --out DIR`).
    #[arg(long, default_value = "data/omg")]
    pub data: PathBuf,
    /// Gating of the float model: constant, linear or cubic.
    #[arg(long, default_value = "cubic")]
    pub gating: GatingMode,
    /// Scripts, comma separated: built-in names (idle, walk, circle-left,
    /// zigzag, jog-stop-jog, crouch-walk), tour names (`tour-SEED-INDEX`)
    /// or JSON script files (default:
    /// walk, circle-left, zigzag, jog-stop-jog, crouch-walk, unless
    /// --tours is given).
    #[arg(long, value_delimiter = ',')]
    pub scripts: Vec<String>,
    /// Also (or, without --scripts, only) this many random command
    /// scripts (`rollout::tour`): calibration data for `exporter
    /// --calibration` that shares no script with `host-sim fidelity`.
    #[arg(long, default_value_t = 0, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::RUNS))]
    pub tours: usize,
    /// Seed of the tours.
    #[arg(long, default_value_t = 1)]
    pub tour_seed: u64,
    /// Frames of each script (60 per second).
    #[arg(long, default_value_t = 600, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::FRAMES))]
    pub frames: usize,
    /// Also record the fixed-point controller of this blob over the same
    /// scripts: the inputs the quantised loop itself visits (rows after
    /// the float controller's, their script indices after its scripts).
    #[arg(long)]
    pub blob: Option<PathBuf>,
    /// Where to write the data set (.npz).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
}

/// Network inputs and phases of the float controller's rollouts.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RolloutDataset {
    /// Inputs, model units, one row per frame.
    pub inputs: Vec<Vec<f64>>,
    /// Phases, radians.
    pub phases: Vec<f64>,
    /// Script index of each row.
    pub script: Vec<usize>,
    /// Frame of each row within its script.
    pub frame: Vec<usize>,
}

impl RolloutDataset {
    /// Appends `other`'s rows.
    pub fn extend(&mut self, other: RolloutDataset) {
        self.inputs.extend(other.inputs);
        self.phases.extend(other.phases);
        self.script.extend(other.script);
        self.frame.extend(other.frame);
    }

    /// Rows.
    pub fn len(&self) -> usize {
        self.inputs.len()
    }

    /// No rows.
    pub fn is_empty(&self) -> bool {
        self.inputs.is_empty()
    }

    /// The arrays of the `.npz`, float32.
    pub fn arrays(&self) -> Vec<(&'static str, Vec<u64>, Vec<f32>)> {
        let n = self.len() as u64;
        let width = self.inputs.first().map_or(0, Vec::len) as u64;
        let f = |v: &[usize]| v.iter().map(|&i| i as f32).collect::<Vec<f32>>();
        vec![
            (
                DATA_INPUTS,
                vec![n, width],
                self.inputs.iter().flatten().map(|&v| v as f32).collect(),
            ),
            (
                DATA_PHASES,
                vec![n],
                self.phases.iter().map(|&p| p as f32).collect(),
            ),
            ("script", vec![n], f(&self.script)),
            ("frame", vec![n], f(&self.frame)),
        ]
    }
}

/// Runs the f64 float controller over `net` for `frames` frames of each
/// script, recording every network input and phase.
pub fn collect(net: &Net, scripts: &[Script], frames: usize) -> Result<RolloutDataset> {
    record(
        scripts,
        frames,
        0,
        "the float controller",
        || reference_f64(net),
        |c| c.state().last_input().to_vec(),
    )
}

/// Runs the fixed-point controller of `blob` (the device's loop, on the
/// host) for `frames` frames of each script, recording every network input
/// and phase: the inputs the quantised loop itself visits, which drift
/// away from the float controller's. Script indices start at
/// `first_script`.
pub fn collect_fixed(
    blob: &[u8],
    scripts: &[Script],
    frames: usize,
    first_script: usize,
) -> Result<RolloutDataset> {
    record(
        scripts,
        frames,
        first_script,
        "the fixed-point controller",
        || FixedController::new(blob, "fixed"),
        |c| c.inner().state().last_input().map(f64::from).to_vec(),
    )
}

/// Runs a fresh controller from `start` over each script (`what` names it
/// on the progress bar and in errors), recording the network input that
/// `input` reads after every step, and the phase.
fn record<C: Controller>(
    scripts: &[Script],
    frames: usize,
    first_script: usize,
    what: &str,
    start: impl Fn() -> Result<C>,
    input: impl Fn(&C) -> Vec<f64>,
) -> Result<RolloutDataset> {
    let mut d = RolloutDataset::default();
    let bar = exporter::progress::bar(
        scripts.len() as u64,
        &format!("recording {what}"),
        "scripts",
    );
    for (si, script) in scripts.iter().enumerate() {
        let mut ctl = start()?;
        for f in 0..frames {
            let pose = ctl
                .step(&script.command(f))
                .with_context(|| format!("script {}: frame {f}", script.name))?;
            let x = input(&ctl);
            if let Some(i) = x.iter().position(|&v| !(v as f32).is_finite()) {
                bail!(
                    "script {}: frame {f}: network input {i} is {} (beyond float32): \
                     {what} diverged",
                    script.name,
                    x[i]
                );
            }
            d.inputs.push(x);
            d.phases.push(pose.phase * TAU);
            d.script.push(first_script + si);
            d.frame.push(f);
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(d)
}

/// The OMG model in `dir` rolled out over `n` training clips of its rig
/// (`omg_reach::train_rollouts`), written to `out` as a rollout data set
/// (`script` is the clip, `frame` the frame; phases 0).
pub fn omg_dataset(dir: &Path, data: &Path, n: usize, out: &Path) -> Result<RolloutDataset> {
    let d = crate::omg::load_dir(dir)?;
    let rig = crate::omg_reach::rig_of(dir)?;
    let rec = crate::omg_reach::train_rollouts(&d, data, &rig, n)?;
    let rows = rec.samples.inputs.len();
    let frames = rows / n;
    let set = RolloutDataset {
        inputs: rec.samples.inputs.clone(),
        phases: rec.samples.phases.clone(),
        script: (0..rows).map(|r| r / frames).collect(),
        frame: (0..rows).map(|r| r % frames).collect(),
    };
    exporter::npz::write_npz(out, &set.arrays())?;
    println!(
        "wrote {}: {rows} rows ({n} training clips of {rig} x {frames} frames, f64 grounded rollouts of {}), arrays X ({rows}, {}), phase, script, frame",
        out.display(),
        dir.display(),
        d.omg.config.model_width
    );
    Ok(set)
}

/// `host-sim rollout-dataset`: runs, writes the `.npz`, prints a summary.
pub fn rollout_dataset_cmd(args: &RolloutDatasetArgs) -> Result<()> {
    if let (Some(dir), Some(n)) = (&args.omg, args.clips) {
        return omg_dataset(dir, &args.data, n, &args.out).map(drop);
    }
    let Some(pfnn) = &args.pfnn else {
        bail!("give --pfnn DIR (or --omg DIR --clips N)");
    };
    if args.frames == 0 {
        bail!("--frames must be at least 1");
    }
    let named: Vec<&str> = if args.scripts.is_empty() && args.tours == 0 {
        DEFAULT_SCRIPTS.split(',').collect()
    } else {
        args.scripts.iter().map(String::as_str).collect()
    };
    // The rows kept (twice with --blob), checked before any is made.
    let runs = named.len().saturating_add(args.tours);
    let rows = runs
        .saturating_mul(args.frames)
        .saturating_mul(if args.blob.is_some() { 2 } else { 1 });
    if rows > exporter::cli_args::bounds::ROWS {
        bail!(
            "{runs} scripts and tours of {} frames{} make {rows} rows, more than the largest \
             data set accepted, {} rows: fewer --tours or --frames",
            args.frames,
            if args.blob.is_some() {
                ", twice with --blob,"
            } else {
                ""
            },
            exporter::cli_args::bounds::ROWS
        );
    }
    let mut scripts = named
        .into_iter()
        .map(Script::load)
        .collect::<Result<Vec<_>>>()?;
    let seconds = args.frames as f64 / super::script::FRAME_RATE;
    scripts.extend((0..args.tours).map(|i| super::tour::tour(args.tour_seed, i, seconds)));
    let net = load_reference(pfnn, args.gating)?;
    if net.input_dim() != phasegate_controller::layout::INPUTS
        || net.output_dim() != phasegate_controller::layout::OUTPUTS
    {
        bail!(
            "{}: the controller needs a PFNN-shaped model ({} inputs, {} outputs), this one has {} and {}",
            pfnn.display(),
            phasegate_controller::layout::INPUTS,
            phasegate_controller::layout::OUTPUTS,
            net.input_dim(),
            net.output_dim()
        );
    }
    let mut d = collect(&net, &scripts, args.frames)?;
    let runs = if let Some(b) = &args.blob {
        let blob = exporter::atomic::read_input(b)
            .with_context(|| format!("cannot read {}", b.display()))?;
        let fixed = collect_fixed(&blob, &scripts, args.frames, scripts.len())
            .with_context(|| b.display().to_string())?;
        d.extend(fixed);
        2
    } else {
        1
    };
    exporter::npz::write_npz(&args.out, &d.arrays())?;
    println!(
        "wrote {}: {} rows ({} scripts x {} frames), arrays X ({}, {}), phase, script, frame",
        args.out.display(),
        d.len(),
        runs * scripts.len(),
        args.frames,
        d.len(),
        net.input_dim()
    );
    for (i, s) in scripts.iter().enumerate() {
        println!("  script {i}: {}", s.name);
    }
    if let Some(b) = &args.blob {
        for (i, s) in scripts.iter().enumerate() {
            println!(
                "  script {}: {}, the fixed-point controller of {}",
                scripts.len() + i,
                s.name,
                b.display()
            );
        }
    }
    // How far the controller's inputs are from the normal samples
    // (Xmean + Xstd N(0,1)): RMS of the normalised inputs, 1 for those.
    let mut sq = 0.0;
    for x in &d.inputs {
        for ((v, m), s) in x.iter().zip(&net.xmean).zip(&net.xstd) {
            sq += ((v - m) / s).powi(2);
        }
    }
    println!(
        "RMS of the normalised inputs: {:.3} (normal samples: 1)",
        (sq / (d.len() * net.input_dim()).max(1) as f64).sqrt()
    );
    Ok(())
}
