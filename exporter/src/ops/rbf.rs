//! The gated RBF op (OMG's RBF-CAT clustering layer):
//! `y_j = sum_k g_k (exp(-sigma_kj^2 |x - c_kj|^2) + b_kj)`.
//!
//! Quantisation (`docs/graph-format.md`, "The RBF op"): the centres are
//! stored in their inputs' own formats, always as int16 (an int8 centre in
//! a Q12 input format could not leave `[-0.03, 0.03]`; they are a few
//! hundred values), each input's squared difference is aligned to the
//! finest input format by a shift, and `sigma^2` becomes a 32-bit
//! multiplier and a shift that map the squared distance to a position in
//! the exp table. The accumulator is `psi` in Q31.

use ndarray::{Array1, Array2};
use phasegate::blob::{AccWidth, LayerOp, RbfScale, Section, WeightFormat};
use phasegate::ops::cp::gate_l1_max;
use phasegate::ops::rbf::MAX_ALIGN;

use crate::lower::qmodel::QLayer;
use crate::quantise::{
    layer_desc, layer_report, requant_for, LayerSpec, QuantError, QuantLayerReport,
};

/// Accumulator units per real unit of `psi`.
const PSI_SCALE: f64 = 2_147_483_648.0;

/// Table positions per real unit of `u = sigma^2 |x - c|^2` (64 samples
/// per unit, Q16 between samples).
const POSITIONS_PER_UNIT: f64 = 4_194_304.0;

/// A gated RBF layer.
#[derive(Clone, Debug, PartialEq)]
pub struct RbfLayer {
    /// `K` matrices of centres, one row per output (`out x in`).
    pub centres: Vec<Array2<f64>>,
    /// `K` vectors of `sigma` per output.
    pub sigma: Vec<Array1<f64>>,
    /// `K` biases per output (0 for OMG's clustering layer).
    pub b: Vec<Array1<f64>>,
}

impl RbfLayer {
    /// `y`.
    pub fn apply(&self, gate: &[(usize, f64)], x: &Array1<f64>) -> Array1<f64> {
        let out = self.centres.first().map_or(0, Array2::nrows);
        let mut y = Array1::zeros(out);
        for &(k, g) in gate {
            for (j, c) in self.centres[k].rows().into_iter().enumerate() {
                let d2: f64 = c.iter().zip(x).map(|(c, x)| (x - c).powi(2)).sum();
                y[j] += g * ((-self.sigma[k][j].powi(2) * d2).exp() + self.b[k][j]);
            }
        }
        y
    }
}

/// The scale record of `sigma` for squared distances in units of
/// `2^-2 finest`: `m / 2^s = sigma^2 2^22 / 4^finest` with `m` as close to
/// 2^32 as the shift range allows.
fn scale_record(sigma: f64, finest: i32) -> RbfScale {
    let real = sigma * sigma * POSITIONS_PER_UNIT / 4f64.powi(finest);
    if !(real.is_finite() && real > 0.0) {
        return RbfScale {
            multiplier: 0,
            shift: 0,
        };
    }
    let max_shift = i32::from(phasegate::blob::RbfScale::MAX_SHIFT);
    let mut shift = (31 - real.log2().floor() as i32).clamp(0, max_shift);
    let mut m = (real * 2f64.powi(shift)).round();
    while m > f64::from(u32::MAX) && shift > 0 {
        shift -= 1;
        m = (real * 2f64.powi(shift)).round();
    }
    RbfScale {
        multiplier: m.min(f64::from(u32::MAX)) as u32,
        shift: shift as u8,
    }
}

/// Quantises an RBF layer for `spec` (centres int16 whatever `spec.format`).
pub fn quantise(
    l: &RbfLayer,
    spec: &LayerSpec<'_>,
) -> Result<(QLayer, QuantLayerReport), QuantError> {
    quantise_as(
        l,
        spec,
        LayerOp::Rbf {
            scales: Section::default(),
            align: Section::default(),
        },
        "rbf",
    )
}

/// Quantises the centres, scales (`sigma^2`) and biases of `l` under the
/// header variant `op` (RBF, or DEC with `sigma = 1`, whose `psi` is also
/// at most `2^31`), named `form` in the report.
pub(crate) fn quantise_as(
    l: &RbfLayer,
    spec: &LayerSpec<'_>,
    op: LayerOp,
    form: &'static str,
) -> Result<(QLayer, QuantLayerReport), QuantError> {
    let experts = l.centres.len();
    let (out, inp) = l.centres.first().map_or((0, 0), Array2::dim);
    let invalid = |why: String| QuantError::Invalid(format!("layer {}: {why}", spec.index));
    // Input formats are powers of two: each input's alignment is the
    // difference of its format and the finest.
    let fracs: Vec<i32> = spec.in_scales[..inp]
        .iter()
        .map(|s| s.log2().round() as i32)
        .collect();
    if let Some(i) =
        (0..inp).find(|&i| (f64::from(fracs[i]).exp2() - spec.in_scales[i]).abs() > 0.0)
    {
        return Err(invalid(format!(
            "{form} input {i} has scale {}, not a power of two",
            spec.in_scales[i]
        )));
    }
    let finest = fracs.iter().copied().max().unwrap_or(0);
    let align: Vec<u8> = fracs
        .iter()
        .map(|&f| u8::try_from(finest - f).ok().filter(|&a| a <= MAX_ALIGN))
        .collect::<Option<_>>()
        .ok_or_else(|| {
            invalid(format!(
                "{form} inputs' formats differ by more than {MAX_ALIGN} bits"
            ))
        })?;
    let mut centres = vec![0i32; experts * out * inp];
    let mut bias = vec![0i64; experts * out];
    let mut scales = Vec::with_capacity(experts * out);
    let (mut sig, mut noise) = (0.0, 0.0);
    let mut worst = 0u128;
    for k in 0..experts {
        for j in 0..out {
            let row = k * out + j;
            for i in 0..inp {
                let c = l.centres[k][[j, i]];
                let q = (c * spec.in_scales[i]).round().clamp(-32767.0, 32767.0);
                centres[row * inp + i] = q as i32;
                sig += c * c;
                noise += (c - q / spec.in_scales[i]).powi(2);
            }
            scales.push(scale_record(l.sigma[k][j], finest));
            bias[row] = (l.b[k][j] * PSI_SCALE).round() as i64;
            worst = worst.max((1u128 << 31) + u128::from(bias[row].unsigned_abs()));
        }
    }
    let acc = if bias.iter().all(|&b| i32::try_from(b).is_ok()) {
        AccWidth::I32
    } else {
        AccWidth::I64
    };
    let g1 = gate_l1_max(&spec.gating) as u128;
    let requant = (0..out)
        .map(|j| requant_for(spec, j, PSI_SCALE, worst * g1))
        .collect::<Result<_, _>>()?;
    let mut desc = layer_desc(spec, op, inp, out, experts, acc);
    desc.weights = WeightFormat::I16;
    let ql = QLayer {
        desc,
        weights: centres,
        bias,
        requant,
        cp: None,
        rbf: Some(QRbf { scales, align }),
        gated: spec.gated,
    };
    let rep = layer_report(spec, &ql, form, None, sig, noise);
    Ok((ql, rep))
}

pub use crate::lower::qmodel::QRbf;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scale_records_carry_sigma_to_32_bits() {
        for (sigma, finest) in [(0.3, 12), (0.01, 14), (2.0, 0), (1e-6, 15)] {
            let r = scale_record(sigma, finest);
            let real = sigma * sigma * POSITIONS_PER_UNIT / 4f64.powi(finest);
            let got = f64::from(r.multiplier) / 2f64.powi(i32::from(r.shift));
            assert!(
                (got / real - 1.0).abs() < 1e-9,
                "{sigma} {finest}: {got} vs {real}"
            );
            assert!(r.multiplier >= 1 << 31 || r.shift == RbfScale::MAX_SHIFT);
        }
        assert_eq!(scale_record(0.0, 12).multiplier, 0);
    }

    #[test]
    fn apply_is_the_gaussian_of_the_distance() {
        let l = RbfLayer {
            centres: vec![Array2::from_shape_vec((2, 2), vec![0.0, 0.0, 1.0, 2.0]).unwrap()],
            sigma: vec![Array1::from(vec![0.5, 2.0])],
            b: vec![Array1::zeros(2)],
        };
        let y = l.apply(&[(0, 1.0)], &Array1::from(vec![1.0, 1.0]));
        assert!((y[0] - (-0.25f64 * 2.0).exp()).abs() < 1e-15);
        assert!((y[1] - (-4.0f64 * 1.0).exp()).abs() < 1e-15);
    }
}
