//! The header's data model, shared by the exporter (which writes it) and the
//! runtime (which reads it). Its wire format is postcard; see
//! `docs/blob-format.md` for the byte-level specification.
//!
//! Enums only ever grow at the end, so a newer minor revision of the format
//! still decodes old blobs (postcard encodes variants as varint indices).

use serde::{Deserialize, Serialize};

/// Most nodes a graph may hold (the PFNN has 3; OMG has 15 to 20).
pub const MAX_NODES: usize = 24;

/// Most slices a node's input may be concatenated from.
pub const MAX_NODE_INPUTS: usize = 4;

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
    /// Any other graph (OMG-shaped networks and the like): a network the
    /// locomotion controller does not drive.
    Graph,
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
    /// Not a phase gating: the coefficients of the layers a softmax gate
    /// node drives ([`GateSource::Node`]), all `experts` of them active,
    /// non-negative and summing to exactly one. Never a header's `gating`;
    /// the loader derives it for each layer the gate feeds.
    Softmax {
        /// Number of experts (logits), at most 8.
        experts: u16,
    },
}

impl Gating {
    /// How many experts each gated layer must have.
    pub fn experts(&self) -> u16 {
        match *self {
            Gating::Single => 1,
            Gating::Constant { tables } | Gating::Linear { tables } => tables,
            Gating::CatmullRom { points } => points,
            Gating::Softmax { experts } => experts,
        }
    }

    /// How many experts are active (non-zero gate) in one frame at most.
    pub fn active(&self) -> usize {
        match *self {
            Gating::Single | Gating::Constant { .. } => 1,
            Gating::Linear { .. } => 2,
            Gating::CatmullRom { .. } => 4,
            Gating::Softmax { experts } => usize::from(experts),
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
    /// Expert count; must equal the node's gate source's (`1` for
    /// ungated layers).
    pub experts: u16,
    /// Weight storage.
    pub weights: WeightFormat,
    /// Accumulator and bias width.
    pub acc: AccWidth,
    /// Non-linearity.
    pub activation: Activation,
    /// `experts x out_dim x in_dim` weights, row-major, little-endian.
    pub weight_section: Section,
    /// `experts x out_dim` biases in accumulator units (`acc` wide, LE).
    pub bias_section: Section,
    /// `out_dim` requantisation records, 8 bytes each (multiplier, shifts
    /// and the row's activation format: scales are per row, and the next
    /// layer's weights absorb them per column).
    pub requant_section: Section,
}

/// Where a slice of a node's input comes from.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Source {
    /// The quantised model input.
    Input,
    /// The output of an earlier node (its index).
    Node(u8),
}

/// Elements `start..start + len` of a source.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Slice {
    /// The vector the slice is taken from.
    pub source: Source,
    /// First element.
    pub start: u16,
    /// Number of elements.
    pub len: u16,
}

/// Where a node's expert coefficients come from.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum GateSource {
    /// Ungated: one expert, weight 1.
    None,
    /// The header's phase gating.
    Phase,
    /// The coefficients an earlier softmax gate node computed this frame.
    Node(u8),
}

/// A range of the activation arena, in i16 elements.
#[derive(Clone, Copy, Debug, Default, Eq, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Span {
    /// First element.
    pub offset: u16,
    /// Number of elements.
    pub len: u16,
}

impl Span {
    /// One past the last element.
    pub fn end(&self) -> u32 {
        u32::from(self.offset) + u32::from(self.len)
    }

    /// Whether the two spans share an element (empty spans share none).
    pub fn overlaps(&self, other: &Span) -> bool {
        self.len > 0
            && other.len > 0
            && u32::from(self.offset) < other.end()
            && u32::from(other.offset) < self.end()
    }
}

/// A softmax gate: its input (the logits, one per expert, all in Q`frac`)
/// becomes the Q16 coefficients of the layers whose gate source it is.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct SoftmaxDesc {
    /// Number of logits and experts, `1..=8`.
    pub experts: u16,
    /// Fraction bits of the logits (at most 15); every row that produces
    /// one must have this format.
    pub frac: u8,
}

/// What a node computes.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum NodeOp {
    /// A gated layer of any [`LayerOp`].
    Layer(LayerDesc),
    /// A softmax gate; its output is a gate, not a vector in the arena.
    Softmax(SoftmaxDesc),
}

/// One node of the graph, with its place in the arena plan.
///
/// Before the op runs, the node's `inputs` are concatenated into `input`
/// (no copy when `inputs` is one slice already at `input`); the op reads
/// `input`, keeps its intermediate vector in `scratch` and writes `output`.
#[derive(Clone, Debug, Eq, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Node {
    /// The op.
    pub op: NodeOp,
    /// Slices concatenated, in order, into the node's input vector.
    pub inputs: heapless::Vec<Slice, MAX_NODE_INPUTS>,
    /// Where the expert coefficients come from.
    pub gate: GateSource,
    /// Arena range of the concatenated input.
    pub input: Span,
    /// Arena range of the op's intermediate vector (empty for one-stage ops).
    pub scratch: Span,
    /// Arena range of the output (empty for a softmax gate).
    pub output: Span,
}

impl Node {
    /// The layer descriptor, for a layer node.
    pub fn layer(&self) -> Option<&LayerDesc> {
        match &self.op {
            NodeOp::Layer(d) => Some(d),
            NodeOp::Softmax(_) => None,
        }
    }

    /// Width of the node's input vector.
    pub fn in_dim(&self) -> u16 {
        match &self.op {
            NodeOp::Layer(d) => d.in_dim,
            NodeOp::Softmax(s) => s.experts,
        }
    }

    /// Width of the node's output vector (0 for a softmax gate).
    pub fn out_dim(&self) -> u16 {
        match &self.op {
            NodeOp::Layer(d) => d.out_dim,
            NodeOp::Softmax(_) => 0,
        }
    }
}

/// The blob header: everything the runtime needs before touching the payload.
#[derive(Clone, Debug, Eq, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// Network family.
    pub kind: ModelKind,
    /// Phase gating of the nodes whose gate source is [`GateSource::Phase`].
    pub gating: Gating,
    /// Width of the model's float input.
    pub input_dim: u16,
    /// Width of the model's float output.
    pub output_dim: u16,
    /// Nodes in evaluation order: a node reads only the input and earlier nodes.
    pub nodes: heapless::Vec<Node, MAX_NODES>,
    /// Arena range of the quantised model input.
    pub input: Span,
    /// The model's output: a slice of a node's output.
    pub output: Slice,
    /// `input_dim` records (offset f32, scale f32): `q = round((x - offset) * scale)`.
    pub input_stage: Section,
    /// `output_dim` records (scale f32, offset f32): `y = q * scale + offset`.
    pub output_stage: Section,
    /// Bytes of the activation arena: exactly twice the largest end of any
    /// span of the plan.
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
            "Header {{ kind: {}, gating: {}, in: {}, out: {}, nodes: {}, ram: {}, macs: {}, payload: {} }}",
            self.kind,
            self.gating,
            self.input_dim,
            self.output_dim,
            self.nodes.len(),
            self.ram_bytes,
            self.macs_per_frame,
            self.payload_len
        )
    }
}
