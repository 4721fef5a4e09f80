//! Small synthetic models and style blobs for the target's tests and log
//! snapshots, built with the exporter (nothing from the shared PFNN): a
//! whole-network CP model, a small PFNN-shaped base, and residual adapters
//! (CP, diagonal, full) for it or for the embedded default model.

use anyhow::{anyhow, Result};
use exporter::encode::{encode, QKind};
use exporter::net::{Adapter, CpLayer, DiagLayer, Net, NetLayer};
use exporter::net::{ExpertLayer, GatingMode};
use exporter::quantise::QuantOptions;
use exporter::style::quantise_adapter;
use ndarray::{Array1, Array2};
use phasegate::Model;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Control points of the synthetic models (cubic gating).
const EXPERTS: usize = 4;

fn normal(rng: &mut ChaCha8Rng) -> f64 {
    // Irwin-Hall: close enough to normal for weights.
    (0..12).map(|_| rng.gen_range(0.0..1.0)).sum::<f64>() - 6.0
}

fn vecs(rng: &mut ChaCha8Rng, n: usize, sd: f64, mean: f64) -> Vec<Array1<f64>> {
    (0..EXPERTS)
        .map(|_| Array1::from_shape_fn(n, |_| mean + sd * normal(rng)))
        .collect()
}

fn cp_layer(rng: &mut ChaCha8Rng, out: usize, inp: usize, rank: usize) -> CpLayer {
    CpLayer {
        a: Array2::from_shape_fn((out, rank), |_| normal(rng) / (rank as f64).sqrt()),
        b: Array2::from_shape_fn((inp, rank), |_| normal(rng) / (inp as f64).sqrt()),
        d: Array2::from_shape_fn((EXPERTS, rank), |_| 1.0 + 0.3 * normal(rng)),
        bias: vecs(rng, out, 0.1, 0.0),
    }
}

fn dense_layer(rng: &mut ChaCha8Rng, out: usize, inp: usize) -> ExpertLayer {
    let sd = 1.5 / (inp as f64).sqrt();
    let base = Array2::from_shape_fn((out, inp), |_| normal(rng) * sd);
    ExpertLayer {
        w: (0..EXPERTS)
            .map(|_| base.mapv(|v| v + 0.4 * sd * normal(rng)))
            .collect(),
        b: vecs(rng, out, 0.1, 0.0),
    }
}

/// A whole-network CP model with cubic gating: CP `input -> hidden` (rank
/// `rank`), diagonal `hidden -> hidden`, CP `hidden -> output` (rank
/// `rank / 2`, at least 1). Every layer gated by the phase.
pub fn cp_net(seed: u64, input: usize, hidden: usize, output: usize, rank: usize) -> Net {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    Net {
        mode: GatingMode::Cubic,
        xmean: Array1::from_shape_fn(input, |_| normal(&mut rng)),
        xstd: Array1::from_shape_fn(input, |_| rng.gen_range(0.2..3.0)),
        ymean: Array1::from_shape_fn(output, |_| 3.0 * normal(&mut rng)),
        ystd: Array1::from_shape_fn(output, |_| rng.gen_range(0.1..10.0)),
        layers: vec![
            NetLayer::Cp(cp_layer(&mut rng, hidden, input, rank)),
            NetLayer::Diagonal(DiagLayer {
                w: vecs(&mut rng, hidden, 0.3, 1.0),
                b: vecs(&mut rng, hidden, 0.1, 0.0),
            }),
            NetLayer::Cp(cp_layer(&mut rng, output, hidden, (rank / 2).max(1))),
        ],
        wiring: exporter::net::Wiring::Chain,
    }
}

/// A small PFNN-shaped dense base (cubic gating): `input -> hidden ->
/// hidden -> output`.
pub fn pfnn_base(seed: u64, input: usize, hidden: usize, output: usize) -> Net {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    Net {
        mode: GatingMode::Cubic,
        xmean: Array1::from_shape_fn(input, |_| normal(&mut rng)),
        xstd: Array1::from_shape_fn(input, |_| rng.gen_range(0.2..3.0)),
        ymean: Array1::from_shape_fn(output, |_| 3.0 * normal(&mut rng)),
        ystd: Array1::from_shape_fn(output, |_| rng.gen_range(0.1..10.0)),
        layers: vec![
            NetLayer::Dense(dense_layer(&mut rng, hidden, input)),
            NetLayer::Dense(dense_layer(&mut rng, hidden, hidden)),
            NetLayer::Dense(dense_layer(&mut rng, output, hidden)),
        ],
        wiring: exporter::net::Wiring::Chain,
    }
}

/// A residual adapter beside layer 1 of a base whose hidden width is
/// `width`: `form` is `full`, `diagonal` or `cp` (rank `rank`), gated by the
/// phase, with weights large enough to change the outputs clearly.
pub fn adapter(form: &str, width: usize, rank: usize, seed: u64) -> Adapter {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let sd = 0.4 / (width as f64).sqrt();
    let op = match form {
        "full" => NetLayer::Dense(ExpertLayer {
            w: (0..EXPERTS)
                .map(|_| Array2::from_shape_fn((width, width), |_| sd * normal(&mut rng)))
                .collect(),
            b: vecs(&mut rng, width, 0.1, 0.0),
        }),
        "diagonal" => NetLayer::Diagonal(DiagLayer {
            w: vecs(&mut rng, width, 0.3, 0.0),
            b: vecs(&mut rng, width, 0.1, 0.0),
        }),
        _ => NetLayer::Cp(CpLayer {
            a: Array2::from_shape_fn((width, rank), |_| 0.3 * normal(&mut rng)),
            b: Array2::from_shape_fn((width, rank), |_| 0.3 * normal(&mut rng)),
            d: Array2::from_shape_fn((EXPERTS, rank), |_| 0.4 + 0.1 * normal(&mut rng)),
            bias: vecs(&mut rng, width, 0.1, 0.0),
        }),
    };
    Adapter { layer: 1, op }
}

/// Quantises `adapter` for `base_blob` (float twin `base`, int8 weights) and
/// encodes the style blob named `name`; with `base_crc`, the blob claims
/// that base instead of `base_blob`'s payload CRC (a style "for another
/// base" whose CRC is known in advance).
pub fn style_blob(
    base_blob: &[u8],
    base: &Net,
    adapter: &Adapter,
    name: &str,
    base_crc: Option<u32>,
) -> Result<Vec<u8>> {
    let model = Model::from_bytes(base_blob).map_err(|e| anyhow!("base blob: {e}"))?;
    let mut q = quantise_adapter(&model, base, adapter, name, &QuantOptions::default())?;
    if let (Some(crc), QKind::Style { base_crc, .. }) = (base_crc, &mut q.kind) {
        *base_crc = crc;
    }
    Ok(encode(&q)?)
}

/// Two styles for the embedded default model, beside its layer 1 (32
/// wide): `snap-cp` (CP, rank 8) and `snap-diagonal`.
pub fn default_model_styles() -> Result<Vec<Vec<u8>>> {
    let net = crate::default_model::float_model()?;
    let blob = crate::default_model::BLOB;
    let width = crate::default_model::HIDDEN;
    Ok(vec![
        style_blob(blob, &net, &adapter("cp", width, 8, 31), "snap-cp", None)?,
        style_blob(
            blob,
            &net,
            &adapter("diagonal", width, 0, 32),
            "snap-diagonal",
            None,
        )?,
    ])
}

/// A style that claims the base with payload CRC `base_crc` (built for the
/// default model, so everything but the CRC fits it).
pub fn default_model_style_for_crc(base_crc: u32) -> Result<Vec<u8>> {
    let net = crate::default_model::float_model()?;
    style_blob(
        crate::default_model::BLOB,
        &net,
        &adapter("cp", crate::default_model::HIDDEN, 8, 31),
        "other-base",
        Some(base_crc),
    )
}

/// Experts of the branching proof model's softmax gate.
pub const BRANCHING_EXPERTS: usize = 4;

/// The branching proof model (issue 9, OMG's new parts on random weights),
/// 40 inputs and 10 outputs:
///
/// ```text
/// input[0..8]   -> gate1 (16, ELU) -> gate2 (16, ELU) -> gate3 (4) -> softmax alpha
/// input[8..28]  -> pose1 (24, ELU) -> pose2 (24, ELU) --+
/// input[28..40] -> cost1 (16, ELU) -> cost2 (16, ELU) --+-> [pose2, cost2] (40)
///   -> moe1 (32, ELU) -> moe2 (32, ELU) -> moe3 (24, ELU), each with 4 experts
///      blended by alpha
///   -> moe3[0..16] -> dec1 (16, ELU) -> dec2 (10): the output
/// ```
pub fn branching_net(seed: u64) -> Net {
    use exporter::net::{GateSource, Graph, GraphNode, GraphOp, Slice, Source, Wiring};
    struct Builder {
        rng: ChaCha8Rng,
        layers: Vec<NetLayer>,
        nodes: Vec<GraphNode>,
    }
    impl Builder {
        /// A dense node of `experts` experts (close to each other, as
        /// trained experts are) and `out` rows; returns it as a source.
        fn dense(
            &mut self,
            name: &str,
            inputs: Vec<Slice>,
            out: usize,
            (experts, gate): (usize, GateSource),
            elu: bool,
        ) -> Source {
            let rng = &mut self.rng;
            let inp: usize = inputs.iter().map(|s| usize::from(s.len)).sum();
            let sd = 1.3 / (inp as f64).sqrt();
            let base = Array2::from_shape_fn((out, inp), |_| normal(rng) * sd);
            self.layers.push(NetLayer::Dense(ExpertLayer {
                w: (0..experts)
                    .map(|_| base.mapv(|v| v + 0.5 * sd * normal(rng)))
                    .collect(),
                b: (0..experts)
                    .map(|_| Array1::from_shape_fn(out, |_| 0.1 * normal(rng)))
                    .collect(),
            }));
            self.push(
                name,
                GraphOp::Layer {
                    layer: self.layers.len() - 1,
                    elu,
                },
                inputs,
                gate,
            )
        }

        fn push(
            &mut self,
            name: &str,
            op: GraphOp,
            inputs: Vec<Slice>,
            gate: GateSource,
        ) -> Source {
            self.nodes.push(GraphNode {
                name: name.to_string(),
                op,
                inputs,
                gate,
            });
            Source::Node(self.nodes.len() as u8 - 1)
        }
    }
    let s = |source, start: u16, len: u16| Slice { source, start, len };
    let mut b = Builder {
        rng: ChaCha8Rng::seed_from_u64(seed),
        layers: Vec::new(),
        nodes: Vec::new(),
    };
    let one = (1, GateSource::None);
    let k = BRANCHING_EXPERTS;
    let g1 = b.dense("gate1", vec![s(Source::Input, 0, 8)], 16, one, true);
    let g2 = b.dense("gate2", vec![s(g1, 0, 16)], 16, one, true);
    let g3 = b.dense("gate3", vec![s(g2, 0, 16)], k, one, false);
    let p1 = b.dense("pose1", vec![s(Source::Input, 8, 20)], 24, one, true);
    let p2 = b.dense("pose2", vec![s(p1, 0, 24)], 24, one, true);
    let c1 = b.dense("cost1", vec![s(Source::Input, 28, 12)], 16, one, true);
    let c2 = b.dense("cost2", vec![s(c1, 0, 16)], 16, one, true);
    // The softmax gate after the encoders: the branches interleave and the
    // logits stay live across them.
    let Source::Node(a) = b.push(
        "alpha",
        GraphOp::Softmax,
        vec![s(g3, 0, k as u16)],
        GateSource::None,
    ) else {
        unreachable!("push returns a node")
    };
    let gated = (k, GateSource::Node(a));
    let cat = vec![s(p2, 0, 24), s(c2, 0, 16)];
    let m1 = b.dense("moe1", cat, 32, gated, true);
    let m2 = b.dense("moe2", vec![s(m1, 0, 32)], 32, gated, true);
    let m3 = b.dense("moe3", vec![s(m2, 0, 32)], 24, gated, true);
    let d1 = b.dense("dec1", vec![s(m3, 0, 16)], 16, one, true);
    let d2 = b.dense("dec2", vec![s(d1, 0, 16)], 10, one, false);
    let rng = &mut b.rng;
    Net {
        mode: GatingMode::Cubic,
        xmean: Array1::from_shape_fn(40, |_| normal(rng)),
        xstd: Array1::from_shape_fn(40, |_| rng.gen_range(0.2..3.0)),
        ymean: Array1::from_shape_fn(10, |_| 3.0 * normal(rng)),
        ystd: Array1::from_shape_fn(10, |_| rng.gen_range(0.1..10.0)),
        layers: b.layers,
        wiring: Wiring::Graph(Graph {
            nodes: b.nodes,
            output: s(d2, 0, 10),
        }),
    }
}

/// A small graph with an RBF node (the clustering layer of OMG's RBF-CAT):
/// an encoder `6 -> 4`, the RBF layer's 3 clusters over its output, and a
/// head reading `[psi, z]`; `6 -> 5`. Fuzz seeds and tests that want the
/// RBF op in a blob of a few hundred bytes.
pub fn rbf_net(seed: u64) -> Net {
    clustering_net(seed, 4, 3, false)
}

/// [`rbf_net`] with a DEC node (OMG's DEC-CAT clustering layer, the soft
/// assignment to 3 centres) in place of the RBF one.
pub fn dec_net(seed: u64) -> Net {
    clustering_net(seed, 4, 3, true)
}

/// An encoder `6 -> latent`, a clustering layer of `clusters` centres over
/// it (RBF, or DEC when `dec`), and a head `clusters + latent -> 5` reading
/// `[psi, z]`.
pub fn clustering_net(seed: u64, latent: usize, clusters: usize, dec: bool) -> Net {
    use exporter::net::{
        DecLayer, GateSource, Graph, GraphNode, GraphOp, RbfLayer, Slice, Source, Wiring,
    };
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let dense = |rng: &mut ChaCha8Rng, out: usize, inp: usize| {
        let sd = 1.3 / (inp as f64).sqrt();
        NetLayer::Dense(ExpertLayer {
            w: vec![Array2::from_shape_fn((out, inp), |_| normal(rng) * sd)],
            b: vec![Array1::from_shape_fn(out, |_| 0.1 * normal(rng))],
        })
    };
    let enc = dense(&mut rng, latent, 6);
    let centres = vec![Array2::from_shape_fn((clusters, latent), |_| {
        normal(&mut rng)
    })];
    let rbf = if dec {
        NetLayer::Dec(DecLayer {
            centres,
            b: vec![Array1::zeros(clusters)],
        })
    } else {
        NetLayer::Rbf(RbfLayer {
            centres,
            sigma: vec![Array1::from_shape_fn(clusters, |_| rng.gen_range(0.2..1.0))],
            b: vec![Array1::zeros(clusters)],
        })
    };
    let head = dense(&mut rng, 5, clusters + latent);
    let s = |source, start: u16, len: u16| Slice { source, start, len };
    let node = |name: &str, layer: usize, inputs: Vec<Slice>| GraphNode {
        name: name.to_string(),
        op: GraphOp::Layer { layer, elu: false },
        inputs,
        gate: GateSource::None,
    };
    Net {
        mode: GatingMode::Cubic,
        xmean: Array1::from_shape_fn(6, |_| normal(&mut rng)),
        xstd: Array1::from_shape_fn(6, |_| rng.gen_range(0.2..3.0)),
        ymean: Array1::from_shape_fn(5, |_| normal(&mut rng)),
        ystd: Array1::from_shape_fn(5, |_| rng.gen_range(0.1..3.0)),
        layers: vec![enc, rbf, head],
        wiring: Wiring::Graph(Graph {
            nodes: vec![
                node("enc", 0, vec![s(Source::Input, 0, 6)]),
                node(
                    if dec { "dec" } else { "rbf" },
                    1,
                    vec![s(Source::Node(0), 0, latent as u16)],
                ),
                node(
                    "head",
                    2,
                    vec![
                        s(Source::Node(1), 0, clusters as u16),
                        s(Source::Node(0), 0, latent as u16),
                    ],
                ),
            ],
            output: s(Source::Node(2), 0, 5),
        }),
    }
}
