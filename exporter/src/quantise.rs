//! One quantiser for every network: float [`Net`] in, integer [`QModel`]
//! out, with a hook per op ([`crate::ops::NetLayer::quantise`]).
//!
//! * Weights: symmetric, per output row, one scale shared by all experts of a
//!   row so their accumulators can be blended before a single requantisation.
//! * Activations: int16. The input format comes from the declared input range
//!   in standard deviations of the normalisation statistics; every column of
//!   a node's input gets its own scale, chosen with the consuming op's
//!   weights (`column_scales`): hidden rows in powers of two (ELU needs to
//!   know where 1.0 is), output rows free scales undone by the output stage.
//! * Calibration: the float network on inputs drawn from the normalisation
//!   statistics ([`crate::calibrate`]); ops say how many samples they need.
//! * Overflow: every accumulator and every intermediate of the
//!   requantisation is bounded for *any* i16 activation vector, so the
//!   proof does not depend on the calibration at all.

use std::collections::BTreeMap;

use ndarray::Array2;
use phasegate::blob::{
    AccWidth, Activation, Gating, LayerDesc, LayerOp, ModelKind, Requant, Section, WeightFormat,
};
use serde::Serialize;

use crate::calibrate::{calibrate, Ranges};
use crate::lower::qmodel::{QKind, QLayer, QModel, Wiring};

pub mod graph;
pub mod moments;
use crate::net::{GatingMode, Net};

/// Knobs of the quantiser.
#[derive(Clone, Debug, Serialize)]
pub struct QuantOptions {
    /// Weight storage.
    #[serde(serialize_with = "ser_weight_format")]
    pub weights: WeightFormat,
    /// Inputs within `mean +- input_range_sigma * std` quantise without
    /// saturating (rounded up to a power of two).
    pub input_range_sigma: f64,
    /// Calibration samples (inputs `mean + std * N(0,1) * scale`).
    pub calibration_samples: usize,
    /// The `scale` of the calibration inputs.
    pub calibration_scale: f64,
    /// Factor between the largest calibrated value and the format's range.
    pub headroom: f64,
    /// Seed of the calibration sampler.
    pub seed: u64,
    /// Per-layer weight storage overriding `weights` (layer index to
    /// format): mixed precision, and per-layer error attribution.
    #[serde(
        serialize_with = "ser_layer_weights",
        skip_serializing_if = "BTreeMap::is_empty"
    )]
    pub layer_weights: BTreeMap<usize, WeightFormat>,
    /// Calibration samples for error-aware rounding of int8 dense weights
    /// (their inputs' second moments, see [`moments`]); 0 rounds every
    /// weight to nearest. 0 here, where tests and fixtures export many
    /// times; the command lines choose per network
    /// ([`crate::cli_args::compensation_samples`]: chains error-aware).
    pub compensation_samples: usize,
    /// Recorded inputs (`--calibration`, for example the float controller's
    /// rollouts from `host-sim rollout-dataset`): added to the normal
    /// samples of the range calibration and of the error-aware rounding,
    /// so that formats and rounding also fit the inputs a controller feeds.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub calibration_data: Option<Recorded>,
    /// The share of error-aware rounding's objective that the recorded
    /// rows carry, whatever their count (the normal samples carry the
    /// rest; in `(0, 1)`, [`DEFAULT_CALIBRATION_WEIGHT`]).
    pub calibration_weight: f64,
    /// Graph nodes whose row formats (fraction bits, one per row) are
    /// given instead of calibrated: a rig quantised against a motion
    /// blob's interface formats ([`crate::rig`]).
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub row_formats: BTreeMap<usize, Vec<u8>>,
}

/// Calibration samples of error-aware rounding when the command line asks
/// for it without a count ([`crate::cli_args::compensation_samples`]): on
/// the real PFNN, 8,192 gave a pooled output RMS of 0.0914 and 16,384
/// 0.0891 (docs/fixed-point.md).
pub const DEFAULT_COMPENSATION_SAMPLES: usize = 16_384;

/// The share of error-aware rounding's objective that recorded rollouts
/// carry by default (`--calibration-weight`): chosen on the calibration
/// scripts' own closed-loop rollouts, not on the scripts `host-sim
/// fidelity` scores (docs/fixed-point.md, "Rounding for the closed loop").
pub const DEFAULT_CALIBRATION_WEIGHT: f64 = 0.7;

pub use crate::io::samples::Recorded;

impl QuantOptions {
    /// Weight storage of layer `l`.
    pub fn weights_of(&self, l: usize) -> WeightFormat {
        self.layer_weights.get(&l).copied().unwrap_or(self.weights)
    }
}

fn ser_layer_weights<S: serde::Serializer>(
    w: &BTreeMap<usize, WeightFormat>,
    s: S,
) -> Result<S::Ok, S::Error> {
    s.collect_map(
        w.iter()
            .map(|(l, f)| (l.to_string(), crate::lower::qmodel::format_name(*f))),
    )
}

fn ser_weight_format<S: serde::Serializer>(w: &WeightFormat, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(crate::lower::qmodel::format_name(*w))
}

impl Default for QuantOptions {
    fn default() -> Self {
        QuantOptions {
            weights: WeightFormat::I8,
            input_range_sigma: 8.0,
            calibration_samples: 512,
            calibration_scale: 1.0,
            headroom: 1.5,
            seed: 0x5EED_CA1B,
            layer_weights: BTreeMap::new(),
            compensation_samples: 0,
            calibration_data: None,
            calibration_weight: DEFAULT_CALIBRATION_WEIGHT,
            row_formats: BTreeMap::new(),
        }
    }
}

/// What the quantiser did to one node and what it proved about it.
#[derive(Clone, Debug, Serialize)]
pub struct QuantLayerReport {
    /// Node index.
    pub index: usize,
    /// "dense", "cp" or "diagonal".
    pub form: &'static str,
    /// Input width.
    pub in_dim: usize,
    /// Output width.
    pub out_dim: usize,
    /// Experts stored.
    pub experts: usize,
    /// CP rank.
    pub rank: Option<usize>,
    /// "int8" or "int16".
    pub weights: &'static str,
    /// Accumulator width chosen ("i32" when provable, else "i64").
    pub accumulator: &'static str,
    /// Smallest and largest Q format (fraction bits) of the rows (hidden
    /// layers; the output layer has a free scale per row).
    pub out_frac_range: Option<(u8, u8)>,
    /// Largest |pre-activation| seen in calibration.
    pub calibrated_max: f64,
    /// Bytes of the node's sections in the blob.
    pub bytes: usize,
    /// Weight signal-to-quantisation-noise ratio, dB (all weight arrays).
    pub weight_sqnr_db: f64,
    /// log2 of the largest per-expert dot product possible for any i16
    /// input (dense nodes).
    pub max_dot_bits: Option<f64>,
    /// log2 of the largest blended accumulator possible for any i16 input
    /// (dense nodes).
    pub max_blend_bits: Option<f64>,
    /// Whether no accumulator or intermediate can overflow or saturate
    /// before the final i16 saturation, for any i16 input (re-checked by
    /// the loader where the format allows).
    pub proof: bool,
}

/// Result of quantising a network.
pub struct Quantised {
    /// Ready to encode.
    pub model: QModel,
    /// Per node.
    pub layers: Vec<QuantLayerReport>,
    /// Ranges measured in calibration.
    pub ranges: Ranges,
    /// Input format (fraction bits of normalised inputs).
    pub input_frac: u8,
    /// Graph nets: the net's layers as the blob computes them (dense
    /// weights and biases scaled back from their integers, other ops as
    /// given); empty for chains.
    pub dequantised: Vec<crate::net::NetLayer>,
    /// Graph nets: per node, the integer units per real unit of each input
    /// column (its producers' row formats); empty for chains and for
    /// softmax nodes.
    pub in_scales: Vec<Vec<f64>>,
}

/// Why quantisation failed.
#[derive(Debug, thiserror::Error)]
pub enum QuantError {
    /// A requantisation multiplier cannot be represented.
    #[error("layer {layer} row {row}: output scale out of the representable range")]
    Scale {
        /// Layer.
        layer: usize,
        /// Row.
        row: usize,
    },
    /// No accumulator width can hold a row.
    #[error("layer {layer} row {row}: no accumulator can be proven not to overflow")]
    Overflow {
        /// Layer.
        layer: usize,
        /// Row.
        row: usize,
    },
    /// Non-finite or degenerate statistics.
    #[error("{0}")]
    Invalid(String),
}

const ACT_MAX: f64 = 32767.0;
const Q16: f64 = 65536.0;
pub(crate) const I32_MAX: u128 = i32::MAX as u128;

/// Fraction bits so that `max * headroom` still fits an i16, at most `cap`.
pub fn frac_for(max: f64, headroom: f64, cap: u8) -> u8 {
    let bits = (ACT_MAX / (max * headroom).max(1e-9)).log2().floor();
    bits.clamp(0.0, f64::from(cap)) as u8
}

/// log2 of a positive bound, 0 for none.
pub(crate) fn bits(v: f64) -> f64 {
    if v <= 0.0 {
        0.0
    } else {
        v.log2()
    }
}

/// Largest integer weight of a format.
pub(crate) fn qmax(format: WeightFormat) -> f64 {
    match format {
        WeightFormat::I8 | WeightFormat::I8Interleaved => 127.0,
        WeightFormat::I16 => 32767.0,
    }
}

fn sqnr(sig: f64, noise: f64) -> f64 {
    10.0 * (sig / noise.max(f64::MIN_POSITIVE)).log10()
}

/// The requantisation record of row `i` of a dense node whose blended
/// accumulator is at most `blend` for any i16 input: a pre-shift that
/// brings the bound within 31 bits, then the multiplier.
pub(crate) fn requant_for_blend(
    spec: &LayerSpec<'_>,
    i: usize,
    row_scale: f64,
    blend: i128,
) -> Result<Requant, QuantError> {
    if blend >= i128::from(i64::MAX) {
        return Err(QuantError::Overflow {
            layer: spec.index,
            row: i,
        });
    }
    let pre = (128 - blend.leading_zeros()).saturating_sub(31) as u8;
    record(spec, i, row_scale, pre)
}

/// The record of row `i`: after a pre-shift of `pre`, the multiplier that
/// takes accumulator units (`row_scale` per real unit, gate in Q16) to the
/// row's target scale.
fn record(spec: &LayerSpec<'_>, i: usize, row_scale: f64, pre: u8) -> Result<Requant, QuantError> {
    let m_real = spec.targets[i] / (Q16 * row_scale) * f64::from(pre).exp2();
    let (multiplier, post_shift) = fixed_multiplier(m_real).ok_or(QuantError::Scale {
        layer: spec.index,
        row: i,
    })?;
    Ok(Requant {
        multiplier,
        pre_shift: pre,
        post_shift,
        frac: spec.fracs[i],
    })
}

/// What a layer's quantisation depends on besides its weights.
#[derive(Clone, Debug)]
pub struct LayerSpec<'s> {
    /// Position, for errors.
    pub index: usize,
    /// Integer units per real unit of each input column.
    pub in_scales: &'s [f64],
    /// Integer units per real unit wanted for each output row.
    pub targets: &'s [f64],
    /// Q format recorded per output row (ELU reads it; adapters must
    /// repeat their base layer's).
    pub fracs: &'s [u8],
    /// Activation after requantisation.
    pub activation: Activation,
    /// Whether the layer uses the phase gate.
    pub gated: bool,
    /// Weight storage.
    pub format: WeightFormat,
    /// Gating (for the worst-case gate magnitude).
    pub gating: Gating,
    /// Largest |u_r| seen in calibration (CP layers).
    pub mid_max: Option<&'s [f64]>,
    /// Mean square of each input column in calibration (real units): with
    /// it, each row's scale trades clipping a few large weights against
    /// rounding all the others, weighted by how much each column carries.
    pub in_power: Option<&'s [f64]>,
    /// Mean square of each middle component in calibration (CP layers).
    pub mid_power: Option<&'s [f64]>,
    /// Factor between calibrated maxima and the i16 range.
    pub headroom: f64,
    /// Per expert, the second and first moments of the input as that
    /// expert sees it (real units): with them, int8 dense weights are
    /// rounded for the least output error rather than to nearest.
    pub in_moments: Option<&'s moments::LayerMoments>,
}

/// `(m, post)` with `m * 2^-post == m_real`, `m` in `[2^30, 2^31)`, post in `[0, 62]`.
pub fn fixed_multiplier(m_real: f64) -> Option<(i32, u8)> {
    if !(m_real.is_finite() && m_real > 0.0) {
        return None;
    }
    let mut post = (30.0 - m_real.log2()).floor() as i32 + 1;
    let mut m = (m_real * f64::from(post).exp2()).round();
    if m >= 2147483648.0 {
        post -= 1;
        m = (m_real * f64::from(post).exp2()).round();
    }
    if post > 62 {
        m = (m_real * 62f64.exp2()).round();
        post = 62;
    }
    if !(0..=62).contains(&post) || m >= 2147483648.0 {
        return None;
    }
    Some((m as i32, post as u8))
}

/// Smallest shift `s` with `(bound >> s) + 1 <= i32::MAX`.
pub fn shift_to_i32(bound: u128) -> u8 {
    let mut s = 0u8;
    while (bound >> s) + 1 > I32_MAX {
        s += 1;
    }
    s
}

/// Quantised rows of one matrix (one scale per row).
pub(crate) struct Rows {
    pub q: Vec<i32>,
    pub scales: Vec<f64>,
    pub l1: Vec<u64>,
    pub sig: f64,
    pub noise: f64,
}

/// Quantises `rows x cols` real values `f(i, j)` with one scale per row.
///
/// Without `power` the scale maps the row's largest value to `q`. With the
/// mean square of each column's input (integer units), the scale is the
/// one between that and 1/0.6 of it that minimises the row's expected
/// output error `sum_j (w - q(w))^2 E[x_j^2]` (clipping a few outliers buys
/// a finer step for every other weight; with int8 this matters).
pub(crate) fn quantise_rows(
    rows: usize,
    cols: usize,
    q: f64,
    f: impl Fn(usize, usize) -> f64,
    power: Option<&[f64]>,
) -> Rows {
    let mut out = Rows {
        q: vec![0; rows * cols],
        scales: vec![1.0; rows],
        l1: vec![0; rows],
        sig: 0.0,
        noise: 0.0,
    };
    for i in 0..rows {
        let row: Vec<f64> = (0..cols).map(|j| f(i, j)).collect();
        let maxabs = row.iter().map(|v| v.abs()).fold(0.0, f64::max);
        let mut s = if maxabs > 0.0 { q / maxabs } else { 1.0 };
        if let (Some(p), true) = (power, maxabs > 0.0) {
            let err = |sc: f64| -> f64 {
                row.iter()
                    .zip(p)
                    .map(|(&v, &pw)| (v - (v * sc).round().clamp(-q, q) / sc).powi(2) * pw)
                    .sum()
            };
            let max_scale = s;
            let mut best = err(s);
            for step in 1..=40 {
                let cand = max_scale / (1.0 - 0.01 * f64::from(step));
                let e = err(cand);
                if e < best {
                    best = e;
                    s = cand;
                }
            }
        }
        out.scales[i] = s;
        for (j, &v) in row.iter().enumerate() {
            let wq = (v * s).round().clamp(-q, q);
            out.q[i * cols + j] = wq as i32;
            out.l1[i] += wq.abs() as u64;
            out.sig += v * v;
            out.noise += (v - wq / s).powi(2);
        }
    }
    out
}

/// The requantisation record of row `i` of a node whose accumulator
/// (blended over the gate) is at most `bound` for any i16 input: the
/// smallest pre-shift that leaves `bound` within an i32 with one unit of
/// slack (the runtime's CP and diagonal checks use the same rule).
pub(crate) fn requant_for(
    spec: &LayerSpec<'_>,
    i: usize,
    row_scale: f64,
    bound: u128,
) -> Result<Requant, QuantError> {
    if bound >= 1 << 63 {
        return Err(QuantError::Overflow {
            layer: spec.index,
            row: i,
        });
    }
    record(spec, i, row_scale, shift_to_i32(bound))
}

pub(crate) fn layer_desc(
    spec: &LayerSpec<'_>,
    op: LayerOp,
    in_dim: usize,
    out_dim: usize,
    experts: usize,
    acc: AccWidth,
) -> LayerDesc {
    LayerDesc {
        op,
        in_dim: in_dim as u16,
        out_dim: out_dim as u16,
        experts: experts as u16,
        weights: spec.format,
        acc,
        activation: spec.activation,
        weight_section: Section::default(),
        bias_section: Section::default(),
        requant_section: Section::default(),
    }
}

fn acc_name(acc: AccWidth) -> &'static str {
    match acc {
        AccWidth::I32 => "i32",
        AccWidth::I64 => "i64",
    }
}

pub(crate) fn layer_bytes(l: &QLayer) -> usize {
    let d = &l.desc;
    let wb = d.weights.bytes();
    let mut n = l.weights.len() * wb + l.bias.len() * d.acc.bytes() + l.requant.len() * 8;
    if let Some(cp) = &l.cp {
        n += cp.a.len() * wb + cp.cores.len() * 2 + cp.mid.len() * 8;
    }
    n
}

pub(crate) fn layer_report(
    spec: &LayerSpec<'_>,
    layer: &QLayer,
    form: &'static str,
    rank: Option<usize>,
    sig: f64,
    noise: f64,
) -> QuantLayerReport {
    let fracs = spec
        .fracs
        .iter()
        .fold((u8::MAX, 0u8), |(lo, hi), &f| (lo.min(f), hi.max(f)));
    QuantLayerReport {
        index: spec.index,
        form,
        in_dim: usize::from(layer.desc.in_dim),
        out_dim: usize::from(layer.desc.out_dim),
        experts: usize::from(layer.desc.experts),
        rank,
        weights: crate::lower::qmodel::format_name(spec.format),
        accumulator: acc_name(layer.desc.acc),
        out_frac_range: (spec.activation == Activation::Elu && !spec.fracs.is_empty())
            .then_some(fracs),
        calibrated_max: 0.0,
        bytes: layer_bytes(layer),
        weight_sqnr_db: sqnr(sig, noise),
        max_dot_bits: None,
        max_blend_bits: None,
        proof: true,
    }
}

/// The blob gating for a float gating mode with `experts` experts.
pub fn gating_for(mode: GatingMode, experts: usize) -> Result<Gating, QuantError> {
    let n = u16::try_from(experts).map_err(|_| QuantError::Invalid("too many experts".into()))?;
    Ok(match mode {
        GatingMode::Constant => Gating::Constant { tables: n },
        GatingMode::Linear => Gating::Linear { tables: n },
        GatingMode::Cubic => Gating::CatmullRom { points: n },
    })
}

/// The output stage: `(scale, offset)` per output, turning the last layer's
/// integers at scale `targets` into model units. Refuses a stage the
/// runtime would refuse (`|scale| <= 2^24`, `|offset| <= 2^39`: outputs
/// within 2^40 model units, `docs/blob-format.md`), naming the output.
pub(crate) fn output_stage_records(
    targets: &[f64],
    ystd: &ndarray::Array1<f64>,
    ymean: &ndarray::Array1<f64>,
) -> Result<Vec<(f32, f32)>, QuantError> {
    use phasegate::blob::{MAX_OUTPUT_OFFSET, MAX_OUTPUT_SCALE};
    targets
        .iter()
        .zip(ystd.iter().zip(ymean))
        .enumerate()
        .map(|(i, (&t, (&sd, &m)))| {
            let (scale, offset) = ((sd / t) as f32, m as f32);
            if scale.abs() <= MAX_OUTPUT_SCALE && offset.abs() <= MAX_OUTPUT_OFFSET {
                Ok((scale, offset))
            } else {
                Err(QuantError::Invalid(format!(
                    "output {i}: Ystd {sd:e} / Ymean {m:e} give an output stage (scale {scale:e}, \
                     offset {offset:e}) beyond the runtime's bounds (|scale| <= 2^24, \
                     |offset| <= 2^39: every output within 2^40 model units)"
                )))
            }
        })
        .collect()
}

/// Scales of the input columns of `consumer` (the matrices its op applies
/// to its input, see [`crate::ops::NetLayer::input_rows`]), at most `caps[j]` each.
///
/// The consumer's rows are quantised with one scale per row, so a column
/// whose effective weight `w / u_j` is large coarsens the whole row. With
/// `u_j = min(cap_j, t * colmax_j)` the expected squared error of row i,
/// `(max_j |w_ij| / u_j / q)^2 / 12 * sum_j E[a_j^2] u_j^2` (weight
/// rounding) `+ sum_j w_ij^2 / (12 u_j^2)` (activation rounding), weighted by
/// `row_weight_i^2` (the output std for the last layer), is evaluated on a
/// grid of `t` and the best kept. Large `t` means every column at its cap,
/// which is what int16 weights choose; int8 weights trade activation
/// precision on lightly weighted columns for finer weights everywhere.
/// `pow2`: scales are powers of two (hidden layers, for ELU).
fn column_scales(
    consumer: &[Array2<f64>],
    caps: &[f64],
    mean_sq: &[f64],
    row_weight: Option<&[f64]>,
    q: f64,
    pow2: bool,
) -> Vec<f64> {
    let (rows, cols) = consumer.first().map_or((0, 0), Array2::dim);
    let mut colmax = vec![0.0f64; cols];
    let mut w2 = vec![vec![0.0f64; cols]; rows];
    let mut absmax = vec![vec![0.0f64; cols]; rows];
    for w in consumer {
        for ((i, j), &v) in w.indexed_iter() {
            colmax[j] = colmax[j].max(v.abs());
            absmax[i][j] = f64::max(absmax[i][j], v.abs());
            w2[i][j] += v * v / consumer.len() as f64;
        }
    }
    let floor = colmax.iter().copied().fold(0.0, f64::max) * 1e-3;
    let candidate = |t: f64| -> Vec<f64> {
        caps.iter()
            .zip(&colmax)
            .map(|(&cap, &cm)| {
                let u = cap.min(t * cm.max(floor)).max(1.0);
                if pow2 {
                    u.log2().floor().exp2()
                } else {
                    u
                }
            })
            .collect()
    };
    let cost = |u: &[f64]| -> f64 {
        let act_power: f64 = mean_sq.iter().zip(u).map(|(m, u)| m * u * u).sum();
        (0..rows)
            .map(|i| {
                let wmax = absmax[i]
                    .iter()
                    .zip(u)
                    .map(|(a, u)| a / u)
                    .fold(0.0, f64::max);
                let act_noise: f64 = w2[i].iter().zip(u).map(|(w, u)| w / (u * u)).sum();
                let rw = row_weight.map_or(1.0, |r| r[i] * r[i]);
                rw * ((wmax / q).powi(2) * act_power + act_noise) / 12.0
            })
            .sum()
    };
    let mut best = caps
        .iter()
        .map(|&c| {
            if pow2 {
                c.max(1.0).log2().floor().exp2()
            } else {
                c
            }
        })
        .collect::<Vec<_>>();
    let mut best_cost = cost(&best);
    for step in -40..=80 {
        let t = f64::from(step).exp2();
        let u = candidate(t);
        let c = cost(&u);
        if c < best_cost {
            best_cost = c;
            best = u;
        }
    }
    best
}

/// Whether layer `l` of a chain gets error-aware rounding under `opts`.
fn compensated(net: &Net, opts: &QuantOptions, l: usize) -> bool {
    opts.compensation_samples > 0
        && opts.weights_of(l) == WeightFormat::I8
        && matches!(
            net.layers.get(l),
            Some(crate::net::NetLayer::Dense(_) | crate::net::NetLayer::Cp(_))
        )
}

/// The inputs error-aware rounding takes its moments from:
/// `compensation_samples` normal samples, then the recorded rows, which
/// together carry `calibration_weight` of the moments' weight.
fn compensation_inputs(net: &Net, opts: &QuantOptions) -> moments::WeightedSamples {
    let mut weighted = moments::WeightedSamples::uniform(crate::io::samples::normal_inputs(
        &net.xmean.to_vec(),
        &net.xstd.to_vec(),
        opts.compensation_samples,
        opts.calibration_scale,
        opts.seed ^ COMPENSATION_SEED,
    ));
    if let Some(r) = &opts.calibration_data {
        weighted.push(
            &r.samples,
            recorded_row_weight(
                opts.calibration_weight,
                opts.compensation_samples,
                r.samples.inputs.len(),
            ),
        );
    }
    weighted
}

/// The weight of one of `recorded` rows beside `normal` normal samples of
/// weight 1, for the recorded rows to carry `share` of the total.
fn recorded_row_weight(share: f64, normal: usize, recorded: usize) -> f64 {
    if normal == 0 || recorded == 0 {
        return 1.0;
    }
    share / (1.0 - share) * normal as f64 / recorded as f64
}

/// Keeps the compensation inputs apart from the calibration inputs.
const COMPENSATION_SEED: u64 = 0xC0_4E57;

/// Quantises `net` into a blob model: one pipeline for every op.
pub fn quantise_net(net: &Net, opts: &QuantOptions) -> Result<Quantised, QuantError> {
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
    if net.layers.is_empty() {
        return Err(QuantError::Invalid("the network has no layers".into()));
    }
    if let crate::net::Wiring::Graph(g) = &net.wiring {
        return graph::quantise_graph(net, g, opts);
    }
    let gating = gating_for(net.mode, net.experts())?;
    let samples = crate::calibrate::calibration_inputs(net, opts);
    let ranges = calibrate(net, &samples);
    let input_frac = frac_for(opts.input_range_sigma, 1.0, 15);
    // Error-aware rounding runs the samples through the layers quantised
    // so far, so that each layer can make up for the ones before it.
    let mut sequential = (0..net.layers.len())
        .any(|l| compensated(net, opts, l))
        .then(|| moments::Sequential::new(net, &compensation_inputs(net, opts)));

    // Each node's input columns get their own scale (integer units per
    // real unit): as fine as the calibrated range allows (the cap), lowered
    // where that balances the consuming op's weight rounding noise against
    // activation rounding noise (see `column_scales`).
    let last = net.layers.len() - 1;
    let input_caps = vec![f64::from(1u32 << input_frac); net.input_dim()];
    let mut in_scales = column_scales(
        &net.layers[0].input_rows(),
        &input_caps,
        &ranges.input_ms[0],
        None,
        qmax(opts.weights_of(0)),
        false,
    );
    let input_stage = net
        .xmean
        .iter()
        .zip(&net.xstd)
        .zip(&in_scales)
        .map(|((&m, &sd), &u)| (m as f32, (u / sd) as f32))
        .collect();

    let mut layers = Vec::new();
    let mut reports = Vec::new();
    let mut output_stage = Vec::new();
    for (li, layer) in net.layers.iter().enumerate() {
        let is_last = li == last;
        // Hidden rows stop at Q15: ELU needs -1.0 to be representable.
        let finest = if is_last {
            f64::INFINITY
        } else {
            f64::from(1u32 << 15)
        };
        let caps: Vec<f64> = ranges.rows[li]
            .iter()
            .map(|&m| (ACT_MAX / (opts.headroom * m.max(1e-6))).min(finest))
            .collect();
        // Hidden rows get a power-of-two format each (ELU needs to know
        // where 1.0 is); output rows a free scale, undone by the output stage.
        let targets = if is_last {
            caps
        } else {
            let next = &net.layers[li + 1];
            // The output std weighs the last layer's rows where they are outputs.
            let ystd = (li + 1 == last && next.rows_are_outputs()).then(|| net.ystd.to_vec());
            column_scales(
                &next.input_rows(),
                &caps,
                &ranges.input_ms[li + 1],
                ystd.as_deref(),
                qmax(opts.weights_of(li + 1)),
                true,
            )
        };
        let fracs: Vec<u8> = targets
            .iter()
            .map(|&t| {
                if is_last {
                    0
                } else {
                    t.log2().round().clamp(0.0, 15.0) as u8
                }
            })
            .collect();
        let layer_moments = sequential
            .as_ref()
            .filter(|_| compensated(net, opts, li))
            .filter(|_| matches!(layer, crate::net::NetLayer::Dense(_)))
            .map(|s| s.moments(layer.experts()));
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
            format: opts.weights_of(li),
            gating,
            mid_max: ranges.mids[li].as_deref(),
            in_power: Some(&ranges.input_ms[li]),
            mid_power: ranges.mid_ms[li].as_deref(),
            headroom: opts.headroom,
            in_moments: layer_moments.as_ref(),
        };
        let (ql, rep, dequantised) = match (&sequential, layer) {
            (Some(_), crate::net::NetLayer::Dense(d)) => {
                let (ql, rep, deq) = crate::ops::dense::quantise_dequantised(d, &spec)?;
                (ql, rep, Some(crate::net::NetLayer::Dense(deq)))
            }
            (Some(seq), crate::net::NetLayer::Cp(c)) if compensated(net, opts, li) => {
                let (ql, rep, deq) = crate::ops::cp::quantise_sequential(c, &spec, seq)?;
                (ql, rep, Some(crate::net::NetLayer::Cp(deq)))
            }
            _ => {
                let (ql, rep) = layer.quantise(&spec)?;
                (ql, rep, None)
            }
        };
        // The samples go on through this layer only if a later one needs them.
        if let Some(seq) = sequential
            .as_mut()
            .filter(|_| (li + 1..net.layers.len()).any(|l| compensated(net, opts, l)))
        {
            seq.advance(net, layer, dequantised.as_ref().unwrap_or(layer));
        }
        reports.push(QuantLayerReport {
            calibrated_max: ranges.layer_max(li),
            ..rep
        });
        layers.push(ql);
        if is_last {
            output_stage = output_stage_records(&targets, &net.ystd, &net.ymean)?;
        }
        in_scales = targets;
    }
    Ok(Quantised {
        dequantised: Vec::new(),
        in_scales: Vec::new(),
        model: QModel {
            kind: QKind::Model(ModelKind::Pfnn),
            gating,
            input_stage,
            output_stage,
            layers,
            wiring: Wiring::Chain,
        },
        layers: reports,
        ranges,
        input_frac,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use phasegate::ops::cp::gate_l1_max;

    #[test]
    fn multiplier_is_accurate() {
        for &m in &[1e-12, 3.7e-9, 0.001, 0.4999, 0.5, 0.9999999, 1.0, 1234.5] {
            let (mul, post) = fixed_multiplier(m).unwrap();
            let back = f64::from(mul) * (-f64::from(post)).exp2();
            assert!(((back - m) / m).abs() < 1e-9 || m < 1e-10, "{m}: {back}");
            assert!(mul >= 1 << 30 || post == 62);
        }
        assert!(fixed_multiplier(f64::NAN).is_none());
        assert!(fixed_multiplier(1e12).is_none());
    }

    #[test]
    fn recorded_rows_carry_their_share() {
        for (share, normal, recorded) in [(0.6, 16_384, 14_400), (0.5, 100, 7), (0.1, 5, 500)] {
            let w = recorded_row_weight(share, normal, recorded);
            let mass = w * recorded as f64;
            assert!((mass / (mass + normal as f64) - share).abs() < 1e-12);
        }
        // Without normal samples the rows are all there is.
        assert_eq!(recorded_row_weight(0.6, 0, 10), 1.0);
    }

    #[test]
    fn gate_bounds() {
        assert_eq!(gate_l1_max(&Gating::Constant { tables: 50 }), 65536 + 8);
        let cr = gate_l1_max(&Gating::CatmullRom { points: 4 });
        assert!((81920..=81940).contains(&cr), "{cr}");
    }

    #[test]
    fn shift_brings_bounds_within_i32() {
        for b in [0u128, 1, I32_MAX - 1, I32_MAX, 1 << 40, (1 << 63) - 1] {
            let s = shift_to_i32(b);
            assert!((b >> s) < I32_MAX);
            assert!(s == 0 || (b >> (s - 1)) + 1 > I32_MAX);
        }
    }
}
