//! The gated DEC op (OMG's DEC-CAT clustering layer, alpha = 1):
//! `y_j = sum_k g_k (q_kj + b_kj)`, `q_kj = t_kj / sum_l t_kl`,
//! `t_kj = 1 / (1 + |x - c_kj|^2)`, normalised over each expert's centres.
//!
//! Quantisation (`docs/graph-format.md`, "The DEC op"): the RBF op's
//! (centres in their inputs' formats as int16, alignment shifts, one scale
//! record per row) with `sigma = 1`; the accumulator is `q` in Q31.

use ndarray::{Array1, Array2};
use phasegate::blob::{LayerOp, Section};

use super::rbf::{quantise_as, RbfLayer};
use crate::lower::qmodel::QLayer;
use crate::quantise::{LayerSpec, QuantError, QuantLayerReport};

/// A gated DEC layer.
#[derive(Clone, Debug, PartialEq)]
pub struct DecLayer {
    /// `K` matrices of centres, one row per output (`out x in`).
    pub centres: Vec<Array2<f64>>,
    /// `K` biases per output (0 for OMG's clustering layer).
    pub b: Vec<Array1<f64>>,
}

impl DecLayer {
    /// Expert `k`'s `t_kj` at `x`, and their sum.
    fn kernel(&self, k: usize, x: &Array1<f64>) -> (Array1<f64>, f64) {
        let t: Array1<f64> = self.centres[k]
            .rows()
            .into_iter()
            .map(|c| {
                let d2: f64 = c.iter().zip(x).map(|(c, x)| (x - c).powi(2)).sum();
                1.0 / (1.0 + d2)
            })
            .collect();
        let sum = t.sum();
        (t, sum)
    }

    /// `y`.
    pub fn apply(&self, gate: &[(usize, f64)], x: &Array1<f64>) -> Array1<f64> {
        let out = self.centres.first().map_or(0, Array2::nrows);
        let mut y = Array1::zeros(out);
        for &(k, g) in gate {
            let (t, sum) = self.kernel(k, x);
            y += &((&t / sum + &self.b[k]) * g);
        }
        y
    }

    /// `dy/dx` applied to `dy` at `x`: with `q = t / S` and `dt_j/dx =
    /// -2 t_j^2 (x - c_j)`, `dx = sum_k g_k sum_j (dy_j - qbar_k) dt_kj/dx
    /// / S_k`, `qbar_k = sum_j dy_j q_kj`.
    pub fn backward(
        &self,
        gate: &[(usize, f64)],
        x: &Array1<f64>,
        dy: &Array1<f64>,
    ) -> Array1<f64> {
        let mut dx = Array1::zeros(x.len());
        for &(k, g) in gate {
            let (t, sum) = self.kernel(k, x);
            let qbar: f64 = dy.iter().zip(&t).map(|(d, t)| d * t / sum).sum();
            for ((c, &tj), &dyj) in self.centres[k].rows().into_iter().zip(&t).zip(dy) {
                let diff = x - &c;
                dx.scaled_add(-2.0 * tj * tj * (dyj - qbar) * g / sum, &diff);
            }
        }
        dx
    }

    /// The same centres as an RBF layer with `sigma = 1` (the shared
    /// quantisation of the distances).
    fn as_distances(&self) -> RbfLayer {
        RbfLayer {
            centres: self.centres.clone(),
            sigma: self
                .centres
                .iter()
                .map(|c| Array1::ones(c.nrows()))
                .collect(),
            b: self.b.clone(),
        }
    }
}

/// Quantises a DEC layer for `spec` (centres int16 whatever `spec.format`).
pub fn quantise(
    l: &DecLayer,
    spec: &LayerSpec<'_>,
) -> Result<(QLayer, QuantLayerReport), QuantError> {
    quantise_as(
        &l.as_distances(),
        spec,
        LayerOp::Dec {
            scales: Section::default(),
            align: Section::default(),
        },
        "dec",
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layer() -> DecLayer {
        DecLayer {
            centres: vec![
                Array2::from_shape_vec((3, 2), vec![0.0, 0.0, 1.0, 2.0, -1.0, 0.5]).unwrap(),
                Array2::from_shape_vec((3, 2), vec![0.5, 0.5, 0.0, -2.0, 3.0, 0.0]).unwrap(),
            ],
            b: vec![Array1::zeros(3), Array1::from(vec![0.1, 0.0, -0.1])],
        }
    }

    #[test]
    fn apply_is_the_normalised_student_kernel() {
        let l = layer();
        let x = Array1::from(vec![1.0, 1.0]);
        let y = l.apply(&[(0, 1.0)], &x);
        // Squared distances 2, 1 and 4.25.
        let t = [1.0 / 3.0, 1.0 / 2.0, 1.0 / 5.25];
        let s: f64 = t.iter().sum();
        for j in 0..3 {
            assert!((y[j] - t[j] / s).abs() < 1e-15, "{j}: {}", y[j]);
        }
        assert!((y.sum() - 1.0).abs() < 1e-15);
    }

    /// The analytic backward pass against central differences.
    #[test]
    fn backward_matches_finite_differences() {
        let l = layer();
        let gate = [(0, 0.3), (1, 0.7)];
        let x = Array1::from(vec![0.2, -0.4]);
        let dy = Array1::from(vec![1.0, -2.0, 0.5]);
        let dx = l.backward(&gate, &x, &dy);
        for i in 0..2 {
            let h = 1e-6;
            let (mut xp, mut xm) = (x.clone(), x.clone());
            xp[i] += h;
            xm[i] -= h;
            let num = (l.apply(&gate, &xp).dot(&dy) - l.apply(&gate, &xm).dot(&dy)) / (2.0 * h);
            assert!((dx[i] - num).abs() < 1e-8, "{i}: {} vs {num}", dx[i]);
        }
    }
}
