//! What every op shares: binding sections of the payload, the output-row
//! records (requantisation + activation) with their load-time checks, and
//! small readers of little-endian tables.

use crate::blob::{Activation, LayerDesc, Requant, Section, WeightFormat, REQUANT_RECORD_LEN};
use crate::error::{Error, Result};
use crate::fixed::elu::elu_q;
use crate::fixed::{round_shift_sat_i16, round_shift_sat_i32};

/// A section lies inside `payload` and starts 4-aligned
/// (`SectionOutOfBounds { layer }` otherwise).
pub(crate) fn check_section(payload: &[u8], s: Section, layer: u8) -> Result<()> {
    match s.end() {
        Some(end) if end as usize <= payload.len() && s.offset.is_multiple_of(4) => Ok(()),
        _ => Err(Error::SectionOutOfBounds { layer }),
    }
}

/// The bytes of `s`, or `None` when it lies outside `payload`.
pub(crate) fn section(payload: &[u8], s: Section) -> Option<&[u8]> {
    payload.get(s.offset as usize..s.end()? as usize)
}

/// Binds the sections of one layer, in the order the op lists them: each
/// must lie in the payload, be 4-aligned (`SectionOutOfBounds`) and have
/// exactly its expected length (`SectionLength`).
pub(crate) struct Sections<'a> {
    payload: &'a [u8],
    layer: u8,
}

impl<'a> Sections<'a> {
    /// Sections of layer `layer` of `payload`.
    pub(crate) fn new(payload: &'a [u8], layer: u8) -> Self {
        Sections { payload, layer }
    }

    /// Section `s`, which must be `len` bytes long.
    pub(crate) fn get(&self, s: Section, len: u64) -> Result<&'a [u8]> {
        check_section(self.payload, s, self.layer)?;
        if u64::from(s.len) != len {
            return Err(Error::SectionLength { layer: self.layer });
        }
        section(self.payload, s).ok_or(Error::SectionOutOfBounds { layer: self.layer })
    }

    /// The two sections every op has, after its own: `experts x out`
    /// biases (`acc` wide) and `out` requantisation records.
    pub(crate) fn rows(&self, desc: &LayerDesc) -> Result<(&'a [u8], &'a [u8])> {
        let out = u64::from(desc.out_dim);
        let bias = self.get(
            desc.bias_section,
            u64::from(desc.experts) * out * desc.acc.bytes() as u64,
        )?;
        let requant = self.get(desc.requant_section, out * REQUANT_RECORD_LEN as u64)?;
        Ok((bias, requant))
    }
}

/// Refuses a layer with an empty input or output (kernels iterate over
/// rows of `in_dim` weights).
pub(crate) fn check_dims(desc: &LayerDesc, layer: u8) -> Result<()> {
    if desc.in_dim == 0 || desc.out_dim == 0 {
        return Err(Error::DimensionMismatch { layer });
    }
    Ok(())
}

/// `sat16(round(sat32(round(total >> pre)) * m >> post))`: the
/// requantisation of one output row (both roundings half up).
#[inline(always)]
pub fn requantise(total: i64, r: &Requant) -> i16 {
    let t = i64::from(round_shift_sat_i32(total, r.pre_shift));
    round_shift_sat_i16(t * i64::from(r.multiplier), r.post_shift)
}

/// The last step of every op's output row: requantise the blended Q16
/// total with the row's record, then apply the layer's activation at the
/// row's format. The loader has validated every record, so an unreadable one
/// cannot occur; it would give 0 rather than a panic.
#[inline(always)]
pub(crate) fn finish_row(
    total: i64,
    record: &[u8; REQUANT_RECORD_LEN],
    activation: Activation,
) -> i16 {
    let r = Requant::from_bytes(record).unwrap_or(Requant {
        multiplier: 0,
        pre_shift: 0,
        post_shift: 0,
        frac: 0,
    });
    let q = requantise(total, &r);
    match activation {
        Activation::Identity => q,
        Activation::Elu => elu_q(q, r.frac),
    }
}

/// [`finish_row`] as one out-of-line function, for ops whose rows are few
/// and costly anyway (diagonal, RBF): one copy of the requantisation and
/// the ELU instead of one inlined into each of their loops.
#[inline(never)]
pub(crate) fn finish_row_outlined(
    total: i64,
    record: &[u8; REQUANT_RECORD_LEN],
    activation: Activation,
) -> i16 {
    finish_row(total, record, activation)
}

/// Load-time check of one output-row record: reserved byte zero, shifts
/// at most [`Requant::MAX_SHIFT`], an ELU row's format at most Q15
/// (`UnsupportedParameter { layer }` otherwise).
pub(crate) fn requant_record(
    rec: &[u8; REQUANT_RECORD_LEN],
    activation: Activation,
    layer: u8,
) -> Result<Requant> {
    let bad = Error::UnsupportedParameter { layer };
    let r = Requant::from_bytes(rec).ok_or(bad)?;
    let elu_frac_bad = activation == Activation::Elu && r.frac > 15;
    if r.pre_shift > Requant::MAX_SHIFT || r.post_shift > Requant::MAX_SHIFT || elu_frac_bad {
        return Err(bad);
    }
    Ok(r)
}

/// [`requant_record`] of every record of a layer, in order.
pub(crate) fn check_requant(requant: &[u8], activation: Activation, layer: u8) -> Result<()> {
    for rec in requant.as_chunks::<REQUANT_RECORD_LEN>().0 {
        requant_record(rec, activation, layer)?;
    }
    Ok(())
}

/// `sum_j |w_j|` of a row of weights (in any order, padding included).
pub(crate) fn row_l1(row: &[u8], format: WeightFormat) -> u64 {
    match format {
        WeightFormat::I8 | WeightFormat::I8Interleaved => row
            .iter()
            .map(|&b| u64::from((b as i8).unsigned_abs()))
            .sum(),
        WeightFormat::I16 => row
            .as_chunks::<2>()
            .0
            .iter()
            .map(|c| u64::from(i16::from_le_bytes(*c).unsigned_abs()))
            .sum(),
    }
}

/// Largest `sum_j |w_j| * 2^15` a dot product with a 32-bit accumulator may
/// have: every i16 input then keeps every partial sum inside i32.
pub(crate) const I32_ROW_BOUND: u64 = i32::MAX as u64;

/// The `i`-th little-endian i16 of `bytes`.
#[inline(always)]
pub(crate) fn i16_at(bytes: &[u8], i: usize) -> Option<i16> {
    let b = bytes.get(i.checked_mul(2)?..)?.first_chunk::<2>()?;
    Some(i16::from_le_bytes(*b))
}

/// The error of an output buffer shorter than `needed`.
pub(crate) fn too_small(needed: usize, capacity: usize) -> Error {
    Error::BufferTooSmall {
        needed: needed as u32,
        capacity: capacity as u32,
    }
}

/// The error of an input shorter than `expected`.
pub(crate) fn too_short(expected: usize, found: usize) -> Error {
    Error::LengthMismatch {
        expected: expected as u32,
        found: found as u32,
    }
}
