//! The exporter's int8 quantiser knobs, for the commands that export the
//! blobs they judge (`accuracy`, `fidelity`), so that a choice is judged
//! with the same flags that would export it.

use anyhow::Result;
use exporter::control_points::Residual;
use exporter::export::ExportReport;
use exporter::net::Net;
use exporter::quantise::{QuantOptions, Recorded};
use std::path::PathBuf;

/// `--compensation-samples` and `--calibration`, as `exporter` takes them;
/// applied to the int8 blob.
#[derive(Clone, Debug, Default, clap::Args)]
pub struct Int8Knobs {
    /// Error-aware rounding of the int8 blob from this many normal samples
    /// (exporter --compensation-samples); 0 rounds to nearest.
    #[arg(long, default_value_t = 0)]
    pub compensation_samples: usize,
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
            compensation_samples: self.compensation_samples,
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
