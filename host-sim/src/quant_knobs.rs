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
#[derive(Clone, Debug, clap::Args)]
pub struct Int8Knobs {
    /// Rounding of the int8 blob's dense weights (exporter --rounding).
    #[arg(long, value_enum)]
    pub rounding: Option<exporter::cli_args::RoundingArg>,
    /// Calibration inputs of compensated rounding (exporter
    /// --compensation-samples).
    #[arg(long, value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::SAMPLES))]
    pub compensation_samples: Option<usize>,
    /// Recorded inputs added to the int8 blob's calibration
    /// (exporter --calibration; `host-sim rollout-dataset` writes them).
    #[arg(
        long,
        value_name = "ROLLOUTS.npz",
        conflicts_with = "calibration_tours"
    )]
    pub calibration: Option<PathBuf>,
    /// Instead of a file: the float controller's rollouts of this many
    /// random command scripts (600 frames each), recorded in memory; the
    /// same rows as `host-sim rollout-dataset --tours N --tour-seed S`
    /// writes, so the blob is the one `exporter --calibration` makes of
    /// that file (PFNN-shaped models; docs/fixed-point.md).
    #[arg(long, value_name = "N", value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::RUNS))]
    pub calibration_tours: Option<usize>,
    /// Seed of --calibration-tours.
    #[arg(long, default_value_t = 1, requires = "calibration_tours")]
    pub tour_seed: u64,
    /// OMG models (`omg-reach`): instead of a file, the float model's
    /// grounded rollouts of the first N training clips of its rig (from
    /// `--data`; the held-out clips it is judged on are never used).
    #[arg(
        long,
        value_name = "N",
        conflicts_with_all = ["calibration", "calibration_tours"]
    )]
    pub calibration_clips: Option<usize>,
    /// The share of error-aware rounding's objective that the
    /// --calibration rows carry (exporter --calibration-weight).
    #[arg(long, value_name = "SHARE")]
    pub calibration_weight: Option<f64>,
    /// Layers of the int8 blob stored with int16 weights instead
    /// (exporter --int16-layers), comma separated.
    #[arg(long, value_delimiter = ',')]
    pub int16_layers: Vec<usize>,
    /// Extra bytes the int8 blob may spend on int16 layers
    /// (exporter --int16-budget).
    #[arg(long, value_name = "BYTES", value_parser = exporter::cli_args::bounds::at_most(exporter::cli_args::bounds::BYTES))]
    pub int16_budget: Option<usize>,
}

/// Frames of each calibration tour (`rollout-dataset`'s default length).
pub const TOUR_FRAMES: usize = 600;

/// The float controller's inputs over `n` tours of `seed`, stored the way
/// `host-sim rollout-dataset` stores them (float32), so that a blob
/// calibrated in memory is the blob calibrated on that file.
pub fn tour_rollouts(net: &Net, n: usize, seed: u64) -> Result<Recorded> {
    if n == 0 {
        anyhow::bail!("--calibration-tours must be at least 1");
    }
    let rows = n.saturating_mul(TOUR_FRAMES);
    if rows > exporter::cli_args::bounds::ROWS {
        anyhow::bail!(
            "--calibration-tours {n}: {n} tours of {TOUR_FRAMES} frames make {rows} rows, more \
             than the largest data set accepted, {} rows",
            exporter::cli_args::bounds::ROWS
        );
    }
    let seconds = TOUR_FRAMES as f64 / crate::rollout::script::FRAME_RATE;
    let scripts: Vec<_> = (0..n)
        .map(|i| crate::rollout::tour::tour(seed, i, seconds))
        .collect();
    let d = crate::rollout::dataset::collect(net, &scripts, TOUR_FRAMES)?;
    let f32_round = |v: &f64| f64::from(*v as f32);
    Ok(Recorded {
        source: format!("{n} tours of seed {seed}, {TOUR_FRAMES} frames each"),
        samples: std::sync::Arc::new(exporter::calibrate::Samples {
            inputs: d
                .inputs
                .iter()
                .map(|x| x.iter().map(f32_round).collect())
                .collect(),
            phases: d.phases.iter().map(f32_round).collect(),
        }),
    })
}

/// The command line's defaults: the exporter's own, no recorded rows.
impl Default for Int8Knobs {
    fn default() -> Self {
        Self {
            rounding: None,
            compensation_samples: None,
            calibration: None,
            calibration_tours: None,
            tour_seed: 1,
            calibration_clips: None,
            calibration_weight: None,
            int16_layers: Vec::new(),
            int16_budget: None,
        }
    }
}

impl Int8Knobs {
    /// Whether any knob differs from the exporter's defaults.
    pub fn is_set(&self) -> bool {
        self.rounding.is_some()
            || self.compensation_samples.is_some()
            || self.calibration.is_some()
            || self.calibration_tours.is_some()
            || self.calibration_clips.is_some()
            || self.calibration_weight.is_some()
            || !self.int16_layers.is_empty()
            || self.int16_budget.is_some()
    }

    /// Exports the int8 blob of `net` with these knobs.
    pub fn export(
        &self,
        net: &Net,
        residual: Option<Residual>,
        opts: QuantOptions,
    ) -> Result<(Vec<u8>, ExportReport)> {
        self.export_with(net, residual, opts, None)
    }

    /// [`Int8Knobs::export`] with `recorded` rows ([`Int8Knobs::apply_with`]).
    pub fn export_with(
        &self,
        net: &Net,
        residual: Option<Residual>,
        opts: QuantOptions,
        recorded: Option<Recorded>,
    ) -> Result<(Vec<u8>, ExportReport)> {
        let opts = self.apply_with(net, opts, recorded)?;
        let msg = match opts.compensation_samples {
            0 => "exporting the int8 blob".to_string(),
            n => format!("exporting the int8 blob (error-aware rounding, {n} samples)"),
        };
        exporter::progress::during(&msg, || {
            Ok(match self.int16_budget {
                Some(b) => {
                    exporter::budget::export_with_int16_budget(net, residual, &opts, b, |_, _| {})?
                }
                None => exporter::export::export(net, residual, &opts)?,
            })
        })
    }

    /// `opts` with these knobs applied.
    pub fn apply(&self, net: &Net, opts: QuantOptions) -> Result<QuantOptions> {
        self.apply_with(net, opts, None)
    }

    /// [`Int8Knobs::apply`], with `recorded` rows made by the caller (as
    /// `--calibration-clips` asks) in place of a file or tours.
    pub fn apply_with(
        &self,
        net: &Net,
        opts: QuantOptions,
        recorded: Option<Recorded>,
    ) -> Result<QuantOptions> {
        if self.calibration_clips.is_some() && recorded.is_none() {
            anyhow::bail!(
                "--calibration-clips is for OMG models (host-sim omg-reach); \
                 here use --calibration FILE or --calibration-tours N"
            );
        }
        let compensation_samples =
            exporter::cli_args::compensation_samples(net, self.rounding, self.compensation_samples)
                .map_err(anyhow::Error::msg)?;
        let calibration_weight = exporter::cli_args::calibration_weight(
            self.calibration_weight,
            self.calibration.is_some() || self.calibration_tours.is_some() || recorded.is_some(),
            compensation_samples,
        )
        .map_err(anyhow::Error::msg)?;
        let calibration_data = match (&self.calibration, self.calibration_tours) {
            (Some(p), _) => Some(Recorded::read(p, net.input_dim())?),
            (None, Some(n)) => Some(tour_rollouts(net, n, self.tour_seed)?),
            (None, None) => recorded,
        };
        Ok(QuantOptions {
            compensation_samples,
            calibration_data,
            calibration_weight,
            layer_weights: self
                .int16_layers
                .iter()
                .map(|&l| (l, phasegate::blob::WeightFormat::I16))
                .collect(),
            ..opts
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `--calibration-clips` needs the OMG data set, which only
    /// `omg-reach` reads: elsewhere it is refused, not ignored.
    #[test]
    fn calibration_clips_are_refused_where_no_clips_are_read() {
        let net = crate::target::synthetic::rbf_net(5);
        let knobs = Int8Knobs {
            calibration_clips: Some(3),
            ..Int8Knobs::default()
        };
        let e = knobs
            .apply(&net, QuantOptions::default())
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("--calibration-clips is for OMG models"),
            "{e}"
        );
        assert!(Int8Knobs::default()
            .apply(&net, QuantOptions::default())
            .is_ok());
    }

    /// `Int8Knobs::default()`, which tests and library callers use, is what
    /// the command line gives when no flag is passed.
    #[test]
    fn default_is_the_command_lines() {
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            knobs: Int8Knobs,
        }
        let parsed = <Cli as clap::Parser>::parse_from(["host-sim"]).knobs;
        assert_eq!(format!("{parsed:?}"), format!("{:?}", Int8Knobs::default()));
    }
}
