//! CP-decomposed gated layers end to end: decomposition, quantisation,
//! blob, loader proof and fixed-point runtime against the float reference;
//! the loader's refusals; CP-ALS on tensors of known rank.

use exporter::cp::als::{cp_als, AlsOptions, CpFactors};
use exporter::cp::import::{read_cp_net, write_cp_net};
use exporter::cp::report::{output_error, run_blob, run_float};
use exporter::encode::frame;
use exporter::export::export;
use exporter::net::{CpLayer, Net, NetLayer};
use exporter::net::{ExpertLayer, GatingMode};
use exporter::quantise::quantise_net;
use exporter::quantise::QuantOptions;
use ndarray::{Array1, Array2};
use phasegate::blob::{crc32, Framed, LayerOp, WeightFormat, PAYLOAD_ALIGN, PREAMBLE_LEN};
use phasegate::ops::cp::MidRecord;
use phasegate::{Error, Model, Phase, Runtime};

fn lay(h: &mut phasegate::Header, i: usize) -> &mut phasegate::blob::LayerDesc {
    match &mut h.nodes[i].op {
        phasegate::blob::NodeOp::Layer(d) => d,
        phasegate::blob::NodeOp::Softmax(_) => panic!("node {i} is not a layer"),
    }
}
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn normal(rng: &mut ChaCha8Rng) -> f64 {
    // Irwin-Hall: close enough to normal for weights.
    (0..12).map(|_| rng.gen_range(0.0..1.0)).sum::<f64>() - 6.0
}

fn dense_layer(rng: &mut ChaCha8Rng, out: usize, inp: usize, experts: usize) -> ExpertLayer {
    let sd = 1.5 / (inp as f64).sqrt();
    let base = Array2::from_shape_fn((out, inp), |_| normal(rng) * sd);
    ExpertLayer {
        w: (0..experts)
            .map(|_| base.mapv(|v| v + 0.4 * sd * normal(rng)))
            .collect(),
        b: (0..experts)
            .map(|_| Array1::from_shape_fn(out, |_| 0.1 * normal(rng)))
            .collect(),
    }
}

/// A small PFNN-shaped dense network (cubic gating, 4 control points).
fn dense_net(seed: u64, dims: [usize; 4]) -> Net {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let [inp, h0, h1, out] = dims;
    Net {
        mode: GatingMode::Cubic,
        xmean: Array1::from_shape_fn(inp, |_| normal(&mut rng)),
        xstd: Array1::from_shape_fn(inp, |_| rng.gen_range(0.2..3.0)),
        ymean: Array1::from_shape_fn(out, |_| 3.0 * normal(&mut rng)),
        ystd: Array1::from_shape_fn(out, |_| rng.gen_range(0.1..10.0)),
        layers: vec![
            NetLayer::Dense(dense_layer(&mut rng, h0, inp, 4)),
            NetLayer::Dense(dense_layer(&mut rng, h1, h0, 4)),
            NetLayer::Dense(dense_layer(&mut rng, out, h1, 4)),
        ],
        wiring: exporter::net::Wiring::Chain,
    }
}

fn decompose(net: &Net, rank: usize, layers: &[usize]) -> Net {
    let mut cp = net.clone();
    for &l in layers {
        let NetLayer::Dense(d) = &net.layers[l] else {
            unreachable!()
        };
        cp.layers[l] = NetLayer::Cp(
            CpLayer::decompose(
                d,
                rank,
                &AlsOptions {
                    ridge: 1e-2,
                    ..AlsOptions::default()
                },
            )
            .0,
        );
    }
    cp
}

fn samples(net: &Net, n: usize, seed: u64) -> (Vec<Vec<f64>>, Vec<f64>) {
    let s =
        exporter::calibrate::normal_inputs(&net.xmean.to_vec(), &net.xstd.to_vec(), n, 1.0, seed);
    (s.inputs, s.phases)
}

/// Fixed point against the float CP network it was quantised from: the
/// error is bounded, and int16 weights cut it by far.
#[test]
fn cp_blobs_track_their_float_network() {
    let dense = dense_net(1, [40, 48, 32, 20]);
    for layers in [vec![0, 1, 2], vec![1]] {
        let net = decompose(&dense, 12, &layers);
        let (xs, ps) = samples(&net, 200, 2);
        let y_float = run_float(&net, &xs, &ps);
        let mut errs = Vec::new();
        for w in [WeightFormat::I8, WeightFormat::I16] {
            let (blob, report) = export(
                &net,
                None,
                &QuantOptions {
                    weights: w,
                    ..QuantOptions::default()
                },
            )
            .unwrap();
            assert!(report.overflow_proof);
            let y_fixed = run_blob(&blob, &xs, &ps).unwrap();
            let e = output_error(&y_fixed, &y_float, &net.ymean.to_vec(), &net.ystd.to_vec());
            println!("layers {layers:?} {w:?}: {e:?}, {} bytes", blob.len());
            errs.push(e.rel_normalised);
        }
        assert!(errs[0] < 0.02, "int8 {errs:?}");
        assert!(errs[1] < 0.002, "int16 {errs:?}");
        assert!(errs[1] < errs[0] / 4.0, "{errs:?}");
    }
}

/// A CP layer never expands W: MACs per frame follow `R (in + out + K)`,
/// and the arena must hold the middle vector beside the input and output.
#[test]
fn header_figures_count_the_factors() {
    let dense = dense_net(3, [10, 8, 8, 6]);
    let net = decompose(&dense, 20, &[1]);
    let (blob, _) = export(&net, None, &QuantOptions::default()).unwrap();
    let m = Model::from_bytes(&blob).unwrap();
    let h = m.header().decoded();
    assert!(matches!(
        h.nodes[1].layer().unwrap().op,
        LayerOp::Cp { rank: 20, .. }
    ));
    assert_eq!(
        u64::from(m.macs_per_frame()),
        4 * 10 * 8 + 20 * (8 + 8 + 4) + 4 * 8 * 6
    );
    // The CP layer's input, middle vector (the rank, 20) and output are
    // live together: 8 + 20 + 8.
    assert_eq!(m.arena_elements(), 36);
    assert!(matches!(
        Runtime::<35>::new(m.clone()),
        Err(Error::BufferTooSmall {
            needed: 36,
            capacity: 35
        })
    ));
    assert!(Runtime::<36>::new(m).is_ok());
}

/// Same blob, same input, same bits, on every call (integer only).
#[test]
fn cp_inference_is_deterministic_and_phase_continuous() {
    let dense = dense_net(4, [16, 24, 24, 8]);
    let net = decompose(&dense, 6, &[0, 1, 2]);
    let (blob, _) = export(&net, None, &QuantOptions::default()).unwrap();
    let mut rt: Runtime<'_, 64> = Runtime::new(Model::from_bytes(&blob).unwrap()).unwrap();
    let x: Vec<f32> = net.xmean.iter().map(|&v| v as f32 + 0.3).collect();
    let mut prev: Option<Vec<f32>> = None;
    for i in 0..256u32 {
        let phase = Phase::from_bits(i << 24);
        let mut a = vec![0f32; 8];
        let mut b = vec![0f32; 8];
        rt.run(phase, &x, &mut a).unwrap();
        rt.run(phase, &x, &mut b).unwrap();
        assert_eq!(a, b);
        if let Some(p) = prev {
            // Small phase steps, small output steps (the spline is smooth).
            let step: f32 = a
                .iter()
                .zip(&p)
                .map(|(u, v)| (u - v).abs())
                .fold(0.0, f32::max);
            let scale: f32 = net.ystd.iter().map(|&s| s as f32).fold(0.0, f32::max);
            assert!(step < 0.5 * scale, "phase step {i}: {step}");
        }
        prev = Some(a);
    }
}

/// Header, payload and the start of the payload of a blob.
fn split(blob: &[u8]) -> (phasegate::Header, Vec<u8>) {
    let f = Framed::parse(blob, true).unwrap();
    (f.header.decoded(), f.payload.to_vec())
}

fn reframe(mut header: phasegate::Header, payload: &[u8]) -> Vec<u8> {
    header.payload_crc = crc32(payload);
    frame(&header, payload)
}

#[test]
fn loader_refuses_bad_cp_layers() {
    let dense = dense_net(5, [12, 10, 10, 6]);
    let net = decompose(&dense, 5, &[1]);
    let (blob, _) = export(&net, None, &QuantOptions::default()).unwrap();
    assert!(Model::from_bytes(&blob).is_ok());
    let (header, payload) = split(&blob);
    let LayerOp::Cp {
        rank,
        a,
        cores,
        mid,
    } = header.nodes[1].layer().unwrap().op
    else {
        panic!("layer 1 should be CP")
    };
    assert_eq!(rank, 5);

    // A middle record with its reserved byte set.
    let mut p = payload.clone();
    p[mid.offset as usize + 7] = 1;
    assert_eq!(
        Model::from_bytes(&reframe(header.clone(), &p)).unwrap_err(),
        Error::UnsupportedParameter { layer: 1 }
    );
    // A middle record whose shift cannot keep t * c within i32.
    let mut p = payload.clone();
    let at = mid.offset as usize;
    let mut rec = MidRecord::from_bytes(p[at..at + 8].try_into().unwrap()).unwrap();
    rec.pre_shift = 0;
    p[at..at + 8].copy_from_slice(&rec.to_bytes());
    assert_eq!(
        Model::from_bytes(&reframe(header.clone(), &p)).unwrap_err(),
        Error::AccumulatorOverflow { layer: 1, row: 0 }
    );
    // A shift out of range.
    let mut p = payload.clone();
    p[at + 4] = 63;
    assert_eq!(
        Model::from_bytes(&reframe(header.clone(), &p)).unwrap_err(),
        Error::UnsupportedParameter { layer: 1 }
    );
    // Rank zero (with the empty scratch span that rank implies).
    let mut h = header.clone();
    lay(&mut h, 1).op = LayerOp::Cp {
        rank: 0,
        a,
        cores,
        mid,
    };
    h.nodes[1].scratch.len = 0;
    assert_eq!(
        Model::from_bytes(&reframe(h, &payload)).unwrap_err(),
        Error::UnsupportedParameter { layer: 1 }
    );
    // A cores section of the wrong length.
    let mut h = header.clone();
    lay(&mut h, 1).op = LayerOp::Cp {
        rank,
        a,
        cores: phasegate::blob::Section {
            offset: cores.offset,
            len: cores.len - 2,
        },
        mid,
    };
    assert_eq!(
        Model::from_bytes(&reframe(h, &payload)).unwrap_err(),
        Error::SectionLength { layer: 1 }
    );
    // An A section outside the payload.
    let mut h = header.clone();
    lay(&mut h, 1).op = LayerOp::Cp {
        rank,
        a: phasegate::blob::Section {
            offset: payload.len() as u32,
            len: a.len,
        },
        cores,
        mid,
    };
    assert_eq!(
        Model::from_bytes(&reframe(h, &payload)).unwrap_err(),
        Error::SectionOutOfBounds { layer: 1 }
    );
    // Weights too large for the i32 accumulators of B^T.
    let q = quantise_net(&net, &QuantOptions::default()).unwrap();
    let mut m = q.model.clone();
    assert_eq!(m.layers[1].desc.acc, phasegate::blob::AccWidth::I32);
    m.layers[1].desc.weights = WeightFormat::I16;
    for w in &mut m.layers[1].weights {
        *w = 32767;
    }
    if let Some(cp) = &mut m.layers[1].cp {
        for w in &mut cp.a {
            *w *= 100;
        }
    }
    let bad = exporter::encode::encode(&m).unwrap();
    assert_eq!(
        Model::from_bytes(&bad).unwrap_err(),
        Error::AccumulatorOverflow { layer: 1, row: 0 }
    );
    let _ = (PREAMBLE_LEN, PAYLOAD_ALIGN);
}

/// Factors imported from .npz give the same blob as the network they
/// were written from.
#[test]
fn imported_factors_give_the_same_blob() {
    let dense = dense_net(6, [12, 10, 10, 6]);
    let net = decompose(&dense, 4, &[0, 2]);
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("factors.npz");
    write_cp_net(&net, &p).unwrap();
    let back = read_cp_net(&p, GatingMode::Cubic).unwrap();
    // float32 round trip
    let (a, _) = export(&back, None, &QuantOptions::default()).unwrap();
    let (b, _) = export(&back, None, &QuantOptions::default()).unwrap();
    assert_eq!(a, b);
    let (xs, ps) = samples(&net, 50, 9);
    let e = output_error(
        &run_float(&back, &xs, &ps),
        &run_float(&net, &xs, &ps),
        &net.ymean.to_vec(),
        &net.ystd.to_vec(),
    );
    assert!(e.rel_normalised < 1e-5, "{e:?}");
}

/// The bar for CP-ALS: a tensor of known rank is recovered to 1e-6.
#[test]
fn cp_als_recovers_a_tensor_of_known_rank() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let (i, j, k, r) = (60, 45, 4, 6);
    let f = CpFactors {
        a: Array2::from_shape_fn((i, r), |_| normal(&mut rng)),
        b: Array2::from_shape_fn((j, r), |_| normal(&mut rng)),
        c: Array2::from_shape_fn((k, r), |_| normal(&mut rng)),
    };
    let slices: Vec<Array2<f64>> = (0..k).map(|kk| f.slice(kk)).collect();
    let res = cp_als(
        &slices,
        r,
        &AlsOptions {
            max_iters: 3000,
            tol: 1e-15,
            ..AlsOptions::default()
        },
    );
    assert!(
        res.rel_error < 1e-6,
        "{} after {} sweeps",
        res.rel_error,
        res.iterations
    );
}

/// The wire bytes of the new header variants (postcard: varint variant
/// index, then the fields), as docs/cp-and-styles.md lists them.
#[test]
fn new_header_variants_have_the_documented_bytes() {
    use phasegate::blob::{LayerOp, ModelKind, Section};
    let enc = |v: &dyn erased::Enc| v.bytes();
    mod erased {
        pub trait Enc {
            fn bytes(&self) -> Vec<u8>;
        }
        impl<T: serde::Serialize> Enc for T {
            fn bytes(&self) -> Vec<u8> {
                postcard::to_allocvec(self).unwrap()
            }
        }
    }
    let s = |offset, len| Section { offset, len };
    assert_eq!(enc(&LayerOp::Dense), [0x00]);
    assert_eq!(
        enc(&LayerOp::Cp {
            rank: 300,
            a: s(16, 8),
            cores: s(24, 2400),
            mid: s(2424, 2400),
        }),
        [0x01, 0xac, 0x02, 0x10, 0x08, 0x18, 0xe0, 0x12, 0xf8, 0x12, 0xe0, 0x12]
    );
    assert_eq!(enc(&LayerOp::Diagonal), [0x02]);
    assert_eq!(enc(&ModelKind::Pfnn), [0x00]);
    assert_eq!(
        enc(&ModelKind::Style {
            base_crc: 0x1234_5678,
            layer: 1,
            name: s(0, 6),
        }),
        [0x02, 0xf8, 0xac, 0xd1, 0x91, 0x01, 0x01, 0x00, 0x06]
    );
}
