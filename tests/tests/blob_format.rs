//! Pins the blob format of `docs/blob-format.md`.
//!
//! * The byte-level example of the document, built with the real encoder,
//!   must equal the hex table below byte for byte, load, and run to the value
//!   the document computes by hand.
//! * The postcard encodings the document lists are checked against postcard.
//! * A header decoder written from the document alone (`spec`, below) must
//!   agree with the runtime on every header, including random ones.
//! * Blobs of other format versions (`fixtures/version0.blob`, a generated
//!   version 2) are refused with `UnsupportedVersion`.
//!
//! `PHASEGATE_BLESS=1 cargo test -p phasegate-tests --test blob_format`
//! rewrites the fixtures in `tests/fixtures/` (only ever needed when the
//! example changes, which is a format change: see the document).

use std::path::PathBuf;

use exporter::encode::{encode, frame, QKind, QLayer, QModel};
use phasegate::blob::{
    crc32, AccWidth, Activation, Gating, Header, LayerDesc, LayerOp, ModelKind, Requant, Section,
    WeightFormat, FORMAT_VERSION, MAGIC, MAX_LAYERS, PAYLOAD_ALIGN, PREAMBLE_LEN,
};
use phasegate::{blob_len_from_prefix, Error, Model, Phase, Runtime};
use proptest::prelude::*;

/// The example blob of `docs/blob-format.md`, section "Byte-level example".
/// Offsets on the left; the document annotates every byte.
const EXAMPLE_HEX: &str = "
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

fn empty() -> Section {
    Section::default()
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
                gated: false,
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
        }],
    }
}

fn example_blob() -> Vec<u8> {
    encode(&example_model()).unwrap()
}

#[test]
fn example_bytes_are_pinned() {
    let blob = example_blob();
    let expected = hex(EXAMPLE_HEX);
    assert_eq!(blob.len(), 88);
    if blob != expected {
        let got: Vec<String> = blob
            .chunks(16)
            .enumerate()
            .map(|(i, c)| {
                format!(
                    "{:04x}: {}",
                    i * 16,
                    c.iter()
                        .map(|b| format!("{b:02x}"))
                        .collect::<Vec<_>>()
                        .join(" ")
                )
            })
            .collect();
        panic!(
            "example blob changed; the encoder now writes:\n{}",
            got.join("\n")
        );
    }
}

#[test]
fn example_header_is_what_the_document_says() {
    let blob = hex(EXAMPLE_HEX);
    let model = Model::from_bytes(&blob).unwrap();
    let h = model.header();
    assert_eq!(h.kind, ModelKind::Mlp);
    assert_eq!(h.gating, Gating::Single);
    assert_eq!((h.input_dim, h.output_dim), (2, 1));
    assert_eq!(h.layers.len(), 1);
    let l = h.layers[0];
    assert_eq!((l.in_dim, l.out_dim, l.experts, l.gated), (2, 1, 1, false));
    assert_eq!(
        (l.weights, l.acc, l.activation),
        (WeightFormat::I8, AccWidth::I32, Activation::Identity)
    );
    assert_eq!(l.weight_section, Section { offset: 24, len: 2 });
    assert_eq!(l.bias_section, Section { offset: 28, len: 4 });
    assert_eq!(l.requant_section, Section { offset: 32, len: 8 });
    assert_eq!(h.input_stage, Section { offset: 0, len: 16 });
    assert_eq!(h.output_stage, Section { offset: 16, len: 8 });
    assert_eq!((h.ram_bytes, h.macs_per_frame), (8, 2));
    assert_eq!((h.payload_len, h.payload_crc), (40, 0x3D3D_D557));
    assert_eq!(model.blob_len(), 88);
    // Preamble: header length 31, header CRC over bytes 0..8 and the header.
    assert_eq!(&blob[6..8], &31u16.to_le_bytes());
    assert_eq!(
        crc32(
            &blob[..8]
                .iter()
                .chain(&blob[12..43])
                .copied()
                .collect::<Vec<_>>()
        ),
        0x3708_101B
    );
    assert_eq!(&blob[8..12], &0x3708_101Bu32.to_le_bytes());
    assert_eq!(crc32(&blob[48..]), 0x3D3D_D557);
    assert_eq!(blob_len_from_prefix(&blob[..48]), Ok(88));
}

/// The hand computation of the document's "Running the example" section.
#[test]
fn example_runs_to_the_hand_computed_value() {
    let blob = hex(EXAMPLE_HEX);
    let model = Model::from_bytes(&blob).unwrap();
    let mut rt: Runtime<'_, 2> = Runtime::new(model).unwrap();
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
    assert_eq!(enc(&Gating::Single), [0x00]);
    assert_eq!(enc(&Gating::Constant { tables: 50 }), [0x01, 0x32]);
    assert_eq!(enc(&Gating::Linear { tables: 10 }), [0x02, 0x0a]);
    assert_eq!(enc(&Gating::CatmullRom { points: 4 }), [0x03, 0x04]);
    assert_eq!(enc(&Gating::Linear { tables: 300 }), [0x02, 0xac, 0x02]);
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
    // u8 is one raw byte, not a varint (200 would be c8 01 as a varint).
    let style = ModelKind::Style {
        base_crc: 1,
        layer: 200,
        name: Section { offset: 0, len: 5 },
    };
    assert_eq!(enc(&style), [0x02, 0x01, 0xc8, 0x00, 0x05]);
    // Structs: fields in order, nothing else.
    assert_eq!(
        enc(&Section {
            offset: 1024,
            len: 36_936
        }),
        [0x80, 0x08, 0xc8, 0xa0, 0x02]
    );
    // heapless::Vec: varint length, then the elements.
    let mut v = heapless::Vec::<Section, 4>::new();
    v.push(Section { offset: 4, len: 8 }).unwrap();
    v.push(Section { offset: 12, len: 0 }).unwrap();
    assert_eq!(enc(&v), [0x02, 0x04, 0x08, 0x0c, 0x00]);
}

/// What the document says about varints a writer should not produce.
#[test]
fn padded_varints_load_and_overlong_ones_do_not() {
    let blob = example_blob();
    let payload = &blob[48..];
    let header = postcard::to_allocvec(Model::from_bytes(&blob).unwrap().header()).unwrap();
    // Byte 2 of the header is input_dim = 2, encoded 0x02. Padded: 0x82 0x00.
    assert_eq!(header[2], 0x02);
    let mut padded = header.clone();
    padded.splice(2..3, [0x82, 0x00]);
    let padded_blob = frame_raw(1, &padded, payload);
    let m = Model::from_bytes(&padded_blob).unwrap();
    assert_eq!(m.header().input_dim, 2);
    // A u16 varint may not take more than 3 bytes, and its third byte may not exceed 0x03.
    let mut overlong = header.clone();
    overlong.splice(2..3, [0x82, 0x80, 0x80, 0x00]);
    assert_eq!(
        Model::from_bytes(&frame_raw(1, &overlong, payload)).unwrap_err(),
        Error::HeaderMalformed
    );
    let mut too_big = header.clone();
    too_big.splice(2..3, [0x82, 0x80, 0x04]);
    assert_eq!(
        Model::from_bytes(&frame_raw(1, &too_big, payload)).unwrap_err(),
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
}

/// The largest header any `Header` value encodes to: every varint at its
/// longest, the longest enum variants, eight CP layers.
#[test]
fn largest_header_size() {
    let s = Section {
        offset: u32::MAX,
        len: u32::MAX,
    };
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
        gated: true,
        weight_section: s,
        bias_section: s,
        requant_section: s,
    };
    let h = Header {
        kind: ModelKind::Style {
            base_crc: u32::MAX,
            layer: u8::MAX,
            name: s,
        },
        gating: Gating::CatmullRom { points: u16::MAX },
        input_dim: u16::MAX,
        output_dim: u16::MAX,
        layers: std::iter::repeat_n(layer, MAX_LAYERS).collect(),
        input_stage: s,
        output_stage: s,
        ram_bytes: u32::MAX,
        macs_per_frame: u32::MAX,
        payload_len: u32::MAX,
        payload_crc: u32::MAX,
    };
    assert_eq!(postcard::to_allocvec(&h).unwrap().len(), 684);
}

#[test]
fn constants_are_the_documented_ones() {
    assert_eq!(MAGIC, *b"PGMB");
    assert_eq!(FORMAT_VERSION, 1);
    assert_eq!((PREAMBLE_LEN, PAYLOAD_ALIGN, MAX_LAYERS), (12, 16, 8));
    let blob = example_blob();
    let header = postcard::to_allocvec(Model::from_bytes(&blob).unwrap().header()).unwrap();
    assert_eq!(frame_raw(1, &header, &blob[48..]), blob);
}

// ---------------------------------------------------------------------------
// Format versions.

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures")
        .join(name)
}

/// The example with another version number, header CRC recomputed.
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

/// The checked-in fixtures are what this file generates; `PHASEGATE_BLESS=1`
/// rewrites them.
#[test]
fn fixtures_are_current() {
    let wanted = [
        ("example-v1.blob", example_blob()),
        ("version0.blob", with_version(&example_blob(), 0)),
    ];
    for (name, bytes) in wanted {
        let path = fixture(name);
        if std::env::var_os("PHASEGATE_BLESS").is_some() {
            std::fs::write(&path, &bytes).unwrap();
        }
        let on_disk = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert_eq!(
            on_disk, bytes,
            "{name} is stale: rerun with PHASEGATE_BLESS=1"
        );
    }
}

/// A blob written by format version 1 must keep loading (or, once version 1
/// is retired, be refused with `UnsupportedVersion`, never misread).
#[test]
fn version1_fixture_loads_and_runs() {
    let blob = std::fs::read(fixture("example-v1.blob")).unwrap();
    let model = Model::from_bytes(&blob).unwrap();
    let mut rt: Runtime<'_, 2> = Runtime::new(model).unwrap();
    let mut y = [0f32];
    rt.run(Phase::from_bits(0), &[1.5, -0.25], &mut y).unwrap();
    assert_eq!(y, [3703.0 / 128.0 - 2.5]); // 26.4296875
}

#[test]
fn version0_fixture_is_refused_with_a_version_error() {
    let blob = std::fs::read(fixture("version0.blob")).unwrap();
    assert_eq!(blob.len(), 88);
    assert_eq!(&blob[4..6], &[0, 0]);
    let want = Error::UnsupportedVersion {
        found: 0,
        supported: 1,
    };
    assert_eq!(Model::from_bytes(&blob).unwrap_err(), want);
    assert_eq!(Model::from_region(&blob).unwrap_err(), want);
    assert_eq!(blob_len_from_prefix(&blob).unwrap_err(), want);
    assert_eq!(
        want.to_string(),
        "blob format version 0 is not supported (this runtime reads version 1)"
    );
}

#[test]
fn future_versions_are_refused_before_anything_else_is_read() {
    let v2 = with_version(&example_blob(), 2);
    assert_eq!(
        Model::from_bytes(&v2).unwrap_err(),
        Error::UnsupportedVersion {
            found: 2,
            supported: 1
        }
    );
    // The version is checked right after the magic: a version-2 blob whose
    // header, CRCs and length mean nothing to this runtime still gets the
    // version error, not a CRC or length one.
    // The whole 12-byte preamble must be there first.
    let mut garbage = b"PGMB".to_vec();
    garbage.extend(2u16.to_le_bytes());
    assert_eq!(
        Model::from_bytes(&garbage).unwrap_err(),
        Error::Truncated {
            needed: 12,
            available: 6
        }
    );
    garbage.extend([0xFF; 6]);
    assert_eq!(
        Model::from_bytes(&garbage).unwrap_err(),
        Error::UnsupportedVersion {
            found: 2,
            supported: 1
        }
    );
    garbage.extend([0xFF; 100]);
    assert_eq!(
        Model::from_bytes(&garbage).unwrap_err(),
        Error::UnsupportedVersion {
            found: 2,
            supported: 1
        }
    );
    let vmax = with_version(&example_blob(), u16::MAX);
    assert_eq!(
        Model::from_bytes(&vmax).unwrap_err(),
        Error::UnsupportedVersion {
            found: u16::MAX,
            supported: 1
        }
    );
    // The magic comes first.
    let mut bad = v2.clone();
    bad[0] = b'X';
    assert_eq!(Model::from_bytes(&bad).unwrap_err(), Error::BadMagic);
}

// ---------------------------------------------------------------------------
// A header decoder written from docs/blob-format.md alone.

mod spec {
    use super::*;

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

        fn bool(&mut self) -> Option<bool> {
            match self.byte()? {
                0 => Some(false),
                1 => Some(true),
                _ => None,
            }
        }

        fn section(&mut self) -> Option<Section> {
            Some(Section {
                offset: self.u32()?,
                len: self.u32()?,
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
                    _ => return None,
                },
                in_dim: self.u16()?,
                out_dim: self.u16()?,
                experts: self.u16()?,
                weights: match self.tag()? {
                    0 => WeightFormat::I8,
                    1 => WeightFormat::I16,
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
                gated: self.bool()?,
                weight_section: self.section()?,
                bias_section: self.section()?,
                requant_section: self.section()?,
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
                _ => return None,
            };
            let input_dim = self.u16()?;
            let output_dim = self.u16()?;
            let count = self.varint(64)?;
            let mut layers = heapless::Vec::new();
            for _ in 0..count {
                layers.push(self.layer()?).ok()?;
            }
            Some(Header {
                kind,
                gating,
                input_dim,
                output_dim,
                layers,
                input_stage: self.section()?,
                output_stage: self.section()?,
                ram_bytes: self.u32()?,
                macs_per_frame: self.u32()?,
                payload_len: self.u32()?,
                payload_crc: self.u32()?,
            })
        }
    }

    /// Preamble, header and payload of a blob, by the document's rules.
    pub fn parse(blob: &[u8]) -> Option<(u16, Header, &[u8])> {
        if blob.get(..4)? != b"PGMB" {
            return None;
        }
        let version = u16::from_le_bytes([*blob.get(4)?, *blob.get(5)?]);
        let header_len = usize::from(u16::from_le_bytes([*blob.get(6)?, *blob.get(7)?]));
        let crc = u32::from_le_bytes(blob.get(8..12)?.try_into().ok()?);
        let header_bytes = blob.get(12..12 + header_len)?;
        let mut crc_input = blob[..8].to_vec();
        crc_input.extend(header_bytes);
        if crc32(&crc_input) != crc {
            return None;
        }
        let mut r = Reader::new(header_bytes);
        let header = r.header()?;
        if !r.at_end() {
            return None;
        }
        let payload_start = (12 + header_len).next_multiple_of(16);
        if blob
            .get(12 + header_len..payload_start)?
            .iter()
            .any(|&b| b != 0)
        {
            return None;
        }
        let payload = blob.get(payload_start..payload_start + header.payload_len as usize)?;
        (crc32(payload) == header.payload_crc).then_some((version, header, payload))
    }
}

#[test]
fn the_spec_decoder_reads_the_example() {
    let blob = hex(EXAMPLE_HEX);
    let (version, header, payload) = spec::parse(&blob).unwrap();
    assert_eq!(version, 1);
    assert_eq!(&header, Model::from_bytes(&blob).unwrap().header());
    assert_eq!(payload, &blob[48..]);
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
            gated: experts > 1,
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
    }
}

/// Larger and stranger headers than the example: multi-byte varints in
/// every field kind, every gating, both weight and accumulator formats.
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
    for (gating, experts) in gatings {
        let m = QModel {
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
        };
        let blob = encode(&m).unwrap();
        let model = Model::from_bytes(&blob).unwrap();
        let (version, header, payload) = spec::parse(&blob).unwrap();
        assert_eq!(version, 1);
        assert_eq!(&header, model.header());
        assert_eq!(payload.len(), header.payload_len as usize);
        // Sections are 4-aligned and in the encoder's order.
        let l = &header.layers;
        let order = [
            header.input_stage,
            header.output_stage,
            l[0].weight_section,
            l[0].bias_section,
            l[0].requant_section,
            l[1].weight_section,
        ];
        for w in order.windows(2) {
            assert_eq!(w[1].offset, w[0].end().unwrap().next_multiple_of(4));
        }
    }
}

fn arb_section() -> impl Strategy<Value = Section> {
    (any::<u32>(), any::<u32>()).prop_map(|(offset, len)| Section { offset, len })
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
    ]
}

fn arb_layer() -> impl Strategy<Value = LayerDesc> {
    (
        (arb_op(), any::<u16>(), any::<u16>(), any::<u16>()),
        prop_oneof![Just(WeightFormat::I8), Just(WeightFormat::I16)],
        prop_oneof![Just(AccWidth::I32), Just(AccWidth::I64)],
        prop_oneof![Just(Activation::Identity), Just(Activation::Elu)],
        any::<bool>(),
        (arb_section(), arb_section(), arb_section()),
    )
        .prop_map(
            |((op, in_dim, out_dim, experts), weights, acc, activation, gated, (w, b, r))| {
                LayerDesc {
                    op,
                    in_dim,
                    out_dim,
                    experts,
                    weights,
                    acc,
                    activation,
                    gated,
                    weight_section: w,
                    bias_section: b,
                    requant_section: r,
                }
            },
        )
}

fn arb_header() -> impl Strategy<Value = Header> {
    let gating = prop_oneof![
        Just(Gating::Single),
        any::<u16>().prop_map(|tables| Gating::Constant { tables }),
        any::<u16>().prop_map(|tables| Gating::Linear { tables }),
        any::<u16>().prop_map(|points| Gating::CatmullRom { points }),
    ];
    (
        prop_oneof![
            Just(ModelKind::Pfnn),
            Just(ModelKind::Mlp),
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
        proptest::collection::vec(arb_layer(), 0..=MAX_LAYERS),
        (arb_section(), arb_section()),
        (any::<u32>(), any::<u32>(), any::<u32>(), any::<u32>()),
    )
        .prop_map(
            |(kind, gating, (input_dim, output_dim), layers, (i, o), (ram, macs, len, crc))| {
                Header {
                    kind,
                    gating,
                    input_dim,
                    output_dim,
                    layers: layers.into_iter().collect(),
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
        let mut r = spec::Reader::new(&bytes);
        prop_assert_eq!(r.header(), Some(h.clone()));
        prop_assert!(r.at_end());
        let payload = [0xA5u8; 5];
        let framed = frame(&h, &payload);
        prop_assert_eq!(&framed, &frame_raw(FORMAT_VERSION, &bytes, &payload));
        prop_assert_eq!(framed.len() % 16, 5);
        // The runtime reads the same header back (or refuses a payload
        // length that does not match, after decoding the header).
        prop_assert_eq!(blob_len_from_prefix(&framed).ok(), Some((12 + bytes.len()).next_multiple_of(16) + h.payload_len as usize));
    }
}
