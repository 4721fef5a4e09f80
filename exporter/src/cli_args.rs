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
