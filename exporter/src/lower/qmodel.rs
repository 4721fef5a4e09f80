//! The quantised model: integer weights, biases and requantisation
//! records per layer, the nodes that connect them, and the input and output
//! stages — what the quantiser makes and the encoder lays out as bytes.

use phasegate::blob::{
    GateSource, Gating, LayerDesc, ModelKind, RbfScale, Requant, Slice, SoftmaxDesc, Source,
    WeightFormat, MAX_NODES,
};
use phasegate::ops::cp::MidRecord;

/// Why a model cannot be encoded (a bug in the caller, not bad user input).
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum EncodeError {
    /// More nodes than a header holds.
    #[error("{0} nodes: a blob holds at most {MAX_NODES}")]
    TooManyNodes(usize),
    /// The wiring does not describe a valid graph (the runtime's check).
    #[error("the graph is invalid: {0}")]
    Graph(phasegate::Error),
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

/// The extra arrays of a CP layer.
#[derive(Clone, Debug, PartialEq)]
pub struct QCp {
    /// `A`: `out x rank` integer weights.
    pub a: Vec<i32>,
    /// `experts x rank` cores.
    pub cores: Vec<i16>,
    /// `rank` middle records.
    pub mid: Vec<MidRecord>,
}

/// One quantised layer of any op.
#[derive(Clone, Debug, PartialEq)]
pub struct QLayer {
    /// Descriptor; sections are filled in by [`crate::encode::encode`]. For CP layers
    /// `op` carries the rank.
    pub desc: LayerDesc,
    /// Dense: `experts x out x in`; CP: `B^T` (`rank x in`); diagonal:
    /// `experts x out`.
    pub weights: Vec<i32>,
    /// `experts x out` biases in accumulator units.
    pub bias: Vec<i64>,
    /// `out` requantisation records.
    pub requant: Vec<Requant>,
    /// CP arrays (CP layers only).
    pub cp: Option<QCp>,
    /// RBF arrays (RBF layers only).
    pub rbf: Option<QRbf>,
    /// Whether the layer is phase-gated when the model is a chain
    /// ([`Wiring::Chain`]); a graph's nodes name their gate source.
    pub gated: bool,
}

/// What a node of a [`Wiring::Graph`] computes.
#[derive(Clone, Debug, PartialEq)]
pub enum QNodeOp {
    /// Layer `i` of [`QModel::layers`].
    Layer(usize),
    /// A softmax gate.
    Softmax(SoftmaxDesc),
}

/// One node of a graph: its op, the slices it concatenates, its gate.
#[derive(Clone, Debug, PartialEq)]
pub struct QNode {
    /// The op.
    pub op: QNodeOp,
    /// Input slices, concatenated in order.
    pub inputs: Vec<Slice>,
    /// Where its expert coefficients come from.
    pub gate: GateSource,
}

/// How the layers of a [`QModel`] are connected.
#[derive(Clone, Debug, PartialEq)]
pub enum Wiring {
    /// Each layer reads the whole output of the one before (the first the
    /// input), phase-gated when [`QLayer::gated`]; the output is the last
    /// layer's.
    Chain,
    /// Any graph of layers and softmax gates.
    Graph {
        /// Nodes in evaluation order.
        nodes: Vec<QNode>,
        /// The model's output.
        output: Slice,
    },
}

/// What kind of blob to write.
#[derive(Clone, Debug, PartialEq)]
pub enum QKind {
    /// A runnable model of this kind (`Pfnn` or `Mlp`).
    Model(ModelKind),
    /// A style for the base with payload CRC `base_crc`, beside base layer
    /// `layer`.
    Style {
        /// Base payload CRC.
        base_crc: u32,
        /// Base layer index.
        layer: u8,
        /// Name (UTF-8, at most [`phasegate::blob::MAX_STYLE_NAME`] bytes).
        name: String,
    },
}

/// A quantised model or style, ready to encode.
#[derive(Clone, Debug, PartialEq)]
pub struct QModel {
    /// Model or style.
    pub kind: QKind,
    /// Gating.
    pub gating: Gating,
    /// `(offset, scale)` per input (empty for styles).
    pub input_stage: Vec<(f32, f32)>,
    /// `(scale, offset)` per output (empty for styles).
    pub output_stage: Vec<(f32, f32)>,
    /// Layers (exactly one, the adapter, for styles).
    pub layers: Vec<QLayer>,
    /// How they are connected (a style's one layer is a chain).
    pub wiring: Wiring,
}

impl QModel {
    /// The graph of the model: its nodes and output, a chain spelled out.
    pub fn graph(&self) -> (Vec<QNode>, Slice) {
        match &self.wiring {
            Wiring::Graph { nodes, output } => (nodes.clone(), *output),
            Wiring::Chain => {
                let mut nodes = Vec::new();
                let mut source = Source::Input;
                for (i, l) in self.layers.iter().enumerate() {
                    nodes.push(QNode {
                        op: QNodeOp::Layer(i),
                        inputs: vec![Slice {
                            source,
                            start: 0,
                            len: l.desc.in_dim,
                        }],
                        gate: if l.gated {
                            GateSource::Phase
                        } else {
                            GateSource::None
                        },
                    });
                    source = Source::Node(i as u8);
                }
                let len = self.layers.last().map_or(0, |l| l.desc.out_dim);
                (
                    nodes,
                    Slice {
                        source,
                        start: 0,
                        len,
                    },
                )
            }
        }
    }
}

/// The RBF op's arrays beside its centres.
#[derive(Clone, Debug, PartialEq)]
pub struct QRbf {
    /// `experts x out` scale records.
    pub scales: Vec<RbfScale>,
    /// `in` alignment shifts.
    pub align: Vec<u8>,
}

/// "int8" or "int16".
pub fn format_name(w: WeightFormat) -> &'static str {
    match w {
        WeightFormat::I8 | WeightFormat::I8Interleaved => "int8",
        WeightFormat::I16 => "int16",
    }
}
