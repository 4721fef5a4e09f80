//! Host inference speed of the fixed-point runtime beside float references,
//! so that ratios come from one run (`cargo bench -p host-sim`; the machines
//! here are noisy, absolute times are not comparable across runs).
//!
//! Models: the embedded default, and (when ../shared/pfnn is present) the
//! real PFNN as int8 and int16 blobs, cubic and constant gating. References:
//! an f32 loop that runs the network the way the PFNN demo does (blend the
//! active experts' weights into one matrix, then one matrix-vector product
//! per layer; constant gating uses its table's matrix as it is), and the
//! exporter's f64 forward pass. After the runs it prints frames per second
//! and the fixed-point / f32 ratio from criterion's own estimates.

use criterion::{criterion_group, Criterion, Throughput};
use exporter::net::{GatingMode, Net, Wiring};
use exporter::ops::NetLayer;
use exporter::quantise::QuantOptions;
use host_sim::accuracy::sample_matrix;
use phasegate::blob::WeightFormat;
use phasegate::{Model, Phase};
use std::hint::black_box;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

/// A dense chain in f32, run as the PFNN demo runs it.
struct DemoF32 {
    gating: Vec<Vec<(usize, f32)>>,
    xmean: Vec<f32>,
    xstd: Vec<f32>,
    ymean: Vec<f32>,
    ystd: Vec<f32>,
    layers: Vec<DemoLayer>,
    blended: Vec<f32>,
    blended_bias: Vec<f32>,
    a: Vec<f32>,
    b: Vec<f32>,
}

/// One layer's experts in f32.
struct DemoLayer {
    out: usize,
    inp: usize,
    /// Row-major `out x inp` matrix per expert.
    w: Vec<Vec<f32>>,
    /// `out` biases per expert.
    b: Vec<Vec<f32>>,
}

impl DemoF32 {
    /// `None` unless `net` is a chain of dense layers.
    fn new(net: &Net, phases: &[f32]) -> Option<Self> {
        if net.wiring != Wiring::Chain {
            return None;
        }
        let to32 = |a: &ndarray::Array1<f64>| a.iter().map(|&v| v as f32).collect::<Vec<_>>();
        let mut layers = Vec::new();
        for l in &net.layers {
            let NetLayer::Dense(d) = l else { return None };
            let (out, inp) = d.dim();
            let w =
                d.w.iter()
                    .map(|m| m.iter().map(|&v| v as f32).collect())
                    .collect();
            layers.push(DemoLayer {
                out,
                inp,
                w,
                b: d.b.iter().map(to32).collect(),
            });
        }
        let widest = layers.iter().map(|l| l.out * l.inp).max().unwrap_or(0);
        let wide = layers.iter().map(|l| l.out.max(l.inp)).max().unwrap_or(0);
        Some(Self {
            // The gate is the phase function's, taken per frame in the demo;
            // computed here up front so both loops time the network alone.
            gating: phases
                .iter()
                .map(|&p| {
                    net.gate(f64::from(p))
                        .into_iter()
                        .map(|(k, g)| (k, g as f32))
                        .collect()
                })
                .collect(),
            xmean: to32(&net.xmean),
            xstd: to32(&net.xstd),
            ymean: to32(&net.ymean),
            ystd: to32(&net.ystd),
            layers,
            blended: vec![0.0; widest],
            blended_bias: vec![0.0; wide],
            a: vec![0.0; wide],
            b: vec![0.0; wide],
        })
    }

    fn frame(&mut self, x: &[f32], frame: usize) -> f32 {
        let gate = &self.gating[frame];
        for (i, &v) in x.iter().enumerate() {
            self.a[i] = (v - self.xmean[i]) / self.xstd[i];
        }
        let last = self.layers.len() - 1;
        for (
            l,
            DemoLayer {
                out,
                inp,
                w,
                b: bias,
            },
        ) in self.layers.iter().enumerate()
        {
            let (m, bb): (&[f32], &[f32]) = match gate.as_slice() {
                [(k, g)] if *g == 1.0 => (&w[*k], &bias[*k]),
                _ => {
                    let m = &mut self.blended[..out * inp];
                    let bb = &mut self.blended_bias[..*out];
                    m.fill(0.0);
                    bb.fill(0.0);
                    for &(k, g) in gate {
                        for (d, s) in m.iter_mut().zip(&w[k]) {
                            *d += g * s;
                        }
                        for (d, s) in bb.iter_mut().zip(&bias[k]) {
                            *d += g * s;
                        }
                    }
                    (&self.blended[..out * inp], &self.blended_bias[..*out])
                }
            };
            for r in 0..*out {
                let row = &m[r * inp..(r + 1) * inp];
                let s = dot(row, &self.a[..*inp]);
                let y = s + bb[r];
                self.b[r] = if l == last || y > 0.0 {
                    y
                } else {
                    y.exp() - 1.0
                };
            }
            std::mem::swap(&mut self.a, &mut self.b);
        }
        self.a[0] * self.ystd[0] + self.ymean[0]
    }
}

/// `w . x` in eight lanes, so the compiler can use SIMD as Eigen does in
/// the demo (a plain sum is one serial chain of float adds).
fn dot(w: &[f32], x: &[f32]) -> f32 {
    let mut lanes = [0f32; 8];
    let (wc, wt) = w.as_chunks::<8>();
    let (xc, xt) = x.as_chunks::<8>();
    for (a, b) in wc.iter().zip(xc) {
        for ((l, a), b) in lanes.iter_mut().zip(a).zip(b) {
            *l += a * b;
        }
    }
    let tail: f32 = wt.iter().zip(xt).map(|(a, b)| a * b).sum();
    lanes.iter().sum::<f32>() + tail
}

const FIXED: &str = "fixed-point frame";
const DEMO: &str = "f32 demo loop frame";
const F64: &str = "f64 float reference frame";

fn bench_blob(c: &mut Criterion, name: &str, blob: &[u8], net: &Net) {
    let model = Model::from_bytes(blob).expect("valid blob");
    let macs = u64::from(model.macs_per_frame());
    let mut rt = host_sim::eval::host_runtime(model).expect("runtime");
    let (x, p) = sample_matrix(net, 16, 0.5, 3);
    let mut q = vec![0i16; x.cols];
    let mut group = c.benchmark_group(name);
    group.throughput(Throughput::Elements(macs));
    group.bench_function(FIXED, |b| {
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
    if let Some(mut demo) = DemoF32::new(net, &p) {
        // A reference that computed something else would time nothing.
        for i in 0..x.rows {
            let (got, want) = (
                demo.frame(x.row(i), i),
                net.forward(&rows[i], f64::from(p[i]))[0],
            );
            assert!(
                (f64::from(got) - want).abs() <= 1e-3 * (1.0 + want.abs()),
                "{name}: f32 demo loop gives {got}, the f64 reference {want}"
            );
        }
        group.bench_function(DEMO, |b| {
            let mut i = 0;
            b.iter(|| {
                i = (i + 1) % x.rows;
                black_box(demo.frame(x.row(i), i))
            })
        });
    }
    group.bench_function(F64, |b| {
        let mut i = 0;
        b.iter(|| {
            i = (i + 1) % rows.len();
            black_box(net.forward(&rows[i], f64::from(p[i]))[0])
        })
    });
    group.finish();
}

/// The groups benchmarked, for the summary.
fn groups() -> Vec<&'static str> {
    vec![
        "default-int8",
        "pfnn-cubic-int8",
        "pfnn-cubic-int16",
        "pfnn-constant-int8",
        "pfnn-constant-int16",
    ]
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
    for (mode, mode_name) in [
        (GatingMode::Cubic, "cubic"),
        (GatingMode::Constant, "constant"),
    ] {
        let (net, residual) = Net::from_pfnn_tables(&tables, mode);
        for (weights, bits) in [(WeightFormat::I8, "int8"), (WeightFormat::I16, "int16")] {
            let opts = QuantOptions {
                weights,
                ..QuantOptions::default()
            };
            let (blob, _) = exporter::export::export(&net, residual, &opts).expect("export");
            bench_blob(c, &format!("pfnn-{mode_name}-{bits}"), &blob, &net);
        }
    }
}

/// Criterion's point estimate of the mean time of `group/function`, in ns,
/// if this run wrote it (a filtered run leaves older estimates behind).
fn mean_ns(root: &Path, group: &str, function: &str, since: SystemTime) -> Option<f64> {
    let path = root
        .join(group)
        .join(function)
        .join("new")
        .join("estimates.json");
    if std::fs::metadata(&path).ok()?.modified().ok()? < since {
        return None;
    }
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(path).ok()?).ok()?;
    v["mean"]["point_estimate"].as_f64()
}

/// Where criterion wrote its estimates: `$CRITERION_HOME`, else the
/// target directory's `criterion` (the bench runs from `target/release/deps`).
fn criterion_home() -> Option<PathBuf> {
    if let Some(h) = std::env::var_os("CRITERION_HOME") {
        return Some(h.into());
    }
    let exe = std::env::current_exe().ok()?;
    Some(exe.parent()?.parent()?.parent()?.join("criterion"))
}

fn summary(since: SystemTime) {
    let Some(root) = criterion_home() else { return };
    println!("\nframes per second (this run; criterion mean estimates)");
    println!(
        "{:<22} {:>14} {:>14} {:>14} {:>16}",
        "model", "fixed point", "f32 demo loop", "f64 reference", "fixed / f32 demo"
    );
    for g in groups() {
        let fps = |f| mean_ns(&root, g, f, since).map(|ns| 1e9 / ns);
        let Some(fixed) = fps(FIXED) else { continue };
        let cell = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.0}"));
        let demo = fps(DEMO);
        println!(
            "{:<22} {:>14.0} {:>14} {:>14} {:>16}",
            g,
            fixed,
            cell(demo),
            cell(fps(F64)),
            demo.map_or("-".to_string(), |d| format!("{:.2}x", fixed / d))
        );
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).measurement_time(std::time::Duration::from_secs(3));
    targets = inference
}

fn main() {
    let since = SystemTime::now();
    benches();
    Criterion::default().configure_from_args().final_summary();
    summary(since);
}
