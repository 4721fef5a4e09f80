//! Style blobs (residual adapters beside a base layer, the paper's eq. 4):
//! every adapter form against its float reference, switching and blending
//! between frames, and the refusals (another base, wrong layer, full bank,
//! damaged blobs).

use exporter::encode::{encode, QKind};
use exporter::export::export;
use exporter::net::{Adapter, CpLayer, DiagLayer, ExpertLayer, GatingMode, Net, NetLayer};
use exporter::quantise::QuantOptions;
use exporter::style::{build_style, quantise_adapter, run_styled};
use ndarray::{Array1, Array2};
use phasegate::style::BlendWeight as U1F15;
use phasegate::{Error, Mix, Model, Phase, Runtime, Style, StyleId};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const IN: usize = 24;
const HID: usize = 20;
const OUT: usize = 10;

fn normal(rng: &mut ChaCha8Rng) -> f64 {
    (0..12).map(|_| rng.gen_range(0.0..1.0)).sum::<f64>() - 6.0
}

fn dense_layer(rng: &mut ChaCha8Rng, out: usize, inp: usize) -> ExpertLayer {
    let sd = 1.5 / (inp as f64).sqrt();
    let base = Array2::from_shape_fn((out, inp), |_| normal(rng) * sd);
    ExpertLayer {
        w: (0..4)
            .map(|_| base.mapv(|v| v + 0.4 * sd * normal(rng)))
            .collect(),
        b: (0..4)
            .map(|_| Array1::from_shape_fn(out, |_| 0.1 * normal(rng)))
            .collect(),
    }
}

fn base_pfnn(seed: u64) -> Net {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    Net {
        mode: GatingMode::Cubic,
        xmean: Array1::from_shape_fn(IN, |_| normal(&mut rng)),
        xstd: Array1::from_shape_fn(IN, |_| rng.gen_range(0.2..3.0)),
        ymean: Array1::from_shape_fn(OUT, |_| 3.0 * normal(&mut rng)),
        ystd: Array1::from_shape_fn(OUT, |_| rng.gen_range(0.1..10.0)),
        layers: [
            dense_layer(&mut rng, HID, IN),
            dense_layer(&mut rng, HID, HID),
            dense_layer(&mut rng, OUT, HID),
        ]
        .into_iter()
        .map(NetLayer::Dense)
        .collect(),
        wiring: exporter::net::Wiring::Chain,
    }
}

fn adapter(form: &str, seed: u64) -> Adapter {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let sd = 0.4 / (HID as f64).sqrt();
    let vecs = |rng: &mut ChaCha8Rng, s: f64| -> Vec<Array1<f64>> {
        (0..4)
            .map(|_| Array1::from_shape_fn(HID, |_| s * normal(rng)))
            .collect()
    };
    let op = match form {
        "full" => NetLayer::Dense(ExpertLayer {
            w: (0..4)
                .map(|_| Array2::from_shape_fn((HID, HID), |_| sd * normal(&mut rng)))
                .collect(),
            b: vecs(&mut rng, 0.1),
        }),
        "diagonal" => NetLayer::Diagonal(DiagLayer {
            w: vecs(&mut rng, 0.3),
            b: vecs(&mut rng, 0.1),
        }),
        _ => NetLayer::Cp(CpLayer {
            a: Array2::from_shape_fn((HID, 3), |_| 0.3 * normal(&mut rng)),
            b: Array2::from_shape_fn((HID, 3), |_| 0.3 * normal(&mut rng)),
            d: Array2::from_shape_fn((4, 3), |_| 0.4 + 0.1 * normal(&mut rng)),
            bias: vecs(&mut rng, 0.1),
        }),
    };
    Adapter { layer: 1, op }
}

struct Fixture {
    net: Net,
    blob: Vec<u8>,
}

fn fixture(seed: u64) -> Fixture {
    let pfnn = base_pfnn(seed);
    let (blob, _) = export(&pfnn, None, &QuantOptions::default()).unwrap();
    Fixture {
        net: pfnn.clone(),
        blob,
    }
}

fn samples(net: &Net, n: usize) -> (Vec<Vec<f64>>, Vec<f64>) {
    let s = exporter::calibrate::normal_inputs(&net.xmean.to_vec(), &net.xstd.to_vec(), n, 1.0, 77);
    (s.inputs, s.phases)
}

/// Each form (full, diagonal, CP) in fixed point tracks the float styled
/// network, and changes the outputs by far more than that error.
#[test]
fn every_adapter_form_tracks_its_float_reference() {
    let f = fixture(1);
    for (i, form) in ["full", "diagonal", "cp"].into_iter().enumerate() {
        let ad = adapter(form, 10 + i as u64);
        for w in [
            phasegate::blob::WeightFormat::I8,
            phasegate::blob::WeightFormat::I16,
        ] {
            let opts = QuantOptions {
                weights: w,
                ..QuantOptions::default()
            };
            let (blob, r) = build_style(&f.blob, &f.net, &ad, form, &opts, 200).unwrap();
            println!(
                "{form} {w:?}: {} bytes, effect {:.4}, fixed vs float {:.5} (base {:.5})",
                blob.len(),
                r.style_effect.rel_normalised,
                r.fixed_vs_float.rel_normalised,
                r.base_fixed_vs_float.rel_normalised
            );
            assert!(r.style_effect.rel_normalised > 0.05, "{form}: {r:?}");
            // The base's own int8 error plus a little for the adapter.
            assert!(
                r.fixed_vs_float.rel_normalised
                    < 2.0 * r.base_fixed_vs_float.rel_normalised + 0.005,
                "{form} {w:?}: {r:?}"
            );
            assert!(r.fixed_vs_float.rel_normalised < 0.1 * r.style_effect.rel_normalised);
            let s = Style::from_bytes(&blob).unwrap();
            assert_eq!(s.name(), form);
            assert_eq!(s.layer(), 1);
            assert_eq!(
                s.base_crc(),
                Model::from_bytes(&f.blob).unwrap().header().payload_crc
            );
        }
    }
}

fn styles(f: &Fixture) -> Vec<Vec<u8>> {
    ["full", "diagonal", "cp"]
        .into_iter()
        .enumerate()
        .map(|(i, form)| {
            build_style(
                &f.blob,
                &f.net,
                &adapter(form, 20 + i as u64),
                form,
                &QuantOptions::default(),
                16,
            )
            .unwrap()
            .0
        })
        .collect()
}

fn run_one(rt: &mut Runtime<'_, 64, 128, 4>, phase: Phase, x: &[f32]) -> Vec<f32> {
    let mut y = vec![0f32; OUT];
    rt.run(phase, x, &mut y).unwrap();
    y
}

/// Switching between frames is exactly as if the new mix had been used all
/// along: the styled runtime keeps no state but the mix. With no style it
/// is the plain runtime, bit for bit.
#[test]
fn switching_styles_between_frames_is_exact_and_stateless() {
    let f = fixture(2);
    let blobs = styles(&f);
    let model = Model::from_bytes(&f.blob).unwrap();
    let mut rt: Runtime<'_, 64, 128, 4> = Runtime::new(model.clone()).unwrap();
    let ids: Vec<StyleId> = blobs
        .iter()
        .map(|b| rt.add_style(Style::from_bytes(b).unwrap()).unwrap())
        .collect();
    let mut plain: Runtime<'_, 64> = Runtime::new(model.clone()).unwrap();
    let (xs, _) = samples(&f.net, 40);
    let mixes = [
        Mix::Base,
        Mix::One(ids[0]),
        Mix::One(ids[1]),
        Mix::One(ids[2]),
    ];
    let mut phase = Phase::from_bits(0);
    for (frame, x) in xs.iter().enumerate() {
        let x: Vec<f32> = x.iter().map(|&v| v as f32).collect();
        let mix = mixes[(frame * 7 + frame / 3) % 4];
        rt.set_mix(mix).unwrap();
        let y = run_one(&mut rt, phase, &x);
        let mut fresh: Runtime<'_, 64, 128, 4> = Runtime::new(model.clone()).unwrap();
        for b in &blobs {
            fresh.add_style(Style::from_bytes(b).unwrap()).unwrap();
        }
        fresh.set_mix(mix).unwrap();
        assert_eq!(y, run_one(&mut fresh, phase, &x), "frame {frame}");
        if mix == Mix::Base {
            let mut yp = vec![0f32; OUT];
            plain.run(phase, &x, &mut yp).unwrap();
            assert_eq!(y, yp, "frame {frame}");
        } else {
            let mut yp = vec![0f32; OUT];
            plain.run(phase, &x, &mut yp).unwrap();
            assert_ne!(y, yp, "frame {frame}: the style should change the output");
        }
        phase = Phase::from_bits(phase.to_bits().wrapping_add(0x0345_6789));
    }
}

/// Blending: weight 0 and 1 give the two styles exactly; in between, the
/// fixed point tracks the float blend of the adapter outputs.
#[test]
fn blending_two_styles_interpolates_their_adapters() {
    let f = fixture(3);
    let (a, b) = (adapter("cp", 31), adapter("full", 32));
    let opts = QuantOptions::default();
    let sa = build_style(&f.blob, &f.net, &a, "a", &opts, 16).unwrap().0;
    let sb = build_style(&f.blob, &f.net, &b, "b", &opts, 16).unwrap().0;
    let (xs, ps) = samples(&f.net, 120);
    let (ia, ib) = (StyleId(0), StyleId(1));
    let one_a = run_styled(&f.blob, &[&sa, &sb], &|_| Mix::One(ia), &xs, &ps).unwrap();
    let one_b = run_styled(&f.blob, &[&sa, &sb], &|_| Mix::One(ib), &xs, &ps).unwrap();
    let blend = |w: f64| {
        move |_: usize| Mix::Blend {
            from: ia,
            to: ib,
            weight: U1F15::from_num(w),
        }
    };
    assert_eq!(
        run_styled(&f.blob, &[&sa, &sb], &blend(0.0), &xs, &ps).unwrap(),
        one_a
    );
    assert_eq!(
        run_styled(&f.blob, &[&sa, &sb], &blend(1.0), &xs, &ps).unwrap(),
        one_b
    );
    // Weights above 1 clamp to 1.
    assert_eq!(
        run_styled(&f.blob, &[&sa, &sb], &blend(1.9), &xs, &ps).unwrap(),
        one_b
    );
    let (ym, ys) = (f.net.ymean.to_vec(), f.net.ystd.to_vec());
    for w in [0.25, 0.5, 0.8] {
        let fixed = run_styled(&f.blob, &[&sa, &sb], &blend(w), &xs, &ps).unwrap();
        let styled = f.net.with_adapters(&[(&a, 1.0 - w), (&b, w)]).unwrap();
        let float: Vec<Vec<f64>> = xs
            .iter()
            .zip(&ps)
            .map(|(x, &p)| styled.forward(x, p))
            .collect();
        let e = exporter::cp::report::output_error(&fixed, &float, &ym, &ys);
        let spread = exporter::cp::report::output_error(&one_a, &one_b, &ym, &ys);
        println!(
            "blend {w}: {e:?} (styles differ by {:.4})",
            spread.rel_normalised
        );
        assert!(e.rel_normalised < 0.05, "{w}: {e:?}");
        assert!(e.rel_normalised < 0.2 * spread.rel_normalised);
    }
    // A per-frame weight: the blend moves smoothly from a to b.
    let ramp = run_styled(
        &f.blob,
        &[&sa, &sb],
        &|i| Mix::Blend {
            from: ia,
            to: ib,
            weight: U1F15::from_num(i as f64 / 119.0),
        },
        &xs,
        &ps,
    )
    .unwrap();
    assert_eq!(ramp[0], one_a[0]);
    assert_eq!(ramp[119], one_b[119]);
}

/// A style built for another base is refused with both checksums in the
/// error; blobs of the wrong kind are refused by either loader.
#[test]
fn mismatched_styles_are_refused_clearly() {
    let f1 = fixture(4);
    let f2 = fixture(5);
    let (style, _) = build_style(
        &f1.blob,
        &f1.net,
        &adapter("cp", 1),
        "walk",
        &QuantOptions::default(),
        8,
    )
    .unwrap();
    let m1 = Model::from_bytes(&f1.blob).unwrap();
    let m2 = Model::from_bytes(&f2.blob).unwrap();
    let (c1, c2) = (m1.header().payload_crc, m2.header().payload_crc);
    let mut rt: Runtime<'_, 64, 128, 4> = Runtime::new(m2).unwrap();
    let e = rt
        .add_style(Style::from_bytes(&style).unwrap())
        .unwrap_err();
    assert_eq!(
        e,
        Error::StyleMismatch {
            base_crc: c2,
            style_crc: c1
        }
    );
    let msg = e.to_string();
    assert!(
        msg.contains(&format!("{c1:#010x}")) && msg.contains(&format!("{c2:#010x}")),
        "{msg}"
    );
    assert!(rt.styles().is_empty());
    // Kinds.
    assert_eq!(Model::from_bytes(&style).unwrap_err(), Error::NotAModel);
    assert_eq!(Style::from_bytes(&f1.blob).unwrap_err(), Error::NotAStyle);
    // Right base, wrong layer: the adapter does not fit layer 2.
    let mut q = quantise_adapter(
        &m1,
        &f1.net,
        &adapter("cp", 1),
        "x",
        &QuantOptions::default(),
    )
    .unwrap();
    if let QKind::Style { layer, .. } = &mut q.kind {
        *layer = 2;
    }
    let wrong_layer = encode(&q).unwrap();
    let mut q = quantise_adapter(
        &m1,
        &f1.net,
        &adapter("cp", 1),
        "x",
        &QuantOptions::default(),
    )
    .unwrap();
    q.layers[0].requant[0].frac ^= 1;
    let wrong_formats = encode(&q).unwrap();
    let mut rt1: Runtime<'_, 64, 128, 4> = Runtime::new(m1.clone()).unwrap();
    assert_eq!(
        rt1.add_style(Style::from_bytes(&wrong_layer).unwrap())
            .unwrap_err(),
        Error::StyleIncompatible { layer: 2 }
    );
    // Right base and layer, other output formats.
    assert_eq!(
        rt1.add_style(Style::from_bytes(&wrong_formats).unwrap())
            .unwrap_err(),
        Error::StyleIncompatible { layer: 1 }
    );
    // The base layer 0 is not a place for an adapter (the exporter says why).
    let e = quantise_adapter(
        &m1,
        &f1.net,
        &Adapter {
            layer: 0,
            ..adapter("cp", 1)
        },
        "x",
        &QuantOptions::default(),
    )
    .unwrap_err();
    assert!(e.to_string().contains("hidden layer"), "{e}");
}

#[test]
fn bank_scratch_and_ids_are_checked() {
    let f = fixture(6);
    let blobs = styles(&f);
    let model = Model::from_bytes(&f.blob).unwrap();
    // One slot.
    let mut rt: Runtime<'_, 64, 128, 1> = Runtime::new(model.clone()).unwrap();
    let id = rt.add_style(Style::from_bytes(&blobs[2]).unwrap()).unwrap();
    assert_eq!(
        rt.add_style(Style::from_bytes(&blobs[1]).unwrap())
            .unwrap_err(),
        Error::TooManyStyles { capacity: 1 }
    );
    assert_eq!(
        rt.set_mix(Mix::One(StyleId(1))).unwrap_err(),
        Error::UnknownStyle { index: 1 }
    );
    assert_eq!(
        rt.set_mix(Mix::Blend {
            from: id,
            to: StyleId(3),
            weight: U1F15::from_num(0.5)
        })
        .unwrap_err(),
        Error::UnknownStyle { index: 3 }
    );
    assert_eq!(rt.mix(), Mix::Base);
    // Scratch for two adapter outputs (2 x 20) plus the CP rank (3).
    let mut small: Runtime<'_, 64, 42, 2> = Runtime::new(model.clone()).unwrap();
    assert_eq!(
        small
            .add_style(Style::from_bytes(&blobs[2]).unwrap())
            .unwrap_err(),
        Error::BufferTooSmall {
            needed: 43,
            capacity: 42
        }
    );
    let mut exact: Runtime<'_, 64, 43, 2> = Runtime::new(model).unwrap();
    assert!(exact
        .add_style(Style::from_bytes(&blobs[2]).unwrap())
        .is_ok());
}

#[test]
fn damaged_style_blobs_are_refused() {
    let f = fixture(7);
    let (style, _) = build_style(
        &f.blob,
        &f.net,
        &adapter("diagonal", 1),
        "d",
        &QuantOptions::default(),
        8,
    )
    .unwrap();
    let mut bad = style.clone();
    let last = bad.len() - 1;
    bad[last] ^= 0x40;
    assert_eq!(Style::from_bytes(&bad).unwrap_err(), Error::PayloadCorrupt);
    assert!(matches!(
        Style::from_bytes(&style[..style.len() - 3]).unwrap_err(),
        Error::Truncated { .. }
    ));
    let mut long = style.clone();
    long.extend([0xFF; 32]);
    assert!(matches!(
        Style::from_bytes(&long),
        Err(Error::TrailingBytes { .. })
    ));
    assert_eq!(Style::from_region(&long).unwrap().name(), "d");
    // A name that is not UTF-8.
    let m = Model::from_bytes(&f.blob).unwrap();
    let q = quantise_adapter(
        &m,
        &f.net,
        &adapter("diagonal", 1),
        "ok",
        &QuantOptions::default(),
    )
    .unwrap();
    let named = encode(&q).unwrap();
    let framed = phasegate::blob::Framed::parse(&named, true).unwrap();
    let mut header = framed.header.decoded();
    let mut payload = framed.payload.to_vec();
    let phasegate::blob::ModelKind::Style { name, .. } = header.kind else {
        panic!("a style")
    };
    assert_eq!(&payload[name.offset as usize..][..2], b"ok");
    payload[name.offset as usize..][..2].copy_from_slice(&[0xC3, 0x28]);
    header.payload_crc = phasegate::blob::crc32(&payload);
    let bad = exporter::encode::frame(&header, &payload);
    assert_eq!(
        Style::from_bytes(&bad).unwrap_err(),
        Error::UnsupportedParameter {
            layer: phasegate::STAGE
        }
    );
}
