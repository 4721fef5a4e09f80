//! CP-decomposed gated layers on the exporter side: decomposition of dense
//! expert weights by CP-ALS ([`als`]), the float reference of networks
//! with CP (and diagonal) layers ([`float`]), their quantisation
//! ([`quantise`]) and blob layout ([`encode`]), import of trained CP
//! factors from `.npz` / `.safetensors` ([`import`]), the per-rank report on
//! a real network ([`report`]) and distillation ([`distill`]).
//!
//! See `docs/cp-and-styles.md` for the formats and the measurements.

pub mod als;
pub mod cli;
pub mod distill;
pub mod encode;
pub mod float;
pub mod import;
pub mod quantise;
pub mod report;

use ndarray::Array1;
use phasegate::blob::{Activation, ModelKind, WeightFormat};
use phasegate::Model;
use serde::Serialize;

use crate::calibrate::{normal_inputs, Samples};
use crate::cp::encode::{encode_net, QKind, QModel};
use crate::cp::float::{Adapter, FloatNet};
use crate::cp::quantise::{quantise_layer, LayerSpec, QuantLayerReport};
use crate::export::ExportError;
use crate::quantise::{gating_for, output_stage_records, QuantError, QuantOptions};

/// Largest |value| per row of every layer's pre-activation and per
/// component of every CP layer's middle vector, over calibration samples.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NetRanges {
    /// Per layer, per row.
    pub rows: Vec<Vec<f64>>,
    /// Per layer, per component (CP layers).
    pub mids: Vec<Option<Vec<f64>>>,
    /// Mean square of each layer's input columns.
    pub input_ms: Vec<Vec<f64>>,
    /// Mean square of each CP layer's middle components.
    pub mid_ms: Vec<Option<Vec<f64>>>,
}

fn ms_into(acc: &mut Vec<f64>, v: &Array1<f64>, n: f64) {
    if acc.len() < v.len() {
        acc.resize(v.len(), 0.0);
    }
    for (m, x) in acc.iter_mut().zip(v) {
        *m += x * x / n;
    }
}

fn max_into(acc: &mut Vec<f64>, v: &Array1<f64>) {
    if acc.len() < v.len() {
        acc.resize(v.len(), 0.0);
    }
    for (m, x) in acc.iter_mut().zip(v) {
        *m = m.max(x.abs());
    }
}

/// Runs `net` (with `adapters`) on every sample and records the ranges.
pub fn calibrate_net(net: &FloatNet, samples: &Samples, adapters: &[(&Adapter, f64)]) -> NetRanges {
    let n = net.layers.len();
    let mut r = NetRanges {
        rows: vec![Vec::new(); n],
        mids: vec![None; n],
        input_ms: vec![Vec::new(); n],
        mid_ms: vec![None; n],
    };
    let count = samples.inputs.len().max(1) as f64;
    for (x, &p) in samples.inputs.iter().zip(&samples.phases) {
        let t = net.forward_trace(x, p, adapters);
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

/// Fewest calibration samples of [`quantise_net`].
pub const CALIBRATION_SAMPLES: usize = 2048;

/// Fraction bits so that `max * headroom` still fits an i16, at most 15.
pub fn frac_for(max: f64, headroom: f64) -> u8 {
    let bits = (32767.0 / (max * headroom).max(1e-9)).log2().floor();
    bits.clamp(0.0, 15.0) as u8
}

/// A quantised network and what the quantiser did.
#[derive(Clone, Debug)]
pub struct QuantisedNet {
    /// Ready to encode.
    pub model: QModel,
    /// Per layer.
    pub layers: Vec<QuantLayerReport>,
    /// Fraction bits of the normalised inputs.
    pub input_frac: u8,
    /// The calibration ranges.
    pub ranges: NetRanges,
}

/// Quantises a float network whose layers may be dense, CP or diagonal.
pub fn quantise_net(net: &FloatNet, opts: &QuantOptions) -> Result<QuantisedNet, QuantError> {
    if net
        .xstd
        .iter()
        .chain(&net.ystd)
        .any(|s| !s.is_finite() || *s <= 0.0)
    {
        return Err(QuantError::Invalid(
            "normalisation std must be finite and positive".into(),
        ));
    }
    let gating = gating_for(net.mode, net.experts())?;
    // More samples than the dense quantiser's default: CP networks'
    // intermediates have heavier tails, and the maxima set the formats.
    let samples = normal_inputs(
        &net.xmean.to_vec(),
        &net.xstd.to_vec(),
        opts.calibration_samples.max(CALIBRATION_SAMPLES),
        opts.calibration_scale,
        opts.seed,
    );
    let ranges = calibrate_net(net, &samples, &[]);
    let input_frac = frac_for(opts.input_range_sigma, 1.0);
    let mut in_scales = vec![f64::from(1u32 << input_frac); net.input_dim()];
    let input_stage = net
        .xmean
        .iter()
        .zip(&net.xstd)
        .zip(&in_scales)
        .map(|((&m, &sd), &u)| (m as f32, (u / sd) as f32))
        .collect();
    let last = net.layers.len().saturating_sub(1);
    let mut layers = Vec::new();
    let mut reports = Vec::new();
    let mut output_stage = Vec::new();
    for (li, layer) in net.layers.iter().enumerate() {
        let is_last = li == last;
        let maxes = &ranges.rows[li];
        let (targets, fracs): (Vec<f64>, Vec<u8>) = if is_last {
            maxes
                .iter()
                .map(|&m| (32767.0 / (opts.headroom * m.max(1e-6)), 0))
                .unzip()
        } else {
            maxes
                .iter()
                .map(|&m| {
                    let f = frac_for(m, opts.headroom);
                    (f64::from(1u32 << f), f)
                })
                .unzip()
        };
        let spec = LayerSpec {
            index: li,
            in_scales: &in_scales,
            targets: &targets,
            fracs: &fracs,
            activation: if is_last {
                Activation::Identity
            } else {
                Activation::Elu
            },
            gated: true,
            format: opts.weights,
            gating,
            mid_max: ranges.mids[li].as_deref(),
            in_power: Some(&ranges.input_ms[li]),
            mid_power: ranges.mid_ms[li].as_deref(),
            headroom: opts.headroom,
        };
        let (ql, rep) = quantise_layer(layer, &spec)?;
        layers.push(ql);
        reports.push(rep);
        if is_last {
            output_stage = output_stage_records(&targets, &net.ystd, &net.ymean);
        }
        in_scales = targets;
    }
    Ok(QuantisedNet {
        model: QModel {
            kind: QKind::Model(ModelKind::Pfnn),
            gating,
            input_stage,
            output_stage,
            layers,
        },
        layers: reports,
        input_frac,
        ranges,
    })
}

/// The report of [`export_net`].
#[derive(Clone, Debug, Serialize)]
pub struct NetExportReport {
    /// Format version of the blob written.
    pub format_version: u16,
    /// "constant", "linear" or "cubic".
    pub gating: String,
    /// Experts per layer.
    pub experts: usize,
    /// "int8" or "int16".
    pub weight_format: &'static str,
    /// Bytes of the blob.
    pub blob_bytes: usize,
    /// Activation RAM, bytes.
    pub ram_bytes: usize,
    /// Multiply-accumulates per frame.
    pub macs_per_frame: u32,
    /// Fraction bits of the normalised inputs.
    pub input_frac: u8,
    /// Per layer.
    pub layers: Vec<QuantLayerReport>,
    /// Every layer's worst-case bounds hold (and the loader re-checked them).
    pub overflow_proof: bool,
}

/// "int8" or "int16".
pub fn format_name(w: WeightFormat) -> &'static str {
    match w {
        WeightFormat::I8 => "int8",
        WeightFormat::I16 => "int16",
    }
}

/// Quantises, encodes and re-loads `net`.
pub fn export_net(
    net: &FloatNet,
    opts: &QuantOptions,
) -> Result<(Vec<u8>, NetExportReport), ExportError> {
    let q = quantise_net(net, opts)?;
    let blob = encode_net(&q.model)?;
    let model = Model::from_bytes(&blob).map_err(ExportError::SelfCheck)?;
    let report = NetExportReport {
        format_version: phasegate::blob::FORMAT_VERSION,
        gating: net.mode.name().to_string(),
        experts: net.experts(),
        weight_format: format_name(opts.weights),
        blob_bytes: blob.len(),
        ram_bytes: model.ram_bytes(),
        macs_per_frame: model.macs_per_frame(),
        input_frac: q.input_frac,
        overflow_proof: q.layers.iter().all(|l| l.proof),
        layers: q.layers,
    };
    Ok((blob, report))
}
