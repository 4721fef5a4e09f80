//! The model blob: framing, header and payload sections.
//!
//! ```text
//! offset 0   magic "PGMB"
//!        4   format version, u16 LE
//!        6   header length H, u16 LE
//!        8   CRC-32 of bytes 0..8 followed by the H header bytes, u32 LE
//!       12   header, postcard, H bytes
//! 12 + H     zero padding up to the next multiple of 16
//!        P   payload (length and CRC-32 in the header), sections 4-aligned
//! ```

mod framing;
mod header;
pub mod records;
#[cfg(feature = "self-test")]
pub mod self_test;

pub use framing::{
    blob_len_from_prefix, crc32, header_from_prefix, Framed, FORMAT_VERSION, MAGIC, PAYLOAD_ALIGN,
    PREAMBLE_LEN,
};
pub use header::{
    AccWidth, Activation, GateSource, Gating, Header, LayerDesc, LayerOp, ModelKind, Node, NodeOp,
    NodeTable, NodeVec, Nodes, Section, Slice, SoftmaxDesc, Source, Span, WeightFormat, MAX_NODES,
    MAX_NODE_INPUTS, MAX_STYLE_NAME,
};
pub use records::{
    RbfScale, Requant, MAX_OUTPUT_OFFSET, MAX_OUTPUT_SCALE, RBF_SCALE_RECORD_LEN,
    REQUANT_RECORD_LEN, STAGE_RECORD_LEN,
};
#[cfg(feature = "self-test")]
pub use self_test::{
    SelfTest, MAX_SELF_TEST_VECTORS, SELF_TEST_FOOTER_LEN, SELF_TEST_MAGIC, SELF_TEST_VERSION,
};
