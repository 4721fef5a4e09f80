//! Assembles a blob: payload sections, header, checksums.
//! The inverse of `phasegate::Model::from_bytes`; see `docs/blob-format.md`.

use phasegate::blob::{
    crc32, Gating, Header, LayerDesc, ModelKind, Requant, FORMAT_VERSION, MAGIC, MAX_LAYERS,
    PAYLOAD_ALIGN, PREAMBLE_LEN,
};

use crate::cp::encode::{encode_net, QKind, QLayer, QModel};

/// One quantised layer, ready to be laid out.
#[derive(Clone, Debug)]
pub struct BlobLayer {
    /// Descriptor; its sections are filled in by [`encode`].
    pub desc: LayerDesc,
    /// `experts x out x in` integer weights (must fit `desc.weights`).
    pub weights: Vec<i32>,
    /// `experts x out` biases in accumulator units (must fit `desc.acc`).
    pub bias: Vec<i64>,
    /// `out` requantisation records.
    pub requant: Vec<Requant>,
}

/// A whole quantised model.
#[derive(Clone, Debug)]
pub struct BlobModel {
    /// Network family.
    pub kind: ModelKind,
    /// Gating of the gated layers.
    pub gating: Gating,
    /// `(offset, scale)` per input.
    pub input_stage: Vec<(f32, f32)>,
    /// `(scale, offset)` per output.
    pub output_stage: Vec<(f32, f32)>,
    /// Layers in order.
    pub layers: Vec<BlobLayer>,
}

/// Why a model cannot be encoded (a bug in the caller, not bad user input).
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum EncodeError {
    /// More layers than a header holds.
    #[error("{0} layers: a blob holds at most {MAX_LAYERS}")]
    TooManyLayers(usize),
    /// A dimension or the payload does not fit its header field.
    #[error("{0} is too large for the blob format")]
    TooLarge(&'static str),
    /// A value does not fit its storage type.
    #[error("layer {layer}: {what} out of range for its storage type")]
    OutOfRange {
        /// Layer index.
        layer: usize,
        /// Which array.
        what: &'static str,
    },
    /// An array has the wrong number of elements.
    #[error("layer {layer}: {what} has the wrong length")]
    Length {
        /// Layer index.
        layer: usize,
        /// Which array.
        what: &'static str,
    },
}

/// Lays out the payload, fills in the header and returns the blob bytes.
/// One layout for every blob: a dense model is the special case of
/// [`crate::cp::encode::encode_net`] with dense layers only (the golden
/// vectors pin its bytes).
pub fn encode(m: &BlobModel) -> Result<Vec<u8>, EncodeError> {
    let layers = m
        .layers
        .iter()
        .map(|l| QLayer {
            desc: l.desc,
            weights: l.weights.clone(),
            bias: l.bias.clone(),
            requant: l.requant.clone(),
            cp: None,
        })
        .collect();
    encode_net(&QModel {
        kind: QKind::Model(m.kind),
        gating: m.gating,
        input_stage: m.input_stage.clone(),
        output_stage: m.output_stage.clone(),
        layers,
    })
}

/// Preamble + header + padding + payload. Public so tests can build blobs
/// with deliberately inconsistent headers.
pub fn frame(header: &Header, payload: &[u8]) -> Vec<u8> {
    let header_bytes = postcard::to_allocvec(header).unwrap_or_default();
    let header_len = u16::try_from(header_bytes.len()).unwrap_or(u16::MAX);
    let mut out =
        Vec::with_capacity(PREAMBLE_LEN + header_bytes.len() + PAYLOAD_ALIGN + payload.len());
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&header_len.to_le_bytes());
    let mut crc_input = out.clone();
    crc_input.extend_from_slice(&header_bytes);
    out.extend_from_slice(&crc32(&crc_input).to_le_bytes());
    out.extend_from_slice(&header_bytes);
    out.resize(out.len().next_multiple_of(PAYLOAD_ALIGN), 0);
    out.extend_from_slice(payload);
    out
}
