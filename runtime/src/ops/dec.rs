//! The gated DEC layer, OMG's deep-embedded-clustering soft assignment
//! (spec §2.2 and §5.4, alpha = 1): `y_j = act(requant(sum_k g_k (psi_kj +
//! b_kj)))` with `psi_kj = 2^31 q_kj`, `q_kj = t_kj / sum_l t_kl` and
//! `t_kj = 1 / (1 + u_kj)`, `u_kj` the squared distance to centre `c_kj`.
//!
//! Integer recipe (`docs/graph-format.md`, "The DEC op"): the layer's
//! sections are an RBF layer's, bound and checked (overflow proof
//! included) by the RBF op; the table position `pos_kj = floor(D m / 2^s)`
//! of each centre is the RBF op's (`RbfLayer::position`, `u = pos /
//! 2^22`); then, per active expert, relative to its nearest centre (the
//! spec's "scale by the largest term", so that small `q` keep their
//! precision and the sum is never 0):
//!
//! * `a = sat64(min_l pos_kl + 2^22)`, `k = max(0, bits(a) - 32)`;
//! * `t_kj = floor((a >> k) 2^31 / (sat64(pos_kj + 2^22) >> k))`, at most
//!   `2^31`, exactly `2^31` at the nearest centre;
//! * `q_kj = floor(t_kj 2^31 / S_k)`, `S_k = sum_l t_kl` (at least `2^31`,
//!   below `2^47`).
//!
//! Only 64-bit divisions, no square root. The positions of an expert's
//! centres and the rows' totals are kept in the node's scratch span
//! (`8 out` elements), so each distance is computed once.

use super::common::{finish_row_outlined, too_short, too_small};
use super::rbf::RbfLayer;
use super::GatedOp;
use crate::blob::records::bias_at;
use crate::blob::{Gating, LayerDesc, LayerOp, REQUANT_RECORD_LEN};
use crate::error::{Error, Result};
use crate::fixed::gate::Gate;

/// `2^22`: the table position of `u = 1`.
const ONE_POS: u64 = 1 << 22;

/// A validated DEC layer: its sections are an RBF layer's (its `desc.op`
/// is `LayerOp::Dec`).
#[derive(Clone, Copy, Debug)]
pub struct DecLayer<'a> {
    /// The centres, scale records, alignment shifts, biases and output
    /// records, bound and checked by the RBF op.
    pub sections: RbfLayer<'a>,
}

/// The kernel `t = 2^31 (1 + u_nearest) / (1 + u)` of one expert, from
/// the position of its nearest centre.
#[derive(Clone, Copy, Debug)]
struct Student {
    /// `(a >> k) 2^31`, below `2^63`.
    top: u64,
    /// `k`.
    shift: u32,
}

impl Student {
    /// The kernel relative to the nearest centre's position `nearest`.
    fn new(nearest: u64) -> Student {
        let a = nearest.saturating_add(ONE_POS);
        let shift = (u64::BITS - a.leading_zeros()).saturating_sub(32);
        Student {
            top: (a >> shift) << 31,
            shift,
        }
    }

    /// `t` at position `pos` (at least the nearest's): at most `2^31`.
    fn t(&self, pos: u64) -> u64 {
        // `pos + 2^22 >= a`, so the divisor is at least `a >> k >= 2^22`.
        self.top
            .checked_div(pos.saturating_add(ONE_POS) >> self.shift)
            .unwrap_or(0)
    }
}

/// A u64 in four scratch elements.
fn store(w: &mut [i16; 4], v: u64) {
    for (i, e) in w.iter_mut().enumerate() {
        *e = (v >> (16 * i)) as u16 as i16;
    }
}

/// The u64 [`store`] left.
fn load(w: &[i16; 4]) -> u64 {
    w.iter()
        .enumerate()
        .fold(0, |v, (i, &e)| v | u64::from(e as u16) << (16 * i))
}

impl<'a> GatedOp<'a> for DecLayer<'a> {
    /// `active x out x in`: one squared difference per input and centre.
    fn macs(desc: &LayerDesc, active: u64) -> u64 {
        active * u64::from(desc.out_dim) * u64::from(desc.in_dim)
    }

    /// An expert's `out` positions and the `out` rows' i64 totals, four
    /// elements each.
    fn scratch(desc: &LayerDesc) -> usize {
        8 * usize::from(desc.out_dim)
    }

    /// `weight_section`: the centres, then the scale records and the
    /// alignment shifts (as the RBF op's), biases and output records.
    fn bind(payload: &'a [u8], desc: LayerDesc, index: u8) -> Result<Self> {
        if !matches!(desc.op, LayerOp::Dec { .. }) {
            return Err(Error::UnsupportedParameter { layer: index });
        }
        Ok(DecLayer {
            sections: RbfLayer::bind(payload, desc, index)?,
        })
    }

    /// The RBF op's checks and proof (the distances), and the output
    /// records. Past the distances nothing can overflow: `t <= 2^31`,
    /// `S < 2^47`, `t 2^31 < 2^63`, `q <= 2^31`; the bias and the blend
    /// saturate in i64, as the RBF op's.
    fn check(&self, gating: &Gating) -> Result<()> {
        self.sections.check(gating)
    }

    fn desc(&self) -> &LayerDesc {
        &self.sections.desc
    }

    fn desc_mut(&mut self) -> &mut LayerDesc {
        &mut self.sections.desc
    }

    fn requant(&self) -> &'a [u8] {
        self.sections.requant
    }

    /// Expert by expert: the positions into scratch, the expert's sum,
    /// then each row's `q` into its total.
    fn run(&self, gate: &Gate, x: &[i16], scratch: &mut [i16], y: &mut [i16]) -> Result<()> {
        let l = &self.sections;
        let (n, out) = (usize::from(l.desc.in_dim), usize::from(l.desc.out_dim));
        let x = x.get(..n).ok_or(too_short(n, x.len()))?;
        let capacity = y.len();
        let y = y.get_mut(..out).ok_or(too_small(out, capacity))?;
        let (need, have) = (8 * out, scratch.len());
        let scratch = scratch.get_mut(..need).ok_or(too_small(need, have))?;
        let (pos, totals) = scratch.split_at_mut(4 * out);
        let (pos, totals) = (pos.as_chunks_mut::<4>().0, totals.as_chunks_mut::<4>().0);
        totals.iter_mut().for_each(|t| store(t, 0));
        let width = l.desc.acc.bytes();
        for (e, g) in gate.iter() {
            let base = usize::from(e) * out;
            let mut nearest = u64::MAX;
            for (j, p) in pos.iter_mut().enumerate() {
                let v = l.position(base + j, x);
                nearest = nearest.min(v);
                store(p, v);
                crate::mac_count::add(n);
            }
            let kernel = Student::new(nearest);
            let sum: u64 = pos.iter().map(|p| kernel.t(load(p))).sum();
            for (j, (p, t)) in pos.iter().zip(totals.iter_mut()).enumerate() {
                let q = (kernel.t(load(p)) << 31).checked_div(sum).unwrap_or(0);
                let b = bias_at(l.bias, width, base + j).unwrap_or(0);
                let v = (q as i64).saturating_add(b);
                let total = (load(t) as i64).saturating_add(v.saturating_mul(i64::from(g)));
                store(t, total as u64);
            }
        }
        let recs = l.requant.as_chunks::<REQUANT_RECORD_LEN>().0;
        for ((yj, rec), t) in y.iter_mut().zip(recs).zip(totals.iter()) {
            *yj = finish_row_outlined(load(t) as i64, rec, l.desc.activation);
        }
        Ok(())
    }
}

/// The DEC op's side of the test contract (`ops::contract`): the RBF
/// case's centres, scales and alignment under `LayerOp::Dec`.
#[cfg(test)]
pub(crate) mod case {
    use super::DecLayer;
    use crate::blob::{Gating, LayerDesc, LayerOp};
    use crate::error::Error;
    use crate::ops::contract::{
        finish, finish_float, fits, sat, OpCase, Payload, Rng, Rows, Shape,
    };
    use crate::ops::rbf::case::Rbf;

    /// Bound of `|t - 2^31 (1 + u_near) / (1 + u)|` in Q31 units: the
    /// floor of each position moves `u` by less than `2^-22` (a relative
    /// `2^-22` of `1 + u`, twice: numerator and divisor), the shift by `k`
    /// a relative `2^-31` twice, and the floor of the quotient 1.
    const T_ERROR: f64 = 2_147_483_648.0 * (2.0 / 4_194_304.0 + 2.0 / 2_147_483_648.0) + 1.0;

    /// A DEC layer as plain integers: an RBF layer's.
    #[derive(Clone, Debug)]
    pub(crate) struct Dec(Rbf);

    /// `2^22`.
    const ONE_POS: i128 = 1 << 22;

    impl Dec {
        /// Per expert `k` of the gate: every row's `psi_kj = q_kj` (Q31),
        /// its real value `2^31 (1/(1+u_kj)) / sum_l (1/(1+u_kl))`, and
        /// whether no saturation of a position acted.
        fn psi(&self, k: usize, x: &[i16]) -> (Vec<i128>, Vec<f64>, bool) {
            let out = self.0.rows.shape.out_dim;
            let u64_max = i128::from(u64::MAX);
            let (pos, real): (Vec<i128>, Vec<f64>) = (0..out)
                .map(|j| {
                    let (p, u) = self.0.pos(k * out + j, x);
                    (i128::from(p), u)
                })
                .unzip();
            let unsaturated = pos.iter().all(|&p| p + ONE_POS <= u64_max && p < u64_max);
            let a = (pos.iter().copied().min().unwrap() + ONE_POS).min(u64_max);
            let bits = 128 - a.leading_zeros();
            let shift = bits.saturating_sub(32);
            let t: Vec<i128> = pos
                .iter()
                .map(|&p| ((a >> shift) << 31) / ((p + ONE_POS).min(u64_max) >> shift))
                .collect();
            let s: i128 = t.iter().sum();
            let q = t.iter().map(|&t| (t << 31) / s).collect();
            let r: Vec<f64> = real.iter().map(|u| 1.0 / (1.0 + u)).collect();
            let rs: f64 = r.iter().sum();
            let qr = r.iter().map(|r| 2f64.powi(31) * r / rs).collect();
            (q, qr, unsaturated)
        }

        /// `sum_k g_k sat64(psi_kj + b_kj)` in gate order for every row,
        /// their real-valued twins, and whether any saturation acted.
        fn totals(&self, g: &[(usize, i128)], x: &[i16]) -> Vec<(i128, f64, bool)> {
            let out = self.0.rows.shape.out_dim;
            let mut rows = vec![(0i128, 0.0, true); out];
            for &(k, gk) in g {
                let (q, qr, unsaturated) = self.psi(k, x);
                for (j, row) in rows.iter_mut().enumerate() {
                    let b = self.0.rows.bias(k, j);
                    let v = q[j] + b;
                    let term = sat(sat(v, 64) * gk, 64);
                    row.2 &=
                        unsaturated && fits(v, 64) && fits(v * gk, 64) && fits(row.0 + term, 64);
                    row.0 = sat(row.0 + term, 64);
                    row.1 += gk as f64 * (qr[j] + b as f64);
                }
            }
            rows
        }
    }

    impl OpCase for Dec {
        type Op<'a> = DecLayer<'a>;

        fn random(rng: &mut Rng, shape: Shape, _gating: Gating) -> Self {
            Dec(Rbf::random_centres(rng, shape))
        }

        fn rows(&self) -> &Rows {
            &self.0.rows
        }

        fn encode(&self, p: &mut Payload) -> LayerDesc {
            self.0
                .encode_as(p, |scales, align| LayerOp::Dec { scales, align })
        }

        /// `q` written out from `docs/graph-format.md` in i128, per
        /// expert; the proof claims `D` fits a u64 (the RBF op's).
        fn reference(&self, g: &[(usize, i128)], x: &[i16]) -> (Vec<i16>, bool) {
            let s = self.0.rows.shape;
            let claims = g.iter().all(|&(k, _)| {
                (0..s.out_dim).all(|j| self.0.d2(k * s.out_dim + j, x) <= i128::from(u64::MAX))
            });
            let y = self
                .totals(g, x)
                .iter()
                .zip(&self.0.rows.requant)
                .map(|(t, r)| finish(t.0, r, s.activation))
                .collect();
            (y, claims)
        }

        /// Each expert's `q` is off its real value by at most `T_ERROR (1 +
        /// out)`: `T_ERROR` from its own `t`, `T_ERROR` per row through
        /// the sum (`S >= 2^31`), and the quotient's floor.
        fn float(&self, g: &[(usize, i128)], x: &[i16]) -> Vec<Option<(f64, f64)>> {
            let s = self.0.rows.shape;
            let q_error = T_ERROR * (1.0 + s.out_dim as f64) + 1.0;
            let err: f64 = g.iter().map(|&(_, gk)| gk as f64 * q_error).sum();
            self.totals(g, x)
                .iter()
                .zip(&self.0.rows.requant)
                .map(|(&(total, real, exact), r)| {
                    exact
                        .then(|| finish_float(total, real, err, r, s.activation))
                        .flatten()
                })
                .collect()
        }

        /// The RBF op's worst case: the distances' proof is the same.
        fn worst_case(rng: &mut Rng, shape: Shape, gating: Gating) -> (Self, Vec<Vec<i16>>) {
            let (case, inputs) = Rbf::worst_case(rng, shape, gating);
            (Dec(case), inputs)
        }

        /// The RBF op's twins, under `LayerOp::Dec`.
        fn past_the_bound(worst: &Self, gating: Gating) -> Vec<(Self, Error)> {
            Rbf::past_the_bound(&worst.0, gating)
                .into_iter()
                .map(|(t, e)| (Dec(t), e))
                .collect()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Student;

    /// `t` against `2^31 (1 + u_near) / (1 + u)` in f64, where no
    /// saturation acts, and its two exact points.
    #[test]
    fn student_kernel_is_relative_to_the_nearest_centre() {
        for nearest in [0u64, 1, 1 << 22, 5 << 30, 1 << 40, 1 << 60] {
            let k = Student::new(nearest);
            assert_eq!(k.t(nearest), 1 << 31, "{nearest}");
            for extra in [0u64, 1, 1 << 20, 1 << 22, 3 << 30, 1 << 50] {
                let pos = nearest + extra;
                let want = 2f64.powi(31) * (nearest as f64 / 4_194_304.0 + 1.0)
                    / (pos as f64 / 4_194_304.0 + 1.0);
                let got = k.t(pos) as f64;
                assert!(
                    (got - want).abs() <= 2.0 + want * 2f64.powi(-30),
                    "{nearest} {pos}: {got} vs {want}"
                );
            }
        }
        assert_eq!(Student::new(u64::MAX).t(u64::MAX), 1 << 31);
    }

    #[test]
    fn scratch_words_round_trip() {
        for v in [
            0u64,
            1,
            u64::MAX,
            0x8000_0000_0000_0000,
            0x1234_5678_9abc_def0,
        ] {
            let mut w = [0i16; 4];
            super::store(&mut w, v);
            assert_eq!(super::load(&w), v);
        }
    }
}
