//! Where a gated node's coefficients come from when its gate source is the
//! phase: the three ways a PFNN's experts are read.
//!
//! * `Constant` and `Linear` reproduce the public demo's `PFNN::predict`
//!   (`demo/pfnn.cpp`) decision for decision: constant uses table
//!   `floor(p / 2pi * n)`; linear blends keyframe `floor(p / 2pi * n)` and
//!   the next one (mod n) with weight `fmod(p / 2pi * n, 1)` on the second.
//! * `Cubic` is the exact Catmull-Rom spline of the 4 control points at
//!   `s = 4 p / 2pi`, not the demo's cubic mode (which uses tables
//!   0/12/25/37 as if they were the control points).
//!
//! The only deliberate departure from the demo: the phase is wrapped into
//! `[0, 2pi)` first. The demo wraps with C `fmod`, which keeps the sign, so a
//! negative phase change gives a negative phase, which it truncates towards
//! table 0 (or, below `-2pi/50`, indexes out of bounds); a float phase that
//! rounds up to `2pi` indexes table 50, one past the end.

use std::f64::consts::TAU;
use std::fmt;
use std::str::FromStr;

use crate::control_points::{catmull_rom_weights, CONTROL_POINTS};

/// How the phase selects and blends the experts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum GatingMode {
    /// One precomputed table, the nearest one at or below the phase.
    Constant,
    /// Linear blend of two neighbouring keyframes (the demo's 10).
    Linear,
    /// Exact Catmull-Rom spline of the 4 recovered control points.
    Cubic,
}

impl GatingMode {
    /// Every mode, in command-line order.
    pub const ALL: [Self; 3] = [Self::Constant, Self::Linear, Self::Cubic];

    /// Lower-case name, as used on command lines and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Self::Constant => "constant",
            Self::Linear => "linear",
            Self::Cubic => "cubic",
        }
    }

    /// The experts active at `phase_rad` and their weights (summing to 1),
    /// for a node with `n` experts.
    ///
    /// The shape is fixed per mode, as in the demo: constant 1 entry,
    /// linear 2 (the second may weigh 0), cubic 4. Empty if `n == 0`;
    /// non-finite phases give NaN weights.
    pub fn gate(self, n: usize, phase_rad: f64) -> Vec<(usize, f64)> {
        if n == 0 {
            return Vec::new();
        }
        let cycles = wrap_phase(phase_rad) / TAU;
        match self {
            Self::Constant => vec![(split(cycles * n as f64, n).0, 1.0)],
            Self::Linear => {
                let (i, a) = split(cycles * n as f64, n);
                vec![(i, 1.0 - a), ((i + 1) % n, a)]
            }
            Self::Cubic => catmull_rom_weights(cycles * CONTROL_POINTS as f64).to_vec(),
        }
    }
}

impl fmt::Display for GatingMode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A string that names no gating mode.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown gating mode {0:?}: expected constant, linear or cubic")]
pub struct ParseGatingModeError(pub String);

impl FromStr for GatingMode {
    type Err = ParseGatingModeError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|m| m.name().eq_ignore_ascii_case(s))
            .ok_or_else(|| ParseGatingModeError(s.to_owned()))
    }
}

/// Wraps a phase in radians into `[0, 2pi)`.
pub fn wrap_phase(phase_rad: f64) -> f64 {
    let p = phase_rad.rem_euclid(TAU);
    // rem_euclid rounds a tiny negative phase up to exactly 2pi.
    if p >= TAU {
        0.0
    } else {
        p
    }
}

/// Integer part (mod `n`) and fraction of a non-negative position, as the
/// demo's `(int)x` and `fmod(x, 1.0)`. A position that rounded up to `n`
/// is the start of the next cycle.
fn split(x: f64, n: usize) -> (usize, f64) {
    let whole = x.floor();
    ((whole as usize) % n, x - whole)
}
