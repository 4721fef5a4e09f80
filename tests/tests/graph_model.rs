//! The branching proof model (issue 9): a gating MLP into a softmax gate,
//! two encoders into a concatenation, three softmax-gated layers and a
//! decoder on a slice, on random weights. Exported from a JSON graph
//! description and its weights (`.npz` and `.safetensors` alike), checked
//! against the float graph, its arena plan against the lower bound. The
//! bit-exact run under QEMU is `host-sim target` on the golden bundle
//! `tests/golden/softmax-graph` (CI, and `host-sim`'s target tests).

use std::path::Path;

use exporter::calibrate::normal_inputs;
use exporter::export::export;
use exporter::net::json::{net_from_file, read_graph, write_graph, GraphFile};
use exporter::net::{GraphOp, Net, Wiring};
use exporter::quantise::QuantOptions;
use host_sim::target::synthetic::branching_net;
use phasegate::blob::{NodeOp, WeightFormat};
use phasegate::{Model, Phase, Runtime};

const SEED: u64 = 0x601D_5F7A;

/// Writes `net` as JSON + weights (`ext`), reads it back.
fn round_trip(net: &Net, dir: &Path, ext: &str) -> Net {
    let (json, weights) = (dir.join("g.json"), dir.join(format!("w.{ext}")));
    write_graph(net, &json, &weights).unwrap();
    read_graph(&json, &weights).unwrap()
}

#[test]
fn the_same_graph_exports_the_same_blob_from_npz_and_safetensors() {
    let dir = tempfile::tempdir().unwrap();
    let net = branching_net(SEED);
    let a = round_trip(&net, dir.path(), "npz");
    let b = round_trip(&net, dir.path(), "safetensors");
    assert_eq!(a, b);
    let opts = QuantOptions::default();
    let (blob_a, report) = export(&a, None, &opts).unwrap();
    let (blob_b, _) = export(&b, None, &opts).unwrap();
    assert_eq!(blob_a, blob_b);
    assert_eq!(report.gating, "none");
    // 13 nodes: 12 dense layers and the softmax gate over 4 experts.
    let model = Model::from_bytes(&blob_a).unwrap();
    let ops: Vec<_> = model
        .nodes()
        .iter()
        .map(|n| match n.op {
            NodeOp::Layer(_) => "dense",
            NodeOp::Softmax(s) => {
                assert_eq!(s.experts, 4);
                "softmax"
            }
        })
        .collect();
    assert_eq!(ops.len(), 13);
    assert_eq!(ops.iter().filter(|&&o| o == "softmax").count(), 1);
    // The golden bundle is this model (same seed, same round trip).
    let golden = std::fs::read(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("golden/softmax-graph/model.blob"),
    )
    .unwrap();
    assert_eq!(golden, blob_a, "regenerate with host-sim golden --write");
}

/// RMS and max of the fixed-point error of `net` exported with `opts`,
/// on 512 inputs drawn like the calibration's (normal around the
/// normalisation means), in units of each output's standard deviation.
fn fixed_error(net: &Net, opts: &QuantOptions) -> (f64, f64) {
    let (blob, _) = export(net, None, opts).unwrap();
    let model = Model::from_bytes(&blob).unwrap();
    let mut rt: Box<Runtime<'_, 256>> = Box::new(Runtime::new(model).unwrap());
    let s = normal_inputs(&net.xmean.to_vec(), &net.xstd.to_vec(), 512, 1.0, 7);
    let (mut sq, mut worst, mut n) = (0.0f64, 0.0f64, 0usize);
    let mut y = vec![0f32; net.output_dim()];
    for (x, &p) in s.inputs.iter().zip(&s.phases) {
        let xf: Vec<f32> = x.iter().map(|&v| v as f32).collect();
        rt.run(Phase::from_radians(p as f32).unwrap(), &xf, &mut y)
            .unwrap();
        let want = net.forward(x, p);
        for ((a, b), sd) in y.iter().zip(&want).zip(&net.ystd) {
            let e = (f64::from(*a) - b).abs() / sd;
            sq += e * e;
            worst = worst.max(e);
            n += 1;
        }
    }
    ((sq / n as f64).sqrt(), worst)
}

/// Fixed point against the float graph ([`fixed_error`]). Measured: see
/// the assertion message (`--nocapture`).
#[test]
fn fixed_point_error_against_the_float_graph_is_bounded() {
    let dir = tempfile::tempdir().unwrap();
    let net = round_trip(&branching_net(SEED), dir.path(), "npz");
    for (weights, rms_bound, max_bound) in [
        (WeightFormat::I8, 0.06, 0.3),
        (WeightFormat::I16, 0.003, 0.02),
    ] {
        let opts = QuantOptions {
            weights,
            ..QuantOptions::default()
        };
        let (rms, worst) = fixed_error(&net, &opts);
        println!("{weights:?}: error / output std: rms {rms:.5}, max {worst:.5}");
        assert!(
            rms <= rms_bound && worst <= max_bound,
            "{weights:?}: rms {rms:.5} (bound {rms_bound}), max {worst:.5} (bound {max_bound})"
        );
    }
}

/// Error-aware rounding reaches the dense nodes of a graph (softmax-gated,
/// ungated, on concatenations): the int8 error falls, the blob size stays.
#[test]
fn error_aware_rounding_lowers_the_graph_int8_error() {
    let net = branching_net(SEED);
    let opts = |compensation_samples| QuantOptions {
        compensation_samples,
        ..QuantOptions::default()
    };
    let (a, b) = (
        export(&net, None, &opts(0)).unwrap().0,
        export(&net, None, &opts(4096)).unwrap().0,
    );
    assert_eq!(a.len(), b.len());
    assert_ne!(a, b);
    let ((rn, mn), (ra, ma)) = (fixed_error(&net, &opts(0)), fixed_error(&net, &opts(4096)));
    println!("graph int8: to nearest rms {rn:.5} max {mn:.5}; error-aware rms {ra:.5} max {ma:.5}");
    assert!(ra < 0.9 * rn, "rms {ra} vs {rn}");
}

/// The exporter's arena plan uses no more than the largest total of
/// buffers live at one step, the least any plan can: on the graph and on
/// every golden chain.
#[test]
fn arena_plans_reach_the_lower_bound() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("golden");
    for case in host_sim::golden::CASES {
        let blob = std::fs::read(root.join(case).join("model.blob")).unwrap();
        let model = Model::from_bytes(&blob).unwrap();
        let bound = exporter::plan::lower_bound(model.header());
        assert_eq!(model.arena_elements(), bound, "{case}");
        println!("{case}: arena {} elements", model.arena_elements());
    }
}

fn description(net: &Net) -> GraphFile {
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("g.json");
    write_graph(net, &json, &dir.path().join("w.npz")).unwrap();
    serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap()
}

/// A broken description is refused with one line naming the node and the
/// problem.
#[test]
fn broken_descriptions_name_the_node_and_the_problem() {
    let net = branching_net(SEED);
    let dir = tempfile::tempdir().unwrap();
    let (json, weights) = (dir.path().join("g.json"), dir.path().join("w.npz"));
    write_graph(&net, &json, &weights).unwrap();
    let arrays = exporter::cp::import::read_arrays(&weights).unwrap();
    let good = description(&net);
    net_from_file(&good, &arrays).unwrap();
    type Edit = Box<dyn Fn(&mut GraphFile)>;
    let cases: Vec<(Edit, &str)> = vec![
        (
            Box::new(|f| f.nodes[1].inputs = vec!["gate9".into()]),
            "no earlier node named \"gate9\"",
        ),
        (
            Box::new(|f| f.nodes[0].inputs = vec!["input[0..41]".into()]),
            "outside 0..40",
        ),
        (
            Box::new(|f| f.nodes[8].gate = Some("gate3".into())),
            "is not \"phase\" or an earlier softmax node",
        ),
        (
            Box::new(|f| f.nodes[8].gate = None),
            "4 experts, but its gate gives 1",
        ),
        (
            Box::new(|f| f.nodes[7].inputs = vec!["gate2".into()]),
            "a softmax gate takes 1 to 8 logits, not 16",
        ),
        (
            Box::new(|f| f.nodes[9].inputs = vec!["alpha".into()]),
            "a softmax gate is a gate, not an input",
        ),
        (
            Box::new(|f| f.nodes[2].activation = Some("relu".into())),
            "activation \"relu\"",
        ),
        (Box::new(|f| f.nodes[3].op = "conv".into()), "op \"conv\""),
        (
            Box::new(|f| f.nodes[4].name = "pose1".into()),
            "the name is taken",
        ),
        (Box::new(|f| f.version = 2), "version 1 description"),
        (
            Box::new(|f| {
                f.nodes[8].gate = Some("phase".into());
                f.phase_gating = None;
            }),
            "node 8 (\"moe1\"): gated by the phase, but the description has no phase_gating",
        ),
        (
            Box::new(|f| f.nodes[1].inputs = vec!["gate1[0..15]".into()]),
            "has 16 inputs, but the node's input slices give 15",
        ),
    ];
    for (edit, want) in cases {
        let mut f = good.clone();
        edit(&mut f);
        let err = format!("{:#}", net_from_file(&f, &arrays).unwrap_err());
        assert!(err.contains(want), "{err:?} should say {want:?}");
        assert!(!err.contains('\n'), "{err:?}");
    }
}

/// The float graph: the gate is a softmax (coefficients sum to 1), the
/// decoder reads only its slice of the last gated layer.
#[test]
fn the_float_graph_wires_what_the_description_says() {
    let net = branching_net(SEED);
    let Wiring::Graph(g) = &net.wiring else {
        panic!("a graph")
    };
    let x: Vec<f64> = net.xmean.iter().map(|m| m + 0.3).collect();
    let t = net.graph_trace(g, &x, 0.0);
    let alpha = g
        .nodes
        .iter()
        .position(|n| n.op == GraphOp::Softmax)
        .unwrap();
    assert!((t.out[alpha].sum() - 1.0).abs() < 1e-12);
    assert!(t.out[alpha].iter().all(|&c| c > 0.0));
    // The concatenation is pose2 then cost2.
    let moe1 = g.nodes.iter().position(|n| n.name == "moe1").unwrap();
    let (p2, c2) = (
        g.nodes.iter().position(|n| n.name == "pose2").unwrap(),
        g.nodes.iter().position(|n| n.name == "cost2").unwrap(),
    );
    let cat: Vec<f64> = t.out[p2].iter().chain(&t.out[c2]).copied().collect();
    assert_eq!(t.inputs[moe1].to_vec(), cat);
    let dec1 = g.nodes.iter().position(|n| n.name == "dec1").unwrap();
    assert_eq!(
        t.inputs[dec1].to_vec(),
        t.out[dec1 - 1].iter().take(16).copied().collect::<Vec<_>>()
    );
}

/// The graph moments (summed a chunk at a time) equal the per-sample sums
/// over each node's concatenated input and its gate's coefficients.
#[test]
fn graph_moments_equal_the_per_sample_sums() {
    use exporter::quantise::moments::graph_moments;
    use phasegate::blob::GateSource;
    let net = branching_net(SEED);
    let Wiring::Graph(g) = &net.wiring else {
        panic!("a graph")
    };
    let samples = normal_inputs(&net.xmean.to_vec(), &net.xstd.to_vec(), 600, 1.0, 3);
    let got = graph_moments(
        &net,
        g,
        &exporter::quantise::moments::WeightedSamples::uniform(samples.clone()),
        |i| i % 2 == 0,
    );
    let n = samples.inputs.len() as f64;
    let close = |a: f64, b: f64| (a - b).abs() < 1e-9 * (1.0 + b.abs());
    let mut checked = 0;
    for (i, node) in g.nodes.iter().enumerate() {
        let GraphOp::Layer { layer, .. } = node.op else {
            assert!(got[i].is_none(), "node {i} is no layer");
            continue;
        };
        let Some(m) = &got[i] else {
            assert!(i % 2 == 1, "node {i} was wanted");
            continue;
        };
        let experts = net.layers[layer].experts().max(1);
        let dim = net.layers[layer].in_dim();
        let mut second = vec![vec![0.0; dim * dim]; experts];
        let mut gm = vec![0.0; experts];
        for (x, &p) in samples.inputs.iter().zip(&samples.phases) {
            let t = net.graph_trace(g, x, p);
            let gate: Vec<f64> = match node.gate {
                GateSource::None => vec![1.0],
                GateSource::Node(j) => t.out[usize::from(j)].to_vec(),
                GateSource::Phase => unreachable!("the proof model has no phase gate"),
            };
            let h = &t.inputs[i];
            for (k, &gk) in gate.iter().enumerate() {
                gm[k] += gk / n;
                for a in 0..dim {
                    for b in 0..dim {
                        second[k][a * dim + b] += gk * gk * h[a] * h[b] / n;
                    }
                }
            }
        }
        for k in 0..experts {
            assert!(close(m.gate_mean[k], gm[k]), "node {i} expert {k}");
            assert!(
                m.second[k]
                    .iter()
                    .zip(&second[k])
                    .all(|(a, b)| close(*a, *b)),
                "node {i} expert {k}"
            );
        }
        checked += 1;
    }
    assert!(checked >= 4, "{checked} nodes checked");
}

/// `--int16-budget` on a graph tries its layer nodes (not its softmax
/// node), or reports those whose int16 weights alone would outgrow the
/// budget, and buys the ones it chooses as int16 nodes.
#[test]
fn int16_budget_buys_graph_layer_nodes() {
    let net = branching_net(SEED);
    let Wiring::Graph(g) = &net.wiring else {
        panic!("a graph")
    };
    let (blob, report) = exporter::budget::export_with_int16_budget(
        &net,
        None,
        &QuantOptions::default(),
        4000,
        |_, _| {},
    )
    .unwrap();
    let b = report.int16_budget.unwrap();
    let round0: Vec<usize> = b
        .trials
        .iter()
        .filter(|t| t.round == 0)
        .map(|t| t.layer)
        .collect();
    let layer_nodes: Vec<usize> = (0..g.nodes.len())
        .filter(|&i| matches!(g.nodes[i].op, GraphOp::Layer { .. }))
        .collect();
    let mut seen: Vec<usize> = round0
        .iter()
        .copied()
        .chain(b.unaffordable.iter().map(|u| u.layer))
        .collect();
    seen.sort_unstable();
    assert_eq!(seen, layer_nodes, "each layer node tried or reported once");
    for u in &b.unaffordable {
        assert!(u.min_extra_bytes > 4000 && u.left_bytes == 4000, "{u:?}");
    }
    assert!(!b.int16_layers.is_empty() && b.spent_bytes <= 4000, "{b:?}");
    let model = Model::from_bytes(&blob).unwrap();
    for &i in &b.int16_layers {
        let NodeOp::Layer(l) = model.nodes().iter().nth(i).unwrap().op else {
            panic!("node {i} is a layer")
        };
        assert_eq!(l.weights, WeightFormat::I16);
    }
    assert!(b.rms < b.rms_int8);
}

/// OMG's DEC clustering layer in a graph (`synthetic::dec_net`: an
/// encoder, the soft assignment to 3 centres, a head on `[q, z]`): the
/// blob carries a `Dec` node and tracks the float graph as closely as the
/// RBF one does ([`fixed_error`]). Measured: see the assertion message.
#[test]
fn dec_graph_tracks_its_float_graph() {
    use host_sim::target::synthetic::{dec_net, rbf_net};
    use phasegate::blob::LayerOp;
    for seed in [5, 6, 7] {
        let dec = dec_net(seed);
        let (blob, _) = export(&dec, None, &QuantOptions::default()).unwrap();
        let model = Model::from_bytes(&blob).unwrap();
        let ops: Vec<_> = model
            .header()
            .nodes
            .iter()
            .filter_map(|n| match n.op {
                NodeOp::Layer(d) => Some(d.op),
                _ => None,
            })
            .collect();
        assert!(matches!(ops[1], LayerOp::Dec { .. }), "{ops:?}");
        for (weights, rms_bound, max_bound) in [
            (WeightFormat::I8, 0.02, 0.08),
            (WeightFormat::I16, 0.0005, 0.002),
        ] {
            let opts = QuantOptions {
                weights,
                ..QuantOptions::default()
            };
            let (rms, worst) = fixed_error(&dec, &opts);
            let (rbf_rms, rbf_worst) = fixed_error(&rbf_net(seed), &opts);
            println!(
                "seed {seed} {weights:?}: DEC rms {rms:.5} max {worst:.5}; \
                 RBF rms {rbf_rms:.5} max {rbf_worst:.5}"
            );
            assert!(
                rms <= rms_bound && worst <= max_bound,
                "seed {seed} {weights:?}: rms {rms:.5} (bound {rms_bound}), \
                 max {worst:.5} (bound {max_bound})"
            );
        }
    }
}
