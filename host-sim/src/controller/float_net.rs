//! The float network behind the controller's `Network` trait, in f64 (the
//! reference) and in f32 (to measure what rounding alone does).

use exporter::net::{ExpertLayer, GatingMode, Net};
use phasegate_controller::{Network, Result};
use std::f64::consts::TAU;

/// The f64 reference network (`Net::forward`).
pub struct FloatNet64<'a>(pub &'a Net);

impl Network<f64> for FloatNet64<'_> {
    fn input_dim(&self) -> usize {
        self.0.xmean.len()
    }

    fn output_dim(&self) -> usize {
        self.0.ymean.len()
    }

    fn predict(&mut self, phase: f64, x: &[f64], y: &mut [f64]) -> Result<()> {
        let out = self.0.forward(x, phase * TAU);
        for (d, s) in y.iter_mut().zip(out) {
            *d = s;
        }
        Ok(())
    }

    fn mean_output(&self, y: &mut [f64]) -> Result<()> {
        for (d, &s) in y.iter_mut().zip(&self.0.ymean) {
            *d = s;
        }
        Ok(())
    }
}

/// One layer's experts, row-major f32.
struct Layer32 {
    rows: usize,
    cols: usize,
    w: Vec<Vec<f32>>,
    b: Vec<Vec<f32>>,
}

/// The float network with every weight and statistic rounded to f32 and
/// every operation done in f32, the same operations in the same order as
/// `Net::forward` (normalise, `sum_k g_k (W_k x + b_k)`, ELU, ...).
/// The gate is computed in f64 by `Net::gate` and rounded: it is a
/// function of the phase only, not a source of divergence worth modelling.
pub struct FloatNet32 {
    mode: GatingMode,
    experts: usize,
    xmean: Vec<f32>,
    xstd: Vec<f32>,
    ymean: Vec<f32>,
    ystd: Vec<f32>,
    layers: Vec<Layer32>,
}

impl FloatNet32 {
    /// Rounds `net` to f32; its layers must be dense.
    pub fn new(net: &Net) -> anyhow::Result<Self> {
        let v = |a: &ndarray::Array1<f64>| a.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        let dense = net
            .layers
            .iter()
            .enumerate()
            .map(|(i, l)| {
                l.as_dense().ok_or_else(|| {
                    anyhow::anyhow!(
                        "the f32 controller needs dense layers; layer {i} is {}",
                        l.form()
                    )
                })
            })
            .collect::<anyhow::Result<Vec<&ExpertLayer>>>()?;
        let layers = dense
            .into_iter()
            .map(|l| Layer32 {
                rows: l.w.first().map_or(0, |w| w.nrows()),
                cols: l.w.first().map_or(0, |w| w.ncols()),
                w: l.w
                    .iter()
                    .map(|w| w.iter().map(|&x| x as f32).collect())
                    .collect(),
                b: l.b.iter().map(v).collect(),
            })
            .collect();
        Ok(FloatNet32 {
            mode: net.mode,
            experts: net.experts(),
            xmean: v(&net.xmean),
            xstd: v(&net.xstd),
            ymean: v(&net.ymean),
            ystd: v(&net.ystd),
            layers,
        })
    }

    /// Raw model units in and out, f32 throughout.
    pub fn forward(&self, x: &[f32], phase_rad: f64) -> Vec<f32> {
        let gate: Vec<(usize, f32)> = self
            .mode
            .gate(self.experts, phase_rad)
            .into_iter()
            .map(|(k, g)| (k, g as f32))
            .collect();
        let mut h: Vec<f32> = x
            .iter()
            .zip(&self.xmean)
            .zip(&self.xstd)
            .map(|((&x, &m), &s)| (x - m) / s)
            .collect();
        let last = self.layers.len().saturating_sub(1);
        for (li, l) in self.layers.iter().enumerate() {
            let mut out = vec![0f32; l.rows];
            for &(k, g) in &gate {
                for (r, o) in out.iter_mut().enumerate() {
                    let row = &l.w[k][r * l.cols..(r + 1) * l.cols];
                    let dot: f32 = row.iter().zip(&h).map(|(a, b)| a * b).sum();
                    *o += g * dot;
                }
                for (o, &b) in out.iter_mut().zip(&l.b[k]) {
                    *o += g * b;
                }
            }
            if li != last {
                for v in out.iter_mut() {
                    if *v <= 0.0 {
                        *v = v.exp_m1();
                    }
                }
            }
            h = out;
        }
        h.iter()
            .zip(&self.ystd)
            .zip(&self.ymean)
            .map(|((&y, &s), &m)| y * s + m)
            .collect()
    }
}

impl Network<f32> for FloatNet32 {
    fn input_dim(&self) -> usize {
        self.xmean.len()
    }

    fn output_dim(&self) -> usize {
        self.ymean.len()
    }

    fn predict(&mut self, phase: f32, x: &[f32], y: &mut [f32]) -> Result<()> {
        let out = self.forward(x, f64::from(phase) * TAU);
        for (d, s) in y.iter_mut().zip(out) {
            *d = s;
        }
        Ok(())
    }

    fn mean_output(&self, y: &mut [f32]) -> Result<()> {
        for (d, &s) in y.iter_mut().zip(&self.ymean) {
            *d = s;
        }
        Ok(())
    }
}
