//! The `exporter` subcommands of styles: `style` (build a style blob from
//! adapter weights and its base blob) and `style-inspect`.

use anyhow::{Context, Result};
use phasegate::blob::WeightFormat;
use std::path::PathBuf;

use crate::cp::cli::{load_dense, write_both};
use crate::cp::import::read_adapter;
use crate::net::GatingMode;
use crate::quantise::QuantOptions;
use crate::style::{build_style, describe_style};

fn parse_bits(s: &str) -> Result<WeightFormat, String> {
    match s {
        "8" => Ok(WeightFormat::I8),
        "16" => Ok(WeightFormat::I16),
        _ => Err(format!("{s} is not a supported weight width (8 or 16)")),
    }
}

/// `exporter style`: a style blob from adapter weights.
#[derive(Clone, Debug, clap::Args)]
pub struct StyleArgs {
    /// The base model blob the style is for (its payload CRC is recorded).
    #[arg(long)]
    pub base: PathBuf,
    /// The base model's float weights (PFNN directory or .npz), for
    /// calibration and the error report.
    #[arg(long)]
    pub base_weights: PathBuf,
    /// Gating of the base float weights.
    #[arg(long, default_value = "cubic")]
    pub gating: GatingMode,
    /// Adapter weights (.npz or .safetensors): A, B, D (CP), W (full) or
    /// w (diagonal), and bias; see docs/cp-and-styles.md.
    #[arg(long)]
    pub adapter: PathBuf,
    /// Base layer the adapter sits beside (the paper: 1).
    #[arg(long, default_value_t = 1)]
    pub layer: usize,
    /// Style name (UTF-8, at most 64 bytes).
    #[arg(long)]
    pub name: String,
    /// Weight width (8 or 16).
    #[arg(long, default_value = "8", value_parser = parse_bits)]
    pub weight_bits: WeightFormat,
    /// Samples for the error report.
    #[arg(long, default_value_t = 256, value_parser = crate::cli_args::bounds::at_most(crate::cli_args::bounds::SAMPLES))]
    pub samples: usize,
    /// Where to write the style blob.
    #[arg(short = 'o', long = "output")]
    pub output: PathBuf,
    /// Also write a JSON report.
    #[arg(long)]
    pub report: Option<PathBuf>,
}

/// Runs `exporter style`.
pub fn style(args: &StyleArgs) -> Result<()> {
    let base_blob = crate::io::atomic::read_input(&args.base)
        .with_context(|| format!("cannot read {}", args.base.display()))?;
    let base = load_dense(&args.base_weights, args.gating)?;
    let adapter = read_adapter(&args.adapter, args.layer)?;
    let opts = QuantOptions {
        weights: args.weight_bits,
        ..QuantOptions::default()
    };
    let (blob, r) = build_style(&base_blob, &base, &adapter, &args.name, &opts, args.samples)
        .with_context(|| format!("style {:?}", args.name))?;
    write_both(&blob, &r, &args.output, args.report.as_deref())?;
    println!(
        "wrote {} ({} bytes: {} adapter{}, {} weights; float32 parameters {} bytes; +{} MACs/frame)",
        args.output.display(),
        r.blob_bytes,
        r.form,
        r.rank.map_or(String::new(), |k| format!(" rank {k}")),
        r.weight_format,
        r.float32_bytes,
        r.macs_per_frame
    );
    println!(
        "style effect (float styled vs base): relative {:.4}, rms {:.4}, max {:.3}",
        r.style_effect.rel_normalised, r.style_effect.rms, r.style_effect.max_abs
    );
    println!(
        "fixed vs float with the style: rms {:.5}, max {:.4} (base alone: rms {:.5}, max {:.4})",
        r.fixed_vs_float.rms,
        r.fixed_vs_float.max_abs,
        r.base_fixed_vs_float.rms,
        r.base_fixed_vs_float.max_abs
    );
    println!(
        "base layer {} range used with the style: {:.0}%{}",
        r.layer,
        100.0 * r.range_used,
        if r.range_used > 1.0 {
            " -- SATURATES: the base formats cannot hold this style"
        } else {
            ""
        }
    );
    Ok(())
}

/// `exporter style-inspect`: print a style blob's header.
#[derive(Clone, Debug, clap::Args)]
pub struct StyleInspectArgs {
    /// The style blob.
    pub style: PathBuf,
}

/// Runs `exporter style-inspect`; fails (non-zero exit) if the blob is invalid.
pub fn style_inspect(args: &StyleInspectArgs) -> Result<()> {
    let bytes = crate::io::atomic::read_input(&args.style)
        .with_context(|| format!("cannot read {}", args.style.display()))?;
    print!(
        "{}",
        describe_style(&bytes).with_context(|| args.style.display().to_string())?
    );
    Ok(())
}
