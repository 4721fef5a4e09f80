//! The gated RBF layer, OMG's clustering layer (RBF-CAT, spec §5.4):
//! `y_j = act(requant(sum_k g_k (psi_kj + b_kj)))` with
//! `psi_kj = 2^31 exp(-sigma_kj^2 |x - c_kj|^2)`.
//!
//! Integer recipe (`docs/graph-format.md`, "The RBF op"): per input
//! `d_i = x_i - c_kji` (at most 65,535 in magnitude), the squared distance
//! `D = sum_i d_i^2 * 4^a_i` in u64 (`a_i` aligns input `i` to the finest
//! input format; the loader proves the sum fits for any input), its table
//! position `pos = floor(D * m / 2^s)` (a 96-bit product), and
//! `psi = 2^31 + expm1(-pos)` from the ELU's Q15 table (`fixed::elu`'s
//! `expm1_neg_q31`, 0 from `u = 16` on). No square root and no division:
//! about 70 instructions per squared difference on the Cortex-M4.

use super::common::{
    check_dims, check_requant, finish_row_outlined, too_short, too_small, Sections,
};
use super::GatedOp;
use crate::blob::records::bias_at;
use crate::blob::{
    Gating, LayerDesc, LayerOp, RbfScale, WeightFormat, RBF_SCALE_RECORD_LEN, REQUANT_RECORD_LEN,
};
use crate::error::{Error, Result};
use crate::fixed::elu::expm1_neg_q31;
use crate::fixed::gate::Gate;

/// Largest alignment shift of an input (`4^15` times its squared
/// difference still leaves room for a few inputs in the u64).
pub const MAX_ALIGN: u8 = 15;

/// `2^31`: `psi` of a point at its centre.
const ONE_Q31: i64 = 1 << 31;

/// A validated RBF layer.
#[derive(Clone, Copy, Debug)]
pub struct RbfLayer<'a> {
    /// The header's description (its `op` is `LayerOp::Rbf`).
    pub desc: LayerDesc,
    /// `experts x out x in` centres, i16.
    pub centres: &'a [u8],
    /// `experts x out` scale records.
    pub scales: &'a [u8],
    /// `in` alignment shifts.
    pub align: &'a [u8],
    /// `experts x out` biases.
    pub bias: &'a [u8],
    /// `out` requantisation records.
    pub requant: &'a [u8],
    /// Position in the network, for error reports.
    pub index: u8,
}

/// The largest `(x - c)^2` over every i16 `x`.
fn max_square(c: i64) -> u64 {
    let far = (i64::from(i16::MAX) - c)
        .unsigned_abs()
        .max((c - i64::from(i16::MIN)).unsigned_abs());
    far.saturating_mul(far)
}

impl<'a> RbfLayer<'a> {
    /// The centres of stored row `row` (expert-major), little-endian i16
    /// pairs, with the alignment of their inputs.
    fn row(&self, row: usize) -> impl Iterator<Item = (i64, u32)> + '_ {
        let n = usize::from(self.desc.in_dim);
        let bytes = row
            .checked_mul(2 * n)
            .and_then(|from| self.centres.get(from..)?.get(..2 * n))
            .unwrap_or(&[]);
        bytes
            .as_chunks::<2>()
            .0
            .iter()
            .zip(self.align)
            .map(|(c, &a)| {
                (
                    i64::from(i16::from_le_bytes(*c)),
                    u32::from(a.min(MAX_ALIGN)),
                )
            })
    }

    /// `psi` of stored row `row` at `x`, Q31.
    fn psi(&self, row: usize, x: &[i16]) -> i64 {
        ONE_Q31 + expm1_neg_q31(self.position(row, x))
    }

    /// The table position of stored row `row` at `x`: `floor(D m / 2^s)`
    /// saturated to u64, `D` the aligned squared distance (the DEC op's
    /// too).
    pub(crate) fn position(&self, row: usize, x: &[i16]) -> u64 {
        let mut d2 = 0u64;
        for ((c, a), &xi) in self.row(row).zip(x) {
            let d = (i64::from(xi) - c).unsigned_abs();
            // `d^2 < 2^32` and `a <= 15`: below 2^62; the sum is proved.
            d2 = d2.saturating_add(d.saturating_mul(d) << (2 * a));
        }
        let scale = self
            .scales
            .as_chunks::<RBF_SCALE_RECORD_LEN>()
            .0
            .get(row)
            .and_then(RbfScale::from_bytes)
            .unwrap_or(RbfScale {
                multiplier: 0,
                shift: 0,
            });
        let pos = (u128::from(d2) * u128::from(scale.multiplier)) >> scale.shift;
        u64::try_from(pos).unwrap_or(u64::MAX)
    }
}

impl<'a> GatedOp<'a> for RbfLayer<'a> {
    /// `active x out x in`: one squared difference per input and centre.
    fn macs(desc: &LayerDesc, active: u64) -> u64 {
        active * u64::from(desc.out_dim) * u64::from(desc.in_dim)
    }

    /// `weight_section`: the centres (`I16` only: a centre lives in its
    /// input's format, which int8 could not span); then the scale records,
    /// the alignment shifts, biases and output records. (The DEC op's
    /// sections are the same: `ops::dec` binds them here.)
    fn bind(payload: &'a [u8], desc: LayerDesc, index: u8) -> Result<Self> {
        let (scales, align) = match desc.op {
            LayerOp::Rbf { scales, align } => (scales, align),
            #[cfg(any(test, feature = "dec"))]
            LayerOp::Dec { scales, align } => (scales, align),
            _ => return Err(Error::UnsupportedParameter { layer: index }),
        };
        if desc.weights != WeightFormat::I16 {
            return Err(Error::UnsupportedParameter { layer: index });
        }
        check_dims(&desc, index)?;
        let s = Sections::new(payload, index);
        let rows = u64::from(desc.experts) * u64::from(desc.out_dim);
        let centres = s.get(
            desc.weight_section,
            rows * u64::from(desc.in_dim) * desc.weights.bytes() as u64,
        )?;
        let scales = s.get(scales, rows * RBF_SCALE_RECORD_LEN as u64)?;
        let align = s.get(align, u64::from(desc.in_dim))?;
        let (bias, requant) = s.rows(&desc)?;
        Ok(RbfLayer {
            desc,
            centres,
            scales,
            align,
            bias,
            requant,
            index,
        })
    }

    /// Records in range (output, scale: reserved bytes zero, shift at
    /// most 95; alignment at most 15: `UnsupportedParameter`), and the
    /// overflow proof: for every stored row, `sum_i max_x (x - c_i)^2 *
    /// 4^a_i` fits a u64 (`AccumulatorOverflow { row }`). The bias and the
    /// blend saturate in i64, as the diagonal op's.
    fn check(&self, _gating: &Gating) -> Result<()> {
        let li = self.index;
        check_requant(self.requant, self.desc.activation, li)?;
        let unsupported = Error::UnsupportedParameter { layer: li };
        if self.align.iter().any(|&a| a > MAX_ALIGN) {
            return Err(unsupported);
        }
        let out = usize::from(self.desc.out_dim).max(1);
        for (r, record) in self
            .scales
            .as_chunks::<RBF_SCALE_RECORD_LEN>()
            .0
            .iter()
            .enumerate()
        {
            if RbfScale::from_bytes(record).is_none() {
                return Err(unsupported);
            }
            // `max_square < 2^32` and `a <= 15`: each term is below 2^62;
            // the sum must not pass u64.
            let bound = self.row(r).try_fold(0u64, |sum, (c, a)| {
                sum.checked_add(max_square(c) << (2 * a))
            });
            if bound.is_none() {
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

    /// One distance per active expert and row; no scratch.
    fn run(&self, gate: &Gate, x: &[i16], _scratch: &mut [i16], y: &mut [i16]) -> Result<()> {
        let (n, out) = (
            usize::from(self.desc.in_dim),
            usize::from(self.desc.out_dim),
        );
        let x = x.get(..n).ok_or(too_short(n, x.len()))?;
        let capacity = y.len();
        let y = y.get_mut(..out).ok_or(too_small(out, capacity))?;
        let width = self.desc.acc.bytes();
        let recs = self.requant.as_chunks::<REQUANT_RECORD_LEN>().0;
        for (j, (yj, rec)) in y.iter_mut().zip(recs).enumerate() {
            let mut total = 0i64;
            for (e, g) in gate.iter() {
                let row = usize::from(e) * out + j;
                let b = bias_at(self.bias, width, row).unwrap_or(0);
                let v = self.psi(row, x).saturating_add(b);
                total = total.saturating_add(v.saturating_mul(i64::from(g)));
                crate::mac_count::add(n);
            }
            *yj = finish_row_outlined(total, rec, self.desc.activation);
        }
        Ok(())
    }
}

/// The RBF op's side of the test contract (`ops::contract`).
#[cfg(test)]
pub(crate) mod case {
    use super::{RbfLayer, MAX_ALIGN};
    use crate::blob::{Gating, LayerDesc, LayerOp, RbfScale, Section, WeightFormat};
    use crate::error::Error;
    use crate::fixed::elu::expm1_neg_q31;
    use crate::ops::contract::{
        finish, finish_float, fits, sat, OpCase, Payload, Rng, Rows, Shape,
    };

    /// Bound of `|psi - 2^31 exp(-u)|` in Q31 units, `u = D m / 2^(s + 22)`:
    /// the table's Q15 rounding (2^15), its linear interpolation between
    /// samples 1/64 apart (`h^2 / 8 * 2^31 = 2^16`), the floor of the
    /// position (`2^-22 * 2^31 = 2^9`), and `exp(-16) * 2^31 < 242` beyond
    /// the table.
    const PSI_ERROR: f64 = 32_768.0 + 65_536.0 + 512.0 + 242.0;

    /// An RBF layer as plain integers.
    #[derive(Clone, Debug)]
    pub(crate) struct Rbf {
        pub(crate) rows: Rows,
        /// `experts x out x in` centres, expert-major.
        pub(crate) c: Vec<i32>,
        /// `experts x out` `(multiplier, shift)`.
        pub(crate) scales: Vec<(u32, u8)>,
        /// `in` alignment shifts (may be out of range in twins).
        pub(crate) align: Vec<u8>,
    }

    impl Rbf {
        /// `D` of stored row `row` at `x`, exactly.
        pub(crate) fn d2(&self, row: usize, x: &[i16]) -> i128 {
            let n = self.rows.shape.in_dim;
            (0..n)
                .map(|i| {
                    let d = i128::from(x[i]) - i128::from(self.c[row * n + i]);
                    (d * d) << (2 * u32::from(self.align[i]))
                })
                .sum()
        }

        /// `pos = floor(D m / 2^s)`, saturated to u64, and the real `u`.
        pub(crate) fn pos(&self, row: usize, x: &[i16]) -> (u64, f64) {
            let (m, s) = self.scales[row];
            let p = (self.d2(row, x) * i128::from(m)) >> s;
            let u = self.d2(row, x) as f64 * f64::from(m) / 2f64.powi(i32::from(s) + 22);
            (u64::try_from(p).unwrap_or(u64::MAX), u)
        }

        /// `sum_k g_k sat64(psi_kj + b_kj)` in gate order, the real-valued
        /// twin, and whether any saturation acted.
        fn total(&self, g: &[(usize, i128)], j: usize, x: &[i16]) -> (i128, f64, bool) {
            let out = self.rows.shape.out_dim;
            let (mut total, mut real, mut exact) = (0i128, 0.0, true);
            for &(k, gk) in g {
                let row = k * out + j;
                let (pos, u) = self.pos(row, x);
                let psi = (1i128 << 31) + i128::from(expm1_neg_q31(pos));
                let v = psi + self.rows.bias(k, j);
                let term = sat(sat(v, 64) * gk, 64);
                exact &= fits(v, 64) && fits(v * gk, 64) && fits(total + term, 64);
                total = sat(total + term, 64);
                real += gk as f64 * (2f64.powi(31) * (-u).exp() + self.rows.bias(k, j) as f64);
            }
            (total, real, exact)
        }

        /// The largest alignment shift (same for every input) that the
        /// proof accepts for these centres, capped at 15.
        pub(crate) fn widest_align(&self) -> u8 {
            let n = self.rows.shape.in_dim;
            (0..=MAX_ALIGN)
                .rev()
                .find(|&a| {
                    self.c.chunks(n).all(|row| {
                        row.iter()
                            .map(|&c| u128::from(super::max_square(c.into())) << (2 * a))
                            .sum::<u128>()
                            <= u128::from(u64::MAX)
                    })
                })
                .unwrap_or(0)
        }

        /// A random layer of `shape`'s rows, its centres int16.
        pub(crate) fn random_centres(rng: &mut Rng, mut shape: Shape) -> Rbf {
            shape.weights = WeightFormat::I16;
            let rows = shape.experts * shape.out_dim;
            let c = shape.weights(rng, rows * shape.in_dim);
            let align = (0..shape.in_dim)
                .map(|_| {
                    if rng.chance(5) {
                        rng.range(0, 16) as u8
                    } else {
                        rng.range(0, 4) as u8
                    }
                })
                .collect();
            let scales = (0..rows)
                .map(|_| {
                    if rng.chance(20) {
                        (rng.next() as u32, rng.range(0, 95) as u8)
                    } else {
                        (
                            rng.range(1 << 20, u32::MAX.into()) as u32,
                            rng.range(40, 60) as u8,
                        )
                    }
                })
                .collect();
            let bias_log2 = if rng.chance(10) { 62 } else { 36 };
            Rbf {
                rows: Rows::random(rng, shape, bias_log2),
                c,
                scales,
                align,
            }
        }

        /// Its sections (centres, scales, alignment, rows) under the header
        /// variant `op` makes of the scales and alignment sections.
        pub(crate) fn encode_as(
            &self,
            p: &mut Payload,
            op: impl Fn(Section, Section) -> LayerOp,
        ) -> LayerDesc {
            let mut d = self
                .rows
                .shape
                .desc(op(Section::default(), Section::default()));
            d.weight_section = p.weights(&self.c, d.weights);
            let scales = p.push(
                &self
                    .scales
                    .iter()
                    .flat_map(|&(multiplier, shift)| RbfScale { multiplier, shift }.to_bytes())
                    .collect::<Vec<_>>(),
            );
            let align = p.push(&self.align);
            d.op = op(scales, align);
            self.rows.encode(p, &mut d);
            d
        }
    }

    impl OpCase for Rbf {
        type Op<'a> = RbfLayer<'a>;

        fn random(rng: &mut Rng, shape: Shape, _gating: Gating) -> Self {
            Rbf::random_centres(rng, shape)
        }

        fn rows(&self) -> &Rows {
            &self.rows
        }

        fn encode(&self, p: &mut Payload) -> LayerDesc {
            self.encode_as(p, |scales, align| LayerOp::Rbf { scales, align })
        }

        /// `y_j = act(requant(sum_k g_k (psi_kj + b_kj)))`, `psi` from `D`
        /// in i128 (`docs/graph-format.md`), the table read by the ELU's
        /// own (separately checked) interpolation. The proof claims `D`
        /// fits a u64.
        fn reference(&self, g: &[(usize, i128)], x: &[i16]) -> (Vec<i16>, bool) {
            let s = self.rows.shape;
            let claims = g.iter().all(|&(k, _)| {
                (0..s.out_dim).all(|j| self.d2(k * s.out_dim + j, x) <= i128::from(u64::MAX))
            });
            let y = (0..s.out_dim)
                .map(|j| finish(self.total(g, j, x).0, &self.rows.requant[j], s.activation))
                .collect();
            (y, claims)
        }

        fn float(&self, g: &[(usize, i128)], x: &[i16]) -> Vec<Option<(f64, f64)>> {
            let s = self.rows.shape;
            let err: f64 = g.iter().map(|&(_, gk)| gk as f64 * PSI_ERROR).sum();
            (0..s.out_dim)
                .map(|j| {
                    let (total, real, exact) = self.total(g, j, x);
                    let r = &self.rows.requant[j];
                    exact
                        .then(|| finish_float(total, real, err, r, s.activation))
                        .flatten()
                })
                .collect()
        }

        /// Centres at the format's minimum (the farthest from `i16::MAX`),
        /// every input aligned by the widest shift the proof accepts,
        /// biases at their extremes.
        fn worst_case(rng: &mut Rng, shape: Shape, gating: Gating) -> (Self, Vec<Vec<i16>>) {
            let mut case = Rbf::random(rng, shape, gating);
            let (lo, _) = case.rows.shape.weight_range();
            case.c.iter_mut().for_each(|c| *c = lo as i32);
            let a = case.widest_align();
            case.align.iter_mut().for_each(|v| *v = a);
            case.rows.extreme_biases(rng);
            let n = case.rows.shape.in_dim;
            let inputs = vec![vec![i16::MAX; n], vec![i16::MIN; n], rng.inputs(n)];
            (case, inputs)
        }

        /// One alignment step more (when the worst case is below 15): the
        /// first row overflows; an alignment of 16, a scale shift of 96
        /// and a set reserved byte are out of range.
        fn past_the_bound(worst: &Self, _gating: Gating) -> Vec<(Self, Error)> {
            let mut twins = Vec::new();
            let a = worst.align[0];
            if a < MAX_ALIGN {
                let mut t = worst.clone();
                t.align.iter_mut().for_each(|v| *v = a + 1);
                twins.push((t, Error::AccumulatorOverflow { layer: 0, row: 0 }));
            }
            let unsupported = Error::UnsupportedParameter { layer: 0 };
            let mut t = worst.clone();
            t.align[0] = MAX_ALIGN + 1;
            twins.push((t, unsupported));
            let mut t = worst.clone();
            t.scales[0].1 = RbfScale::MAX_SHIFT + 1;
            twins.push((t, unsupported));
            // int8 centres could not span their inputs' formats.
            let mut t = worst.clone();
            t.rows.shape.weights = WeightFormat::I8;
            t.c.iter_mut().for_each(|c| *c = (*c).clamp(-128, 127));
            twins.push((t, unsupported));
            twins
        }
    }
}
