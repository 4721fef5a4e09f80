//! `host-sim style-demo`: learning residual adapters without style data.
//!
//! Two target styles are defined as transformations of the base model's own
//! behaviour, applied to its outputs on rollouts of the controller:
//!
//! * `crouch`: every joint's height (position and vertical velocity) times
//!   0.8, a lowered, crouched posture;
//! * `swing`: the forward swing of the arms (elbows, hands, fingers) about
//!   their mean position doubled, position and velocity.
//!
//! The transformation applies to the whole rollout, the fed-back previous
//! pose in the inputs included, as if a styled actor had been captured
//! doing what the base controller did. For each style, a CP adapter of rank
//! `--rank` beside layer 1 (the paper's eq. 4) is fitted with the base
//! frozen (Adam on the normalised output error,
//! [`exporter::cp::distill::train`]) on those transformed rollouts, then on
//! the styled controller's own rollouts (`--rounds`, DAgger-style: a state
//! is labelled with the transformed base output of its unstyled
//! equivalent), exported as an int8 style blob, and rolled out on a
//! held-out script in fixed point (`Runtime`) and float, alone,
//! blended, and switched between frames.

use anyhow::Result;
use exporter::cp::distill::{inputs_and_gates, train, Dataset, TrainOptions};
use exporter::cp::import::adapter_bytes;
use exporter::export::export;
use exporter::net::GatingMode;
use exporter::net::{Adapter, CpLayer, Net, NetLayer};
use exporter::quantise::QuantOptions;
use exporter::style::{build_style, StyleReport};
use ndarray::{concatenate, Array1, Array2, Axis};
use phasegate::style::BlendWeight;
use phasegate::{Mix, StyleId};
use phasegate_controller::layout::JOINTS;
use phasegate_controller::{Command, Gait};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::path::PathBuf;

use super::{
    metrics, mix_label, pose_difference, rollout, svg_side_views, Run, StyleMetrics, StyledFixed,
};
use crate::controller::FloatNet64;

/// `host-sim style-demo`.
#[derive(Debug, clap::Args)]
pub struct StyleDemoArgs {
    /// The base model's float weights: a PFNN weight directory or a
    /// PFNN-shaped .npz (cubic gating).
    #[arg(long)]
    pub pfnn: PathBuf,
    /// Directory for the blobs, adapters, report and pictures.
    #[arg(long)]
    pub out: PathBuf,
    /// CP rank of the adapters (the paper: 30).
    #[arg(long, default_value_t = 30, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::RANK))]
    pub rank: usize,
    /// Adam steps of the first fit.
    #[arg(long, default_value_t = 1500, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::STEPS))]
    pub steps: usize,
    /// Further fits on the styled controller's own rollouts.
    #[arg(long, default_value_t = 1, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::RUNS))]
    pub rounds: usize,
    /// Frames of each training script.
    #[arg(long, default_value_t = 480, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::FRAMES))]
    pub frames: usize,
}

/// Frames per second of the controller.
const FPS: f64 = 60.0;

fn at(f: usize) -> f64 {
    f as f64 / FPS
}

/// The training scripts: the base controller's behaviour to transform.
pub fn training_scripts(frames: usize) -> Vec<(&'static str, Vec<Command>)> {
    let stand = |f: usize| at(f) < 0.5;
    let walk = |v: [f32; 2]| Command::moving(v, Gait::Walk);
    vec![
        (
            "walk",
            (0..frames)
                .map(|f| {
                    if stand(f) {
                        Command::stand()
                    } else {
                        walk([0.0, 2.5])
                    }
                })
                .collect(),
        ),
        (
            "circle",
            (0..frames)
                .map(|f| {
                    let a = 0.6 * at(f) as f32;
                    if stand(f) {
                        Command::stand()
                    } else {
                        walk([2.5 * a.sin(), 2.5 * a.cos()])
                    }
                })
                .collect(),
        ),
        (
            "zigzag",
            (0..frames)
                .map(|f| {
                    let side = if (f / 90) % 2 == 0 { 1.77 } else { -1.77 };
                    if stand(f) {
                        Command::stand()
                    } else {
                        walk([side, 1.77])
                    }
                })
                .collect(),
        ),
        (
            "jog-stop",
            (0..frames)
                .map(|f| {
                    let t = at(f);
                    if stand(f) || (3.0..4.5).contains(&t) {
                        Command::stand()
                    } else {
                        Command::moving([0.0, 4.5], Gait::Jog)
                    }
                })
                .collect(),
        ),
        (
            "slow-turns",
            (0..frames)
                .map(|f| {
                    let a = -0.9 * at(f) as f32;
                    if stand(f) {
                        Command::stand()
                    } else {
                        walk([1.8 * a.sin(), 1.8 * a.cos()])
                    }
                })
                .collect(),
        ),
    ]
}

/// The held-out script: walk, turn right, jog, slow down, walk left.
pub fn evaluation_script(frames: usize) -> Vec<Command> {
    (0..frames)
        .map(|f| {
            let t = at(f);
            match t {
                t if t < 0.5 => Command::stand(),
                t if t < 3.0 => Command::moving([0.0, 2.5], Gait::Walk),
                t if t < 5.0 => {
                    let a = 0.8 * (t - 3.0) as f32;
                    Command::moving([2.5 * a.sin(), 2.5 * a.cos()], Gait::Walk)
                }
                t if t < 7.0 => Command::moving([3.5, 2.0], Gait::Jog),
                _ => Command::moving([-1.5, 1.5], Gait::Walk),
            }
        })
        .collect()
}

/// Arm joints whose swing `swing` exaggerates: elbows, hands and fingers.
pub const ARM_JOINTS: [usize; 10] = [19, 20, 21, 22, 23, 26, 27, 28, 29, 30];
const POS: usize = 32;
const VEL: usize = POS + 3 * JOINTS;

/// A target style: a transformation of the base network's outputs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Target {
    /// Heights times 0.8.
    Crouch,
    /// Forward arm swing about the mean doubled.
    Swing,
}

impl Target {
    /// Name.
    pub fn name(self) -> &'static str {
        match self {
            Target::Crouch => "crouch",
            Target::Swing => "swing",
        }
    }

    /// The styled output for a base output `y` (model units); `ymean` is the
    /// data set's mean output.
    pub fn apply(self, y: &[f64], ymean: &[f64]) -> Vec<f64> {
        let mut out = y.to_vec();
        self.joints(&mut out, POS, VEL, ymean, false);
        out
    }

    /// The same transformation of the previous pose inside a network input
    /// `x` (joint positions and velocities, as the controller feeds back the
    /// last output), or its inverse.
    pub fn apply_input(self, x: &[f64], ymean: &[f64], inverse: bool) -> Vec<f64> {
        let mut out = x.to_vec();
        self.joints(&mut out, IN_POS, IN_VEL, ymean, inverse);
        out
    }

    fn joints(self, v: &mut [f64], pos: usize, vel: usize, ymean: &[f64], inverse: bool) {
        match self {
            Target::Crouch => {
                let k = if inverse { 1.0 / 0.8 } else { 0.8 };
                for j in 0..JOINTS {
                    v[pos + 3 * j + 1] *= k;
                    v[vel + 3 * j + 1] *= k;
                }
            }
            Target::Swing => {
                let k = if inverse { 0.5 } else { 2.0 };
                for &j in &ARM_JOINTS {
                    let m = ymean[POS + 3 * j + 2];
                    let z = pos + 3 * j + 2;
                    v[z] = m + k * (v[z] - m);
                    v[vel + 3 * j + 2] *= k;
                }
            }
        }
    }
}

/// Previous joint positions and velocities in the network input.
const IN_POS: usize = 120;
const IN_VEL: usize = IN_POS + 3 * JOINTS;

/// The styled data set of some rollouts. Base rollouts (`styled` false):
/// inputs and outputs both transformed, as if a styled actor had been
/// captured doing the same. Styled rollouts (`styled` true, DAgger-style):
/// the states the styled controller reached, labelled with the transformed
/// base output of the equivalent unstyled state.
fn dataset(net: &Net, runs: &[Run], target: Target, styled: bool) -> Dataset {
    let ymean = net.ymean.to_vec();
    let raw: Vec<Vec<f64>> = runs.iter().flat_map(|r| r.inputs.clone()).collect();
    let ps: Vec<f64> = runs.iter().flat_map(|r| r.phases.clone()).collect();
    let (xs, ys): (Vec<Vec<f64>>, Vec<Vec<f64>>) = if styled {
        raw.iter()
            .zip(&ps)
            .map(|(x, &p)| {
                let plain = target.apply_input(x, &ymean, true);
                (x.clone(), target.apply(&net.forward(&plain, p), &ymean))
            })
            .unzip()
    } else {
        let outs = runs.iter().flat_map(|r| r.outputs.clone());
        raw.iter()
            .zip(outs)
            .map(|(x, y)| {
                (
                    target.apply_input(x, &ymean, false),
                    target.apply(&y, &ymean),
                )
            })
            .unzip()
    };
    let (x, g) = inputs_and_gates(net, &xs, &ps);
    let mut y = Array2::zeros((ys.len(), net.output_dim()));
    for (i, row) in ys.iter().enumerate() {
        for (j, v) in row.iter().enumerate() {
            y[(i, j)] = (v - net.ymean[j]) / net.ystd[j];
        }
    }
    Dataset { x, g, y }
}

fn merge(a: Dataset, b: Dataset) -> Dataset {
    let cat = |p: &Array2<f64>, q: &Array2<f64>| {
        concatenate(Axis(0), &[p.view(), q.view()]).unwrap_or_else(|_| p.clone())
    };
    Dataset {
        x: cat(&a.x, &b.x),
        g: cat(&a.g, &b.g),
        y: cat(&a.y, &b.y),
    }
}

/// A small CP adapter to start from (`A` near zero: the style starts as
/// the base).
pub fn initial_adapter(hidden: usize, experts: usize, rank: usize, seed: u64) -> Adapter {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut n = |s: f64| s * ((0..12).map(|_| rng.gen_range(0.0..1.0)).sum::<f64>() - 6.0);
    let a = Array2::from_shape_fn((hidden, rank), |_| n(1e-3));
    let b = Array2::from_shape_fn((hidden, rank), |_| n(1.0 / (hidden as f64).sqrt()));
    Adapter {
        layer: 1,
        op: NetLayer::Cp(CpLayer {
            a,
            b,
            d: Array2::ones((experts, rank)),
            bias: vec![Array1::zeros(hidden); experts],
        }),
    }
}

/// One style's fit and measurements.
#[derive(Clone, Debug, Serialize)]
pub struct StyleResult {
    /// Style.
    pub name: &'static str,
    /// Training loss (mean squared normalised error) before and after each fit.
    pub losses: Vec<(f64, f64)>,
    /// The style blob's report (sizes, fixed vs float on random inputs).
    pub blob: StyleReport,
    /// Metrics of the fixed-point styled rollout of the held-out script.
    pub fixed: StyleMetrics,
    /// Metrics of the float styled rollout.
    pub float: StyleMetrics,
    /// Fixed vs float styled rollout: RMS and max joint distance (root space).
    pub fixed_vs_float_pose: (f64, f64),
    /// How far the style got to its target on the held-out rollout: the
    /// RMS of (network output - transformed base output) over the
    /// transformed coordinates, fixed point, relative to the RMS of the
    /// transformation itself (0 = perfect, 1 = no style at all).
    pub target_residual: f64,
}

/// The whole demonstration.
#[derive(Clone, Debug, Serialize)]
pub struct DemoReport {
    /// Adapter rank.
    pub rank: usize,
    /// Base blob bytes.
    pub base_blob_bytes: usize,
    /// Base rollout metrics (fixed point, held-out script).
    pub base: StyleMetrics,
    /// Base float metrics.
    pub base_float: StyleMetrics,
    /// Base fixed vs base float rollout: RMS and max joint distance.
    pub base_fixed_vs_float_pose: (f64, f64),
    /// Per style.
    pub styles: Vec<StyleResult>,
    /// 50/50 blend of the two styles (fixed point).
    pub blend: StyleMetrics,
    /// Mix switched every third of the script (base, crouch, swing, blend).
    pub switched: StyleMetrics,
    /// Largest per-frame phase step in the switched run, and in the base run.
    pub phase_step_max: (f64, f64),
}

fn residual(target: Target, run: &Run, net: &Net) -> f64 {
    let ymean = net.ymean.to_vec();
    let coords: Vec<usize> = match target {
        Target::Crouch => (0..JOINTS)
            .flat_map(|j| [POS + 3 * j + 1, VEL + 3 * j + 1])
            .collect(),
        Target::Swing => ARM_JOINTS
            .iter()
            .flat_map(|&j| [POS + 3 * j + 2, VEL + 3 * j + 2])
            .collect(),
    };
    let (mut res, mut change) = (0.0, 0.0);
    for ((x, &p), y) in run.inputs.iter().zip(&run.phases).zip(&run.outputs) {
        let base = net.forward(&target.apply_input(x, &ymean, true), p);
        let want = target.apply(&base, &ymean);
        for &c in &coords {
            res += ((y[c] - want[c]) / net.ystd[c]).powi(2);
            change += ((want[c] - base[c]) / net.ystd[c]).powi(2);
        }
    }
    (res / change.max(f64::MIN_POSITIVE)).sqrt()
}

fn max_phase_step(run: &Run) -> f64 {
    run.phases
        .windows(2)
        .map(|w| (w[1] - w[0]).rem_euclid(std::f64::consts::TAU))
        .fold(0.0, f64::max)
}

/// The training rows `style-demo` keeps for `frames` and `rounds`: every
/// training script's frames, once per fit (the data of each round is
/// added to the last's).
pub fn training_rows(frames: usize, rounds: usize) -> usize {
    training_scripts(0)
        .len()
        .saturating_mul(frames)
        .saturating_mul(rounds.saturating_add(1))
}

/// Runs the demonstration.
pub fn style_demo(args: &StyleDemoArgs) -> Result<DemoReport> {
    let rows = training_rows(args.frames, args.rounds);
    if rows > exporter::cli_args::bounds::STYLE_ROWS {
        anyhow::bail!(
            "{} training scripts of {} frames over {} fits make {rows} rows, more than the \
             largest style-demo data set, {} rows: fewer --frames or --rounds",
            training_scripts(0).len(),
            args.frames,
            args.rounds.saturating_add(1),
            exporter::cli_args::bounds::STYLE_ROWS
        );
    }
    // Every file or none, in `--out` (made if missing).
    let mut outputs = exporter::atomic::Outputs::new();
    outputs.dir(&args.out);
    let pfnn = crate::style::load_float(&args.pfnn)?;
    let net = pfnn.clone();
    let hidden = net.layers[1].out_dim();
    eprintln!("exporting the int8 base blob");
    let (base_blob, _) = export(&pfnn, None, &QuantOptions::default())?;
    outputs.add(args.out.join("base.blob"), base_blob.clone());

    eprintln!("base rollouts for training");
    let scripts = training_scripts(args.frames);
    let mut base_runs = Vec::new();
    for (_, cmds) in &scripts {
        base_runs.push(rollout::<f64, _>(&mut FloatNet64(&net), cmds)?);
    }

    let eval = evaluation_script(600);
    let skip = 60;
    let mut styles = Vec::new();
    let mut adapters = Vec::new();
    let mut blobs = Vec::new();
    for (si, target) in [Target::Crouch, Target::Swing].into_iter().enumerate() {
        let mut ad = vec![initial_adapter(
            hidden,
            net.experts(),
            args.rank,
            100 + si as u64,
        )];
        let mut data = dataset(&net, &base_runs, target, false);
        let mut losses = Vec::new();
        for round in 0..=args.rounds {
            eprintln!("{}: fit {round} on {} frames", target.name(), data.len());
            let steps = if round == 0 {
                args.steps
            } else {
                args.steps / 2
            };
            let rep = train(
                &mut net.clone(),
                &[],
                &mut ad,
                &data,
                &TrainOptions {
                    steps,
                    batch: 64,
                    lr: if round == 0 { 2e-3 } else { 1e-3 },
                    l1: 0.0,
                    seed: 7 + round as u64,
                },
            );
            losses.push((rep.loss_before, rep.loss_after));
            if round < args.rounds {
                let styled = net.with_adapters(&[(&ad[0], 1.0)])?;
                let mut own = Vec::new();
                for (_, cmds) in &scripts {
                    own.push(rollout::<f64, _>(&mut FloatNet64(&styled), cmds)?);
                }
                data = merge(data, dataset(&net, &own, target, true));
            }
        }
        let adapter = ad.remove(0);
        outputs.add(
            args.out.join(format!("{}.npz", target.name())),
            adapter_bytes(&adapter)?,
        );
        let (blob, report) = build_style(
            &base_blob,
            &net,
            &adapter,
            target.name(),
            &QuantOptions::default(),
            256,
        )?;
        outputs.add(
            args.out.join(format!("{}.style", target.name())),
            blob.clone(),
        );
        blobs.push(blob);
        adapters.push(adapter);
        styles.push((target, losses, report));
    }

    eprintln!("held-out rollouts");
    let blob_refs: Vec<&[u8]> = blobs.iter().map(Vec::as_slice).collect();
    let fixed_run = |mix: &dyn Fn(usize) -> Mix| -> Result<Run> {
        let mut fx = StyledFixed::new(&base_blob, &blob_refs)?;
        let mut state = phasegate_controller::Locomotion::<f32>::new(&fx)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let mut run = Run::default();
        for (f, c) in eval.iter().enumerate() {
            fx.rt.set_mix(mix(f)).map_err(|e| anyhow::anyhow!("{e}"))?;
            let pose = state.step(&mut fx, c).map_err(|e| anyhow::anyhow!("{e}"))?;
            run.poses.push(super::widen(pose));
            run.phases
                .push(f64::from(pose.phase) * std::f64::consts::TAU);
            run.inputs
                .push(state.last_input().iter().map(|&v| f64::from(v)).collect());
            run.outputs
                .push(state.last_output().iter().map(|&v| f64::from(v)).collect());
        }
        Ok(run)
    };
    let base_fixed = fixed_run(&|_| Mix::Base)?;
    let base_float = rollout::<f64, _>(&mut FloatNet64(&net), &eval)?;
    let mut results = Vec::new();
    let mut styled_fixed = Vec::new();
    for (i, (target, losses, report)) in styles.into_iter().enumerate() {
        let fixed = fixed_run(&|_| Mix::One(StyleId(i as u8)))?;
        let styled = net.with_adapters(&[(&adapters[i], 1.0)])?;
        let float = rollout::<f64, _>(&mut FloatNet64(&styled), &eval)?;
        results.push(StyleResult {
            name: target.name(),
            losses,
            blob: report,
            fixed: metrics(&fixed.poses, skip),
            float: metrics(&float.poses, skip),
            fixed_vs_float_pose: pose_difference(&fixed.poses, &float.poses),
            target_residual: residual(target, &fixed, &net),
        });
        styled_fixed.push(fixed);
    }
    let half = Mix::Blend {
        from: StyleId(0),
        to: StyleId(1),
        weight: BlendWeight::from_num(0.5),
    };
    let blend = fixed_run(&|_| half)?;
    let third = eval.len() / 4;
    let switches = [Mix::Base, Mix::One(StyleId(0)), Mix::One(StyleId(1)), half];
    let switched = fixed_run(&|f| switches[(f / third).min(3)])?;

    let frames = [90usize, 150, 210, 270, 330, 390, 450, 510];
    let names = ["crouch", "swing"];
    let blend_label = mix_label(half, &names);
    let rows: [(&str, &[phasegate_controller::Pose<f64>], &str); 4] = [
        ("base (int8, fixed point)", &base_fixed.poses, "#1f5fbf"),
        ("crouch style", &styled_fixed[0].poses, "#d9661f"),
        ("swing style", &styled_fixed[1].poses, "#2a9d3a"),
        (&blend_label, &blend.poses, "#8a3ab9"),
    ];
    let title = format!(
        "PFNN with rank-{} CP style adapters (int8 Runtime), held-out script, side views in root space",
        args.rank
    );
    outputs.add(
        args.out.join("styles.png"),
        super::side_views_canvas(&rows, &frames, &title).png_bytes()?,
    );
    let svg = svg_side_views(&rows, &frames, &title);
    outputs.add(args.out.join("styles.svg"), svg.into_bytes());
    let report = DemoReport {
        rank: args.rank,
        base_blob_bytes: base_blob.len(),
        base: metrics(&base_fixed.poses, skip),
        base_float: metrics(&base_float.poses, skip),
        base_fixed_vs_float_pose: pose_difference(&base_fixed.poses, &base_float.poses),
        styles: results,
        blend: metrics(&blend.poses, skip),
        switched: metrics(&switched.poses, skip),
        phase_step_max: (max_phase_step(&switched), max_phase_step(&base_fixed)),
    };
    outputs.add(
        args.out.join("report.json"),
        serde_json::to_vec_pretty(&report)?,
    );
    outputs.commit()?;
    Ok(report)
}

impl DemoReport {
    /// The table `host-sim style-demo` prints.
    pub fn table(&self) -> String {
        let mut s = format!(
            "rank-{} CP adapters beside layer 1, base int8 blob {} bytes; held-out script, 600 frames\n\n",
            self.rank, self.base_blob_bytes
        );
        s += &format!(
            "{:<22} {:>11} {:>11} {:>11} {:>10}\n",
            "rollout (fixed point)", "head height", "hips height", "hand swing", "distance"
        );
        let row = |n: &str, m: &StyleMetrics| {
            format!(
                "{n:<22} {:>11.1} {:>11.1} {:>11.2} {:>10.0}\n",
                m.head_height, m.hips_height, m.hand_swing, m.distance
            )
        };
        s += &row("base", &self.base);
        s += &row("base (float)", &self.base_float);
        for r in &self.styles {
            s += &row(r.name, &r.fixed);
            s += &row(&format!("{} (float)", r.name), &r.float);
        }
        s += &row("50% crouch + 50% swing", &self.blend);
        s += &row("switched every 150 fr", &self.switched);
        s += "\n";
        for r in &self.styles {
            s += &format!(
                "{}: blob {} bytes (float32 parameters {} bytes), +{} MACs/frame; fit loss {}; \
                 target residual {:.2}; fixed vs float: outputs rms {:.4} (base alone {:.4}), rollout joints rms {:.2} max {:.2}; base layer range used {:.0}%\n",
                r.name,
                r.blob.blob_bytes,
                r.blob.float32_bytes,
                r.blob.macs_per_frame,
                r.losses
                    .iter()
                    .map(|(a, b)| format!("{a:.4}->{b:.4}"))
                    .collect::<Vec<_>>()
                    .join(", "),
                r.target_residual,
                r.blob.fixed_vs_float.rms,
                r.blob.base_fixed_vs_float.rms,
                r.fixed_vs_float_pose.0,
                r.fixed_vs_float_pose.1,
                100.0 * r.blob.range_used
            );
        }
        s += &format!(
            "base alone, fixed vs float rollout joints: rms {:.2} max {:.2}\n",
            self.base_fixed_vs_float_pose.0, self.base_fixed_vs_float_pose.1
        );
        s += &format!(
            "largest per-frame phase step: switched run {:.4} rad, base run {:.4} rad\n",
            self.phase_step_max.0, self.phase_step_max.1
        );
        s
    }
}

/// Runs `host-sim style-demo` and prints its table.
pub fn style_demo_cmd(args: &StyleDemoArgs) -> Result<()> {
    let r = style_demo(args)?;
    print!("{}", r.table());
    println!("wrote {}/{{base.blob, crouch.style, swing.style, crouch.npz, swing.npz, styles.svg, styles.png, report.json}}", args.out.display());
    let _ = GatingMode::Cubic;
    Ok(())
}
