//! Valid CRCs around a lying header: each lie refused with its own error.

mod hostile;

use hostile::*;

#[test]
fn hand_blob_is_valid_and_reframes_identically() {
    let blob = hand_blob();
    let p = Parts::of(&blob);
    assert_eq!(p.blob(), blob);
    let h = &p.header;
    assert_eq!(h.nodes.len(), 3);
    assert_eq!(
        (0..3)
            .map(|i| layer_of(h, i))
            .map(|l| (l.weights, l.acc))
            .collect::<Vec<_>>(),
        vec![
            (WeightFormat::I16, AccWidth::I32),
            (WeightFormat::I8, AccWidth::I64),
            (WeightFormat::I8, AccWidth::I32)
        ]
    );
    // The quantised blobs: Catmull-Rom, three gated layers, both formats.
    for (w, bytes) in [(WeightFormat::I8, 1usize), (WeightFormat::I16, 2)] {
        let q = quantised(w);
        let m = Model::from_bytes(&q).unwrap();
        assert_eq!(m.header().gating, Gating::CatmullRom { points: 4 });
        assert!(m.header().nodes.iter().all(|n| {
            let l = n.layer().unwrap();
            n.gate == GateSource::Phase && l.experts == 4 && l.weights.bytes() == bytes
        }));
        // The plan: layer 1's input and output (24 each) live together.
        assert_eq!(
            (m.input_dim(), m.output_dim(), m.arena_elements()),
            (20, 12, 48)
        );
    }
}

#[test]
fn sections_out_of_bounds_or_misaligned() {
    let base = Parts::of(&hand_blob());
    let len = base.payload.len() as u32;
    let cases: Vec<Case> = vec![
        (
            "weights past the end",
            Box::new(move |h| lay(h, 1).weight_section.offset = len.next_multiple_of(4) + 4),
            Error::SectionOutOfBounds { layer: 1 },
        ),
        (
            "bias misaligned",
            Box::new(|h| lay(h, 1).bias_section.offset += 2),
            Error::SectionOutOfBounds { layer: 1 },
        ),
        (
            "requant misaligned",
            Box::new(|h| lay(h, 2).requant_section.offset += 1),
            Error::SectionOutOfBounds { layer: 2 },
        ),
        (
            "offset + len overflows u32",
            Box::new(|h| lay(h, 0).weight_section.offset = 0xFFFF_FFFC),
            Error::SectionOutOfBounds { layer: 0 },
        ),
        (
            "last section one record too long",
            Box::new(|h| lay(h, 2).requant_section.len += 8),
            Error::SectionOutOfBounds { layer: 2 },
        ),
        (
            "output stage misaligned",
            Box::new(|h| h.output_stage.offset = 2),
            Error::SectionOutOfBounds { layer: STAGE },
        ),
        (
            "input stage past the end",
            Box::new(move |h| h.input_stage.offset = len.next_multiple_of(4)),
            Error::SectionOutOfBounds { layer: STAGE },
        ),
    ];
    for (name, edit, want) in cases {
        let mut p = base.clone();
        edit(&mut p.header);
        assert_eq!(refused(&p), want, "{name}");
    }
}

#[test]
fn sections_of_the_wrong_length() {
    let base = Parts::of(&hand_blob());
    let cases: Vec<Case> = vec![
        (
            "weights one byte short",
            Box::new(|h| lay(h, 0).weight_section.len -= 1),
            Error::SectionLength { layer: 0 },
        ),
        (
            "bias one i64 short",
            Box::new(|h| lay(h, 1).bias_section.len -= 8),
            Error::SectionLength { layer: 1 },
        ),
        (
            "requant one record short",
            Box::new(|h| lay(h, 2).requant_section.len -= 8),
            Error::SectionLength { layer: 2 },
        ),
        (
            "bias as if i32",
            Box::new(|h| lay(h, 1).acc = AccWidth::I32),
            Error::SectionLength { layer: 1 },
        ),
        (
            "weights as if int8",
            Box::new(|h| lay(h, 0).weights = WeightFormat::I8),
            Error::SectionLength { layer: 0 },
        ),
        (
            "input stage one record short",
            Box::new(|h| h.input_stage.len -= 8),
            Error::SectionLength { layer: STAGE },
        ),
        (
            "output stage one byte short",
            Box::new(|h| h.output_stage.len -= 1),
            Error::SectionLength { layer: STAGE },
        ),
        (
            "empty weights",
            Box::new(|h| lay(h, 1).weight_section.len = 0),
            Error::SectionLength { layer: 1 },
        ),
    ];
    for (name, edit, want) in cases {
        let mut p = base.clone();
        edit(&mut p.header);
        assert_eq!(refused(&p), want, "{name}");
    }
}

#[test]
fn dimensions_that_do_not_chain() {
    let base = Parts::of(&hand_blob());
    let cases: Vec<Case> = vec![
        (
            "layer 1 input != layer 0 output",
            Box::new(|h| lay(h, 1).in_dim = 9),
            Error::DimensionMismatch { layer: 1 },
        ),
        (
            "layer 0 input != model input",
            Box::new(|h| lay(h, 0).in_dim = 5),
            Error::DimensionMismatch { layer: 0 },
        ),
        (
            "model input != its arena span",
            Box::new(|h| h.input_dim = 7),
            Error::DimensionMismatch { layer: STAGE },
        ),
        (
            "model output != its slice",
            Box::new(|h| h.output_dim = 4),
            Error::DimensionMismatch { layer: STAGE },
        ),
        (
            "zero-width layer",
            Box::new(|h| lay(h, 1).out_dim = 0),
            Error::DimensionMismatch { layer: 1 },
        ),
        (
            "zero model input",
            Box::new(|h| h.input_dim = 0),
            Error::UnsupportedParameter { layer: STAGE },
        ),
        (
            "zero model output",
            Box::new(|h| h.output_dim = 0),
            Error::UnsupportedParameter { layer: STAGE },
        ),
        (
            "no layers",
            Box::new(|h| h.nodes.clear()),
            Error::UnsupportedParameter { layer: STAGE },
        ),
    ];
    for (name, edit, want) in cases {
        let mut p = base.clone();
        edit(&mut p.header);
        assert_eq!(refused(&p), want, "{name}");
    }
}

#[test]
fn experts_that_do_not_fit_the_gating() {
    let base = Parts::of(&hand_blob());
    let cases: Vec<Case> = vec![
        (
            "gated layer with 4 of 5 experts",
            Box::new(|h| lay(h, 0).experts = 4),
            Error::GatingMismatch { layer: 0 },
        ),
        (
            "ungated layer with 5 experts",
            Box::new(|h| lay(h, 2).experts = 5),
            Error::GatingMismatch { layer: 2 },
        ),
        (
            "ungated layer marked gated",
            Box::new(|h| h.nodes[2].gate = GateSource::Phase),
            Error::GatingMismatch { layer: 2 },
        ),
        (
            "gated layer marked ungated",
            Box::new(|h| h.nodes[1].gate = GateSource::None),
            Error::GatingMismatch { layer: 1 },
        ),
        (
            "6 control points",
            Box::new(|h| h.gating = Gating::CatmullRom { points: 6 }),
            Error::GatingMismatch { layer: 0 },
        ),
        (
            "single gating",
            Box::new(|h| h.gating = Gating::Single),
            Error::GatingMismatch { layer: 0 },
        ),
        (
            "3 control points",
            Box::new(|h| h.gating = Gating::CatmullRom { points: 3 }),
            Error::UnsupportedParameter { layer: STAGE },
        ),
        (
            "0 tables (constant)",
            Box::new(|h| h.gating = Gating::Constant { tables: 0 }),
            Error::UnsupportedParameter { layer: STAGE },
        ),
        (
            "0 tables (linear)",
            Box::new(|h| h.gating = Gating::Linear { tables: 0 }),
            Error::UnsupportedParameter { layer: STAGE },
        ),
        // Same expert count, fewer active experts: the MAC figure gives it away.
        (
            "linear over 5 tables, MACs of 4 active",
            Box::new(|h| h.gating = Gating::Linear { tables: 5 }),
            Error::HeaderInconsistent,
        ),
    ];
    for (name, edit, want) in cases {
        let mut p = base.clone();
        edit(&mut p.header);
        assert_eq!(refused(&p), want, "{name}");
    }
    // With its figures right, the same blob under another gating is valid.
    for gating in [Gating::Linear { tables: 5 }, Gating::Constant { tables: 5 }] {
        let mut p = base.clone();
        p.header.gating = gating;
        p.refigure();
        assert_eq!(p.load(), Ok(()));
    }
}

#[test]
fn a_style_blob_is_not_a_model() {
    let mut p = Parts::of(&hand_blob());
    p.header.kind = ModelKind::Style {
        base_crc: 0x1234_5678,
        layer: 1,
        name: Section::default(),
    };
    assert_eq!(refused(&p), Error::NotAModel);
}

#[test]
fn wrong_ram_or_mac_figures() {
    let base = Parts::of(&hand_blob());
    // The arena plan of 6 -> 8 -> 7 -> 5: 15 elements (layer 1's 8 + 7).
    assert_eq!(base.header.ram_bytes, 2 * 15);
    assert_eq!(base.header.macs_per_frame, 4 * 6 * 8 + 4 * 8 * 7 + 7 * 5);
    for (ram, macs) in [
        (32, 451),
        (28, 451),
        (31, 451),
        (0, 451),
        (u32::MAX, 451),
        (30, 452),
        (30, 450),
        (30, 0),
    ] {
        let mut p = base.clone();
        (p.header.ram_bytes, p.header.macs_per_frame) = (ram, macs);
        assert_eq!(
            refused(&p),
            Error::HeaderInconsistent,
            "ram {ram} macs {macs}"
        );
    }
}

#[test]
fn requantisation_records_out_of_range() {
    let base = Parts::of(&hand_blob());
    // (layer, row, byte, value, expected)
    let cases = [
        (1, 3, 4, 63, Some(Error::UnsupportedParameter { layer: 1 })), // pre_shift 63
        (2, 0, 5, 63, Some(Error::UnsupportedParameter { layer: 2 })), // post_shift 63
        (0, 7, 4, 255, Some(Error::UnsupportedParameter { layer: 0 })),
        (0, 0, 5, 200, Some(Error::UnsupportedParameter { layer: 0 })),
        (1, 6, 7, 1, Some(Error::UnsupportedParameter { layer: 1 })), // reserved byte
        (
            2,
            4,
            7,
            0x80,
            Some(Error::UnsupportedParameter { layer: 2 }),
        ),
        (0, 2, 6, 16, Some(Error::UnsupportedParameter { layer: 0 })), // ELU frac 16
        (1, 0, 6, 255, Some(Error::UnsupportedParameter { layer: 1 })),
        // Boundaries that load.
        (1, 3, 4, 62, None),
        (2, 0, 5, 62, None),
        (0, 2, 6, 15, None),
        (0, 2, 6, 0, None),
        (2, 1, 6, 200, None), // frac is only read by ELU; layer 2 is identity
        (2, 1, 4, 0, None),
    ];
    for (layer, row, byte, value, want) in cases {
        let mut p = base.clone();
        p.requant_at(layer, row)[byte] = value;
        p.reseal();
        match want {
            Some(e) => assert_eq!(
                refused(&p),
                e,
                "layer {layer} row {row} byte {byte} = {value}"
            ),
            None => assert_eq!(
                p.load(),
                Ok(()),
                "layer {layer} row {row} byte {byte} = {value}"
            ),
        }
    }
    // Negative and extreme multipliers are in range.
    for m in [i32::MIN, -1, 0, i32::MAX] {
        let mut p = base.clone();
        p.requant_at(1, 2)[..4].copy_from_slice(&m.to_le_bytes());
        p.reseal();
        assert_eq!(p.load(), Ok(()));
    }
}

/// Rows whose `sum |w| * 2^15` exceeds `i32::MAX` in a layer with 32-bit
/// accumulators; the bound is exact (65535 passes, 65536 does not).
#[test]
fn i32_rows_that_could_overflow() {
    let base = Parts::of(&hand_blob());
    let l0 = layer_of(&base.header, 0);
    // Layer 0: int16, 6 inputs, 8 rows, 5 experts. Row 5 of expert 3.
    let row_at = |expert: usize, row: usize| {
        l0.weight_section.offset as usize + ((expert * 8 + row) * 6) * 2
    };
    let cases: [(usize, usize, [i16; 6], bool); 6] = [
        (3, 5, [32767, 32767, 2, 0, 0, 0], false),
        (3, 5, [32767, 32767, 1, 0, 0, 0], true),
        (3, 5, [-32768, -32767, 0, 0, 0, 0], true), // 65535
        (3, 5, [-32768, -32768, 0, 0, 0, 0], false), // 65536
        (0, 0, [16384, -16384, 16384, -16384, 1, 0], false),
        (4, 7, [10923, -10923, 10923, -10923, 10923, -10920], true), // 65535
    ];
    for (expert, row, w, ok) in cases {
        let mut p = base.clone();
        let at = row_at(expert, row);
        for (j, v) in w.iter().enumerate() {
            p.payload[at + 2 * j..at + 2 * j + 2].copy_from_slice(&v.to_le_bytes());
        }
        p.reseal();
        if ok {
            assert_eq!(p.load(), Ok(()), "{w:?}");
        } else {
            assert_eq!(
                refused(&p),
                Error::AccumulatorOverflow {
                    layer: 0,
                    row: row as u16
                },
                "{w:?}"
            );
        }
    }
    // With 64-bit accumulators the same row is fine.
    let mut m = hand_model();
    m.layers[0].desc.acc = AccWidth::I64;
    m.layers[0].weights[(3 * 8 + 5) * 6..][..6]
        .copy_from_slice(&[32767, 32767, 32767, 32767, 32767, 32767]);
    assert!(Model::from_bytes(&encode(&m).unwrap()).is_ok());
    m.layers[0].desc.acc = AccWidth::I32;
    assert_eq!(
        Model::from_bytes(&encode(&m).unwrap()).unwrap_err(),
        Error::AccumulatorOverflow { layer: 0, row: 5 }
    );
}

#[test]
fn non_finite_stage_records() {
    let base = Parts::of(&hand_blob());
    let input = base.header.input_stage.offset as usize;
    let output = base.header.output_stage.offset as usize;
    for (at, v, ok) in [
        (input + 2 * 8, f32::NAN, false),          // offset of input 2
        (input + 5 * 8 + 4, f32::INFINITY, false), // scale of input 5
        (output, f32::NEG_INFINITY, false),        // scale of output 0
        (output + 4 * 8 + 4, -f32::NAN, false),    // offset of output 4
        (input, f32::MAX, true),
        (input + 4, 0.0, true),
        (output + 4, f32::MIN_POSITIVE / 4.0, true),
    ] {
        let mut p = base.clone();
        p.payload[at..at + 4].copy_from_slice(&v.to_le_bytes());
        p.reseal();
        if ok {
            assert_eq!(p.load(), Ok(()), "{v} at {at}");
        } else {
            assert_eq!(
                refused(&p),
                Error::UnsupportedParameter { layer: STAGE },
                "{v} at {at}"
            );
        }
    }
}

#[test]
fn payload_length_that_lies() {
    let blob = hand_blob();
    let base = Parts::of(&blob);
    let mut p = base.clone();
    p.header.payload_len += 4;
    let framed = p.blob();
    let want = Error::Truncated {
        needed: blob.len() as u32 + 4,
        available: blob.len() as u32,
    };
    assert_eq!(Model::from_bytes(&framed).unwrap_err(), want);
    assert_eq!(Model::from_region(&framed).unwrap_err(), want);

    let mut p = base.clone();
    p.header.payload_len -= 4;
    let framed = p.blob();
    let want = Error::TrailingBytes {
        blob_len: blob.len() as u32 - 4,
        found: blob.len() as u32,
    };
    assert_eq!(Model::from_bytes(&framed).unwrap_err(), want);
    assert_eq!(
        Model::from_region(&framed).unwrap_err(),
        Error::PayloadCorrupt
    );

    // Shorter payload with a CRC that matches it: the last section now ends
    // past the payload.
    let mut p = base.clone();
    p.payload.truncate(p.payload.len() - 4);
    p.reseal();
    assert_eq!(refused(&p), Error::SectionOutOfBounds { layer: 2 });
}

#[test]
fn headers_that_do_not_decode() {
    let blob = hand_blob();
    let p = Parts::of(&blob);
    let header = postcard::to_allocvec(&p.header).unwrap();
    assert_eq!(frame_raw(&header, &p.payload), blob);
    let malformed = |h: &[u8]| {
        let b = frame_raw(h, &p.payload);
        assert_eq!(
            Model::from_bytes(&b).unwrap_err(),
            Error::HeaderMalformed,
            "{h:02x?}"
        );
        assert_eq!(
            blob_len_from_prefix(&b).unwrap_err(),
            Error::HeaderMalformed
        );
    };
    // Bytes after the header (within the header length).
    malformed(&[header.clone(), vec![0]].concat());
    // Empty and cut-short headers.
    malformed(&[]);
    malformed(&header[..header.len() - 1]);
    malformed(&header[..3]);
    // Unknown enum variants: kind (byte 0; 0-3 are taken), gating (byte 1;
    // 0-4 are taken).
    assert_eq!(header[..3], [0x00, 0x03, 0x05]);
    for (at, v) in [(0, 4u8), (0, 0x7f), (1, 5), (1, 0x80)] {
        let mut h = header.clone();
        h[at] = v;
        malformed(&h);
    }
    // Gating 4 is `Softmax { experts: 5 }`: it decodes, but only a softmax
    // gate node can drive it, never the header.
    let mut h = header.clone();
    h[1] = 4;
    assert_eq!(
        Model::from_bytes(&frame_raw(&h, &p.payload)).unwrap_err(),
        Error::UnsupportedParameter { layer: STAGE }
    );
    // Node 0 starts at byte 6 (kind, gating tag, points, input, output,
    // count): its op tag (Layer), then the layer's op, in, out, experts,
    // weights, acc, activation.
    assert_eq!(
        header[5..14],
        [0x03, 0x00, 0x00, 0x06, 0x08, 0x05, 0x01, 0x00, 0x01]
    );
    // Unknown node op (0-1 are taken), layer op (0-2), weight format
    // (0-2), accumulator, activation.
    for (at, v) in [(6, 2u8), (7, 3), (11, 3), (12, 2), (13, 2), (13, 0xff)] {
        let mut h = header.clone();
        h[at] = v;
        malformed(&h);
    }
    // More nodes than a header holds: the node count says 25.
    let h = &p.header;
    let many: Vec<Node> = vec![h.nodes[0].clone(); phasegate::blob::MAX_NODES + 1];
    let too_many = postcard::to_allocvec(&(
        h.kind,
        h.gating,
        h.input_dim,
        h.output_dim,
        many,
        h.input,
        h.output,
        h.input_stage,
        h.output_stage,
        (h.ram_bytes, h.macs_per_frame, h.payload_len, h.payload_crc),
    ))
    .unwrap();
    malformed(&too_many);
    // Non-zero padding between header and payload.
    let end = 12 + header.len();
    assert!(end < payload_start(&blob), "the hand blob has padding");
    for at in end..payload_start(&blob) {
        let mut b = blob.clone();
        b[at] = 1;
        assert_eq!(Model::from_bytes(&b).unwrap_err(), Error::HeaderMalformed);
    }
}
