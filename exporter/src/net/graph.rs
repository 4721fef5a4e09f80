//! A [`Net`] wired as a graph: nodes in evaluation order, each reading the
//! concatenation of slices of the normalised input and of earlier nodes'
//! outputs. A layer node applies one of the net's layers (gated by nothing,
//! the phase, or a softmax gate node) and optionally ELU; a softmax gate
//! node turns its input (the logits) into expert coefficients; a residual
//! node adds its input slices, each at a weight, and optionally applies ELU
//! (style adapters beside a layer, [`Net::with_adapters`]). The blob's
//! graph (`docs/blob-format.md`) mirrors layer and softmax nodes node for
//! node; a residual addition reaches the device as a style blob beside its
//! base layer (`docs/cp-and-styles.md`).

use ndarray::{concatenate, Array1, Axis};

use super::{elu, Net, NetLayer};
use phasegate::blob::{GateSource, Slice, Source};

/// What a node computes.
#[derive(Clone, Debug, PartialEq)]
pub enum GraphOp {
    /// Layer `layer` of [`Net::layers`], then ELU when `elu`.
    Layer {
        /// Index into the net's layers.
        layer: usize,
        /// ELU after the layer (else identity).
        elu: bool,
    },
    /// Softmax of the node's input, one coefficient per expert.
    Softmax,
    /// A residual addition: `sum_i weights[i] * input_i` over the node's
    /// input slices (all of one width, added, not concatenated), then ELU
    /// when `elu`.
    Residual {
        /// One weight per input slice.
        weights: Vec<f64>,
        /// ELU after the sum (else identity).
        elu: bool,
    },
}

/// One node: a name (for errors and reports), its op, the slices it
/// concatenates and where its expert coefficients come from.
#[derive(Clone, Debug, PartialEq)]
pub struct GraphNode {
    /// Unique name.
    pub name: String,
    /// The op.
    pub op: GraphOp,
    /// Input slices, concatenated in order.
    pub inputs: Vec<Slice>,
    /// Gate source (always `None` for a softmax gate).
    pub gate: GateSource,
}

/// The nodes and the model's output (a slice of a node's output, or of the
/// input).
#[derive(Clone, Debug, PartialEq)]
pub struct Graph {
    /// Nodes in evaluation order.
    pub nodes: Vec<GraphNode>,
    /// The model output.
    pub output: Slice,
}

/// Everything a forward pass of a graph computed, per node.
#[derive(Clone, Debug, PartialEq)]
pub struct GraphTrace {
    /// Each node's concatenated input.
    pub inputs: Vec<Array1<f64>>,
    /// Each layer or residual node's pre-activation (empty for softmax
    /// gates).
    pub pre: Vec<Array1<f64>>,
    /// Each node's output (the softmax coefficients for a gate).
    pub out: Vec<Array1<f64>>,
    /// Middle vectors of CP layers.
    pub mids: Vec<Option<Array1<f64>>>,
    /// The output in model units.
    pub y: Vec<f64>,
}

/// `exp(z_i - max z) / sum_j exp(z_j - max z)`.
pub fn softmax(z: &Array1<f64>) -> Array1<f64> {
    let m = z.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let e = z.mapv(|v| (v - m).exp());
    let s = e.sum();
    e / s
}

impl Graph {
    /// The index of the node named `name`.
    pub fn node(&self, name: &str) -> Option<usize> {
        self.nodes.iter().position(|n| n.name == name)
    }

    /// Experts of the phase-gated layer nodes (0 when none is).
    pub fn phase_experts(&self, layers: &[NetLayer]) -> usize {
        self.nodes
            .iter()
            .find_map(|n| match (&n.op, n.gate) {
                (GraphOp::Layer { layer, .. }, GateSource::Phase) => {
                    layers.get(*layer).map(NetLayer::experts)
                }
                _ => None,
            })
            .unwrap_or(0)
    }

    /// Width of node `j`'s output (the expert count for a softmax gate).
    pub fn width(&self, layers: &[NetLayer], input_dim: usize, source: Source) -> usize {
        match source {
            Source::Input => input_dim,
            Source::Node(j) => match self.nodes.get(usize::from(j)).map(|n| &n.op) {
                Some(GraphOp::Layer { layer, .. }) => {
                    layers.get(*layer).map_or(0, NetLayer::out_dim)
                }
                Some(GraphOp::Softmax) => self.nodes[usize::from(j)]
                    .inputs
                    .iter()
                    .map(|s| usize::from(s.len))
                    .sum(),
                Some(GraphOp::Residual { .. }) => self.nodes[usize::from(j)]
                    .inputs
                    .first()
                    .map_or(0, |s| usize::from(s.len)),
                None => 0,
            },
        }
    }
}

fn take(v: &Array1<f64>, s: &Slice) -> Array1<f64> {
    let start = usize::from(s.start);
    v.slice(ndarray::s![start..start + usize::from(s.len)])
        .to_owned()
}

/// `sum_i weights[i] * parts[i]`, summed left to right from the first
/// part scaled (not from zero), so that a base pre-activation at weight 1
/// keeps its exact value, signed zeros included.
fn weighted_sum(parts: &[Array1<f64>], weights: &[f64]) -> Array1<f64> {
    let mut pairs = parts.iter().zip(weights);
    let Some((first, &w0)) = pairs.next() else {
        return Array1::zeros(0);
    };
    let mut sum = first.mapv(|v| w0 * v);
    for (p, &w) in pairs {
        sum.scaled_add(w, p);
    }
    sum
}

impl Net {
    /// The forward pass of graph `g` (this net's wiring), raw model units
    /// in; every node's vectors kept.
    ///
    /// # Panics
    /// If `x_raw` has the wrong length or the graph is inconsistent (the
    /// JSON importer checks graphs before they get here).
    pub fn graph_trace(&self, g: &Graph, x_raw: &[f64], phase_rad: f64) -> GraphTrace {
        assert_eq!(x_raw.len(), self.input_dim(), "graph input width");
        let x = (&Array1::from(x_raw.to_vec()) - &self.xmean) / &self.xstd;
        let phase_gate = self.mode.gate(g.phase_experts(&self.layers), phase_rad);
        let mut t = GraphTrace {
            inputs: Vec::new(),
            pre: Vec::new(),
            out: Vec::new(),
            mids: Vec::new(),
            y: Vec::new(),
        };
        let source = |t: &GraphTrace, s: &Slice| match s.source {
            Source::Input => take(&x, s),
            Source::Node(j) => take(&t.out[usize::from(j)], s),
        };
        for n in &g.nodes {
            let parts: Vec<Array1<f64>> = n.inputs.iter().map(|s| source(&t, s)).collect();
            let views: Vec<_> = parts.iter().map(|p| p.view()).collect();
            let h = concatenate(Axis(0), &views).expect("slices concatenate");
            let (pre, out, mid) = match &n.op {
                GraphOp::Softmax => (Array1::zeros(0), softmax(&h), None),
                GraphOp::Residual { weights, elu: act } => {
                    let p = weighted_sum(&parts, weights);
                    let o = if *act { p.mapv(elu) } else { p.clone() };
                    (p, o, None)
                }
                GraphOp::Layer { layer, elu: act } => {
                    let gate: Vec<(usize, f64)> = match n.gate {
                        GateSource::None => vec![(0, 1.0)],
                        GateSource::Phase => phase_gate.clone(),
                        GateSource::Node(j) => {
                            t.out[usize::from(j)].iter().copied().enumerate().collect()
                        }
                    };
                    let (p, mid) = self.layers[*layer].apply_mid(&gate, &h);
                    let o = if *act { p.mapv(elu) } else { p.clone() };
                    (p, o, mid)
                }
            };
            t.inputs.push(h);
            t.pre.push(pre);
            t.out.push(out);
            t.mids.push(mid);
        }
        let y = source(&t, &g.output);
        t.y = (&y * &self.ystd + &self.ymean).to_vec();
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn softmax_sums_to_one_and_survives_large_logits() {
        let p = softmax(&Array1::from(vec![1000.0, 999.0, -1e9]));
        assert!((p.sum() - 1.0).abs() < 1e-12);
        assert!((p[0] / p[1] - 1f64.exp()).abs() < 1e-9);
        assert_eq!(p[2], 0.0);
    }
}
