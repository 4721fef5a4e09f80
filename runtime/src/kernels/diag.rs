//! The phase-gated diagonal layer (`in_dim == out_dim`):
//! `y_i = act(requant(sum_k g_k (w_ki x_i + b_ki)))`, the cheapest residual
//! adapter form. Every product `|w x| <= 2^30` fits an i32, so no row needs
//! an accumulator proof; the blend is done in i64 like the dense kernel's.

use crate::blob::records::bias_at;
use crate::blob::{LayerDesc, WeightFormat, REQUANT_RECORD_LEN};
use crate::error::{Error, Result};
use crate::fixed::gate::Gate;
use crate::kernels::cp::i16_at;
use crate::kernels::dense::finish_row;

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

impl DiagLayer<'_> {
    fn weight(&self, k: usize, i: usize) -> i64 {
        let n = usize::from(self.desc.out_dim);
        let at = k * n + i;
        match self.desc.weights {
            WeightFormat::I8 => self.weights.get(at).map_or(0, |&b| i64::from(b as i8)),
            WeightFormat::I16 => i16_at(self.weights, at).map_or(0, i64::from),
        }
    }

    /// Runs the layer: `x` has `in_dim` elements, `y` at least `out_dim`.
    pub fn run(&self, gate: &Gate, x: &[i16], y: &mut [i16]) -> Result<()> {
        let n = usize::from(self.desc.out_dim);
        let x = x.get(..n).ok_or(Error::LengthMismatch {
            expected: n as u32,
            found: x.len() as u32,
        })?;
        let capacity = y.len() as u32;
        let y = y.get_mut(..n).ok_or(Error::BufferTooSmall {
            needed: n as u32,
            capacity,
        })?;
        let width = self.desc.acc.bytes();
        let recs = self.requant.as_chunks::<REQUANT_RECORD_LEN>().0;
        for (i, ((yi, &xi), rec)) in y.iter_mut().zip(x).zip(recs).enumerate() {
            let mut total = 0i64;
            for (e, g) in gate.iter() {
                let k = usize::from(e);
                let b = bias_at(self.bias, width, k * n + i).unwrap_or(0);
                let v = (self.weight(k, i) * i64::from(xi)).saturating_add(b);
                total = total.saturating_add(v.saturating_mul(i64::from(g)));
            }
            *yi = finish_row(total, rec, self.desc.activation);
        }
        Ok(())
    }
}
