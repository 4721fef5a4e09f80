//! Float network -> integer blob model.
//!
//! * Weights: symmetric, per output row, one scale shared by all experts of a
//!   row so their accumulators can be blended before a single requantisation.
//! * Activations: int16. The input format comes from the declared input range
//!   in standard deviations of the normalisation statistics; each hidden
//!   layer's format from the largest pre-activation the float network reaches
//!   on inputs drawn from those statistics, times a headroom factor; the
//!   output layer gets a scale per row the same way.
//! * Overflow: every accumulator and every intermediate of the requantisation
//!   is bounded for *any* i16 activation vector (|x| <= 2^15), so the proof
//!   does not depend on the calibration at all; see [`LayerReport::proof`].

use ndarray::Array2;
use phasegate::blob::{
    AccWidth, Activation, Gating, LayerDesc, LayerOp, ModelKind, Requant, Section, WeightFormat,
};
use phasegate::{Gate, Phase};
use serde::Serialize;

use crate::blob_writer::{BlobLayer, BlobModel};
use crate::calibrate::{measure_ranges, normal_inputs, Ranges};
use crate::float_pfnn::{ExpertLayer, FloatPfnn, GatingMode};

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
}

fn ser_weight_format<S: serde::Serializer>(w: &WeightFormat, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(match w {
        WeightFormat::I8 => "int8",
        WeightFormat::I16 => "int16",
    })
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
        }
    }
}

/// What the quantiser did to one layer and what it proved about it.
#[derive(Clone, Debug, Serialize)]
pub struct LayerReport {
    /// Layer index.
    pub index: usize,
    /// `in x out`, experts.
    pub in_dim: usize,
    /// Output width.
    pub out_dim: usize,
    /// Experts stored.
    pub experts: usize,
    /// Accumulator width chosen ("i32" when provable, else "i64").
    pub accumulator: &'static str,
    /// Smallest and largest Q format (fraction bits) of the rows (hidden
    /// layers; the output layer has a free scale per row).
    pub out_frac_range: Option<(u8, u8)>,
    /// Largest |pre-activation| seen in calibration.
    pub calibrated_max: f64,
    /// Weight signal-to-quantisation-noise ratio, dB.
    pub weight_sqnr_db: f64,
    /// log2 of the largest per-expert dot product possible for any i16 input.
    pub max_dot_bits: f64,
    /// log2 of the largest blended accumulator possible for any i16 input.
    pub max_blend_bits: f64,
    /// Whether no accumulator or intermediate can overflow or saturate
    /// before the final i16 saturation, for any i16 input.
    pub proof: bool,
}

/// Result of quantising a network.
pub struct Quantised {
    /// Ready to encode.
    pub model: BlobModel,
    /// Per-layer figures.
    pub layers: Vec<LayerReport>,
    /// Ranges measured in calibration.
    pub ranges: Ranges,
    /// Input format (fraction bits of normalised inputs).
    pub input_frac: u8,
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

/// Fraction bits so that `max * headroom` still fits an i16, at most `cap`.
fn frac_for(max: f64, headroom: f64, cap: u8) -> u8 {
    let bits = (ACT_MAX / (max * headroom).max(1e-9)).log2().floor();
    bits.clamp(0.0, f64::from(cap)) as u8
}

/// Largest `sum_k |g_k|` (Q16) of `gating` over a fine phase grid, plus the
/// rounding slack of the gate computation.
pub fn gate_l1_bound(gating: &Gating) -> i64 {
    let worst = (0..=u16::MAX)
        .map(|i| {
            let g = Gate::new(gating, Phase::from_bits(u32::from(i) << 16));
            g.iter().map(|(_, w)| i64::from(w).abs()).sum::<i64>()
        })
        .max()
        .unwrap_or(1 << 16);
    worst + 8
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

fn bits(v: f64) -> f64 {
    if v <= 0.0 {
        0.0
    } else {
        v.log2()
    }
}

/// Quantises `net` (a PFNN-shaped float network) into a blob model.
pub fn quantise_pfnn(net: &FloatPfnn, opts: &QuantOptions) -> Result<Quantised, QuantError> {
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
    let experts = net.layers[0].experts();
    let gating = gating_for(net.mode, experts)?;
    let samples = normal_inputs(
        &net.xmean.to_vec(),
        &net.xstd.to_vec(),
        opts.calibration_samples,
        opts.calibration_scale,
        opts.seed,
    );
    let ranges = measure_ranges(net, &samples);
    let input_frac = frac_for(opts.input_range_sigma, 1.0, 15);
    let gsum = gate_l1_bound(&gating);
    let q = match opts.weights {
        WeightFormat::I8 => 127.0,
        WeightFormat::I16 => 32767.0,
    };

    // Each layer's input columns get their own scale (integer units per
    // real unit): as fine as the calibrated range allows (the cap), lowered
    // where that balances the consuming layer's weight rounding noise
    // against activation rounding noise (see `column_scales`).
    let last = net.layers.len() - 1;
    let input_caps = vec![f64::from(1u32 << input_frac); net.input_dim()];
    let mut in_scales = column_scales(
        &net.layers[0],
        &input_caps,
        &ranges.input_ms[0],
        None,
        q,
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
        let row_max = &ranges.rows[li];
        // Hidden rows stop at Q15: ELU needs -1.0 to be representable.
        let finest = if is_last {
            f64::INFINITY
        } else {
            f64::from(1u32 << 15)
        };
        let caps: Vec<f64> = row_max
            .iter()
            .map(|&m| (ACT_MAX / (opts.headroom * m.max(1e-6))).min(finest))
            .collect();
        // Hidden rows get a power-of-two format each (ELU needs to know
        // where 1.0 is); output rows a free scale, undone by the output stage.
        let targets = if is_last {
            caps.clone()
        } else {
            let ystd = (li + 1 == last).then(|| net.ystd.to_vec());
            column_scales(
                &net.layers[li + 1],
                &caps,
                &ranges.input_ms[li + 1],
                ystd.as_deref(),
                q,
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
        let in_power: Vec<f64> = ranges.input_ms[li]
            .iter()
            .zip(&in_scales)
            .map(|(m, u)| m * u * u)
            .collect();
        let spec = LayerSpec {
            index: li,
            in_scales: &in_scales,
            in_power: &in_power,
            targets: &targets,
            fracs: &fracs,
            elu: !is_last,
        };
        let (bl, rep) = quantise_layer(&spec, layer, q, opts.weights, gsum)?;
        reports.push(LayerReport {
            calibrated_max: ranges.layer[li],
            ..rep
        });
        layers.push(bl);
        if is_last {
            output_stage = output_stage_records(&targets, &net.ystd, &net.ymean);
        }
        in_scales = targets;
    }
    Ok(Quantised {
        model: BlobModel {
            kind: ModelKind::Pfnn,
            gating,
            input_stage,
            output_stage,
            layers,
        },
        layers: reports,
        ranges,
        input_frac,
    })
}

/// The output stage: `(scale, offset)` per output, turning the last layer's
/// integers at scale `targets` into model units.
pub(crate) fn output_stage_records(
    targets: &[f64],
    ystd: &ndarray::Array1<f64>,
    ymean: &ndarray::Array1<f64>,
) -> Vec<(f32, f32)> {
    targets
        .iter()
        .zip(ystd.iter().zip(ymean))
        .map(|(&t, (&sd, &m))| ((sd / t) as f32, m as f32))
        .collect()
}

/// Scales of the input columns of `consumer`, at most `caps[j]` each.
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
    consumer: &ExpertLayer,
    caps: &[f64],
    mean_sq: &[f64],
    row_weight: Option<&[f64]>,
    q: f64,
    pow2: bool,
) -> Vec<f64> {
    let (rows, cols) = consumer.w.first().map_or((0, 0), Array2::dim);
    let mut colmax = vec![0.0f64; cols];
    let mut w2 = vec![vec![0.0f64; cols]; rows];
    let mut absmax = vec![vec![0.0f64; cols]; rows];
    for w in &consumer.w {
        for ((i, j), &v) in w.indexed_iter() {
            colmax[j] = colmax[j].max(v.abs());
            absmax[i][j] = f64::max(absmax[i][j], v.abs());
            w2[i][j] += v * v / consumer.w.len() as f64;
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

/// What a layer's quantisation depends on besides its weights.
struct LayerSpec<'s> {
    index: usize,
    /// Integer units per real unit, per input column.
    in_scales: &'s [f64],
    /// Mean square of each input column in integer units (calibrated).
    in_power: &'s [f64],
    /// Integer units per real unit wanted, per output row.
    targets: &'s [f64],
    /// Q format per output row (hidden layers).
    fracs: &'s [u8],
    elu: bool,
}

/// The row scale, between `max_scale` (no weight clipped) and 1/0.6 of it,
/// that minimises the row's expected output error from weight rounding and
/// clipping, `sum_k sum_j (w - q(w))^2 E[a_j^2]`. Clipping a few outlier
/// weights buys a finer step for all the others; with int8 this matters.
fn best_row_scale(
    layer: &ExpertLayer,
    i: usize,
    max_scale: f64,
    q: f64,
    eff: &dyn Fn(f64, usize) -> f64,
    power: &[f64],
) -> f64 {
    let row_err = |scale: f64| -> f64 {
        layer
            .w
            .iter()
            .flat_map(|w| {
                w.row(i)
                    .iter()
                    .enumerate()
                    .map(|(j, &v)| (j, v))
                    .collect::<Vec<_>>()
            })
            .map(|(j, v)| {
                let v = eff(v, j);
                let d = v - (v * scale).round().clamp(-q, q) / scale;
                d * d * power[j]
            })
            .sum()
    };
    (0..=40)
        .map(|step| max_scale / (1.0 - 0.01 * f64::from(step)))
        .map(|s| (row_err(s), s))
        .fold((f64::INFINITY, max_scale), |best, c| {
            if c.0 < best.0 {
                c
            } else {
                best
            }
        })
        .1
}

struct RowQuant {
    scale: f64,
    l1: Vec<i64>,
}

fn quantise_layer(
    spec: &LayerSpec<'_>,
    layer: &ExpertLayer,
    q: f64,
    format: WeightFormat,
    gsum: i64,
) -> Result<(BlobLayer, LayerReport), QuantError> {
    let li = spec.index;
    let experts = layer.experts();
    let (out_dim, in_dim) = layer.w.first().map_or((0, 0), Array2::dim);
    // The integer input of column j is x_j * in_scales[j]: its weights carry 1 / in_scales[j].
    let eff = |w: f64, j: usize| w / spec.in_scales[j];
    let mut weights = vec![0i32; experts * out_dim * in_dim];
    let mut bias = vec![0i64; experts * out_dim];
    let mut rows = Vec::with_capacity(out_dim);
    let (mut sig, mut noise) = (0.0f64, 0.0f64);
    for i in 0..out_dim {
        let maxabs = layer
            .w
            .iter()
            .flat_map(|w| {
                w.row(i)
                    .iter()
                    .enumerate()
                    .map(|(j, &v)| eff(v, j).abs())
                    .collect::<Vec<_>>()
            })
            .fold(0.0, f64::max);
        let scale = if maxabs > 0.0 {
            best_row_scale(layer, i, q / maxabs, q, &eff, spec.in_power)
        } else {
            1.0
        };
        let mut l1 = vec![0i64; experts];
        for (k, w) in layer.w.iter().enumerate() {
            let base = (k * out_dim + i) * in_dim;
            for (j, &v) in w.row(i).iter().enumerate() {
                let v = eff(v, j);
                let wq = (v * scale).round().clamp(-q, q);
                weights[base + j] = wq as i32;
                l1[k] += (wq as i64).abs();
                sig += v * v;
                noise += (v - wq / scale).powi(2);
            }
            bias[k * out_dim + i] = (layer.b[k][i] * scale).round() as i64;
        }
        rows.push(RowQuant { scale, l1 });
    }
    // 32-bit accumulators when every row provably fits, else 64-bit.
    let fits_i32 = rows.iter().enumerate().all(|(i, r)| {
        r.l1.iter().all(|&l| l << 15 <= i64::from(i32::MAX))
            && (0..experts).all(|k| i32::try_from(bias[k * out_dim + i]).is_ok())
    });
    let acc = if fits_i32 {
        AccWidth::I32
    } else {
        AccWidth::I64
    };
    let mut requant = Vec::with_capacity(out_dim);
    let (mut max_dot, mut max_blend) = (0.0f64, 0.0f64);
    for (i, r) in rows.iter().enumerate() {
        let worst_expert = (0..experts)
            .map(|k| i128::from(r.l1[k]) * 32768 + i128::from(bias[k * out_dim + i].abs()))
            .max()
            .unwrap_or(0);
        let blend = worst_expert * i128::from(gsum);
        if blend >= i128::from(i64::MAX) {
            return Err(QuantError::Overflow { layer: li, row: i });
        }
        max_dot = max_dot.max(bits(
            r.l1.iter().copied().max().unwrap_or(0) as f64 * 32768.0,
        ));
        max_blend = max_blend.max(bits(blend as f64));
        let pre = (128 - blend.leading_zeros()).saturating_sub(31) as u8;
        let m_real = spec.targets[i] / (Q16 * r.scale) * f64::from(pre).exp2();
        let mut rq = multiplier(m_real, pre).ok_or(QuantError::Scale { layer: li, row: i })?;
        rq.frac = spec.fracs[i];
        requant.push(rq);
    }
    let desc = LayerDesc {
        op: LayerOp::Dense,
        in_dim: in_dim as u16,
        out_dim: out_dim as u16,
        experts: experts as u16,
        weights: format,
        acc,
        activation: if spec.elu {
            Activation::Elu
        } else {
            Activation::Identity
        },
        gated: true,
        weight_section: Section::default(),
        bias_section: Section::default(),
        requant_section: Section::default(),
    };
    let frac_range = spec
        .fracs
        .iter()
        .fold((u8::MAX, 0u8), |(lo, hi), &f| (lo.min(f), hi.max(f)));
    let report = LayerReport {
        index: li,
        in_dim,
        out_dim,
        experts,
        accumulator: if acc == AccWidth::I32 { "i32" } else { "i64" },
        out_frac_range: spec.elu.then_some(frac_range),
        calibrated_max: 0.0,
        weight_sqnr_db: 10.0 * (sig / noise.max(f64::MIN_POSITIVE)).log10(),
        max_dot_bits: max_dot,
        max_blend_bits: max_blend,
        // Dot products: i32 proven row by row (and re-checked by the loader),
        // i64 by |w x| <= 2^30 and in_dim < 2^16. Blend: < 2^63 (checked
        // above). Pre-shift: the blend fits i32 after it, so sat32 never clips.
        proof: true,
    };
    Ok((
        BlobLayer {
            desc,
            weights,
            bias,
            requant,
        },
        report,
    ))
}

/// The requantisation record for multiplier `m_real` after a pre-shift of `pre`.
fn multiplier(m_real: f64, pre: u8) -> Option<Requant> {
    let (m, post) = crate::cp::quantise::fixed_multiplier(m_real)?;
    Some(Requant {
        multiplier: m,
        pre_shift: pre,
        post_shift: post,
        frac: 0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn multiplier_is_accurate() {
        for &m in &[1e-12, 3.7e-9, 0.001, 0.4999, 0.5, 0.9999999, 1.0, 1234.5] {
            let r = multiplier(m, 0).unwrap();
            let back = f64::from(r.multiplier) * (-f64::from(r.post_shift)).exp2();
            assert!(((back - m) / m).abs() < 1e-9 || m < 1e-10, "{m}: {back}");
            assert!(r.multiplier >= 1 << 30 || r.post_shift == 62);
        }
        assert!(multiplier(f64::NAN, 0).is_none());
        assert!(multiplier(1e12, 0).is_none());
    }

    #[test]
    fn gate_bounds() {
        assert_eq!(gate_l1_bound(&Gating::Constant { tables: 50 }), 65536 + 8);
        let cr = gate_l1_bound(&Gating::CatmullRom { points: 4 });
        assert!((81920..=81940).contains(&cr), "{cr}");
    }
}
