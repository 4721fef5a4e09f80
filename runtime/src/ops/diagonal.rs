//! The phase-gated diagonal layer (`in_dim == out_dim`):
//! `y_i = act(requant(sum_k g_k (w_ki x_i + b_ki)))`, the cheapest residual
//! adapter form. Every product `|w x| <= 2^30` fits an i32, so no row needs
//! an accumulator proof; the blend is done in i64 like the dense kernel's.

use super::common::{
    check_dims, check_requant, finish_row_outlined, i16_at, too_short, too_small, Sections,
};
use super::GatedOp;
use crate::blob::records::bias_at;
use crate::blob::{Gating, LayerDesc, WeightFormat, REQUANT_RECORD_LEN};
use crate::error::{Error, Result};
use crate::fixed::gate::Gate;

/// A validated diagonal layer.
#[derive(Clone, Copy, Debug)]
pub struct DiagLayer<'a> {
    /// The header's description (its `op` is `LayerOp::Diagonal`).
    pub desc: LayerDesc,
    /// `experts x out` weights.
    pub weights: &'a [u8],
    /// `experts x out` biases.
    pub bias: &'a [u8],
    /// `out` requantisation records.
    pub requant: &'a [u8],
    /// Position in the network (or style), for error reports.
    pub index: u8,
}

impl<'a> DiagLayer<'a> {
    fn weight(&self, k: usize, i: usize) -> i64 {
        let n = usize::from(self.desc.out_dim);
        let at = k * n + i;
        match self.desc.weights {
            WeightFormat::I8 | WeightFormat::I8Interleaved => {
                self.weights.get(at).map_or(0, |&b| i64::from(b as i8))
            }
            WeightFormat::I16 => i16_at(self.weights, at).map_or(0, i64::from),
        }
    }

    fn run_rows(&self, gate: &Gate, x: &[i16], y: &mut [i16]) -> Result<()> {
        let n = usize::from(self.desc.out_dim);
        let x = x.get(..n).ok_or(too_short(n, x.len()))?;
        let capacity = y.len();
        let y = y.get_mut(..n).ok_or(too_small(n, capacity))?;
        let width = self.desc.acc.bytes();
        let recs = self.requant.as_chunks::<REQUANT_RECORD_LEN>().0;
        for (i, ((yi, &xi), rec)) in y.iter_mut().zip(x).zip(recs).enumerate() {
            let mut total = 0i64;
            for (e, g) in gate.iter() {
                let k = usize::from(e);
                let b = bias_at(self.bias, width, k * n + i).unwrap_or(0);
                let v = (self.weight(k, i) * i64::from(xi)).saturating_add(b);
                total = total.saturating_add(v.saturating_mul(i64::from(g)));
                crate::mac_count::add(1);
            }
            *yi = finish_row_outlined(total, rec, self.desc.activation);
        }
        Ok(())
    }
}

impl<'a> GatedOp<'a> for DiagLayer<'a> {
    /// `active x out`.
    fn macs(desc: &LayerDesc, active: u64) -> u64 {
        active * u64::from(desc.out_dim)
    }

    /// `in_dim == out_dim` (`DimensionMismatch`); `weight_section`:
    /// `experts x out` weights; then biases and records.
    fn bind(payload: &'a [u8], desc: LayerDesc, index: u8) -> Result<Self> {
        if desc.in_dim != desc.out_dim {
            return Err(Error::DimensionMismatch { layer: index });
        }
        if desc.weights == WeightFormat::I8Interleaved {
            return Err(Error::UnsupportedParameter { layer: index });
        }
        check_dims(&desc, index)?;
        let s = Sections::new(payload, index);
        let weights = s.get(
            desc.weight_section,
            u64::from(desc.experts) * u64::from(desc.out_dim) * desc.weights.bytes() as u64,
        )?;
        let (bias, requant) = s.rows(&desc)?;
        Ok(DiagLayer {
            desc,
            weights,
            bias,
            requant,
            index,
        })
    }

    /// Records in range. No overflow proof is needed: every product
    /// `|w x| <= 2^30` and the sum with an (at most 64-bit) bias and the
    /// blend are done in saturating i64.
    fn check(&self, _gating: &Gating) -> Result<()> {
        check_requant(self.requant, self.desc.activation, self.index)
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

    /// One product per row; no scratch.
    fn run(&self, gate: &Gate, x: &[i16], _scratch: &mut [i16], y: &mut [i16]) -> Result<()> {
        self.run_rows(gate, x, y)
    }
}

/// The diagonal op's side of the test contract (`ops::contract`).
#[cfg(test)]
pub(crate) mod case {
    use super::DiagLayer;
    use crate::blob::{Gating, LayerDesc, LayerOp};
    use crate::error::Error;
    use crate::ops::contract::{
        finish, finish_float, fits, sat, OpCase, Payload, Rng, Rows, Shape,
    };

    /// A diagonal layer as plain integers.
    #[derive(Clone, Debug)]
    pub(crate) struct Diagonal {
        rows: Rows,
        /// `experts x n`, expert-major.
        w: Vec<i32>,
    }

    impl Diagonal {
        /// `sum_k g_k sat64(w_ki x_i + b_ki)`, saturated to i64 in gate
        /// order as the dense blend, and whether any saturation acted.
        fn total(&self, g: &[(usize, i128)], i: usize, x: &[i16]) -> (i128, bool) {
            let n = self.rows.shape.out_dim;
            let (mut total, mut exact) = (0i128, true);
            for &(k, gk) in g {
                let v = i128::from(self.w[k * n + i]) * i128::from(x[i]) + self.rows.bias(k, i);
                let term = sat(sat(v, 64) * gk, 64);
                exact &= fits(v, 64) && fits(v * gk, 64) && fits(total + term, 64);
                total = sat(total + term, 64);
            }
            (total, exact)
        }
    }

    impl OpCase for Diagonal {
        type Op<'a> = DiagLayer<'a>;

        fn random(rng: &mut Rng, mut shape: Shape, _gating: Gating) -> Self {
            shape.out_dim = shape.in_dim;
            let w = shape.weights(rng, shape.experts * shape.out_dim);
            let bias_log2 = if rng.chance(10) { 62 } else { 40 };
            Diagonal {
                rows: Rows::random(rng, shape, bias_log2),
                w,
            }
        }

        fn rows(&self) -> &Rows {
            &self.rows
        }

        fn encode(&self, p: &mut Payload) -> LayerDesc {
            let mut d = self.rows.shape.desc(LayerOp::Diagonal);
            d.weight_section = p.weights(&self.w, d.weights);
            self.rows.encode(p, &mut d);
            d
        }

        /// `y_i = act(requant(sum_k g_k (w_ki x_i + b_ki)))` with the dense
        /// layer's saturations (`docs/cp-and-styles.md`). The op claims
        /// nothing that could fail: `|w x| <= 2^30`, all else saturates.
        fn reference(&self, g: &[(usize, i128)], x: &[i16]) -> (Vec<i16>, bool) {
            let s = self.rows.shape;
            let y = (0..s.out_dim)
                .map(|i| finish(self.total(g, i, x).0, &self.rows.requant[i], s.activation))
                .collect();
            (y, true)
        }

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

        /// Every weight at the format's minimum, biases at their extremes.
        fn worst_case(rng: &mut Rng, shape: Shape, gating: Gating) -> (Self, Vec<Vec<i16>>) {
            let mut case = Diagonal::random(rng, shape, gating);
            let (lo, _) = case.rows.shape.weight_range();
            case.w.iter_mut().for_each(|w| *w = lo as i32);
            case.rows.extreme_biases(rng);
            let n = case.rows.shape.in_dim;
            let inputs = vec![vec![i16::MIN; n], vec![i16::MAX; n], rng.inputs(n)];
            (case, inputs)
        }

        /// No weight or bias can overflow (see `reference`); only the
        /// output records can be out of range, which the contract checks
        /// for every op.
        fn past_the_bound(_worst: &Self, _gating: Gating) -> Vec<(Self, Error)> {
            Vec::new()
        }
    }
}
