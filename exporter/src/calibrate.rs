//! Inputs drawn from the model's normalisation statistics, and the value
//! ranges the float network reaches on them. The quantiser picks every
//! activation format from these ranges; the accuracy checks reuse the same
//! sampler so that both speak of the same input distribution.

use ndarray::Array1;

use crate::net::Net;

pub use crate::io::samples::{normal_inputs, Samples};

/// Largest magnitudes and mean squares the float network reached, per
/// layer: what the quantiser picks every format from.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Ranges {
    /// Max |pre-activation| per row, per layer.
    pub rows: Vec<Vec<f64>>,
    /// Max |middle component| per CP layer.
    pub mids: Vec<Option<Vec<f64>>>,
    /// Mean square of each layer's input columns (normalised inputs for
    /// layer 0, the previous layer's activations after).
    pub input_ms: Vec<Vec<f64>>,
    /// Mean square of each CP layer's middle components.
    pub mid_ms: Vec<Option<Vec<f64>>>,
}

impl Ranges {
    /// Max |pre-activation| of layer `l` over all its rows.
    pub fn layer_max(&self, l: usize) -> f64 {
        self.rows
            .get(l)
            .map_or(0.0, |r| r.iter().copied().fold(0.0, f64::max))
    }
}

/// Adds `v_i^2 / n` to `acc_i` (grown to `v`'s length).
pub(crate) fn ms_into(acc: &mut Vec<f64>, v: &Array1<f64>, n: f64) {
    if acc.len() < v.len() {
        acc.resize(v.len(), 0.0);
    }
    for (m, x) in acc.iter_mut().zip(v) {
        *m += x * x / n;
    }
}

/// Raises `acc_i` to `|v_i|` (grown to `v`'s length).
pub(crate) fn max_into(acc: &mut Vec<f64>, v: &Array1<f64>) {
    if acc.len() < v.len() {
        acc.resize(v.len(), 0.0);
    }
    for (m, x) in acc.iter_mut().zip(v) {
        *m = m.max(x.abs());
    }
}

/// The calibration inputs of `net` under `opts`: as many normal samples as
/// its most demanding op needs ([`crate::net::NetLayer::calibration_samples`]).
pub fn calibration_inputs(net: &Net, opts: &crate::quantise::QuantOptions) -> Samples {
    let wanted = net
        .layers
        .iter()
        .map(crate::net::NetLayer::calibration_samples)
        .fold(opts.calibration_samples, usize::max);
    let mut s = normal_inputs(
        &net.xmean.to_vec(),
        &net.xstd.to_vec(),
        wanted,
        opts.calibration_scale,
        opts.seed,
    );
    if let Some(r) = &opts.calibration_data {
        s.extend(&r.samples);
    }
    s
}

/// Runs the chain `net` on every sample and records the ranges.
pub fn calibrate(net: &Net, samples: &Samples) -> Ranges {
    let n = net.layers.len();
    let mut r = Ranges {
        rows: vec![Vec::new(); n],
        mids: vec![None; n],
        input_ms: vec![Vec::new(); n],
        mid_ms: vec![None; n],
    };
    let count = samples.inputs.len().max(1) as f64;
    for (x, &p) in samples.inputs.iter().zip(&samples.phases) {
        let t = net.forward_trace(x, p);
        for l in 0..n {
            max_into(&mut r.rows[l], &t.pre[l]);
            ms_into(&mut r.input_ms[l], &t.inputs[l], count);
            if let Some(u) = &t.mids[l] {
                max_into(r.mids[l].get_or_insert_with(Vec::new), u);
                ms_into(r.mid_ms[l].get_or_insert_with(Vec::new), u, count);
            }
        }
    }
    r
}
