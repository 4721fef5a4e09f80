//! The dense gated op: one `out x in` matrix and bias per expert,
//! `y = sum_k g_k (W_k x + b_k)`.
//!
//! Quantised with one scale per output row shared by the experts (so their
//! accumulators blend before a single requantisation), each row's scale
//! searched between "no weight clipped" and 1/0.6 of it for the least
//! expected output error on the calibrated inputs.

use ndarray::{Array1, Array2};
use phasegate::blob::{AccWidth, LayerOp};
use phasegate::ops::cp::gate_l1_max;

use crate::encode::QLayer;
use crate::quantise::{
    bits, layer_desc, layer_report, qmax, requant_for_blend, LayerSpec, QuantError,
    QuantLayerReport,
};

/// One layer as a set of experts that the gate blends. What an expert is
/// depends on the gating: a table (constant), a keyframe (linear), a
/// control point (cubic), or a softmax expert.
#[derive(Clone, Debug, PartialEq)]
pub struct ExpertLayer {
    /// `out x in` per expert.
    pub w: Vec<Array2<f64>>,
    /// `out` per expert.
    pub b: Vec<Array1<f64>>,
}

impl ExpertLayer {
    /// Number of experts.
    pub fn experts(&self) -> usize {
        self.w.len()
    }

    /// `(out, in)`.
    pub fn dim(&self) -> (usize, usize) {
        self.w.first().map_or((0, 0), Array2::dim)
    }

    /// `sum_k g_k (W_k x + b_k)` over the gate's experts.
    ///
    /// Equal to blending the weights first, `(sum g_k W_k) x + sum g_k b_k`,
    /// as the PFNN demo does, but needs no blended matrix: one mat-vec per
    /// active expert.
    ///
    /// # Panics
    /// If the gate names an expert `>= self.experts()` or `x` has the wrong
    /// length.
    pub fn apply(&self, gate: &[(usize, f64)], x: &Array1<f64>) -> Array1<f64> {
        let mut out = Array1::zeros(self.dim().0);
        for &(k, g) in gate {
            out.scaled_add(g, &self.w[k].dot(x));
            out.scaled_add(g, &self.b[k]);
        }
        out
    }
}

/// The row scale, between `max_scale` (no weight clipped) and 1/0.6 of it,
/// that minimises the row's expected output error from weight rounding and
/// clipping, `sum_k sum_j (w - q(w))^2 E[a_j^2]`. Clipping a few outlier
/// weights buys a finer step for all the others; with int8 this matters.
fn best_row_scale(row: &[(usize, f64)], max_scale: f64, q: f64, power: &[f64]) -> f64 {
    let row_err = |scale: f64| -> f64 {
        row.iter()
            .map(|&(j, v)| {
                let d = v - (v * scale).round().clamp(-q, q) / scale;
                d * d * power[j]
            })
            .sum()
    };
    (0..=40)
        .map(|step| max_scale / (1.0 - 0.01 * f64::from(step)))
        .map(|s| (row_err(s), s))
        .fold((f64::INFINITY, max_scale), |best, c| {
            if c.0 < best.0 {
                c
            } else {
                best
            }
        })
        .1
}

/// Quantises a dense layer for `spec`.
pub fn quantise(
    layer: &ExpertLayer,
    spec: &LayerSpec<'_>,
) -> Result<(QLayer, QuantLayerReport), QuantError> {
    let experts = layer.experts();
    let (out_dim, in_dim) = layer.dim();
    let q = qmax(spec.format);
    // The integer input of column j is x_j * in_scales[j]: its weights carry 1 / in_scales[j].
    let eff = |w: f64, j: usize| w / spec.in_scales[j];
    let power: Vec<f64> = match spec.in_power {
        Some(p) => p
            .iter()
            .zip(spec.in_scales)
            .map(|(m, u)| m * u * u)
            .collect(),
        None => vec![1.0; in_dim],
    };
    let mut weights = vec![0i32; experts * out_dim * in_dim];
    let mut bias = vec![0i64; experts * out_dim];
    let mut scales = Vec::with_capacity(out_dim);
    let mut l1 = vec![vec![0i64; experts]; out_dim];
    let (mut sig, mut noise) = (0.0f64, 0.0f64);
    for i in 0..out_dim {
        let row: Vec<(usize, f64)> = layer
            .w
            .iter()
            .flat_map(|w| {
                w.row(i)
                    .iter()
                    .enumerate()
                    .map(|(j, &v)| (j, eff(v, j)))
                    .collect::<Vec<_>>()
            })
            .collect();
        let maxabs = row.iter().map(|(_, v)| v.abs()).fold(0.0, f64::max);
        let scale = if maxabs > 0.0 {
            best_row_scale(&row, q / maxabs, q, &power)
        } else {
            1.0
        };
        for (k, w) in layer.w.iter().enumerate() {
            let base = (k * out_dim + i) * in_dim;
            for (j, &v) in w.row(i).iter().enumerate() {
                let v = eff(v, j);
                let wq = (v * scale).round().clamp(-q, q);
                weights[base + j] = wq as i32;
                l1[i][k] += (wq as i64).abs();
                sig += v * v;
                noise += (v - wq / scale).powi(2);
            }
            bias[k * out_dim + i] = (layer.b[k][i] * scale).round() as i64;
        }
        scales.push(scale);
    }
    // 32-bit accumulators when every row provably fits, else 64-bit.
    let fits_i32 = l1.iter().enumerate().all(|(i, r)| {
        r.iter().all(|&l| l << 15 <= i64::from(i32::MAX))
            && (0..experts).all(|k| i32::try_from(bias[k * out_dim + i]).is_ok())
    });
    let acc = if fits_i32 {
        AccWidth::I32
    } else {
        AccWidth::I64
    };
    // The largest sum_k |g_k| any phase gives (Q16), as the runtime bounds it.
    let gsum = gate_l1_max(&spec.gating);
    let mut requant = Vec::with_capacity(out_dim);
    let (mut max_dot, mut max_blend) = (0.0f64, 0.0f64);
    for (i, r) in l1.iter().enumerate() {
        let worst_expert = (0..experts)
            .map(|k| i128::from(r[k]) * 32768 + i128::from(bias[k * out_dim + i].abs()))
            .max()
            .unwrap_or(0);
        let blend = worst_expert * i128::from(gsum);
        max_dot = max_dot.max(bits(r.iter().copied().max().unwrap_or(0) as f64 * 32768.0));
        max_blend = max_blend.max(bits(blend as f64));
        requant.push(requant_for_blend(spec, i, scales[i], blend)?);
    }
    let ql = QLayer {
        desc: layer_desc(spec, LayerOp::Dense, in_dim, out_dim, experts, acc),
        weights,
        bias,
        requant,
        cp: None,
        gated: spec.gated,
    };
    let mut rep = layer_report(spec, &ql, "dense", None, sig, noise);
    rep.max_dot_bits = Some(max_dot);
    rep.max_blend_bits = Some(max_blend);
    Ok((ql, rep))
}
