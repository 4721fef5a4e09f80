//! The dense gated op: one `out x in` matrix and bias per expert,
//! `y = sum_k g_k (W_k x + b_k)`.
//!
//! Quantised with one scale per output row shared by the experts (so their
//! accumulators blend before a single requantisation), each row's scale
//! searched between "no weight clipped" and 1/0.6 of it for the least
//! expected output error on the calibrated inputs.

use nalgebra::DMatrix;
use ndarray::{Array1, Array2};
use phasegate::blob::{AccWidth, LayerOp, WeightFormat};
use phasegate::ops::cp::gate_l1_max;

use crate::lower::qmodel::QLayer;
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

/// Added to `H`'s diagonal, times its mean: calibration inputs are finite,
/// and without it the rounding overfits them. On the real PFNN int8, 0.05
/// gave the lowest output RMS of 0.001, 0.01, 0.05 and 0.2 (4,096 samples,
/// nearest-target rounding) and of 0.02, 0.05 and 0.1 (16,384 samples,
/// sequential rounding aimed at the float network).
const DAMPING: f64 = 0.05;

/// Below this mean gate an expert's bias is not corrected (its mean error
/// is divided by the mean gate).
const MIN_GATE_MEAN: f64 = 1e-3;

/// `E[g^2 a a^T]` of the integer inputs `a_j = x_j u_j`, from the moments
/// of `x` (real units) and the column scales `u`.
pub(crate) fn integer_moments(second: &Array2<f64>, u: &[f64]) -> Array2<f64> {
    Array2::from_shape_fn(second.dim(), |(j, l)| second[(j, l)] * u[j] * u[l])
}

/// Rounds `exact` (`out x in` integer weights before rounding) to integers
/// in `[-q, q]` column by column, folding each column's rounding error into
/// the columns not rounded yet so that `E[(dW a)^2] = dW H dW^T` stays
/// small, not only `|dW|` (GPTQ: Frantar et al., 2022, with columns taken
/// in decreasing order of `H_jj`, and [`DAMPING`]). `None` when `H` is not
/// positive definite even with the damping.
pub(crate) fn round_compensated(
    exact: &Array2<f64>,
    h: &Array2<f64>,
    q: f64,
) -> Option<Array2<f64>> {
    let (rows, n) = exact.dim();
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| h[(b, b)].total_cmp(&h[(a, a)]));
    let mean_diag = (0..n).map(|j| h[(j, j)]).sum::<f64>() / n.max(1) as f64;
    let damp = DAMPING * mean_diag.max(f64::MIN_POSITIVE);
    let hp = DMatrix::from_fn(n, n, |a, b| {
        let (j, l) = (order[a], order[b]);
        let v = h[(j, l)];
        match (a == b, v > 0.0) {
            (true, true) => v + damp,
            // A column that is always zero: any rounding is free there.
            (true, false) => 1.0,
            _ => v,
        }
    });
    let hinv = hp.cholesky()?.inverse();
    // Hinv = U^T U with U upper triangular: row a of U spreads column a's
    // error over the later columns.
    let u = hinv.cholesky()?.l().transpose();
    let mut w = DMatrix::from_fn(rows, n, |i, a| exact[(i, order[a])]);
    for a in 0..n {
        let d = u[(a, a)];
        for i in 0..rows {
            let v = w[(i, a)];
            let r = v.round().clamp(-q, q);
            w[(i, a)] = r;
            let err = (v - r) / d;
            for b in a + 1..n {
                w[(i, b)] -= err * u[(a, b)];
            }
        }
    }
    let mut out = Array2::zeros((rows, n));
    for (a, &j) in order.iter().enumerate() {
        for i in 0..rows {
            out[(i, j)] = w[(i, a)];
        }
    }
    Some(out)
}

/// What the layer's rounding should reproduce, in integer units: the
/// row-scaled weights themselves, or, when the input comes from quantised
/// layers before it (`FloatSide`), the weights that best map that input
/// to the float network's output, `E (C + l I) (H~ + l I)^-1` with
/// `C = E[g^2 a a~^T]`, `H~ = E[g^2 a~ a~^T]` (integer units) and a ridge
/// `l` ([`DAMPING`] times the mean of `H~`'s diagonal) that keeps the
/// target at the weights where the samples say little. `None` when the
/// system cannot be solved.
pub(crate) fn target_weights(
    exact: &Array2<f64>,
    h: &Array2<f64>,
    cross: &Array2<f64>,
) -> Option<Array2<f64>> {
    let n = h.nrows();
    let mean_diag = (0..n).map(|j| h[(j, j)]).sum::<f64>() / n.max(1) as f64;
    let ridge = DAMPING * mean_diag.max(f64::MIN_POSITIVE);
    let hr = DMatrix::from_fn(n, n, |a, b| h[(a, b)] + if a == b { ridge } else { 0.0 });
    // rhs = (C + l I)^T E^T, n x rows.
    let mut ct = cross.t().to_owned();
    ct.diag_mut().mapv_inplace(|v| v + ridge);
    let rhs = ct.dot(&exact.t());
    let rows = exact.nrows();
    let rhs = DMatrix::from_fn(n, rows, |l, i| rhs[(l, i)]);
    let t = hr.cholesky()?.solve(&rhs);
    Some(Array2::from_shape_fn((rows, n), |(i, l)| t[(l, i)]))
}

/// Quantises a dense layer for `spec`.
pub fn quantise(
    layer: &ExpertLayer,
    spec: &LayerSpec<'_>,
) -> Result<(QLayer, QuantLayerReport), QuantError> {
    quantise_dequantised(layer, spec).map(|(ql, rep, _)| (ql, rep))
}

/// [`quantise`], and the layer as the blob computes it, in real units (its
/// integer weights and biases scaled back): what the layers after it see.
pub fn quantise_dequantised(
    layer: &ExpertLayer,
    spec: &LayerSpec<'_>,
) -> Result<(QLayer, QuantLayerReport, ExpertLayer), QuantError> {
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
    let mut l1 = vec![vec![0i64; experts]; out_dim];
    let (mut sig, mut noise) = (0.0f64, 0.0f64);
    let scales: Vec<f64> = (0..out_dim)
        .map(|i| {
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
            if maxabs > 0.0 {
                best_row_scale(&row, q / maxabs, q, &power)
            } else {
                1.0
            }
        })
        .collect();
    // Error-aware rounding pays off where the weight step is coarse.
    let moments = spec
        .in_moments
        .filter(|m| spec.format == WeightFormat::I8 && m.first.len() == experts);
    // Row-scaled weights of each expert in integer units, before rounding.
    let exact: Vec<Array2<f64>> = layer
        .w
        .iter()
        .map(|w| Array2::from_shape_fn((out_dim, in_dim), |(i, j)| eff(w[(i, j)], j) * scales[i]))
        .collect();
    let nearest = |e: &Array2<f64>| e.mapv(|v| v.round().clamp(-q, q));
    let rounded: Vec<Array2<f64>> = match moments {
        Some(m) => exact
            .iter()
            .enumerate()
            .map(|(k, e)| {
                let h = integer_moments(&m.second[k], spec.in_scales);
                let target = m
                    .float
                    .as_ref()
                    .and_then(|f| {
                        target_weights(e, &h, &integer_moments(&f.cross[k], spec.in_scales))
                    })
                    .unwrap_or_else(|| e.clone());
                round_compensated(&target, &h, q).unwrap_or_else(|| nearest(e))
            })
            .collect(),
        None => exact.iter().map(nearest).collect(),
    };
    let mut dequantised = ExpertLayer {
        w: vec![Array2::zeros((out_dim, in_dim)); experts],
        b: vec![Array1::zeros(out_dim); experts],
    };
    for (k, w) in layer.w.iter().enumerate() {
        let (exact, rounded) = (&exact[k], &rounded[k]);
        for i in 0..out_dim {
            let base = (k * out_dim + i) * in_dim;
            let mut b = layer.b[k][i] * scales[i];
            if let Some(m) = moments.filter(|m| m.gate_mean[k] > MIN_GATE_MEAN) {
                // Bias correction: the rounding's mean effect on this row
                // (against the float network's input where it differs), undone.
                let float_first = m.float.as_ref().map_or(&m.first[k], |f| &f.first[k]);
                let mean_err: f64 = (0..in_dim)
                    .map(|j| {
                        (rounded[(i, j)] * m.first[k][j] - exact[(i, j)] * float_first[j])
                            * spec.in_scales[j]
                    })
                    .sum();
                b -= mean_err / m.gate_mean[k];
            }
            for j in 0..in_dim {
                let wq = rounded[(i, j)];
                let v = eff(w[(i, j)], j);
                weights[base + j] = wq as i32;
                l1[i][k] += (wq as i64).abs();
                sig += v * v;
                noise += (v - wq / scales[i]).powi(2);
                dequantised.w[k][(i, j)] = wq / scales[i] * spec.in_scales[j];
            }
            bias[k * out_dim + i] = b.round() as i64;
            dequantised.b[k][i] = bias[k * out_dim + i] as f64 / scales[i];
        }
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
            .map(|k| i128::from(r[k]) * 32768 + i128::from(bias[k * out_dim + i].unsigned_abs()))
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
        rbf: None,
        gated: spec.gated,
    };
    let mut rep = layer_report(spec, &ql, "dense", None, sig, noise);
    rep.max_dot_bits = Some(max_dot);
    rep.max_blend_bits = Some(max_blend);
    Ok((ql, rep, dequantised))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// `sum_i dW_i H dW_i^T`: the expected squared output error.
    fn cost(exact: &Array2<f64>, rounded: &Array2<f64>, h: &Array2<f64>) -> f64 {
        let d = rounded - exact;
        (&d.dot(h) * &d).sum()
    }

    fn weights(rows: usize, cols: usize, rng: &mut ChaCha8Rng) -> Array2<f64> {
        Array2::from_shape_fn((rows, cols), |_| rng.gen_range(-127.0..127.0))
    }

    /// Correlated inputs (few underlying factors, like a hidden layer's
    /// activations): compensation leaves much less output error than
    /// rounding to nearest, on fresh inputs too, and stays in range.
    #[test]
    fn compensated_rounding_beats_nearest_on_correlated_inputs() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (cols, factors) = (48, 12);
        let mix = Array2::from_shape_fn((factors, cols), |_| rng.gen_range(-1.0..1.0));
        let moments = |n: usize, rng: &mut ChaCha8Rng| {
            let f = Array2::from_shape_fn((n, factors), |_| rng.gen_range(-1.0..1.0));
            let x = f.dot(&mix) + Array2::from_shape_fn((n, cols), |_| rng.gen_range(-0.05..0.05));
            x.t().dot(&x) / n as f64
        };
        let (fit, check) = (moments(4000, &mut rng), moments(4000, &mut rng));
        let exact = weights(16, cols, &mut rng);
        let nearest = exact.mapv(|v| v.round().clamp(-127.0, 127.0));
        let comp = round_compensated(&exact, &fit, 127.0).unwrap();
        assert!(comp.iter().all(|v| v.fract() == 0.0 && v.abs() <= 127.0));
        let (a, b) = (cost(&exact, &comp, &check), cost(&exact, &nearest, &check));
        assert!(a < 0.5 * b, "compensated {a} vs nearest {b}");
    }

    /// Where the quantised chain's input is the float one (`C = H`), the
    /// target is the weights themselves; where it is the float input
    /// scaled by 2, the target is half the weights (the ridge aside).
    #[test]
    fn target_weights_undo_a_distorted_input() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let exact = weights(5, 6, &mut rng);
        let f = Array2::from_shape_fn((6, 6), |_| rng.gen_range(-1.0..1.0));
        let h = f.t().dot(&f) + Array2::<f64>::eye(6) * 10.0;
        let same = target_weights(&exact, &h, &h).unwrap();
        assert!(same.iter().zip(&exact).all(|(a, b)| (a - b).abs() < 1e-9));
        // x~ = 2x: H~ = 4H, C = E[x x~^T] = 2H.
        let half = target_weights(&exact, &(&h * 4.0), &(&h * 2.0)).unwrap();
        let rel = (&half - &(&exact * 0.5)).mapv(f64::abs).sum() / exact.mapv(f64::abs).sum();
        assert!(rel < 0.1, "{rel}");
    }

    /// Independent inputs: nothing to fold an error into, so the rounding
    /// is to nearest; a column no input ever reaches is rounded too.
    #[test]
    fn uncorrelated_inputs_round_to_nearest() {
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        let exact = weights(8, 10, &mut rng);
        let mut h = Array2::from_diag(&Array1::from_iter((0..10).map(|j| 1.0 + j as f64)));
        h[(3, 3)] = 0.0;
        let comp = round_compensated(&exact, &h, 127.0).unwrap();
        assert_eq!(comp, exact.mapv(|v| v.round().clamp(-127.0, 127.0)));
    }

    /// A bias far beyond any integer (here -1e300, which rounds and
    /// saturates to `i64::MIN`) is bounded by its magnitude, never by a
    /// negated `i64::MIN` (which overflows: a panic in a debug build; in a
    /// release build a negative bound, so a blob that requantises for the
    /// wrong range): no accumulator can hold the row, and the export says
    /// so. (F6 in `fuzz/README.md`.)
    #[test]
    fn a_saturated_bias_is_bounded_by_its_magnitude() {
        let golden = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../tests/golden/default/model.npz");
        let mut net = crate::npz::pfnn_from_npz(&golden, crate::net::GatingMode::Cubic).unwrap();
        let crate::ops::NetLayer::Dense(l) = &mut net.layers[0] else {
            panic!("the golden's first layer is dense");
        };
        l.b[0][0] = -1e300;
        let opts = crate::quantise::QuantOptions {
            calibration_samples: 16,
            ..Default::default()
        };
        let e = crate::export::export(&net, None, &opts).unwrap_err();
        assert_eq!(
            format!("{e:#}"),
            "layer 0 row 0: no accumulator can be proven not to overflow"
        );
    }
}
