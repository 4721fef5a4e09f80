//! Inputs drawn from the model's normalisation statistics, and the value
//! ranges the float network reaches on them. The quantiser picks every
//! activation format from these ranges; the accuracy checks reuse the same
//! sampler so that both speak of the same input distribution.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use std::f64::consts::TAU;

use crate::float_pfnn::FloatPfnn;

/// Raw inputs (model units) and phases (radians).
#[derive(Clone, Debug, Default)]
pub struct Samples {
    /// One input vector per sample.
    pub inputs: Vec<Vec<f64>>,
    /// One phase per sample, uniform in `[0, 2 pi)`.
    pub phases: Vec<f64>,
}

/// `n` inputs `mean + std * N(0, 1) * scale` with uniform random phases,
/// from a ChaCha8 stream seeded by `seed` (same on every platform).
pub fn normal_inputs(mean: &[f64], std: &[f64], n: usize, scale: f64, seed: u64) -> Samples {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut s = Samples::default();
    for _ in 0..n {
        let x = mean
            .iter()
            .zip(std)
            .map(|(&m, &sd)| m + sd * rng.sample::<f64, _>(StandardNormal) * scale)
            .collect();
        s.inputs.push(x);
        s.phases.push(rng.gen_range(0.0..TAU));
    }
    s
}

/// Largest magnitudes the float network reached.
#[derive(Clone, Debug, PartialEq)]
pub struct Ranges {
    /// Max |normalised input| per input column.
    pub input: Vec<f64>,
    /// Max |pre-activation| per layer (all rows).
    pub layer: Vec<f64>,
    /// Max |pre-activation| per row, per layer.
    pub rows: Vec<Vec<f64>>,
    /// Mean square of each layer's input columns (normalised inputs for
    /// layer 0, the previous layer's activations after).
    pub input_ms: Vec<Vec<f64>>,
}

/// Runs `net` on every sample and records the ranges.
pub fn measure_ranges(net: &FloatPfnn, samples: &Samples) -> Ranges {
    let mut r = Ranges {
        input: vec![0.0; net.input_dim()],
        layer: vec![0.0; net.layers.len()],
        rows: net
            .layers
            .iter()
            .map(|l| vec![0.0; l.w.first().map_or(0, |w| w.nrows())])
            .collect(),
        input_ms: net
            .layers
            .iter()
            .map(|l| vec![0.0; l.w.first().map_or(0, |w| w.ncols())])
            .collect(),
    };
    let n = samples.inputs.len().max(1) as f64;
    for (x, &p) in samples.inputs.iter().zip(&samples.phases) {
        let t = net.forward_trace(x, p);
        for (l, ms) in r.input_ms.iter_mut().enumerate() {
            let inputs: Vec<f64> = match l {
                0 => t.x_norm.clone(),
                _ => t.pre[l - 1]
                    .iter()
                    .map(|&v| crate::float_pfnn::elu(v))
                    .collect(),
            };
            for (m, v) in ms.iter_mut().zip(inputs) {
                *m += v * v / n;
            }
        }
        for (m, v) in r.input.iter_mut().zip(&t.x_norm) {
            *m = m.max(v.abs());
        }
        for (l, pre) in t.pre.iter().enumerate() {
            for (m, v) in r.rows[l].iter_mut().zip(pre) {
                *m = m.max(v.abs());
            }
            r.layer[l] = r.rows[l].iter().copied().fold(0.0, f64::max);
        }
    }
    r
}
