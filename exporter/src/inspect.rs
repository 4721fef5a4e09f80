//! `exporter inspect`: a blob's header as a readable table, model blobs
//! and style blobs alike: per layer its op (dense, CP and its rank,
//! diagonal), multiply-accumulates, formats and section offsets.

use phasegate::blob::{
    AccWidth, Activation, GateSource, Gating, LayerOp, Node, NodeOp, Requant, Slice, Source, Span,
    WeightFormat, FORMAT_VERSION, REQUANT_RECORD_LEN,
};
use phasegate::ops::{GatedOp, Layer};
use phasegate::{node_gating, Model, Style};
use std::fmt::Write;

fn gating(g: &Gating) -> String {
    match g {
        Gating::Single => "single (no phase)".into(),
        Gating::Constant { tables } => format!("constant, {tables} tables"),
        Gating::Linear { tables } => format!("linear, {tables} tables"),
        Gating::CatmullRom { points } => format!("cubic Catmull-Rom, {points} control points"),
        Gating::Softmax { experts } => format!("softmax gate, {experts} experts"),
    }
}

/// The row formats (Q`frac` of each output row, from its requantisation
/// record) of layer node `i` of `model`: what a blob built against it must
/// share (rig blobs, style adapters) and what bounds each row's range.
pub fn row_formats(model: &Model<'_>, i: usize) -> anyhow::Result<Vec<u8>> {
    let k = model
        .kernel(i)
        .ok_or_else(|| anyhow::anyhow!("node {i} is not a layer"))?;
    k.requant()
        .as_chunks::<REQUANT_RECORD_LEN>()
        .0
        .iter()
        .map(|r| Requant::from_bytes(r).map(|q| q.frac))
        .collect::<Option<Vec<u8>>>()
        .ok_or_else(|| anyhow::anyhow!("node {i} has a bad requantisation record"))
}

/// The table `exporter inspect` prints for a valid blob.
/// The runtime's refusal of a blob, for a person: its `Display`, plus what
/// `255` (`phasegate::STAGE`: not a node) stands for where it appears.
pub fn explain(e: &phasegate::Error) -> String {
    match e {
        phasegate::Error::UnsupportedParameter { layer } if *layer == phasegate::STAGE => format!(
            "{e} (255: the header's gating or the input/output stages; an output stage \
             must keep |scale| <= 2^24 and |offset| <= 2^39, docs/blob-format.md check 34)"
        ),
        _ => e.to_string(),
    }
}

pub fn describe(model: &Model<'_>) -> String {
    let h = model.header();
    let mut s = String::new();
    let _ = writeln!(s, "format version   {FORMAT_VERSION}");
    let _ = writeln!(s, "model kind       {:?}", h.kind);
    let _ = writeln!(s, "gating           {}", gating(&h.gating));
    let _ = writeln!(s, "input, output    {}, {}", h.input_dim, h.output_dim);
    let _ = writeln!(s, "blob bytes       {}", model.blob_len());
    let _ = writeln!(
        s,
        "payload bytes    {} (CRC-32 {:#010x}, verified)",
        h.payload_len, h.payload_crc
    );
    let _ = writeln!(
        s,
        "RAM needed       {} bytes (an arena of {} i16, planned and checked)",
        h.ram_bytes,
        model.arena_elements()
    );
    let _ = writeln!(s, "MACs per frame   {}", h.macs_per_frame);
    if let Some(t) = model.self_test() {
        let _ = writeln!(
            s,
            "self-test        {} vectors and their integer outputs (end of the payload; run at boot)",
            t.count()
        );
    }
    let _ = writeln!(
        s,
        "input            arena @{}..{}, output {}",
        h.input.offset,
        h.input.end(),
        slice_name(&h.output)
    );
    s.push('\n');
    s.push_str(&node_table(&h.gating, &h.nodes.to_vec()));
    let _ = writeln!(
        s,
        "\ninput stage @{} ({} B), output stage @{} ({} B)",
        h.input_stage.offset, h.input_stage.len, h.output_stage.offset, h.output_stage.len
    );
    s
}

/// How a layer computes `W x`: "dense", "cp rank R", "diagonal", "rbf" or
/// "dec".
pub fn op_name(op: &LayerOp) -> String {
    match op {
        LayerOp::Dense => "dense".into(),
        LayerOp::Cp { rank, .. } => format!("cp rank {rank}"),
        LayerOp::Diagonal => "diagonal".into(),
        LayerOp::Rbf { .. } => "rbf".into(),
        LayerOp::Dec { .. } => "dec".into(),
    }
}

/// `input[a..b]` or `node k[a..b]`.
pub fn slice_name(s: &Slice) -> String {
    let end = u32::from(s.start) + u32::from(s.len);
    match s.source {
        Source::Input => format!("input[{}..{end}]", s.start),
        Source::Node(j) => format!("node {j}[{}..{end}]", s.start),
    }
}

fn span_name(s: &Span) -> String {
    if s.len == 0 {
        "-".into()
    } else {
        format!("@{}..{}", s.offset, s.end())
    }
}

/// The per-node table: op, shapes, inputs and gate source, MACs per frame
/// (as [`phasegate::macs`] counts them), formats, arena spans and section
/// offsets.
pub fn node_table(gating: &Gating, nodes: &[Node]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{:>4} {:>5} {:>5} {:>7} {:<12} {:>9} {:<8} {:>7} {:>4} {:>4} {:<13} {:<13} {:<13} {:>9} {:>9} {:>9}  inputs",
        "node",
        "in",
        "out",
        "experts",
        "op",
        "MACs",
        "gate",
        "weights",
        "acc",
        "act",
        "input",
        "scratch",
        "output",
        "weights@",
        "bias@",
        "requant@"
    );
    for (i, n) in nodes.iter().enumerate() {
        let inputs: Vec<String> = n.inputs.iter().map(slice_name).collect();
        let gate = match n.gate {
            GateSource::None => "-".to_string(),
            GateSource::Phase => "phase".to_string(),
            GateSource::Node(j) => format!("node {j}"),
        };
        let (name, experts, macs, formats, sections) = match &n.op {
            NodeOp::Layer(l) => (
                op_name(&l.op),
                l.experts,
                Layer::macs(l, node_gating(gating, nodes, n).active() as u64),
                (
                    match l.weights {
                        WeightFormat::I8 | WeightFormat::I8Interleaved => "int8",
                        WeightFormat::I16 => "int16",
                    },
                    match l.acc {
                        AccWidth::I32 => "i32",
                        AccWidth::I64 => "i64",
                    },
                    match l.activation {
                        Activation::Identity => "-",
                        Activation::Elu => "ELU",
                    },
                ),
                (
                    l.weight_section.offset.to_string(),
                    l.bias_section.offset.to_string(),
                    l.requant_section.offset.to_string(),
                ),
            ),
            NodeOp::Softmax(g) => (
                format!("softmax Q{}", g.frac),
                g.experts,
                0,
                ("-", "-", "-"),
                ("-".into(), "-".into(), "-".into()),
            ),
        };
        let _ = writeln!(
            s,
            "{:>4} {:>5} {:>5} {:>7} {:<12} {:>9} {:<8} {:>7} {:>4} {:>4} {:<13} {:<13} {:<13} {:>9} {:>9} {:>9}  {}",
            i,
            n.in_dim(),
            n.out_dim(),
            experts,
            name,
            macs,
            gate,
            formats.0,
            formats.1,
            formats.2,
            span_name(&n.input),
            span_name(&n.scratch),
            span_name(&n.output),
            sections.0,
            sections.1,
            sections.2,
            inputs.join(" + "),
        );
    }
    s
}

/// The table `exporter inspect` prints for a valid style blob.
pub fn describe_style(style: &Style<'_>) -> String {
    let d = style.kernel().desc();
    let mut s = String::new();
    let _ = writeln!(s, "format version   {FORMAT_VERSION}");
    let _ = writeln!(s, "model kind       style (residual adapter)");
    let _ = writeln!(s, "style name       {:?}", style.name());
    let _ = writeln!(
        s,
        "base blob        payload CRC-32 {:#010x}",
        style.base_crc()
    );
    let _ = writeln!(
        s,
        "beside layer     {} (adds to its pre-activation)",
        style.layer()
    );
    let _ = writeln!(s, "gating           {}", gating(&style.gating()));
    let _ = writeln!(s, "input, output    {}, {}", d.in_dim, d.out_dim);
    let _ = writeln!(s, "blob bytes       {}", style.blob_len());
    let _ = writeln!(
        s,
        "payload CRC-32   {:#010x} (verified)",
        style.payload_crc()
    );
    let _ = writeln!(s, "MACs per frame   {}", style.macs_per_frame());
    s.push('\n');
    let node = Node {
        op: NodeOp::Layer(*d),
        inputs: [Slice {
            source: Source::Input,
            start: 0,
            len: d.in_dim,
        }]
        .into_iter()
        .collect(),
        gate: style.gate(),
        input: Span::default(),
        scratch: Span::default(),
        output: Span::default(),
    };
    s.push_str(&node_table(&style.gating(), &[node]));
    s
}
