//! The one error type of the runtime.

use core::fmt;

/// Everything that can go wrong when loading a blob or running a frame.
///
/// Loading validates the whole blob, so after `phasegate::Model::from_bytes`
/// succeeds, the only errors a frame can return are about its arguments.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum Error {
    /// The blob is shorter than its preamble, header or declared payload.
    Truncated {
        /// Bytes the blob needs.
        needed: u32,
        /// Bytes there are.
        available: u32,
    },
    /// The first four bytes are not `PGMB`: this is not a phasegate blob.
    BadMagic,
    /// The blob was written by a format version this runtime cannot read.
    UnsupportedVersion {
        /// Version in the blob.
        found: u16,
        /// Version this runtime reads.
        supported: u16,
    },
    /// Bytes follow the payload: the slice is longer than the blob it holds
    /// (use `phasegate::Model::from_region` for a flash region).
    TrailingBytes {
        /// Length of the blob the header declares.
        blob_len: u32,
        /// Length of the slice given.
        found: u32,
    },
    /// The header's CRC-32 does not match: the header bytes are damaged.
    HeaderCorrupt,
    /// The header passed its CRC but does not decode: written by a broken tool.
    HeaderMalformed,
    /// The payload's CRC-32 does not match: the weights are damaged.
    PayloadCorrupt,
    /// A section lies outside the payload or is not 4-byte aligned.
    SectionOutOfBounds {
        /// Index of the layer that owns the section (`255` for the input/output stages).
        layer: u8,
    },
    /// A section's length does not match the dimensions the header declares.
    SectionLength {
        /// Index of the layer (`255` for the input/output stages).
        layer: u8,
    },
    /// Layer dimensions do not chain (a layer's input width differs from the
    /// previous layer's output width, or the ends differ from the model's).
    DimensionMismatch {
        /// Index of the first layer that does not fit.
        layer: u8,
    },
    /// The number of experts of a layer does not fit the gating scheme.
    GatingMismatch {
        /// Index of the layer.
        layer: u8,
    },
    /// A layer parameter is out of the supported range (zero width, a shift
    /// of 63 or more, an ELU format finer than Q15, no layers, ...).
    UnsupportedParameter {
        /// Index of the layer (`255` for model-level parameters).
        layer: u8,
    },
    /// A row's weights are too large for a 32-bit accumulator: the
    /// no-overflow guarantee cannot be proven for this blob.
    AccumulatorOverflow {
        /// Index of the layer.
        layer: u8,
        /// Index of the row.
        row: u16,
    },
    /// The header's RAM or MAC figure differs from what its layers imply.
    HeaderInconsistent,
    /// The activation buffers are smaller than the model needs.
    BufferTooSmall {
        /// Elements (i16) per buffer the model needs.
        needed: u32,
        /// Elements (i16) per buffer there are.
        capacity: u32,
    },
    /// An input or output slice has the wrong length.
    LengthMismatch {
        /// Length the model needs.
        expected: u32,
        /// Length given.
        found: u32,
    },
    /// An input value or phase is NaN or infinite.
    NonFinite {
        /// Index of the first offending value.
        index: u32,
    },
    /// The blob is a style (adapter) or rig blob where a model was expected.
    NotAModel,
    /// The blob is a model where a style (adapter) blob was expected.
    NotAStyle,
    /// The style was built for another base model: its recorded base CRC
    /// differs from the base blob's payload CRC.
    StyleMismatch {
        /// Payload CRC-32 of the base model in use.
        base_crc: u32,
        /// Base CRC-32 the style was built for.
        style_crc: u32,
    },
    /// The style's adapter does not fit the base model's layer (index,
    /// dimensions, gating or output formats differ).
    StyleIncompatible {
        /// Base layer the style targets.
        layer: u8,
    },
    /// The style bank is full.
    TooManyStyles {
        /// Styles the runtime holds at most.
        capacity: u32,
    },
    /// A style index that was never returned by `add_style`.
    UnknownStyle {
        /// The index given.
        index: u32,
    },
    /// A node reads something that is not defined before it: a later node,
    /// a slice past the end of its source, a softmax gate's (vectorless)
    /// output, or a gate source that is not a softmax gate node.
    GraphInvalid {
        /// Index of the node (`255` for the model's output).
        node: u8,
    },
    /// The arena plan puts two buffers that are live at the same time on
    /// the same elements, or a buffer past the arena's end.
    ArenaOverlap {
        /// Index of the node whose buffers collide (`255` for the input).
        node: u8,
    },
    /// The blob is not a rig blob where one was expected.
    #[cfg(feature = "rig")]
    NotARig,
    /// The rig was built for another motion blob: its recorded base CRC
    /// differs from the motion blob's payload CRC.
    #[cfg(feature = "rig")]
    RigMismatch {
        /// Payload CRC-32 of the motion blob in use.
        motion_crc: u32,
        /// Payload CRC-32 of the motion blob the rig was built for.
        rig_crc: u32,
    },
    /// The rig's graph does not fit the motion blob at this node: a motion
    /// node that differs from the motion blob's, a rig node that is not a
    /// layer or past the graph, another gating, or an interface whose
    /// formats differ (input-stage records of a slice a motion node reads,
    /// the row formats of a rig node a motion node reads).
    #[cfg(feature = "rig")]
    RigIncompatible {
        /// Index of the node (`255` for the header).
        node: u8,
    },
    /// The payload ends with the self-test footer (`PGST`), but the
    /// section is not as it states: another self-test version, no vectors
    /// or more than 1,024, dimensions other than the model's, or records
    /// misaligned or not inside the payload before the footer.
    #[cfg(feature = "self-test")]
    SelfTestMalformed,
    /// A stored self-test vector did not give its expected output: the
    /// runtime on this device computes something else than the one that
    /// wrote the blob.
    #[cfg(feature = "self-test")]
    SelfTestFailed {
        /// Index of the vector (0-based, stored order).
        vector: u16,
        /// Index of the first output that differs.
        output: u16,
        /// The output stored in the blob.
        expected: i16,
        /// The output computed here.
        got: i16,
    },
}

/// Result with the runtime's [`Error`].
pub type Result<T> = core::result::Result<T, Error>;

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Error::Truncated { needed, available } => {
                write!(f, "blob truncated: needs {needed} bytes, has {available}")
            }
            Error::BadMagic => f.write_str("not a phasegate model blob (bad magic)"),
            Error::UnsupportedVersion { found, supported } => write!(
                f,
                "blob format version {found} is not supported (this runtime reads version {supported})"
            ),
            Error::TrailingBytes { blob_len, found } => write!(
                f,
                "{found} bytes given but the blob is {blob_len} bytes long"
            ),
            Error::HeaderCorrupt => f.write_str("blob header is corrupt (CRC-32 mismatch)"),
            Error::HeaderMalformed => f.write_str("blob header does not decode"),
            Error::PayloadCorrupt => f.write_str("blob payload is corrupt (CRC-32 mismatch)"),
            Error::SectionOutOfBounds { layer } => {
                write!(f, "section of layer {layer} lies outside the payload or is misaligned")
            }
            Error::SectionLength { layer } => {
                write!(f, "section of layer {layer} has the wrong length for its dimensions")
            }
            Error::DimensionMismatch { layer } => {
                write!(f, "layer {layer} dimensions do not chain with its neighbours")
            }
            Error::GatingMismatch { layer } => {
                write!(f, "layer {layer} expert count does not fit the gating")
            }
            Error::UnsupportedParameter { layer } => {
                write!(f, "layer {layer} has a parameter out of the supported range")
            }
            Error::AccumulatorOverflow { layer, row } => write!(
                f,
                "layer {layer} row {row} could overflow its 32-bit accumulator"
            ),
            Error::HeaderInconsistent => {
                f.write_str("header RAM or MAC figures differ from its nodes")
            }
            Error::BufferTooSmall { needed, capacity } => write!(
                f,
                "activation buffers too small: model needs {needed} elements, runtime has {capacity}"
            ),
            Error::LengthMismatch { expected, found } => {
                write!(f, "slice length {found}, model needs {expected}")
            }
            Error::NonFinite { index } => write!(f, "value {index} is NaN or infinite"),
            Error::NotAModel => f.write_str(
                "blob is a style (adapter) or rig blob, not a model: load it beside its base",
            ),
            Error::NotAStyle => f.write_str("blob is a model, not a style (adapter) blob"),
            Error::StyleMismatch {
                base_crc,
                style_crc,
            } => write!(
                f,
                "style was built for the base model with payload CRC {style_crc:#010x}, \
                 but the base model in use has payload CRC {base_crc:#010x}"
            ),
            Error::StyleIncompatible { layer } => write!(
                f,
                "style adapter does not fit layer {layer} of the base model"
            ),
            Error::TooManyStyles { capacity } => {
                write!(f, "style bank full: it holds at most {capacity} styles")
            }
            Error::UnknownStyle { index } => write!(f, "no style with index {index}"),
            Error::GraphInvalid { node } => write!(
                f,
                "node {node} reads an input or gate that is not defined before it"
            ),
            Error::ArenaOverlap { node } => write!(
                f,
                "arena plan of node {node} overlaps a live buffer or leaves the arena"
            ),
            #[cfg(feature = "rig")]
            Error::NotARig => f.write_str("blob is not a rig blob"),
            #[cfg(feature = "rig")]
            Error::RigMismatch { motion_crc, rig_crc } => write!(
                f,
                "rig was built for the motion blob with payload CRC {rig_crc:#010x}, \
                 but the motion blob in use has payload CRC {motion_crc:#010x}"
            ),
            #[cfg(feature = "rig")]
            Error::RigIncompatible { node } => write!(
                f,
                "rig does not fit the motion blob at node {node} (op, gating or interface formats differ)"
            ),
            #[cfg(feature = "self-test")]
            Error::SelfTestMalformed => f.write_str(
                "the blob's self-test section is malformed (version, count, dimensions or records)",
            ),
            #[cfg(feature = "self-test")]
            Error::SelfTestFailed {
                vector,
                output,
                expected,
                got,
            } => write!(
                f,
                "self-test vector {vector} output {output}: expected {expected}, got {got}"
            ),
        }
    }
}

impl core::error::Error for Error {}
