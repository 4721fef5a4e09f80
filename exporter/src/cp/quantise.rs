//! Float layers of any form (dense, CP, diagonal) to integer blob layers.
//!
//! The scheme is the dense quantiser's ([`crate::quantise`]) in its plain
//! form: symmetric weights with one scale per stored row, biases in
//! accumulator units, int16 activations whose per-row formats come from
//! calibration (powers of two for hidden rows, for ELU; free scales for the
//! output rows), and the input columns' scales absorbed into the weights.
//! What CP layers add:
//!
//! * `B^T` gets one scale per rank component `sB_r`, the cores `d_k[r]`
//!   (int16 always: they are tiny) one per component `sD_r`, shared by the
//!   experts so the gate blends them before any rounding;
//! * the middle vector `u_r = c_r t_r` gets its own free int16 scale `zs_r`
//!   from calibration, and `A`'s columns absorb `1 / zs_r`;
//! * every shift is chosen from worst-case bounds over all i16 inputs and
//!   all phases, with the same formulas the loader re-checks
//!   (`phasegate::kernels::cp::CpLayer::check`), so a blob this writes is
//!   never refused and never saturates before its final i16.

use ndarray::{Array1, Array2};
use phasegate::blob::{
    AccWidth, Activation, Gating, LayerDesc, LayerOp, Requant, Section, WeightFormat,
};
use phasegate::kernels::cp::{gate_l1_max, MidRecord};
use serde::Serialize;

use crate::cp::encode::{QCp, QLayer};
use crate::cp::float::{CpLayer, DiagLayer, NetLayer};
use crate::float_pfnn::ExpertLayer;
use crate::quantise::QuantError;

const ACT_MAX: f64 = 32767.0;
const Q16: f64 = 65536.0;
const I32_MAX: u128 = i32::MAX as u128;

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
}

/// Extra headroom of CP middle vectors over the rows' (a product of two
/// calibrated quantities has heavier tails than either; measured on the
/// real PFNN, 1.5x of the calibrated maximum saturates a few values in a
/// few hundred frames, 4x none).
pub const MID_HEADROOM_FACTOR: f64 = 2.5;

/// What the quantiser did to one layer.
#[derive(Clone, Debug, Serialize)]
pub struct QuantLayerReport {
    /// Layer index.
    pub index: usize,
    /// "dense", "cp" or "diagonal".
    pub form: &'static str,
    /// Input width.
    pub in_dim: usize,
    /// Output width.
    pub out_dim: usize,
    /// Experts.
    pub experts: usize,
    /// CP rank.
    pub rank: Option<usize>,
    /// "i32" or "i64".
    pub accumulator: &'static str,
    /// Bytes of the layer's sections in the blob.
    pub bytes: usize,
    /// Weight signal-to-quantisation-noise ratio, dB (all weight arrays).
    pub weight_sqnr_db: f64,
    /// The worst-case bounds hold for every i16 input (re-checked at load).
    pub proof: bool,
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

fn qmax(format: WeightFormat) -> f64 {
    match format {
        WeightFormat::I8 => 127.0,
        WeightFormat::I16 => 32767.0,
    }
}

/// Quantised rows of one matrix (one scale per row).
struct Rows {
    q: Vec<i32>,
    scales: Vec<f64>,
    l1: Vec<u64>,
    sig: f64,
    noise: f64,
}

/// Quantises `rows x cols` real values `f(i, j)` with one scale per row.
///
/// Without `power` the scale maps the row's largest value to `q`. With the
/// mean square of each column's input (integer units), the scale is the
/// one between that and 1/0.6 of it that minimises the row's expected
/// output error `sum_j (w - q(w))^2 E[x_j^2]` (clipping a few outliers buys
/// a finer step for every other weight; with int8 this matters).
fn quantise_rows(
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

fn sqnr(sig: f64, noise: f64) -> f64 {
    10.0 * (sig / noise.max(f64::MIN_POSITIVE)).log10()
}

fn requant_for(
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
    let pre = shift_to_i32(bound);
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

fn desc(
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
        gated: spec.gated,
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

fn layer_bytes(l: &QLayer) -> usize {
    let d = &l.desc;
    let wb = d.weights.bytes();
    let mut n = l.weights.len() * wb + l.bias.len() * d.acc.bytes() + l.requant.len() * 8;
    if let Some(cp) = &l.cp {
        n += cp.a.len() * wb + cp.cores.len() * 2 + cp.mid.len() * 8;
    }
    n
}

/// Quantises one layer of any form.
pub fn quantise_layer(
    layer: &NetLayer,
    spec: &LayerSpec<'_>,
) -> Result<(QLayer, QuantLayerReport), QuantError> {
    let q = match layer {
        NetLayer::Dense(l) => quantise_dense(l, spec)?,
        NetLayer::Cp(l) => quantise_cp(l, spec)?,
        NetLayer::Diagonal(l) => quantise_diag(l, spec)?,
    };
    Ok(q)
}

fn report(
    spec: &LayerSpec<'_>,
    layer: &QLayer,
    form: &'static str,
    rank: Option<usize>,
    sig: f64,
    noise: f64,
) -> QuantLayerReport {
    QuantLayerReport {
        index: spec.index,
        form,
        in_dim: usize::from(layer.desc.in_dim),
        out_dim: usize::from(layer.desc.out_dim),
        experts: usize::from(layer.desc.experts),
        rank,
        accumulator: acc_name(layer.desc.acc),
        bytes: layer_bytes(layer),
        weight_sqnr_db: sqnr(sig, noise),
        proof: true,
    }
}

fn quantise_dense(
    l: &ExpertLayer,
    spec: &LayerSpec<'_>,
) -> Result<(QLayer, QuantLayerReport), QuantError> {
    let experts = l.experts();
    let (out, inp) = l.w.first().map_or((0, 0), Array2::dim);
    let q = qmax(spec.format);
    // One scale per output row, shared by the experts.
    let mut weights = vec![0i32; experts * out * inp];
    let mut bias = vec![0i64; experts * out];
    let mut l1 = vec![vec![0u64; experts]; out];
    let mut scales = vec![1.0; out];
    let (mut sig, mut noise) = (0.0, 0.0);
    for i in 0..out {
        let maxabs =
            l.w.iter()
                .flat_map(|w| (0..inp).map(move |j| (w[(i, j)] / spec.in_scales[j]).abs()))
                .fold(0.0, f64::max);
        let s = if maxabs > 0.0 { q / maxabs } else { 1.0 };
        scales[i] = s;
        for (k, w) in l.w.iter().enumerate() {
            for j in 0..inp {
                let v = w[(i, j)] / spec.in_scales[j];
                let wq = (v * s).round().clamp(-q, q);
                weights[(k * out + i) * inp + j] = wq as i32;
                l1[i][k] += wq.abs() as u64;
                sig += v * v;
                noise += (v - wq / s).powi(2);
            }
            bias[k * out + i] = (l.b[k][i] * s).round() as i64;
        }
    }
    let fits = l1.iter().flatten().all(|&v| u128::from(v) << 15 <= I32_MAX)
        && bias.iter().all(|&b| i32::try_from(b).is_ok());
    let acc = if fits { AccWidth::I32 } else { AccWidth::I64 };
    let g1 = gate_l1_max(&spec.gating) as u128;
    let mut requant = Vec::with_capacity(out);
    for i in 0..out {
        let worst = (0..experts)
            .map(|k| (u128::from(l1[i][k]) << 15) + u128::from(bias[k * out + i].unsigned_abs()))
            .max()
            .unwrap_or(0);
        requant.push(requant_for(spec, i, scales[i], worst * g1)?);
    }
    let ql = QLayer {
        desc: desc(spec, LayerOp::Dense, inp, out, experts, acc),
        weights,
        bias,
        requant,
        cp: None,
    };
    let rep = report(spec, &ql, "dense", None, sig, noise);
    Ok((ql, rep))
}

fn quantise_diag(
    l: &DiagLayer,
    spec: &LayerSpec<'_>,
) -> Result<(QLayer, QuantLayerReport), QuantError> {
    let experts = l.w.len();
    let n = l.w.first().map_or(0, Array1::len);
    let q = qmax(spec.format);
    let mut weights = vec![0i32; experts * n];
    let mut bias = vec![0i64; experts * n];
    let (mut sig, mut noise) = (0.0, 0.0);
    let mut requant = Vec::with_capacity(n);
    let g1 = gate_l1_max(&spec.gating) as u128;
    let mut rows = Vec::with_capacity(n);
    for i in 0..n {
        let eff = |k: usize| l.w[k][i] / spec.in_scales[i];
        let maxabs = (0..experts).map(|k| eff(k).abs()).fold(0.0, f64::max);
        let s = if maxabs > 0.0 { q / maxabs } else { 1.0 };
        let mut worst = 0u128;
        for k in 0..experts {
            let wq = (eff(k) * s).round().clamp(-q, q);
            weights[k * n + i] = wq as i32;
            bias[k * n + i] = (l.b[k][i] * s).round() as i64;
            sig += eff(k).powi(2);
            noise += (eff(k) - wq / s).powi(2);
            worst = worst.max(
                (u128::from(wq.abs() as u64) << 15) + u128::from(bias[k * n + i].unsigned_abs()),
            );
        }
        rows.push((s, worst));
    }
    let acc = if bias.iter().all(|&b| i32::try_from(b).is_ok()) {
        AccWidth::I32
    } else {
        AccWidth::I64
    };
    for (i, &(s, worst)) in rows.iter().enumerate() {
        requant.push(requant_for(spec, i, s, worst * g1)?);
    }
    let ql = QLayer {
        desc: desc(spec, LayerOp::Diagonal, n, n, experts, acc),
        weights,
        bias,
        requant,
        cp: None,
    };
    let rep = report(spec, &ql, "diagonal", None, sig, noise);
    Ok((ql, rep))
}

fn quantise_cp(
    l: &CpLayer,
    spec: &LayerSpec<'_>,
) -> Result<(QLayer, QuantLayerReport), QuantError> {
    let (rank, experts) = (l.rank(), l.experts());
    let (out, inp) = (l.a.nrows(), l.b.nrows());
    let q = qmax(spec.format);
    let mid_max = spec.mid_max.ok_or_else(|| {
        QuantError::Invalid(format!(
            "layer {}: CP layer without calibration",
            spec.index
        ))
    })?;
    // B^T: one scale per component; the input columns' scales absorbed.
    let in_power: Option<Vec<f64>> = spec.in_power.map(|p| {
        p.iter()
            .zip(spec.in_scales)
            .map(|(m, u)| m * u * u)
            .collect()
    });
    let bt = quantise_rows(
        rank,
        inp,
        q,
        |r, j| l.b[(j, r)] / spec.in_scales[j],
        in_power.as_deref(),
    );
    // Cores: int16, one scale per component shared by the experts.
    let mut cores = vec![0i16; experts * rank];
    let mut core_scales = vec![1.0; rank];
    let mut core_max = vec![0u64; rank];
    for r in 0..rank {
        let maxabs = (0..experts).map(|k| l.d[(k, r)].abs()).fold(0.0, f64::max);
        let s = if maxabs > 0.0 { ACT_MAX / maxabs } else { 1.0 };
        core_scales[r] = s;
        for k in 0..experts {
            let v = (l.d[(k, r)] * s).round().clamp(-ACT_MAX, ACT_MAX);
            cores[k * rank + r] = v as i16;
            core_max[r] = core_max[r].max(v.abs() as u64);
        }
    }
    // Middle formats: free scales from calibration.
    let zs: Vec<f64> = mid_max
        .iter()
        .map(|&m| {
            if m > 0.0 {
                ACT_MAX / (spec.headroom * MID_HEADROOM_FACTOR * m)
            } else {
                1.0
            }
        })
        .collect();
    let mid_power: Option<Vec<f64>> = spec
        .mid_power
        .map(|p| p.iter().zip(&zs).map(|(m, z)| m * z * z).collect());
    let a = quantise_rows(
        out,
        rank,
        q,
        |i, r| l.a[(i, r)] / zs[r],
        mid_power.as_deref(),
    );
    let mut bias = vec![0i64; experts * out];
    for k in 0..experts {
        for i in 0..out {
            bias[k * out + i] = (l.bias[k][i] * a.scales[i]).round() as i64;
        }
    }
    let fits = bt
        .l1
        .iter()
        .chain(&a.l1)
        .all(|&v| u128::from(v) << 15 <= I32_MAX)
        && bias.iter().all(|&b| i32::try_from(b).is_ok());
    let acc = if fits { AccWidth::I32 } else { AccWidth::I64 };
    let g1 = gate_l1_max(&spec.gating) as u128;
    let mut mid = Vec::with_capacity(rank);
    for r in 0..rank {
        let t_bound = u128::from(bt.l1[r]) << 15;
        let t_shift = shift_to_i32(t_bound);
        let t = (t_bound >> t_shift) + 1;
        let c = ((g1 * u128::from(core_max[r])) >> 16) + 1;
        let pre = shift_to_i32(t * c);
        let m_real = zs[r] * f64::from(t_shift).exp2() / (bt.scales[r] * core_scales[r])
            * f64::from(pre).exp2();
        let (multiplier, post_shift) = fixed_multiplier(m_real).ok_or(QuantError::Scale {
            layer: spec.index,
            row: r,
        })?;
        mid.push(MidRecord {
            multiplier,
            t_shift,
            pre_shift: pre,
            post_shift,
        });
    }
    let mut requant = Vec::with_capacity(out);
    for i in 0..out {
        let bmax = (0..experts)
            .map(|k| u128::from(bias[k * out + i].unsigned_abs()))
            .max()
            .unwrap_or(0);
        let bound = ((u128::from(a.l1[i]) << 15) << 16) + g1 * bmax;
        requant.push(requant_for(spec, i, a.scales[i], bound)?);
    }
    let ql = QLayer {
        desc: desc(
            spec,
            LayerOp::Cp {
                rank: u16::try_from(rank)
                    .map_err(|_| QuantError::Invalid("rank above 65535".into()))?,
                a: Section::default(),
                cores: Section::default(),
                mid: Section::default(),
            },
            inp,
            out,
            experts,
            acc,
        ),
        weights: bt.q,
        bias,
        requant,
        cp: Some(QCp { a: a.q, cores, mid }),
    };
    let rep = report(
        spec,
        &ql,
        "cp",
        Some(rank),
        bt.sig + a.sig,
        bt.noise + a.noise,
    );
    Ok((ql, rep))
}
