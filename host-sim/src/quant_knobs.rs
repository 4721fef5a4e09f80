//! The exporter's int8 quantiser knobs, for the commands that export the
//! blobs they judge (`accuracy`, `fidelity`), so that a choice is judged
//! with the same flags that would export it.

use anyhow::Result;
use exporter::control_points::Residual;
use exporter::export::ExportReport;
use exporter::net::Net;
use exporter::quantise::{QuantOptions, Recorded};
use std::path::PathBuf;

/// `--rounding`, `--compensation-samples`, `--calibration` and the int16
/// layers, as `exporter` takes them (with its defaults: a PFNN's int8 blob
/// is rounded error-aware, an OMG graph's to nearest); applied to the int8
/// blob.
#[derive(Clone, Debug, Default, clap::Args)]
pub struct Int8Knobs {
    /// Rounding of the int8 blob's dense weights (exporter --rounding).
    #[arg(long, value_enum)]
    pub rounding: Option<exporter::cli_args::RoundingArg>,
    /// Calibration inputs of compensated rounding (exporter
    /// --compensation-samples).
    #[arg(long)]
    pub compensation_samples: Option<usize>,
    /// Recorded inputs added to the int8 blob's calibration
    /// (exporter --calibration; `host-sim rollout-dataset` writes them).
    #[arg(long, value_name = "ROLLOUTS.npz")]
    pub calibration: Option<PathBuf>,
    /// Layers of the int8 blob stored with int16 weights instead
    /// (exporter --int16-layers), comma separated.
    #[arg(long, value_delimiter = ',')]
    pub int16_layers: Vec<usize>,
    /// Extra bytes the int8 blob may spend on int16 layers
    /// (exporter --int16-budget).
    #[arg(long, value_name = "BYTES")]
    pub int16_budget: Option<usize>,
}

impl Int8Knobs {
    /// Exports the int8 blob of `net` with these knobs.
    pub fn export(
        &self,
        net: &Net,
        residual: Option<Residual>,
        opts: QuantOptions,
    ) -> Result<(Vec<u8>, ExportReport)> {
        let opts = self.apply(net, opts)?;
        Ok(match self.int16_budget {
            Some(b) => {
                exporter::budget::export_with_int16_budget(net, residual, &opts, b, |_, _| {})?
            }
            None => exporter::export::export(net, residual, &opts)?,
        })
    }

    /// `opts` with these knobs applied.
    pub fn apply(&self, net: &Net, opts: QuantOptions) -> Result<QuantOptions> {
        let calibration_data = self
            .calibration
            .as_deref()
            .map(|p| Recorded::read(p, net.input_dim()))
            .transpose()?;
        Ok(QuantOptions {
            compensation_samples: exporter::cli_args::compensation_samples(
                net,
                self.rounding,
                self.compensation_samples,
            )
            .map_err(anyhow::Error::msg)?,
            calibration_data,
            layer_weights: self
                .int16_layers
                .iter()
                .map(|&l| (l, phasegate::blob::WeightFormat::I16))
                .collect(),
            ..opts
        })
    }
}
