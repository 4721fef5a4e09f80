//! From a float [`Net`] to blob bytes and the one export report, whatever
//! the importer and the ops.

use phasegate::Model;
use serde::Serialize;

use crate::control_points::Residual;
use crate::encode::encode;
use crate::net::Net;
use crate::quantise::{quantise_net, QuantLayerReport, QuantOptions};

/// The `--report` JSON.
#[derive(Clone, Debug, Serialize)]
pub struct ExportReport {
    /// Format version of the blob written.
    pub format_version: u16,
    /// "constant", "linear" or "cubic".
    pub gating: String,
    /// Experts per layer.
    pub experts: usize,
    /// "int8" or "int16" ("mixed" when layers differ).
    pub weight_format: &'static str,
    /// Bytes of the blob.
    pub blob_bytes: usize,
    /// Activation RAM, bytes.
    pub ram_bytes: usize,
    /// Multiply-accumulates per frame.
    pub macs_per_frame: u32,
    /// Control-point recovery residual (cubic only).
    pub control_point_residual: Option<ResidualReport>,
    /// Fraction bits of the normalised inputs.
    pub input_frac: u8,
    /// Inputs within this many standard deviations of the mean do not saturate.
    pub input_range_sigma: f64,
    /// Per-layer figures.
    pub layers: Vec<QuantLayerReport>,
    /// True when every layer's no-overflow proof holds.
    pub overflow_proof: bool,
    /// How the proof is made.
    pub overflow_proof_statement: &'static str,
    /// Quantiser options used.
    pub options: QuantOptions,
    /// Where `--int16-budget` went, when given.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub int16_budget: Option<crate::budget::BudgetReport>,
    /// The estimated cost per frame against `--budget-instructions`, when
    /// given (`crate::cost`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frame_budget: Option<crate::cost::BudgetCheck>,
    /// The self-test section (`--self-test N`), when the blob has one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub self_test: Option<crate::self_test::SelfTestReport>,
}

/// JSON form of [`Residual`].
#[derive(Clone, Copy, Debug, Serialize)]
pub struct ResidualReport {
    /// Largest absolute difference between the tables and the spline.
    pub max_abs: f64,
    /// Relative Frobenius error.
    pub rel_frobenius: f64,
}

impl From<Residual> for ResidualReport {
    fn from(r: Residual) -> Self {
        ResidualReport {
            max_abs: r.max_abs,
            rel_frobenius: r.rel_frobenius,
        }
    }
}

/// Export failure.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// Quantisation failed.
    #[error(transparent)]
    Quant(#[from] crate::quantise::QuantError),
    /// Encoding failed.
    #[error(transparent)]
    Encode(#[from] crate::lower::qmodel::EncodeError),
    /// The blob written does not load: a bug, never shipped.
    #[error("the blob written does not load back: {0}")]
    SelfCheck(phasegate::Error),
}

/// The proof, in words, for the report.
pub const PROOF_STATEMENT: &str = "for every row: sum|w|*2^15 fits the accumulator (i32 rows are re-checked by the runtime at load), \
the gate-blended sum max_k(sum|w_k|*2^15+|b_k|)*sum|g| < 2^63, and the pre-shift brings that bound below 2^31; \
activations are i16, so this holds for any input, not only the calibrated range";

pub use crate::lower::qmodel::format_name;

/// Quantises, encodes and re-loads `net`; returns the blob and its report.
/// `residual` is the control-point recovery residual of a cubic PFNN, for
/// the report.
pub fn export(
    net: &Net,
    residual: Option<Residual>,
    opts: &QuantOptions,
) -> Result<(Vec<u8>, ExportReport), ExportError> {
    let q = quantise_net(net, opts)?;
    let blob = encode(&q.model)?;
    let model = Model::from_bytes(&blob).map_err(ExportError::SelfCheck)?;
    let report = ExportReport {
        format_version: phasegate::blob::FORMAT_VERSION,
        gating: if net.experts() == 0 {
            "none".to_string()
        } else {
            net.mode.name().to_string()
        },
        experts: net.experts(),
        weight_format: if q.layers.iter().all(|l| l.weights == q.layers[0].weights) {
            format_name(opts.weights_of(0))
        } else {
            "mixed"
        },
        blob_bytes: blob.len(),
        ram_bytes: model.ram_bytes(),
        macs_per_frame: model.macs_per_frame(),
        control_point_residual: residual.map(Into::into),
        input_frac: q.input_frac,
        input_range_sigma: f64::from(1u32 << 15) / f64::from(1u32 << q.input_frac),
        overflow_proof: q.layers.iter().all(|l| l.proof),
        overflow_proof_statement: PROOF_STATEMENT,
        layers: q.layers,
        options: opts.clone(),
        int16_budget: None,
        frame_budget: None,
        self_test: None,
    };
    Ok((blob, report))
}
