//! The header's data model, shared by the exporter (which writes it) and the
//! runtime (which reads it). Its wire format is postcard; see
//! `docs/blob-format.md` for the byte-level specification.
//!
//! Enums only ever grow at the end, so a newer minor revision of the format
//! still decodes old blobs (postcard encodes variants as varint indices).

#![deny(clippy::arithmetic_side_effects)]

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

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
    /// A rig: the rig-specific nodes of a graph (an OMG autoencoder and the
    /// output node reading its decoder) for one motion blob, loaded beside
    /// it (see `docs/graph-format.md`, "Rig blobs"). Its node table is the
    /// whole graph of the combination: the nodes of `nodes` have their
    /// sections in this blob's payload, every other node is the motion
    /// blob's node of the same index, op for op, its sections in the
    /// motion blob's payload. `input_stage` and `output_stage` are the
    /// rig's own, in this payload. (With the runtime's `rig` feature only;
    /// without it such a header does not decode.)
    #[cfg(feature = "rig")]
    Rig {
        /// `payload_crc` of the motion blob this rig was built for.
        base_crc: u32,
        /// Bit `i` set: node `i` is the rig's (at most [`MAX_NODES`] bits).
        nodes: u32,
        /// The rig's name, UTF-8, at most [`MAX_STYLE_NAME`] bytes.
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
    #[inline]
    pub fn experts(&self) -> u16 {
        match *self {
            Gating::Single => 1,
            Gating::Constant { tables } | Gating::Linear { tables } => tables,
            Gating::CatmullRom { points } => points,
            Gating::Softmax { experts } => experts,
        }
    }

    /// How many experts are active (non-zero gate) in one frame at most.
    #[inline]
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
    /// `I8` in the order the Cortex-M4 DSP kernel reads (dense layers
    /// only): each row padded with zeros to a multiple of 4 bytes, each
    /// group of 4 weights `w0 w1 w2 w3` stored `w0 w2 w1 w3`, so that
    /// `SXTB16` of a word gives `(w0, w1)` and `SXTB16 ROR 8` `(w2, w3)`,
    /// the activations' pair order.
    I8Interleaved,
}

impl WeightFormat {
    /// Bytes per weight.
    #[inline]
    pub fn bytes(&self) -> usize {
        match self {
            WeightFormat::I8 | WeightFormat::I8Interleaved => 1,
            WeightFormat::I16 => 2,
        }
    }

    /// Bytes of a stored row of `len` weights (`I8Interleaved` pads to 4).
    #[inline]
    pub fn row_bytes(&self, len: usize) -> usize {
        match self {
            WeightFormat::I8Interleaved => len.checked_next_multiple_of(4).unwrap_or(usize::MAX),
            WeightFormat::I8 | WeightFormat::I16 => len.saturating_mul(self.bytes()),
        }
    }

    /// Where in its row (counted in weights) weight `j` is stored. For
    /// `I8Interleaved` this swaps the middle two of every group of 4, so
    /// it is its own inverse: storage slot `s` holds weight `position(s)`.
    #[inline]
    pub fn position(&self, j: usize) -> usize {
        match self {
            WeightFormat::I8Interleaved => (j & !3) | ((j & 1) << 1) | ((j >> 1) & 1),
            WeightFormat::I8 | WeightFormat::I16 => j,
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
    #[inline]
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
    /// Gaussian radial basis functions (OMG's RBF-CAT clustering layer):
    /// `psi_kj = 2^31 exp(-sigma_kj^2 |x - c_kj|^2)` in place of `W_k x`.
    /// `weight_section` holds the centres `c` (`experts x out_dim x
    /// in_dim`, `weights` format, each element in its input's format).
    Rbf {
        /// `experts x out_dim` scale records, 8 bytes each
        /// ([`crate::blob::RbfScale`]).
        scales: Section,
        /// `in_dim` bytes: input `i`'s squared differences are shifted left
        /// by twice this (at most 15), which brings every input to the
        /// finest input format.
        align: Section,
    },
    /// Student-t soft assignment (OMG's DEC clustering layer, alpha = 1):
    /// `psi_kj = 2^31 q_kj`, `q_kj = t_kj / sum_l t_kl` with `t_kj = 1 /
    /// (1 + u_kj)`, `u_kj` the squared distance of the input to centre
    /// `c_kj` as the RBF op computes it (the same sections: `weight_section`
    /// holds the centres, `scales` the `experts x out_dim` scale records,
    /// `align` the `in_dim` alignment shifts), normalised over each
    /// expert's `out_dim` centres. (With the runtime's `dec` feature only;
    /// without it such a layer does not decode.)
    #[cfg(feature = "dec")]
    Dec {
        /// `experts x out_dim` scale records, 8 bytes each
        /// ([`crate::blob::RbfScale`]).
        scales: Section,
        /// `in_dim` bytes, as [`LayerOp::Rbf`]'s.
        align: Section,
    },
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
    #[inline]
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
    #[allow(clippy::arithmetic_side_effects)] // two u16 in a u32: cannot overflow
    #[inline]
    pub fn end(&self) -> u32 {
        u32::from(self.offset) + u32::from(self.len)
    }

    /// Whether the two spans share an element (empty spans share none).
    #[inline]
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
    #[inline]
    pub fn layer(&self) -> Option<&LayerDesc> {
        match &self.op {
            NodeOp::Layer(d) => Some(d),
            NodeOp::Softmax(_) => None,
        }
    }

    /// Width of the node's input vector.
    #[inline]
    pub fn in_dim(&self) -> u16 {
        match &self.op {
            NodeOp::Layer(d) => d.in_dim,
            NodeOp::Softmax(s) => s.experts,
        }
    }

    /// Width of the node's output vector (0 for a softmax gate).
    #[inline]
    pub fn out_dim(&self) -> u16 {
        match &self.op {
            NodeOp::Layer(d) => d.out_dim,
            NodeOp::Softmax(_) => 0,
        }
    }
}

/// The node table the exporter writes and host code edits.
pub type NodeVec = heapless::Vec<Node, MAX_NODES>;

/// The blob header: everything the runtime needs before touching the payload.
///
/// `N` is how the nodes are held: a [`NodeVec`] (the default; what the
/// exporter builds and serialises) or, in a loaded blob, a [`NodeTable`]
/// that leaves them in the blob's bytes and decodes one when it is used,
/// so a loaded header costs a few dozen bytes of RAM, not 24 decoded nodes.
#[derive(Clone, Debug, Eq, PartialEq, Serialize, Deserialize)]
pub struct Header<N = NodeVec> {
    /// Network family.
    pub kind: ModelKind,
    /// Phase gating of the nodes whose gate source is [`GateSource::Phase`].
    pub gating: Gating,
    /// Width of the model's float input.
    pub input_dim: u16,
    /// Width of the model's float output.
    pub output_dim: u16,
    /// Nodes in evaluation order: a node reads only the input and earlier nodes.
    pub nodes: N,
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
impl<N: Nodes> defmt::Format for Header<N> {
    fn format(&self, f: defmt::Formatter) {
        defmt::write!(
            f,
            "Header {{ kind: {}, gating: {}, in: {}, out: {}, nodes: {}, ram: {}, macs: {}, payload: {} }}",
            self.kind,
            self.gating,
            self.input_dim,
            self.output_dim,
            self.nodes.count(),
            self.ram_bytes,
            self.macs_per_frame,
            self.payload_len
        )
    }
}

/// Read access to a header's nodes, however they are held.
pub trait Nodes {
    /// How many nodes there are.
    fn count(&self) -> usize;

    /// Node `i`, or `None` past the last one.
    fn node(&self, i: usize) -> Option<Node>;

    /// The nodes in evaluation order.
    fn each(&self) -> impl Iterator<Item = Node> + '_ {
        (0..self.count()).map_while(|i| self.node(i))
    }
}

impl Nodes for [Node] {
    #[inline]
    fn count(&self) -> usize {
        self.len()
    }

    fn node(&self, i: usize) -> Option<Node> {
        self.get(i).cloned()
    }
}

impl<const M: usize> Nodes for heapless::Vec<Node, M> {
    #[inline]
    fn count(&self) -> usize {
        self.len()
    }

    fn node(&self, i: usize) -> Option<Node> {
        self.get(i).cloned()
    }
}

/// The nodes of a loaded header, left in their postcard bytes (zero-copy):
/// [`Header::parse`] decodes each once to check it and keeps where it
/// starts; [`Nodes::node`] decodes it again when it is used.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
pub struct NodeTable<'a> {
    bytes: &'a [u8],
    /// Where node `i` starts in `bytes`; entry `count` is the table's end.
    starts: [u16; MAX_NODES + 1],
    count: u8,
}

impl Nodes for NodeTable<'_> {
    #[inline]
    fn count(&self) -> usize {
        usize::from(self.count)
    }

    fn node(&self, i: usize) -> Option<Node> {
        if i >= self.count() {
            return None;
        }
        let from = usize::from(*self.starts.get(i)?);
        // Cannot overflow: i < count <= MAX_NODES.
        #[allow(clippy::arithmetic_side_effects)]
        let to = usize::from(*self.starts.get(i + 1)?);
        postcard::from_bytes(self.bytes.get(from..to)?).ok()
    }
}

impl NodeTable<'_> {
    /// How many nodes there are.
    pub fn len(&self) -> usize {
        self.count()
    }

    /// Whether there are none (a loaded model has at least one).
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// The nodes in evaluation order, each decoded as it is reached.
    pub fn iter(&self) -> impl Iterator<Item = Node> + '_ {
        self.each()
    }

    /// The nodes, decoded into a [`NodeVec`] (for host tools that edit them).
    pub fn to_vec(&self) -> NodeVec {
        self.each().collect()
    }
}

/// The header fields before the node table, in wire order.
type Prefix = (ModelKind, Gating, u16, u16);
/// The header fields after the node table, in wire order.
type Suffix = (Span, Slice, Section, Section, u32, u32, u32, u32);

impl<'a> Header<NodeTable<'a>> {
    /// Decodes the postcard bytes of a header (exactly one, nothing after
    /// it), checking every node decodes but leaving them in `bytes`.
    pub fn parse(bytes: &'a [u8]) -> Result<Self> {
        let bad = |_: postcard::Error| Error::HeaderMalformed;
        let (prefix, rest) = postcard::take_from_bytes::<Prefix>(bytes).map_err(bad)?;
        // The node count is a varint; up to MAX_NODES (< 128) it is one byte.
        let (&count, table) = rest.split_first().ok_or(Error::HeaderMalformed)?;
        let count = usize::from(count);
        if count > MAX_NODES {
            return Err(Error::HeaderMalformed);
        }
        let mut starts = [0u16; MAX_NODES + 1];
        let mut rest = table;
        for i in 1..=count {
            rest = postcard::take_from_bytes::<Node>(rest).map_err(bad)?.1;
            if let Some(s) = starts.get_mut(i) {
                *s = u16::try_from(table.len().saturating_sub(rest.len()))
                    .map_err(|_| Error::HeaderMalformed)?;
            }
        }
        // `rest` is a suffix of `table`: the difference never saturates.
        let table = table
            .get(..table.len().saturating_sub(rest.len()))
            .ok_or(Error::HeaderMalformed)?;
        let (suffix, rest) = postcard::take_from_bytes::<Suffix>(rest).map_err(bad)?;
        if !rest.is_empty() {
            return Err(Error::HeaderMalformed);
        }
        let (kind, gating, input_dim, output_dim) = prefix;
        let (
            input,
            output,
            input_stage,
            output_stage,
            ram_bytes,
            macs_per_frame,
            payload_len,
            payload_crc,
        ) = suffix;
        Ok(Header {
            kind,
            gating,
            input_dim,
            output_dim,
            nodes: NodeTable {
                bytes: table,
                starts,
                count: count as u8,
            },
            input,
            output,
            input_stage,
            output_stage,
            ram_bytes,
            macs_per_frame,
            payload_len,
            payload_crc,
        })
    }

    /// The same header with its nodes decoded (for host tools that edit
    /// or re-encode it).
    pub fn decoded(&self) -> Header {
        Header {
            kind: self.kind,
            gating: self.gating,
            input_dim: self.input_dim,
            output_dim: self.output_dim,
            nodes: self.nodes.to_vec(),
            input: self.input,
            output: self.output,
            input_stage: self.input_stage,
            output_stage: self.output_stage,
            ram_bytes: self.ram_bytes,
            macs_per_frame: self.macs_per_frame,
            payload_len: self.payload_len,
            payload_crc: self.payload_crc,
        }
    }
}

#[cfg(test)]
#[allow(clippy::arithmetic_side_effects)] // test fixtures, not blob input
mod tests {
    use super::*;

    fn node(i: u16) -> Node {
        Node {
            op: NodeOp::Softmax(SoftmaxDesc {
                experts: 1 + i % 8,
                frac: (i % 16) as u8,
            }),
            inputs: (0..1 + i % 4)
                .map(|k| Slice {
                    source: if k == 0 {
                        Source::Input
                    } else {
                        Source::Node(k as u8)
                    },
                    start: 300 * i + k,
                    len: 7 * k + 1,
                })
                .collect(),
            gate: GateSource::None,
            input: Span {
                offset: 200 * i,
                len: i,
            },
            scratch: Span::default(),
            output: Span { offset: i, len: 0 },
        }
    }

    fn header(nodes: usize) -> Header {
        Header {
            kind: ModelKind::Graph,
            gating: Gating::CatmullRom { points: 4 },
            input_dim: 342,
            output_dim: 311,
            nodes: (0..nodes as u16).map(node).collect(),
            input: Span {
                offset: 0,
                len: 342,
            },
            output: Slice {
                source: Source::Node(1),
                start: 0,
                len: 311,
            },
            input_stage: Section { offset: 0, len: 8 },
            output_stage: Section { offset: 8, len: 16 },
            ram_bytes: 70_000,
            macs_per_frame: 1 << 30,
            payload_len: 123_456,
            payload_crc: 0xdead_beef,
        }
    }

    #[test]
    fn the_table_decodes_what_the_exporter_wrote() {
        for n in [0, 1, 3, MAX_NODES] {
            let h = header(n);
            let bytes = postcard::to_allocvec(&h).unwrap();
            let view = Header::parse(&bytes).unwrap();
            assert_eq!(view.nodes.len(), n);
            assert_eq!(view.decoded(), h);
            for i in 0..n {
                assert_eq!(view.nodes.node(i), Some(h.nodes[i].clone()));
            }
            assert_eq!(view.nodes.node(n), None);
        }
    }

    #[test]
    fn a_damaged_table_is_refused_at_parse() {
        let bytes = postcard::to_allocvec(&header(3)).unwrap();
        for cut in 0..bytes.len() {
            assert_eq!(
                Header::parse(&bytes[..cut]),
                Err(Error::HeaderMalformed),
                "{cut}"
            );
        }
        let mut long = bytes.clone();
        long.push(0);
        assert_eq!(Header::parse(&long), Err(Error::HeaderMalformed));
        // More nodes than MAX_NODES: the count follows the four leading fields.
        let mut h = header(1);
        let bytes = postcard::to_allocvec(&h).unwrap();
        let prefix: Prefix = (h.kind, h.gating, h.input_dim, h.output_dim);
        let at = postcard::to_allocvec(&prefix).unwrap().len();
        assert_eq!(bytes[at], 1);
        let mut many = bytes.clone();
        many[at] = (MAX_NODES + 1) as u8;
        assert_eq!(Header::parse(&many), Err(Error::HeaderMalformed));
        // The same count of 1 as a two-byte varint.
        let mut long_count = bytes.clone();
        long_count.splice(at..=at, [0x81, 0x00]);
        assert_eq!(Header::parse(&long_count), Err(Error::HeaderMalformed));
        h.nodes.clear();
        assert!(Header::parse(&postcard::to_allocvec(&h).unwrap()).is_ok());
    }
}
