//! `exporter`: trained weights in, checksummed fixed-point blob out.

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use exporter::progress::{during, spinner};
use phasegate::blob::WeightFormat;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use exporter::export::ExportReport;
use exporter::net::{GatingMode, Net};
use exporter::quantise::QuantOptions;

#[derive(Parser)]
#[command(
    name = "exporter",
    version,
    about = "Turns trained phase-gated networks into phasegate model blobs"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

use exporter::cli_args::GatingArg as Gating;
use exporter::cli_args::RoundingArg;

#[derive(clap::Args)]
struct QuantArgs {
    /// Phase gating of the blob.
    #[arg(long, value_enum)]
    gating: Gating,
    #[command(flatten)]
    out: OutputArgs,
}

/// `exporter omg-rig`'s arguments.
#[derive(clap::Args)]
struct OmgRigArgs {
    /// The motion blob the rig is for.
    #[arg(long)]
    base: PathBuf,
    /// The rig's model (model.safetensors); its cost encoder, gate and
    /// experts must be the motion blob's source model's.
    #[arg(long)]
    weights: PathBuf,
    /// The rig's config.json.
    #[arg(long)]
    config: PathBuf,
    /// The rig's name, stored in the blob (default: the weights'
    /// directory name).
    #[arg(long)]
    name: Option<String>,
    /// The rig blob (the weight width of its nodes) and its report (sizes,
    /// nodes, RAM of the combination).
    #[command(flatten)]
    blob: BlobArgs,
    /// The grid of the rig's nodes is the rig blob's, of the others the
    /// motion blob's.
    #[command(flatten)]
    grid: GridArgs,
}

/// The fixed-point grid of an OMG model's blob, for quantisation-aware
/// training (`python3 -m tools.omg.train.qat`, docs/omg.md).
#[derive(clap::Args)]
struct GridArgs {
    /// Also write the model as the blob computes it: model.safetensors
    /// with every dense weight and bias replaced by its integer scaled back.
    #[arg(long)]
    snap_out: Option<PathBuf>,
    /// Also write, as JSON, the grid the blob's weights lie on: per weight
    /// tensor, the integer units per real unit of each input column.
    #[arg(long)]
    grid_out: Option<PathBuf>,
}

/// The blob a command writes, its weight width and its report.
#[derive(clap::Args)]
struct BlobArgs {
    /// Weight width.
    #[arg(long, default_value_t = 8, value_parser = parse_bits)]
    weight_bits: u8,
    /// Where to write the blob.
    #[arg(short = 'o', long = "output")]
    output: PathBuf,
    /// Also write a JSON report (sizes, SQNR per layer, residual, overflow
    /// proof; for a rig blob its nodes and the pair's RAM).
    #[arg(long)]
    report: Option<PathBuf>,
}

#[derive(clap::Args)]
struct OutputArgs {
    #[command(flatten)]
    blob: BlobArgs,
    /// Raw inputs within mean +- this many standard deviations quantise
    /// without clipping (rounded up to a power of two; wider = coarser).
    #[arg(long, default_value_t = 8.0)]
    input_range_sigma: f64,
    /// How int8 dense weights are rounded: for the least output error on
    /// calibration inputs (GPTQ layer after layer with bias correction,
    /// docs/fixed-point.md), or each to nearest. Default: compensated for
    /// `pfnn` and `npz`, nearest for `graph` and `omg`.
    #[arg(long, value_enum)]
    rounding: Option<RoundingArg>,
    /// Calibration inputs of compensated rounding (default 16384, drawn
    /// from the normalisation statistics; --calibration rows come on top,
    /// weighted by --calibration-weight);
    /// on `graph` and `omg`, a count above 0 turns compensated rounding on.
    #[arg(long, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::SAMPLES))]
    compensation_samples: Option<usize>,
    /// Recorded network inputs (an .npz with X (N, inputs) and phase (N,),
    /// as `host-sim rollout-dataset` writes) added to the normal samples
    /// of the range calibration and of the error-aware rounding.
    #[arg(long, value_name = "ROLLOUTS.npz")]
    calibration: Option<PathBuf>,
    /// The share of error-aware rounding's objective that the
    /// --calibration rows carry, whatever their count (default 0.7;
    /// docs/fixed-point.md).
    #[arg(long, value_name = "SHARE")]
    calibration_weight: Option<f64>,
    /// Spend up to this many extra bytes on int16 weights where they remove
    /// the most output error per byte (whole layers, measured; int8 blobs
    /// only; the report's int16_budget says where it went).
    #[arg(long, value_name = "BYTES", value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::BYTES))]
    int16_budget: Option<usize>,
    /// Factor between the largest calibrated value of a row and its
    /// format's range (default 1.5; `exporter omg`: 3, because its
    /// calibration inputs, independent normal features, reach smaller
    /// activations than real motion frames, docs/omg.md).
    #[arg(long)]
    headroom: Option<f64>,
    /// Warn (one line on stderr, and `frame_budget` in the report) when the
    /// estimated instructions per frame of the network on the reference
    /// target (Cortex-M4 under QEMU; the cost model of exporter/src/cost.rs)
    /// exceed N. A warning: the blob is written and the exit status is
    /// unchanged.
    #[arg(long, value_name = "N")]
    budget_instructions: Option<u64>,
    #[command(flatten)]
    self_test: SelfTestArgs,
}

/// `--self-test N` (docs/blob-format.md, "Self-test section").
#[derive(clap::Args)]
struct SelfTestArgs {
    /// Store N input vectors and the integer outputs this runtime computes
    /// for them in the blob (a section at the end of its payload, under the
    /// payload CRC); the firmware runs them at boot and refuses the model
    /// on any mismatch. 0 (the default): no section, the blob as without
    /// the option.
    #[arg(long = "self-test", value_name = "N", default_value_t = 0,
          value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::SELF_TEST))]
    vectors: usize,
}

/// The quantiser's default headroom.
const DEFAULT_HEADROOM: f64 = 1.5;

fn parse_bits(s: &str) -> Result<u8, String> {
    match s {
        "8" => Ok(8),
        "16" => Ok(16),
        _ => Err(format!("{s} is not a supported weight width (8 or 16)")),
    }
}

#[derive(Subcommand)]
enum Command {
    /// Import a PFNN demo weight directory (Xmean.bin, W0_000.bin, ...).
    Pfnn {
        /// The directory.
        #[arg(long)]
        weights: PathBuf,
        #[command(flatten)]
        quant: QuantArgs,
    },
    /// Import a PFNN-shaped model from a NumPy .npz (Xmean, Xstd, Ymean, Ystd, W0..W2 (K,out,in), b0..b2 (K,out)).
    Npz {
        /// The .npz file.
        #[arg(long)]
        weights: PathBuf,
        #[command(flatten)]
        quant: QuantArgs,
    },
    /// Import a graph (OMG-shaped networks and others): a JSON description
    /// of the nodes (docs/graph-format.md) and their weights in an .npz or
    /// .safetensors file.
    Graph {
        /// The JSON description.
        #[arg(long)]
        graph: PathBuf,
        /// The weights (.npz or .safetensors).
        #[arg(long)]
        weights: PathBuf,
        #[command(flatten)]
        out: OutputArgs,
    },
    /// Import a trained OMG model (FE, FS, RBF-CAT or DEC-CAT; tools/omg/train's
    /// model.safetensors + config.json) as a graph (docs/omg.md).
    Omg {
        /// The weights and normalisation (model.safetensors).
        #[arg(long)]
        weights: PathBuf,
        /// The model's config.json (sizes, slices, out_slices, phase update).
        #[arg(long)]
        config: PathBuf,
        #[command(flatten)]
        grid: GridArgs,
        #[command(flatten)]
        out: OutputArgs,
    },
    /// Build a rig blob (docs/omg.md, "Rig blobs"): an OMG model's
    /// autoencoder and output node, quantised against a motion blob (an
    /// `exporter omg` blob, default options) and bound to it by its payload
    /// CRC; the rest of the graph is the motion blob's.
    OmgRig(OmgRigArgs),
    /// Decompose a dense model's layers by CP-ALS and write a CP blob.
    Cp(exporter::cp::cli::CpArgs),
    /// Write a blob from trained CP factors (.npz or .safetensors).
    CpImport(exporter::cp::cli::CpImportArgs),
    /// Size and error of post-hoc CP per rank, every layer decomposed.
    CpReport(exporter::cp::cli::CpReportArgs),
    /// Build a style blob (residual adapter) for a base blob.
    Style(exporter::style::cli::StyleArgs),
    /// Print a style blob's header; exits non-zero if the blob is invalid.
    StyleInspect(exporter::style::cli::StyleInspectArgs),
    /// Print a blob's header (model or style blob), per layer its op
    /// (dense, cp rank R, diagonal) and MACs; exits non-zero if the blob is invalid.
    Inspect {
        /// The blob.
        blob: PathBuf,
    },
}

fn load_pfnn_dir(
    dir: &Path,
    mode: GatingMode,
) -> Result<(Net, Option<exporter::control_points::Residual>)> {
    let bar = exporter::progress::bar(0, &format!("reading {}", dir.display()), "files");
    let tables = exporter::pfnn_dir::load_pfnn_dir_auto(
        dir,
        Some(&mut |done, total| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
        }),
    )?;
    bar.finish_and_clear();
    let msg = match mode {
        GatingMode::Cubic => "recovering control points",
        _ => "selecting tables",
    };
    Ok(during(msg, || Net::from_pfnn_tables(&tables, mode)))
}

/// The quantiser's options that `q` asks for on `net`.
fn quant_options(net: &Net, q: &OutputArgs, default_headroom: f64) -> Result<QuantOptions> {
    let weights = if q.blob.weight_bits == 16 {
        WeightFormat::I16
    } else {
        WeightFormat::I8
    };
    if !(q.input_range_sigma.is_finite() && q.input_range_sigma >= 1.0) {
        bail!(
            "--input-range-sigma {} must be at least 1",
            q.input_range_sigma
        );
    }
    let calibration_data = q
        .calibration
        .as_deref()
        .map(|p| exporter::quantise::Recorded::read(p, net.input_dim()))
        .transpose()?;
    let headroom = q.headroom.unwrap_or(default_headroom);
    if !(headroom.is_finite() && headroom >= 1.0) {
        bail!("--headroom {headroom} must be at least 1");
    }
    let compensation_samples =
        exporter::cli_args::compensation_samples(net, q.rounding, q.compensation_samples)
            .map_err(anyhow::Error::msg)?;
    let calibration_weight = exporter::cli_args::calibration_weight(
        q.calibration_weight,
        q.calibration.is_some(),
        compensation_samples,
    )
    .map_err(anyhow::Error::msg)?;
    let opts = QuantOptions {
        weights,
        headroom,
        input_range_sigma: q.input_range_sigma,
        compensation_samples,
        calibration_data,
        calibration_weight,
        ..QuantOptions::default()
    };
    Ok(opts)
}

/// Every file or none (`exporter::io::atomic::write_together`).
fn write_all(files: &[(PathBuf, Vec<u8>)]) -> Result<()> {
    let refs: Vec<(&Path, &[u8])> = files
        .iter()
        .map(|(p, b)| (p.as_path(), b.as_slice()))
        .collect();
    exporter::io::atomic::write_together(&refs)
}

/// The `--snap-out` and `--grid-out` files of an OMG model quantised with
/// `opts`, made before anything is written.
fn omg_grid_files(
    omg: &exporter::net::omg::OmgNet,
    weights: &Path,
    opts: &QuantOptions,
    grid: &GridArgs,
) -> Result<Vec<(PathBuf, Vec<u8>)>> {
    if grid.snap_out.is_none() && grid.grid_out.is_none() {
        return Ok(Vec::new());
    }
    let quantised = during("quantising for the grid", || {
        exporter::quantise::quantise_net(&omg.net, opts)
    })
    .with_context(|| weights.display().to_string())?;
    let mut files = Vec::new();
    if let Some(path) = grid.snap_out.clone() {
        let bytes = std::fs::read(weights).with_context(|| weights.display().to_string())?;
        let arrays = exporter::cp::import::parse_safetensors(&bytes)
            .with_context(|| weights.display().to_string())?;
        let snapped = exporter::net::omg_snap::snapped(omg, &quantised, &arrays)
            .with_context(|| weights.display().to_string())?;
        files.push((path, exporter::net::omg_snap::to_safetensors(&snapped)?));
    }
    if let Some(path) = grid.grid_out.clone() {
        let scales = exporter::net::omg_snap::grid(omg, &quantised)?;
        let sixteen = opts.weights == WeightFormat::I16;
        let json = serde_json::json!({
            "format": "phasegate-omg-grid-1",
            "weight_bits": if sixteen { 16 } else { 8 },
            "qmax": if sixteen { 32767 } else { 127 },
            "rule": "w_ij -> round(w_ij / u_j * s_i) * u_j / s_i, s_i = qmax / max_j |w_ij / u_j| \
                     over the row (an expert stack's experts share the row)",
            "column_scales": scales,
        });
        files.push((path, serde_json::to_vec_pretty(&json)?));
    }
    Ok(files)
}

/// Quantises and writes `net`, read from `source` (named in errors about
/// the network's values).
fn export(
    net: &Net,
    residual: Option<exporter::control_points::Residual>,
    q: &OutputArgs,
    default_headroom: f64,
    source: &Path,
    side_files: Vec<(PathBuf, Vec<u8>)>,
) -> Result<()> {
    let opts = quant_options(net, q, default_headroom)?;
    let weights = opts.weights;
    let (blob, report) = match q.int16_budget {
        None => {
            let msg = match opts.compensation_samples {
                0 => "calibrating and quantising".to_string(),
                n => format!("calibrating and quantising, error-aware rounding on {n} samples"),
            };
            during(&msg, || exporter::export::export(net, residual, &opts))
                .with_context(|| source.display().to_string())?
        }
        Some(_) if weights == WeightFormat::I16 => {
            bail!("--int16-budget spends bytes on an int8 blob; this one is int16 already")
        }
        Some(budget) => {
            let pb = spinner("int16 budget: exporting and measuring candidates");
            let r = exporter::budget::export_with_int16_budget(
                net,
                residual,
                &opts,
                budget,
                |done, most| {
                    pb.set_message(format!("int16 budget: candidate {done} of at most {most}"));
                },
            )
            .with_context(|| source.display().to_string())?;
            pb.finish_and_clear();
            r
        }
    };
    let mut report = report;
    let blob = exporter::self_test::apply(blob, &mut report, q.self_test.vectors)?;
    if let Some(n) = q.budget_instructions {
        let model = phasegate::Model::from_bytes(&blob)
            .map_err(|e| anyhow::anyhow!("the blob written does not load back: {e}"))?;
        report.frame_budget = Some(exporter::cost::check_budget(&model, n));
    }
    write_outputs(&blob, &report, q, side_files)?;
    if let Some(w) = report
        .frame_budget
        .as_ref()
        .and_then(|c| c.warning.as_ref())
    {
        eprintln!("{}: {w}", q.blob.output.display());
    }
    if std::io::stdout().is_terminal() || std::env::var_os("PHASEGATE_VERBOSE").is_some() {
        summary(&report, &q.blob.output);
    } else {
        let with = report.self_test.as_ref().map_or(String::new(), |t| {
            format!(" (a self-test of {} vectors, {} bytes)", t.vectors, t.bytes)
        });
        println!(
            "{}: {} bytes{with}",
            q.blob.output.display(),
            report.blob_bytes
        );
    }
    Ok(())
}

/// The blob, its report and `side_files`: all of them or none.
fn write_outputs(
    blob: &[u8],
    report: &ExportReport,
    q: &OutputArgs,
    side_files: Vec<(PathBuf, Vec<u8>)>,
) -> Result<()> {
    let mut files = vec![(q.blob.output.clone(), blob.to_vec())];
    if let Some(path) = &q.blob.report {
        files.push((path.clone(), serde_json::to_vec_pretty(report)?));
    }
    files.extend(side_files);
    write_all(&files)
}

fn summary(r: &ExportReport, out: &Path) {
    println!(
        "wrote {} ({} bytes, {} weights, {} gating)",
        out.display(),
        r.blob_bytes,
        r.weight_format,
        r.gating
    );
    if let Some(res) = &r.control_point_residual {
        println!(
            "control-point residual: max {:.3e}, relative {:.3e}",
            res.max_abs, res.rel_frobenius
        );
    }
    println!(
        "RAM {} bytes, {} MACs per frame",
        r.ram_bytes, r.macs_per_frame
    );
    if let Some(t) = &r.self_test {
        println!(
            "self-test: {} vectors and their outputs, {} bytes at the end of the payload",
            t.vectors, t.bytes
        );
    }
    for l in &r.layers {
        let blend = l.max_blend_bits.map_or(String::new(), |b| {
            format!(", worst blended accumulator 2^{b:.1}")
        });
        println!(
            "layer {}: {} {}x{} x{} experts, acc {}, weight SQNR {:.1} dB{blend}",
            l.index, l.form, l.out_dim, l.in_dim, l.experts, l.accumulator, l.weight_sqnr_db
        );
    }
    if let Some(b) = &r.int16_budget {
        println!(
            "int16 budget: {} of {} bytes spent, int16 layers {:?}, output RMS {:.4} -> {:.4} (output stds)",
            b.spent_bytes, b.budget_bytes, b.int16_layers, b.rms_int8, b.rms
        );
        for u in &b.unaffordable {
            println!(
                "  layer {} not tried: its int16 weights add at least {} bytes, {} were left",
                u.layer, u.min_extra_bytes, u.left_bytes
            );
        }
    }
    println!(
        "overflow proof: {}",
        if r.overflow_proof {
            "holds for every i16 input"
        } else {
            "FAILED"
        }
    );
}

fn omg_rig(a: &OmgRigArgs) -> Result<()> {
    let OmgRigArgs {
        base,
        weights,
        config,
        name,
        blob: BlobArgs {
            weight_bits,
            output,
            report,
        },
        grid,
    } = a;
    let (base, weights, config, report) = (
        base.as_path(),
        weights.as_path(),
        config.as_path(),
        report.as_deref(),
    );
    let motion = exporter::atomic::read_input(base)
        .with_context(|| format!("cannot read {}", base.display()))?;
    let omg = exporter::net::omg::read_omg(weights, config)?;
    let name = name.clone().unwrap_or_else(|| {
        weights
            .parent()
            .and_then(Path::file_name)
            .map_or_else(|| "rig".to_string(), |n| n.to_string_lossy().into_owned())
    });
    let opts = QuantOptions {
        weights: if *weight_bits == 16 {
            WeightFormat::I16
        } else {
            WeightFormat::I8
        },
        headroom: exporter::net::omg::HEADROOM,
        ..QuantOptions::default()
    };
    let mask = exporter::rig::rig_mask(&omg.net, &exporter::rig::OMG_RIG_NODES)
        .with_context(|| config.display().to_string())?;
    let against = || format!("{} against {}", weights.display(), base.display());
    let grid_files = match grid.snap_out.is_some() || grid.grid_out.is_some() {
        true => {
            let rig_opts =
                exporter::rig::rig_options(&motion, mask, &opts).with_context(against)?;
            omg_grid_files(&omg, weights, &rig_opts, grid)?
        }
        false => Vec::new(),
    };
    let (blob, rep) =
        exporter::rig::export_rig(&omg.net, &motion, mask, &name, &opts).with_context(against)?;
    let mut files = vec![(output.clone(), blob)];
    if let Some(path) = report {
        files.push((path.to_path_buf(), serde_json::to_vec_pretty(&rep)?));
    }
    files.extend(grid_files);
    write_all(&files)?;
    println!(
        "{}: rig {:?}, {} bytes, for motion blob {} (payload CRC {:#010x}, {} bytes); \
         the pair needs {} bytes of activation RAM, {} MACs per frame",
        output.display(),
        rep.name,
        rep.blob_bytes,
        base.display(),
        rep.base_crc,
        rep.motion_bytes,
        rep.ram_bytes,
        rep.macs_per_frame
    );
    Ok(())
}

fn inspect(path: &Path) -> Result<()> {
    let bytes = exporter::atomic::read_input(path)
        .with_context(|| format!("cannot read {}", path.display()))?;
    match phasegate::Model::from_bytes(&bytes) {
        Ok(model) => {
            print!("{}", exporter::inspect::describe(&model));
            Ok(())
        }
        Err(phasegate::Error::NotAModel) => match phasegate::Style::from_bytes(&bytes) {
            Ok(style) => {
                print!("{}", exporter::inspect::describe_style(&style));
                Ok(())
            }
            Err(phasegate::Error::NotAStyle) => match phasegate::RigInfo::from_bytes(&bytes) {
                Ok(rig) => {
                    let nodes: Vec<u32> = (0..32).filter(|i| (rig.nodes >> i) & 1 != 0).collect();
                    println!(
                        "rig blob {:?}: {} bytes, payload CRC {:#010x}, for the motion blob with \
                         payload CRC {:#010x}; its nodes {nodes:?} (load it beside that blob: \
                         host-sim omg-accuracy --motion --rig)",
                        rig.name, rig.blob_len, rig.payload_crc, rig.base_crc
                    );
                    Ok(())
                }
                Err(e) => bail!("{}: {}", path.display(), exporter::inspect::explain(&e)),
            },
            Err(e) => bail!("{}: {}", path.display(), exporter::inspect::explain(&e)),
        },
        Err(e) => bail!("{}: {}", path.display(), exporter::inspect::explain(&e)),
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Pfnn { weights, quant } => {
            let (net, residual) = load_pfnn_dir(&weights, quant.gating.into())?;
            export(
                &net,
                residual,
                &quant.out,
                DEFAULT_HEADROOM,
                &weights,
                Vec::new(),
            )
        }
        Command::Npz { weights, quant } => {
            let net = exporter::npz::pfnn_from_npz(&weights, quant.gating.into())?;
            export(
                &net,
                None,
                &quant.out,
                DEFAULT_HEADROOM,
                &weights,
                Vec::new(),
            )
        }
        Command::Graph {
            graph,
            weights,
            out,
        } => {
            let net = exporter::net::json::read_graph(&graph, &weights)?;
            export(&net, None, &out, DEFAULT_HEADROOM, &weights, Vec::new())
        }
        Command::Omg {
            weights,
            config,
            grid,
            out,
        } => {
            let omg = exporter::net::omg::read_omg(&weights, &config)?;
            let grid_files = if grid.snap_out.is_some() || grid.grid_out.is_some() {
                if out.int16_budget.is_some() {
                    bail!(
                        "--snap-out and --grid-out describe one weight width; \
                         leave out --int16-budget"
                    );
                }
                let opts = quant_options(&omg.net, &out, exporter::net::omg::HEADROOM)?;
                omg_grid_files(&omg, &weights, &opts, &grid)?
            } else {
                Vec::new()
            };
            export(
                &omg.net,
                None,
                &out,
                exporter::net::omg::HEADROOM,
                &weights,
                grid_files,
            )
        }
        Command::OmgRig(a) => omg_rig(&a),
        Command::Cp(a) => exporter::cp::cli::cp(&a),
        Command::CpImport(a) => exporter::cp::cli::cp_import(&a),
        Command::CpReport(a) => exporter::cp::cli::cp_report(&a),
        Command::Style(a) => exporter::style::cli::style(&a),
        Command::StyleInspect(a) => exporter::style::cli::style_inspect(&a),
        Command::Inspect { blob } => inspect(&blob),
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
