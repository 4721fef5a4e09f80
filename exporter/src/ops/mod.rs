//! The ops of a network, one module each: its float forward (what the
//! fixed-point runtime is measured against and calibrated on) and its
//! quantisation hook. Every op goes through the one pipeline of
//! [`crate::quantise`] and the one encoder of [`crate::encode`].
//!
//! To add an op: a module here with its float type, `apply` and
//! `quantise`, one variant of [`NetLayer`] and an arm in each match below
//! (see `docs/adding-an-op.md`).

pub mod cp;
pub mod dec;
pub mod dense;
pub mod diag;
pub mod rbf;

use ndarray::{Array1, Array2};

pub use cp::CpLayer;
pub use dec::DecLayer;
pub use dense::ExpertLayer;
pub use diag::DiagLayer;
pub use rbf::RbfLayer;

use crate::lower::qmodel::QLayer;
use crate::quantise::{LayerSpec, QuantError, QuantLayerReport};

/// Fewest calibration samples of a network with CP layers: their middle
/// vectors (products of two calibrated quantities) have heavier tails than
/// plain pre-activations, and the maxima set the formats.
pub const CP_CALIBRATION_SAMPLES: usize = 2048;

/// One gated layer of any form.
#[derive(Clone, Debug, PartialEq)]
pub enum NetLayer {
    /// One `out x in` matrix per expert.
    Dense(ExpertLayer),
    /// CP factors.
    Cp(CpLayer),
    /// One diagonal per expert.
    Diagonal(DiagLayer),
    /// Gaussian radial basis functions (not linear).
    Rbf(RbfLayer),
    /// Student-t soft assignment to centres (not linear).
    Dec(DecLayer),
}

impl NetLayer {
    /// `y` (pre-activation) and, for CP layers, the middle vector.
    pub fn apply_mid(
        &self,
        gate: &[(usize, f64)],
        x: &Array1<f64>,
    ) -> (Array1<f64>, Option<Array1<f64>>) {
        match self {
            NetLayer::Dense(l) => (l.apply(gate, x), None),
            NetLayer::Cp(l) => {
                let (y, u) = l.apply_mid(gate, x);
                (y, Some(u))
            }
            NetLayer::Diagonal(l) => (l.apply(gate, x), None),
            NetLayer::Rbf(l) => (l.apply(gate, x), None),
            NetLayer::Dec(l) => (l.apply(gate, x), None),
        }
    }

    /// `y` (pre-activation).
    pub fn apply(&self, gate: &[(usize, f64)], x: &Array1<f64>) -> Array1<f64> {
        self.apply_mid(gate, x).0
    }

    /// Input width.
    pub fn in_dim(&self) -> usize {
        match self {
            NetLayer::Dense(l) => l.w.first().map_or(0, |w| w.ncols()),
            NetLayer::Cp(l) => l.b.nrows(),
            NetLayer::Diagonal(l) => l.w.first().map_or(0, |w| w.len()),
            NetLayer::Rbf(l) => l.centres.first().map_or(0, |c| c.ncols()),
            NetLayer::Dec(l) => l.centres.first().map_or(0, |c| c.ncols()),
        }
    }

    /// Output width.
    pub fn out_dim(&self) -> usize {
        match self {
            NetLayer::Dense(l) => l.w.first().map_or(0, |w| w.nrows()),
            NetLayer::Cp(l) => l.a.nrows(),
            NetLayer::Diagonal(l) => l.w.first().map_or(0, |w| w.len()),
            NetLayer::Rbf(l) => l.centres.first().map_or(0, |c| c.nrows()),
            NetLayer::Dec(l) => l.centres.first().map_or(0, |c| c.nrows()),
        }
    }

    /// Expert count.
    pub fn experts(&self) -> usize {
        match self {
            NetLayer::Dense(l) => l.experts(),
            NetLayer::Cp(l) => l.experts(),
            NetLayer::Diagonal(l) => l.w.len(),
            NetLayer::Rbf(l) => l.centres.len(),
            NetLayer::Dec(l) => l.centres.len(),
        }
    }

    /// Weights stored (biases excluded).
    pub fn weight_count(&self) -> usize {
        match self {
            NetLayer::Dense(l) => l.experts() * self.in_dim() * self.out_dim(),
            NetLayer::Cp(l) => l.rank() * (self.in_dim() + self.out_dim() + l.experts()),
            NetLayer::Diagonal(l) => l.w.len() * self.out_dim(),
            NetLayer::Rbf(l) => l.centres.len() * self.out_dim() * (self.in_dim() + 1),
            NetLayer::Dec(l) => l.centres.len() * self.out_dim() * self.in_dim(),
        }
    }

    /// Rank for CP layers.
    pub fn rank(&self) -> Option<usize> {
        match self {
            NetLayer::Cp(l) => Some(l.rank()),
            _ => None,
        }
    }

    /// "dense", "cp", "diagonal", "rbf" or "dec".
    pub fn form(&self) -> &'static str {
        match self {
            NetLayer::Dense(_) => "dense",
            NetLayer::Cp(_) => "cp",
            NetLayer::Diagonal(_) => "diagonal",
            NetLayer::Rbf(_) => "rbf",
            NetLayer::Dec(_) => "dec",
        }
    }

    /// Quantises the op for `spec`: the op's hook into the one pipeline.
    pub fn quantise(&self, spec: &LayerSpec<'_>) -> Result<(QLayer, QuantLayerReport), QuantError> {
        match self {
            NetLayer::Dense(l) => dense::quantise(l, spec),
            NetLayer::Cp(l) => cp::quantise(l, spec),
            NetLayer::Diagonal(l) => diag::quantise(l, spec),
            NetLayer::Rbf(l) => rbf::quantise(l, spec),
            NetLayer::Dec(l) => dec::quantise(l, spec),
        }
    }

    /// The matrices the op applies to its input, one per stored set (per
    /// expert, or one for CP's shared `B^T`): the pipeline scales the input
    /// columns with them in view.
    pub fn input_rows(&self) -> Vec<Array2<f64>> {
        match self {
            NetLayer::Dense(l) => l.w.clone(),
            NetLayer::Cp(l) => vec![l.b.t().to_owned()],
            NetLayer::Diagonal(l) => l.w.iter().map(Array2::from_diag).collect(),
            // No weights multiply the inputs: every column counts the same.
            NetLayer::Rbf(l) => vec![Array2::eye(self.in_dim()); l.centres.len()],
            NetLayer::Dec(l) => vec![Array2::eye(self.in_dim()); l.centres.len()],
        }
    }

    /// Whether the rows of [`Self::input_rows`] are the op's outputs (so
    /// output weights apply to them).
    pub fn rows_are_outputs(&self) -> bool {
        !matches!(self, NetLayer::Cp(_) | NetLayer::Rbf(_) | NetLayer::Dec(_))
    }

    /// Fewest calibration samples this op needs.
    pub fn calibration_samples(&self) -> usize {
        match self {
            NetLayer::Cp(_) => CP_CALIBRATION_SAMPLES,
            _ => 0,
        }
    }

    /// The dense layer, if the op is one.
    pub fn as_dense(&self) -> Option<&ExpertLayer> {
        match self {
            NetLayer::Dense(l) => Some(l),
            _ => None,
        }
    }

    /// The dense layer, mutably, if the op is one.
    pub fn as_dense_mut(&mut self) -> Option<&mut ExpertLayer> {
        match self {
            NetLayer::Dense(l) => Some(l),
            _ => None,
        }
    }
}
