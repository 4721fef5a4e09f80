//! Style adapters as nodes of the net's graph: [`Net::with_adapters`]
//! rewires a chain as a graph in which every base layer with adapters
//! beside it becomes a residual addition,
//!
//! ```text
//! layer{l}            = base layer l of its input, no activation
//! layer{l}.adapter{s} = adapter s of the same input, no activation
//! layer{l}.residual   = act(1 * layer{l} + sum_s w_s * layer{l}.adapter{s})
//! ```
//!
//! (the paper's eq. 4), and every other layer a plain layer node. The
//! styled float reference is then the one graph forward pass,
//! [`Net::graph_trace`].

use anyhow::{bail, Result};

use super::graph::{Graph, GraphNode, GraphOp};
use super::{Net, NetLayer, Wiring};
use phasegate::blob::{GateSource, Slice, Source};

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

/// The name of the node of the `s`-th adapter beside base layer `layer`.
pub fn adapter_node_name(layer: usize, s: usize) -> String {
    format!("layer{layer}.adapter{s}")
}

/// The name of the residual node of base layer `layer`.
pub fn residual_node_name(layer: usize) -> String {
    format!("layer{layer}.residual")
}

/// All `width` values of `source`.
fn whole(source: Source, width: usize) -> Result<Slice> {
    let Ok(len) = u16::try_from(width) else {
        bail!("a vector of {width} values is too wide for a graph slice");
    };
    Ok(Slice {
        source,
        start: 0,
        len,
    })
}

fn layer_node(name: String, layer: usize, elu: bool, input: Slice, gate: GateSource) -> GraphNode {
    GraphNode {
        name,
        op: GraphOp::Layer { layer, elu },
        inputs: vec![input],
        gate,
    }
}

/// A graph under construction and the layers its nodes apply.
struct Builder {
    layers: Vec<NetLayer>,
    nodes: Vec<GraphNode>,
}

impl Builder {
    /// Appends `node` and returns its whole output, `width` wide.
    fn push(&mut self, node: GraphNode, width: usize) -> Result<Slice> {
        let Ok(j) = u8::try_from(self.nodes.len()) else {
            bail!("more than 256 nodes: too many adapters for one graph");
        };
        self.nodes.push(node);
        whole(Source::Node(j), width)
    }

    /// Appends the nodes of `adapters` beside base layer `l` (whose node
    /// reads `input` and gives `base`, `width` wide) and their residual
    /// node; returns the residual node's output.
    fn beside(
        &mut self,
        l: usize,
        act: bool,
        (input, base, width): (Slice, Slice, usize),
        adapters: &[(&Adapter, f64)],
    ) -> Result<Slice> {
        let mut terms = vec![base];
        let mut weights = vec![1.0];
        for (s, (a, w)) in adapters.iter().enumerate() {
            self.layers.push(a.op.clone());
            let gate = if a.op.experts() == 1 {
                GateSource::None
            } else {
                GateSource::Phase
            };
            let name = adapter_node_name(l, s);
            let node = layer_node(name, self.layers.len() - 1, false, input, gate);
            terms.push(self.push(node, width)?);
            weights.push(*w);
        }
        let sum = GraphNode {
            name: residual_node_name(l),
            op: GraphOp::Residual { weights, elu: act },
            inputs: terms,
            gate: GateSource::None,
        };
        self.push(sum, width)
    }
}

impl Net {
    /// This chain with `adapters` beside its layers, each at its mixing
    /// weight (a switch is one adapter at 1, a blend two at `1 - t` and
    /// `t`), as a graph net: the adapters' ops are appended to the layers,
    /// a one-expert adapter ungated, any other phase-gated like its base.
    /// No adapters give the chain itself as a graph.
    ///
    /// # Errors
    /// If the net is not a chain, an adapter sits beside no layer or does
    /// not fit its layer, or the graph outgrows its slice and node indices.
    pub fn with_adapters(&self, adapters: &[(&Adapter, f64)]) -> Result<Net> {
        if self.wiring != Wiring::Chain {
            bail!("adapters sit beside the layers of a chain; this net is already a graph");
        }
        for (a, _) in adapters {
            self.check_fits(a)?;
        }
        let mut b = Builder {
            layers: self.layers.clone(),
            nodes: Vec::new(),
        };
        let mut h = whole(Source::Input, self.input_dim())?;
        let last = self.layers.len().saturating_sub(1);
        for (l, layer) in self.layers.iter().enumerate() {
            let beside: Vec<(&Adapter, f64)> = adapters
                .iter()
                .copied()
                .filter(|(a, _)| a.layer == l)
                .collect();
            let (input, width, act) = (h, layer.out_dim(), l != last);
            // With adapters the base node gives its pre-activation and the
            // residual node applies the activation to the sum.
            let elu = act && beside.is_empty();
            let base = layer_node(format!("layer{l}"), l, elu, input, GateSource::Phase);
            h = b.push(base, width)?;
            if !beside.is_empty() {
                h = b.beside(l, act, (input, h, width), &beside)?;
            }
        }
        Ok(Net {
            mode: self.mode,
            xmean: self.xmean.clone(),
            xstd: self.xstd.clone(),
            ymean: self.ymean.clone(),
            ystd: self.ystd.clone(),
            layers: b.layers,
            wiring: Wiring::Graph(Graph {
                nodes: b.nodes,
                output: h,
            }),
        })
    }

    /// Refuses an adapter that sits beside no layer of this chain or
    /// whose shape differs from its layer's.
    fn check_fits(&self, a: &Adapter) -> Result<()> {
        let Some(base) = self.layers.get(a.layer) else {
            bail!(
                "an adapter beside layer {} of a {}-layer net",
                a.layer,
                self.layers.len()
            );
        };
        if (a.op.in_dim(), a.op.out_dim()) != (base.in_dim(), base.out_dim()) {
            bail!(
                "adapter is {}x{}, base layer {} is {}x{}",
                a.op.out_dim(),
                a.op.in_dim(),
                a.layer,
                base.out_dim(),
                base.in_dim()
            );
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::net::{elu, CpLayer, DiagLayer, ExpertLayer, GatingMode};
    use ndarray::{Array1, Array2};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn vector(rng: &mut ChaCha8Rng, n: usize, s: f64) -> Array1<f64> {
        Array1::from_shape_fn(n, |_| s * rng.gen_range(-1.0..1.0))
    }

    fn matrix(rng: &mut ChaCha8Rng, r: usize, c: usize, s: f64) -> Array2<f64> {
        Array2::from_shape_fn((r, c), |_| s * rng.gen_range(-1.0..1.0))
    }

    fn dense(rng: &mut ChaCha8Rng, k: usize, out: usize, inp: usize) -> NetLayer {
        NetLayer::Dense(ExpertLayer {
            w: (0..k).map(|_| matrix(rng, out, inp, 0.8)).collect(),
            b: (0..k).map(|_| vector(rng, out, 0.2)).collect(),
        })
    }

    fn diagonal(rng: &mut ChaCha8Rng, k: usize, n: usize) -> NetLayer {
        NetLayer::Diagonal(DiagLayer {
            w: (0..k).map(|_| vector(rng, n, 0.5)).collect(),
            b: (0..k).map(|_| vector(rng, n, 0.2)).collect(),
        })
    }

    fn cp(rng: &mut ChaCha8Rng, k: usize, out: usize, inp: usize) -> NetLayer {
        NetLayer::Cp(CpLayer {
            a: matrix(rng, out, 3, 0.6),
            b: matrix(rng, inp, 3, 0.6),
            d: matrix(rng, k, 3, 1.0),
            bias: (0..k).map(|_| vector(rng, out, 0.2)).collect(),
        })
    }

    /// A cubic 7 -> 6 -> 6 -> 4 chain (dense, CP, dense).
    fn chain(rng: &mut ChaCha8Rng) -> Net {
        Net {
            mode: GatingMode::Cubic,
            xmean: vector(rng, 7, 1.0),
            xstd: vector(rng, 7, 0.5).mapv(|v| v + 1.0),
            ymean: vector(rng, 4, 2.0),
            ystd: vector(rng, 4, 0.5).mapv(|v| v + 1.0),
            layers: vec![dense(rng, 4, 6, 7), cp(rng, 4, 6, 6), dense(rng, 4, 4, 6)],
            wiring: Wiring::Chain,
        }
    }

    /// Dense, diagonal and CP adapters, gated and not, beside the first,
    /// a hidden and the last (activation-free) layer.
    fn adapters(rng: &mut ChaCha8Rng) -> Vec<Adapter> {
        [
            (1, dense(rng, 4, 6, 6)),
            (1, diagonal(rng, 1, 6)),
            (1, cp(rng, 4, 6, 6)),
            (0, dense(rng, 1, 6, 7)),
            (2, dense(rng, 4, 4, 6)),
            (2, cp(rng, 1, 4, 6)),
        ]
        .into_iter()
        .map(|(layer, op)| Adapter { layer, op })
        .collect()
    }

    /// The styled chain as it ran before adapters were graph nodes: each
    /// layer's pre-activation plus `w * adapter(layer input)` for its
    /// adapters in order, then ELU (but after the last layer).
    fn adapter_loop(net: &Net, x: &[f64], phase: f64, adapters: &[(&Adapter, f64)]) -> Vec<f64> {
        let gate = net.gate(phase);
        let mut h = (&Array1::from(x.to_vec()) - &net.xmean) / &net.xstd;
        let last = net.layers.len() - 1;
        for (l, layer) in net.layers.iter().enumerate() {
            let mut p = layer.apply(&gate, &h);
            for (a, w) in adapters.iter().filter(|(a, _)| a.layer == l) {
                let g = if a.op.experts() == 1 {
                    vec![(0, 1.0)]
                } else {
                    gate.clone()
                };
                p.scaled_add(*w, &a.op.apply(&g, &h));
            }
            h = if l == last { p } else { p.mapv(elu) };
        }
        (&h * &net.ystd + &net.ymean).to_vec()
    }

    /// Switches (one adapter at 1), blends of two (`1 - t`, `t`) and all
    /// adapters at once give through the graph what the adapter loop gave.
    #[test]
    fn styled_graph_equals_the_adapter_loop() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let net = chain(&mut rng);
        let ads = adapters(&mut rng);
        let mut mixes: Vec<Vec<(&Adapter, f64)>> = ads.iter().map(|a| vec![(a, 1.0)]).collect();
        for (i, j, t) in [
            (0, 2, 0.3),
            (1, 2, 0.75),
            (0, 1, 0.5),
            (4, 5, 0.2),
            (3, 0, 0.9),
        ] {
            mixes.push(vec![(&ads[i], 1.0 - t), (&ads[j], t)]);
        }
        mixes.push(ads.iter().map(|a| (a, rng.gen_range(-1.0..1.5))).collect());
        for mix in &mixes {
            let styled = net.with_adapters(mix).expect("adapters fit");
            for _ in 0..16 {
                let x: Vec<f64> = (0..7).map(|_| rng.gen_range(-3.0..3.0)).collect();
                let p = rng.gen_range(0.0..std::f64::consts::TAU);
                let want = adapter_loop(&net, &x, p, mix);
                let got = styled.forward(&x, p);
                for (g, w) in got.iter().zip(&want) {
                    assert!((g - w).abs() <= 1e-12, "{got:?} vs {want:?}");
                }
            }
        }
    }

    /// Without adapters the graph is the chain, value for value.
    #[test]
    fn no_adapters_give_the_chain_as_a_graph() {
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        let net = chain(&mut rng);
        let g = net.with_adapters(&[]).expect("a chain");
        let Wiring::Graph(graph) = &g.wiring else {
            panic!("not a graph");
        };
        assert_eq!(graph.nodes.len(), 3);
        for p in [0.0, 1.0, 4.5] {
            let x: Vec<f64> = (0..7).map(|i| i as f64 * 0.3 - 1.0).collect();
            assert_eq!(g.forward(&x, p), net.forward(&x, p));
        }
    }

    /// One adapter beside layer 1: base, adapter and residual nodes, the
    /// adapter's op appended to the layers, the next layer reading the sum.
    #[test]
    fn an_adapter_becomes_a_layer_node_and_a_residual_node() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let net = chain(&mut rng);
        let ads = adapters(&mut rng);
        let g = net.with_adapters(&[(&ads[1], 0.4)]).expect("fits");
        assert_eq!(g.layers.len(), 4);
        assert_eq!(g.layers[3], ads[1].op);
        let Wiring::Graph(graph) = &g.wiring else {
            panic!("not a graph");
        };
        let names: Vec<&str> = graph.nodes.iter().map(|n| n.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "layer0",
                "layer1",
                "layer1.adapter0",
                "layer1.residual",
                "layer2"
            ]
        );
        assert_eq!(
            graph.nodes[1].op,
            GraphOp::Layer {
                layer: 1,
                elu: false
            }
        );
        assert_eq!(graph.nodes[2].inputs, graph.nodes[1].inputs);
        assert_eq!(graph.nodes[2].gate, GateSource::None);
        assert_eq!(
            graph.nodes[3].op,
            GraphOp::Residual {
                weights: vec![1.0, 0.4],
                elu: true
            }
        );
        assert_eq!(graph.nodes[4].inputs[0].source, Source::Node(3));
    }

    /// The blob's graph has no residual node: a styled net is exported as
    /// a base blob and style blobs, never as one model blob or description.
    #[test]
    fn a_styled_net_is_refused_as_a_model_blob_and_a_description() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        let net = chain(&mut rng);
        let ads = adapters(&mut rng);
        // Beside layer 0, so that its residual node comes before the CP
        // layer, which descriptions cannot hold either.
        let styled = net.with_adapters(&[(&ads[3], 1.0)]).expect("fits");
        let opts = crate::quantise::QuantOptions::default();
        let e = crate::export::export(&styled, None, &opts).expect_err("a residual node");
        assert!(e.to_string().contains("residual addition"), "{e}");
        let dir = tempfile::tempdir().expect("a temporary directory");
        let (json, weights) = (dir.path().join("g.json"), dir.path().join("g.npz"));
        let e =
            crate::net::json::write_graph(&styled, &json, &weights).expect_err("a residual node");
        assert!(e.to_string().contains("residual addition"), "{e}");
        assert!(!json.exists() && !weights.exists());
    }

    #[test]
    fn adapters_that_do_not_fit_are_refused() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let net = chain(&mut rng);
        let beside = |layer, op| Adapter { layer, op };
        let far = beside(3, diagonal(&mut rng, 4, 4));
        let wrong = beside(0, diagonal(&mut rng, 4, 6));
        for a in [&far, &wrong] {
            assert!(net.with_adapters(&[(a, 1.0)]).is_err());
        }
        let graph = net.with_adapters(&[]).expect("a chain");
        let e = graph.with_adapters(&[]).expect_err("a graph");
        assert!(e.to_string().contains("already a graph"), "{e}");
    }
}
