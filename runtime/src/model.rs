//! `Model`: a validated, zero-copy view of a blob.

use crate::blob::records::stage_record;
use crate::blob::{
    AccWidth, Activation, Framed, Gating, Header, LayerDesc, LayerOp, ModelKind, Requant, Section,
    REQUANT_RECORD_LEN, STAGE_RECORD_LEN,
};
use crate::error::{Error, Result};
use crate::fixed::gate::Gate;
use crate::fixed::phase::Phase;
use crate::kernels::cp::MID_RECORD_LEN;
use crate::kernels::dense::DenseLayer;
use crate::kernels::layer::Kernel;

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
        let desc = *self.header.layers.get(i)?;
        if desc.op != LayerOp::Dense {
            return None;
        }
        Some(DenseLayer {
            desc,
            weights: section(self.payload, desc.weight_section)?,
            bias: section(self.payload, desc.bias_section)?,
            requant: section(self.payload, desc.requant_section)?,
            index: i as u8,
        })
    }

    /// Layer `i` of any op (dense, CP, diagonal), ready to run.
    pub fn kernel(&self, i: usize) -> Option<Kernel<'a>> {
        let desc = *self.header.layers.get(i)?;
        Kernel::new(self.payload, desc, i as u8)
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
            validate_sections(self.payload, li, l)?;
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
            validate_values(self.payload, &h.gating, l, i as u8)?;
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

/// Checks that every section of layer `l` lies in the payload, is aligned
/// and has the length its dimensions imply.
pub(crate) fn validate_sections(payload: &[u8], li: u8, l: &LayerDesc) -> Result<()> {
    let experts = u64::from(l.experts);
    let (out, inp) = (u64::from(l.out_dim), u64::from(l.in_dim));
    let wb = l.weights.bytes() as u64;
    let common = [
        (l.bias_section, experts * out * l.acc.bytes() as u64),
        (l.requant_section, out * REQUANT_RECORD_LEN as u64),
    ];
    let check = |list: &[(Section, u64)]| -> Result<()> {
        for &(s, len) in list {
            check_section(payload, s, li)?;
            if u64::from(s.len) != len {
                return Err(Error::SectionLength { layer: li });
            }
        }
        Ok(())
    };
    match l.op {
        LayerOp::Dense => {
            check(&[(l.weight_section, experts * out * inp * wb)])?;
        }
        LayerOp::Cp {
            rank,
            a,
            cores,
            mid,
        } => {
            if rank == 0 {
                return Err(Error::UnsupportedParameter { layer: li });
            }
            let r = u64::from(rank);
            check(&[
                (l.weight_section, r * inp * wb),
                (a, out * r * wb),
                (cores, experts * r * 2),
                (mid, r * MID_RECORD_LEN as u64),
            ])?;
        }
        LayerOp::Diagonal => {
            if l.in_dim != l.out_dim {
                return Err(Error::DimensionMismatch { layer: li });
            }
            check(&[(l.weight_section, experts * out * wb)])?;
        }
    }
    check(&common)
}

/// Value checks of a layer: requantisation records in range, and the
/// overflow proof. Dense layers with 32-bit accumulators: `sum |w| * 2^15
/// <= i32::MAX` for every row (activations are i16, so |x| <= 2^15 whatever
/// the input); CP layers: see [`crate::kernels::cp::CpLayer::check`];
/// diagonal layers need none (`|w x| <= 2^30`).
pub(crate) fn validate_values(
    payload: &[u8],
    gating: &Gating,
    l: &LayerDesc,
    li: u8,
) -> Result<()> {
    let kernel = Kernel::new(payload, *l, li).ok_or(Error::SectionOutOfBounds { layer: li })?;
    match kernel {
        Kernel::Cp(cp) => cp.check(gating),
        Kernel::Diagonal(d) => check_requant(d.requant, l.activation, li),
        Kernel::Dense(d) => {
            check_requant(d.requant, l.activation, li)?;
            if l.acc != AccWidth::I32 {
                return Ok(());
            }
            let rows = usize::from(l.experts) * usize::from(l.out_dim);
            for r in 0..rows {
                let l1 = row_l1(&d, r).ok_or(Error::SectionLength { layer: li })?;
                if l1 << 15 > i32::MAX as u64 {
                    let row = (r % usize::from(l.out_dim.max(1))) as u16;
                    return Err(Error::AccumulatorOverflow { layer: li, row });
                }
            }
            Ok(())
        }
    }
}

/// Requantisation records in range: reserved byte zero, shifts at most
/// [`Requant::MAX_SHIFT`], ELU formats at most Q15.
fn check_requant(requant: &[u8], activation: Activation, li: u8) -> Result<()> {
    for rec in requant.as_chunks::<REQUANT_RECORD_LEN>().0 {
        let r = Requant::from_bytes(rec).ok_or(Error::UnsupportedParameter { layer: li })?;
        let elu_frac_bad = activation == Activation::Elu && r.frac > 15;
        if r.pre_shift > Requant::MAX_SHIFT || r.post_shift > Requant::MAX_SHIFT || elu_frac_bad {
            return Err(Error::UnsupportedParameter { layer: li });
        }
    }
    Ok(())
}

/// `sum |w|` of flat row `r` (expert-major).
fn row_l1(layer: &DenseLayer<'_>, r: usize) -> Option<u64> {
    let wb = layer.desc.weights.bytes();
    let rb = usize::from(layer.desc.in_dim) * wb;
    let row = layer.weights.get(r * rb..(r + 1) * rb)?;
    Some(match wb {
        1 => row
            .iter()
            .map(|&b| u64::from((b as i8).unsigned_abs()))
            .sum(),
        _ => row
            .as_chunks::<2>()
            .0
            .iter()
            .map(|c| u64::from(i16::from_le_bytes(*c).unsigned_abs()))
            .sum(),
    })
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

fn check_section(payload: &[u8], s: Section, layer: u8) -> Result<()> {
    match s.end() {
        Some(end) if end as usize <= payload.len() && s.offset.is_multiple_of(4) => Ok(()),
        _ => Err(Error::SectionOutOfBounds { layer }),
    }
}

fn section(payload: &[u8], s: Section) -> Option<&[u8]> {
    payload.get(s.offset as usize..s.end()? as usize)
}

fn stage(payload: &[u8], s: Section) -> impl Iterator<Item = (f32, f32)> + '_ {
    let bytes = section(payload, s).unwrap_or(&[]);
    bytes
        .as_chunks::<STAGE_RECORD_LEN>()
        .0
        .iter()
        .map(stage_record)
}

/// Widest activation vector of the network (input included; the middle
/// vector of a CP layer counts too).
pub fn max_width(layers: &[LayerDesc]) -> usize {
    layers
        .iter()
        .map(|l| {
            let rank = match l.op {
                LayerOp::Cp { rank, .. } => rank,
                _ => 0,
            };
            usize::from(l.in_dim.max(l.out_dim).max(rank))
        })
        .max()
        .unwrap_or(0)
}

/// Activation RAM: two ping-pong i16 buffers of the widest layer.
pub fn ram_bytes(layers: &[LayerDesc]) -> usize {
    2 * max_width(layers) * core::mem::size_of::<i16>()
}

/// Multiply-accumulates per frame, summed over the layers: dense
/// `active x in x out`; CP `rank x (in + out + active)` (the two factor
/// products and the core blend); diagonal `active x out`.
pub fn macs(gating: &Gating, layers: &[LayerDesc]) -> u64 {
    layers
        .iter()
        .map(|l| {
            let active = if l.gated { gating.active() } else { 1 } as u64;
            let (inp, out) = (u64::from(l.in_dim), u64::from(l.out_dim));
            match l.op {
                LayerOp::Dense => active * inp * out,
                LayerOp::Cp { rank, .. } => u64::from(rank) * (inp + out + active),
                LayerOp::Diagonal => active * out,
            }
        })
        .sum()
}
