//! Rollouts: a controller driven by a command script for N frames, recorded,
//! checked for physical sanity and compared with another rollout.

pub mod compare;
pub mod dataset;
pub mod fidelity;
pub mod metrics;
pub mod record;
pub mod script;
pub mod tour;

use anyhow::{anyhow, bail, Context, Result};
use exporter::net::{GatingMode, Net};
use std::path::{Path, PathBuf};

use crate::controller::{reference_f32, reference_f64, Controller, FixedController};
pub use compare::{compare, Comparison};
pub use metrics::{sanity, Sanity};
pub use record::Rollout;
pub use script::Script;

/// Runs `ctl` for `frames` frames of `script`.
pub fn run(ctl: &mut dyn Controller, script: &Script, frames: usize) -> Result<Rollout> {
    let mut poses = Vec::with_capacity(frames);
    let mut commands = Vec::with_capacity(frames);
    // Long runs (up to an hour of frames) show how far they are.
    let bar = (frames >= LONG_RUN_FRAMES)
        .then(|| exporter::progress::bar(frames as u64, "rollout", "frames"));
    for f in 0..frames {
        let c = script.command(f);
        poses.push(ctl.step(&c).with_context(|| format!("frame {f}"))?);
        commands.push(c);
        if let Some(b) = bar.as_ref().filter(|_| f % 600 == 0) {
            b.set_position(f as u64);
        }
    }
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    Ok(Rollout {
        poses,
        commands,
        mean_pose: ctl.mean_pose(),
        frame_rate: script::FRAME_RATE,
    })
}

/// Float precision of the reference controller.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Precision {
    /// f64 throughout (the reference).
    F64,
    /// f32 throughout (to see what rounding alone does).
    F32,
}

/// `host-sim rollout`.
#[derive(Debug, clap::Args)]
pub struct RolloutArgs {
    /// A model blob: runs the device controller (fixed point); with
    /// --omg, the blob of that OMG model.
    #[arg(
        long,
        conflicts_with = "reference",
        required_unless_present_any = ["reference", "omg"]
    )]
    pub model: Option<PathBuf>,
    /// An OMG model directory (models/omg/...): a reaching rollout whose
    /// --script is a target script (reach-front, alternate, a JSON file,
    /// ref:N, clip:N; docs/omg.md), in f64 or, with --model, fixed point.
    #[arg(long, conflicts_with = "reference")]
    pub omg: Option<PathBuf>,
    /// With --omg and --model: a rig blob for that (motion) blob, run as
    /// one model with it (docs/omg.md, "Rig blobs").
    #[arg(long, requires_all = ["omg", "model"])]
    pub rig: Option<PathBuf>,
    /// With --omg and clip:N: the generated data (tools/omg/generate --out).
    #[arg(long, requires = "omg")]
    pub data: Option<PathBuf>,
    /// With --omg: feed the predicted costs back (faithful mode) instead of
    /// recomputing them (grounded, the default).
    #[arg(long, requires = "omg")]
    pub faithful: bool,
    /// A PFNN weight directory or PFNN-shaped .npz: runs the float reference.
    #[arg(long, requires = "gating")]
    pub reference: Option<PathBuf>,
    /// Gating of the float reference: constant, linear or cubic.
    #[arg(long)]
    pub gating: Option<GatingMode>,
    /// Precision of the float reference.
    #[arg(long, value_enum, default_value = "f64")]
    pub precision: Precision,
    /// A built-in script (idle, walk, circle-left, zigzag, jog-stop-jog,
    /// crouch-walk), a calibration tour (`tour-SEED-INDEX`) or a JSON
    /// script file (format in docs/controller.md).
    #[arg(long)]
    pub script: String,
    /// Frames to run, 60 per second (default 600; with --omg the target
    /// script's length).
    #[arg(long, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::FRAMES))]
    pub frames: Option<usize>,
    /// Where to write the rollout (.npz).
    #[arg(long)]
    pub out: PathBuf,
}

/// Loads a float network from a PFNN directory or an .npz.
pub fn load_reference(path: &Path, mode: GatingMode) -> Result<Net> {
    if path.is_dir() {
        let tables = exporter::pfnn_dir::load_pfnn_dir_auto(path, None)?;
        Ok(Net::from_pfnn_tables(&tables, mode).0)
    } else {
        exporter::npz::pfnn_from_npz(path, mode)
    }
}

/// Runs the controller the arguments name; returns the rollout and a
/// description of the controller.
pub fn rollout_from_args(args: &RolloutArgs) -> Result<(Rollout, String)> {
    let script = Script::load(&args.script)?;
    let frames = args.frames.unwrap_or(DEFAULT_FRAMES);
    if frames == 0 {
        bail!("--frames must be at least 1");
    }
    if let Some(model) = &args.model {
        let blob = exporter::atomic::read_input(model)
            .with_context(|| format!("cannot read {}", model.display()))?;
        let mut ctl = FixedController::new(&blob, format!("fixed point ({})", model.display()))
            .map_err(|e| anyhow!("{}: {e}", model.display()))?;
        let ram = ctl.device_ram_bytes();
        let state = crate::controller::HostController::STATE_RAM_BYTES;
        let r = run(&mut ctl, &script, frames)?;
        let label = format!(
            "{}\ncontroller RAM on a device sized for this model: {ram} bytes ({state} of loop state, the rest activations and header)",
            ctl.describe()
        );
        Ok((r, label))
    } else {
        let (Some(path), Some(mode)) = (&args.reference, args.gating) else {
            bail!("give --model, or --reference with --gating");
        };
        let net = load_reference(path, mode)?;
        let (r, label) = match args.precision {
            Precision::F64 => {
                let mut c = reference_f64(&net)?;
                (run(&mut c, &script, frames)?, c.describe())
            }
            Precision::F32 => {
                let mut c = reference_f32(&net)?;
                (run(&mut c, &script, frames)?, c.describe())
            }
        };
        Ok((r, format!("{label} ({})", path.display())))
    }
}

/// Rollouts of at least this many frames (100 s) show a progress bar.
pub const LONG_RUN_FRAMES: usize = 6000;

/// Frames of a locomotion rollout when `--frames` is not given.
pub const DEFAULT_FRAMES: usize = 600;

/// `host-sim rollout --omg`: the reaching rollout, its record and reach.
fn omg_rollout_cmd(args: &RolloutArgs, dir: &Path) -> Result<()> {
    let (r, label) = crate::omg_rollout::run(&crate::omg_rollout::OmgRolloutArgs {
        dir: dir.to_path_buf(),
        model: args.model.clone(),
        rig: args.rig.clone(),
        script: args.script.clone(),
        data: args.data.clone(),
        frames: args.frames,
        mode: if args.faithful {
            crate::omg::Mode::Faithful
        } else {
            crate::omg::Mode::Grounded
        },
    })?;
    r.write(&args.out)?;
    println!("{label}");
    println!(
        "targets {}: {} frames ({:.1} s) -> {}",
        args.script,
        r.len(),
        r.len() as f64 / r.frame_rate,
        args.out.display()
    );
    print!("{}", crate::omg_rollout::reach_table(&r));
    Ok(())
}

/// `host-sim rollout`: runs, writes the .npz, prints the sanity metrics.
pub fn rollout_cmd(args: &RolloutArgs) -> Result<()> {
    if let Some(dir) = &args.omg {
        return omg_rollout_cmd(args, dir);
    }
    let (r, label) = rollout_from_args(args)?;
    r.write(&args.out)?;
    let last = r.poses.last().ok_or_else(|| anyhow!("no frames"))?;
    println!("{label}");
    println!(
        "script {}: {} frames ({:.1} s) -> {}",
        args.script,
        r.len(),
        r.len() as f64 / r.frame_rate,
        args.out.display()
    );
    println!(
        "final root ({:.1}, {:.1}), yaw {:.3} rad, phase {:.3} rad",
        last.root_position[0],
        last.root_position[2],
        last.yaw(),
        last.phase * std::f64::consts::TAU
    );
    print!("{}", sanity(&r));
    Ok(())
}

/// `host-sim rollout-compare`.
#[derive(Debug, clap::Args)]
pub struct RolloutCompareArgs {
    /// First rollout (.npz), usually the reference.
    pub a: PathBuf,
    /// Second rollout (.npz).
    pub b: PathBuf,
    /// Print every N-th frame (1 for all).
    #[arg(long, default_value_t = 60, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::FRAMES))]
    pub every: usize,
    /// Also write per-frame errors and the summary as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// `host-sim rollout-compare`: per-frame and summary errors, and both
/// rollouts' sanity metrics.
pub fn rollout_compare_cmd(args: &RolloutCompareArgs) -> Result<()> {
    if crate::omg_rollout::record::OmgRecord::is_record(&args.a)? {
        use crate::omg_rollout::{compare as omg_compare, reach_table, record::OmgRecord};
        let (a, b) = (OmgRecord::read(&args.a)?, OmgRecord::read(&args.b)?);
        let c = omg_compare(&a, &b)
            .with_context(|| format!("{} vs {}", args.a.display(), args.b.display()))?;
        println!("A = {}\nB = {}\n", args.a.display(), args.b.display());
        print!("{}", c.table(args.every));
        println!("\nA reach:\n{}", reach_table(&a));
        println!("B reach:\n{}", reach_table(&b));
        if let Some(path) = &args.json {
            exporter::atomic::write_atomic(path, &serde_json::to_vec_pretty(&c)?)?;
        }
        return Ok(());
    }
    let (a, b) = (Rollout::read(&args.a)?, Rollout::read(&args.b)?);
    let c =
        compare(&a, &b).with_context(|| format!("{} vs {}", args.a.display(), args.b.display()))?;
    println!("A = {}\nB = {}\n", args.a.display(), args.b.display());
    print!("{}", c.table(args.every));
    println!("\nA {}", sanity(&a));
    println!("B {}", sanity(&b));
    if let Some(path) = &args.json {
        exporter::atomic::write_atomic(path, &serde_json::to_vec_pretty(&c)?)?;
    }
    Ok(())
}
