//! Pins the blob format of `docs/blob-format.md` (format version 2).
//!
//! * The byte-level example of the document, built with the real encoder,
//!   must equal the hex table below byte for byte, load, and run to the value
//!   the document computes by hand; the document must show the same bytes.
//! * The postcard encodings the document lists are checked against postcard.
//! * A header decoder written from the document alone (`spec`, below) must
//!   agree with the runtime on the example, on real blobs (chains and
//!   graphs with concatenations and a softmax gate) and on random headers.
//! * Blobs of other format versions are refused with `UnsupportedVersion`
//!   before anything else is read: the version-1 record
//!   (`fixtures/example-v1.blob`, never regenerated), `fixtures/version0.blob`
//!   and generated version-3 blobs. `fixtures/example-v2.blob` (the example)
//!   must keep loading and running to the documented value.
//!
//! `PHASEGATE_BLESS=1 cargo test -p phasegate-tests --test blob_format`
//! rewrites the version-2 fixtures: `tests/fixtures/example-v2.blob` (only
//! ever needed when the example changes, which is a format change: see the
//! document) and the rig pair (when the exporter quantises its small model
//! differently). The version-1 and version-0 fixtures are records and are
//! never rewritten.

use std::path::PathBuf;

use exporter::encode::{encode, frame, QKind, QLayer, QModel, QNode, QNodeOp, Wiring};
use phasegate::blob::{
    crc32, AccWidth, Activation, GateSource, Gating, Header, LayerDesc, LayerOp, ModelKind, Node,
    NodeOp, Requant, Section, Slice, SoftmaxDesc, Source, Span, WeightFormat, FORMAT_VERSION,
    MAGIC, MAX_NODES, MAX_NODE_INPUTS, PAYLOAD_ALIGN, PREAMBLE_LEN,
};
use phasegate::{blob_len_from_prefix, Error, Model, Phase, Runtime, MAX_GATES};
use proptest::prelude::*;

/// The example blob of `docs/blob-format.md`, section "Byte-level example".
/// Offsets on the left; the document annotates every byte.
const EXAMPLE_HEX: &str = "
    0000: 50 47 4d 42 02 00 30 00 cc 47 92 d2 01 00 02 01
    0010: 01 00 00 02 01 01 00 00 00 18 02 1c 04 20 08 01
    0020: 00 00 02 00 00 02 00 00 02 01 00 02 01 00 00 01
    0030: 00 10 10 08 06 02 28 d7 aa f7 e9 03 00 00 00 00
    0040: 00 00 00 00 00 00 80 43 00 00 80 3f 00 00 00 43
    0050: 00 00 00 3c 00 00 20 c0 64 ce 00 00 e8 03 00 00
    0060: 00 00 00 50 03 2f 00 00
";

/// The byte-level example of format version 1 (the same model), as the
/// version-1 document showed it: the record kept in
/// `tests/fixtures/example-v1.blob`. Never changes.
const EXAMPLE_V1_HEX: &str = "
    0000: 50 47 4d 42 01 00 1f 00 1b 10 08 37 01 00 02 01
    0010: 01 00 02 01 01 00 00 00 00 18 02 1c 04 20 08 00
    0020: 10 10 08 08 02 28 d7 aa f7 e9 03 00 00 00 00 00
    0030: 00 00 00 00 00 00 80 43 00 00 80 3f 00 00 00 43
    0040: 00 00 00 3c 00 00 20 c0 64 ce 00 00 e8 03 00 00
    0050: 00 00 00 50 03 2f 00 00
";

/// Parses `EXAMPLE_HEX`-style text: `offset:` prefixes are checked and dropped.
fn hex(text: &str) -> Vec<u8> {
    let mut out = Vec::new();
    for line in text.lines().map(str::trim).filter(|l| !l.is_empty()) {
        let (offset, bytes) = line.split_once(':').expect("offset: bytes");
        assert_eq!(
            usize::from_str_radix(offset, 16).unwrap(),
            out.len(),
            "offset of {line:?}"
        );
        out.extend(
            bytes
                .split_whitespace()
                .map(|b| u8::from_str_radix(b, 16).unwrap()),
        );
    }
    out
}

fn dump(blob: &[u8]) -> String {
    blob.chunks(16)
        .enumerate()
        .map(|(i, c)| {
            format!(
                "{:04x}: {}\n",
                i * 16,
                c.iter()
                    .map(|b| format!("{b:02x}"))
                    .collect::<Vec<_>>()
                    .join(" ")
            )
        })
        .collect()
}

fn empty() -> Section {
    Section::default()
}

fn span(offset: u16, len: u16) -> Span {
    Span { offset, len }
}

fn slice(source: Source, start: u16, len: u16) -> Slice {
    Slice { source, start, len }
}

/// The document's example model: no phase, two inputs, one int8 dense
/// neuron with a 32-bit accumulator and no activation.
fn example_model() -> QModel {
    QModel {
        kind: QKind::Model(ModelKind::Mlp),
        gating: Gating::Single,
        input_stage: vec![(0.0, 256.0), (1.0, 128.0)],
        output_stage: vec![(0.0078125, -2.5)],
        layers: vec![QLayer {
            desc: LayerDesc {
                op: LayerOp::Dense,
                in_dim: 2,
                out_dim: 1,
                experts: 1,
                weights: WeightFormat::I8,
                acc: AccWidth::I32,
                activation: Activation::Identity,
                weight_section: empty(),
                bias_section: empty(),
                requant_section: empty(),
            },
            weights: vec![100, -50],
            bias: vec![1000],
            requant: vec![Requant {
                multiplier: 0x5000_0000,
                pre_shift: 3,
                post_shift: 47,
                frac: 0,
            }],
            cp: None,
            rbf: None,
            gated: false,
        }],
        wiring: Wiring::Chain,
    }
}

fn example_blob() -> Vec<u8> {
    encode(&example_model()).unwrap()
}

#[test]
fn example_bytes_are_pinned() {
    let blob = example_blob();
    let expected = hex(EXAMPLE_HEX);
    if blob != expected {
        panic!(
            "example blob changed; the encoder now writes ({} bytes):\n{}",
            blob.len(),
            dump(&blob)
        );
    }
    assert_eq!(blob.len(), 104);
}

#[test]
fn example_header_is_what_the_document_says() {
    let blob = hex(EXAMPLE_HEX);
    let model = Model::from_bytes(&blob).unwrap();
    let h = model.header().decoded();
    assert_eq!(h.kind, ModelKind::Mlp);
    assert_eq!(h.gating, Gating::Single);
    assert_eq!((h.input_dim, h.output_dim), (2, 1));
    assert_eq!(h.nodes.len(), 1);
    let n = &h.nodes[0];
    let NodeOp::Layer(l) = n.op else {
        panic!("node 0 is a layer")
    };
    assert_eq!(
        (l.op, l.in_dim, l.out_dim, l.experts),
        (LayerOp::Dense, 2, 1, 1)
    );
    assert_eq!(
        (l.weights, l.acc, l.activation),
        (WeightFormat::I8, AccWidth::I32, Activation::Identity)
    );
    assert_eq!(l.weight_section, Section { offset: 24, len: 2 });
    assert_eq!(l.bias_section, Section { offset: 28, len: 4 });
    assert_eq!(l.requant_section, Section { offset: 32, len: 8 });
    assert_eq!(n.inputs.as_slice(), &[slice(Source::Input, 0, 2)]);
    assert_eq!(n.gate, GateSource::None);
    // One input slice: read in place, so the node's input span is the
    // model input's; no scratch; the output after the input.
    assert_eq!(
        (n.input, n.scratch, n.output),
        (span(0, 2), span(0, 0), span(2, 1))
    );
    assert_eq!(h.input, span(0, 2));
    assert_eq!(h.output, slice(Source::Node(0), 0, 1));
    assert_eq!(h.input_stage, Section { offset: 0, len: 16 });
    assert_eq!(h.output_stage, Section { offset: 16, len: 8 });
    assert_eq!((h.ram_bytes, h.macs_per_frame), (6, 2));
    assert_eq!((h.payload_len, h.payload_crc), (40, 0x3D3D_D557));
    assert_eq!(model.blob_len(), 104);
    assert_eq!(model.arena_elements(), 3);
    // Preamble: version 2, header length 48, header CRC over bytes 0..8 and the header.
    assert_eq!(&blob[4..6], &2u16.to_le_bytes());
    assert_eq!(&blob[6..8], &48u16.to_le_bytes());
    let crc = crc32(
        &blob[..8]
            .iter()
            .chain(&blob[12..60])
            .copied()
            .collect::<Vec<_>>(),
    );
    assert_eq!(&blob[8..12], &crc.to_le_bytes());
    assert_eq!(crc, EXAMPLE_HEADER_CRC);
    assert!(blob[60..64].iter().all(|&b| b == 0));
    assert_eq!(crc32(&blob[64..]), 0x3D3D_D557);
    // The payload is the version-1 example's, unchanged.
    assert_eq!(&blob[64..], &hex(EXAMPLE_V1_HEX)[48..]);
    assert_eq!(blob_len_from_prefix(&blob[..60]), Ok(104));
}

/// The header CRC of the example (document: "Every byte", offset 8).
const EXAMPLE_HEADER_CRC: u32 = 0xD292_47CC;

/// The hand computation of the document's "Running the example" section.
#[test]
fn example_runs_to_the_hand_computed_value() {
    let blob = hex(EXAMPLE_HEX);
    // The arena is 3 elements (ram_bytes 6): input at 0..2, output at 2..3.
    assert_eq!(
        Runtime::<'_, 2>::new(Model::from_bytes(&blob).unwrap()).err(),
        Some(Error::BufferTooSmall {
            needed: 3,
            capacity: 2
        })
    );
    let model = Model::from_bytes(&blob).unwrap();
    assert_eq!(Runtime::<0>::required_elements(&model), 3);
    let mut rt: Runtime<'_, 3> = Runtime::new(model).unwrap();
    let x = [1.5f32, -0.25];

    // Input stage: q0 = (1.5 - 0) * 256 = 384, q1 = (-0.25 - 1) * 128 = -160.
    let mut q = [0i16; 2];
    rt.quantise_input(&x, &mut q).unwrap();
    assert_eq!(q, [384, -160]);

    // acc = 100*384 + (-50)*(-160) = 46400; + bias 1000 = 47400;
    // total = 47400 * 65536 = 3106406400; >> 3 (round) = 388300800;
    // * 0x50000000 = 521168511565824000; >> 47 (round half up) = 3703.125 -> 3703.
    let acc: i64 = 100 * 384 + (-50) * (-160);
    assert_eq!(acc, 46_400);
    let total = (acc + 1000) * 65_536;
    assert_eq!(total, 3_106_406_400);
    let t = (total + 4) >> 3;
    assert_eq!(t, 388_300_800);
    let prod = t * 0x5000_0000;
    assert_eq!(prod, 521_168_511_565_824_000);
    assert_eq!((prod + (1 << 46)) >> 47, 3703);
    for phase in [0u32, 1, 0x8000_0000, u32::MAX] {
        assert_eq!(
            rt.run_quantised(Phase::from_bits(phase), &q).unwrap(),
            &[3703]
        );
    }

    // Output stage: y = 3703 * (1/128) + (-2.5) = 26.4296875 (exact in f32).
    let mut y = [0f32; 1];
    rt.run(Phase::from_bits(0), &x, &mut y).unwrap();
    assert_eq!(y, [3703.0 / 128.0 - 2.5]); // 26.4296875
    assert_eq!(f64::from(y[0]), 26.4296875);
}

#[test]
fn crc32_is_iso_hdlc() {
    // The standard check value of CRC-32/ISO-HDLC (zlib.crc32, PNG, Ethernet).
    assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    assert_eq!(crc32(b""), 0);
    assert_eq!(crc32(b"a"), 0xE8B7_BE43);
}

/// Every encoding example in the document's postcard section.
#[test]
fn postcard_encodings_match_the_document() {
    fn enc<T: serde::Serialize>(v: &T) -> Vec<u8> {
        postcard::to_allocvec(v).unwrap()
    }
    // Unsigned varints (u16, u32): LEB128, shortest form.
    assert_eq!(enc(&0u16), [0x00]);
    assert_eq!(enc(&127u16), [0x7f]);
    assert_eq!(enc(&128u16), [0x80, 0x01]);
    assert_eq!(enc(&300u16), [0xac, 0x02]);
    assert_eq!(enc(&342u16), [0xd6, 0x02]);
    assert_eq!(enc(&u16::MAX), [0xff, 0xff, 0x03]);
    assert_eq!(enc(&16_384u32), [0x80, 0x80, 0x01]);
    assert_eq!(enc(&u32::MAX), [0xff, 0xff, 0xff, 0xff, 0x0f]);
    // Signed varints are zigzag (not used by the header, listed for completeness).
    assert_eq!(enc(&-1i32), [0x01]);
    assert_eq!(enc(&1i32), [0x02]);
    assert_eq!(enc(&-64i16), [0x7f]);
    assert_eq!(enc(&64i16), [0x80, 0x01]);
    // bool: one byte.
    assert_eq!(enc(&false), [0x00]);
    assert_eq!(enc(&true), [0x01]);
    // Enums: varint variant index, then the variant's fields.
    assert_eq!(enc(&ModelKind::Pfnn), [0x00]);
    assert_eq!(enc(&ModelKind::Mlp), [0x01]);
    assert_eq!(enc(&ModelKind::Graph), [0x03]);
    assert_eq!(enc(&Gating::Single), [0x00]);
    assert_eq!(enc(&Gating::Constant { tables: 50 }), [0x01, 0x32]);
    assert_eq!(enc(&Gating::Linear { tables: 10 }), [0x02, 0x0a]);
    assert_eq!(enc(&Gating::CatmullRom { points: 4 }), [0x03, 0x04]);
    assert_eq!(enc(&Gating::Linear { tables: 300 }), [0x02, 0xac, 0x02]);
    assert_eq!(enc(&Gating::Softmax { experts: 8 }), [0x04, 0x08]);
    assert_eq!(enc(&WeightFormat::I8), [0x00]);
    assert_eq!(enc(&WeightFormat::I16), [0x01]);
    assert_eq!(enc(&AccWidth::I32), [0x00]);
    assert_eq!(enc(&AccWidth::I64), [0x01]);
    assert_eq!(enc(&Activation::Identity), [0x00]);
    assert_eq!(enc(&Activation::Elu), [0x01]);
    assert_eq!(enc(&LayerOp::Dense), [0x00]);
    assert_eq!(enc(&LayerOp::Diagonal), [0x02]);
    let cp = LayerOp::Cp {
        rank: 3,
        a: Section { offset: 0, len: 4 },
        cores: Section { offset: 4, len: 8 },
        mid: Section {
            offset: 12,
            len: 24,
        },
    };
    assert_eq!(enc(&cp), [0x01, 0x03, 0x00, 0x04, 0x04, 0x08, 0x0c, 0x18]);
    // RBF and DEC share their sections' layout; only the index differs.
    let scales = Section {
        offset: 16,
        len: 128,
    };
    let align = Section {
        offset: 144,
        len: 32,
    };
    let rbf = LayerOp::Rbf { scales, align };
    assert_eq!(enc(&rbf), [0x03, 0x10, 0x80, 0x01, 0x90, 0x01, 0x20]);
    let dec = LayerOp::Dec { scales, align };
    assert_eq!(enc(&dec), [0x04, 0x10, 0x80, 0x01, 0x90, 0x01, 0x20]);
    // u8 is one raw byte, not a varint (200 would be c8 01 as a varint).
    let style = ModelKind::Style {
        base_crc: 1,
        layer: 200,
        name: Section { offset: 0, len: 5 },
    };
    assert_eq!(enc(&style), [0x02, 0x01, 0xc8, 0x00, 0x05]);
    assert_eq!(enc(&Source::Input), [0x00]);
    assert_eq!(enc(&Source::Node(200)), [0x01, 0xc8]);
    assert_eq!(enc(&GateSource::None), [0x00]);
    assert_eq!(enc(&GateSource::Phase), [0x01]);
    assert_eq!(enc(&GateSource::Node(2)), [0x02, 0x02]);
    // Structs: fields in order, nothing else.
    assert_eq!(
        enc(&Section {
            offset: 1024,
            len: 36_936
        }),
        [0x80, 0x08, 0xc8, 0xa0, 0x02]
    );
    assert_eq!(enc(&span(342, 32)), [0xd6, 0x02, 0x20]);
    assert_eq!(
        enc(&slice(Source::Node(1), 128, 3)),
        [0x01, 0x01, 0x80, 0x01, 0x03]
    );
    assert_eq!(
        enc(&SoftmaxDesc {
            experts: 8,
            frac: 200
        }),
        [0x08, 0xc8]
    );
    assert_eq!(
        enc(&NodeOp::Softmax(SoftmaxDesc {
            experts: 4,
            frac: 7
        })),
        [0x01, 0x04, 0x07]
    );
    // heapless::Vec: varint length, then the elements.
    let mut v = heapless::Vec::<Section, 4>::new();
    v.push(Section { offset: 4, len: 8 }).unwrap();
    v.push(Section { offset: 12, len: 0 }).unwrap();
    assert_eq!(enc(&v), [0x02, 0x04, 0x08, 0x0c, 0x00]);
    // A whole softmax node: op, inputs, gate, input, scratch, output.
    let node = Node {
        op: NodeOp::Softmax(SoftmaxDesc {
            experts: 4,
            frac: 7,
        }),
        inputs: [slice(Source::Node(0), 0, 2), slice(Source::Node(1), 0, 2)]
            .into_iter()
            .collect(),
        gate: GateSource::None,
        input: span(10, 4),
        scratch: span(0, 0),
        output: span(0, 0),
    };
    assert_eq!(
        enc(&node),
        [
            0x01, 0x04, 0x07, // op: Softmax { experts 4, frac 7 }
            0x02, // two input slices
            0x01, 0x00, 0x00, 0x02, // Node(0)[0..2]
            0x01, 0x01, 0x00, 0x02, // Node(1)[0..2]
            0x00, // gate: None
            0x0a, 0x04, 0x00, 0x00, 0x00, 0x00 // input 10+4, scratch, output
        ]
    );
}

/// What the document says about varints a writer should not produce.
#[test]
fn padded_varints_load_and_overlong_ones_do_not() {
    let blob = example_blob();
    let payload = &blob[64..];
    let header =
        postcard::to_allocvec(&Model::from_bytes(&blob).unwrap().header().decoded()).unwrap();
    // Byte 2 of the header is input_dim = 2, encoded 0x02. Padded: 0x82 0x00.
    assert_eq!(header[2], 0x02);
    let mut padded = header.clone();
    padded.splice(2..3, [0x82, 0x00]);
    let padded_blob = frame_raw(2, &padded, payload);
    let m = Model::from_bytes(&padded_blob).unwrap();
    assert_eq!(m.header().input_dim, 2);
    // A u16 varint may not take more than 3 bytes, and its third byte may not exceed 0x03.
    let mut overlong = header.clone();
    overlong.splice(2..3, [0x82, 0x80, 0x80, 0x00]);
    assert_eq!(
        Model::from_bytes(&frame_raw(2, &overlong, payload)).unwrap_err(),
        Error::HeaderMalformed
    );
    let mut too_big = header.clone();
    too_big.splice(2..3, [0x82, 0x80, 0x04]);
    assert_eq!(
        Model::from_bytes(&frame_raw(2, &too_big, payload)).unwrap_err(),
        Error::HeaderMalformed
    );
    // More than 24 nodes: the node count 25 is refused while decoding.
    let mut many = header.clone();
    assert_eq!(many[4], 0x01);
    many[4] = 25;
    assert_eq!(
        Model::from_bytes(&frame_raw(2, &many, payload)).unwrap_err(),
        Error::HeaderMalformed
    );
    // An unknown enum index (Softmax is never a header's gating, but it
    // decodes; index 5 does not).
    let mut gating = header.clone();
    gating[1] = 0x05;
    assert_eq!(
        Model::from_bytes(&frame_raw(2, &gating, payload)).unwrap_err(),
        Error::HeaderMalformed
    );
    gating[1] = 0x04; // Softmax { experts: 2 } (the next byte is input_dim)
    assert_eq!(
        Model::from_bytes(&frame_raw(2, &gating, payload)).unwrap_err(),
        Error::HeaderMalformed
    );
    // A trailing byte after the header.
    let mut trailing = header.clone();
    trailing.push(0);
    assert_eq!(
        Model::from_bytes(&frame_raw(2, &trailing, payload)).unwrap_err(),
        Error::HeaderMalformed
    );
}

/// Frames raw header bytes exactly as the document's preamble section says,
/// independently of `exporter::encode::frame`.
fn frame_raw(version: u16, header: &[u8], payload: &[u8]) -> Vec<u8> {
    let mut out = b"PGMB".to_vec();
    out.extend(version.to_le_bytes());
    out.extend(u16::try_from(header.len()).unwrap().to_le_bytes());
    let crc = crc32(&out.iter().chain(header).copied().collect::<Vec<_>>());
    out.extend(crc.to_le_bytes());
    out.extend(header);
    while !out.len().is_multiple_of(16) {
        out.push(0);
    }
    out.extend(payload);
    out
}

/// Re-frames a decoded header (possibly edited) with the example's payload.
fn reframe(h: &Header, payload: &[u8]) -> Vec<u8> {
    frame_raw(2, &postcard::to_allocvec(h).unwrap(), payload)
}

/// The example's header with one field edited gives the error the document's
/// loader table says.
#[test]
fn the_loader_checks_of_the_document() {
    let blob = example_blob();
    let payload = blob[64..].to_vec();
    let base = Model::from_bytes(&blob).unwrap().header().decoded();
    let check = |edit: &dyn Fn(&mut Header), want: Error| {
        let mut h = base.clone();
        edit(&mut h);
        assert_eq!(
            Model::from_bytes(&reframe(&h, &payload)).unwrap_err(),
            want,
            "{h:?}"
        );
    };
    let layer = |h: &mut Header| -> LayerDesc {
        match h.nodes[0].op {
            NodeOp::Layer(d) => d,
            NodeOp::Softmax(_) => unreachable!(),
        }
    };
    check(
        &|h| {
            h.kind = ModelKind::Style {
                base_crc: 0,
                layer: 0,
                name: empty(),
            }
        },
        Error::NotAModel,
    );
    check(
        &|h| h.gating = Gating::Softmax { experts: 1 },
        Error::UnsupportedParameter { layer: 255 },
    );
    check(
        &|h| h.gating = Gating::CatmullRom { points: 3 },
        Error::UnsupportedParameter { layer: 255 },
    );
    check(
        &|h| h.nodes.clear(),
        Error::UnsupportedParameter { layer: 255 },
    );
    check(
        &|h| h.input.len = 3,
        Error::DimensionMismatch { layer: 255 },
    );
    // Slices: earlier sources only, non-empty, inside the source.
    check(
        &|h| h.nodes[0].inputs[0].source = Source::Node(0),
        Error::GraphInvalid { node: 0 },
    );
    check(
        &|h| h.nodes[0].inputs[0].start = 1,
        Error::GraphInvalid { node: 0 },
    );
    check(
        &|h| h.nodes[0].inputs.clear(),
        Error::GraphInvalid { node: 0 },
    );
    // Widths.
    check(
        &|h| {
            h.nodes[0].inputs[0].len = 1;
            h.nodes[0].input.len = 1;
        },
        Error::DimensionMismatch { layer: 0 },
    );
    check(
        &|h| h.nodes[0].output.len = 2,
        Error::DimensionMismatch { layer: 0 },
    );
    // A single slice is read in place: the node's input span is where it lies.
    check(
        &|h| h.nodes[0].input.offset = 1,
        Error::ArenaOverlap { node: 0 },
    );
    // Gate sources.
    check(
        &|h| h.nodes[0].gate = GateSource::Node(0),
        Error::GraphInvalid { node: 0 },
    );
    // (A phase gate with `Gating::Single` is one expert: valid.)
    let mut h = base.clone();
    h.nodes[0].gate = GateSource::Phase;
    assert!(Model::from_bytes(&reframe(&h, &payload)).is_ok());
    // The output slice.
    check(
        &|h| h.output.source = Source::Node(1),
        Error::GraphInvalid { node: 255 },
    );
    check(
        &|h| h.output.len = 0,
        Error::DimensionMismatch { layer: 255 },
    );
    // Per layer: experts, sections.
    check(
        &|h| {
            let mut d = layer(h);
            d.experts = 2;
            h.nodes[0].op = NodeOp::Layer(d);
        },
        Error::GatingMismatch { layer: 0 },
    );
    check(
        &|h| {
            let mut d = layer(h);
            d.bias_section.offset = 26;
            h.nodes[0].op = NodeOp::Layer(d);
        },
        Error::SectionOutOfBounds { layer: 0 },
    );
    check(
        &|h| {
            let mut d = layer(h);
            d.weight_section.len = 3;
            h.nodes[0].op = NodeOp::Layer(d);
        },
        Error::SectionLength { layer: 0 },
    );
    // Stages.
    check(
        &|h| h.output_stage.offset = 36,
        Error::SectionOutOfBounds { layer: 255 },
    );
    check(
        &|h| h.input_stage.len = 8,
        Error::SectionLength { layer: 255 },
    );
    // The plan.
    check(
        &|h| h.nodes[0].output.offset = 1,
        Error::ArenaOverlap { node: 0 },
    );
    check(&|h| h.ram_bytes = 8, Error::HeaderInconsistent);
    check(&|h| h.macs_per_frame = 3, Error::HeaderInconsistent);
    // A plan that reuses nothing is fine as long as ram_bytes is exact.
    let mut h = base.clone();
    h.nodes[0].output.offset = 5;
    h.ram_bytes = 12;
    assert!(Model::from_bytes(&reframe(&h, &payload)).is_ok());
}

/// The hex block of `docs/blob-format.md` is `EXAMPLE_HEX`.
#[test]
fn the_document_shows_the_pinned_bytes() {
    let doc = std::fs::read_to_string(
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../docs/blob-format.md"),
    )
    .unwrap();
    let dump: String = doc
        .lines()
        .filter(|l| {
            let b = l.as_bytes();
            b.len() > 6 && b[4] == b':' && b[..4].iter().all(u8::is_ascii_hexdigit)
        })
        .map(|l| format!("{l}\n"))
        .collect();
    assert_eq!(hex(&dump), hex(EXAMPLE_HEX));
    assert!(doc.contains("# The phasegate blob format, version 2"));
}

/// The largest header any `Header` value encodes to: every varint at its
/// longest, the longest enum variants, 24 CP layer nodes of four input
/// slices each, gated by a node.
#[test]
fn largest_header_size() {
    let s = Section {
        offset: u32::MAX,
        len: u32::MAX,
    };
    let sp = span(u16::MAX, u16::MAX);
    let sl = slice(Source::Node(u8::MAX), u16::MAX, u16::MAX);
    let layer = LayerDesc {
        op: LayerOp::Cp {
            rank: u16::MAX,
            a: s,
            cores: s,
            mid: s,
        },
        in_dim: u16::MAX,
        out_dim: u16::MAX,
        experts: u16::MAX,
        weights: WeightFormat::I16,
        acc: AccWidth::I64,
        activation: Activation::Elu,
        weight_section: s,
        bias_section: s,
        requant_section: s,
    };
    let node = Node {
        op: NodeOp::Layer(layer),
        inputs: std::iter::repeat_n(sl, MAX_NODE_INPUTS).collect(),
        gate: GateSource::Node(u8::MAX),
        input: sp,
        scratch: sp,
        output: sp,
    };
    assert_eq!(postcard::to_allocvec(&node).unwrap().len(), 130);
    let h: Header = Header {
        kind: ModelKind::Style {
            base_crc: u32::MAX,
            layer: u8::MAX,
            name: s,
        },
        gating: Gating::CatmullRom { points: u16::MAX },
        input_dim: u16::MAX,
        output_dim: u16::MAX,
        nodes: std::iter::repeat_n(node, MAX_NODES).collect(),
        input: sp,
        output: sl,
        input_stage: s,
        output_stage: s,
        ram_bytes: u32::MAX,
        macs_per_frame: u32::MAX,
        payload_len: u32::MAX,
        payload_crc: u32::MAX,
    };
    assert_eq!(postcard::to_allocvec(&h).unwrap().len(), 3202);
}

#[test]
fn constants_are_the_documented_ones() {
    assert_eq!(MAGIC, *b"PGMB");
    assert_eq!(FORMAT_VERSION, 2);
    assert_eq!((PREAMBLE_LEN, PAYLOAD_ALIGN), (12, 16));
    assert_eq!((MAX_NODES, MAX_NODE_INPUTS, MAX_GATES), (24, 4, 2));
    assert_eq!(phasegate::STAGE, 255);
    assert_eq!(phasegate::graph::IO, 255);
    let blob = example_blob();
    let header =
        postcard::to_allocvec(&Model::from_bytes(&blob).unwrap().header().decoded()).unwrap();
    assert_eq!(frame_raw(2, &header, &blob[64..]), blob);
}

// ---------------------------------------------------------------------------
// Format versions.

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures")
        .join(name)
}

/// `blob` with another version number, header CRC recomputed.
fn with_version(blob: &[u8], version: u16) -> Vec<u8> {
    let mut b = blob.to_vec();
    b[4..6].copy_from_slice(&version.to_le_bytes());
    let header_len = usize::from(u16::from_le_bytes([b[6], b[7]]));
    let crc = crc32(
        &b[..8]
            .iter()
            .chain(&b[12..12 + header_len])
            .copied()
            .collect::<Vec<_>>(),
    );
    b[8..12].copy_from_slice(&crc.to_le_bytes());
    b
}

/// The checked-in fixtures are what they should be. `PHASEGATE_BLESS=1`
/// rewrites the version-2 ones only: `example-v1.blob` and `version0.blob`
/// are records of versions this runtime refuses and never change.
#[test]
fn fixtures_are_current() {
    let v1 = hex(EXAMPLE_V1_HEX);
    let (motion, rig) = phasegate_tests::fuzz::small_rig_pair();
    let wanted = [
        ("example-v2.blob", example_blob(), true),
        ("rig-motion-v2.blob", motion, true),
        ("rig-v2.blob", rig, true),
        ("example-v1.blob", v1.clone(), false),
        ("version0.blob", with_version(&v1, 0), false),
    ];
    for (name, bytes, blessable) in wanted {
        let path = fixture(name);
        if blessable && std::env::var_os("PHASEGATE_BLESS").is_some() {
            std::fs::write(&path, &bytes).unwrap();
        }
        let on_disk = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert_eq!(
            on_disk, bytes,
            "{name} differs from what it should be (only the version-2 fixtures may be rewritten, with PHASEGATE_BLESS=1)"
        );
    }
}

/// The version-2 example must keep loading and running to the documented value.
#[test]
fn version2_fixture_loads_and_runs() {
    let blob = std::fs::read(fixture("example-v2.blob")).unwrap();
    assert_eq!(blob, hex(EXAMPLE_HEX));
    let model = Model::from_bytes(&blob).unwrap();
    let mut rt: Runtime<'_, 3> = Runtime::new(model).unwrap();
    let mut y = [0f32];
    rt.run(Phase::from_bits(0), &[1.5, -0.25], &mut y).unwrap();
    assert_eq!(y, [3703.0 / 128.0 - 2.5]); // 26.4296875
}

/// The version-2 rig fixture (a small motion blob and a rig blob of its
/// own encoder and decoder) must keep loading as a pair and computing what
/// the motion blob computes alone, the outputs pinned by their CRC.
#[test]
fn version2_rig_fixture_loads_and_runs() {
    let motion = std::fs::read(fixture("rig-motion-v2.blob")).unwrap();
    let rig = std::fs::read(fixture("rig-v2.blob")).unwrap();
    let run = |model: Model<'_>| -> Vec<i16> {
        let mut rt: Box<Runtime<'_, 4096>> = Box::new(Runtime::new(model).unwrap());
        let n = rt.model().input_dim();
        let mut out = Vec::new();
        for k in 0..8i32 {
            let q: Vec<i16> = (0..n as i32)
                .map(|i| ((i * 977 + k * 331) % 4001 - 2000) as i16)
                .collect();
            out.extend_from_slice(rt.run_quantised(Phase::from_bits(0), &q).unwrap());
        }
        out
    };
    let pair = run(Model::with_rig(&motion, &rig).unwrap());
    assert_eq!(pair, run(Model::from_bytes(&motion).unwrap()));
    let bytes: Vec<u8> = pair.iter().flat_map(|v| v.to_le_bytes()).collect();
    assert_eq!(
        crc32(&bytes),
        RIG_FIXTURE_OUTPUT_CRC,
        "{:#010x}",
        crc32(&bytes)
    );
}

/// CRC-32 of the rig fixture's outputs (i16 LE) in `version2_rig_fixture_loads_and_runs`
/// (new on 2026-12-01 with the fixtures, when the exporter's output rows
/// came to cover the input stage's range).
const RIG_FIXTURE_OUTPUT_CRC: u32 = 0xadfb_7252;

/// Version 1 is retired: its record is refused with the version error,
/// and nothing after the preamble's version field is looked at.
#[test]
fn version1_fixture_is_refused_before_anything_else_is_read() {
    let blob = std::fs::read(fixture("example-v1.blob")).unwrap();
    assert_eq!(blob.len(), 88);
    assert_eq!(&blob[4..6], &[1, 0]);
    let want = Error::UnsupportedVersion {
        found: 1,
        supported: 2,
    };
    assert_eq!(Model::from_bytes(&blob).unwrap_err(), want);
    assert_eq!(Model::from_region(&blob).unwrap_err(), want);
    assert_eq!(blob_len_from_prefix(&blob).unwrap_err(), want);
    assert_eq!(phasegate::Style::from_bytes(&blob).unwrap_err(), want);
    assert_eq!(
        want.to_string(),
        "blob format version 1 is not supported (this runtime reads version 2)"
    );
    // Its preamble alone gives the same error: header, CRCs, padding and
    // payload are never read (a truncated or damaged rest changes nothing).
    assert_eq!(Model::from_bytes(&blob[..12]).unwrap_err(), want);
    let mut damaged = blob.clone();
    for b in &mut damaged[8..] {
        *b ^= 0xFF;
    }
    assert_eq!(Model::from_bytes(&damaged).unwrap_err(), want);
    let mut longer = blob.clone();
    longer.extend([0u8; 40]);
    assert_eq!(Model::from_bytes(&longer).unwrap_err(), want);
    // A version-1 header is not a version-2 header: even relabelled as
    // version 2 (CRC recomputed) it does not decode.
    assert_eq!(
        Model::from_bytes(&with_version(&blob, 2)).unwrap_err(),
        Error::HeaderMalformed
    );
    // The spec decoder reads its preamble the same way.
    assert_eq!(spec::parse(&blob).err(), Some(spec::Refused::Version(1)));
}

#[test]
fn version0_fixture_is_refused_with_a_version_error() {
    let blob = std::fs::read(fixture("version0.blob")).unwrap();
    assert_eq!(blob.len(), 88);
    assert_eq!(&blob[4..6], &[0, 0]);
    let want = Error::UnsupportedVersion {
        found: 0,
        supported: 2,
    };
    assert_eq!(Model::from_bytes(&blob).unwrap_err(), want);
    assert_eq!(Model::from_region(&blob).unwrap_err(), want);
    assert_eq!(blob_len_from_prefix(&blob).unwrap_err(), want);
    assert_eq!(
        want.to_string(),
        "blob format version 0 is not supported (this runtime reads version 2)"
    );
}

#[test]
fn future_versions_are_refused_before_anything_else_is_read() {
    let v3 = with_version(&example_blob(), 3);
    let want = Error::UnsupportedVersion {
        found: 3,
        supported: 2,
    };
    assert_eq!(Model::from_bytes(&v3).unwrap_err(), want);
    assert_eq!(blob_len_from_prefix(&v3).unwrap_err(), want);
    // The version is checked right after the magic: a version-3 blob whose
    // header, CRCs and length mean nothing to this runtime still gets the
    // version error, not a CRC or length one.
    // The whole 12-byte preamble must be there first.
    let mut garbage = b"PGMB".to_vec();
    garbage.extend(3u16.to_le_bytes());
    assert_eq!(
        Model::from_bytes(&garbage).unwrap_err(),
        Error::Truncated {
            needed: 12,
            available: 6
        }
    );
    garbage.extend([0xFF; 6]);
    assert_eq!(Model::from_bytes(&garbage).unwrap_err(), want);
    garbage.extend([0xFF; 100]);
    assert_eq!(Model::from_bytes(&garbage).unwrap_err(), want);
    let vmax = with_version(&example_blob(), u16::MAX);
    assert_eq!(
        Model::from_bytes(&vmax).unwrap_err(),
        Error::UnsupportedVersion {
            found: u16::MAX,
            supported: 2
        }
    );
    // The magic comes first.
    let mut bad = v3.clone();
    bad[0] = b'X';
    assert_eq!(Model::from_bytes(&bad).unwrap_err(), Error::BadMagic);
    // Fewer than 4 bytes: truncated, before the magic is compared.
    assert_eq!(
        Model::from_bytes(b"PG").unwrap_err(),
        Error::Truncated {
            needed: 12,
            available: 2
        }
    );
}

// ---------------------------------------------------------------------------
// A header decoder written from docs/blob-format.md alone.

mod spec {
    use super::*;

    /// Why `parse` refused a blob.
    #[derive(Debug, PartialEq, Eq)]
    pub enum Refused {
        /// Shorter than the part being read.
        Short,
        /// Not `PGMB`.
        Magic,
        /// Another format version: nothing after the preamble is read.
        Version(u16),
        /// Header CRC.
        HeaderCrc,
        /// The header bytes do not decode, or leave bytes over, or the
        /// padding is not zero.
        Malformed,
        /// Payload CRC.
        PayloadCrc,
    }

    pub struct Reader<'a> {
        bytes: &'a [u8],
        pos: usize,
    }

    impl<'a> Reader<'a> {
        pub fn new(bytes: &'a [u8]) -> Self {
            Reader { bytes, pos: 0 }
        }

        pub fn at_end(&self) -> bool {
            self.pos == self.bytes.len()
        }

        /// A `u8`: one raw byte.
        fn byte(&mut self) -> Option<u8> {
            let b = *self.bytes.get(self.pos)?;
            self.pos += 1;
            Some(b)
        }

        /// Unsigned LEB128 of a `bits`-bit integer: at most ceil(bits/7)
        /// bytes, the last of which may only carry the remaining bits.
        fn varint(&mut self, bits: u32) -> Option<u64> {
            let max_bytes = bits.div_ceil(7);
            let mut v = 0u64;
            for i in 0..max_bytes {
                let b = self.byte()?;
                v |= u64::from(b & 0x7f) << (7 * i);
                if b & 0x80 == 0 {
                    let last_max = (1u64 << (bits - 7 * (max_bytes - 1))) - 1;
                    if i == max_bytes - 1 && u64::from(b) > last_max {
                        return None;
                    }
                    return Some(v);
                }
            }
            None
        }

        fn u16(&mut self) -> Option<u16> {
            self.varint(16).map(|v| v as u16)
        }

        fn u32(&mut self) -> Option<u32> {
            self.varint(32).map(|v| v as u32)
        }

        /// Enum variant index: a u32 varint.
        fn tag(&mut self) -> Option<u32> {
            self.u32()
        }

        /// A vector length: a usize varint, at most `max`.
        fn count(&mut self, max: usize) -> Option<usize> {
            let n = self.varint(64)?;
            (n <= max as u64).then_some(n as usize)
        }

        fn section(&mut self) -> Option<Section> {
            Some(Section {
                offset: self.u32()?,
                len: self.u32()?,
            })
        }

        fn span(&mut self) -> Option<Span> {
            Some(Span {
                offset: self.u16()?,
                len: self.u16()?,
            })
        }

        fn source(&mut self) -> Option<Source> {
            match self.tag()? {
                0 => Some(Source::Input),
                1 => Some(Source::Node(self.byte()?)),
                _ => None,
            }
        }

        fn slice(&mut self) -> Option<Slice> {
            Some(Slice {
                source: self.source()?,
                start: self.u16()?,
                len: self.u16()?,
            })
        }

        fn layer(&mut self) -> Option<LayerDesc> {
            Some(LayerDesc {
                op: match self.tag()? {
                    0 => LayerOp::Dense,
                    1 => LayerOp::Cp {
                        rank: self.u16()?,
                        a: self.section()?,
                        cores: self.section()?,
                        mid: self.section()?,
                    },
                    2 => LayerOp::Diagonal,
                    3 => LayerOp::Rbf {
                        scales: self.section()?,
                        align: self.section()?,
                    },
                    4 => LayerOp::Dec {
                        scales: self.section()?,
                        align: self.section()?,
                    },
                    _ => return None,
                },
                in_dim: self.u16()?,
                out_dim: self.u16()?,
                experts: self.u16()?,
                weights: match self.tag()? {
                    0 => WeightFormat::I8,
                    1 => WeightFormat::I16,
                    2 => WeightFormat::I8Interleaved,
                    _ => return None,
                },
                acc: match self.tag()? {
                    0 => AccWidth::I32,
                    1 => AccWidth::I64,
                    _ => return None,
                },
                activation: match self.tag()? {
                    0 => Activation::Identity,
                    1 => Activation::Elu,
                    _ => return None,
                },
                weight_section: self.section()?,
                bias_section: self.section()?,
                requant_section: self.section()?,
            })
        }

        fn node(&mut self) -> Option<Node> {
            let op = match self.tag()? {
                0 => NodeOp::Layer(self.layer()?),
                1 => NodeOp::Softmax(SoftmaxDesc {
                    experts: self.u16()?,
                    frac: self.byte()?, // u8: one raw byte
                }),
                _ => return None,
            };
            let n = self.count(4)?;
            let mut inputs = heapless::Vec::new();
            for _ in 0..n {
                inputs.push(self.slice()?).ok()?;
            }
            let gate = match self.tag()? {
                0 => GateSource::None,
                1 => GateSource::Phase,
                2 => GateSource::Node(self.byte()?),
                _ => return None,
            };
            Some(Node {
                op,
                inputs,
                gate,
                input: self.span()?,
                scratch: self.span()?,
                output: self.span()?,
            })
        }

        pub fn header(&mut self) -> Option<Header> {
            let kind = match self.tag()? {
                0 => ModelKind::Pfnn,
                1 => ModelKind::Mlp,
                2 => ModelKind::Style {
                    base_crc: self.u32()?,
                    layer: self.byte()?, // u8: one raw byte, not a varint
                    name: self.section()?,
                },
                3 => ModelKind::Graph,
                _ => return None,
            };
            let gating = match self.tag()? {
                0 => Gating::Single,
                1 => Gating::Constant {
                    tables: self.u16()?,
                },
                2 => Gating::Linear {
                    tables: self.u16()?,
                },
                3 => Gating::CatmullRom {
                    points: self.u16()?,
                },
                4 => Gating::Softmax {
                    experts: self.u16()?,
                },
                _ => return None,
            };
            let input_dim = self.u16()?;
            let output_dim = self.u16()?;
            let count = self.count(24)?;
            let mut nodes = heapless::Vec::new();
            for _ in 0..count {
                nodes.push(self.node()?).ok()?;
            }
            Some(Header {
                kind,
                gating,
                input_dim,
                output_dim,
                nodes,
                input: self.span()?,
                output: self.slice()?,
                input_stage: self.section()?,
                output_stage: self.section()?,
                ram_bytes: self.u32()?,
                macs_per_frame: self.u32()?,
                payload_len: self.u32()?,
                payload_crc: self.u32()?,
            })
        }
    }

    /// Preamble, header and payload of a version-2 blob, by the document's
    /// rules (framing checks 1 to 12, in order, except that this returns
    /// the payload of a longer slice).
    pub fn parse(blob: &[u8]) -> Result<(Header, &[u8]), Refused> {
        if blob.get(..4).ok_or(Refused::Short)? != b"PGMB" {
            return Err(Refused::Magic);
        }
        let pre = blob.get(..12).ok_or(Refused::Short)?;
        let version = u16::from_le_bytes([pre[4], pre[5]]);
        if version != 2 {
            return Err(Refused::Version(version));
        }
        let header_len = usize::from(u16::from_le_bytes([pre[6], pre[7]]));
        let crc = u32::from_le_bytes([pre[8], pre[9], pre[10], pre[11]]);
        let header_bytes = blob.get(12..12 + header_len).ok_or(Refused::Short)?;
        let mut crc_input = blob[..8].to_vec();
        crc_input.extend(header_bytes);
        if crc32(&crc_input) != crc {
            return Err(Refused::HeaderCrc);
        }
        let mut r = Reader::new(header_bytes);
        let header = r.header().ok_or(Refused::Malformed)?;
        if !r.at_end() {
            return Err(Refused::Malformed);
        }
        let payload_start = (12 + header_len).next_multiple_of(16);
        let padding = blob
            .get(12 + header_len..payload_start)
            .ok_or(Refused::Short)?;
        if padding.iter().any(|&b| b != 0) {
            return Err(Refused::Malformed);
        }
        let payload = blob
            .get(payload_start..payload_start + header.payload_len as usize)
            .ok_or(Refused::Short)?;
        if crc32(payload) != header.payload_crc {
            return Err(Refused::PayloadCrc);
        }
        Ok((header, payload))
    }
}

#[test]
fn the_spec_decoder_reads_the_example() {
    let blob = hex(EXAMPLE_HEX);
    let (header, payload) = spec::parse(&blob).unwrap();
    assert_eq!(header, Model::from_bytes(&blob).unwrap().header().decoded());
    assert_eq!(payload, &blob[64..]);
}

fn layer(
    in_dim: u16,
    out_dim: u16,
    experts: u16,
    w: WeightFormat,
    acc: AccWidth,
    act: Activation,
) -> QLayer {
    let n = usize::from(experts) * usize::from(out_dim);
    QLayer {
        desc: LayerDesc {
            op: LayerOp::Dense,
            in_dim,
            out_dim,
            experts,
            weights: w,
            acc,
            activation: act,
            weight_section: empty(),
            bias_section: empty(),
            requant_section: empty(),
        },
        weights: (0..n * usize::from(in_dim))
            .map(|i| (i % 7) as i32 - 3)
            .collect(),
        bias: (0..n).map(|i| i as i64 * 1000 - 5000).collect(),
        requant: (0..out_dim)
            .map(|i| Requant {
                multiplier: 1 << 30,
                pre_shift: 4,
                post_shift: 32,
                frac: (i % 16) as u8,
            })
            .collect(),
        cp: None,
        rbf: None,
        gated: experts > 1,
    }
}

/// Larger and stranger headers than the example: multi-byte varints in
/// every field kind, every gating, both weight and accumulator formats,
/// chains and a graph with concatenations, a partial output slice and a
/// softmax gate.
#[test]
fn the_spec_decoder_agrees_with_the_runtime_on_real_blobs() {
    use AccWidth::*;
    use Activation::*;
    use WeightFormat::*;
    let gatings = [
        (Gating::Single, 1),
        (Gating::Constant { tables: 50 }, 50),
        (Gating::Linear { tables: 10 }, 10),
        (Gating::CatmullRom { points: 4 }, 4),
    ];
    let mut blobs = Vec::new();
    for (gating, experts) in gatings {
        let chain = QModel {
            kind: QKind::Model(ModelKind::Pfnn),
            gating,
            input_stage: (0..200)
                .map(|i| (i as f32, 1.0 / (1.0 + i as f32)))
                .collect(),
            output_stage: (0..130).map(|i| (0.5, i as f32)).collect(),
            layers: vec![
                layer(200, 3, experts, I8, I32, Elu),
                layer(3, 150, experts, I16, I64, Elu),
                layer(150, 130, 1, I16, I32, Identity),
            ],
            wiring: Wiring::Chain,
        };
        // The same layers as a graph: a softmax gate over four logits
        // (two slices of one layer, concatenated) drives a layer that
        // reads a concatenation of node 0 and part of the input.
        let mut logits = layer(200, 4, 1, I8, I32, Identity);
        for r in &mut logits.requant {
            r.frac = 9;
        }
        let mut graph = chain.clone();
        graph.layers = vec![
            layer(200, 3, experts, I8, I32, Elu),
            logits,
            layer(13, 150, 4, I16, I64, Elu),
            layer(150, 131, 1, I16, I32, Identity),
        ];
        graph.wiring = Wiring::Graph {
            nodes: vec![
                QNode {
                    op: QNodeOp::Layer(0),
                    inputs: vec![slice(Source::Input, 0, 200)],
                    gate: if experts > 1 {
                        GateSource::Phase
                    } else {
                        GateSource::None
                    },
                },
                QNode {
                    op: QNodeOp::Layer(1),
                    inputs: vec![slice(Source::Input, 0, 200)],
                    gate: GateSource::None,
                },
                QNode {
                    op: QNodeOp::Softmax(SoftmaxDesc {
                        experts: 4,
                        frac: 9,
                    }),
                    inputs: vec![slice(Source::Node(1), 2, 2), slice(Source::Node(1), 0, 2)],
                    gate: GateSource::None,
                },
                QNode {
                    op: QNodeOp::Layer(2),
                    inputs: vec![slice(Source::Node(0), 0, 3), slice(Source::Input, 190, 10)],
                    gate: GateSource::Node(2),
                },
                QNode {
                    op: QNodeOp::Layer(3),
                    inputs: vec![slice(Source::Node(3), 0, 150)],
                    gate: GateSource::None,
                },
            ],
            output: slice(Source::Node(4), 1, 130),
        };
        blobs.push(encode(&chain).unwrap());
        blobs.push(encode(&graph).unwrap());
    }
    for blob in &blobs {
        let model = Model::from_bytes(blob).unwrap();
        let (header, payload) = spec::parse(blob).unwrap();
        assert_eq!(&header, &model.header().decoded());
        assert_eq!(payload.len(), header.payload_len as usize);
        assert!(postcard::to_allocvec(&header).unwrap().len() > 127);
        // Sections are 4-aligned and in the encoder's order.
        let l = |i: usize| *header.nodes[i].layer().unwrap();
        let order = [
            header.input_stage,
            header.output_stage,
            l(0).weight_section,
            l(0).bias_section,
            l(0).requant_section,
            l(1).weight_section,
        ];
        for w in order.windows(2) {
            assert_eq!(w[1].offset, w[0].end().unwrap().next_multiple_of(4));
        }
        // ram_bytes is twice the largest span end.
        let ends = header
            .nodes
            .iter()
            .flat_map(|n| [n.input, n.scratch, n.output])
            .chain([header.input])
            .map(|s| s.end())
            .max()
            .unwrap();
        assert_eq!(header.ram_bytes, 2 * ends);
        let mut rt: Runtime<'_, 1024> = Runtime::new(model).unwrap();
        let mut y = vec![0f32; 130];
        rt.run(Phase::from_bits(0x1234_5678), &[0.25; 200], &mut y)
            .unwrap();
    }
}

fn arb_section() -> impl Strategy<Value = Section> {
    (any::<u32>(), any::<u32>()).prop_map(|(offset, len)| Section { offset, len })
}

fn arb_span() -> impl Strategy<Value = Span> {
    (any::<u16>(), any::<u16>()).prop_map(|(offset, len)| Span { offset, len })
}

fn arb_slice() -> impl Strategy<Value = Slice> {
    (
        prop_oneof![Just(Source::Input), any::<u8>().prop_map(Source::Node)],
        any::<u16>(),
        any::<u16>(),
    )
        .prop_map(|(source, start, len)| Slice { source, start, len })
}

fn arb_op() -> impl Strategy<Value = LayerOp> {
    prop_oneof![
        Just(LayerOp::Dense),
        (any::<u16>(), arb_section(), arb_section(), arb_section()).prop_map(
            |(rank, a, cores, mid)| LayerOp::Cp {
                rank,
                a,
                cores,
                mid
            }
        ),
        Just(LayerOp::Diagonal),
        (arb_section(), arb_section()).prop_map(|(scales, align)| LayerOp::Rbf { scales, align }),
        (arb_section(), arb_section()).prop_map(|(scales, align)| LayerOp::Dec { scales, align }),
    ]
}

fn arb_layer() -> impl Strategy<Value = LayerDesc> {
    (
        (arb_op(), any::<u16>(), any::<u16>(), any::<u16>()),
        prop_oneof![Just(WeightFormat::I8), Just(WeightFormat::I16)],
        prop_oneof![Just(AccWidth::I32), Just(AccWidth::I64)],
        prop_oneof![Just(Activation::Identity), Just(Activation::Elu)],
        (arb_section(), arb_section(), arb_section()),
    )
        .prop_map(
            |((op, in_dim, out_dim, experts), weights, acc, activation, (w, b, r))| LayerDesc {
                op,
                in_dim,
                out_dim,
                experts,
                weights,
                acc,
                activation,
                weight_section: w,
                bias_section: b,
                requant_section: r,
            },
        )
}

fn arb_node() -> impl Strategy<Value = Node> {
    (
        prop_oneof![
            arb_layer().prop_map(NodeOp::Layer),
            (any::<u16>(), any::<u8>())
                .prop_map(|(experts, frac)| NodeOp::Softmax(SoftmaxDesc { experts, frac })),
        ],
        proptest::collection::vec(arb_slice(), 0..=MAX_NODE_INPUTS),
        prop_oneof![
            Just(GateSource::None),
            Just(GateSource::Phase),
            any::<u8>().prop_map(GateSource::Node),
        ],
        (arb_span(), arb_span(), arb_span()),
    )
        .prop_map(|(op, inputs, gate, (input, scratch, output))| Node {
            op,
            inputs: inputs.into_iter().collect(),
            gate,
            input,
            scratch,
            output,
        })
}

fn arb_header() -> impl Strategy<Value = Header> {
    let gating = prop_oneof![
        Just(Gating::Single),
        any::<u16>().prop_map(|tables| Gating::Constant { tables }),
        any::<u16>().prop_map(|tables| Gating::Linear { tables }),
        any::<u16>().prop_map(|points| Gating::CatmullRom { points }),
        any::<u16>().prop_map(|experts| Gating::Softmax { experts }),
    ];
    (
        prop_oneof![
            Just(ModelKind::Pfnn),
            Just(ModelKind::Mlp),
            Just(ModelKind::Graph),
            (any::<u32>(), any::<u8>(), arb_section()).prop_map(|(base_crc, layer, name)| {
                ModelKind::Style {
                    base_crc,
                    layer,
                    name,
                }
            }),
        ],
        gating,
        (any::<u16>(), any::<u16>()),
        proptest::collection::vec(arb_node(), 0..=MAX_NODES),
        (arb_span(), arb_slice()),
        (arb_section(), arb_section()),
        (any::<u32>(), any::<u32>(), any::<u32>(), any::<u32>()),
    )
        .prop_map(
            |(
                kind,
                gating,
                (input_dim, output_dim),
                nodes,
                (input, output),
                (i, o),
                (ram, macs, len, crc),
            )| {
                Header {
                    kind,
                    gating,
                    input_dim,
                    output_dim,
                    nodes: nodes.into_iter().collect(),
                    input,
                    output,
                    input_stage: i,
                    output_stage: o,
                    ram_bytes: ram,
                    macs_per_frame: macs,
                    payload_len: len,
                    payload_crc: crc,
                }
            },
        )
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

    /// Every header the runtime's type can hold encodes to bytes that the
    /// document's decoder reads back field for field, and `frame` lays out
    /// the preamble and padding as the document says.
    #[test]
    fn the_spec_decoder_reads_any_header(h in arb_header()) {
        let bytes = postcard::to_allocvec(&h).unwrap();
        prop_assert!(bytes.len() <= 3202);
        let mut r = spec::Reader::new(&bytes);
        prop_assert_eq!(r.header(), Some(h.clone()));
        prop_assert!(r.at_end());
        // And the runtime's decoder reads the spec's bytes back the same.
        prop_assert_eq!(postcard::from_bytes::<Header>(&bytes).ok(), Some(h.clone()));
        let payload = [0xA5u8; 5];
        let framed = frame(&h, &payload);
        prop_assert_eq!(&framed, &frame_raw(FORMAT_VERSION, &bytes, &payload));
        prop_assert_eq!(framed.len() % 16, 5);
        // The runtime reads the same header back (or refuses a payload
        // length that does not match, after decoding the header).
        prop_assert_eq!(blob_len_from_prefix(&framed).ok(), Some((12 + bytes.len()).next_multiple_of(16) + h.payload_len as usize));
        // The spec parser and the runtime's framing agree on it.
        let mut exact = framed.clone();
        exact.truncate((12 + bytes.len()).next_multiple_of(16));
        exact.extend(std::iter::repeat_n(0xA5u8, (h.payload_len as usize).min(64)));
        if h.payload_len as usize <= 64 {
            let mut h2 = h.clone();
            h2.payload_crc = crc32(&exact[(12 + bytes.len()).next_multiple_of(16)..]);
            let b2 = frame(&h2, &exact[(12 + bytes.len()).next_multiple_of(16)..]);
            let (sh, _) = spec::parse(&b2).unwrap();
            prop_assert_eq!(sh, h2);
        }
    }
}
