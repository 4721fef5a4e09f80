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

/// The largest value each count option of `exporter` and `host-sim`
/// accepts, checked when the command line is parsed, before anything is
/// read or allocated. Each bounds the memory and time that a mistyped
/// number can ask for (the memory of a run grows with these counts times
/// the model's width; the tables in `docs/input-files.md`, "Bounds").
pub mod bounds {
    /// Frames of a rollout or a run (one hour at 60 frames per second).
    pub const FRAMES: usize = 216_000;
    /// Samples drawn or measured: calibration, error-aware rounding,
    /// distillation, error reports (16 times the largest default).
    pub const SAMPLES: usize = 262_144;
    /// Optimiser steps and sweeps: `--distill`, `--als-iters`, `--steps`.
    pub const STEPS: usize = 100_000;
    /// CP ranks.
    pub const RANK: usize = 4_096;
    /// Scripts, tours, clips, noise seeds, rounds and snapshots.
    pub const RUNS: usize = 10_000;
    /// Extra bytes of `--int16-budget` (a blob is at most 4 GiB).
    pub const BYTES: usize = 1 << 32;

    /// Self-test vectors stored in a blob (`--self-test`; the format's
    /// limit, `phasegate::blob::MAX_SELF_TEST_VECTORS`).
    pub const SELF_TEST: usize = 1_024;

    /// Rows of a recorded data set (scripts and tours times frames):
    /// about 720 MB of f64 rows at the PFNN's 342 inputs.
    pub const ROWS: usize = 262_144;

    /// Training rows of `host-sim style-demo` (its scripts times
    /// `--frames` times the fits, `--rounds` + 1): a row takes about 19 KB
    /// while the adapters are fitted (1.27 GB peak resident at 65,530
    /// rows), so a quarter of [`ROWS`].
    pub const STYLE_ROWS: usize = 65_536;

    /// A value parser for a count option of at most `max`.
    pub fn at_most<T>(max: T) -> impl Fn(&str) -> Result<T, String> + Clone + Send + Sync
    where
        T: std::str::FromStr + PartialOrd + std::fmt::Display + Copy + Send + Sync + 'static,
    {
        move |s: &str| {
            let n: T = s
                .parse()
                .map_err(|_| format!("{s} is not a whole number from 0 to {max}"))?;
            if n > max {
                return Err(format!("{n} is more than the largest accepted, {max}"));
            }
            Ok(n)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::bounds::at_most;

    #[test]
    fn counts_are_accepted_up_to_their_maximum() {
        let p = at_most(4096usize);
        assert_eq!(p("0"), Ok(0));
        assert_eq!(p("4096"), Ok(4096));
        assert_eq!(
            p("4097"),
            Err("4097 is more than the largest accepted, 4096".into())
        );
        for bad in ["-1", "1e3", "", "99999999999999999999999"] {
            assert!(p(bad).unwrap_err().contains("not a whole number"), "{bad}");
        }
        assert_eq!(at_most(4u64)("4"), Ok(4));
    }
}
