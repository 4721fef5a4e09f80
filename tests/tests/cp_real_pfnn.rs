//! CP on the real PFNN (../shared/pfnn/network, or $PHASEGATE_PFNN_DIR):
//! post-hoc decomposition is lossy and the test says how lossy, the CP
//! blobs track their own float network, and a style attaches to the real
//! base. Skipped, with a message, where the weights are absent.

use exporter::cp::als::AlsOptions;
use exporter::cp::export_net;
use exporter::cp::float::{Adapter, CpLayer, FloatNet, NetLayer};
use exporter::cp::report::{decompose_all, output_error, run_blob, run_float};
use exporter::export::export_pfnn;
use exporter::float_pfnn::{FloatPfnn, GatingMode};
use exporter::quantise::QuantOptions;
use exporter::style::build_style;
use ndarray::{Array1, Array2};
use phasegate::blob::WeightFormat;
use std::path::{Path, PathBuf};

fn pfnn_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("PHASEGATE_PFNN_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/pfnn/network"));
    if dir.join("Xmean.bin").is_file() {
        Some(dir)
    } else {
        eprintln!(
            "skipped: real PFNN weights not found at {} (set PHASEGATE_PFNN_DIR)",
            dir.display()
        );
        None
    }
}

fn load(dir: &Path) -> FloatPfnn {
    let t = exporter::pfnn_dir::load_pfnn_dir(dir).unwrap();
    FloatPfnn::from_tables(&t, GatingMode::Cubic).0
}

#[test]
fn post_hoc_cp_of_the_real_pfnn_is_lossy_and_its_blobs_are_faithful() {
    let Some(dir) = pfnn_dir() else { return };
    let dense = load(&dir);
    let (net, layers) = decompose_all(
        &dense,
        64,
        &AlsOptions {
            max_iters: 60,
            ridge: 1e-2,
            ..AlsOptions::default()
        },
    );
    let s =
        exporter::calibrate::normal_inputs(&dense.xmean.to_vec(), &dense.xstd.to_vec(), 96, 1.0, 7);
    let (ym, ys) = (dense.ymean.to_vec(), dense.ystd.to_vec());
    let y_dense = run_float(&FloatNet::from_pfnn(&dense), &s.inputs, &s.phases);
    let y_cp = run_float(&net, &s.inputs, &s.phases);
    let e = output_error(&y_cp, &y_dense, &ym, &ys);
    println!(
        "rank 64: layers {:?}",
        layers.iter().map(|l| l.rel_frobenius).collect::<Vec<_>>()
    );
    println!("rank 64: float CP vs dense {e:?}");
    // Honest bars: at rank 64 every layer keeps most of its energy, yet the
    // network's outputs are far off (measured 0.66).
    assert!(layers
        .iter()
        .all(|l| l.rel_frobenius > 0.2 && l.rel_frobenius < 0.8));
    assert!((0.4..0.9).contains(&e.rel_normalised), "{e:?}");
    // (format, rms bar, bytes of the dense blob of that format)
    for (w, rms, dense_bytes) in [
        (WeightFormat::I16, 0.05, 4_830_592),
        (WeightFormat::I8, 1.5, 2_423_312),
    ] {
        let (blob, rep) = export_net(
            &net,
            &QuantOptions {
                weights: w,
                ..QuantOptions::default()
            },
        )
        .unwrap();
        let y = run_blob(&blob, &s.inputs, &s.phases).unwrap();
        let fe = output_error(&y, &y_cp, &ym, &ys);
        println!(
            "{w:?}: {} bytes, {} MACs, fixed vs float {fe:?}",
            blob.len(),
            rep.macs_per_frame
        );
        assert!(rep.overflow_proof);
        assert!(fe.rms < rms, "{w:?}: {fe:?}");
        assert!(blob.len() < dense_bytes / 10);
    }
}

#[test]
fn a_style_attaches_to_the_real_base_and_tracks_its_float_reference() {
    let Some(dir) = pfnn_dir() else { return };
    let dense = load(&dir);
    let (base, _) = export_pfnn(&dense, None, &QuantOptions::default()).unwrap();
    let net = FloatNet::from_pfnn(&dense);
    let (h, r) = (512, 30);
    let f =
        |i: usize, j: usize, s: f64| s * (((i * 7919 + j * 104_729) % 1000) as f64 / 500.0 - 1.0);
    let adapter = Adapter {
        layer: 1,
        op: NetLayer::Cp(CpLayer {
            a: Array2::from_shape_fn((h, r), |(i, j)| f(i, j, 0.05)),
            b: Array2::from_shape_fn((h, r), |(i, j)| f(j, i, 0.05)),
            d: Array2::from_shape_fn((4, r), |(k, j)| 1.0 + f(k, j, 0.3)),
            bias: vec![Array1::zeros(h); 4],
        }),
    };
    let (blob, rep) =
        build_style(&base, &net, &adapter, "test", &QuantOptions::default(), 64).unwrap();
    println!("{rep:?}");
    // About a quarter of the float32 factors, plus per-row biases and records.
    assert!(
        blob.len() < rep.float32_bytes / 2,
        "{} vs {}",
        blob.len(),
        rep.float32_bytes
    );
    assert!(rep.range_used < 1.0);
    assert!(
        rep.fixed_vs_float.rms < 1.5 * rep.base_fixed_vs_float.rms + 0.05,
        "{rep:?}"
    );
}
