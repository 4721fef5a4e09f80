//! `exporter inspect`: a blob's header as a readable table.

use phasegate::blob::{AccWidth, Activation, Gating, WeightFormat, FORMAT_VERSION};
use phasegate::Model;
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
    let _ = writeln!(
        s,
        "\n{:>5} {:>5} {:>5} {:>7} {:>7} {:>4} {:>5} {:>10} {:>10} {:>10}",
        "layer", "in", "out", "experts", "weights", "acc", "act", "weights@", "bias@", "requant@"
    );
    for (i, l) in h.layers.iter().enumerate() {
        let _ = writeln!(
            s,
            "{:>5} {:>5} {:>5} {:>7} {:>7} {:>4} {:>5} {:>10} {:>10} {:>10}",
            i,
            l.in_dim,
            l.out_dim,
            l.experts,
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
    let _ = writeln!(
        s,
        "\ninput stage @{} ({} B), output stage @{} ({} B)",
        h.input_stage.offset, h.input_stage.len, h.output_stage.offset, h.output_stage.len
    );
    s
}
