//! Host inference speed of the fixed-point runtime: the embedded default
//! model, and (when ../shared/pfnn is present) the real PFNN as int8 and
//! int16 cubic blobs against the f64 float reference, so their ratios come
//! from one run. `cargo bench -p host-sim`.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use exporter::net::{GatingMode, Net};
use exporter::quantise::QuantOptions;
use host_sim::accuracy::sample_matrix;
use phasegate::blob::WeightFormat;
use phasegate::{Model, Phase};
use std::hint::black_box;
use std::path::Path;

fn bench_blob(c: &mut Criterion, name: &str, blob: &[u8], net: &Net) {
    let model = Model::from_bytes(blob).expect("valid blob");
    let macs = u64::from(model.macs_per_frame());
    let mut rt = host_sim::eval::host_runtime(model).expect("runtime");
    let (x, p) = sample_matrix(net, 16, 0.5, 3);
    let mut q = vec![0i16; x.cols];
    let mut group = c.benchmark_group(name);
    group.throughput(Throughput::Elements(macs));
    group.bench_function("fixed-point frame", |b| {
        let mut i = 0;
        b.iter(|| {
            i = (i + 1) % x.rows;
            rt.quantise_input(x.row(i), &mut q).expect("input");
            let out = rt
                .run_quantised(Phase::from_radians(p[i]).expect("phase"), &q)
                .expect("run");
            black_box(out[0])
        })
    });
    let rows: Vec<Vec<f64>> = x
        .iter_rows()
        .map(|r| r.iter().map(|&v| f64::from(v)).collect())
        .collect();
    group.bench_function("f64 float reference frame", |b| {
        let mut i = 0;
        b.iter(|| {
            i = (i + 1) % rows.len();
            black_box(net.forward(&rows[i], f64::from(p[i]))[0])
        })
    });
    group.finish();
}

fn inference(c: &mut Criterion) {
    let net = host_sim::default_model::float_model().expect("embedded model");
    bench_blob(c, "default-int8", host_sim::default_model::BLOB, &net);
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/pfnn/network");
    let Ok(tables) = exporter::pfnn_dir::load_pfnn_dir(&dir) else {
        eprintln!(
            "real PFNN not found at {}: benchmarking the default model only",
            dir.display()
        );
        return;
    };
    let (net, residual) = Net::from_pfnn_tables(&tables, GatingMode::Cubic);
    for (name, weights) in [
        ("pfnn-int8", WeightFormat::I8),
        ("pfnn-int16", WeightFormat::I16),
    ] {
        let opts = QuantOptions {
            weights,
            ..QuantOptions::default()
        };
        let (blob, _) = exporter::export::export(&net, residual, &opts).expect("export");
        bench_blob(c, name, &blob, &net);
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).measurement_time(std::time::Duration::from_secs(3));
    targets = inference
}
criterion_main!(benches);
