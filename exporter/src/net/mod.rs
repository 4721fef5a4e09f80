//! The one network description of the exporter: a [`Net`] is what every
//! importer produces (PFNN directories and `.npz`, CP factors, CP-ALS of
//! dense weights, a chain with style adapters beside it), what the float
//! reference runs and what the one quantiser ([`crate::quantise`]) turns
//! into a blob.
//!
//! A `Net` holds its layers ([`NetLayer`]) and how they are wired
//! ([`Wiring`]): a chain sharing the phase gate with ELU after every layer
//! but the last (PFNN, and every network the PFNN-shaped importers make),
//! or a graph of layer, softmax gate and residual nodes whose inputs are
//! slices of the input and of earlier nodes (OMG-shaped networks, imported
//! from a JSON description, [`json`]; a chain with style adapters,
//! [`Net::with_adapters`], whose adapters are layer nodes beside their base
//! layer and whose additions are residual nodes, [`residual`]).
//!
//! Everything is `f64`.

pub mod gating;
pub mod graph;
pub mod json;
pub mod omg;
pub mod omg_snap;
pub mod pfnn;
pub mod residual;

use ndarray::{Array1, Array2, Axis};

pub use crate::ops::{CpLayer, DecLayer, DiagLayer, ExpertLayer, NetLayer, RbfLayer};
pub use gating::{wrap_phase, GatingMode, ParseGatingModeError};
pub use graph::{Graph, GraphNode, GraphOp, GraphTrace};
pub use phasegate::blob::{GateSource, Slice, Source};
pub use residual::Adapter;

/// How a [`Net`]'s layers are connected.
#[derive(Clone, Debug, Default, PartialEq)]
pub enum Wiring {
    /// Layer `l` reads layer `l - 1`'s output (layer 0 the normalised
    /// input), every layer phase-gated, ELU after all but the last.
    #[default]
    Chain,
    /// Any graph of layer, softmax gate and residual nodes.
    Graph(Graph),
}

/// Exponential linear unit: `x` for `x > 0`, `exp(x) - 1` otherwise.
pub fn elu(x: f64) -> f64 {
    if x > 0.0 {
        x
    } else {
        x.exp_m1()
    }
}

/// Everything a forward pass computed.
#[derive(Clone, Debug, PartialEq)]
pub struct NetTrace {
    /// The gate used.
    pub gate: Vec<(usize, f64)>,
    /// Input of each layer (normalised input for layer 0).
    pub inputs: Vec<Array1<f64>>,
    /// Pre-activation of each layer.
    pub pre: Vec<Array1<f64>>,
    /// Middle vectors of CP layers.
    pub mids: Vec<Option<Array1<f64>>>,
    /// Output in model units.
    pub y: Vec<f64>,
}

/// A PFNN-shaped float network with any mix of layer forms.
#[derive(Clone, Debug, PartialEq)]
pub struct Net {
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
    /// Layers; for a chain, ELU after all but the last.
    pub layers: Vec<NetLayer>,
    /// How the layers are connected.
    pub wiring: Wiring,
}

impl Net {
    /// Input width.
    pub fn input_dim(&self) -> usize {
        self.xmean.len()
    }

    /// Output width.
    pub fn output_dim(&self) -> usize {
        self.ymean.len()
    }

    /// Experts of the phase-gated layers (0 for a graph without one).
    pub fn experts(&self) -> usize {
        match &self.wiring {
            Wiring::Chain => self.layers.first().map_or(0, NetLayer::experts),
            Wiring::Graph(g) => g.phase_experts(&self.layers),
        }
    }

    /// The gate at `phase_rad`.
    pub fn gate(&self, phase_rad: f64) -> Vec<(usize, f64)> {
        self.mode.gate(self.experts(), phase_rad)
    }

    /// Raw model units in and out.
    pub fn forward(&self, x_raw: &[f64], phase_rad: f64) -> Vec<f64> {
        match &self.wiring {
            Wiring::Chain => self.forward_trace(x_raw, phase_rad).y,
            Wiring::Graph(g) => self.graph_trace(g, x_raw, phase_rad).y,
        }
    }

    /// The forward pass of a chain, every layer's vectors kept (a chain
    /// with adapters is a graph: [`Net::with_adapters`]).
    ///
    /// # Panics
    /// If `x_raw` has the wrong length, or the net is a graph (see
    /// [`Net::graph_trace`]).
    pub fn forward_trace(&self, x_raw: &[f64], phase_rad: f64) -> NetTrace {
        assert_eq!(
            x_raw.len(),
            self.input_dim(),
            "Net input has {} values, the model expects {}",
            x_raw.len(),
            self.input_dim()
        );
        assert!(
            self.wiring == Wiring::Chain,
            "forward_trace runs chains; graphs run with graph_trace"
        );
        let gate = self.gate(phase_rad);
        let mut h = (&Array1::from(x_raw.to_vec()) - &self.xmean) / &self.xstd;
        let last = self.layers.len().saturating_sub(1);
        let (mut inputs, mut pre, mut mids) = (Vec::new(), Vec::new(), Vec::new());
        for (l, layer) in self.layers.iter().enumerate() {
            let (p, mid) = layer.apply_mid(&gate, &h);
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
    pub fn outputs(&self, xs: &[Vec<f64>], phases: &[f64]) -> Array2<f64> {
        let rows: Vec<Array1<f64>> = xs
            .iter()
            .zip(phases)
            .map(|(x, &p)| Array1::from(self.forward(x, p)))
            .collect();
        let views: Vec<_> = rows.iter().map(|r| r.view()).collect();
        ndarray::stack(Axis(0), &views).unwrap_or_else(|_| Array2::zeros((0, self.output_dim())))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control_points::catmull_rom_weights;

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
