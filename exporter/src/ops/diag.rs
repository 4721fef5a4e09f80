//! The diagonal gated op (`in == out`): `y_i = sum_k g_k (w_ki x_i + b_ki)`.
//! Cheap per-feature gains, used as style adapters.

use ndarray::Array1;
use phasegate::blob::{AccWidth, LayerOp};
use phasegate::ops::cp::gate_l1_max;

use crate::lower::qmodel::QLayer;
use crate::quantise::{
    layer_desc, layer_report, qmax, requant_for, LayerSpec, QuantError, QuantLayerReport,
};

/// A diagonal gated layer (`in == out`): `y_i = sum_k g_k (w_ki x_i + b_ki)`.
#[derive(Clone, Debug, PartialEq)]
pub struct DiagLayer {
    /// `K` weight vectors.
    pub w: Vec<Array1<f64>>,
    /// `K` biases.
    pub b: Vec<Array1<f64>>,
}

impl DiagLayer {
    /// `y`.
    pub fn apply(&self, gate: &[(usize, f64)], x: &Array1<f64>) -> Array1<f64> {
        let mut y = Array1::zeros(x.len());
        for &(k, g) in gate {
            y.scaled_add(g, &(&self.w[k] * x + &self.b[k]));
        }
        y
    }
}

/// Quantises a diagonal layer for `spec`.
pub fn quantise(
    l: &DiagLayer,
    spec: &LayerSpec<'_>,
) -> Result<(QLayer, QuantLayerReport), QuantError> {
    let experts = l.w.len();
    let n = l.w.first().map_or(0, Array1::len);
    let q = qmax(spec.format);
    let mut weights = vec![0i32; experts * n];
    let mut bias = vec![0i64; experts * n];
    let (mut sig, mut noise) = (0.0, 0.0);
    let mut requant = Vec::with_capacity(n);
    let g1 = gate_l1_max(&spec.gating) as u128;
    let mut rows = Vec::with_capacity(n);
    for i in 0..n {
        let eff = |k: usize| l.w[k][i] / spec.in_scales[i];
        let maxabs = (0..experts).map(|k| eff(k).abs()).fold(0.0, f64::max);
        let s = if maxabs > 0.0 { q / maxabs } else { 1.0 };
        let mut worst = 0u128;
        for k in 0..experts {
            let wq = (eff(k) * s).round().clamp(-q, q);
            weights[k * n + i] = wq as i32;
            bias[k * n + i] = (l.b[k][i] * s).round() as i64;
            sig += eff(k).powi(2);
            noise += (eff(k) - wq / s).powi(2);
            worst = worst.max(
                (u128::from(wq.abs() as u64) << 15) + u128::from(bias[k * n + i].unsigned_abs()),
            );
        }
        rows.push((s, worst));
    }
    let acc = if bias.iter().all(|&b| i32::try_from(b).is_ok()) {
        AccWidth::I32
    } else {
        AccWidth::I64
    };
    for (i, &(s, worst)) in rows.iter().enumerate() {
        requant.push(requant_for(spec, i, s, worst * g1)?);
    }
    let ql = QLayer {
        desc: layer_desc(spec, LayerOp::Diagonal, n, n, experts, acc),
        weights,
        bias,
        requant,
        cp: None,
        rbf: None,
        gated: spec.gated,
    };
    let rep = layer_report(spec, &ql, "diagonal", None, sig, noise);
    Ok((ql, rep))
}
