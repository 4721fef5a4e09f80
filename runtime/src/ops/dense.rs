//! The phase-gated dense layer: `y = act(requant(sum_k g_k (W_k x + b_k)))`.
//!
//! For each output row the active experts' dot products are taken in one
//! pass over `x` (one accumulator per expert), then blended by the Q16 gate
//! and requantised once: the blended weight matrix never exists.

use super::common::{
    check_dims, check_requant, finish_row, row_l1, too_short, too_small, Sections, I32_ROW_BOUND,
};
use super::GatedOp;
use crate::blob::records::bias_at;
use crate::blob::{AccWidth, Gating, LayerDesc, WeightFormat, REQUANT_RECORD_LEN};
use crate::error::{Error, Result};
use crate::fixed::gate::{Gate, MAX_ACTIVE};

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

#[cfg(any(test, phasegate_dsp))]
mod dsp;
/// The on-target self-test of the DSP kernels (`kernel-check` feature).
#[cfg(all(feature = "kernel-check", phasegate_dsp))]
pub use dsp::check::kernel_check;

/// Storage order of a weight row, and the inputs in the same order.
trait Weight {
    /// The row's stored weights, in storage order.
    fn row(bytes: &[u8]) -> impl Iterator<Item = i32> + '_;
    /// The inputs each stored weight meets, in storage order (0 against
    /// padding).
    fn xs(x: &[i16]) -> impl Iterator<Item = i32> + '_;
}

/// `WeightFormat::I8`.
struct W8;
/// `WeightFormat::I8Interleaved`.
struct W8I;
/// `WeightFormat::I16`.
struct W16;
/// `WeightFormat::I16` read by the kernels with 64-bit accumulators (the
/// same rows; a separate name selects the `SMLALD` loops).
struct W16L;

#[inline(always)]
fn plain(x: &[i16]) -> impl Iterator<Item = i32> + '_ {
    x.iter().map(|&v| i32::from(v))
}

impl Weight for W8 {
    #[inline(always)]
    fn row(bytes: &[u8]) -> impl Iterator<Item = i32> + '_ {
        bytes.iter().map(|&b| i32::from(b as i8))
    }
    #[inline(always)]
    fn xs(x: &[i16]) -> impl Iterator<Item = i32> + '_ {
        plain(x)
    }
}

impl Weight for W8I {
    #[inline(always)]
    fn row(bytes: &[u8]) -> impl Iterator<Item = i32> + '_ {
        W8::row(bytes)
    }
    /// Storage slot `s` holds weight `position(s)` (the order is its own
    /// inverse); slots past `in_dim` are padding.
    #[inline(always)]
    fn xs(x: &[i16]) -> impl Iterator<Item = i32> + '_ {
        let f = WeightFormat::I8Interleaved;
        (0..f.row_bytes(x.len())).map(move |s| x.get(f.position(s)).map_or(0, |&v| i32::from(v)))
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
    #[inline(always)]
    fn xs(x: &[i16]) -> impl Iterator<Item = i32> + '_ {
        plain(x)
    }
}

impl Weight for W16L {
    #[inline(always)]
    fn row(bytes: &[u8]) -> impl Iterator<Item = i32> + '_ {
        W16::row(bytes)
    }
    #[inline(always)]
    fn xs(x: &[i16]) -> impl Iterator<Item = i32> + '_ {
        plain(x)
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
    /// Cannot wrap: the loader proved `sum |w| * 2^15 <= i32::MAX` for
    /// every row. (Were it to, wrapping addition is exact modulo 2^32 in
    /// any order, so every kernel would still agree bit for bit.)
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

/// The model's multiply-accumulates among `steps` steps over `x` of
/// `rows` rows: a layout's padding slots (past `x`) multiply zeros.
#[inline(always)]
fn model_macs(steps: usize, x: &[i16], rows: usize) -> usize {
    steps.min(x.len()) * rows
}

#[inline(always)]
fn dot1<W: Weight, A: Acc>(r: [&[u8]; 1], x: &[i16]) -> [A; 1] {
    let mut a = A::ZERO;
    let mut n = 0;
    for (w, v) in W::row(r[0]).zip(W::xs(x)) {
        a = a.mac(w * v);
        n += 1;
    }
    crate::mac_count::add(model_macs(n, x, 1));
    [a]
}

#[inline(always)]
fn dot2<W: Weight, A: Acc>(r: [&[u8]; 2], x: &[i16]) -> [A; 2] {
    let (mut a0, mut a1) = (A::ZERO, A::ZERO);
    let mut n = 0;
    for ((w0, w1), v) in W::row(r[0]).zip(W::row(r[1])).zip(W::xs(x)) {
        a0 = a0.mac(w0 * v);
        a1 = a1.mac(w1 * v);
        n += 1;
    }
    crate::mac_count::add(model_macs(n, x, 2));
    [a0, a1]
}

#[inline(always)]
fn dot4<W: Weight, A: Acc>(r: [&[u8]; 4], x: &[i16]) -> [A; 4] {
    let (mut a0, mut a1, mut a2, mut a3) = (A::ZERO, A::ZERO, A::ZERO, A::ZERO);
    let rows = W::row(r[0])
        .zip(W::row(r[1]))
        .zip(W::row(r[2]))
        .zip(W::row(r[3]));
    let mut n = 0;
    for ((((w0, w1), w2), w3), v) in rows.zip(W::xs(x)) {
        a0 = a0.mac(w0 * v);
        a1 = a1.mac(w1 * v);
        a2 = a2.mac(w2 * v);
        a3 = a3.mac(w3 * v);
        n += 1;
    }
    crate::mac_count::add(model_macs(n, x, 4));
    [a0, a1, a2, a3]
}

/// The dot products of one pass over `x`: 1, 2 or 4 experts' rows (each
/// `row_bytes` long) against the same inputs.
trait Kernel {
    fn dot1(r: [&[u8]; 1], x: &[i16]) -> [i64; 1];
    fn dot2(r: [&[u8]; 2], x: &[i16]) -> [i64; 2];
    fn dot4(r: [&[u8]; 4], x: &[i16]) -> [i64; 4];
}

/// The portable kernel: the reference, and the kernel of every target
/// without the DSP extension.
struct Portable<W, A>(core::marker::PhantomData<(W, A)>);

impl<W: Weight, A: Acc> Kernel for Portable<W, A> {
    #[inline(always)]
    fn dot1(r: [&[u8]; 1], x: &[i16]) -> [i64; 1] {
        dot1::<W, A>(r, x).map(Acc::widen)
    }
    #[inline(always)]
    fn dot2(r: [&[u8]; 2], x: &[i16]) -> [i64; 2] {
        dot2::<W, A>(r, x).map(Acc::widen)
    }
    #[inline(always)]
    fn dot4(r: [&[u8]; 4], x: &[i16]) -> [i64; 4] {
        dot4::<W, A>(r, x).map(Acc::widen)
    }
}

/// A kernel as function pointers: one copy of the row loop (blend,
/// requantisation, activation) serves every layout, which keeps the
/// firmware's `.text` in budget; a call per pass costs nothing measurable.
#[derive(Clone, Copy)]
struct Dots {
    one: Rows<1>,
    two: Option<Rows<2>>,
    four: Option<Rows<4>>,
}

/// An `N`-row kernel.
pub(super) type Rows<const N: usize> = fn([&[u8]; N], &[i16]) -> [i64; N];

impl Dots {
    /// Up to four experts per pass.
    fn of<K: Kernel>() -> Self {
        Dots {
            one: K::dot1,
            two: Some(K::dot2),
            four: Some(K::dot4),
        }
    }

    /// One expert per pass.
    fn one<K: Kernel>() -> Self {
        Dots {
            one: K::dot1,
            two: None,
            four: None,
        }
    }
}

/// The plain int8 layout of blobs written before `I8Interleaved`: the
/// portable kernel everywhere; on the DSP target without its two-row
/// variant (two experts take the four-row kernel, two of its rows unused),
/// which keeps the firmware's `.text` in budget while the cubic gate's
/// four experts keep their speed (re-exporting such a blob gives it the
/// DSP kernel).
struct Legacy8;

impl Legacy8 {
    #[cfg(phasegate_dsp)]
    fn dots() -> Dots {
        type K = Portable<W8, i32>;
        Dots {
            one: K::dot1,
            two: None,
            four: Some(K::dot4),
        }
    }

    #[cfg(not(phasegate_dsp))]
    fn dots() -> Dots {
        Dots::of::<Portable<W8, i32>>()
    }
}

/// The kernels of the two layouts the DSP kernels read: `SMLAD` (int8,
/// 32-bit accumulators) and `SMLALD` (int16, 64-bit) loops on Armv7E-M, the
/// portable ones elsewhere. On the DSP target int16 rows with 32-bit
/// accumulators take the `SMLALD` loops too: their sums are exact, and the
/// loader's proof makes the exact sum the 32-bit one, so the bits are the
/// same and one int16 kernel fits the firmware's `.text` budget.
#[cfg(phasegate_dsp)]
type Fast8 = dsp::Smlad<W8I, dsp::Asm>;
#[cfg(not(phasegate_dsp))]
type Fast8 = Portable<W8I, i32>;
#[cfg(phasegate_dsp)]
type Fast16 = dsp::Smlad<W16L, dsp::Asm>;
#[cfg(not(phasegate_dsp))]
type Fast16 = Portable<W16, i32>;
#[cfg(phasegate_dsp)]
type Fast16L = dsp::Smlad<W16L, dsp::Asm>;
#[cfg(not(phasegate_dsp))]
type Fast16L = Portable<W16L, i64>;

/// The two-row loop over the row pairs of a whole matrix after one check
/// (`dsp::matrix_pairs`): `false` when the check fails.
type MatrixPairs = fn(&[u8], usize, &[i16], &mut [[i64; 2]]) -> bool;

/// The kernels of one weight matrix (no experts: the factors of a CP
/// layer), one and, where it has one, two rows per pass over `x`: the
/// kernels a dense layer of the same formats runs (each row is
/// `weights.row_bytes(x.len())` long); and, on the DSP target, the
/// two-row loop over a whole matrix after one check (`dsp::matrix_pairs`).
pub(super) fn matrix_kernel(weights: WeightFormat, acc: AccWidth) -> MatrixKernel {
    let k = match (weights, acc) {
        (WeightFormat::I8, AccWidth::I32) => Legacy8::dots(),
        (WeightFormat::I8, AccWidth::I64) => Dots::one::<Portable<W8, i64>>(),
        (WeightFormat::I8Interleaved, AccWidth::I32) => Dots::of::<Fast8>(),
        (WeightFormat::I8Interleaved, AccWidth::I64) => Dots::one::<Portable<W8I, i64>>(),
        (WeightFormat::I16, AccWidth::I32) => Dots::of::<Fast16>(),
        (WeightFormat::I16, AccWidth::I64) => Dots::one::<Portable<W16, i64>>(),
    };
    MatrixKernel {
        one: k.one,
        two: k.two,
        pairs: whole_matrix(weights, acc),
    }
}

/// See [`matrix_kernel`].
#[derive(Clone, Copy)]
pub(super) struct MatrixKernel {
    one: Rows<1>,
    two: Option<Rows<2>>,
    pairs: Option<MatrixPairs>,
}

impl MatrixKernel {
    /// `out[i]` = row `i` of `matrix` (consecutive rows of `rb` bytes) with
    /// `x`; `None` when the matrix holds fewer than `out.len()` rows. Not
    /// inlined: one copy serves both factors of every CP layer (`.text`).
    #[inline(never)]
    pub(super) fn rows(&self, matrix: &[u8], rb: usize, x: &[i16], out: &mut [i64]) -> Option<()> {
        let matrix = matrix.get(..out.len().checked_mul(rb)?)?;
        let (pairs, last) = out.as_chunks_mut::<2>();
        let paired = 2 * pairs.len();
        let fast = self.pairs.is_some_and(|f| f(matrix, rb, x, pairs));
        let mut rows = matrix
            .chunks_exact(rb.max(1))
            .skip(if fast { paired } else { 0 });
        match self.two {
            _ if fast => {}
            Some(two) => {
                for pair in pairs {
                    *pair = two([rows.next()?, rows.next()?], x);
                }
            }
            None => {
                for o in pairs.as_flattened_mut() {
                    [*o] = (self.one)([rows.next()?], x);
                }
            }
        }
        for o in last {
            [*o] = (self.one)([rows.next()?], x);
        }
        Some(())
    }
}

/// The DSP kernels' whole-matrix loop for the two layouts they read.
#[cfg(phasegate_dsp)]
fn whole_matrix(weights: WeightFormat, acc: AccWidth) -> Option<MatrixPairs> {
    match (weights, acc) {
        (WeightFormat::I8Interleaved, AccWidth::I32) => Some(dsp::matrix_pairs::<W8I, dsp::Asm>),
        (WeightFormat::I16, AccWidth::I32) => Some(dsp::matrix_pairs::<W16L, dsp::Asm>),
        _ => None,
    }
}

/// None off the DSP target: the portable kernels take a matrix pair by pair.
#[cfg(not(phasegate_dsp))]
fn whole_matrix(_: WeightFormat, _: AccWidth) -> Option<MatrixPairs> {
    None
}

impl<'a> DenseLayer<'a> {
    fn row_bytes(&self) -> usize {
        self.desc.weights.row_bytes(usize::from(self.desc.in_dim))
    }

    /// Weight row `row` of expert `expert`.
    fn row(&self, expert: u16, row: usize) -> Result<&'a [u8]> {
        let rb = self.row_bytes();
        let start = (usize::from(expert) * usize::from(self.desc.out_dim) + row) * rb;
        self.weights
            .get(start..start + rb)
            .ok_or(Error::SectionLength { layer: self.index })
    }

    /// The layer with kernel `k`: up to 4 experts per pass over `x` when it
    /// has a 4-row kernel, else one.
    fn run_with(&self, k: Dots, gate: &Gate, x: &[i16], y: &mut [i16]) -> Result<()> {
        let step = if k.four.is_some() { 4 } else { 1 };
        let out = usize::from(self.desc.out_dim);
        let n_in = usize::from(self.desc.in_dim);
        let x = x.get(..n_in).ok_or(too_short(n_in, x.len()))?;
        let capacity = y.len();
        let y = y.get_mut(..out).ok_or(too_small(out, capacity))?;
        let mut experts = [0u16; MAX_ACTIVE];
        let mut coefs = [0i64; MAX_ACTIVE];
        for (slot, (e, w)) in gate.iter().enumerate().take(MAX_ACTIVE) {
            if let (Some(es), Some(cs)) = (experts.get_mut(slot), coefs.get_mut(slot)) {
                (*es, *cs) = (e, i64::from(w));
            }
        }
        let n = gate.len();
        // 32-bit accumulators and biases give `|acc + b| <= 2^32`; with
        // `sum |g| < 2^31` every term and partial sum of the blend stays
        // below 2^63 in magnitude, so none of its saturations can act and
        // plain i64 arithmetic gives the same bits, without the M4's costly
        // overflow checks.
        let sum_g = coefs.iter().map(|g| g.unsigned_abs()).sum::<u64>();
        let exact = self.desc.acc == AccWidth::I32 && sum_g < 1 << 31;
        let bias_width = self.desc.acc.bytes();
        let bias32 = self.bias.as_chunks::<4>().0;
        let records = self.requant.as_chunks::<REQUANT_RECORD_LEN>().0;
        if let (4, Some(four)) = (n, k.four) {
            let active = |s: usize| {
                let e = experts.get(s).copied().unwrap_or(0);
                (e, coefs.get(s).copied().unwrap_or(0))
            };
            let active = [0, 1, 2, 3].map(active);
            if exact {
                return self.run_four::<4>(four, active, u64::MAX, x, y);
            }
            if self.desc.acc == AccWidth::I64 {
                // `|acc| <= in_dim * 2^15 * 2^15`: a row whose biases are
                // all within `limit` has `|acc + b| <= i64::MAX / sum |g|`,
                // so no term or partial sum of its blend saturates. A shift
                // by the bits of `sum |g|` (`2^bits > sum |g|`) stands in
                // for the division: a smaller limit only sends more rows
                // to the saturating formula, whose bits are the same, and
                // the M4 build links no 64-bit division routine (`.text`).
                let acc_bound = u64::from(self.desc.in_dim) << 30;
                let limit = (i64::MAX as u64)
                    .checked_shr(u64::BITS - sum_g.leading_zeros())
                    .unwrap_or(0)
                    .saturating_sub(acc_bound);
                return self.run_four::<8>(four, active, limit, x, y);
            }
        }
        for (i, (yi, rec)) in y.iter_mut().zip(records).enumerate() {
            let mut total = 0i64;
            // Up to `step` experts per pass over `x`; a softmax gate's eight
            // take two passes or more. The blend adds in gate order either way.
            for first in (0..n).step_by(step) {
                let e = |k: usize| experts.get(first + k).copied().unwrap_or(0);
                let accs: [i64; 4] = match (n - first).min(step) {
                    1 => {
                        let [a] = (k.one)([self.row(e(0), i)?], x);
                        [a, 0, 0, 0]
                    }
                    m => match (m, k.two, k.four) {
                        (2, Some(two), _) => {
                            let [a, b] = two([self.row(e(0), i)?, self.row(e(1), i)?], x);
                            [a, b, 0, 0]
                        }
                        (_, _, Some(four)) => {
                            let rows = [
                                self.row(e(0), i)?,
                                self.row(e(1), i)?,
                                self.row(e(2), i)?,
                                self.row(e(3), i)?,
                            ];
                            four(rows, x)
                        }
                        _ => [0; 4],
                    },
                };
                let pass = experts
                    .iter()
                    .zip(&coefs)
                    .skip(first)
                    .take((n - first).min(step));
                for ((&e, &g), &acc) in pass.zip(&accs) {
                    let at = usize::from(e) * out + i;
                    total = if exact {
                        let b = bias32.get(at).map_or(0, |c| i32::from_le_bytes(*c));
                        total.wrapping_add(acc.wrapping_add(i64::from(b)).wrapping_mul(g))
                    } else {
                        let b = bias_at(self.bias, bias_width, at).unwrap_or(0);
                        blend_saturating(total, acc, b, g)
                    };
                }
            }
            *yi = finish_row(total, rec, self.desc.activation);
        }
        Ok(())
    }
}

impl DenseLayer<'_> {
    /// `run_with` for exactly four experts (the cubic phase gate's case),
    /// biases `BW` bytes wide: the same arithmetic, with each expert's rows
    /// and biases walked in step instead of indexed per row. The blend is
    /// plain wrapping i64 arithmetic, exact for every row whose biases are
    /// all within `limit` (the caller's proof; `u64::MAX` for 32-bit
    /// accumulators, exact whatever the biases, see `exact` in `run_with`);
    /// any other row takes the saturating formula.
    fn run_four<const BW: usize>(
        &self,
        four: Rows<4>,
        active: [(u16, i64); 4],
        limit: u64,
        x: &[i16],
        y: &mut [i16],
    ) -> Result<()> {
        let out = usize::from(self.desc.out_dim);
        let rb = self.row_bytes().max(1);
        let biases = self.bias.as_chunks::<BW>().0;
        let records = self.requant.as_chunks::<REQUANT_RECORD_LEN>().0;
        let too_short = Error::SectionLength { layer: self.index };
        let expert =
            |(e, _): (u16, i64)| -> Result<(core::slice::ChunksExact<'_, u8>, &[[u8; BW]])> {
                let first = usize::from(e) * out;
                let w = self
                    .weights
                    .get(first * rb..(first + out) * rb)
                    .ok_or(too_short)?;
                let b = biases.get(first..first + out).ok_or(too_short)?;
                Ok((w.chunks_exact(rb), b))
            };
        let [(mut w0, b0), (mut w1, b1), (mut w2, b2), (mut w3, b3)] = [
            expert(active[0])?,
            expert(active[1])?,
            expert(active[2])?,
            expert(active[3])?,
        ];
        let g = active.map(|(_, g)| g);
        let rows = y
            .iter_mut()
            .zip(records)
            .zip(b0.iter().zip(b1).zip(b2.iter().zip(b3)));
        for ((yi, rec), ((c0, c1), (c2, c3))) in rows {
            let (Some(r0), Some(r1), Some(r2), Some(r3)) =
                (w0.next(), w1.next(), w2.next(), w3.next())
            else {
                return Err(too_short);
            };
            let [a0, a1, a2, a3] = four([r0, r1, r2, r3], x);
            let b = [c0, c1, c2, c3].map(bias_value);
            let terms = [
                (a0, (b[0], g[0])),
                (a1, (b[1], g[1])),
                (a2, (b[2], g[2])),
                (a3, (b[3], g[3])),
            ];
            let mut total = 0i64;
            if BW == 4 || b.iter().all(|b| b.unsigned_abs() <= limit) {
                // Gate order, wrapping: exact here.
                for (a, (b, g)) in terms {
                    total = total.wrapping_add(a.wrapping_add(b).wrapping_mul(g));
                }
            } else {
                for (a, (b, g)) in terms {
                    total = blend_saturating(total, a, b, g);
                }
            }
            *yi = finish_row(total, rec, self.desc.activation);
        }
        Ok(())
    }
}

/// `total + g (acc + b)` with the documented i64 saturations: the blend's
/// step where it is not proved exact. Not inlined: one copy serves every
/// row loop (`.text`).
#[inline(never)]
fn blend_saturating(total: i64, acc: i64, b: i64, g: i64) -> i64 {
    total.saturating_add(acc.saturating_add(b).saturating_mul(g))
}

/// A bias of the blob's width (little-endian i32 or i64).
#[inline(always)]
fn bias_value<const BW: usize>(b: &[u8; BW]) -> i64 {
    match *b.as_slice() {
        [a, b, c, d] => i64::from(i32::from_le_bytes([a, b, c, d])),
        [a, b, c, d, e, f, g, h] => i64::from_le_bytes([a, b, c, d, e, f, g, h]),
        _ => 0,
    }
}

impl<'a> GatedOp<'a> for DenseLayer<'a> {
    /// `active x in x out`.
    fn macs(desc: &LayerDesc, active: u64) -> u64 {
        active * u64::from(desc.in_dim) * u64::from(desc.out_dim)
    }

    /// `weight_section`: `experts x out` rows of `in` weights (each padded
    /// to 4 bytes for `I8Interleaved`); then biases and records.
    fn bind(payload: &'a [u8], desc: LayerDesc, index: u8) -> Result<Self> {
        check_dims(&desc, index)?;
        let s = Sections::new(payload, index);
        let weights = s.get(
            desc.weight_section,
            u64::from(desc.experts)
                * u64::from(desc.out_dim)
                * desc.weights.row_bytes(usize::from(desc.in_dim)) as u64,
        )?;
        let (bias, requant) = s.rows(&desc)?;
        Ok(DenseLayer {
            desc,
            weights,
            bias,
            requant,
            index,
        })
    }

    /// Records in range; with 32-bit accumulators, for every row of every
    /// expert (in storage order) `sum_j |w_j| * 2^15 <= i32::MAX`, so no
    /// partial sum of any i16 input wraps (`AccumulatorOverflow { row }`).
    /// With 64-bit accumulators `|acc| < 65535 * 2^15 * 2^15 < 2^47`: no
    /// proof needed. The blend saturates rather than wraps, so biases need
    /// no proof for safety (the exporter proves they never saturate).
    fn check(&self, _gating: &Gating) -> Result<()> {
        let li = self.index;
        check_requant(self.requant, self.desc.activation, li)?;
        if self.desc.acc != AccWidth::I32 {
            return Ok(());
        }
        let out = usize::from(self.desc.out_dim).max(1);
        for (r, row) in self
            .weights
            .chunks_exact(self.row_bytes().max(1))
            .enumerate()
        {
            if row_l1(row, self.desc.weights) << 15 > I32_ROW_BOUND {
                let row = (r % out) as u16;
                return Err(Error::AccumulatorOverflow { layer: li, row });
            }
        }
        Ok(())
    }

    fn desc(&self) -> &LayerDesc {
        &self.desc
    }

    fn desc_mut(&mut self) -> &mut LayerDesc {
        &mut self.desc
    }

    fn requant(&self) -> &'a [u8] {
        self.requant
    }

    /// One pass over `x` per output row; no scratch.
    fn run(&self, gate: &Gate, x: &[i16], _scratch: &mut [i16], y: &mut [i16]) -> Result<()> {
        let k = match (self.desc.weights, self.desc.acc) {
            // int8 with 64-bit accumulators (rows too heavy for the 32-bit
            // proof, rare) takes one expert per pass: a quarter of the
            // unrolled code.
            (WeightFormat::I8, AccWidth::I32) => Legacy8::dots(),
            (WeightFormat::I8, AccWidth::I64) => Dots::one::<Portable<W8, i64>>(),
            (WeightFormat::I8Interleaved, AccWidth::I32) => Dots::of::<Fast8>(),
            (WeightFormat::I8Interleaved, AccWidth::I64) => Dots::one::<Portable<W8I, i64>>(),
            (WeightFormat::I16, AccWidth::I32) => Dots::of::<Fast16>(),
            (WeightFormat::I16, AccWidth::I64) => Dots::of::<Fast16L>(),
        };
        self.run_with(k, gate, x, y)
    }
}

/// The dense op's side of the test contract (`ops::contract`).
#[cfg(test)]
pub(crate) mod case {
    use super::DenseLayer;
    use crate::blob::{AccWidth, Gating, LayerDesc, LayerOp, WeightFormat};
    use crate::error::Error;
    use crate::ops::contract::{
        finish, finish_float, fit_i32_rows, fits, sat, OpCase, Payload, Rng, Rows, Shape,
    };

    /// A dense layer as plain integers.
    #[derive(Clone, Debug)]
    pub(crate) struct Dense {
        rows: Rows,
        /// `experts x out x in`, expert-major then row-major.
        w: Vec<i32>,
    }

    impl Dense {
        fn row(&self, k: usize, i: usize) -> &[i32] {
            let s = self.rows.shape;
            &self.w[(k * s.out_dim + i) * s.in_dim..][..s.in_dim]
        }

        /// `sum_j w[k][i][j] x[j]`, exactly.
        fn acc(&self, k: usize, i: usize, x: &[i16]) -> i128 {
            self.row(k, i)
                .iter()
                .zip(x)
                .map(|(&w, &v)| i128::from(w) * i128::from(v))
                .sum()
        }

        /// The blend `sum_k g_k (acc_k + b_k)` with the documented
        /// saturations (in gate order), and whether any acted.
        fn total(&self, g: &[(usize, i128)], i: usize, x: &[i16]) -> (i128, bool) {
            let (mut total, mut exact) = (0i128, true);
            for &(k, gk) in g {
                let v = self.acc(k, i, x) + self.rows.bias(k, i);
                let term = sat(sat(v, 64) * gk, 64);
                exact &= fits(v, 64) && fits(v * gk, 64) && fits(total + term, 64);
                total = sat(total + term, 64);
            }
            (total, exact)
        }
    }

    impl OpCase for Dense {
        type Op<'a> = DenseLayer<'a>;

        fn random(rng: &mut Rng, mut shape: Shape, _gating: Gating) -> Self {
            if shape.weights == WeightFormat::I8 && rng.chance(50) {
                shape.weights = WeightFormat::I8Interleaved;
            }
            let mut w = shape.weights(rng, shape.experts * shape.out_dim * shape.in_dim);
            if shape.acc == AccWidth::I32 && rng.chance(90) {
                fit_i32_rows(&mut w, shape.in_dim);
            }
            let bias_log2 = if rng.chance(10) { 62 } else { 44 };
            Dense {
                rows: Rows::random(rng, shape, bias_log2),
                w,
            }
        }

        fn rows(&self) -> &Rows {
            &self.rows
        }

        fn encode(&self, p: &mut Payload) -> LayerDesc {
            let mut d = self.rows.shape.desc(LayerOp::Dense);
            d.weight_section = p.rows(&self.w, self.rows.shape.in_dim, d.weights);
            self.rows.encode(p, &mut d);
            d
        }

        /// `docs/blob-format.md`, "Dense layer": for each row, the blend
        /// of the active experts' exact dot products plus biases, saturated
        /// to i64 in gate order, then the row's record. The proof claims
        /// that 32-bit accumulators hold every dot product.
        fn reference(&self, g: &[(usize, i128)], x: &[i16]) -> (Vec<i16>, bool) {
            let s = self.rows.shape;
            let mut claims = true;
            let y = (0..s.out_dim)
                .map(|i| {
                    for &(k, _) in g {
                        claims &= s.acc == AccWidth::I64 || fits(self.acc(k, i, x), 32);
                    }
                    let (total, _) = self.total(g, i, x);
                    finish(total, &self.rows.requant[i], s.activation)
                })
                .collect();
            (y, claims)
        }

        /// The blend is exact (integers times the Q16 gate), so the float
        /// twin differs only by the requantisation and the ELU.
        fn float(&self, g: &[(usize, i128)], x: &[i16]) -> Vec<Option<(f64, f64)>> {
            let s = self.rows.shape;
            (0..s.out_dim)
                .map(|i| {
                    let (total, exact) = self.total(g, i, x);
                    let r = &self.rows.requant[i];
                    exact
                        .then(|| finish_float(total, total as f64, 0.0, r, s.activation))
                        .flatten()
                })
                .collect()
        }

        /// 32-bit accumulators: every row at `sum |w| = 65535` exactly
        /// (`[-32768, 32767]` for int16 weights, `511 x -128 + 127` for
        /// int8), which every i16 input keeps inside i32. 64-bit: every
        /// weight at the format's minimum. Biases at their extremes.
        fn worst_case(rng: &mut Rng, mut shape: Shape, gating: Gating) -> (Self, Vec<Vec<i16>>) {
            let (lo, hi) = shape.weight_range();
            let narrow = shape.acc == AccWidth::I32;
            let (n_min, n_hi) = match shape.weights {
                WeightFormat::I16 => (1, 1),
                WeightFormat::I8 | WeightFormat::I8Interleaved => (511, 1),
            };
            if narrow {
                shape.in_dim = n_min + n_hi + rng.below(3);
            }
            let rows = shape.experts * shape.out_dim;
            let mut w = Vec::new();
            for _ in 0..rows {
                let mut row = vec![lo as i32; shape.in_dim];
                if narrow {
                    row[n_min..].iter_mut().for_each(|v| *v = 0);
                    row[n_min] = hi as i32;
                    let shift = rng.below(shape.in_dim);
                    row.rotate_right(shift);
                }
                w.extend(row);
            }
            let mut case = Dense::random(rng, shape, gating);
            case.w = w;
            case.rows.extreme_biases(rng);
            // Inputs that push every row's dot product to its bound, both ways.
            let row0 = case.row(0, 0).to_vec();
            let push = |neg: bool| -> Vec<i16> {
                row0.iter()
                    .map(|&w| match (w > 0) ^ neg {
                        _ if w == 0 => 0,
                        true => i16::MIN,
                        false => i16::MAX,
                    })
                    .collect()
            };
            let inputs = vec![
                push(false),
                push(true),
                vec![i16::MIN; shape.in_dim],
                rng.inputs(shape.in_dim),
            ];
            (case, inputs)
        }

        /// 32-bit accumulators: one row one unit past `sum |w| = 65535`.
        fn past_the_bound(worst: &Self, _gating: Gating) -> Vec<(Self, Error)> {
            let s = worst.rows.shape;
            if s.acc != AccWidth::I32 {
                return Vec::new();
            }
            let (lo, _) = s.weight_range();
            let (k, i) = (s.experts - 1, s.out_dim / 2);
            let mut twin = worst.clone();
            let start = (k * s.out_dim + i) * s.in_dim;
            let row = &mut twin.w[start..start + s.in_dim];
            let Some(v) = row.iter_mut().find(|v| **v > 0) else {
                return Vec::new();
            };
            *v = lo as i32;
            let err = Error::AccumulatorOverflow {
                layer: 0,
                row: i as u16,
            };
            vec![(twin, err)]
        }
    }
}
