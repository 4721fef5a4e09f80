//! The header's data model, shared by the exporter (which writes it) and the
//! runtime (which reads it). Its wire format is postcard; see
//! `docs/blob-format.md` for the byte-level specification.
//!
//! Enums only ever grow at the end, so a newer minor revision of the format
//! still decodes old blobs (postcard encodes variants as varint indices).

use serde::{Deserialize, Serialize};

/// Most layers a blob may hold (the PFNN has 3; OMG's generator and gating
/// network fit within this too).
pub const MAX_LAYERS: usize = 8;

/// Which network family, so a controller can refuse a blob that is not its own.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ModelKind {
    /// Phase-functioned neural network (locomotion).
    Pfnn,
    /// A plain phase-free MLP.
    Mlp,
    /// A style: residual adapters for one base model, loaded beside it
    /// (see `docs/cp-and-styles.md`). Its header's single layer is the
    /// adapter; `input_stage` and `output_stage` are empty.
    Style {
        /// `payload_crc` of the base blob this style was built for.
        base_crc: u32,
        /// Index of the base layer whose pre-activation the adapter adds to.
        layer: u8,
        /// The style's name, UTF-8, at most [`MAX_STYLE_NAME`] bytes.
        name: Section,
    },
}

/// Longest style name, bytes.
pub const MAX_STYLE_NAME: usize = 64;

/// How the gate coefficients of the experts are computed from the phase.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Gating {
    /// One expert, always weight 1.
    Single,
    /// `tables` experts spread evenly over the cycle; the nearest lower one
    /// is used alone (the PFNN demo's default mode with 50 tables).
    Constant {
        /// Number of experts.
        tables: u16,
    },
    /// `tables` experts spread evenly over the cycle, blended linearly
    /// between the two around the phase (the demo's mode with 10 tables).
    Linear {
        /// Number of experts.
        tables: u16,
    },
    /// Periodic Catmull-Rom spline through `points` control points
    /// (PFNN: 4); four experts are active at any phase.
    CatmullRom {
        /// Number of control points (at least 4).
        points: u16,
    },
}

impl Gating {
    /// How many experts each gated layer must have.
    pub fn experts(&self) -> u16 {
        match *self {
            Gating::Single => 1,
            Gating::Constant { tables } | Gating::Linear { tables } => tables,
            Gating::CatmullRom { points } => points,
        }
    }

    /// How many experts are active (non-zero gate) in one frame at most.
    pub fn active(&self) -> usize {
        match *self {
            Gating::Single | Gating::Constant { .. } => 1,
            Gating::Linear { .. } => 2,
            Gating::CatmullRom { .. } => 4,
        }
    }
}

/// Storage type of the weights of a layer.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum WeightFormat {
    /// Signed 8 bit, symmetric (-127..=127), per-row scale.
    I8,
    /// Signed 16 bit, symmetric (-32767..=32767), per-row scale.
    I16,
}

impl WeightFormat {
    /// Bytes per weight.
    pub fn bytes(&self) -> usize {
        match self {
            WeightFormat::I8 => 1,
            WeightFormat::I16 => 2,
        }
    }
}

/// Width of a layer's per-expert dot-product accumulators and biases.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum AccWidth {
    /// 32-bit accumulators and biases; the loader proves per row that
    /// `sum |w| * 32768` fits.
    I32,
    /// 64-bit accumulators and biases; cannot overflow for `in_dim < 2^30`.
    I64,
}

impl AccWidth {
    /// Bytes per bias element.
    pub fn bytes(&self) -> usize {
        match self {
            AccWidth::I32 => 4,
            AccWidth::I64 => 8,
        }
    }
}

/// Non-linearity applied to a layer's requantised output.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Activation {
    /// None (output layers).
    Identity,
    /// `x` for `x > 0`, `exp(x) - 1` otherwise; table-interpolated.
    Elu,
}

/// How a layer computes `W x`.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum LayerOp {
    /// Dense weights, one `out x in` matrix per expert.
    Dense,
    /// CP-decomposed weights `W_k = A diag(d_k) B^T`, computed as
    /// `A ((sum_k g_k d_k) . (B^T x))` without forming `W`. `weight_section`
    /// holds `B^T` (`rank x in_dim`, row-major, `weights` format).
    Cp {
        /// Number of rank-one components `R`.
        rank: u16,
        /// `A`: `out_dim x rank`, row-major, `weights` format.
        a: Section,
        /// Cores `d_k`: `experts x rank` i16, little-endian.
        cores: Section,
        /// `rank` middle records, 8 bytes each (see `kernels::cp::MidRecord`).
        mid: Section,
    },
    /// Diagonal weights (`in_dim == out_dim`): `y_i = w_ki x_i`;
    /// `weight_section` holds `experts x out_dim` weights.
    Diagonal,
}

/// A byte range of the payload (offsets are from the payload's first byte).
#[derive(Clone, Copy, Debug, Default, Eq, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Section {
    /// Offset from the start of the payload; a multiple of 4.
    pub offset: u32,
    /// Length in bytes.
    pub len: u32,
}

impl Section {
    /// One past the last byte, or `None` when that overflows.
    pub fn end(&self) -> Option<u32> {
        self.offset.checked_add(self.len)
    }
}

/// One gated layer: `y = act(requant(sum_k g_k (W_k x + b_k)))`.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LayerDesc {
    /// How `W x` is computed.
    pub op: LayerOp,
    /// Input width.
    pub in_dim: u16,
    /// Output width.
    pub out_dim: u16,
    /// Expert count; must equal the gating's (`1` for ungated layers).
    pub experts: u16,
    /// Weight storage.
    pub weights: WeightFormat,
    /// Accumulator and bias width.
    pub acc: AccWidth,
    /// Non-linearity.
    pub activation: Activation,
    /// Whether the layer is gated (uses the phase gate) or has one expert.
    pub gated: bool,
    /// `experts x out_dim x in_dim` weights, row-major, little-endian.
    pub weight_section: Section,
    /// `experts x out_dim` biases in accumulator units (`acc` wide, LE).
    pub bias_section: Section,
    /// `out_dim` requantisation records, 8 bytes each (multiplier, shifts
    /// and the row's activation format: scales are per row, and the next
    /// layer's weights absorb them per column).
    pub requant_section: Section,
}

/// The blob header: everything the runtime needs before touching the payload.
#[derive(Clone, Debug, Eq, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// Network family.
    pub kind: ModelKind,
    /// Gating of the gated layers.
    pub gating: Gating,
    /// Width of the model's float input.
    pub input_dim: u16,
    /// Width of the model's float output.
    pub output_dim: u16,
    /// Layers in evaluation order.
    pub layers: heapless::Vec<LayerDesc, MAX_LAYERS>,
    /// `input_dim` records (offset f32, scale f32): `q = round((x - offset) * scale)`.
    pub input_stage: Section,
    /// `output_dim` records (scale f32, offset f32): `y = q * scale + offset`.
    pub output_stage: Section,
    /// Activation RAM the runtime needs, bytes (two ping-pong i16 buffers of
    /// the widest layer).
    pub ram_bytes: u32,
    /// Multiply-accumulates per frame (all active experts of all layers).
    pub macs_per_frame: u32,
    /// Payload length in bytes.
    pub payload_len: u32,
    /// CRC-32 (ISO-HDLC, as zlib's `crc32`) of the payload bytes.
    pub payload_crc: u32,
}

#[cfg(feature = "defmt")]
impl defmt::Format for Header {
    fn format(&self, f: defmt::Formatter) {
        defmt::write!(
            f,
            "Header {{ kind: {}, gating: {}, in: {}, out: {}, layers: {}, ram: {}, macs: {}, payload: {} }}",
            self.kind,
            self.gating,
            self.input_dim,
            self.output_dim,
            self.layers.len(),
            self.ram_bytes,
            self.macs_per_frame,
            self.payload_len
        )
    }
}
