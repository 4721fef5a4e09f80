//! Float reference of networks whose gated layers may be dense, CP or
//! diagonal, with optional residual adapters: what CP blobs and style blobs
//! are measured against, and what the quantiser calibrates them on.
//!
//! The arithmetic is that of [`crate::float_pfnn`]: f64, the same gate (the
//! demo's constant and linear modes, the exact Catmull-Rom spline of the
//! control points in cubic mode), ELU after every layer but the last.

use ndarray::{Array1, Array2, Axis};

use crate::control_points::{catmull_rom_weights, CONTROL_POINTS};
use crate::cp::als::{cp_als, sort_components, AlsOptions, AlsResult};
use crate::float_pfnn::{elu, wrap_phase, ExpertLayer, FloatPfnn, GatingMode};

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

/// A diagonal gated layer (`in == out`): `y_i = sum_k g_k (w_ki x_i + b_ki)`.
#[derive(Clone, Debug, PartialEq)]
pub struct DiagLayer {
    /// `K` weight vectors.
    pub w: Vec<Array1<f64>>,
    /// `K` biases.
    pub b: Vec<Array1<f64>>,
}

/// One gated layer of any form.
#[derive(Clone, Debug, PartialEq)]
pub enum NetLayer {
    /// One `out x in` matrix per expert.
    Dense(ExpertLayer),
    /// CP factors.
    Cp(CpLayer),
    /// One diagonal per expert.
    Diagonal(DiagLayer),
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

impl NetLayer {
    /// `y` (pre-activation) and, for CP layers, the middle vector.
    pub fn apply_mid(
        &self,
        gate: &[(usize, f64)],
        x: &Array1<f64>,
    ) -> (Array1<f64>, Option<Array1<f64>>) {
        match self {
            NetLayer::Dense(l) => (l.apply(gate, x), None),
            NetLayer::Cp(l) => {
                let (y, u) = l.apply_mid(gate, x);
                (y, Some(u))
            }
            NetLayer::Diagonal(l) => (l.apply(gate, x), None),
        }
    }

    /// `y` (pre-activation).
    pub fn apply(&self, gate: &[(usize, f64)], x: &Array1<f64>) -> Array1<f64> {
        self.apply_mid(gate, x).0
    }

    /// Input width.
    pub fn in_dim(&self) -> usize {
        match self {
            NetLayer::Dense(l) => l.w.first().map_or(0, |w| w.ncols()),
            NetLayer::Cp(l) => l.b.nrows(),
            NetLayer::Diagonal(l) => l.w.first().map_or(0, |w| w.len()),
        }
    }

    /// Output width.
    pub fn out_dim(&self) -> usize {
        match self {
            NetLayer::Dense(l) => l.w.first().map_or(0, |w| w.nrows()),
            NetLayer::Cp(l) => l.a.nrows(),
            NetLayer::Diagonal(l) => l.w.first().map_or(0, |w| w.len()),
        }
    }

    /// Expert count.
    pub fn experts(&self) -> usize {
        match self {
            NetLayer::Dense(l) => l.experts(),
            NetLayer::Cp(l) => l.experts(),
            NetLayer::Diagonal(l) => l.w.len(),
        }
    }

    /// Weights stored (biases excluded).
    pub fn weight_count(&self) -> usize {
        match self {
            NetLayer::Dense(l) => l.experts() * self.in_dim() * self.out_dim(),
            NetLayer::Cp(l) => l.rank() * (self.in_dim() + self.out_dim() + l.experts()),
            NetLayer::Diagonal(l) => l.w.len() * self.out_dim(),
        }
    }

    /// Rank for CP layers.
    pub fn rank(&self) -> Option<usize> {
        match self {
            NetLayer::Cp(l) => Some(l.rank()),
            _ => None,
        }
    }

    /// "dense", "cp" or "diagonal".
    pub fn form(&self) -> &'static str {
        match self {
            NetLayer::Dense(_) => "dense",
            NetLayer::Cp(_) => "cp",
            NetLayer::Diagonal(_) => "diagonal",
        }
    }
}

/// A residual adapter: `op` adds to the pre-activation of base layer `layer`
/// and reads that layer's input (the paper's eq. 4 with `layer = 1`).
#[derive(Clone, Debug, PartialEq)]
pub struct Adapter {
    /// Base layer it sits beside.
    pub layer: usize,
    /// Its weights (same experts as the base, or one expert for an
    /// ungated adapter).
    pub op: NetLayer,
}

/// Everything a forward pass computed.
#[derive(Clone, Debug, PartialEq)]
pub struct NetTrace {
    /// The gate used.
    pub gate: Vec<(usize, f64)>,
    /// Input of each layer (normalised input for layer 0).
    pub inputs: Vec<Array1<f64>>,
    /// Pre-activation of each layer, adapters included.
    pub pre: Vec<Array1<f64>>,
    /// Middle vectors of CP layers.
    pub mids: Vec<Option<Array1<f64>>>,
    /// Output in model units.
    pub y: Vec<f64>,
}

/// A PFNN-shaped float network with any mix of layer forms.
#[derive(Clone, Debug, PartialEq)]
pub struct FloatNet {
    /// Gating mode (what the experts mean).
    pub mode: GatingMode,
    /// Input normalisation.
    pub xmean: Array1<f64>,
    /// Input normalisation.
    pub xstd: Array1<f64>,
    /// Output de-normalisation.
    pub ymean: Array1<f64>,
    /// Output de-normalisation.
    pub ystd: Array1<f64>,
    /// Layers; ELU after all but the last.
    pub layers: Vec<NetLayer>,
}

/// The gate of `mode` with `n` experts at `phase_rad`, as
/// [`FloatPfnn::gate`] computes it.
pub fn gate_for(mode: GatingMode, n: usize, phase_rad: f64) -> Vec<(usize, f64)> {
    if n == 0 {
        return Vec::new();
    }
    let cycles = wrap_phase(phase_rad) / std::f64::consts::TAU;
    let split = |x: f64| {
        let whole = x.floor();
        ((whole as usize) % n, x - whole)
    };
    match mode {
        GatingMode::Constant => vec![(split(cycles * n as f64).0, 1.0)],
        GatingMode::Linear => {
            let (i, a) = split(cycles * n as f64);
            vec![(i, 1.0 - a), ((i + 1) % n, a)]
        }
        GatingMode::Cubic => catmull_rom_weights(cycles * CONTROL_POINTS as f64).to_vec(),
    }
}

impl FloatNet {
    /// The all-dense network of a float PFNN.
    pub fn from_pfnn(net: &FloatPfnn) -> FloatNet {
        FloatNet {
            mode: net.mode,
            xmean: net.xmean.clone(),
            xstd: net.xstd.clone(),
            ymean: net.ymean.clone(),
            ystd: net.ystd.clone(),
            layers: net.layers.iter().cloned().map(NetLayer::Dense).collect(),
        }
    }

    /// Input width.
    pub fn input_dim(&self) -> usize {
        self.xmean.len()
    }

    /// Output width.
    pub fn output_dim(&self) -> usize {
        self.ymean.len()
    }

    /// Experts of the gated layers.
    pub fn experts(&self) -> usize {
        self.layers.first().map_or(0, NetLayer::experts)
    }

    /// The gate at `phase_rad`.
    pub fn gate(&self, phase_rad: f64) -> Vec<(usize, f64)> {
        gate_for(self.mode, self.experts(), phase_rad)
    }

    /// Raw model units in and out.
    pub fn forward(&self, x_raw: &[f64], phase_rad: f64) -> Vec<f64> {
        self.forward_trace(x_raw, phase_rad, &[]).y
    }

    /// The forward pass with `adapters`, each with its mixing weight: the
    /// adapters of layer `l` add `sum_s w_s op_s(x_l)` to its pre-activation.
    ///
    /// # Panics
    /// If `x_raw` has the wrong length.
    pub fn forward_trace(
        &self,
        x_raw: &[f64],
        phase_rad: f64,
        adapters: &[(&Adapter, f64)],
    ) -> NetTrace {
        assert_eq!(x_raw.len(), self.input_dim(), "FloatNet input length");
        let gate = self.gate(phase_rad);
        let mut h = (&Array1::from(x_raw.to_vec()) - &self.xmean) / &self.xstd;
        let last = self.layers.len().saturating_sub(1);
        let (mut inputs, mut pre, mut mids) = (Vec::new(), Vec::new(), Vec::new());
        for (l, layer) in self.layers.iter().enumerate() {
            let (mut p, mid) = layer.apply_mid(&gate, &h);
            for (ad, w) in adapters.iter().filter(|(a, _)| a.layer == l) {
                let g = if ad.op.experts() == 1 {
                    vec![(0, 1.0)]
                } else {
                    gate.clone()
                };
                p.scaled_add(*w, &ad.op.apply(&g, &h));
            }
            inputs.push(h);
            h = if l == last { p.clone() } else { p.mapv(elu) };
            pre.push(p);
            mids.push(mid);
        }
        let y = (&h * &self.ystd + &self.ymean).to_vec();
        NetTrace {
            gate,
            inputs,
            pre,
            mids,
            y,
        }
    }

    /// Normalised outputs of many samples, as a matrix (rows = samples).
    pub fn outputs(
        &self,
        xs: &[Vec<f64>],
        phases: &[f64],
        adapters: &[(&Adapter, f64)],
    ) -> Array2<f64> {
        let rows: Vec<Array1<f64>> = xs
            .iter()
            .zip(phases)
            .map(|(x, &p)| Array1::from(self.forward_trace(x, p, adapters).y))
            .collect();
        let views: Vec<_> = rows.iter().map(|r| r.view()).collect();
        ndarray::stack(Axis(0), &views).unwrap_or_else(|_| Array2::zeros((0, self.output_dim())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pfnn_dir::fixtures::random_tables;
    use crate::pfnn_dir::PfnnDims;

    #[test]
    fn all_dense_net_equals_float_pfnn() {
        let t = random_tables(
            PfnnDims {
                input: 6,
                hidden: 8,
                output: 5,
                tables: 50,
            },
            3,
        );
        for mode in GatingMode::ALL {
            let (pfnn, _) = FloatPfnn::from_tables(&t, mode);
            let net = FloatNet::from_pfnn(&pfnn);
            let x: Vec<f64> = (0..6).map(|i| i as f64 * 0.3 - 1.0).collect();
            for p in [0.0, 1.0, 2.5, 6.0] {
                let (a, b) = (net.forward(&x, p), pfnn.forward(&x, p));
                for (u, v) in a.iter().zip(&b) {
                    assert!((u - v).abs() < 1e-12, "{mode} {p}");
                }
                assert_eq!(net.gate(p), pfnn.gate(p));
            }
        }
    }

    #[test]
    fn cp_layer_equals_its_dense_expansion() {
        let cp = CpLayer {
            a: Array2::from_shape_fn((5, 3), |(i, j)| (i + 2 * j) as f64 * 0.1 - 0.3),
            b: Array2::from_shape_fn((4, 3), |(i, j)| (3 * i + j) as f64 * 0.07 - 0.2),
            d: Array2::from_shape_fn((4, 3), |(i, j)| (i * j) as f64 * 0.5 + 0.1),
            bias: (0..4).map(|k| Array1::from_elem(5, k as f64)).collect(),
        };
        let dense = ExpertLayer {
            w: (0..4).map(|k| cp.expert(k)).collect(),
            b: cp.bias.clone(),
        };
        let x = Array1::from(vec![0.5, -1.0, 2.0, 0.25]);
        let gate = catmull_rom_weights(1.3).to_vec();
        let (y, _) = cp.apply_mid(&gate, &x);
        let want = dense.apply(&gate, &x);
        assert!((&y - &want).iter().all(|v| v.abs() < 1e-12));
    }
}
