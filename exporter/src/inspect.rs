//! `exporter inspect`: a blob's header as a readable table, model blobs
//! and style blobs alike: per layer its op (dense, CP and its rank,
//! diagonal), multiply-accumulates, formats and section offsets.

use phasegate::blob::{
    AccWidth, Activation, Gating, LayerDesc, LayerOp, WeightFormat, FORMAT_VERSION,
};
use phasegate::{Model, Style};
use std::fmt::Write;

fn gating(g: &Gating) -> String {
    match g {
        Gating::Single => "single (no phase)".into(),
        Gating::Constant { tables } => format!("constant, {tables} tables"),
        Gating::Linear { tables } => format!("linear, {tables} tables"),
        Gating::CatmullRom { points } => format!("cubic Catmull-Rom, {points} control points"),
    }
}

/// The table `exporter inspect` prints for a valid blob.
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
        "RAM needed       {} bytes (two i16 buffers of {})",
        h.ram_bytes,
        model.buffer_elements()
    );
    let _ = writeln!(s, "MACs per frame   {}", h.macs_per_frame);
    s.push('\n');
    s.push_str(&layer_table(&h.gating, &h.layers));
    let _ = writeln!(
        s,
        "\ninput stage @{} ({} B), output stage @{} ({} B)",
        h.input_stage.offset, h.input_stage.len, h.output_stage.offset, h.output_stage.len
    );
    s
}

/// How a layer computes `W x`: "dense", "cp rank R" or "diagonal".
pub fn op_name(op: &LayerOp) -> String {
    match op {
        LayerOp::Dense => "dense".into(),
        LayerOp::Cp { rank, .. } => format!("cp rank {rank}"),
        LayerOp::Diagonal => "diagonal".into(),
    }
}

/// The per-layer table: shapes, op, MACs per frame (as
/// [`phasegate::macs`] counts them), formats and section offsets.
pub fn layer_table(gating: &Gating, layers: &[LayerDesc]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{:>5} {:>5} {:>5} {:>7} {:<12} {:>9} {:>7} {:>4} {:>5} {:>10} {:>10} {:>10}",
        "layer",
        "in",
        "out",
        "experts",
        "op",
        "MACs",
        "weights",
        "acc",
        "act",
        "weights@",
        "bias@",
        "requant@"
    );
    for (i, l) in layers.iter().enumerate() {
        let _ = writeln!(
            s,
            "{:>5} {:>5} {:>5} {:>7} {:<12} {:>9} {:>7} {:>4} {:>5} {:>10} {:>10} {:>10}",
            i,
            l.in_dim,
            l.out_dim,
            l.experts,
            op_name(&l.op),
            phasegate::macs(gating, core::slice::from_ref(l)),
            match l.weights {
                WeightFormat::I8 => "int8",
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
            l.weight_section.offset,
            l.bias_section.offset,
            l.requant_section.offset,
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
    s.push_str(&layer_table(&style.gating(), core::slice::from_ref(d)));
    s
}
