//! The quantiser's format policy for graphs ([`crate::net::Wiring::Graph`]): the same
//! per-op hooks ([`crate::net::NetLayer::quantise`]) and encoder as chains, with formats
//! chosen per node from calibration:
//!
//! * the normalised input columns at Q`input_frac`, as for chains;
//! * every layer row at a power of two, as fine as its calibrated maximum
//!   (times the headroom) allows, at most Q15 (ELU reads it; a row feeding
//!   several nodes needs one format, so the chain's joint choice with its
//!   one consumer does not apply); the graph's output rows no finer than
//!   the input columns, whose range real motion needs;
//! * every logit row of a softmax gate at the coarsest format among them,
//!   so the gate compares integers of one scale (the loader checks it);
//! * each node's input columns at its producers' row formats, the output
//!   stage undoing the output rows' formats.
//!
//! Calibration runs the float graph on the quantiser's usual inputs (normal
//! around the normalisation means) and phases.

use std::collections::BTreeMap;

use phasegate::blob::{Activation, GateSource, Gating, ModelKind, Slice, SoftmaxDesc, Source};

use super::{
    frac_for, gating_for, output_stage_records, LayerSpec, QuantError, QuantLayerReport,
    QuantOptions, Quantised,
};
use crate::calibrate::{calibration_inputs, max_into, ms_into, Ranges};
use crate::lower::qmodel::{QKind, QModel, QNode, QNodeOp, Wiring as QWiring};
use crate::net::{Graph, GraphOp, Net};

/// What calibration saw at one node.
#[derive(Clone, Debug, Default)]
struct NodeStats {
    /// Max |pre-activation| per row.
    rows: Vec<f64>,
    /// Mean square per input column.
    input_ms: Vec<f64>,
    /// Max |middle component| (CP).
    mid_max: Option<Vec<f64>>,
    /// Mean square per middle component (CP).
    mid_ms: Option<Vec<f64>>,
}

fn calibrate(net: &Net, g: &Graph, opts: &QuantOptions) -> Vec<NodeStats> {
    let samples = calibration_inputs(net, opts);
    let n = samples.inputs.len().max(1) as f64;
    let mut stats = vec![NodeStats::default(); g.nodes.len()];
    for (x, &p) in samples.inputs.iter().zip(&samples.phases) {
        let t = net.graph_trace(g, x, p);
        for (i, s) in stats.iter_mut().enumerate() {
            max_into(&mut s.rows, &t.pre[i]);
            ms_into(&mut s.input_ms, &t.inputs[i], n);
            if let Some(m) = &t.mids[i] {
                max_into(s.mid_max.get_or_insert_with(Vec::new), m);
                ms_into(s.mid_ms.get_or_insert_with(Vec::new), m, n);
            }
        }
    }
    stats
}

/// The scales (integer units per real unit) of `s`'s elements.
fn scales_of<'a>(input: &'a [f64], rows: &'a [Vec<f64>], s: &Slice) -> &'a [f64] {
    let v = match s.source {
        Source::Input => input,
        Source::Node(j) => &rows[usize::from(j)],
    };
    let a = usize::from(s.start);
    &v[a..a + usize::from(s.len)]
}

/// The input moments of the graph's int8 dense nodes, from
/// `compensation_samples` normal inputs and the recorded rows, for
/// error-aware rounding (none when `compensation_samples` is 0).
fn graph_moments(
    net: &Net,
    g: &Graph,
    opts: &QuantOptions,
) -> Vec<Option<super::moments::LayerMoments>> {
    if opts.compensation_samples == 0 {
        return vec![None; g.nodes.len()];
    }
    let samples = super::compensation_inputs(net, opts);
    super::moments::graph_moments(net, g, &samples, |i| {
        opts.weights_of(i) == phasegate::blob::WeightFormat::I8
            && matches!(
                g.nodes[i].op,
                GraphOp::Layer { layer, .. } if matches!(net.layers.get(layer), Some(crate::net::NetLayer::Dense(_)))
            )
    })
}

/// Caps the rows of the graph's output at the input stage's format. An
/// autoregressive model's outputs are its next inputs, which the input
/// stage takes to `input_range_sigma` standard deviations; real motion
/// drives some outputs past what the normal calibration inputs reach
/// (small_rbfcat_r1's joint velocities to -4.6 std, where rows whose
/// calibration reached about 1 std saturated at -4 for dozens of frames,
/// docs/omg.md), and a row finer than the input stage buys nothing the
/// next frame keeps.
fn cover_the_input_range(fracs: &mut [Vec<u8>], g: &Graph, input_frac: u8) {
    let Source::Node(j) = g.output.source else {
        return;
    };
    let (a, n) = (usize::from(g.output.start), usize::from(g.output.len));
    if let Some(rows) = fracs
        .get_mut(usize::from(j))
        .and_then(|f| f.get_mut(a..a + n))
    {
        for f in rows {
            *f = (*f).min(input_frac);
        }
    }
}

/// Quantises a graph net: see the module documentation.
pub fn quantise_graph(net: &Net, g: &Graph, opts: &QuantOptions) -> Result<Quantised, QuantError> {
    let phase_experts = g.phase_experts(&net.layers);
    let gating = if phase_experts > 0 {
        gating_for(net.mode, phase_experts)?
    } else {
        Gating::Single
    };
    let stats = calibrate(net, g, opts);
    let moments = graph_moments(net, g, opts);
    let input_frac = frac_for(opts.input_range_sigma, 1.0, 15);
    let input_scales = vec![f64::from(1u32 << input_frac); net.input_dim()];
    // Row formats: each row as fine as its range allows, then the logits of
    // each softmax gate brought to their coarsest.
    let mut fracs: Vec<Vec<u8>> = stats
        .iter()
        .map(|s| {
            s.rows
                .iter()
                .map(|&m| frac_for(m, opts.headroom, 15))
                .collect()
        })
        .collect();
    cover_the_input_range(&mut fracs, g, input_frac);
    for (&i, given) in &opts.row_formats {
        match fracs.get_mut(i) {
            Some(f) if f.len() == given.len() => f.clone_from(given),
            _ => {
                return Err(QuantError::Invalid(format!(
                    "node {i}: {} row formats given for a node of {} rows",
                    given.len(),
                    fracs.get(i).map_or(0, Vec::len)
                )))
            }
        }
    }
    let mut softmax_frac = BTreeMap::new();
    for (i, n) in g.nodes.iter().enumerate() {
        if n.op != GraphOp::Softmax {
            continue;
        }
        let rows = |s: &Slice| match s.source {
            Source::Node(j) => Ok((
                usize::from(j),
                usize::from(s.start)..usize::from(s.start + s.len),
            )),
            Source::Input => Err(QuantError::Invalid(format!(
                "node {:?}: softmax logits must come from layer nodes, not the input",
                n.name
            ))),
        };
        let mut frac = 15u8;
        for s in &n.inputs {
            let (j, r) = rows(s)?;
            frac = fracs[j][r].iter().copied().fold(frac, u8::min);
        }
        for s in &n.inputs {
            let (j, r) = rows(s)?;
            fracs[j][r].iter_mut().for_each(|f| *f = frac);
        }
        softmax_frac.insert(i, frac);
    }
    let scales: Vec<Vec<f64>> = fracs
        .iter()
        .map(|f| f.iter().map(|&b| f64::from(1u32 << b)).collect())
        .collect();

    let mut layers = Vec::new();
    let mut dequantised = net.layers.clone();
    let mut node_in_scales = vec![Vec::new(); g.nodes.len()];
    let mut reports = Vec::new();
    let mut nodes = Vec::new();
    for (i, n) in g.nodes.iter().enumerate() {
        let op = match &n.op {
            GraphOp::Softmax => QNodeOp::Softmax(SoftmaxDesc {
                experts: n.inputs.iter().map(|s| s.len).sum(),
                frac: softmax_frac[&i],
            }),
            // The blob's graph has no addition: the runtime adds a style's
            // output to its base layer's pre-activation itself.
            GraphOp::Residual { .. } => {
                return Err(QuantError::Invalid(format!(
                    "node {:?}: a residual addition is exported as style blobs beside \
                     the base model's blob (exporter style), not in a model blob",
                    n.name
                )))
            }
            GraphOp::Layer { layer, elu } => {
                let l = &net.layers[*layer];
                let in_scales: Vec<f64> = n
                    .inputs
                    .iter()
                    .flat_map(|s| scales_of(&input_scales, &scales, s).iter().copied())
                    .collect();
                let node_gating = match n.gate {
                    GateSource::None => Gating::Single,
                    GateSource::Phase => gating,
                    GateSource::Node(_) => Gating::Softmax {
                        experts: l.experts() as u16,
                    },
                };
                let spec = LayerSpec {
                    index: i,
                    in_scales: &in_scales,
                    targets: &scales[i],
                    fracs: &fracs[i],
                    activation: if *elu {
                        Activation::Elu
                    } else {
                        Activation::Identity
                    },
                    gated: n.gate != GateSource::None,
                    format: opts.weights_of(i),
                    gating: node_gating,
                    mid_max: stats[i].mid_max.as_deref(),
                    in_power: Some(&stats[i].input_ms),
                    mid_power: stats[i].mid_ms.as_deref(),
                    headroom: opts.headroom,
                    in_moments: moments.get(i).and_then(Option::as_ref),
                };
                let (ql, rep) = match l {
                    crate::net::NetLayer::Dense(d) => {
                        let (ql, rep, deq) = crate::ops::dense::quantise_dequantised(d, &spec)?;
                        dequantised[*layer] = crate::net::NetLayer::Dense(deq);
                        (ql, rep)
                    }
                    _ => l.quantise(&spec)?,
                };
                node_in_scales[i].clone_from(&in_scales);
                reports.push(QuantLayerReport {
                    calibrated_max: stats[i].rows.iter().copied().fold(0.0, f64::max),
                    ..rep
                });
                layers.push(ql);
                QNodeOp::Layer(layers.len() - 1)
            }
        };
        nodes.push(QNode {
            op,
            inputs: n.inputs.clone(),
            gate: n.gate,
        });
    }
    let out_scales = scales_of(&input_scales, &scales, &g.output);
    Ok(Quantised {
        model: QModel {
            kind: QKind::Model(ModelKind::Graph),
            gating,
            input_stage: net
                .xmean
                .iter()
                .zip(&net.xstd)
                .zip(&input_scales)
                .map(|((&m, &sd), &u)| (m as f32, (u / sd) as f32))
                .collect(),
            output_stage: output_stage_records(out_scales, &net.ystd, &net.ymean)?,
            layers,
            wiring: QWiring::Graph {
                nodes,
                output: g.output,
            },
        },
        layers: reports,
        ranges: Ranges::default(),
        input_frac,
        dequantised,
        in_scales: node_in_scales,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn output_rows_are_no_finer_than_the_input_stage() {
        let g = Graph {
            nodes: Vec::new(),
            output: Slice {
                source: Source::Node(1),
                start: 1,
                len: 2,
            },
        };
        let mut fracs = vec![vec![14, 14, 14], vec![13, 13, 12, 10]];
        cover_the_input_range(&mut fracs, &g, 11);
        // Only the output slice's rows move, and none gets finer.
        assert_eq!(fracs, vec![vec![14, 14, 14], vec![13, 11, 11, 10]]);
        let from_input = Graph {
            output: Slice {
                source: Source::Input,
                ..g.output
            },
            ..g
        };
        cover_the_input_range(&mut fracs, &from_input, 0);
        assert_eq!(fracs, vec![vec![14, 14, 14], vec![13, 11, 11, 10]]);
    }
}
