//! The graph importer: a small JSON description of the wiring plus the
//! weights in an `.npz` or `.safetensors` file (PyTorch state dicts saved
//! with `safetensors.torch.save_file` load as they are). The format is
//! specified in `docs/graph-format.md`; [`write_graph`] writes it back.
//!
//! ```json
//! {
//!   "format": "phasegate-graph", "version": 1,
//!   "input_dim": 40,
//!   "normalisation": {"x_mean": "x_mean", "x_std": "x_std",
//!                     "y_mean": "y_mean", "y_std": "y_std"},
//!   "phase_gating": null,
//!   "nodes": [
//!     {"name": "gate1", "op": "dense", "inputs": ["input[0..8]"], "activation": "elu"},
//!     {"name": "gate3", "op": "dense", "inputs": ["gate1"]},
//!     {"name": "alpha", "op": "softmax", "inputs": ["gate3"]},
//!     {"name": "moe1", "op": "dense", "inputs": ["pose2", "cost2"],
//!      "gate": "alpha", "activation": "elu"}
//!   ],
//!   "output": "dec2[0..10]"
//! }
//! ```

#![deny(clippy::arithmetic_side_effects)]

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use ndarray::{Array1, Array2};
use serde::{Deserialize, Serialize};

use super::graph::{Graph, GraphNode, GraphOp};
use super::{ExpertLayer, GatingMode, Net, NetLayer, Wiring};
use crate::error::in_weights;
use crate::io::tensors::NpArray;
use phasegate::blob::{GateSource, Slice, Source, MAX_NODES, MAX_NODE_INPUTS};

/// The `format` field.
pub const FORMAT: &str = "phasegate-graph";
/// The `version` field this exporter reads and writes.
pub const VERSION: u32 = 1;

/// Names of the normalisation arrays in the weights file.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Normalisation {
    /// Input mean (`input_dim`).
    pub x_mean: String,
    /// Input standard deviation (`input_dim`, positive).
    pub x_std: String,
    /// Output mean (the output's width).
    pub y_mean: String,
    /// Output standard deviation (the output's width, positive).
    pub y_std: String,
}

/// One node as the JSON file spells it.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct NodeFile {
    /// Unique name; slices name nodes by it.
    pub name: String,
    /// `"dense"` or `"softmax"`.
    pub op: String,
    /// Input slices, concatenated: `"input"`, `"input[a..b]"`, `"<node>"`,
    /// `"<node>[a..b]"`.
    pub inputs: Vec<String>,
    /// Weights array (dense): `(out, in)`, or `(K, out, in)` for `K`
    /// experts. Default `"<name>.weight"`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub weight: Option<String>,
    /// Bias array (dense): `(out)` or `(K, out)`. Default `"<name>.bias"`;
    /// zero when absent from the weights file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bias: Option<String>,
    /// `"phase"` or the name of a softmax node; absent for ungated nodes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gate: Option<String>,
    /// `"elu"` or `"none"` (default).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub activation: Option<String>,
}

/// The whole JSON file.
#[derive(Clone, Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct GraphFile {
    /// Must be [`FORMAT`].
    pub format: String,
    /// Must be [`VERSION`].
    pub version: u32,
    /// Width of the raw input.
    pub input_dim: usize,
    /// Normalisation arrays; absent means mean 0, std 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normalisation: Option<Normalisation>,
    /// `"constant"`, `"linear"` or `"cubic"` for nodes gated by `"phase"`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub phase_gating: Option<String>,
    /// Nodes in evaluation order.
    pub nodes: Vec<NodeFile>,
    /// The model output: a slice, as in `inputs`.
    pub output: String,
}

/// Parses `"name"` or `"name[a..b]"`.
fn parse_slice(text: &str, names: &BTreeMap<&str, (u8, usize)>, input_dim: usize) -> Result<Slice> {
    let (name, range) = match text.split_once('[') {
        None => (text, None),
        Some((n, rest)) => {
            let r = rest
                .strip_suffix(']')
                .ok_or_else(|| anyhow!("slice {text:?}: expected name[a..b]"))?;
            let (a, b) = r
                .split_once("..")
                .ok_or_else(|| anyhow!("slice {text:?}: expected name[a..b]"))?;
            let a: usize = a
                .trim()
                .parse()
                .with_context(|| format!("slice {text:?}"))?;
            let b: usize = b
                .trim()
                .parse()
                .with_context(|| format!("slice {text:?}"))?;
            (n, Some((a, b)))
        }
    };
    let (source, width) = if name == "input" {
        (Source::Input, input_dim)
    } else {
        let &(j, w) = names
            .get(name)
            .ok_or_else(|| anyhow!("slice {text:?}: no earlier node named {name:?}"))?;
        (Source::Node(j), w)
    };
    let (a, b) = range.unwrap_or((0, width));
    if a >= b || b > width {
        bail!("slice {text:?}: {a}..{b} is empty or outside 0..{width}");
    }
    let u16_of = |v: usize| u16::try_from(v).map_err(|_| anyhow!("slice {text:?} too wide"));
    Ok(Slice {
        source,
        start: u16_of(a)?,
        len: u16_of(b.saturating_sub(a))?, // a < b above
    })
}

fn vector(arrays: &BTreeMap<String, NpArray>, name: &str, len: usize) -> Result<Array1<f64>> {
    let a = arrays
        .get(name)
        .ok_or_else(|| in_weights(format!("missing array {name:?}")))?;
    if a.data.len() != len || a.shape.len() != 1 {
        return Err(in_weights(format!(
            "array {name:?} has shape {:?}, expected ({len})",
            a.shape
        )));
    }
    Ok(Array1::from(a.data.clone()))
}

/// A dense layer from a `(out, in)` or `(K, out, in)` weight and a bias.
fn dense(
    arrays: &BTreeMap<String, NpArray>,
    weight: &str,
    bias: &str,
    in_dim: usize,
) -> Result<ExpertLayer> {
    let w = arrays
        .get(weight)
        .ok_or_else(|| in_weights(format!("missing array {weight:?}")))?;
    let (k, out, inp) = match (
        crate::io::sizes::dims::<2>(&w.shape),
        crate::io::sizes::dims::<3>(&w.shape),
    ) {
        (Some([o, i]), _) => (1, o, i),
        (_, Some([k, o, i])) => (k, o, i),
        _ => {
            return Err(in_weights(format!(
                "array {weight:?} has shape {:?}, expected (out, in) or (K, out, in)",
                w.shape
            )))
        }
    };
    if inp != in_dim {
        return Err(in_weights(format!(
            "array {weight:?} has {inp} inputs, but the node's input slices give {in_dim}"
        )));
    }
    let (per, rows) = (
        crate::io::sizes::mul(out, inp, weight)?,
        crate::io::sizes::mul(k, out, weight)?,
    );
    if k == 0 || per == 0 {
        return Err(in_weights(format!("array {weight:?} is empty")));
    }
    if crate::io::sizes::element_count(&w.shape) != Some(w.data.len()) {
        return Err(in_weights(format!(
            "array {weight:?} does not hold the elements of its shape {:?}",
            w.shape
        )));
    }
    let b = match arrays.get(bias) {
        None => vec![0.0; rows],
        Some(b) if b.data.len() == rows => b.data.clone(),
        Some(b) if b.data.len() == out => b.data.repeat(k),
        Some(b) => {
            return Err(in_weights(format!(
                "array {bias:?} has shape {:?}, expected ({k}, {out}) or ({out})",
                b.shape
            )))
        }
    };
    if let Some(i) = w.data.iter().position(|v| !v.is_finite()) {
        return Err(in_weights(format!(
            "array {weight:?} has a non-finite value at index {i}"
        )));
    }
    if let Some(i) = b.iter().position(|v| !v.is_finite()) {
        return Err(in_weights(format!(
            "array {bias:?} has a non-finite value at index {i}"
        )));
    }
    Ok(ExpertLayer {
        w: w.data
            .chunks_exact(per)
            .map(|ws| Array2::from_shape_vec((out, inp), ws.to_vec()))
            .collect::<Result<_, _>>()?,
        b: b.chunks_exact(out)
            .map(|bs| Array1::from(bs.to_vec()))
            .collect(),
    })
}

/// Builds a graph [`Net`] from a parsed description and its arrays.
pub fn net_from_file(file: &GraphFile, arrays: &BTreeMap<String, NpArray>) -> Result<Net> {
    if file.format != FORMAT || file.version != VERSION {
        bail!(
            "not a {FORMAT} version {VERSION} description (format {:?}, version {})",
            file.format,
            file.version
        );
    }
    if file.nodes.is_empty() || file.nodes.len() > MAX_NODES {
        bail!("{} nodes: a graph has 1 to {MAX_NODES}", file.nodes.len());
    }
    let mode = match file.phase_gating.as_deref() {
        None => GatingMode::Constant,
        Some(m) => m.parse().map_err(|e| anyhow!("phase_gating: {e}"))?,
    };
    let mut names: BTreeMap<&str, (u8, usize)> = BTreeMap::new();
    let mut layers = Vec::new();
    let mut nodes: Vec<GraphNode> = Vec::new();
    for (i, n) in file.nodes.iter().enumerate() {
        let ctx = || format!("node {i} ({:?})", n.name);
        if n.name == "input" || names.contains_key(n.name.as_str()) {
            bail!("{}: the name is taken", ctx());
        }
        if n.inputs.is_empty() || n.inputs.len() > MAX_NODE_INPUTS {
            bail!("{}: 1 to {MAX_NODE_INPUTS} input slices", ctx());
        }
        let inputs = n
            .inputs
            .iter()
            .map(|s| parse_slice(s, &names, file.input_dim))
            .collect::<Result<Vec<_>>>()
            .with_context(ctx)?;
        for s in &inputs {
            if let Source::Node(j) = s.source {
                if nodes[usize::from(j)].op == GraphOp::Softmax {
                    bail!("{}: a softmax gate is a gate, not an input", ctx());
                }
            }
        }
        let in_dim: usize = inputs.iter().map(|s| usize::from(s.len)).sum();
        // The gate, and the expert count it implies (a softmax gate's is
        // its width; the phase's is whatever the weights have).
        let (gate, gate_experts) = match n.gate.as_deref() {
            None => (GateSource::None, Some(1)),
            // Absent, the mode would default to constant: a network other
            // than the one trained.
            Some("phase") if file.phase_gating.is_none() => bail!(
                "{}: gated by the phase, but the description has no phase_gating \
                 (\"constant\", \"linear\" or \"cubic\")",
                ctx()
            ),
            Some("phase") => (GateSource::Phase, None),
            Some(g) => match names.get(g) {
                Some(&(j, k))
                    if matches!(
                        nodes.get(usize::from(j)),
                        Some(GraphNode {
                            op: GraphOp::Softmax,
                            ..
                        })
                    ) =>
                {
                    (GateSource::Node(j), Some(k))
                }
                _ => bail!(
                    "{}: gate {g:?} is not \"phase\" or an earlier softmax node",
                    ctx()
                ),
            },
        };
        let elu = match n.activation.as_deref() {
            None | Some("none") => false,
            Some("elu") => true,
            Some(a) => bail!("{}: activation {a:?} (expected \"elu\" or \"none\")", ctx()),
        };
        let (op, width) = match n.op.as_str() {
            "softmax" => {
                if gate != GateSource::None || elu || n.weight.is_some() || n.bias.is_some() {
                    bail!(
                        "{}: a softmax node has no gate, activation or weights",
                        ctx()
                    );
                }
                if !(1..=phasegate::MAX_LOGITS).contains(&in_dim) {
                    bail!(
                        "{}: a softmax gate takes 1 to 8 logits, not {in_dim}",
                        ctx()
                    );
                }
                (GraphOp::Softmax, in_dim)
            }
            "dense" => {
                let weight = n.weight.clone().unwrap_or(format!("{}.weight", n.name));
                let bias = n.bias.clone().unwrap_or(format!("{}.bias", n.name));
                let layer = dense(arrays, &weight, &bias, in_dim).with_context(ctx)?;
                let (k, out) = (layer.experts(), layer.w[0].nrows());
                let want = gate_experts.unwrap_or(k);
                if k != want {
                    bail!("{}: {k} experts, but its gate gives {want}", ctx());
                }
                layers.push(NetLayer::Dense(layer));
                (
                    GraphOp::Layer {
                        layer: layers.len().saturating_sub(1), // just pushed
                        elu,
                    },
                    out,
                )
            }
            other => bail!(
                "{}: op {other:?} (expected \"dense\" or \"softmax\")",
                ctx()
            ),
        };
        names.insert(&n.name, (i as u8, width));
        nodes.push(GraphNode {
            name: n.name.clone(),
            op,
            inputs,
            gate,
        });
    }
    let output = parse_slice(&file.output, &names, file.input_dim).context("output")?;
    if let Source::Node(j) = output.source {
        if nodes[usize::from(j)].op == GraphOp::Softmax {
            bail!("output: a softmax gate has no output vector");
        }
    }
    let out_dim = usize::from(output.len);
    let (xmean, xstd, ymean, ystd) = match &file.normalisation {
        None => (
            Array1::zeros(file.input_dim),
            Array1::ones(file.input_dim),
            Array1::zeros(out_dim),
            Array1::ones(out_dim),
        ),
        Some(nm) => (
            vector(arrays, &nm.x_mean, file.input_dim)?,
            vector(arrays, &nm.x_std, file.input_dim)?,
            vector(arrays, &nm.y_mean, out_dim)?,
            vector(arrays, &nm.y_std, out_dim)?,
        ),
    };
    if xstd
        .iter()
        .chain(&ystd)
        .any(|s| !(s.is_finite() && *s > 0.0))
        || xmean.iter().chain(&ymean).any(|m| !m.is_finite())
    {
        bail!("normalisation: means must be finite and standard deviations finite and positive");
    }
    Ok(Net {
        mode,
        xmean,
        xstd,
        ymean,
        ystd,
        layers,
        wiring: Wiring::Graph(Graph { nodes, output }),
    })
}

/// Reads a graph description (`.json`) and its weights (`.npz` or
/// `.safetensors`).
pub fn read_graph(json: &Path, weights: &Path) -> Result<Net> {
    let bytes = crate::io::atomic::read_input(json)
        .with_context(|| format!("cannot read {}", json.display()))?;
    let text = String::from_utf8(bytes)
        .with_context(|| format!("{}: not a graph description (not UTF-8)", json.display()))?;
    let file: GraphFile = serde_json::from_str(&text)
        .with_context(|| format!("{}: not a graph description", json.display()))?;
    let arrays = crate::io::tensors::read_arrays(weights)?;
    net_from_file(&file, &arrays).map_err(|e| name_the_file(e, json, weights))
}

/// `e` as one line naming the file of the (description, weights) pair it
/// concerns: the weights file (and whose weights) for a missing array, a
/// wrong shape or a bad value, the description for the rest.
pub(crate) fn name_the_file(e: anyhow::Error, description: &Path, weights: &Path) -> anyhow::Error {
    if crate::error::concerns_weights(&e) {
        anyhow!(
            "{}: {e:#} (the weights of {})",
            weights.display(),
            description.display()
        )
    } else {
        anyhow!("{}: {e:#}", description.display())
    }
}

fn slice_text(g: &Graph, s: &Slice, width: usize) -> String {
    let name = match s.source {
        Source::Input => "input",
        Source::Node(j) => g.nodes[usize::from(j)].name.as_str(),
    };
    if s.start == 0 && usize::from(s.len) == width {
        name.to_string()
    } else {
        format!(
            "{name}[{}..{}]",
            s.start,
            u32::from(s.start).saturating_add(u32::from(s.len))
        )
    }
}

/// Writes a graph net as a description (`json`) and its weights as f32
/// (`.npz`, or `.safetensors` by extension: `"<node>.weight"`,
/// `"<node>.bias"`, and the normalisation as `x_mean`, `x_std`, `y_mean`,
/// `y_std`), which [`read_graph`] reads back to the same net up to the
/// f32 rounding of the weights.
pub fn write_graph(net: &Net, json: &Path, weights: &Path) -> Result<()> {
    let Wiring::Graph(g) = &net.wiring else {
        bail!("write_graph writes graphs; chains have their own .npz layouts");
    };
    let f32s = |v: &mut dyn Iterator<Item = f64>| v.map(|x| x as f32).collect::<Vec<f32>>();
    let mut arrays: Vec<(String, Vec<u64>, Vec<f32>)> = vec![
        (
            "x_mean".into(),
            vec![net.xmean.len() as u64],
            f32s(&mut net.xmean.iter().copied()),
        ),
        (
            "x_std".into(),
            vec![net.xstd.len() as u64],
            f32s(&mut net.xstd.iter().copied()),
        ),
        (
            "y_mean".into(),
            vec![net.ymean.len() as u64],
            f32s(&mut net.ymean.iter().copied()),
        ),
        (
            "y_std".into(),
            vec![net.ystd.len() as u64],
            f32s(&mut net.ystd.iter().copied()),
        ),
    ];
    let mut nodes = Vec::new();
    for n in &g.nodes {
        let width = |s: &Slice| g.width(&net.layers, net.input_dim(), s.source);
        let inputs = n
            .inputs
            .iter()
            .map(|s| slice_text(g, s, width(s)))
            .collect();
        let gate = match n.gate {
            GateSource::None => None,
            GateSource::Phase => Some("phase".to_string()),
            GateSource::Node(j) => Some(g.nodes[usize::from(j)].name.clone()),
        };
        let (op, activation) = match &n.op {
            GraphOp::Softmax => ("softmax", None),
            GraphOp::Residual { .. } => bail!(
                "node {:?}: a residual addition (style adapters) has no place in a graph \
                 description; adapters are written with write_adapter and exported as style blobs",
                n.name
            ),
            GraphOp::Layer { layer, elu } => {
                let NetLayer::Dense(d) = &net.layers[*layer] else {
                    bail!("node {:?}: only dense layers are written", n.name);
                };
                let (k, out, inp) = (d.experts(), d.w[0].nrows(), d.w[0].ncols());
                let shape = if k == 1 && n.gate == GateSource::None {
                    vec![out as u64, inp as u64]
                } else {
                    vec![k as u64, out as u64, inp as u64]
                };
                let bshape = if shape.len() == 2 {
                    vec![out as u64]
                } else {
                    vec![k as u64, out as u64]
                };
                arrays.push((
                    format!("{}.weight", n.name),
                    shape,
                    f32s(&mut d.w.iter().flat_map(|w| w.iter().copied())),
                ));
                arrays.push((
                    format!("{}.bias", n.name),
                    bshape,
                    f32s(&mut d.b.iter().flat_map(|b| b.iter().copied())),
                ));
                ("dense", elu.then(|| "elu".to_string()))
            }
        };
        nodes.push(NodeFile {
            name: n.name.clone(),
            op: op.to_string(),
            inputs,
            weight: None,
            bias: None,
            gate,
            activation,
        });
    }
    let phase_gating = g
        .nodes
        .iter()
        .any(|n| n.gate == GateSource::Phase)
        .then(|| net.mode.name().to_string());
    let file = GraphFile {
        format: FORMAT.to_string(),
        version: VERSION,
        input_dim: net.input_dim(),
        normalisation: Some(Normalisation {
            x_mean: "x_mean".into(),
            x_std: "x_std".into(),
            y_mean: "y_mean".into(),
            y_std: "y_std".into(),
        }),
        phase_gating,
        output: slice_text(
            g,
            &g.output,
            g.width(&net.layers, net.input_dim(), g.output.source),
        ),
        nodes,
    };
    let refs: Vec<(&str, Vec<u64>, Vec<f32>)> = arrays
        .iter()
        .map(|(n, s, d)| (n.as_str(), s.clone(), d.clone()))
        .collect();
    crate::io::tensors::write_arrays(weights, &refs)?;
    let text = serde_json::to_string_pretty(&file)?;
    crate::io::atomic::write_atomic(json, format!("{text}\n").as_bytes())?;
    Ok(())
}
