//! `host-sim`: the runtime on the host, float references, comparisons,
//! demos and golden vectors.

use anyhow::{anyhow, bail, Context, Result};
use clap::{Parser, Subcommand};
use exporter::net::{GatingMode, Net};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use host_sim::{accuracy, compare, demo, eval, golden, npy};

#[derive(Parser)]
#[command(
    name = "host-sim",
    version,
    about = "Runs phasegate models on the host and checks them"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

use exporter::cli_args::GatingArg as Gating;

#[derive(Subcommand)]
enum Command {
    /// Run a blob (fixed point) or a float reference over inputs and phases.
    Eval {
        /// The model blob (fixed-point runtime).
        #[arg(
            long,
            conflicts_with = "reference",
            required_unless_present = "reference"
        )]
        model: Option<PathBuf>,
        /// A PFNN weight directory or a PFNN-shaped .npz (float reference).
        #[arg(long, requires = "gating")]
        reference: Option<PathBuf>,
        /// Gating of the float reference.
        #[arg(long, value_enum)]
        gating: Option<Gating>,
        /// float32 (N, inputs) raw inputs in model units.
        #[arg(long)]
        inputs: PathBuf,
        /// float32 (N,) phases in radians.
        #[arg(long)]
        phases: PathBuf,
        /// float32 (N, outputs) outputs in model units.
        #[arg(long)]
        out: PathBuf,
        /// Also write the raw int16 outputs of the runtime (with --model).
        #[arg(long, requires = "model")]
        raw_out: Option<PathBuf>,
    },
    /// Max and RMS absolute difference per PFNN output group and overall.
    Compare {
        /// First outputs (.npy).
        a: PathBuf,
        /// Second outputs (.npy).
        b: PathBuf,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
    /// The main job: the embedded default model (or the real PFNN) fixed vs float.
    Demo {
        /// Run on a PFNN weight directory instead (int8 cubic blob built in
        /// memory, fixed vs float on sampled inputs).
        #[arg(long)]
        pfnn: Option<PathBuf>,
        /// Frames to run (--pfnn).
        #[arg(long, default_value_t = 300, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::FRAMES))]
        frames: usize,
        /// Where to write the picture of the reaching run (front and side views).
        #[arg(long, default_value = "target/phasegate-demo/omg-reach.png")]
        picture: PathBuf,
        /// Where to write the animation of the reaching run (every 3rd frame).
        #[arg(long, default_value = "target/phasegate-demo/omg-reach.gif")]
        gif: PathBuf,
        /// Do not run the blob on the Cortex-M4 under QEMU.
        #[arg(long)]
        no_target: bool,
    },
    /// Fixed vs float accuracy of int16 and int8 cubic blobs on a PFNN, vs the demo's own error.
    Accuracy {
        /// The PFNN weight directory.
        #[arg(long)]
        pfnn: PathBuf,
        /// Samples per input spread.
        #[arg(long, default_value_t = 64, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::SAMPLES))]
        samples: usize,
        /// Seed of the input sampler.
        #[arg(long, default_value_t = 7)]
        seed: u64,
        /// Also write every figure as JSON.
        #[arg(long)]
        json: Option<PathBuf>,
        #[command(flatten)]
        int8: host_sim::quant_knobs::Int8Knobs,
    },
    /// OMG models reaching (docs/omg.md): grounded rollouts of the rig's
    /// held-out clips (and with --scripts the target scripts) in f64 and as
    /// int16 and int8 blobs, beside the data and holding still; targets
    /// (near start apart), reach and plausible reach, frames to reach,
    /// final distance, bone-length error, roughness, joint error, and the
    /// blobs' joint difference to the f64 rollout.
    OmgReach {
        /// Model directories (model.safetensors, config.json, references.npz).
        #[arg(required = true)]
        dirs: Vec<PathBuf>,
        /// The data set `python3 -m tools.omg.generate --out DIR` wrote
        /// (its `<rig>/{test,val}.npy` and `clips.json` are read).
        #[arg(long, default_value = "data/omg")]
        data: PathBuf,
        /// Also write every figure as JSON.
        #[arg(long)]
        json: Option<PathBuf>,
        /// Factor between calibrated maxima and the i16 range (as `exporter
        /// omg --headroom`).
        #[arg(long, default_value_t = exporter::net::omg::HEADROOM)]
        headroom: f64,
        /// The int8 blob's quantiser knobs, as `exporter omg` takes them.
        #[command(flatten)]
        int8: host_sim::quant_knobs::Int8Knobs,
        /// Deploy the models as rig blobs against this model's motion blobs
        /// (Frozen rig transfer: `tiny_fe_r4_frozen` against `tiny_fe_r1`,
        /// as `exporter omg-rig` builds them) instead of whole blobs.
        #[arg(long)]
        motion_from: Option<PathBuf>,
        /// Judge on the first N clips of the rig's training split instead
        /// of the held-out ones (to choose among training runs without
        /// looking at the clips they are reported on).
        #[arg(long, value_name = "N", value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::RUNS))]
        train_clips: Option<usize>,
        /// Also roll the f64 model out with every input feature moved each
        /// frame by uniform noise in [-A, A] of its standard deviation
        /// (repeatable; e.g. half a blob's input step, or float32's 6e-8),
        /// each against the plain f64 rollout: how sensitive the model's
        /// own closed loop is, apart from any arithmetic.
        #[arg(long, value_name = "A", allow_negative_numbers = true)]
        input_noise: Vec<f64>,
        /// Seeds of each --input-noise amount.
        #[arg(long, value_name = "N", default_value_t = 4, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::RUNS as u64))]
        noise_seeds: u64,
        /// Also run every target script of DIR (`tools/omg/scripts` is the
        /// committed set; R1 joint-velocity models, from rest): the same
        /// rows summed over the scripts, and each `unreachable` target.
        #[arg(long, value_name = "DIR")]
        scripts: Option<PathBuf>,
    },
    /// OMG models (docs/omg.md): the f64 graph forward vs the committed
    /// PyTorch references, and int16 / int8 blobs vs the f64 forward, one
    /// step and over the 300-frame grounded rollout.
    OmgAccuracy {
        /// Model directories (model.safetensors, config.json, references.npz).
        #[arg(required = true)]
        dirs: Vec<PathBuf>,
        /// Also write every figure as JSON.
        #[arg(long)]
        json: Option<PathBuf>,
        /// Spread of the calibration inputs, in standard deviations (the
        /// quantiser's calibration_scale).
        #[arg(long, default_value_t = 1.0)]
        calibration_scale: f64,
        /// Factor between calibrated maxima and the i16 range (as `exporter
        /// omg --headroom`).
        #[arg(long, default_value_t = exporter::net::omg::HEADROOM)]
        headroom: f64,
        /// The int8 blob's quantiser knobs, as `exporter omg` takes them.
        #[command(flatten)]
        int8: host_sim::quant_knobs::Int8Knobs,
        /// Instead of exporting blobs: measure this motion blob with
        /// --rig against the f64 model of the one directory given (the
        /// rig's model; docs/omg.md, "Rig blobs").
        #[arg(long, requires = "rig")]
        motion: Option<PathBuf>,
        /// The rig blob run with --motion.
        #[arg(long, requires = "motion")]
        rig: Option<PathBuf>,
    },
    /// Run a blob on the Cortex-M4 firmware under QEMU, bit for bit against the host runtime.
    Target {
        /// The model blob, flashed at the MODEL region on its own.
        #[arg(long)]
        model: PathBuf,
        /// Frames to run (default: all golden frames, or 16 generated ones;
        /// 60 controller steps with --controller).
        #[arg(long, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::FRAMES))]
        frames: Option<usize>,
        /// float32 (N, inputs) raw inputs in model units.
        #[arg(long, requires = "phases")]
        inputs: Option<PathBuf>,
        /// float32 (N,) phases in radians.
        #[arg(long, requires = "inputs")]
        phases: Option<PathBuf>,
        /// A style blob for the model, flashed in the STYLES region; repeat
        /// for more (style id = order given).
        #[arg(long = "style", value_name = "FILE")]
        styles: Vec<PathBuf>,
        /// A rig blob for the model (`exporter omg-rig --base MODEL`),
        /// flashed at the start of the STYLES region: the firmware runs the
        /// model (the motion blob) with that rig's autoencoder as one
        /// model, compared bit for bit with the host runtime's pair.
        #[arg(long, value_name = "FILE", conflicts_with_all = ["styles", "controller", "reach"])]
        rig: Option<PathBuf>,
        /// Mix of each frame: `base`, a style id (`0`), `blend:FROM:TO:WEIGHT`,
        /// a comma-separated list repeated over the frames (`ITEM*N` = N
        /// frames), or `cycle[:STEP]` (base, 0, 1, blend 0->1 at weights 0,
        /// 0.25, 0.5, 0.75, 1; STEP frames each, default 2). Default: base;
        /// `base*2,0*2` with one --style; cycle with two or more.
        #[arg(long, value_name = "SPEC")]
        mix: Option<host_sim::target::MixSpec>,
        /// Also estimate Cortex-M4 cycles per frame: the run is traced
        /// (slower) and each executed instruction priced with the Cortex-M4
        /// TRM's cycle counts (docs/performance.md).
        #[arg(long, conflicts_with = "controller")]
        cycles: bool,
        /// Also check the firmware's boot self-test with N vectors, both
        /// ways: the blob with a self-test of N vectors (`exporter
        /// --self-test N`; the blob's own if it has one) must pass at boot
        /// and run its frames as without it, and a copy with one stored
        /// output changed (CRC re-sealed) must be refused with exit code 12
        /// and a log line naming the vector and output.
        #[arg(long = "self-test", value_name = "N",
              conflicts_with_all = ["rig", "controller", "reach"],
              value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::SELF_TEST))]
        self_test: Option<usize>,
        /// Run the locomotion controller on the firmware instead of raw
        /// network frames: a rollout script (idle, walk, circle-left, zigzag,
        /// jog-stop-jog, crouch-walk, or a JSON file) gives each frame's
        /// command; every pose is compared bit for bit with the host's loop.
        /// The model must be PFNN-shaped (342 inputs, 311 outputs). Default
        /// 60 frames.
        #[arg(long, value_name = "SCRIPT", conflicts_with = "inputs")]
        controller: Option<String>,
        /// With --controller: a frame budget of this many instructions
        /// (rounded down to SysTick ticks of 40 instructions); the firmware
        /// times every frame against it, reports each overrun and applies
        /// --overrun-policy (docs/deadline.md).
        #[arg(long, value_name = "N", requires = "controller")]
        budget_instructions: Option<u64>,
        /// With --budget-instructions: what an overrun does to the next frame.
        #[arg(
            long,
            value_enum,
            default_value = "hold-next",
            requires = "budget_instructions"
        )]
        overrun_policy: PolicyArg,
        /// Run the OMG reaching loop on the firmware (its `reach` build):
        /// a target script as `host-sim rollout --omg --script` takes it
        /// (reach-front, alternate, a JSON file, ref:N, clip:N) gives the
        /// hands' targets; every frame is compared bit for bit with the
        /// host's `Reach<f32>`. Needs --omg. Default 60 steps.
        #[arg(long, value_name = "SCRIPT", requires = "omg", conflicts_with_all = ["controller", "inputs", "cycles"])]
        reach: Option<String>,
        /// With --reach: the model's directory (config.json: the layout;
        /// its first reference frame: the start frame).
        #[arg(long, value_name = "DIR", requires = "reach")]
        omg: Option<PathBuf>,
        /// With --reach: feed the predicted costs back instead of
        /// recomputing them from the pose (grounded, the default).
        #[arg(long, requires = "reach")]
        faithful: bool,
        /// With --reach clip:N: the data tools/omg/generate wrote.
        #[arg(long, value_name = "DIR", requires = "reach")]
        data: Option<PathBuf>,
        /// A speed bar the run must meet (else it fails after its report):
        /// `per-mac=F` (every layer node at most F instructions per MAC),
        /// `nodeN-per-mac=F` (node N), `frame=N` (median inference
        /// instructions per frame); repeat for more. Network runs only.
        #[arg(long = "bar", value_name = "SPEC", conflicts_with_all = ["controller", "reach"])]
        bars: Vec<host_sim::target::bars::Bar>,
    },
    /// Code size, static RAM and stack of the inference core, the firmware
    /// and the controller firmware, each against its .text budget.
    Footprint {
        /// Also write the figures as JSON (one object per build).
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// Check the firmware's log snapshots (firmware/snapshots), or bless new ones.
    FirmwareSnapshots {
        /// Write the current logs as the expected ones.
        #[arg(long)]
        overwrite: bool,
    },
    /// Drive a controller with a command script and record the rollout (.npz).
    Rollout(host_sim::rollout::RolloutArgs),
    /// Per-frame and summary errors between two rollouts of the same script.
    RolloutCompare(host_sim::rollout::RolloutCompareArgs),
    /// The float controller's network inputs and phases over scripts (.npz), for `exporter cp --distill-data`.
    RolloutDataset(host_sim::rollout::dataset::RolloutDatasetArgs),
    /// Draw skeleton snapshots of one or two rollouts (PNG).
    Render(host_sim::render::RenderArgs),
    /// Plot the errors between two rollouts against frame number (PNG).
    PlotErrors(host_sim::render::PlotErrorsArgs),
    /// Controller fidelity on a real PFNN: int16/int8 blobs and f32 vs f64, every built-in script.
    Fidelity(host_sim::rollout::fidelity::FidelityArgs),
    /// Learn two CP style adapters from the base model's own rollouts, export and roll them out.
    StyleDemo(host_sim::style::demo::StyleDemoArgs),
    /// Check (default) or rewrite the golden vectors of the default model.
    Golden {
        /// The golden directory.
        #[arg(default_value = "tests/golden/default")]
        dir: PathBuf,
        /// Regenerate every file from the seeds instead of checking.
        #[arg(long)]
        write: bool,
    },
}

fn load_reference(path: &Path, mode: GatingMode) -> Result<Net> {
    if path.is_dir() {
        let tables = exporter::pfnn_dir::load_pfnn_dir_auto(path, None)?;
        Ok(Net::from_pfnn_tables(&tables, mode).0)
    } else {
        exporter::npz::pfnn_from_npz(path, mode)
    }
}

#[allow(clippy::too_many_arguments)]
fn eval_cmd(
    model: Option<PathBuf>,
    reference: Option<PathBuf>,
    gating: Option<Gating>,
    inputs: &Path,
    phases: &Path,
    out: &Path,
    raw_out: Option<PathBuf>,
) -> Result<()> {
    let p = npy::read_vector_f32(phases)?;
    if let Some(model) = model {
        let blob = exporter::atomic::read_input(&model)
            .map_err(|e| anyhow!("cannot read {}: {e}", model.display()))?;
        let m = phasegate::Model::from_bytes(&blob)
            .map_err(|e| anyhow!("{}: {}", model.display(), exporter::inspect::explain(&e)))?;
        let x = npy::read_matrix_f32(inputs, m.input_dim())?;
        check_frames(&x, inputs, &p, phases)?;
        let run = eval::run_fixed(&blob, &x, &p)?;
        let mut outputs = exporter::atomic::Outputs::new();
        outputs.add(out, npy::matrix_bytes(&run.outputs)?);
        if let Some(raw) = raw_out {
            outputs.add(raw, npy::matrix_bytes(&run.raw)?);
        }
        outputs.commit()
    } else {
        let (Some(r), Some(g)) = (reference, gating) else {
            bail!("--reference needs --gating")
        };
        let net = load_reference(&r, g.into())?;
        let x = npy::read_matrix_f32(inputs, net.input_dim())?;
        check_frames(&x, inputs, &p, phases)?;
        npy::write_matrix(out, &eval::run_reference(&net, &x, &p)?)
    }
}

/// The frames `eval` runs, checked before any is: one phase per input row,
/// every value finite; errors name the file, row and column.
fn check_frames(x: &npy::Matrix<f32>, inputs: &Path, p: &[f32], phases: &Path) -> Result<()> {
    if x.rows != p.len() {
        bail!(
            "{} has {} input rows, but {} has {} phases (one per row)",
            inputs.display(),
            x.rows,
            phases.display(),
            p.len()
        );
    }
    if let Some(i) = x.data.iter().position(|v| !v.is_finite()) {
        bail!(
            "{}: row {}, column {} is {}: inputs must be finite",
            inputs.display(),
            i / x.cols.max(1),
            i % x.cols.max(1),
            x.data[i]
        );
    }
    if let Some(i) = p.iter().position(|v| !v.is_finite()) {
        bail!(
            "{}: phase {i} is {}: phases must be finite",
            phases.display(),
            p[i]
        );
    }
    Ok(())
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Eval {
            model,
            reference,
            gating,
            inputs,
            phases,
            out,
            raw_out,
        } => eval_cmd(model, reference, gating, &inputs, &phases, &out, raw_out),
        Command::Compare { a, b, json } => {
            let c = compare::compare(
                &npy::read_matrix_f32_any(&a)?,
                &npy::read_matrix_f32_any(&b)?,
            )
            .with_context(|| format!("{} vs {}", a.display(), b.display()))?;
            if json {
                println!("{}", serde_json::to_string_pretty(&c)?);
            } else {
                print!("{}", c.table());
            }
            Ok(())
        }
        Command::Demo {
            pfnn,
            frames,
            picture,
            gif,
            no_target,
        } => {
            let Some(dir) = pfnn else {
                let d = host_sim::demo_omg::run_demo(Some(&picture), Some(&gif), no_target)?;
                print!("{}", d.render());
                return Ok(());
            };
            let tables = exporter::pfnn_dir::load_pfnn_dir_auto(&dir, None)?;
            let (net, residual) = Net::from_pfnn_tables(&tables, GatingMode::Cubic);
            let (blob, _) = exporter::export::export(&net, residual, &Default::default())?;
            let title = format!("PFNN from {} (int8 cubic)", dir.display());
            print!(
                "{}",
                demo::run_demo(&blob, &net, frames, 11)?.render(&title)
            );
            Ok(())
        }
        Command::Accuracy {
            pfnn,
            samples,
            seed,
            json,
            int8,
        } => {
            let tables = exporter::pfnn_dir::load_pfnn_dir_auto(&pfnn, None)?;
            let a = accuracy::measure(&tables, samples, seed, &int8)?;
            print!("{}", a.table());
            println!(
                "blob sizes: int16 cubic {} bytes, int8 cubic {} bytes",
                a.int16_report.blob_bytes, a.int8_report.blob_bytes
            );
            if let Some(path) = json {
                exporter::atomic::write_atomic(&path, &serde_json::to_vec_pretty(&a)?)?;
            }
            Ok(())
        }
        Command::OmgReach {
            dirs,
            data,
            json,
            headroom,
            int8,
            motion_from,
            train_clips,
            input_noise,
            noise_seeds,
            scripts,
        } => {
            let opts = exporter::quantise::QuantOptions {
                headroom,
                ..Default::default()
            };
            let mut all = Vec::new();
            for d in &dirs {
                let judged = host_sim::omg_reach::Judged::new(d, &data, train_clips)?;
                let mut r = host_sim::omg_reach::measure_with_scripts(
                    &judged,
                    &opts,
                    &int8,
                    motion_from.as_deref(),
                    scripts.as_deref(),
                )?;
                r.rows.extend(host_sim::omg_reach::input_noise_rows(
                    &judged,
                    &input_noise,
                    noise_seeds,
                )?);
                print!("{}", r.table());
                all.push(r);
            }
            if let Some(path) = json {
                exporter::atomic::write_atomic(&path, &serde_json::to_vec_pretty(&all)?)?;
            }
            Ok(())
        }
        Command::OmgAccuracy {
            dirs,
            json,
            calibration_scale,
            headroom,
            int8,
            motion,
            rig,
        } => {
            if let (Some(motion), Some(rig)) = (&motion, &rig) {
                let [dir] = dirs.as_slice() else {
                    anyhow::bail!("--motion and --rig measure one model directory, the rig's");
                };
                let (text, a) = host_sim::omg::rig_pair_report(dir, motion, rig)?;
                print!("{text}");
                if let Some(path) = json {
                    exporter::atomic::write_atomic(&path, &serde_json::to_vec_pretty(&a)?)?;
                }
                return Ok(());
            }
            let opts = exporter::quantise::QuantOptions {
                calibration_scale,
                headroom,
                ..Default::default()
            };
            let mut all = Vec::new();
            for d in &dirs {
                let a = host_sim::omg::measure(d, &opts, &int8)?;
                print!("{}", a.table());
                all.push(a);
            }
            if let Some(path) = json {
                exporter::atomic::write_atomic(&path, &serde_json::to_vec_pretty(&all)?)?;
            }
            Ok(())
        }
        Command::Target {
            model,
            frames,
            inputs,
            phases,
            styles,
            rig,
            mix,
            cycles,
            self_test,
            controller,
            budget_instructions,
            overrun_policy,
            reach,
            omg,
            faithful,
            data,
            bars,
        } => {
            if let (Some(script), Some(dir)) = (reach, omg) {
                host_sim::target::reach::run(&host_sim::target::reach::ReachArgs {
                    model: &model,
                    dir: &dir,
                    script: &script,
                    data,
                    frames,
                    mode: if faithful {
                        phasegate_controller::CostMode::Faithful
                    } else {
                        phasegate_controller::CostMode::Grounded
                    },
                })?;
                return Ok(());
            }
            if let Some(script) = controller {
                let deadline = match budget_instructions {
                    None => phasegate_controller::DeadlineConfig::NONE,
                    Some(n) => phasegate_controller::DeadlineConfig {
                        budget: Some(
                            phasegate_controller::FrameBudget::from_instructions(
                                n,
                                host_sim::target::INSTRUCTIONS_PER_TICK as u32,
                            )
                            .map_err(|e| anyhow::anyhow!("--budget-instructions {n}: {e}"))?,
                        ),
                        policy: overrun_policy.into(),
                    },
                };
                host_sim::target::controller::run(&host_sim::target::controller::ControllerArgs {
                    model: &model,
                    script: &script,
                    frames,
                    styles: &styles,
                    mix,
                    deadline,
                })?;
                return Ok(());
            }
            let report = host_sim::target::run_target(&host_sim::target::TargetArgs {
                model,
                frames,
                inputs,
                phases,
                styles,
                rig,
                mix,
                cycles,
                self_test,
            })?;
            host_sim::target::bars::check(&bars, &report)
        }
        Command::Footprint { json } => host_sim::footprint::footprint_cmd(json.as_deref()),
        Command::FirmwareSnapshots { overwrite } => {
            let outcomes = host_sim::target::snapshot::run_snapshots(overwrite)?;
            for (name, outcome) in &outcomes {
                println!("{name}: {outcome:?}");
            }
            Ok(())
        }
        Command::Rollout(args) => host_sim::rollout::rollout_cmd(&args),
        Command::RolloutCompare(args) => host_sim::rollout::rollout_compare_cmd(&args),
        Command::RolloutDataset(args) => host_sim::rollout::dataset::rollout_dataset_cmd(&args),
        Command::Render(args) => host_sim::render::render_cmd(&args),
        Command::PlotErrors(args) => host_sim::render::plot_errors_cmd(&args),
        Command::Fidelity(args) => host_sim::rollout::fidelity::fidelity_cmd(&args),
        Command::StyleDemo(args) => host_sim::style::demo::style_demo_cmd(&args),
        Command::Golden { dir, write } => {
            if write {
                golden::write(&dir)?;
                println!("wrote golden vectors to {}", dir.display());
            } else {
                let n = golden::check(&dir)?;
                println!("golden vectors: {n} frames bit-exact ({})", dir.display());
            }
            Ok(())
        }
    }
}

fn main() -> ExitCode {
    exporter::atomic::guard_inputs();
    exporter::atomic::clean_up_on_interrupt();
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            if exporter::atomic::is_interrupted(&e) {
                exporter::atomic::end_interrupted();
            }
            eprintln!("error: {}", format!("{e:#}").replace('\n', " "));
            ExitCode::FAILURE
        }
    }
}

/// `--overrun-policy` of `host-sim target --controller`.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum PolicyArg {
    /// Report overruns only; every frame infers.
    Report,
    /// Hold the last pose and skip the next frame's inference.
    HoldNext,
}

impl From<PolicyArg> for phasegate_controller::OverrunPolicy {
    fn from(p: PolicyArg) -> Self {
        match p {
            PolicyArg::Report => phasegate_controller::OverrunPolicy::Report,
            PolicyArg::HoldNext => phasegate_controller::OverrunPolicy::HoldNext,
        }
    }
}
