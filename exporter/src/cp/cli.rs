//! The `exporter` subcommands of CP models: `cp` (decompose a dense model),
//! `cp-import` (trained CP factors) and `cp-report` (size and error per rank).

use anyhow::{bail, Context, Result};
use phasegate::blob::WeightFormat;
use serde::Serialize;
use std::path::{Path, PathBuf};

use crate::cp::als::{AlsOptions, AlsResult};
use crate::cp::distill::{
    distill, DistillData, DistillOptions, DistillReport, DEFAULT_NORMAL_FRACTION,
};
use crate::cp::import::{cp_net_bytes, read_cp_net};
use crate::cp::report::{
    measure_ranks, output_error, run_blob, run_float, tables_error, OutputError,
};
use crate::export::{export, ExportReport};
use crate::io::samples::{normal_inputs, Samples};
use crate::net::{CpLayer, Net, NetLayer};
use crate::net::{ExpertLayer, GatingMode};
use crate::quantise::QuantOptions;

fn parse_bits(s: &str) -> Result<WeightFormat, String> {
    match s {
        "8" => Ok(WeightFormat::I8),
        "16" => Ok(WeightFormat::I16),
        _ => Err(format!("{s} is not a supported weight width (8 or 16)")),
    }
}

/// Loads a dense float PFNN from a demo weight directory or a PFNN-shaped `.npz`.
pub fn load_dense(path: &Path, mode: GatingMode) -> Result<Net> {
    if path.is_dir() {
        let tables = crate::pfnn_dir::load_pfnn_dir_auto(path, None)?;
        Ok(Net::from_pfnn_tables(&tables, mode).0)
    } else {
        crate::npz::pfnn_from_npz(path, mode)
    }
}

/// `exporter cp`: decompose a dense model's layers and write a CP blob.
#[derive(Clone, Debug, clap::Args)]
pub struct CpArgs {
    /// Dense source: a PFNN weight directory or a PFNN-shaped .npz.
    #[arg(long)]
    pub weights: PathBuf,
    /// Gating (what the experts are): cubic = 4 control points.
    #[arg(long, default_value = "cubic")]
    pub gating: GatingMode,
    /// Weight width of the blob (8 or 16).
    #[arg(long, default_value = "8", value_parser = parse_bits)]
    pub weight_bits: WeightFormat,
    /// Rank of every decomposed layer.
    #[arg(
        long,
        required_unless_present = "cp_max_error",
        conflicts_with = "cp_max_error",
        value_parser = crate::cli_args::bounds::at_most(crate::cli_args::bounds::RANK)
    )]
    pub cp_rank: Option<usize>,
    /// Instead of a rank: per layer, the smallest rank whose relative
    /// Frobenius error is at most this (e.g. 0.3).
    #[arg(long)]
    pub cp_max_error: Option<f64>,
    /// Largest rank `--cp-max-error` may choose.
    #[arg(long, default_value_t = 1024, value_parser = crate::cli_args::bounds::at_most(crate::cli_args::bounds::RANK))]
    pub cp_max_rank: usize,
    /// Layers to decompose (comma separated); the others stay dense.
    #[arg(long, value_delimiter = ',')]
    pub cp_layers: Option<Vec<usize>>,
    /// Fine-tune the factors for this many Adam steps to match the dense
    /// model's outputs on inputs drawn from its normalisation statistics
    /// (and from --distill-data).
    #[arg(long, default_value_t = 0, value_parser = crate::cli_args::bounds::at_most(crate::cli_args::bounds::STEPS))]
    pub distill: usize,
    /// Size of the distillation training set.
    #[arg(long, default_value_t = 4096, value_parser = crate::cli_args::bounds::at_most(crate::cli_args::bounds::SAMPLES))]
    pub distill_samples: usize,
    /// Adam learning rate of distillation (cosine-decayed to a tenth).
    #[arg(long, default_value_t = 3e-4)]
    pub distill_lr: f64,
    /// Rollout inputs to distil on (.npz with X (N, inputs) in model units
    /// and phase (N,) in radians, as `host-sim rollout-dataset` writes);
    /// repeat for several files. One block of rows in 8 is held out.
    #[arg(long)]
    pub distill_data: Vec<PathBuf>,
    /// With --distill-data: the share of the training set drawn from the
    /// normalisation statistics instead (0 = rollout rows only, 1 = normal
    /// samples only, the rollout rows then only evaluated).
    #[arg(long, default_value_t = DEFAULT_NORMAL_FRACTION)]
    pub distill_normal_fraction: f64,
    /// Rollout data sets (same layout) to evaluate on only: the report
    /// gives every error on each of them too.
    #[arg(long)]
    pub eval_data: Vec<PathBuf>,
    /// Most CP-ALS sweeps per decomposition.
    #[arg(long, default_value_t = 200, value_parser = crate::cli_args::bounds::at_most(crate::cli_args::bounds::STEPS))]
    pub als_iters: usize,
    /// Ridge of CP-ALS (relative): keeps components from degenerating into
    /// large cancelling pairs, which fixed point cannot represent well.
    /// 0 is plain least squares.
    #[arg(long, default_value_t = 1e-2)]
    pub cp_ridge: f64,
    /// Samples for the output-error measurement.
    #[arg(long, default_value_t = 256, value_parser = crate::cli_args::bounds::at_most(crate::cli_args::bounds::SAMPLES))]
    pub samples: usize,
    /// How int8 weights are rounded (as `exporter pfnn --rounding`; both
    /// CP factors, and dense layers kept): default compensated.
    #[arg(long, value_enum)]
    pub rounding: Option<crate::cli_args::RoundingArg>,
    /// Calibration inputs of compensated rounding (default 16384).
    #[arg(long, value_parser = crate::cli_args::bounds::at_most(crate::cli_args::bounds::SAMPLES))]
    pub compensation_samples: Option<usize>,
    /// Where to write the blob.
    #[arg(short = 'o', long = "output")]
    pub output: PathBuf,
    /// Also write a JSON report.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Also write the float CP network (.npz, the `cp-import` layout).
    #[arg(long)]
    pub factors_out: Option<PathBuf>,
    /// Store N input vectors and the integer outputs this runtime computes
    /// for them in the blob (as `exporter pfnn --self-test`; 0: none).
    #[arg(long = "self-test", value_name = "N", default_value_t = 0,
          value_parser = crate::cli_args::bounds::at_most(crate::cli_args::bounds::SELF_TEST))]
    pub self_test: usize,
}

/// Per decomposed layer, in the `cp` report.
#[derive(Clone, Debug, Serialize)]
pub struct CpLayerSummary {
    /// Layer index.
    pub index: usize,
    /// Chosen rank.
    pub rank: usize,
    /// ALS sweeps.
    pub sweeps: usize,
    /// Relative Frobenius error of the expert tensor.
    pub rel_frobenius: f64,
    /// Relative Frobenius error over the 50 phase tables (cubic).
    pub rel_frobenius_tables: Option<f64>,
    /// Bytes of the layer in the blob (dense: what it would have taken).
    pub bytes: usize,
    /// Bytes of the dense layer at the same weight width.
    pub dense_bytes: usize,
}

/// Output errors on one set of rollout inputs, in the `cp` report.
#[derive(Clone, Debug, Serialize)]
pub struct RolloutSetError {
    /// "rollout rows held out" or the evaluation file.
    pub name: String,
    /// Rows.
    pub rows: usize,
    /// Float CP network vs dense float network, before distillation.
    pub float_vs_dense_before_distill: Option<OutputError>,
    /// Float CP network vs dense float network.
    pub float_vs_dense: OutputError,
    /// The blob vs the float CP network.
    pub fixed_vs_float: OutputError,
    /// The blob vs the dense float network.
    pub fixed_vs_dense: OutputError,
}

/// The `cp` report.
#[derive(Clone, Debug, Serialize)]
pub struct CpExportReport {
    /// Decomposed layers.
    pub decomposed: Vec<CpLayerSummary>,
    /// Float CP network vs dense float network, before distillation.
    pub float_vs_dense_before_distill: Option<OutputError>,
    /// Float CP network vs dense float network.
    pub float_vs_dense: OutputError,
    /// The blob vs the float CP network.
    pub fixed_vs_float: OutputError,
    /// The blob vs the dense float network.
    pub fixed_vs_dense: OutputError,
    /// Distillation, if run.
    pub distill: Option<DistillReport>,
    /// The same errors on the held-out rollout rows of --distill-data and
    /// on every --eval-data set (the figures above are on normal samples).
    pub rollout_sets: Vec<RolloutSetError>,
    /// The blob.
    pub blob: ExportReport,
}

/// Decomposes `layer` at the smallest rank in `1..=max_rank` whose
/// relative Frobenius error is at most `max_err` (bisection; the error is
/// taken as non-increasing in the rank). Fails if `max_rank` is not enough.
pub fn decompose_to_error(
    layer: &ExpertLayer,
    max_err: f64,
    max_rank: usize,
    als: &AlsOptions,
) -> Result<(CpLayer, AlsResult)> {
    let (out, inp) = layer.w[0].dim();
    let cap = max_rank.min(out.min(inp) * layer.experts()).max(1);
    let top = CpLayer::decompose(layer, cap, als);
    if top.1.rel_error > max_err {
        bail!(
            "relative error {max_err} needs a rank above {cap} (rank {cap} gives {:.4}); \
             raise --cp-max-rank or the error",
            top.1.rel_error
        );
    }
    let (mut lo, mut hi, mut best) = (0usize, cap, top);
    while hi - lo > 1 {
        let mid = (lo + hi) / 2;
        let cand = CpLayer::decompose(layer, mid, als);
        if cand.1.rel_error <= max_err {
            hi = mid;
            best = cand;
        } else {
            lo = mid;
        }
    }
    Ok(best)
}

fn layer_bytes(l: &NetLayer, wb: usize) -> usize {
    let (k, out) = (l.experts(), l.out_dim());
    // weights, plus 4-byte biases and 8-byte requantisation records;
    // CP layers add int16 cores and 8-byte middle records.
    let extra = match l {
        NetLayer::Cp(c) => c.rank() * (k * 2 + 8) - c.rank() * k * wb,
        _ => 0,
    };
    l.weight_count() * wb + extra + k * out * 4 + out * 8
}

/// Runs `exporter cp`.
pub fn cp(args: &CpArgs) -> Result<()> {
    let dense = load_dense(&args.weights, args.gating)?;
    let als = AlsOptions {
        max_iters: args.als_iters,
        ridge: args.cp_ridge,
        ..AlsOptions::default()
    };
    let wb = args.weight_bits.bytes();
    let chosen: Vec<usize> = args
        .cp_layers
        .clone()
        .unwrap_or_else(|| (0..dense.layers.len()).collect());
    if let Some(&bad) = chosen.iter().find(|&&l| l >= dense.layers.len()) {
        bail!("--cp-layers: the model has no layer {bad}");
    }
    if let Some(e) = args.cp_max_error {
        if !(e.is_finite() && e >= 0.0) {
            bail!("--cp-max-error must be a finite non-negative number");
        }
    }
    if !args.distill_data.is_empty() && args.distill == 0 {
        bail!("--distill-data needs --distill STEPS (use --eval-data to evaluate only)");
    }
    if !(args.distill_lr.is_finite() && args.distill_lr > 0.0) {
        bail!("--distill-lr must be a positive number");
    }
    let f = args.distill_normal_fraction;
    if !(0.0..=1.0).contains(&f) {
        bail!("--distill-normal-fraction must be between 0 and 1, not {f}");
    }
    // Read the data sets before the (long) decomposition, so a bad file
    // fails at once.
    let data = DistillData::load(&args.distill_data, &args.eval_data, dense.input_dim())?;
    let mut net = dense.clone();
    let mut decomposed = Vec::new();
    let bar = crate::progress::bar(chosen.len() as u64, "CP decomposition (ALS)", "layers");
    for &l in &chosen {
        let layer = dense.layers[l]
            .as_dense()
            .with_context(|| format!("layer {l} of {} is not dense", args.weights.display()))?;
        let (cp, res) = match (args.cp_rank, args.cp_max_error) {
            (Some(r), _) if r > 0 => CpLayer::decompose(layer, r, &als),
            (Some(_), _) => bail!("--cp-rank must be at least 1"),
            (None, Some(e)) => decompose_to_error(layer, e, args.cp_max_rank, &als)
                .with_context(|| format!("layer {l}"))?,
            (None, None) => bail!("give --cp-rank or --cp-max-error"),
        };
        let tables = (dense.mode == GatingMode::Cubic && layer.experts() == 4)
            .then(|| tables_error(layer, &cp, 50));
        let dense_bytes = layer_bytes(&NetLayer::Dense(layer.clone()), wb);
        let op = NetLayer::Cp(cp);
        decomposed.push(CpLayerSummary {
            index: l,
            rank: res.factors.rank(),
            sweeps: res.iterations,
            rel_frobenius: res.rel_error,
            rel_frobenius_tables: tables,
            bytes: layer_bytes(&op, wb),
            dense_bytes,
        });
        net.layers[l] = op;
        bar.inc(1);
    }
    bar.finish_and_clear();
    let s = normal_inputs(
        &dense.xmean.to_vec(),
        &dense.xstd.to_vec(),
        args.samples,
        1.0,
        0xE7A1,
    );
    let dense_net = dense.clone();
    let y_dense = run_float(&dense_net, &s.inputs, &s.phases);
    let (ym, ys) = (dense.ymean.to_vec(), dense.ystd.to_vec());
    let mut sets: Vec<(String, &Samples)> = Vec::new();
    if !data.held_out.inputs.is_empty() {
        sets.push(("rollout rows held out".into(), &data.held_out));
    }
    sets.extend(data.eval.iter().map(|(n, e)| (n.clone(), e)));
    let sets_dense: Vec<Vec<Vec<f64>>> = sets
        .iter()
        .map(|(_, e)| run_float(&dense_net, &e.inputs, &e.phases))
        .collect();
    let mut before = None;
    let mut sets_before = vec![None; sets.len()];
    let mut distill_report = None;
    if args.distill > 0 {
        before = Some(output_error(
            &run_float(&net, &s.inputs, &s.phases),
            &y_dense,
            &ym,
            &ys,
        ));
        for ((_, e), (b, yd)) in sets.iter().zip(sets_before.iter_mut().zip(&sets_dense)) {
            *b = Some(output_error(
                &run_float(&net, &e.inputs, &e.phases),
                yd,
                &ym,
                &ys,
            ));
        }
        let (tuned, rep) =
            crate::progress::during(&format!("distilling, {} steps", args.distill), || {
                distill(
                    &dense,
                    &net,
                    &data,
                    &DistillOptions {
                        steps: args.distill,
                        samples: args.distill_samples.max(1),
                        normal_fraction: f,
                        lr: args.distill_lr,
                        ..DistillOptions::default()
                    },
                )
            });
        net = tuned;
        distill_report = Some(rep);
    }
    let y_cp = run_float(&net, &s.inputs, &s.phases);
    let opts = QuantOptions {
        weights: args.weight_bits,
        compensation_samples: crate::cli_args::compensation_samples(
            &net,
            args.rounding,
            args.compensation_samples,
        )
        .map_err(anyhow::Error::msg)?,
        ..QuantOptions::default()
    };
    let (blob, mut blob_report) =
        crate::progress::during("quantising", || export(&net, None, &opts))?;
    let blob = crate::self_test::apply(blob, &mut blob_report, args.self_test)?;
    let y_fixed = run_blob(&blob, &s.inputs, &s.phases)?;
    let mut rollout_sets = Vec::new();
    for (((name, e), yd), b) in sets.iter().zip(&sets_dense).zip(sets_before) {
        let (yc, yf) = (
            run_float(&net, &e.inputs, &e.phases),
            run_blob(&blob, &e.inputs, &e.phases)?,
        );
        rollout_sets.push(RolloutSetError {
            name: name.clone(),
            rows: e.inputs.len(),
            float_vs_dense_before_distill: b,
            float_vs_dense: output_error(&yc, yd, &ym, &ys),
            fixed_vs_float: output_error(&yf, &yc, &ym, &ys),
            fixed_vs_dense: output_error(&yf, yd, &ym, &ys),
        });
    }
    let report = CpExportReport {
        decomposed,
        float_vs_dense_before_distill: before,
        float_vs_dense: output_error(&y_cp, &y_dense, &ym, &ys),
        fixed_vs_float: output_error(&y_fixed, &y_cp, &ym, &ys),
        fixed_vs_dense: output_error(&y_fixed, &y_dense, &ym, &ys),
        distill: distill_report,
        rollout_sets,
        blob: blob_report,
    };
    // The blob, its report and the factors: all of them or none.
    let factors = args
        .factors_out
        .as_ref()
        .map(|p| Ok::<_, anyhow::Error>((p.as_path(), cp_net_bytes(&net)?)))
        .transpose()?;
    let text = args
        .report
        .as_ref()
        .map(|_| serde_json::to_vec_pretty(&report))
        .transpose()?;
    let mut files: Vec<(&Path, &[u8])> = vec![(args.output.as_path(), blob.as_slice())];
    if let (Some(path), Some(text)) = (&args.report, &text) {
        files.push((path.as_path(), text));
    }
    if let Some((path, bytes)) = &factors {
        files.push((path, bytes));
    }
    crate::io::atomic::write_together(&files)?;
    print_cp_summary(&report, &args.output);
    Ok(())
}

/// The blob and its report, both or neither.
pub fn write_both<T: Serialize>(
    blob: &[u8],
    report: &T,
    output: &Path,
    json: Option<&Path>,
) -> Result<()> {
    let text = json
        .map(|_| serde_json::to_vec_pretty(report))
        .transpose()?;
    let mut files: Vec<(&Path, &[u8])> = vec![(output, blob)];
    if let (Some(path), Some(text)) = (json, &text) {
        files.push((path, text));
    }
    crate::io::atomic::write_together(&files)
}

fn print_cp_summary(r: &CpExportReport, out: &Path) {
    println!(
        "wrote {} ({} bytes, {} weights, {} MACs/frame)",
        out.display(),
        r.blob.blob_bytes,
        r.blob.weight_format,
        r.blob.macs_per_frame
    );
    println!(
        "{:>5} {:>6} {:>10} {:>10} {:>10} {:>10}",
        "layer", "rank", "bytes", "dense", "rel err", "tables"
    );
    for l in &r.decomposed {
        println!(
            "{:>5} {:>6} {:>10} {:>10} {:>10.4} {:>10}",
            l.index,
            l.rank,
            l.bytes,
            l.dense_bytes,
            l.rel_frobenius,
            l.rel_frobenius_tables
                .map_or("-".to_string(), |t| format!("{t:.4}"))
        );
    }
    if let Some(b) = &r.float_vs_dense_before_distill {
        println!(
            "before distillation: relative output error {:.4}, rms {:.4}, max {:.3} (output units)",
            b.rel_normalised, b.rms, b.max_abs
        );
    }
    let f = &r.float_vs_dense;
    println!(
        "float CP vs dense: relative output error {:.4}, rms {:.4}, max {:.3} (output units)",
        f.rel_normalised, f.rms, f.max_abs
    );
    let x = &r.fixed_vs_float;
    println!(
        "blob vs float CP: relative {:.5}, rms {:.5}, max {:.4}",
        x.rel_normalised, x.rms, x.max_abs
    );
    if let Some(d) = &r.distill {
        println!(
            "distillation: {} steps on {} inputs ({} normal samples, {} rollout rows drawn from {})",
            d.options.steps,
            d.normal_samples + d.rollout_samples,
            d.normal_samples,
            d.rollout_samples,
            d.rollout_rows
        );
        println!(
            "{:<52} {:>10} {:>10}",
            "held-out loss (mean squared normalised output error)", "before", "after"
        );
        let row = |name: &str, rows: usize, b: f64, a: f64| {
            println!("  {:<50} {b:>10.5} {a:>10.5}", format!("{name} ({rows})"));
        };
        row("normal samples", 512, d.held_out_before, d.held_out_after);
        for h in d.rollout_held_out.iter().chain(&d.eval) {
            row(&h.name, h.rows, h.before, h.after);
        }
    }
    if !r.rollout_sets.is_empty() {
        println!(
            "on rollout inputs: float CP vs dense (relative before, after; rms after) \
             and blob vs float CP (rms, max), output units"
        );
        println!(
            "  {:<40} {:>10} {:>10} {:>10} {:>10} {:>10}",
            "", "rel before", "rel after", "rms", "blob rms", "blob max"
        );
        for e in &r.rollout_sets {
            println!(
                "  {:<40} {:>10} {:>10.4} {:>10.4} {:>10.5} {:>10.4}",
                format!("{} ({})", e.name, e.rows),
                e.float_vs_dense_before_distill
                    .map_or("-".to_string(), |b| format!("{:.4}", b.rel_normalised)),
                e.float_vs_dense.rel_normalised,
                e.float_vs_dense.rms,
                e.fixed_vs_float.rms,
                e.fixed_vs_float.max_abs
            );
        }
    }
    println!(
        "overflow proof: {}",
        if r.blob.overflow_proof {
            "holds for every i16 input (re-checked at load)"
        } else {
            "FAILED"
        }
    );
}

/// `exporter cp-import`: a blob from trained CP factors (.npz or .safetensors).
#[derive(Clone, Debug, clap::Args)]
pub struct CpImportArgs {
    /// The factors (layout in docs/cp-and-styles.md: Xmean, Xstd, Ymean,
    /// Ystd, A{l} (out,R), B{l} (in,R), D{l} (K,R), b{l} (K,out), or W{l}
    /// (K,out,in) for a dense layer).
    #[arg(long)]
    pub factors: PathBuf,
    /// Gating (what the K experts are).
    #[arg(long, default_value = "cubic")]
    pub gating: GatingMode,
    /// Weight width (8 or 16).
    #[arg(long, default_value = "8", value_parser = parse_bits)]
    pub weight_bits: WeightFormat,
    /// Where to write the blob.
    #[arg(short = 'o', long = "output")]
    pub output: PathBuf,
    /// Also write a JSON report.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Store N input vectors and the integer outputs this runtime computes
    /// for them in the blob (as `exporter pfnn --self-test`; 0: none).
    #[arg(long = "self-test", value_name = "N", default_value_t = 0,
          value_parser = crate::cli_args::bounds::at_most(crate::cli_args::bounds::SELF_TEST))]
    pub self_test: usize,
}

/// Runs `exporter cp-import`.
pub fn cp_import(args: &CpImportArgs) -> Result<()> {
    let net = read_cp_net(&args.factors, args.gating)?;
    let opts = QuantOptions {
        weights: args.weight_bits,
        ..QuantOptions::default()
    };
    let (blob, mut report) = export(&net, None, &opts)?;
    let blob = crate::self_test::apply(blob, &mut report, args.self_test)?;
    write_both(&blob, &report, &args.output, args.report.as_deref())?;
    println!(
        "wrote {} ({} bytes, {} MACs/frame; layers: {})",
        args.output.display(),
        report.blob_bytes,
        report.macs_per_frame,
        net.layers
            .iter()
            .map(|l| match l.rank() {
                Some(r) => format!("cp rank {r}"),
                None => l.form().to_string(),
            })
            .collect::<Vec<_>>()
            .join(", ")
    );
    Ok(())
}

/// `exporter cp-report`: size and error per rank, every layer decomposed.
#[derive(Clone, Debug, clap::Args)]
pub struct CpReportArgs {
    /// Dense source: a PFNN weight directory or a PFNN-shaped .npz.
    #[arg(long)]
    pub weights: PathBuf,
    /// Gating.
    #[arg(long, default_value = "cubic")]
    pub gating: GatingMode,
    /// Ranks to measure.
    #[arg(long, value_delimiter = ',', default_value = "16,32,64,128,256,512", value_parser = crate::cli_args::bounds::at_most(crate::cli_args::bounds::RANK))]
    pub ranks: Vec<usize>,
    /// Weight widths of the blobs measured (8, 16 or both).
    #[arg(long, value_delimiter = ',', default_value = "8,16", value_parser = parse_bits)]
    pub weight_bits: Vec<WeightFormat>,
    /// Samples per measurement.
    #[arg(long, default_value_t = 256, value_parser = crate::cli_args::bounds::at_most(crate::cli_args::bounds::SAMPLES))]
    pub samples: usize,
    /// Seed of the sampler.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// Most CP-ALS sweeps per decomposition.
    #[arg(long, default_value_t = 200, value_parser = crate::cli_args::bounds::at_most(crate::cli_args::bounds::STEPS))]
    pub als_iters: usize,
    /// Ridge of CP-ALS (relative; see `exporter cp --help`).
    #[arg(long, default_value_t = 1e-2)]
    pub cp_ridge: f64,
    /// Also write the report as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// How the blobs' int8 weights are rounded (dense and CP alike; as
    /// `exporter pfnn --rounding`): default nearest here, where many
    /// blobs are exported.
    #[arg(long, value_enum, default_value = "nearest")]
    pub rounding: crate::cli_args::RoundingArg,
}

/// Runs `exporter cp-report`.
pub fn cp_report(args: &CpReportArgs) -> Result<()> {
    let dense = load_dense(&args.weights, args.gating)?;
    let als = AlsOptions {
        max_iters: args.als_iters,
        ridge: args.cp_ridge,
        ..AlsOptions::default()
    };
    let report = measure_ranks(
        &dense,
        &args.ranks,
        args.samples,
        args.seed,
        &args.weight_bits,
        match args.rounding {
            crate::cli_args::RoundingArg::Nearest => 0,
            crate::cli_args::RoundingArg::Compensated => {
                crate::quantise::DEFAULT_COMPENSATION_SAMPLES
            }
        },
        &als,
        |m| eprintln!("{m}"),
    )?;
    if let Some(p) = &args.json {
        crate::io::atomic::write_atomic(p, &serde_json::to_vec_pretty(&report)?)?;
    }
    print!("{}", report.table());
    Ok(())
}
