//! Command-line pieces shared by `exporter` and `host-sim`.

use crate::net::GatingMode;

/// `--gating` of the command lines.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum GatingArg {
    /// Nearest lower of the tables (the demo's default mode).
    Constant,
    /// Linear blend of 10 tables (every 5th of 50).
    Linear,
    /// Exact Catmull-Rom spline of the 4 recovered control points.
    Cubic,
}

impl From<GatingArg> for GatingMode {
    fn from(g: GatingArg) -> Self {
        match g {
            GatingArg::Constant => GatingMode::Constant,
            GatingArg::Linear => GatingMode::Linear,
            GatingArg::Cubic => GatingMode::Cubic,
        }
    }
}

/// `--rounding` of the command lines: how int8 dense weights are rounded.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum RoundingArg {
    /// Each weight to nearest.
    Nearest,
    /// For the least output error on calibration inputs (GPTQ, layer after
    /// layer, aimed at the float network; docs/fixed-point.md).
    Compensated,
}

/// The `compensation_samples` of [`crate::quantise::QuantOptions`] that
/// `--rounding` and `--compensation-samples` ask for on `net` (0 rounds to
/// nearest). Without `--rounding`, a chain (PFNN-shaped network) is
/// rounded error-aware, with
/// [`DEFAULT_COMPENSATION_SAMPLES`](crate::quantise::DEFAULT_COMPENSATION_SAMPLES)
/// unless `--compensation-samples` says otherwise; a graph (OMG) is
/// rounded to nearest unless `--compensation-samples` is given (error-aware
/// rounding has not been measured on the OMG models yet).
pub fn compensation_samples(
    net: &crate::net::Net,
    rounding: Option<RoundingArg>,
    samples: Option<usize>,
) -> Result<usize, String> {
    let chain = matches!(net.wiring, crate::net::Wiring::Chain);
    match (rounding, samples) {
        (Some(RoundingArg::Nearest), Some(n)) if n > 0 => Err(format!(
            "--compensation-samples {n} is for --rounding compensated, not nearest"
        )),
        (Some(RoundingArg::Nearest), _) => Ok(0),
        (Some(RoundingArg::Compensated), Some(0)) => {
            Err("--rounding compensated needs --compensation-samples above 0".into())
        }
        (Some(RoundingArg::Compensated), n) => {
            Ok(n.unwrap_or(crate::quantise::DEFAULT_COMPENSATION_SAMPLES))
        }
        (None, Some(n)) => Ok(n),
        (None, None) if chain => Ok(crate::quantise::DEFAULT_COMPENSATION_SAMPLES),
        (None, None) => Ok(0),
    }
}

/// `--calibration-weight`: the share of error-aware rounding's objective
/// that the recorded rows carry (default
/// [`DEFAULT_CALIBRATION_WEIGHT`](crate::quantise::DEFAULT_CALIBRATION_WEIGHT));
/// only with `--calibration` and error-aware rounding (`compensation_samples`
/// above 0), strictly between 0 and 1.
pub fn calibration_weight(
    weight: Option<f64>,
    has_calibration: bool,
    compensation_samples: usize,
) -> Result<f64, String> {
    match weight {
        None => Ok(crate::quantise::DEFAULT_CALIBRATION_WEIGHT),
        Some(_) if !has_calibration => {
            Err("--calibration-weight weighs the --calibration rows: give the file".into())
        }
        Some(_) if compensation_samples == 0 => Err(
            "--calibration-weight weighs error-aware rounding, which is off (--rounding nearest)"
                .into(),
        ),
        Some(w) if w > 0.0 && w < 1.0 => Ok(w),
        Some(w) => Err(format!(
            "--calibration-weight {w} must be strictly between 0 and 1"
        )),
    }
}
