//! Styles: small blobs of residual adapters that change how a base model
//! moves without touching it (the few-shot styles paper, eq. 4):
//!
//! ```text
//! h1 = ELU(W1(p) h0 + b1 + W_res(p) h0 + b_res(p))
//! ```
//!
//! A style blob has the model blob's framing (magic, version, both CRCs)
//! and a header of kind [`ModelKind::Style`]: the payload CRC of the base
//! blob it was built for, the index of the base layer node it sits beside,
//! a name, and a graph of one layer node reading the whole input, the
//! adapter, ungated or phase-gated, whose op gives its form: `Dense` (full),
//! `Diagonal`, or `Cp` (`W_res(p) = A diag(d(p)) B^T`, the paper's choice).
//! The adapter reads the base layer's input in the base's activation formats
//! and writes, with identity activation, in the base layer's output formats,
//! so its output adds to the base layer's pre-activation in i16 before the
//! base layer's own activation.
//!
//! [`crate::Runtime`] runs one base model with any number of styles from
//! separate flash regions (its `S` and `N` parameters): it refuses a style
//! built for another base ([`Error::StyleMismatch`]) and switches or blends
//! styles between frames ([`Mix`]).

/// The blend weight of [`Mix::Blend`]: `fixed`'s `U1F15`, `[0, 2)` in steps
/// of 2^-15 (weights above 1 act as 1).
pub use fixed::types::U1F15 as BlendWeight;

use fixed::types::U1F15;

use crate::blob::{
    Activation, Framed, GateSource, Gating, ModelKind, NodeOp, Nodes, Section, Source,
    MAX_STYLE_NAME,
};
use crate::error::{Error, Result};
use crate::fixed::gate::ONE;
use crate::graph::{check_plan, check_structure};
use crate::model::{macs, node_gating, validate_gating, STAGE};
use crate::ops::{GatedOp, Layer};

/// Handle of a style in a [`crate::Runtime`]'s bank.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct StyleId(pub u8);

/// Which adapters a frame uses.
#[derive(Clone, Copy, Debug, Default, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Mix {
    /// No adapter: the base model alone.
    #[default]
    Base,
    /// One style.
    One(StyleId),
    /// Two styles, their adapter outputs interpolated:
    /// `r = (1 - weight) r_from + weight r_to`, `weight` clamped to `[0, 1]`.
    Blend {
        /// Style at weight 0.
        from: StyleId,
        /// Style at weight 1.
        to: StyleId,
        /// Interpolation weight.
        #[cfg_attr(feature = "defmt", defmt(Debug2Format))]
        weight: U1F15,
    },
}

impl Mix {
    /// The active styles with their Q16 weights.
    pub(crate) fn weights(&self) -> [(Option<StyleId>, i64); 2] {
        let one = i64::from(ONE);
        match *self {
            Mix::Base => [(None, 0), (None, 0)],
            Mix::One(s) => [(Some(s), one), (None, 0)],
            Mix::Blend { from, to, weight } => {
                let w = (i64::from(weight.to_bits()) << 1).min(one);
                [(Some(from), one - w), (Some(to), w)]
            }
        }
    }
}

/// A validated style blob, borrowed (its weights stay where the blob is).
#[derive(Clone, Copy, Debug)]
pub struct Style<'a> {
    kernel: Layer<'a>,
    gate: GateSource,
    gating: Gating,
    name: &'a str,
    base_crc: u32,
    layer: u8,
    payload_crc: u32,
    blob_len: usize,
}

impl<'a> Style<'a> {
    /// Validates a style blob completely (framing, CRCs, header, the
    /// adapter's sections, records and overflow proof); the slice must be
    /// exactly one blob.
    pub fn from_bytes(blob: &'a [u8]) -> Result<Self> {
        Self::load(blob, true)
    }

    /// Like [`Style::from_bytes`] for a blob at the start of a larger flash
    /// region: bytes after the blob are ignored.
    pub fn from_region(region: &'a [u8]) -> Result<Self> {
        Self::load(region, false)
    }

    fn load(bytes: &'a [u8], exact: bool) -> Result<Self> {
        let Framed {
            header,
            payload,
            blob_len,
        } = Framed::parse(bytes, exact)?;
        let ModelKind::Style {
            base_crc,
            layer,
            name,
        } = header.kind
        else {
            return Err(Error::NotAStyle);
        };
        validate_gating(&header.gating)?;
        check_structure(&header)?;
        let node = match header.nodes.count() {
            1 => header
                .nodes
                .node(0)
                .ok_or(Error::GraphInvalid { node: 0 })?,
            _ => return Err(Error::UnsupportedParameter { layer: STAGE }),
        };
        let (NodeOp::Layer(desc), [input]) = (&node.op, node.inputs.as_slice()) else {
            return Err(Error::UnsupportedParameter { layer: 0 });
        };
        if input.source != Source::Input || matches!(node.gate, GateSource::Node(_)) {
            return Err(Error::UnsupportedParameter { layer: 0 });
        }
        if desc.experts != node_gating(&header.gating, &header.nodes, &node).experts() {
            return Err(Error::GatingMismatch { layer: 0 });
        }
        if desc.activation != Activation::Identity {
            return Err(Error::UnsupportedParameter { layer: 0 });
        }
        let kernel = Layer::bind(payload, *desc, 0)?;
        let empty = Section::default();
        if (header.input_stage, header.output_stage) != (empty, empty) {
            return Err(Error::UnsupportedParameter { layer: STAGE });
        }
        let name = name_str(payload, name)?;
        check_plan(&header)?;
        if u64::from(header.macs_per_frame) != macs(&header) {
            return Err(Error::HeaderInconsistent);
        }
        kernel.check(&node_gating(&header.gating, &header.nodes, &node))?;
        let gate = node.gate;
        Ok(Style {
            kernel,
            gate,
            gating: header.gating,
            name,
            base_crc,
            layer,
            payload_crc: header.payload_crc,
            blob_len,
        })
    }

    /// The style's name.
    pub fn name(&self) -> &'a str {
        self.name
    }

    /// Payload CRC-32 of the base blob this style was built for.
    pub fn base_crc(&self) -> u32 {
        self.base_crc
    }

    /// Payload CRC-32 of this style blob.
    pub fn payload_crc(&self) -> u32 {
        self.payload_crc
    }

    /// Index of the base layer the adapter sits beside.
    pub fn layer(&self) -> u8 {
        self.layer
    }

    /// The adapter.
    pub fn kernel(&self) -> &Layer<'a> {
        &self.kernel
    }

    /// Whether the adapter is phase-gated ([`GateSource::Phase`]) or not
    /// ([`GateSource::None`]).
    pub fn gate(&self) -> GateSource {
        self.gate
    }

    /// Gating the style was built with (the base model's).
    pub fn gating(&self) -> Gating {
        self.gating
    }

    /// Bytes of the whole blob.
    pub fn blob_len(&self) -> usize {
        self.blob_len
    }

    /// Scratch elements the styled runtime needs for this style (two
    /// adapter outputs, for blending, plus a CP adapter's middle vector).
    pub fn scratch_elements(&self) -> usize {
        2 * usize::from(self.kernel.desc().out_dim) + self.kernel.scratch_elements()
    }

    /// Multiply-accumulates the adapter adds to a frame.
    pub fn macs_per_frame(&self) -> u64 {
        let active = match self.gate {
            GateSource::Phase => self.gating.active(),
            _ => 1,
        };
        Layer::macs(self.kernel.desc(), active as u64)
    }
}

pub(crate) fn name_str(payload: &[u8], s: Section) -> Result<&str> {
    let bad = Error::UnsupportedParameter { layer: STAGE };
    let end = s.end().ok_or(Error::SectionOutOfBounds { layer: STAGE })?;
    let bytes = payload
        .get(s.offset as usize..end as usize)
        .ok_or(Error::SectionOutOfBounds { layer: STAGE })?;
    if bytes.len() > MAX_STYLE_NAME {
        return Err(bad);
    }
    core::str::from_utf8(bytes).map_err(|_| bad)
}
