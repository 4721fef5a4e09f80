//! Style blobs: a residual adapter (full, diagonal or CP) quantised against
//! one base blob, so that its output adds to the base layer's pre-activation
//! in the base's own integer formats.
//!
//! * The adapter reads base layer `L`'s input: the output of base layer
//!   `L - 1`, whose rows are int16 in power-of-two formats (`frac` of that
//!   layer's requantisation records). Those formats become the adapter's
//!   input column scales.
//! * It writes, with identity activation, in base layer `L`'s formats
//!   (`frac` of its records, copied into the adapter's records, which the
//!   runtime checks when the style is added).
//! * A CP adapter's middle vector gets its own scales from calibration on
//!   the base float network's layer-`L` inputs.
//!
//! So `L` must have a hidden layer on both sides (`1 <= L`, layers `L - 1`
//! and `L` with ELU): the paper's position, beside the middle layer of the
//! PFNN, is `L = 1`.
//!
//! The float reference of a styled run is the base chain with the adapter
//! as nodes of its graph ([`Net::with_adapters`]): the adapter a layer node
//! reading base layer `L`'s input, a residual node adding it to `L`'s
//! pre-activation, as the runtime adds the style's output.

pub mod cli;

use anyhow::{anyhow, bail, Result};
use phasegate::blob::{Activation, Gating};
use phasegate::{Mix, Model, Phase, Runtime, Style};
use serde::Serialize;

use crate::calibrate::{max_into, ms_into, normal_inputs, Samples};
use crate::cp::report::{output_error, OutputError};
use crate::encode::encode;
use crate::lower::qmodel::format_name;
use crate::lower::qmodel::{QKind, QModel, Wiring};
use crate::net::residual::{adapter_node_name, residual_node_name};
use crate::net::{Adapter, Graph, Net, NetLayer};
use crate::quantise::LayerSpec;
use crate::quantise::QuantOptions;

/// Integer formats of base layer `layer`: the scales of its input columns
/// (from layer `layer - 1`'s row formats) and its own rows' `frac`.
pub fn base_formats(model: &Model<'_>, layer: usize) -> Result<(Vec<f64>, Vec<u8>)> {
    let count = model.nodes().len();
    if layer == 0 || layer + 1 > count {
        bail!(
            "an adapter must sit beside a hidden layer with a hidden layer before it \
             (1 <= layer < {count}), not layer {layer}"
        );
    }
    let fracs = |i: usize| -> Result<Vec<u8>> {
        let k = model
            .kernel(i)
            .ok_or_else(|| anyhow!("base layer {i} missing"))?;
        if k.desc().activation != Activation::Elu {
            bail!("base layer {i} has no ELU: its output formats are not powers of two");
        }
        crate::inspect::row_formats(model, i)
    };
    let inputs = fracs(layer - 1)?
        .into_iter()
        .map(|f| f64::from(1u32 << f))
        .collect();
    Ok((inputs, fracs(layer)?))
}

/// What calibration saw at an adapter.
struct AdapterStats {
    /// Mean square of each input column.
    in_ms: Vec<f64>,
    /// Max |middle component| (CP).
    mid_max: Option<Vec<f64>>,
    /// Mean square of each middle component (CP).
    mid_ms: Option<Vec<f64>>,
}

/// Runs `base` with `adapter` beside its layer on the quantiser's
/// calibration inputs and records what the adapter's node saw.
fn calibrate_adapter(base: &Net, adapter: &Adapter, opts: &QuantOptions) -> Result<AdapterStats> {
    let samples = normal_inputs(
        &base.xmean.to_vec(),
        &base.xstd.to_vec(),
        opts.calibration_samples,
        opts.calibration_scale,
        opts.seed,
    );
    let styled = base.with_adapters(&[(adapter, 1.0)])?;
    let (g, node, _) = styled_nodes(&styled, adapter.layer)?;
    let mut stats = AdapterStats {
        in_ms: vec![0.0; adapter.op.in_dim()],
        mid_max: None,
        mid_ms: None,
    };
    let count = samples.inputs.len().max(1) as f64;
    for (x, &p) in samples.inputs.iter().zip(&samples.phases) {
        let t = styled.graph_trace(g, x, p);
        ms_into(&mut stats.in_ms, &t.inputs[node], count);
        if let Some(u) = &t.mids[node] {
            max_into(stats.mid_max.get_or_insert_with(Vec::new), u);
            ms_into(stats.mid_ms.get_or_insert_with(Vec::new), u, count);
        }
    }
    Ok(stats)
}

/// Quantises `adapter` for the base `model` (whose float twin is `base`).
pub fn quantise_adapter(
    model: &Model<'_>,
    base: &Net,
    adapter: &Adapter,
    name: &str,
    opts: &QuantOptions,
) -> Result<QModel> {
    let l = adapter.layer;
    let (in_scales, fracs) = base_formats(model, l)?;
    let base_desc = model
        .kernel(l)
        .ok_or_else(|| anyhow!("base layer {l} missing"))?;
    let bd = base_desc.desc();
    if adapter.op.in_dim() != usize::from(bd.in_dim)
        || adapter.op.out_dim() != usize::from(bd.out_dim)
    {
        bail!(
            "adapter is {}x{}, base layer {l} is {}x{}",
            adapter.op.out_dim(),
            adapter.op.in_dim(),
            bd.out_dim,
            bd.in_dim
        );
    }
    let gating = model.header().gating;
    let experts = adapter.op.experts();
    if experts != 1 && experts != usize::from(gating.experts()) {
        bail!(
            "adapter has {experts} experts; the base gating has {} (or use 1 for a phase-free adapter)",
            gating.experts()
        );
    }
    let targets: Vec<f64> = fracs.iter().map(|&f| f64::from(1u32 << f)).collect();
    let stats = calibrate_adapter(base, adapter, opts)?;
    let spec = LayerSpec {
        index: 0,
        in_scales: &in_scales,
        targets: &targets,
        fracs: &fracs,
        activation: Activation::Identity,
        gated: experts > 1,
        format: opts.weights,
        gating,
        mid_max: stats.mid_max.as_deref(),
        in_power: Some(&stats.in_ms),
        mid_power: stats.mid_ms.as_deref(),
        headroom: opts.headroom,
        in_moments: None,
    };
    let (ql, _) = adapter.op.quantise(&spec)?;
    Ok(QModel {
        kind: QKind::Style {
            base_crc: model.header().payload_crc,
            layer: u8::try_from(l)?,
            name: name.to_string(),
        },
        gating,
        input_stage: Vec::new(),
        output_stage: Vec::new(),
        layers: vec![ql],
        wiring: Wiring::Chain,
    })
}

/// What `build_style` made and measured.
#[derive(Clone, Debug, Serialize)]
pub struct StyleReport {
    /// Style name.
    pub name: String,
    /// "full" (dense), "diagonal" or "cp".
    pub form: &'static str,
    /// CP rank.
    pub rank: Option<usize>,
    /// Base layer.
    pub layer: usize,
    /// Payload CRC of the base.
    pub base_crc: String,
    /// "int8" or "int16".
    pub weight_format: &'static str,
    /// Bytes of the style blob.
    pub blob_bytes: usize,
    /// Bytes of the adapter's parameters as float32 (the paper's unit).
    pub float32_bytes: usize,
    /// MACs the adapter adds per frame.
    pub macs_per_frame: u64,
    /// How much the style changes the float outputs (styled vs base).
    pub style_effect: OutputError,
    /// Styled fixed point vs styled float.
    pub fixed_vs_float: OutputError,
    /// Base fixed point vs base float, for comparison.
    pub base_fixed_vs_float: OutputError,
    /// Largest `|base pre-activation + adapter output|` over the samples,
    /// as a fraction of the i16 range of the base layer's row formats.
    /// Above 1 the styled pre-activation saturates: the base blob's formats
    /// (chosen for the base alone, with headroom) cannot hold this style,
    /// and the style should be weaker or the base exported with more
    /// headroom.
    pub range_used: f64,
}

/// "full", "diagonal", "cp", "rbf" or "dec".
pub fn form_name(op: &NetLayer) -> &'static str {
    match op {
        NetLayer::Dense(_) => "full",
        NetLayer::Diagonal(_) => "diagonal",
        NetLayer::Cp(_) => "cp",
        NetLayer::Rbf(_) => "rbf",
        NetLayer::Dec(_) => "dec",
    }
}

/// Runs base + styles on raw inputs with a mix per sample.
pub fn run_styled(
    base_blob: &[u8],
    styles: &[&[u8]],
    mix: &dyn Fn(usize) -> Mix,
    xs: &[Vec<f64>],
    phases: &[f64],
) -> Result<Vec<Vec<f64>>> {
    let model = Model::from_bytes(base_blob).map_err(|e| anyhow!("base blob: {e}"))?;
    let mut rt: Box<Runtime<'_, 4096, 8192, 8>> =
        Box::new(Runtime::new(model).map_err(|e| anyhow!("runtime: {e}"))?);
    for s in styles {
        let style = Style::from_bytes(s).map_err(|e| anyhow!("style blob: {e}"))?;
        rt.add_style(style).map_err(|e| anyhow!("style: {e}"))?;
    }
    let n_out = rt.model().output_dim();
    let mut out = Vec::with_capacity(xs.len());
    for (i, (x, &p)) in xs.iter().zip(phases).enumerate() {
        rt.set_mix(mix(i)).map_err(|e| anyhow!("mix: {e}"))?;
        let xf: Vec<f32> = x.iter().map(|&v| v as f32).collect();
        let mut y = vec![0f32; n_out];
        let phase = Phase::from_radians(p as f32).map_err(|e| anyhow!("phase: {e}"))?;
        rt.run(phase, &xf, &mut y)
            .map_err(|e| anyhow!("run: {e}"))?;
        out.push(y.into_iter().map(f64::from).collect());
    }
    Ok(out)
}

/// The graph of `styled` (a base with one adapter beside its layer
/// `layer`, [`Net::with_adapters`]), its adapter node and its residual node.
fn styled_nodes(styled: &Net, layer: usize) -> Result<(&Graph, usize, usize)> {
    let crate::net::Wiring::Graph(g) = &styled.wiring else {
        bail!("the styled net is not a graph");
    };
    let node = |name: String| {
        g.node(&name)
            .ok_or_else(|| anyhow!("the styled net has no node {name:?}"))
    };
    Ok((
        g,
        node(adapter_node_name(layer, 0))?,
        node(residual_node_name(layer))?,
    ))
}

/// Largest `|styled pre-activation|` of base layer `layer` over `samples`,
/// as a fraction of the i16 range of its row formats `fracs`.
fn range_used(styled: &Net, layer: usize, samples: &Samples, fracs: &[u8]) -> Result<f64> {
    let (g, _, node) = styled_nodes(styled, layer)?;
    let mut used = 0.0f64;
    for (x, &p) in samples.inputs.iter().zip(&samples.phases) {
        let t = styled.graph_trace(g, x, p);
        for (v, &f) in t.pre[node].iter().zip(fracs) {
            used = used.max(v.abs() * f64::from(1u32 << f) / 32767.0);
        }
    }
    Ok(used)
}

/// Quantises `adapter` against `base_blob`, encodes and self-checks the
/// style blob (it loads and attaches to the base), and measures it.
pub fn build_style(
    base_blob: &[u8],
    base: &Net,
    adapter: &Adapter,
    name: &str,
    opts: &QuantOptions,
    samples: usize,
) -> Result<(Vec<u8>, StyleReport)> {
    let model = Model::from_bytes(base_blob).map_err(|e| anyhow!("base blob: {e}"))?;
    let q = quantise_adapter(&model, base, adapter, name, opts)?;
    let blob = encode(&q)?;
    let style =
        Style::from_bytes(&blob).map_err(|e| anyhow!("style written does not load: {e}"))?;
    let s = normal_inputs(
        &base.xmean.to_vec(),
        &base.xstd.to_vec(),
        samples,
        1.0,
        0x57_11E,
    );
    let float_base: Vec<Vec<f64>> = s
        .inputs
        .iter()
        .zip(&s.phases)
        .map(|(x, &p)| base.forward(x, p))
        .collect();
    let styled = base.with_adapters(&[(adapter, 1.0)])?;
    let float_styled: Vec<Vec<f64>> = s
        .inputs
        .iter()
        .zip(&s.phases)
        .map(|(x, &p)| styled.forward(x, p))
        .collect();
    let fixed_styled = run_styled(
        base_blob,
        &[&blob],
        &|_| Mix::One(phasegate::StyleId(0)),
        &s.inputs,
        &s.phases,
    )?;
    let fixed_base = run_styled(base_blob, &[], &|_| Mix::Base, &s.inputs, &s.phases)?;
    let (ym, ys) = (base.ymean.to_vec(), base.ystd.to_vec());
    let (_, fracs) = base_formats(&model, adapter.layer)?;
    let range_used = range_used(&styled, adapter.layer, &s, &fracs)?;
    let report = StyleReport {
        name: name.to_string(),
        form: form_name(&adapter.op),
        rank: adapter.op.rank(),
        layer: adapter.layer,
        base_crc: format!("{:#010x}", model.header().payload_crc),
        weight_format: format_name(opts.weights),
        blob_bytes: blob.len(),
        float32_bytes: 4
            * (adapter.op.weight_count() + adapter.op.experts() * adapter.op.out_dim()),
        macs_per_frame: style.macs_per_frame(),
        style_effect: output_error(&float_styled, &float_base, &ym, &ys),
        fixed_vs_float: output_error(&fixed_styled, &float_styled, &ym, &ys),
        base_fixed_vs_float: output_error(&fixed_base, &float_base, &ym, &ys),
        range_used,
    };
    Ok((blob, report))
}

/// A one-paragraph description of a style blob (or its error).
pub fn describe_style(bytes: &[u8]) -> Result<String> {
    let s = Style::from_bytes(bytes).map_err(|e| anyhow!("{e}"))?;
    let d = s.kernel().desc();
    let form = match d.op {
        phasegate::blob::LayerOp::Dense => "full".to_string(),
        phasegate::blob::LayerOp::Diagonal => "diagonal".to_string(),
        phasegate::blob::LayerOp::Cp { rank, .. } => format!("cp rank {rank}"),
        phasegate::blob::LayerOp::Rbf { .. } => "rbf".to_string(),
        phasegate::blob::LayerOp::Dec { .. } => "dec".to_string(),
    };
    let gating = match s.gating() {
        Gating::Single => "single".to_string(),
        Gating::Constant { tables } => format!("constant {tables}"),
        Gating::Linear { tables } => format!("linear {tables}"),
        Gating::CatmullRom { points } => format!("catmull-rom {points}"),
        Gating::Softmax { experts } => format!("softmax {experts}"),
    };
    Ok(format!(
        "style {:?}: {form} adapter beside base layer {}, {}x{}, {} experts{}, {} weights, {} bytes, {} MACs/frame\n\
         base payload CRC {:#010x}, gating {gating}\n",
        s.name(),
        s.layer(),
        d.out_dim,
        d.in_dim,
        d.experts,
        if s.gate() == phasegate::blob::GateSource::Phase {
            ""
        } else {
            " (phase-free)"
        },
        format_name(d.weights),
        s.blob_len(),
        s.macs_per_frame(),
        s.base_crc()
    ))
}
