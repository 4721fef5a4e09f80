//! Hostile blobs and hostile arguments: the runtime answers every one with
//! an error (the right one where it can be named) and never panics.
//!
//! Blobs used:
//! * `quantised(..)`: a random, small PFNN-shaped float network (20 -> 24 ->
//!   24 -> 12, four Catmull-Rom control points) through the real quantiser
//!   and encoder (`exporter::export::export`), int8 and int16 weights;
//! * `hand_model()`: a hand-made three-layer model with a five-point
//!   Catmull-Rom gating, both weight formats and both accumulator widths,
//!   an ungated last layer;
//! * `cp_and_styles()`: a whole-network CP model (CP, diagonal, CP layers)
//!   and style blobs (CP, diagonal and full adapters) for a small dense
//!   base, all through the real exporter.

use exporter::encode::{encode, frame, QKind, QLayer, QModel};
use exporter::export::export;
use exporter::net::{ExpertLayer, GatingMode, Net, NetLayer};
use exporter::quantise::QuantOptions;
use ndarray::{Array1, Array2};
use phasegate::blob::{
    crc32, AccWidth, Activation, Gating, Header, LayerDesc, LayerOp, ModelKind, Requant, Section,
    WeightFormat, REQUANT_RECORD_LEN,
};
use phasegate::style::BlendWeight;
use phasegate::{
    blob_len_from_prefix, Error, Mix, Model, Phase, Runtime, Style, StyleId, StyledRuntime, STAGE,
};
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

// ---------------------------------------------------------------------------
// Blobs.

fn matrix(rng: &mut ChaCha8Rng, rows: usize, cols: usize, scale: f64) -> Array2<f64> {
    Array2::from_shape_fn((rows, cols), |_| rng.gen_range(-scale..scale))
}

fn vector(rng: &mut ChaCha8Rng, n: usize, lo: f64, hi: f64) -> Array1<f64> {
    Array1::from_shape_fn(n, |_| rng.gen_range(lo..hi))
}

fn expert_layer(rng: &mut ChaCha8Rng, inp: usize, out: usize) -> ExpertLayer {
    let s = 1.5 / (inp as f64).sqrt();
    ExpertLayer {
        w: (0..4).map(|_| matrix(rng, out, inp, s)).collect(),
        b: (0..4).map(|_| vector(rng, out, -0.2, 0.2)).collect(),
    }
}

/// A random PFNN-shaped float network: 20 inputs, two hidden layers of 24,
/// 12 outputs, 4 control points.
fn float_net(seed: u64) -> Net {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (i, h, o) = (20, 24, 12);
    Net {
        mode: GatingMode::Cubic,
        xmean: vector(&mut rng, i, -3.0, 3.0),
        xstd: vector(&mut rng, i, 0.2, 4.0),
        ymean: vector(&mut rng, o, -1.0, 1.0),
        ystd: vector(&mut rng, o, 0.1, 2.0),
        layers: [
            expert_layer(&mut rng, i, h),
            expert_layer(&mut rng, h, h),
            expert_layer(&mut rng, h, o),
        ]
        .into_iter()
        .map(NetLayer::Dense)
        .collect(),
    }
}

/// The float network through the real quantiser and encoder.
fn quantised(weights: WeightFormat) -> Vec<u8> {
    let opts = QuantOptions {
        weights,
        calibration_samples: 128,
        ..QuantOptions::default()
    };
    export(&float_net(7), None, &opts).unwrap().0
}

fn desc(
    in_dim: u16,
    out_dim: u16,
    experts: u16,
    w: WeightFormat,
    acc: AccWidth,
    act: Activation,
) -> LayerDesc {
    LayerDesc {
        op: LayerOp::Dense,
        in_dim,
        out_dim,
        experts,
        weights: w,
        acc,
        activation: act,
        gated: experts > 1,
        weight_section: Section::default(),
        bias_section: Section::default(),
        requant_section: Section::default(),
    }
}

/// Catmull-Rom over 5 points; layer 0 int16/i32/ELU 6 -> 8, layer 1
/// int8/i64/ELU 8 -> 7, layer 2 ungated int8/i32/identity 7 -> 5.
fn hand_model() -> QModel {
    use AccWidth::*;
    use Activation::*;
    use WeightFormat::*;
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let mut layer = |d: LayerDesc, wmax: i32, bmax: i64, pre: u8, post: u8| {
        let rows = usize::from(d.experts) * usize::from(d.out_dim);
        QLayer {
            desc: d,
            weights: (0..rows * usize::from(d.in_dim))
                .map(|_| rng.gen_range(-wmax..=wmax))
                .collect(),
            bias: (0..rows).map(|_| rng.gen_range(-bmax..=bmax)).collect(),
            requant: (0..d.out_dim)
                .map(|i| Requant {
                    multiplier: rng.gen_range(1 << 30..i32::MAX),
                    pre_shift: pre,
                    post_shift: post,
                    frac: 8 + (i % 4) as u8,
                })
                .collect(),
            cp: None,
        }
    };
    let layers = vec![
        layer(desc(6, 8, 5, I16, I32, Elu), 8000, 1 << 28, 16, 44),
        layer(desc(8, 7, 5, I8, I64, Elu), 127, 1 << 40, 20, 40),
        layer(desc(7, 5, 1, I8, I32, Identity), 127, 1 << 20, 4, 36),
    ];
    QModel {
        kind: QKind::Model(ModelKind::Pfnn),
        gating: Gating::CatmullRom { points: 5 },
        input_stage: (0..6)
            .map(|i| (i as f32 - 2.0, 100.0 * (i + 1) as f32))
            .collect(),
        output_stage: (0..5).map(|i| (0.01 * (i + 1) as f32, i as f32)).collect(),
        layers,
    }
}

fn hand_blob() -> Vec<u8> {
    encode(&hand_model()).unwrap()
}

/// Header and payload of a valid blob, to be edited and re-framed with
/// valid CRCs.
#[derive(Clone)]
struct Parts {
    header: Header,
    payload: Vec<u8>,
}

impl Parts {
    fn of(blob: &[u8]) -> Parts {
        let header = Model::from_bytes(blob).unwrap().header().clone();
        let payload = blob[blob.len() - header.payload_len as usize..].to_vec();
        Parts { header, payload }
    }

    /// Frames the header as it stands (its payload CRC and length unchanged).
    fn blob(&self) -> Vec<u8> {
        frame(&self.header, &self.payload)
    }

    /// Recomputes the payload CRC and length after an edit of the payload.
    fn reseal(&mut self) -> &mut Self {
        self.header.payload_crc = crc32(&self.payload);
        self.header.payload_len = self.payload.len() as u32;
        self
    }

    /// Recomputes the RAM and MAC figures after an edit of the layers.
    fn refigure(&mut self) -> &mut Self {
        self.header.ram_bytes = phasegate::ram_bytes(&self.header.layers) as u32;
        self.header.macs_per_frame =
            phasegate::macs(&self.header.gating, &self.header.layers) as u32;
        self
    }

    fn requant_at(&mut self, layer: usize, row: usize) -> &mut [u8] {
        let s =
            self.header.layers[layer].requant_section.offset as usize + row * REQUANT_RECORD_LEN;
        &mut self.payload[s..s + REQUANT_RECORD_LEN]
    }

    fn load(&self) -> Result<(), Error> {
        Model::from_bytes(&self.blob()).map(|_| ())
    }
}

fn payload_start(blob: &[u8]) -> usize {
    (12 + usize::from(u16::from_le_bytes([blob[6], blob[7]]))).next_multiple_of(16)
}

// ---------------------------------------------------------------------------
// (a) Truncation.

#[test]
fn every_truncation_is_refused_with_the_length_it_needs() {
    for blob in [
        quantised(WeightFormat::I8),
        quantised(WeightFormat::I16),
        hand_blob(),
    ] {
        let header_end = 12 + usize::from(u16::from_le_bytes([blob[6], blob[7]]));
        let start = payload_start(&blob);
        for n in 0..blob.len() {
            let needed = if n < 12 {
                12
            } else if n < header_end {
                header_end
            } else if n < start {
                start
            } else {
                blob.len()
            };
            let want = Error::Truncated {
                needed: needed as u32,
                available: n as u32,
            };
            assert_eq!(
                Model::from_bytes(&blob[..n]).unwrap_err(),
                want,
                "prefix {n}"
            );
            assert_eq!(
                Model::from_region(&blob[..n]).unwrap_err(),
                want,
                "prefix {n}"
            );
            let from_prefix = blob_len_from_prefix(&blob[..n]);
            if n >= header_end {
                assert_eq!(from_prefix, Ok(blob.len()));
            } else {
                assert_eq!(from_prefix.unwrap_err(), want);
            }
        }
        assert!(Model::from_bytes(&blob).is_ok());
    }
}

#[test]
fn trailing_bytes_are_refused_by_from_bytes_and_ignored_by_from_region() {
    let blob = hand_blob();
    for extra in [&[0u8][..], &[0xFF; 3], &blob[..]] {
        let mut longer = blob.clone();
        longer.extend_from_slice(extra);
        let want = Error::TrailingBytes {
            blob_len: blob.len() as u32,
            found: longer.len() as u32,
        };
        assert_eq!(Model::from_bytes(&longer).unwrap_err(), want);
        assert_eq!(Model::from_region(&longer).unwrap().blob_len(), blob.len());
    }
}

// ---------------------------------------------------------------------------
// (b) Random damage.

/// The one error a single flipped bit at `pos` must give.
fn single_flip_error(blob: &[u8], damaged: &[u8], pos: usize) -> Error {
    let header_end = 12 + usize::from(u16::from_le_bytes([blob[6], blob[7]]));
    match pos {
        0..4 => Error::BadMagic,
        4..6 => Error::UnsupportedVersion {
            found: u16::from_le_bytes([damaged[4], damaged[5]]),
            supported: 1,
        },
        6..8 => {
            let h = 12 + usize::from(u16::from_le_bytes([damaged[6], damaged[7]]));
            if h > blob.len() {
                Error::Truncated {
                    needed: h as u32,
                    available: blob.len() as u32,
                }
            } else {
                Error::HeaderCorrupt
            }
        }
        p if p < header_end => Error::HeaderCorrupt,
        p if p < payload_start(blob) => Error::HeaderMalformed,
        _ => Error::PayloadCorrupt,
    }
}

fn is_header_class(e: &Error) -> bool {
    matches!(
        e,
        Error::BadMagic
            | Error::UnsupportedVersion { .. }
            | Error::HeaderCorrupt
            | Error::HeaderMalformed
            | Error::Truncated { .. }
            | Error::TrailingBytes { .. }
    )
}

/// Loads a model blob exactly (`true`) or from a region (`false`).
fn load_model(bytes: &[u8], exact: bool) -> Result<(), Error> {
    if exact {
        Model::from_bytes(bytes).map(|_| ())
    } else {
        Model::from_region(bytes).map(|_| ())
    }
}

/// Loads a style blob exactly (`true`) or from a region (`false`).
fn load_style(bytes: &[u8], exact: bool) -> Result<(), Error> {
    if exact {
        Style::from_bytes(bytes).map(|_| ())
    } else {
        Style::from_region(bytes).map(|_| ())
    }
}

fn flip_all(blob: &[u8], seed: u64, random_flips: usize) -> usize {
    flip_all_with(blob, seed, random_flips, load_model)
}

fn flip_all_with(
    blob: &[u8],
    seed: u64,
    random_flips: usize,
    load: fn(&[u8], bool) -> Result<(), Error>,
) -> usize {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let start = payload_start(blob);
    // Every bit of preamble, header and padding, then random bits, half of
    // them in the header region and half in the payload.
    let exhaustive = (0..start * 8).map(|b| (b / 8, b % 8));
    let random: Vec<(usize, usize)> = (0..random_flips)
        .map(|i| {
            let pos = if i % 2 == 0 {
                rng.gen_range(0..start)
            } else {
                rng.gen_range(start..blob.len())
            };
            (pos, rng.gen_range(0..8))
        })
        .collect();
    let mut count = 0;
    for (pos, bit) in exhaustive.chain(random) {
        let mut d = blob.to_vec();
        d[pos] ^= 1 << bit;
        let want = single_flip_error(blob, &d, pos);
        assert_eq!(load(&d, true).unwrap_err(), want, "bit {bit} of byte {pos}");
        assert_eq!(
            load(&d, false).unwrap_err(),
            want,
            "bit {bit} of byte {pos}"
        );
        count += 1;
    }
    count
}

#[test]
fn single_bit_flips_are_refused_with_the_error_of_their_region() {
    let blobs = [
        quantised(WeightFormat::I8),
        quantised(WeightFormat::I16),
        hand_blob(),
    ];
    let mut total = 0;
    for (i, blob) in blobs.iter().enumerate() {
        total += flip_all(blob, 100 + i as u64, 10_000);
    }
    assert!(total >= 30_000, "{total}");
}

#[test]
fn multi_byte_corruptions_are_refused() {
    for (seed, blob) in [quantised(WeightFormat::I8), hand_blob()]
        .iter()
        .enumerate()
    {
        let mut rng = ChaCha8Rng::seed_from_u64(seed as u64);
        let start = payload_start(blob);
        for case in 0..400 {
            let mut d = blob.clone();
            // Where: the header region, the payload, or anywhere.
            let (lo, hi) = match case % 4 {
                0 => (0, start),
                1 | 2 => (start, blob.len()),
                _ => (0, blob.len()),
            };
            let mut touched = Vec::new();
            if case % 2 == 0 {
                // A burst: a run of 2..=16 random bytes.
                let len = rng.gen_range(2..=16).min(hi - lo);
                let at = rng.gen_range(lo..=hi - len);
                for (p, byte) in d.iter_mut().enumerate().skip(at).take(len) {
                    *byte = rng.gen();
                    touched.push(p);
                }
            } else {
                // Scattered: 2..=8 random bytes, each xor-ed with a non-zero value.
                for _ in 0..rng.gen_range(2..=8) {
                    let p = rng.gen_range(lo..hi);
                    d[p] ^= rng.gen_range(1..=255u8);
                    touched.push(p);
                }
            }
            if d == *blob {
                continue;
            }
            let e = Model::from_bytes(&d).expect_err("damaged blob loaded");
            let _ = Model::from_region(&d).expect_err("damaged blob loaded");
            if touched.iter().all(|&p| p >= start) {
                assert_eq!(e, Error::PayloadCorrupt, "case {case}");
            } else if touched.iter().all(|&p| p < start) {
                assert!(is_header_class(&e), "case {case}: {e:?}");
            }
        }
    }
}

// ---------------------------------------------------------------------------
// (c) Valid CRCs, lying header.

/// A named edit of a header and the error it must give.
type Case = (&'static str, Box<dyn Fn(&mut Header)>, Error);

fn refused(p: &Parts) -> Error {
    let blob = p.blob();
    let e = Model::from_bytes(&blob).unwrap_err();
    assert_eq!(Model::from_region(&blob).unwrap_err(), e);
    e
}

#[test]
fn hand_blob_is_valid_and_reframes_identically() {
    let blob = hand_blob();
    let p = Parts::of(&blob);
    assert_eq!(p.blob(), blob);
    let h = &p.header;
    assert_eq!(h.layers.len(), 3);
    assert_eq!(
        h.layers
            .iter()
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
        assert!(m
            .header()
            .layers
            .iter()
            .all(|l| l.gated && l.experts == 4 && l.weights.bytes() == bytes));
        assert_eq!(
            (m.input_dim(), m.output_dim(), m.buffer_elements()),
            (20, 12, 24)
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
            Box::new(move |h| h.layers[1].weight_section.offset = len.next_multiple_of(4) + 4),
            Error::SectionOutOfBounds { layer: 1 },
        ),
        (
            "bias misaligned",
            Box::new(|h| h.layers[1].bias_section.offset += 2),
            Error::SectionOutOfBounds { layer: 1 },
        ),
        (
            "requant misaligned",
            Box::new(|h| h.layers[2].requant_section.offset += 1),
            Error::SectionOutOfBounds { layer: 2 },
        ),
        (
            "offset + len overflows u32",
            Box::new(|h| h.layers[0].weight_section.offset = 0xFFFF_FFFC),
            Error::SectionOutOfBounds { layer: 0 },
        ),
        (
            "last section one record too long",
            Box::new(|h| h.layers[2].requant_section.len += 8),
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
            Box::new(|h| h.layers[0].weight_section.len -= 1),
            Error::SectionLength { layer: 0 },
        ),
        (
            "bias one i64 short",
            Box::new(|h| h.layers[1].bias_section.len -= 8),
            Error::SectionLength { layer: 1 },
        ),
        (
            "requant one record short",
            Box::new(|h| h.layers[2].requant_section.len -= 8),
            Error::SectionLength { layer: 2 },
        ),
        (
            "bias as if i32",
            Box::new(|h| h.layers[1].acc = AccWidth::I32),
            Error::SectionLength { layer: 1 },
        ),
        (
            "weights as if int8",
            Box::new(|h| h.layers[0].weights = WeightFormat::I8),
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
            Box::new(|h| h.layers[1].weight_section.len = 0),
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
            Box::new(|h| h.layers[1].in_dim = 9),
            Error::DimensionMismatch { layer: 1 },
        ),
        (
            "layer 0 input != model input",
            Box::new(|h| h.layers[0].in_dim = 5),
            Error::DimensionMismatch { layer: 0 },
        ),
        (
            "model input != layer 0 input",
            Box::new(|h| h.input_dim = 7),
            Error::DimensionMismatch { layer: 0 },
        ),
        (
            "model output != last layer output",
            Box::new(|h| h.output_dim = 4),
            Error::DimensionMismatch { layer: 2 },
        ),
        (
            "zero-width layer",
            Box::new(|h| h.layers[1].out_dim = 0),
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
            Box::new(|h| h.layers.clear()),
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
            Box::new(|h| h.layers[0].experts = 4),
            Error::GatingMismatch { layer: 0 },
        ),
        (
            "ungated layer with 5 experts",
            Box::new(|h| h.layers[2].experts = 5),
            Error::GatingMismatch { layer: 2 },
        ),
        (
            "ungated layer marked gated",
            Box::new(|h| h.layers[2].gated = true),
            Error::GatingMismatch { layer: 2 },
        ),
        (
            "gated layer marked ungated",
            Box::new(|h| h.layers[1].gated = false),
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
    assert_eq!(base.header.ram_bytes, 2 * 8 * 2);
    assert_eq!(base.header.macs_per_frame, 4 * 6 * 8 + 4 * 8 * 7 + 7 * 5);
    for (ram, macs) in [
        (34, 451),
        (30, 451),
        (0, 451),
        (u32::MAX, 451),
        (32, 452),
        (32, 450),
        (32, 0),
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
    let l0 = base.header.layers[0];
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

/// Frames raw header bytes with a valid CRC, as the document says.
fn frame_raw(header: &[u8], payload: &[u8]) -> Vec<u8> {
    let mut out = b"PGMB".to_vec();
    out.extend(1u16.to_le_bytes());
    out.extend(u16::try_from(header.len()).unwrap().to_le_bytes());
    let crc = crc32(&out.iter().chain(header).copied().collect::<Vec<_>>());
    out.extend(crc.to_le_bytes());
    out.extend(header);
    out.resize(out.len().next_multiple_of(16), 0);
    out.extend(payload);
    out
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
    // Unknown enum variants: kind (byte 0; 0-2 are taken), gating (byte 1).
    assert_eq!(header[..3], [0x00, 0x03, 0x05]);
    for (at, v) in [(0, 3u8), (0, 0x7f), (1, 4), (1, 0x80)] {
        let mut h = header.clone();
        h[at] = v;
        malformed(&h);
    }
    // Layer 0 starts at byte 6 (kind, gating tag, points, input, output, count):
    // op, in, out, experts, weights, acc, activation, gated.
    assert_eq!(
        header[5..14],
        [0x03, 0x00, 0x06, 0x08, 0x05, 0x01, 0x00, 0x01, 0x01]
    );
    // Unknown op (0-2 are taken), weight format, accumulator, activation; bool 2.
    for (at, v) in [(6, 3u8), (10, 2), (11, 2), (12, 2), (13, 2), (13, 0xff)] {
        let mut h = header.clone();
        h[at] = v;
        malformed(&h);
    }
    // More layers than a header holds: the layer count says 9.
    let layer = p.header.layers[0];
    let nine: Vec<LayerDesc> = vec![layer; 9];
    let h = &p.header;
    let too_many = postcard::to_allocvec(&(
        h.kind,
        h.gating,
        h.input_dim,
        h.output_dim,
        nine,
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

// ---------------------------------------------------------------------------
// (d) Bad arguments.

#[test]
fn runtime_capacity_is_checked_when_it_is_made() {
    let blob = hand_blob(); // widest layer: 8
    let model = Model::from_bytes(&blob).unwrap();
    assert_eq!(model.buffer_elements(), 8);
    assert_eq!(
        Runtime::<7>::new(model.clone()).err(),
        Some(Error::BufferTooSmall {
            needed: 8,
            capacity: 7
        })
    );
    assert_eq!(
        Runtime::<0>::new(model.clone()).err(),
        Some(Error::BufferTooSmall {
            needed: 8,
            capacity: 0
        })
    );
    assert!(Runtime::<8>::new(model.clone()).is_ok());
    assert_eq!(Runtime::<8>::CAPACITY_BYTES, 32);
    assert_eq!(model.ram_bytes(), Runtime::<8>::CAPACITY_BYTES);
    let q = quantised(WeightFormat::I8);
    let model = Model::from_bytes(&q).unwrap();
    assert_eq!(
        Runtime::<23>::new(model.clone()).err(),
        Some(Error::BufferTooSmall {
            needed: 24,
            capacity: 23
        })
    );
    assert!(Runtime::<24>::new(model).is_ok());
}

#[test]
fn run_refuses_bad_slices_and_non_finite_values() {
    let blob = hand_blob();
    let mut rt: Runtime<'_, 8> = Runtime::new(Model::from_bytes(&blob).unwrap()).unwrap();
    let x = [0.5f32, -1.0, 2.0, 0.0, 0.25, -0.75];
    let p = Phase::from_bits(0x1234_5678);
    let mut y = [0f32; 5];
    rt.run(p, &x, &mut y).unwrap();
    let good = y;

    let mut short = [0f32; 4];
    assert_eq!(
        rt.run(p, &x, &mut short),
        Err(Error::LengthMismatch {
            expected: 5,
            found: 4
        })
    );
    let mut long = [0f32; 6];
    assert_eq!(
        rt.run(p, &x, &mut long),
        Err(Error::LengthMismatch {
            expected: 5,
            found: 6
        })
    );
    assert_eq!(
        rt.run(p, &x[..5], &mut y),
        Err(Error::LengthMismatch {
            expected: 6,
            found: 5
        })
    );
    assert_eq!(
        rt.run(p, &[0.0; 7], &mut y),
        Err(Error::LengthMismatch {
            expected: 6,
            found: 7
        })
    );
    assert_eq!(
        rt.run(p, &[], &mut y),
        Err(Error::LengthMismatch {
            expected: 6,
            found: 0
        })
    );
    assert_eq!(
        rt.run_quantised(p, &[0; 5]).err(),
        Some(Error::LengthMismatch {
            expected: 6,
            found: 5
        })
    );
    assert_eq!(
        rt.run_quantised(p, &[0; 9]).err(),
        Some(Error::LengthMismatch {
            expected: 6,
            found: 9
        })
    );
    for (i, bad) in [
        (0, f32::NAN),
        (3, f32::INFINITY),
        (5, f32::NEG_INFINITY),
        (2, -f32::NAN),
    ] {
        let mut xi = x;
        xi[i] = bad;
        assert_eq!(
            rt.run(p, &xi, &mut y),
            Err(Error::NonFinite { index: i as u32 }),
            "{bad} at {i}"
        );
        let mut q = [0i16; 6];
        assert_eq!(
            rt.quantise_input(&xi, &mut q),
            Err(Error::NonFinite { index: i as u32 })
        );
    }
    let mut xi = x;
    (xi[1], xi[4]) = (f32::NAN, f32::NAN);
    assert_eq!(rt.run(p, &xi, &mut y), Err(Error::NonFinite { index: 1 }));
    for r in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        assert_eq!(Phase::from_radians(r), Err(Error::NonFinite { index: 0 }));
    }
    let mut q = [0i16; 5];
    assert_eq!(
        rt.quantise_input(&x, &mut q),
        Err(Error::BufferTooSmall {
            needed: 6,
            capacity: 5
        })
    );
    assert_eq!(
        rt.quantise_input(&x[..5], &mut [0i16; 6]),
        Err(Error::LengthMismatch {
            expected: 6,
            found: 5
        })
    );
    assert_eq!(
        rt.dequantise_output(&[0; 4], &mut [0.0; 5]),
        Err(Error::LengthMismatch {
            expected: 5,
            found: 4
        })
    );
    assert_eq!(
        rt.dequantise_output(&[0; 5], &mut [0.0; 6]),
        Err(Error::LengthMismatch {
            expected: 5,
            found: 6
        })
    );

    // None of that disturbed the runtime.
    rt.run(p, &x, &mut y).unwrap();
    assert_eq!(y, good);
}

// ---------------------------------------------------------------------------
// Extreme but valid: inputs at +-f32::MAX, every kind of phase.

/// Phases: the edges of the cycle and of every expert's segment, plus a
/// stride through all of u32.
fn phases() -> Vec<u32> {
    let mut v = vec![
        0,
        1,
        u32::MAX,
        u32::MAX - 1,
        1 << 31,
        (1 << 31) - 1,
        1 << 30,
        3 << 30,
    ];
    for n in [4u64, 5, 10, 50] {
        for k in 0..n {
            let edge = ((k << 32) / n) as u32;
            v.extend([edge, edge.wrapping_sub(1), edge.wrapping_add(1)]);
        }
    }
    v.extend((0..2048u32).map(|i| i.wrapping_mul(0x0020_0003) ^ (i << 7)));
    v
}

fn extreme_inputs(n: usize) -> Vec<Vec<f32>> {
    let alt = |a: f32, b: f32| (0..n).map(|i| if i % 2 == 0 { a } else { b }).collect();
    vec![
        vec![f32::MAX; n],
        vec![-f32::MAX; n],
        alt(f32::MAX, -f32::MAX),
        alt(-f32::MAX, f32::MAX),
        vec![0.0; n],
        vec![1e30; n],
        vec![f32::MIN_POSITIVE / 8.0; n],
    ]
}

/// Runs every extreme input at every phase; returns the quantised outputs.
fn hammer<const W: usize>(model: Model<'_>, phases: &[u32]) -> Vec<Vec<i16>> {
    let Ok(mut rt) = Runtime::<W>::new(model) else {
        return Vec::new();
    };
    let (n, m) = (rt.model().input_dim(), rt.model().output_dim());
    let mut outs = Vec::new();
    for x in extreme_inputs(n) {
        let mut q = vec![0i16; n];
        rt.quantise_input(&x, &mut q).unwrap();
        for &ph in phases {
            let mut y = vec![0f32; m];
            rt.run(Phase::from_bits(ph), &x, &mut y).unwrap();
            let yq = rt.run_quantised(Phase::from_bits(ph), &q).unwrap().to_vec();
            let mut back = vec![0f32; m];
            rt.dequantise_output(&yq, &mut back).unwrap();
            assert_eq!(
                back.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                y.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
            );
            outs.push(yq);
        }
    }
    outs
}

#[test]
fn extreme_inputs_and_any_phase_on_real_blobs() {
    for blob in [
        quantised(WeightFormat::I8),
        quantised(WeightFormat::I16),
        hand_blob(),
    ] {
        let model = Model::from_bytes(&blob).unwrap();
        let rt: Runtime<'_, 24> = Runtime::new(model.clone()).unwrap();
        let n = model.input_dim();
        // The input stage saturates: every scale is positive.
        let mut q = vec![0i16; n];
        rt.quantise_input(&vec![f32::MAX; n], &mut q).unwrap();
        assert!(q.iter().all(|&v| v == i16::MAX));
        rt.quantise_input(&vec![-f32::MAX; n], &mut q).unwrap();
        assert!(q.iter().all(|&v| v == i16::MIN));
        let outs = hammer::<24>(model, &phases());
        assert_eq!(outs.len(), 7 * phases().len());
    }
}

/// A valid blob built to saturate: all-positive weights at full scale,
/// 64-bit accumulators and biases at the extremes, the largest multiplier
/// and no shift. Every output row must come out pinned at the i16 rail
/// that the sign of its inputs selects, whatever the phase.
#[test]
fn saturating_blob_pins_its_outputs() {
    let experts = 5u16;
    let mut layers = Vec::new();
    for (i, (inp, out)) in [(6u16, 8u16), (8, 4)].into_iter().enumerate() {
        let rows = usize::from(experts) * usize::from(out);
        layers.push(QLayer {
            desc: desc(
                inp,
                out,
                experts,
                if i == 0 {
                    WeightFormat::I16
                } else {
                    WeightFormat::I8
                },
                AccWidth::I64,
                Activation::Identity,
            ),
            weights: vec![if i == 0 { 32767 } else { 127 }; rows * usize::from(inp)],
            bias: vec![0; rows],
            requant: vec![
                Requant {
                    multiplier: i32::MAX,
                    pre_shift: 0,
                    post_shift: 0,
                    frac: 0
                };
                usize::from(out)
            ],
            cp: None,
        });
    }
    let m = QModel {
        kind: QKind::Model(ModelKind::Pfnn),
        gating: Gating::CatmullRom { points: experts },
        input_stage: vec![(0.0, 1.0); 6],
        output_stage: vec![(1.0, 0.0); 4],
        layers,
    };
    let blob = encode(&m).unwrap();
    let outs = hammer::<8>(Model::from_bytes(&blob).unwrap(), &phases());
    let per = phases().len();
    // The five experts are equal and the gate sums to exactly 1.0 at every
    // phase, so each output is the sign of sum(x) pinned to a rail.
    // Inputs: +MAX, -MAX, alternating (+32767 -32768 ...: negative), the
    // other alternation (also negative), 0, 1e30, a subnormal (rounds to 0).
    let expect = [i16::MAX, i16::MIN, i16::MIN, i16::MIN, 0, i16::MAX, 0];
    for (k, &e) in expect.iter().enumerate() {
        for o in &outs[k * per..(k + 1) * per] {
            assert_eq!(o, &[e; 4], "input pattern {k}");
        }
    }

    // The same with biases at the i64 extremes: the blend saturates in i64
    // instead of wrapping, then the requantisation saturates.
    let mut m2 = m.clone();
    for l in &mut m2.layers {
        for (j, b) in l.bias.iter_mut().enumerate() {
            *b = if j % 2 == 0 { i64::MAX } else { i64::MIN };
        }
    }
    let blob2 = encode(&m2).unwrap();
    let outs2 = hammer::<8>(Model::from_bytes(&blob2).unwrap(), &phases());
    assert_eq!(outs2.len(), 7 * per);
    assert!(outs2
        .iter()
        .flatten()
        .all(|&v| v == i16::MAX || v == i16::MIN || v == 0));
}

/// An i32 layer at the exact accumulator bound, fed the worst input.
#[test]
fn i32_row_at_the_bound_does_not_wrap() {
    let d = desc(
        2,
        2,
        1,
        WeightFormat::I16,
        AccWidth::I32,
        Activation::Identity,
    );
    let m = QModel {
        kind: QKind::Model(ModelKind::Mlp),
        gating: Gating::Single,
        input_stage: vec![(0.0, 1.0); 2],
        output_stage: vec![(1.0, 0.0); 2],
        layers: vec![QLayer {
            desc: d,
            // Row 0: sum |w| = 65535, the largest that loads.
            weights: vec![-32768, -32767, 32767, 32767],
            bias: vec![i32::MIN as i64, i32::MAX as i64],
            // Identity requantisation of the blended sum (Q16 gate): >> 16, then * 1.
            requant: vec![
                Requant {
                    multiplier: 1,
                    pre_shift: 16,
                    post_shift: 16,
                    frac: 0
                };
                2
            ],
            cp: None,
        }],
    };
    let blob = encode(&m).unwrap();
    let mut rt: Runtime<'_, 2> = Runtime::new(Model::from_bytes(&blob).unwrap()).unwrap();
    // acc0 = 65535 * 32768 = 2147450880 = i32::MAX - 32767; + bias i32::MIN = -32768.
    let y = rt
        .run_quantised(Phase::from_bits(0), &[-32768, -32768])
        .unwrap()
        .to_vec();
    // Row 0: (2147450880 - 2147483648) = -32768 -> >>16 -> -0.5 -> rounds up to 0.
    // Row 1: -65534*32768 + i32::MAX = -2147418112 + 2147483647 = 65535 -> 1.
    assert_eq!(y, [0, 1]);
}

// ---------------------------------------------------------------------------
// (e) Property tests: nothing panics.

fn loads_and_runs(bytes: &[u8]) {
    for m in [Model::from_bytes(bytes), Model::from_region(bytes)]
        .into_iter()
        .flatten()
    {
        hammer::<64>(m, &[0, 0x4000_0000, u32::MAX]);
    }
    let _ = blob_len_from_prefix(bytes);
}

/// One random edit of a header.
#[derive(Clone, Debug)]
enum Edit {
    Dim {
        layer: usize,
        which: u8,
        value: u16,
    },
    Experts {
        layer: usize,
        value: u16,
    },
    Gated {
        layer: usize,
    },
    Section {
        layer: usize,
        which: u8,
        offset: u32,
        len: u32,
    },
    Format {
        layer: usize,
        weights: bool,
        acc: bool,
        elu: bool,
    },
    Gating(Gating),
    Figures {
        ram: u32,
        macs: u32,
    },
    Model {
        input: u16,
        output: u16,
    },
    Payload {
        at: usize,
        byte: u8,
    },
}

fn arb_edit() -> impl Strategy<Value = Edit> {
    let small = prop_oneof![0u16..12, any::<u16>()];
    prop_oneof![
        (0usize..3, 0u8..2, small.clone()).prop_map(|(layer, which, value)| Edit::Dim {
            layer,
            which,
            value
        }),
        (0usize..3, small.clone()).prop_map(|(layer, value)| Edit::Experts { layer, value }),
        (0usize..3).prop_map(|layer| Edit::Gated { layer }),
        (
            0usize..3,
            0u8..3,
            prop_oneof![0u32..2048, any::<u32>()],
            prop_oneof![0u32..512, any::<u32>()]
        )
            .prop_map(|(layer, which, offset, len)| Edit::Section {
                layer,
                which,
                offset,
                len
            }),
        (0usize..3, any::<bool>(), any::<bool>(), any::<bool>()).prop_map(
            |(layer, weights, acc, elu)| Edit::Format {
                layer,
                weights,
                acc,
                elu
            }
        ),
        prop_oneof![
            Just(Gating::Single),
            small.clone().prop_map(|tables| Gating::Constant { tables }),
            small.clone().prop_map(|tables| Gating::Linear { tables }),
            small
                .clone()
                .prop_map(|points| Gating::CatmullRom { points }),
        ]
        .prop_map(Edit::Gating),
        (any::<u32>(), any::<u32>()).prop_map(|(ram, macs)| Edit::Figures { ram, macs }),
        (small.clone(), small).prop_map(|(input, output)| Edit::Model { input, output }),
        (any::<usize>(), any::<u8>()).prop_map(|(at, byte)| Edit::Payload { at, byte }),
    ]
}

fn apply(p: &mut Parts, e: &Edit) {
    let n = p.header.layers.len().max(1);
    match *e {
        Edit::Dim {
            layer,
            which,
            value,
        } => {
            if let Some(l) = p.header.layers.get_mut(layer % n) {
                if which == 0 {
                    l.in_dim = value;
                } else {
                    l.out_dim = value;
                }
            }
        }
        Edit::Experts { layer, value } => {
            if let Some(l) = p.header.layers.get_mut(layer % n) {
                l.experts = value;
            }
        }
        Edit::Gated { layer } => {
            if let Some(l) = p.header.layers.get_mut(layer % n) {
                l.gated = !l.gated;
            }
        }
        Edit::Section {
            layer,
            which,
            offset,
            len,
        } => {
            if let Some(l) = p.header.layers.get_mut(layer % n) {
                let s = match which {
                    0 => &mut l.weight_section,
                    1 => &mut l.bias_section,
                    _ => &mut l.requant_section,
                };
                *s = Section { offset, len };
            }
        }
        Edit::Format {
            layer,
            weights,
            acc,
            elu,
        } => {
            if let Some(l) = p.header.layers.get_mut(layer % n) {
                l.weights = if weights {
                    WeightFormat::I16
                } else {
                    WeightFormat::I8
                };
                l.acc = if acc { AccWidth::I64 } else { AccWidth::I32 };
                l.activation = if elu {
                    Activation::Elu
                } else {
                    Activation::Identity
                };
            }
        }
        Edit::Gating(g) => p.header.gating = g,
        Edit::Figures { ram, macs } => (p.header.ram_bytes, p.header.macs_per_frame) = (ram, macs),
        Edit::Model { input, output } => {
            (p.header.input_dim, p.header.output_dim) = (input, output)
        }
        Edit::Payload { at, byte } => {
            let len = p.payload.len();
            p.payload[at % len] = byte;
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
        loads_and_runs(&bytes);
        // The same bytes behind a valid preamble start (magic and version).
        let mut b = b"PGMB\x01\x00".to_vec();
        b.extend(&bytes);
        loads_and_runs(&b);
    }

    #[test]
    fn random_mutations_of_a_valid_blob_never_panic(
        edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..8),
        cut in proptest::option::of(any::<usize>()),
        extra in proptest::collection::vec(any::<u8>(), 0..4),
    ) {
        let blob = hand_blob();
        let mut b = blob.clone();
        for &(at, v) in &edits {
            let i = at % b.len();
            b[i] = v;
        }
        if let Some(c) = cut {
            b.truncate(c % (b.len() + 1));
        }
        b.extend(&extra);
        let changed = b != blob;
        loads_and_runs(&b);
        if changed {
            prop_assert!(Model::from_bytes(&b).is_err());
        }
    }

    /// Headers that lie with valid CRCs, and payloads edited and resealed:
    /// refused or loaded, never a panic; what loads runs on extreme inputs.
    #[test]
    fn lying_headers_with_valid_crcs_never_panic(
        edits in proptest::collection::vec(arb_edit(), 1..5),
        refigure in any::<bool>(),
    ) {
        let mut p = Parts::of(&hand_blob());
        for e in &edits {
            apply(&mut p, e);
        }
        p.reseal();
        if refigure {
            p.refigure();
        }
        loads_and_runs(&p.blob());
    }

    /// Random weights, biases and requantisation records in a valid layout.
    #[test]
    fn random_payload_values_never_panic(seed in any::<u64>(), density in 1usize..64) {
        let mut p = Parts::of(&hand_blob());
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        for _ in 0..density {
            let at = rng.gen_range(0..p.payload.len());
            p.payload[at] = rng.gen();
        }
        // Keep the requantisation records loadable half of the time.
        if seed % 2 == 0 {
            for l in 0..3 {
                for r in 0..usize::from(p.header.layers[l].out_dim) {
                    let rec = p.requant_at(l, r);
                    rec[4] %= 63;
                    rec[5] %= 63;
                    rec[6] %= 16;
                    rec[7] = 0;
                }
            }
        }
        p.reseal();
        loads_and_runs(&p.blob());
    }
}

// ---------------------------------------------------------------------------
// (f) CP models and style blobs: the same guarantees.

struct CpAndStyles {
    cp: Vec<u8>,
    base: Vec<u8>,
    styles: Vec<Vec<u8>>,
}

fn cp_and_styles() -> CpAndStyles {
    use host_sim::target::synthetic;
    let opts = QuantOptions {
        calibration_samples: 128,
        ..QuantOptions::default()
    };
    let cp = exporter::export::export(&synthetic::cp_net(3, 20, 24, 12, 6), None, &opts)
        .unwrap()
        .0;
    let pfnn = synthetic::pfnn_base(4, 20, 24, 12);
    let base = export(&pfnn, None, &opts).unwrap().0;
    let net = pfnn.clone();
    let styles = ["cp", "diagonal", "full"]
        .iter()
        .enumerate()
        .map(|(i, form)| {
            let ad = synthetic::adapter(form, 24, 5, 30 + i as u64);
            synthetic::style_blob(&base, &net, &ad, form, None).unwrap()
        })
        .collect();
    CpAndStyles { cp, base, styles }
}

/// Every mix of `styles` (none, each one, each ordered pair blended at
/// weights 0, 1/2 and 1).
fn mixes(styles: usize) -> Vec<Mix> {
    let mut v = vec![Mix::Base];
    for a in 0..styles as u8 {
        v.push(Mix::One(StyleId(a)));
        for b in 0..styles as u8 {
            for w in [0.0, 0.5, 1.0] {
                v.push(Mix::Blend {
                    from: StyleId(a),
                    to: StyleId(b),
                    weight: BlendWeight::from_num(w),
                });
            }
        }
    }
    v
}

/// Runs extreme inputs at `phases` through the styled runtime with every
/// mix; the float and the integer paths agree bit for bit.
fn hammer_styled(base: Model<'_>, styles: &[Style<'_>], phases: &[u32]) -> usize {
    let Ok(mut rt) = StyledRuntime::<'_, 64, 256, 4>::new(base) else {
        return 0;
    };
    let attached = styles.iter().filter(|s| rt.add_style(**s).is_ok()).count();
    let (n, m) = (rt.model().input_dim(), rt.model().output_dim());
    let mut runs = 0;
    for mix in mixes(attached) {
        rt.set_mix(mix).unwrap();
        for x in extreme_inputs(n) {
            let mut q = vec![0i16; n];
            rt.quantise_input(&x, &mut q).unwrap();
            for &ph in phases {
                let mut y = vec![0f32; m];
                rt.run(Phase::from_bits(ph), &x, &mut y).unwrap();
                let yq = rt.run_quantised(Phase::from_bits(ph), &q).unwrap().to_vec();
                let mut back = vec![0f32; m];
                rt.dequantise_output(&yq, &mut back).unwrap();
                assert_eq!(
                    back.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    y.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
                );
                runs += 1;
            }
        }
    }
    runs
}

#[test]
fn single_bit_flips_in_cp_models_and_styles_are_refused() {
    let b = cp_and_styles();
    let mut total = flip_all_with(&b.cp, 200, 4_000, load_model);
    for (i, s) in b.styles.iter().enumerate() {
        total += flip_all_with(s, 210 + i as u64, 2_000, load_style);
    }
    assert!(total >= 10_000, "{total}");
}

#[test]
fn cp_models_and_styles_take_extreme_inputs_at_any_phase() {
    let b = cp_and_styles();
    let outs = hammer::<64>(Model::from_bytes(&b.cp).unwrap(), &phases());
    assert_eq!(outs.len(), 7 * phases().len());
    let styles: Vec<Style<'_>> = b
        .styles
        .iter()
        .map(|s| Style::from_bytes(s).unwrap())
        .collect();
    let some_phases: Vec<u32> = phases().into_iter().step_by(16).collect();
    let runs = hammer_styled(Model::from_bytes(&b.base).unwrap(), &styles, &some_phases);
    assert_eq!(runs, mixes(3).len() * 7 * some_phases.len());
}

/// Splits a blob into its postcard header bytes and its payload.
fn raw_parts(blob: &[u8]) -> (Vec<u8>, Vec<u8>) {
    let header_len = usize::from(u16::from_le_bytes([blob[6], blob[7]]));
    (
        blob[12..12 + header_len].to_vec(),
        blob[payload_start(blob)..].to_vec(),
    )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Random edits of a CP model's or a style's header bytes, framed with a
    /// valid header CRC (so the header decoder and every check behind it
    /// see them): refused with an error, or loaded and then run with
    /// extreme inputs at any phase and every mix, never a panic.
    #[test]
    fn lying_cp_and_style_headers_never_panic(
        which in 0usize..4,
        edits in proptest::collection::vec((any::<u16>(), any::<u8>()), 1..6),
    ) {
        let b = cp_and_styles_cached();
        let blob = if which == 0 { &b.cp } else { &b.styles[which - 1] };
        let (mut header, payload) = raw_parts(blob);
        for (at, v) in edits {
            let i = usize::from(at) % header.len();
            header[i] = v;
        }
        let damaged = frame_raw(&header, &payload);
        let few = [0, 0x4000_0000, u32::MAX];
        if which == 0 {
            for m in [Model::from_bytes(&damaged), Model::from_region(&damaged)].into_iter().flatten() {
                hammer::<64>(m, &few);
            }
        } else if let Ok(style) = Style::from_bytes(&damaged) {
            hammer_styled(Model::from_bytes(&b.base).unwrap(), &[style], &few);
        }
        let _ = Style::from_region(&damaged);
        let _ = blob_len_from_prefix(&damaged);
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Random factors, cores, middle and requantisation records, biases
    /// (a CP model's or a style's payload bytes edited, the payload CRC
    /// resealed): the loader's overflow proof refuses what could wrap or
    /// saturate; what loads runs on extreme inputs, never a panic.
    #[test]
    fn random_cp_and_style_payload_values_never_panic(
        which in 0usize..4,
        seed in any::<u64>(),
        density in 1usize..32,
    ) {
        let b = cp_and_styles_cached();
        let blob = if which == 0 { &b.cp } else { &b.styles[which - 1] };
        let mut header = phasegate::blob::Framed::parse(blob, true).unwrap().header;
        let mut payload = raw_parts(blob).1;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        for _ in 0..density {
            let at = rng.gen_range(0..payload.len());
            payload[at] = rng.gen();
        }
        header.payload_crc = crc32(&payload);
        let damaged = frame(&header, &payload);
        let few = [0, 0x4000_0000, u32::MAX];
        if which == 0 {
            if let Ok(m) = Model::from_bytes(&damaged) {
                hammer::<64>(m, &few);
            }
        } else if let Ok(style) = Style::from_bytes(&damaged) {
            hammer_styled(Model::from_bytes(&b.base).unwrap(), &[style], &few);
        }
    }
}

/// Built once: the exporter's calibration is the slow part.
fn cp_and_styles_cached() -> &'static CpAndStyles {
    static BLOBS: std::sync::OnceLock<CpAndStyles> = std::sync::OnceLock::new();
    BLOBS.get_or_init(cp_and_styles)
}
