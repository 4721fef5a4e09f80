//! The CP-decomposed gated op: `W_k = A diag(d_k) B^T`, so
//! `y = A ((sum_k g_k d_k) . (B^T x)) + sum_k g_k b_k`; `W` is never expanded.
//!
//! Quantised like every op ([`crate::quantise`]): symmetric weights with one
//! scale per stored row, biases in accumulator units, the input columns'
//! scales absorbed into the weights, per-row output formats from the
//! pipeline. What CP layers add:
//!
//! * `B^T` gets one scale per rank component `sB_r`, the cores `d_k[r]`
//!   (int16 always: they are tiny) one per component `sD_r`, shared by the
//!   experts so the gate blends them before any rounding;
//! * the middle vector `u_r = c_r t_r` gets its own free int16 scale `zs_r`
//!   from calibration, and `A`'s columns absorb `1 / zs_r`;
//! * every shift is chosen from worst-case bounds over all i16 inputs and
//!   all phases, with the same formulas the loader re-checks
//!   (`phasegate::ops::cp::CpLayer::check`), so a blob this writes is
//!   never refused and never saturates before its final i16.

use ndarray::{Array1, Array2, ArrayView2, Axis};
use phasegate::blob::{AccWidth, LayerOp, Section};
use phasegate::ops::cp::{gate_l1_max, MidRecord};

use crate::cp::als::{cp_als, sort_components, AlsOptions, AlsResult};
use crate::lower::qmodel::{QCp, QLayer};
use crate::ops::dense::ExpertLayer;
use crate::ops::dense::{integer_moments, round_compensated, target_weights};
use crate::quantise::moments::Sequential;
use crate::quantise::{
    fixed_multiplier, layer_desc, layer_report, qmax, quantise_rows, requant_for, shift_to_i32,
    LayerSpec, QuantError, QuantLayerReport, Rows, I32_MAX,
};

const ACT_MAX: f64 = 32767.0;

/// A CP-decomposed gated layer: `W_k = A diag(d_k) B^T`, so
/// `y = A ((sum_k g_k d_k) . (B^T x)) + sum_k g_k b_k`.
#[derive(Clone, Debug, PartialEq)]
pub struct CpLayer {
    /// `out x R`.
    pub a: Array2<f64>,
    /// `in x R`.
    pub b: Array2<f64>,
    /// `K x R`: row k is the core `d_k` of expert k.
    pub d: Array2<f64>,
    /// `K` biases of `out`.
    pub bias: Vec<Array1<f64>>,
}

impl CpLayer {
    /// Rank `R`.
    pub fn rank(&self) -> usize {
        self.a.ncols()
    }

    /// Expert count `K`.
    pub fn experts(&self) -> usize {
        self.d.nrows()
    }

    /// The middle vector `u = (sum_k g_k d_k) . (B^T x)`.
    pub fn middle(&self, gate: &[(usize, f64)], x: &Array1<f64>) -> Array1<f64> {
        let mut c = Array1::zeros(self.rank());
        for &(k, g) in gate {
            c.scaled_add(g, &self.d.row(k));
        }
        self.b.t().dot(x) * c
    }

    /// `y` and the middle vector `u`.
    pub fn apply_mid(&self, gate: &[(usize, f64)], x: &Array1<f64>) -> (Array1<f64>, Array1<f64>) {
        let u = self.middle(gate, x);
        let mut y = self.a.dot(&u);
        for &(k, g) in gate {
            y.scaled_add(g, &self.bias[k]);
        }
        (y, u)
    }

    /// The dense weights of expert `k` (for tests and error reports).
    pub fn expert(&self, k: usize) -> Array2<f64> {
        (&self.a * &self.d.row(k)).dot(&self.b.t())
    }

    /// Decomposes a dense layer at rank `rank`: the experts' weights,
    /// stacked `out x in x K`, by CP-ALS; the biases are kept as they are.
    pub fn decompose(layer: &ExpertLayer, rank: usize, opts: &AlsOptions) -> (CpLayer, AlsResult) {
        let mut res = cp_als(&layer.w, rank, opts);
        sort_components(&mut res.factors);
        let f = &res.factors;
        let cp = CpLayer {
            a: f.a.clone(),
            b: f.b.clone(),
            d: f.c.clone(),
            bias: layer.b.clone(),
        };
        (cp, res)
    }
}

/// Extra headroom of CP middle vectors over the rows' (a product of two
/// calibrated quantities has heavier tails than either; measured on the
/// real PFNN, 1.5x of the calibrated maximum saturates a few values in a
/// few hundred frames, 4x none).
pub const MID_HEADROOM_FACTOR: f64 = 2.5;

/// Re-rounds `rows`' integer weights (their scales kept) for the least
/// output error, as [`crate::ops::dense`] rounds dense weights: `h` the
/// second moments of their input as the blob computes it, `cross` (where
/// that differs from the float network's) its cross moments with the float
/// input, both real units, `u` integer units per real unit. The L1 norms
/// and the noise follow.
#[allow(clippy::too_many_arguments)]
fn compensate(
    rows: &mut Rows,
    n_rows: usize,
    cols: usize,
    q: f64,
    f: impl Fn(usize, usize) -> f64,
    h: &Array2<f64>,
    cross: Option<&Array2<f64>>,
    u: &[f64],
) {
    let exact = Array2::from_shape_fn((n_rows, cols), |(i, j)| f(i, j) * rows.scales[i]);
    let h = integer_moments(h, u);
    let target = cross
        .and_then(|c| target_weights(&exact, &h, &integer_moments(c, u)))
        .unwrap_or(exact);
    let Some(rounded) = round_compensated(&target, &h, q) else {
        return;
    };
    rows.noise = 0.0;
    for i in 0..n_rows {
        rows.l1[i] = 0;
        for j in 0..cols {
            let wq = rounded[(i, j)];
            rows.q[i * cols + j] = wq as i32;
            rows.l1[i] += wq.abs() as u64;
            rows.noise += (f(i, j) - wq / rows.scales[i]).powi(2);
        }
    }
}

/// `x^T y / rows`.
fn moment(x: &ArrayView2<'_, f64>, y: &ArrayView2<'_, f64>) -> Array2<f64> {
    x.t().dot(y) / x.nrows().max(1) as f64
}

/// Quantises a CP layer for `spec`.
pub fn quantise(
    l: &CpLayer,
    spec: &LayerSpec<'_>,
) -> Result<(QLayer, QuantLayerReport), QuantError> {
    quantise_with(l, spec, None).map(|(ql, rep, _)| (ql, rep))
}

/// [`quantise`] with both products rounded error-aware on `seq`'s samples
/// (`B^T` against the layer's input, `A` against the middle vector as the
/// quantised `B^T` and cores give it, each aimed at the float network's,
/// and `A`'s mean error taken off the biases: the gate sums to one), and
/// the layer as the blob computes it, in real units.
pub fn quantise_sequential(
    l: &CpLayer,
    spec: &LayerSpec<'_>,
    seq: &Sequential,
) -> Result<(QLayer, QuantLayerReport, CpLayer), QuantError> {
    quantise_with(l, spec, Some(seq))
}

fn quantise_with(
    l: &CpLayer,
    spec: &LayerSpec<'_>,
    seq: Option<&Sequential>,
) -> Result<(QLayer, QuantLayerReport, CpLayer), QuantError> {
    let (rank, experts) = (l.rank(), l.experts());
    let (out, inp) = (l.a.nrows(), l.b.nrows());
    let q = qmax(spec.format);
    let mid_max = spec.mid_max.ok_or_else(|| {
        QuantError::Invalid(format!(
            "layer {}: CP layer without calibration",
            spec.index
        ))
    })?;
    // B^T: one scale per component; the input columns' scales absorbed.
    let in_power: Option<Vec<f64>> = spec.in_power.map(|p| {
        p.iter()
            .zip(spec.in_scales)
            .map(|(m, u)| m * u * u)
            .collect()
    });
    let mut bt = quantise_rows(
        rank,
        inp,
        q,
        |r, j| l.b[(j, r)] / spec.in_scales[j],
        in_power.as_deref(),
    );
    if let Some((x, xq, _)) = seq.map(Sequential::inputs) {
        let input = xq.as_ref().unwrap_or(&x);
        let cross = xq.as_ref().map(|xq| moment(&x, xq));
        compensate(
            &mut bt,
            rank,
            inp,
            q,
            |r, j| l.b[(j, r)] / spec.in_scales[j],
            &moment(input, input),
            cross.as_ref(),
            spec.in_scales,
        );
    }
    let b_deq = Array2::from_shape_fn((inp, rank), |(j, r)| {
        f64::from(bt.q[r * inp + j]) * spec.in_scales[j] / bt.scales[r]
    });
    // Cores: int16, one scale per component shared by the experts.
    let mut cores = vec![0i16; experts * rank];
    let mut core_scales = vec![1.0; rank];
    let mut core_max = vec![0u64; rank];
    for r in 0..rank {
        let maxabs = (0..experts).map(|k| l.d[(k, r)].abs()).fold(0.0, f64::max);
        let s = if maxabs > 0.0 { ACT_MAX / maxabs } else { 1.0 };
        core_scales[r] = s;
        for k in 0..experts {
            let v = (l.d[(k, r)] * s).round().clamp(-ACT_MAX, ACT_MAX);
            cores[k * rank + r] = v as i16;
            core_max[r] = core_max[r].max(v.abs() as u64);
        }
    }
    // Middle formats: free scales from calibration.
    let zs: Vec<f64> = mid_max
        .iter()
        .map(|&m| {
            if m > 0.0 {
                ACT_MAX / (spec.headroom * MID_HEADROOM_FACTOR * m)
            } else {
                1.0
            }
        })
        .collect();
    let mid_power: Option<Vec<f64>> = spec
        .mid_power
        .map(|p| p.iter().zip(&zs).map(|(m, z)| m * z * z).collect());
    let a = quantise_rows(
        out,
        rank,
        q,
        |i, r| l.a[(i, r)] / zs[r],
        mid_power.as_deref(),
    );
    let d_deq = Array2::from_shape_fn((experts, rank), |(k, r)| {
        f64::from(cores[k * rank + r]) / core_scales[r]
    });
    let mut a = a;
    let mut a_mean_err = vec![0.0; out];
    if let Some((x, xq, g)) = seq.map(Sequential::inputs) {
        let blend = g.dot(&l.d);
        let u = x.dot(&l.b) * &blend;
        let uq = xq.as_ref().unwrap_or(&x).dot(&b_deq) * g.dot(&d_deq);
        let exact = |i: usize, r: usize| l.a[(i, r)] / zs[r];
        compensate(
            &mut a,
            out,
            rank,
            q,
            exact,
            &moment(&uq.view(), &uq.view()),
            Some(&moment(&u.view(), &uq.view())),
            &zs,
        );
        let n = x.nrows().max(1) as f64;
        let (mean_u, mean_uq) = (u.sum_axis(Axis(0)) / n, uq.sum_axis(Axis(0)) / n);
        for (i, e) in a_mean_err.iter_mut().enumerate() {
            *e = (0..rank)
                .map(|r| {
                    (f64::from(a.q[i * rank + r]) * mean_uq[r]
                        - exact(i, r) * a.scales[i] * mean_u[r])
                        * zs[r]
                })
                .sum();
        }
    }
    let mut bias = vec![0i64; experts * out];
    for k in 0..experts {
        for i in 0..out {
            bias[k * out + i] = (l.bias[k][i] * a.scales[i] - a_mean_err[i]).round() as i64;
        }
    }
    let fits = bt
        .l1
        .iter()
        .chain(&a.l1)
        .all(|&v| u128::from(v) << 15 <= I32_MAX)
        && bias.iter().all(|&b| i32::try_from(b).is_ok());
    let acc = if fits { AccWidth::I32 } else { AccWidth::I64 };
    let g1 = gate_l1_max(&spec.gating) as u128;
    let mut mid = Vec::with_capacity(rank);
    for r in 0..rank {
        let t_bound = u128::from(bt.l1[r]) << 15;
        let t_shift = shift_to_i32(t_bound);
        let t = (t_bound >> t_shift) + 1;
        let c = ((g1 * u128::from(core_max[r])) >> 16) + 1;
        let pre = shift_to_i32(t * c);
        let m_real = zs[r] * f64::from(t_shift).exp2() / (bt.scales[r] * core_scales[r])
            * f64::from(pre).exp2();
        let (multiplier, post_shift) = fixed_multiplier(m_real).ok_or(QuantError::Scale {
            layer: spec.index,
            row: r,
        })?;
        mid.push(MidRecord {
            multiplier,
            t_shift,
            pre_shift: pre,
            post_shift,
        });
    }
    let mut requant = Vec::with_capacity(out);
    for i in 0..out {
        let bmax = (0..experts)
            .map(|k| u128::from(bias[k * out + i].unsigned_abs()))
            .max()
            .unwrap_or(0);
        let bound = ((u128::from(a.l1[i]) << 15) << 16) + g1 * bmax;
        requant.push(requant_for(spec, i, a.scales[i], bound)?);
    }
    let dequantised = CpLayer {
        a: Array2::from_shape_fn((out, rank), |(i, r)| {
            f64::from(a.q[i * rank + r]) * zs[r] / a.scales[i]
        }),
        b: b_deq,
        d: d_deq,
        bias: (0..experts)
            .map(|k| Array1::from_shape_fn(out, |i| bias[k * out + i] as f64 / a.scales[i]))
            .collect(),
    };
    let ql = QLayer {
        desc: layer_desc(
            spec,
            LayerOp::Cp {
                rank: u16::try_from(rank)
                    .map_err(|_| QuantError::Invalid("rank above 65535".into()))?,
                a: Section::default(),
                cores: Section::default(),
                mid: Section::default(),
            },
            inp,
            out,
            experts,
            acc,
        ),
        weights: bt.q,
        bias,
        requant,
        cp: Some(QCp { a: a.q, cores, mid }),
        rbf: None,
        gated: spec.gated,
    };
    let rep = layer_report(
        spec,
        &ql,
        "cp",
        Some(rank),
        bt.sig + a.sig,
        bt.noise + a.noise,
    );
    Ok((ql, rep, dequantised))
}
