//! `Model`: a validated, zero-copy view of a blob.

use crate::blob::records::stage_record;
use crate::blob::{Framed, Gating, Header, LayerDesc, ModelKind, Section, STAGE_RECORD_LEN};
use crate::error::{Error, Result};
use crate::fixed::gate::Gate;
use crate::fixed::phase::Phase;
use crate::ops::common::{check_section, section};
use crate::ops::dense::DenseLayer;
use crate::ops::{GatedOp, Layer};

/// Layer index used in errors about the input and output stages.
pub const STAGE: u8 = 255;

/// A blob that passed every check: its header and its payload, borrowed.
///
/// Weights stay where the blob is (flash on a device); only the header
/// (a few hundred bytes) is copied out.
#[derive(Clone, Debug)]
pub struct Model<'a> {
    header: Header,
    payload: &'a [u8],
    blob_len: usize,
}

impl<'a> Model<'a> {
    /// Validates `blob` completely (framing, both CRCs, every section, every
    /// requantisation record, the accumulator bound of every row, the header's
    /// RAM and MAC figures). The slice must be exactly one blob.
    pub fn from_bytes(blob: &'a [u8]) -> Result<Self> {
        Self::load(blob, true)
    }

    /// Like [`Model::from_bytes`], for a blob at the start of a larger
    /// region (a flash partition): bytes after the blob are ignored.
    pub fn from_region(region: &'a [u8]) -> Result<Self> {
        Self::load(region, false)
    }

    fn load(bytes: &'a [u8], exact: bool) -> Result<Self> {
        let Framed {
            header,
            payload,
            blob_len,
        } = Framed::parse(bytes, exact)?;
        let model = Model {
            header,
            payload,
            blob_len,
        };
        model.validate()?;
        Ok(model)
    }

    /// The decoded header.
    pub fn header(&self) -> &Header {
        &self.header
    }

    /// Bytes of the whole blob.
    pub fn blob_len(&self) -> usize {
        self.blob_len
    }

    /// Width of the float input.
    pub fn input_dim(&self) -> usize {
        usize::from(self.header.input_dim)
    }

    /// Width of the float output.
    pub fn output_dim(&self) -> usize {
        usize::from(self.header.output_dim)
    }

    /// Activation RAM the model needs, bytes.
    pub fn ram_bytes(&self) -> usize {
        self.header.ram_bytes as usize
    }

    /// Elements (i16) each of the two activation buffers must hold.
    pub fn buffer_elements(&self) -> usize {
        max_width(&self.header.layers)
    }

    /// Multiply-accumulates per frame: a function of the header alone.
    pub fn macs_per_frame(&self) -> u32 {
        self.header.macs_per_frame
    }

    /// The gate of this model's gating at `phase`.
    pub fn gate(&self, phase: Phase) -> Gate {
        Gate::new(&self.header.gating, phase)
    }

    /// Dense layer `i` with its sections (`None` for other ops: see
    /// [`Model::kernel`]).
    pub fn layer(&self, i: usize) -> Option<DenseLayer<'a>> {
        match self.kernel(i)? {
            Layer::Dense(d) => Some(d),
            _ => None,
        }
    }

    /// Layer `i` of any op, bound to its sections, ready to run.
    pub fn kernel(&self, i: usize) -> Option<Layer<'a>> {
        Layer::new(self.payload, *self.header.layers.get(i)?, i as u8)
    }

    /// The payload bytes (CRC verified).
    pub fn payload(&self) -> &'a [u8] {
        self.payload
    }

    /// Number of layers.
    pub fn layer_count(&self) -> usize {
        self.header.layers.len()
    }

    /// Input-stage records (offset, scale), one per input.
    pub fn input_stage(&self) -> impl Iterator<Item = (f32, f32)> + 'a {
        stage(self.payload, self.header.input_stage)
    }

    /// Output-stage records (scale, offset), one per output.
    pub fn output_stage(&self) -> impl Iterator<Item = (f32, f32)> + 'a {
        stage(self.payload, self.header.output_stage)
    }

    fn validate(&self) -> Result<()> {
        let h = &self.header;
        if matches!(h.kind, ModelKind::Style { .. }) {
            return Err(Error::NotAModel);
        }
        let gated_experts = validate_gating(&h.gating)?;
        if h.layers.is_empty() || h.input_dim == 0 || h.output_dim == 0 {
            return Err(Error::UnsupportedParameter { layer: STAGE });
        }
        let mut width = h.input_dim;
        for (i, l) in h.layers.iter().enumerate() {
            let li = i as u8;
            if l.in_dim != width || l.out_dim == 0 {
                return Err(Error::DimensionMismatch { layer: li });
            }
            let want = if l.gated { gated_experts } else { 1 };
            if l.experts != want {
                return Err(Error::GatingMismatch { layer: li });
            }
            Layer::bind(self.payload, *l, li)?;
            width = l.out_dim;
        }
        if width != h.output_dim {
            return Err(Error::DimensionMismatch {
                layer: (h.layers.len() - 1) as u8,
            });
        }
        self.validate_stage(h.input_stage, h.input_dim)?;
        self.validate_stage(h.output_stage, h.output_dim)?;
        if u64::from(h.ram_bytes) != ram_bytes(&h.layers) as u64
            || u64::from(h.macs_per_frame) != macs(&h.gating, &h.layers)
        {
            return Err(Error::HeaderInconsistent);
        }
        for (i, l) in h.layers.iter().enumerate() {
            Layer::bind(self.payload, *l, i as u8)?.check(&h.gating)?;
        }
        Ok(())
    }

    fn validate_stage(&self, s: Section, dim: u16) -> Result<()> {
        check_section(self.payload, s, STAGE)?;
        if s.len as usize != usize::from(dim) * STAGE_RECORD_LEN {
            return Err(Error::SectionLength { layer: STAGE });
        }
        if stage(self.payload, s).any(|(a, b)| !a.is_finite() || !b.is_finite()) {
            return Err(Error::UnsupportedParameter { layer: STAGE });
        }
        Ok(())
    }
}

pub(crate) fn validate_gating(g: &Gating) -> Result<u16> {
    let ok = match *g {
        Gating::Single => true,
        Gating::Constant { tables } | Gating::Linear { tables } => tables >= 1,
        Gating::CatmullRom { points } => points >= 4,
    };
    if ok {
        Ok(g.experts())
    } else {
        Err(Error::UnsupportedParameter { layer: STAGE })
    }
}

fn stage(payload: &[u8], s: Section) -> impl Iterator<Item = (f32, f32)> + '_ {
    let bytes = section(payload, s).unwrap_or(&[]);
    bytes
        .as_chunks::<STAGE_RECORD_LEN>()
        .0
        .iter()
        .map(stage_record)
}

/// Widest activation vector of the network (input included; an op's
/// intermediate vector, such as a CP layer's middle, counts too).
pub fn max_width(layers: &[LayerDesc]) -> usize {
    layers
        .iter()
        .map(|l| usize::from(l.in_dim.max(l.out_dim)).max(Layer::scratch(l)))
        .max()
        .unwrap_or(0)
}

/// Activation RAM: two ping-pong i16 buffers of the widest layer.
pub fn ram_bytes(layers: &[LayerDesc]) -> usize {
    2 * max_width(layers) * core::mem::size_of::<i16>()
}

/// Multiply-accumulates per frame, summed over the layers ([`GatedOp::macs`]
/// of each op: dense `active x in x out`; CP `rank x (in + out + active)`;
/// diagonal `active x out`), `active` being 1 for ungated layers.
pub fn macs(gating: &Gating, layers: &[LayerDesc]) -> u64 {
    layers
        .iter()
        .map(|l| {
            let active = if l.gated { gating.active() } else { 1 } as u64;
            Layer::macs(l, active)
        })
        .sum()
}
