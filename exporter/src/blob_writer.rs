//! Assembles a blob: payload sections, header, checksums.
//! The inverse of `phasegate::Model::from_bytes`; see `docs/blob-format.md`.

use phasegate::blob::{
    crc32, AccWidth, Gating, Header, LayerDesc, ModelKind, Requant, Section, WeightFormat,
    FORMAT_VERSION, MAGIC, MAX_LAYERS, PAYLOAD_ALIGN, PREAMBLE_LEN,
};

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

struct Payload(Vec<u8>);

impl Payload {
    fn push(&mut self, bytes: &[u8]) -> Result<Section, EncodeError> {
        while !self.0.len().is_multiple_of(4) {
            self.0.push(0);
        }
        let offset = u32::try_from(self.0.len()).map_err(|_| EncodeError::TooLarge("payload"))?;
        let len = u32::try_from(bytes.len()).map_err(|_| EncodeError::TooLarge("section"))?;
        self.0.extend_from_slice(bytes);
        Ok(Section { offset, len })
    }
}

fn weight_bytes(l: &BlobLayer, i: usize) -> Result<Vec<u8>, EncodeError> {
    let d = &l.desc;
    let n = usize::from(d.experts) * usize::from(d.out_dim) * usize::from(d.in_dim);
    if l.weights.len() != n {
        return Err(EncodeError::Length {
            layer: i,
            what: "weights",
        });
    }
    let bad = || EncodeError::OutOfRange {
        layer: i,
        what: "weights",
    };
    let mut out = Vec::with_capacity(n * d.weights.bytes());
    for &w in &l.weights {
        match d.weights {
            WeightFormat::I8 => out.push(i8::try_from(w).map_err(|_| bad())? as u8),
            WeightFormat::I16 => out.extend(i16::try_from(w).map_err(|_| bad())?.to_le_bytes()),
        }
    }
    Ok(out)
}

fn bias_bytes(l: &BlobLayer, i: usize) -> Result<Vec<u8>, EncodeError> {
    let d = &l.desc;
    if l.bias.len() != usize::from(d.experts) * usize::from(d.out_dim) {
        return Err(EncodeError::Length {
            layer: i,
            what: "bias",
        });
    }
    let mut out = Vec::new();
    for &b in &l.bias {
        match d.acc {
            AccWidth::I32 => out.extend(
                i32::try_from(b)
                    .map_err(|_| EncodeError::OutOfRange {
                        layer: i,
                        what: "bias",
                    })?
                    .to_le_bytes(),
            ),
            AccWidth::I64 => out.extend(b.to_le_bytes()),
        }
    }
    Ok(out)
}

fn stage_bytes(records: &[(f32, f32)]) -> Vec<u8> {
    records
        .iter()
        .flat_map(|(a, b)| a.to_le_bytes().into_iter().chain(b.to_le_bytes()))
        .collect()
}

/// Lays out the payload, fills in the header and returns the blob bytes.
pub fn encode(m: &BlobModel) -> Result<Vec<u8>, EncodeError> {
    if m.layers.len() > MAX_LAYERS {
        return Err(EncodeError::TooManyLayers(m.layers.len()));
    }
    let mut payload = Payload(Vec::new());
    let mut layers = heapless::Vec::<LayerDesc, MAX_LAYERS>::new();
    let input_stage = payload.push(&stage_bytes(&m.input_stage))?;
    let output_stage = payload.push(&stage_bytes(&m.output_stage))?;
    for (i, l) in m.layers.iter().enumerate() {
        if l.requant.len() != usize::from(l.desc.out_dim) {
            return Err(EncodeError::Length {
                layer: i,
                what: "requant",
            });
        }
        let mut desc = l.desc;
        desc.weight_section = payload.push(&weight_bytes(l, i)?)?;
        desc.bias_section = payload.push(&bias_bytes(l, i)?)?;
        let rq: Vec<u8> = l.requant.iter().flat_map(|r| r.to_bytes()).collect();
        desc.requant_section = payload.push(&rq)?;
        layers
            .push(desc)
            .map_err(|_| EncodeError::TooManyLayers(m.layers.len()))?;
    }
    let dim = |n: usize, what| u16::try_from(n).map_err(|_| EncodeError::TooLarge(what));
    let header = Header {
        kind: m.kind,
        gating: m.gating,
        input_dim: dim(m.input_stage.len(), "input width")?,
        output_dim: dim(m.output_stage.len(), "output width")?,
        ram_bytes: u32::try_from(phasegate::ram_bytes(&layers))
            .map_err(|_| EncodeError::TooLarge("RAM"))?,
        macs_per_frame: u32::try_from(phasegate::macs(&m.gating, &layers))
            .map_err(|_| EncodeError::TooLarge("MACs per frame"))?,
        layers,
        input_stage,
        output_stage,
        payload_len: u32::try_from(payload.0.len())
            .map_err(|_| EncodeError::TooLarge("payload"))?,
        payload_crc: crc32(&payload.0),
    };
    Ok(frame(&header, &payload.0))
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
