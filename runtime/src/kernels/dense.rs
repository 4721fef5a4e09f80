//! The phase-gated dense layer: `y = act(requant(sum_k g_k (W_k x + b_k)))`.
//!
//! For each output row the active experts' dot products are taken in one
//! pass over `x` (one accumulator per expert), then blended by the Q16 gate
//! and requantised once: the blended weight matrix never exists.

use crate::blob::records::bias_at;
use crate::blob::{AccWidth, Activation, LayerDesc, Requant, WeightFormat, REQUANT_RECORD_LEN};
use crate::error::{Error, Result};
use crate::fixed::elu::elu_q;
use crate::fixed::gate::{Gate, MAX_ACTIVE};
use crate::fixed::{round_shift, sat_i16, sat_i32};

/// A validated layer: its descriptor and its payload sections.
#[derive(Clone, Copy, Debug)]
pub struct DenseLayer<'a> {
    /// The header's description.
    pub desc: LayerDesc,
    /// `experts x out x in` weights.
    pub weights: &'a [u8],
    /// `experts x out` biases.
    pub bias: &'a [u8],
    /// `out` requantisation records.
    pub requant: &'a [u8],
    /// Position in the network, for error reports.
    pub index: u8,
}

/// Element type of a weight row.
trait Weight {
    fn row(bytes: &[u8]) -> impl Iterator<Item = i32> + '_;
}

struct W8;
struct W16;

impl Weight for W8 {
    #[inline(always)]
    fn row(bytes: &[u8]) -> impl Iterator<Item = i32> + '_ {
        bytes.iter().map(|&b| i32::from(b as i8))
    }
}

impl Weight for W16 {
    #[inline(always)]
    fn row(bytes: &[u8]) -> impl Iterator<Item = i32> + '_ {
        bytes
            .as_chunks::<2>()
            .0
            .iter()
            .map(|c| i32::from(i16::from_le_bytes(*c)))
    }
}

/// A dot-product accumulator. `w * x` of an i16 weight and an i16
/// activation always fits an i32 (|w x| <= 2^30).
trait Acc: Copy {
    const ZERO: Self;
    fn mac(self, product: i32) -> Self;
    fn widen(self) -> i64;
}

impl Acc for i32 {
    const ZERO: Self = 0;
    /// Cannot wrap: the loader proved `sum |w| * 2^15 <= i32::MAX` for every row.
    #[inline(always)]
    fn mac(self, product: i32) -> Self {
        self.wrapping_add(product)
    }
    #[inline(always)]
    fn widen(self) -> i64 {
        i64::from(self)
    }
}

impl Acc for i64 {
    const ZERO: Self = 0;
    #[inline(always)]
    fn mac(self, product: i32) -> Self {
        self.wrapping_add(i64::from(product))
    }
    #[inline(always)]
    fn widen(self) -> i64 {
        self
    }
}

#[inline(always)]
fn dot1<W: Weight, A: Acc>(r: [&[u8]; 1], x: &[i16]) -> [A; 1] {
    let mut a = A::ZERO;
    for (w, &v) in W::row(r[0]).zip(x) {
        a = a.mac(w * i32::from(v));
    }
    [a]
}

#[inline(always)]
fn dot2<W: Weight, A: Acc>(r: [&[u8]; 2], x: &[i16]) -> [A; 2] {
    let (mut a0, mut a1) = (A::ZERO, A::ZERO);
    for ((w0, w1), &v) in W::row(r[0]).zip(W::row(r[1])).zip(x) {
        let v = i32::from(v);
        a0 = a0.mac(w0 * v);
        a1 = a1.mac(w1 * v);
    }
    [a0, a1]
}

#[inline(always)]
fn dot4<W: Weight, A: Acc>(r: [&[u8]; 4], x: &[i16]) -> [A; 4] {
    let (mut a0, mut a1, mut a2, mut a3) = (A::ZERO, A::ZERO, A::ZERO, A::ZERO);
    let rows = W::row(r[0])
        .zip(W::row(r[1]))
        .zip(W::row(r[2]))
        .zip(W::row(r[3]));
    for ((((w0, w1), w2), w3), &v) in rows.zip(x) {
        let v = i32::from(v);
        a0 = a0.mac(w0 * v);
        a1 = a1.mac(w1 * v);
        a2 = a2.mac(w2 * v);
        a3 = a3.mac(w3 * v);
    }
    [a0, a1, a2, a3]
}

/// `sat16(round(sat32(round(total >> pre)) * m >> post))`.
#[inline(always)]
pub fn requantise(total: i64, r: &Requant) -> i16 {
    let t = i64::from(sat_i32(round_shift(total, r.pre_shift)));
    sat_i16(round_shift(t * i64::from(r.multiplier), r.post_shift))
}

/// The last step of every gated kernel's output row: requantise the blended
/// Q16 total with the row's record, then apply the layer's activation at the
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

impl<'a> DenseLayer<'a> {
    fn row_bytes(&self) -> usize {
        usize::from(self.desc.in_dim) * self.desc.weights.bytes()
    }

    /// Weight row `row` of expert `expert`.
    fn row(&self, expert: u16, row: usize) -> Result<&'a [u8]> {
        let rb = self.row_bytes();
        let start = (usize::from(expert) * usize::from(self.desc.out_dim) + row) * rb;
        self.weights
            .get(start..start + rb)
            .ok_or(Error::SectionLength { layer: self.index })
    }

    /// Runs the layer: `x` has `in_dim` elements, `y` at least `out_dim`.
    pub fn run(&self, gate: &Gate, x: &[i16], y: &mut [i16]) -> Result<()> {
        match (self.desc.weights, self.desc.acc) {
            (WeightFormat::I8, AccWidth::I32) => self.run_typed::<W8, i32>(gate, x, y),
            (WeightFormat::I8, AccWidth::I64) => self.run_typed::<W8, i64>(gate, x, y),
            (WeightFormat::I16, AccWidth::I32) => self.run_typed::<W16, i32>(gate, x, y),
            (WeightFormat::I16, AccWidth::I64) => self.run_typed::<W16, i64>(gate, x, y),
        }
    }

    fn run_typed<W: Weight, A: Acc>(&self, gate: &Gate, x: &[i16], y: &mut [i16]) -> Result<()> {
        let out = usize::from(self.desc.out_dim);
        let x = x
            .get(..usize::from(self.desc.in_dim))
            .ok_or(Error::LengthMismatch {
                expected: u32::from(self.desc.in_dim),
                found: x.len() as u32,
            })?;
        let capacity = y.len() as u32;
        let y = y.get_mut(..out).ok_or(Error::BufferTooSmall {
            needed: u32::from(self.desc.out_dim),
            capacity,
        })?;
        let mut experts = [0u16; MAX_ACTIVE];
        let mut coefs = [0i64; MAX_ACTIVE];
        for (slot, (e, w)) in gate.iter().enumerate().take(MAX_ACTIVE) {
            if let (Some(es), Some(cs)) = (experts.get_mut(slot), coefs.get_mut(slot)) {
                (*es, *cs) = (e, i64::from(w));
            }
        }
        let n = gate.len();
        let bias_width = self.desc.acc.bytes();
        let records = self.requant.as_chunks::<REQUANT_RECORD_LEN>().0;
        for (i, (yi, rec)) in y.iter_mut().zip(records).enumerate() {
            let [e0, e1, e2, e3] = experts;
            let accs: [i64; MAX_ACTIVE] = match n {
                1 => {
                    let [a] = dot1::<W, A>([self.row(e0, i)?], x);
                    [a.widen(), 0, 0, 0]
                }
                2 => {
                    let [a, b] = dot2::<W, A>([self.row(e0, i)?, self.row(e1, i)?], x);
                    [a.widen(), b.widen(), 0, 0]
                }
                _ => {
                    let rows = [
                        self.row(e0, i)?,
                        self.row(e1, i)?,
                        self.row(e2, i)?,
                        self.row(e3, i)?,
                    ];
                    dot4::<W, A>(rows, x).map(Acc::widen)
                }
            };
            let mut total = 0i64;
            for ((&e, &g), &acc) in experts.iter().zip(&coefs).zip(&accs).take(n) {
                let b = bias_at(self.bias, bias_width, usize::from(e) * out + i).unwrap_or(0);
                total = total.saturating_add(acc.saturating_add(b).saturating_mul(g));
            }
            *yi = finish_row(total, rec, self.desc.activation);
        }
        Ok(())
    }
}
