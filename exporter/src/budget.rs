//! Mixed precision under a flash budget (`--int16-budget BYTES`): which
//! layers of an int8 blob get int16 weights.
//!
//! Each choice is measured, not modelled: a candidate blob is exported
//! with the layer at int16 and run by the runtime itself on evaluation
//! inputs (normal samples around the input mean, plus the recorded rows of
//! `--calibration`), against the float network. The error is the RMS of
//! the outputs in units of each output's standard deviation, so outputs
//! with a large spread do not dominate. Greedy: while a layer fits in what
//! is left of the budget, take the one whose int16 weights remove the most
//! error per extra byte, if any removes error at all.
//!
//! The unit of choice is a whole layer: the runtime keeps one weight width
//! per layer, so on a three-layer network the budget buys at most three
//! steps, and a budget smaller than the smallest layer's extra bytes buys
//! nothing (the report says so, and which layers it did not try).

use phasegate::blob::WeightFormat;
use phasegate::{Model, Phase, Runtime};
use serde::Serialize;

use crate::control_points::Residual;
use crate::export::{export, ExportError, ExportReport};
use crate::io::samples::{normal_inputs, Samples};
use crate::net::{GraphOp, Net, Wiring};
use crate::quantise::QuantOptions;

/// Normal evaluation samples (the recorded rows come on top).
const EVAL_SAMPLES: usize = 256;
/// Keeps the evaluation inputs apart from the calibration inputs.
const EVAL_SEED: u64 = 0x00B0_D6E7;
/// Activation buffer elements of the evaluating runtime: any width a blob
/// header can declare.
const CAPACITY: usize = u16::MAX as usize;

/// One greedy step: a layer tried at int16 on top of the layers already
/// chosen.
#[derive(Clone, Debug, Serialize)]
pub struct Trial {
    /// Greedy round (0 first).
    pub round: usize,
    /// Layer index (of a graph: node index).
    pub layer: usize,
    /// Bytes the blob grows by.
    pub extra_bytes: usize,
    /// Output RMS (in output standard deviations) with this layer at int16.
    pub rms: f64,
    /// Taken in this round.
    pub chosen: bool,
}

/// Where the budget went (`int16_budget` in the export report).
#[derive(Clone, Debug, Serialize)]
pub struct BudgetReport {
    /// The budget, bytes.
    pub budget_bytes: usize,
    /// Bytes spent.
    pub spent_bytes: usize,
    /// Layers (of a graph: nodes) given int16 weights, in the order they
    /// were chosen.
    pub int16_layers: Vec<usize>,
    /// Output RMS of the all-int8 blob, output standard deviations.
    pub rms_int8: f64,
    /// Output RMS of the blob written.
    pub rms: f64,
    /// Evaluation inputs (normal samples + recorded rows).
    pub eval_rows: usize,
    /// Every trial.
    pub trials: Vec<Trial>,
    /// Layers never tried: their int16 weights alone would add more bytes
    /// than the budget had left.
    pub unaffordable: Vec<Unaffordable>,
}

/// A layer the budget could not buy whatever it gains.
#[derive(Clone, Debug, Serialize)]
pub struct Unaffordable {
    /// Layer index (of a graph: node index).
    pub layer: usize,
    /// Bytes its int16 weights add at least (one per int8 weight).
    pub min_extra_bytes: usize,
    /// What was left of the budget when it came up.
    pub left_bytes: usize,
}

/// Section alignment and header varints can move a blob's length by a
/// few bytes either way.
const LAYOUT_SLACK: usize = 64;

/// The bytes a layer of `report` grows by at least when its weights go
/// from int8 to int16: one per weight of a dense layer, less
/// [`LAYOUT_SLACK`]. 0 (always worth a trial) for the other forms, whose
/// weight counts the report does not give.
fn min_extra_bytes(report: &ExportReport, layer: usize) -> usize {
    report
        .layers
        .iter()
        .find(|r| r.index == layer && r.form == "dense" && r.weights == "int8")
        .map_or(0, |r| {
            (r.experts * r.in_dim * r.out_dim).saturating_sub(LAYOUT_SLACK)
        })
}

/// Exports `net` with int8 weights but for the layers `--int16-budget`
/// buys; `progress` is told each trial (done, upper bound of the total).
pub fn export_with_int16_budget(
    net: &Net,
    residual: Option<Residual>,
    opts: &QuantOptions,
    budget: usize,
    mut progress: impl FnMut(usize, usize),
) -> Result<(Vec<u8>, ExportReport), ExportError> {
    let eval = eval_inputs(net, opts);
    let keys = weight_keys(net);
    let layers = keys.len();
    let total = layers * (layers + 1) / 2 + 1;
    let mut done = 0;
    let mut try_layers = |chosen: &[usize]| -> Result<(Vec<u8>, ExportReport, f64), ExportError> {
        let mut o = opts.clone();
        o.weights = WeightFormat::I8;
        o.layer_weights = chosen.iter().map(|&l| (l, WeightFormat::I16)).collect();
        let (blob, report) = export(net, residual, &o)?;
        let rms = output_rms(net, &blob, &eval)?;
        done += 1;
        progress(done, total);
        Ok((blob, report, rms))
    };
    let (mut blob, mut report, rms_int8) = try_layers(&[])?;
    let (mut rms, mut chosen, mut trials) = (rms_int8, Vec::<usize>::new(), Vec::<Trial>::new());
    // What each layer adds at least: its floor before any trial (a layer
    // whose int16 weights alone outgrow the budget is not exported to find
    // out; on the real PFNN a trial is a full export of half a minute or
    // more), then what its first-round trial measured (a layer's extra
    // bytes do not depend on the others).
    let mut extra_of: std::collections::BTreeMap<usize, usize> = keys
        .iter()
        .map(|&l| (l, min_extra_bytes(&report, l)))
        .collect();
    let mut unaffordable = Vec::new();
    for round in 0..layers {
        let spent = spent_bytes(&trials);
        let mut best: Option<(f64, usize, Vec<u8>, ExportReport, f64)> = None;
        for &l in keys.iter().filter(|l| !chosen.contains(l)) {
            let at_least = extra_of.get(&l).copied().unwrap_or(0);
            if spent + at_least > budget {
                if round == 0 {
                    unaffordable.push(Unaffordable {
                        layer: l,
                        min_extra_bytes: at_least,
                        left_bytes: budget.saturating_sub(spent),
                    });
                }
                continue;
            }
            let mut with = chosen.clone();
            with.push(l);
            let (b, r, e) = try_layers(&with)?;
            let extra = b.len().saturating_sub(blob.len());
            extra_of.insert(l, extra);
            trials.push(Trial {
                round,
                layer: l,
                extra_bytes: extra,
                rms: e,
                chosen: false,
            });
            if spent + extra > budget || e >= rms {
                continue;
            }
            let gain = (rms - e) / extra.max(1) as f64;
            if best.as_ref().is_none_or(|b| gain > b.0) {
                best = Some((gain, l, b, r, e));
            }
        }
        let Some((_, l, b, r, e)) = best else { break };
        if let Some(t) = trials.iter_mut().rev().find(|t| t.layer == l) {
            t.chosen = true;
        }
        chosen.push(l);
        (blob, report, rms) = (b, r, e);
    }
    report.int16_budget = Some(BudgetReport {
        budget_bytes: budget,
        spent_bytes: spent_bytes(&trials),
        int16_layers: chosen,
        rms_int8,
        rms,
        eval_rows: eval.inputs.len(),
        trials,
        unaffordable,
    });
    Ok((blob, report))
}

/// What `QuantOptions::layer_weights` is keyed by: layer indices of a
/// chain, the indices of a graph's layer nodes.
fn weight_keys(net: &Net) -> Vec<usize> {
    match &net.wiring {
        Wiring::Chain => (0..net.layers.len()).collect(),
        Wiring::Graph(g) => g
            .nodes
            .iter()
            .enumerate()
            .filter(|(_, n)| matches!(n.op, GraphOp::Layer { .. }))
            .map(|(i, _)| i)
            .collect(),
    }
}

fn spent_bytes(trials: &[Trial]) -> usize {
    trials
        .iter()
        .filter(|t| t.chosen)
        .map(|t| t.extra_bytes)
        .sum()
}

/// Normal samples around the input mean (as the calibration draws them,
/// from another seed), then the recorded rows.
fn eval_inputs(net: &Net, opts: &QuantOptions) -> Samples {
    let mut s = normal_inputs(
        &net.xmean.to_vec(),
        &net.xstd.to_vec(),
        EVAL_SAMPLES,
        opts.calibration_scale,
        opts.seed ^ EVAL_SEED,
    );
    if let Some(r) = &opts.calibration_data {
        s.extend(&r.samples);
    }
    s
}

/// RMS over `eval` and every output of `(fixed - float) / y_std`.
fn output_rms(net: &Net, blob: &[u8], eval: &Samples) -> Result<f64, ExportError> {
    let model = Model::from_bytes(blob).map_err(ExportError::SelfCheck)?;
    let mut rt: Box<Runtime<'_, CAPACITY>> =
        Box::new(Runtime::new(model).map_err(ExportError::SelfCheck)?);
    let (mut sum, mut count) = (0.0f64, 0usize);
    let mut y = vec![0.0f32; net.output_dim()];
    for (x, &p) in eval.inputs.iter().zip(&eval.phases) {
        let xf: Vec<f32> = x.iter().map(|&v| v as f32).collect();
        let phase = Phase::from_radians(p as f32).map_err(ExportError::SelfCheck)?;
        rt.run(phase, &xf, &mut y).map_err(ExportError::SelfCheck)?;
        for ((&q, f), sd) in y.iter().zip(net.forward(x, p)).zip(&net.ystd) {
            let d = (f64::from(q) - f) / sd;
            sum += d * d;
            count += 1;
        }
    }
    Ok((sum / count.max(1) as f64).sqrt())
}
