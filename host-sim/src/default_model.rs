//! The embedded default model: a small PFNN-shaped network (342 inputs,
//! 311 outputs, 4 Catmull-Rom control points, two hidden layers of
//! [`HIDDEN`]) generated from a fixed seed. Nothing in it comes from the
//! shared PFNN weights; it exists so that every command and test has a
//! model on a fresh machine. Its float source (`model.npz`), its int8 blob
//! and the golden vectors are checked in under `tests/golden/default/`.

use exporter::net::{ExpertLayer, GatingMode, Net, NetLayer};
use ndarray::{Array1, Array2};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

/// Hidden width.
pub const HIDDEN: usize = 32;
/// Input width (PFNN's).
pub const INPUT: usize = 342;
/// Output width (PFNN's).
pub const OUTPUT: usize = 311;
/// The seed; changing it changes every golden file.
pub const SEED: u64 = 0x00DE_FA17_0001;

/// The checked-in float source of the default model.
pub const NPZ: &[u8] = include_bytes!("../../tests/golden/default/model.npz");
/// The checked-in int8 cubic blob of the default model.
pub const BLOB: &[u8] = include_bytes!("../../tests/golden/default/model.blob");

/// Rounded through f32 so the checked-in float32 `.npz` holds it exactly.
fn normal(rng: &mut ChaCha8Rng, sd: f64) -> f64 {
    f64::from((rng.sample::<f64, _>(StandardNormal) * sd) as f32)
}

fn uniform(rng: &mut ChaCha8Rng, lo: f64, hi: f64) -> f64 {
    f64::from(rng.gen_range(lo..hi) as f32)
}

/// One layer: a shared base plus a per-control-point variation, so the
/// output really depends on the phase.
fn layer(rng: &mut ChaCha8Rng, rows: usize, cols: usize, gain: f64) -> ExpertLayer {
    let sd = gain / (cols as f64).sqrt();
    let base = Array2::from_shape_fn((rows, cols), |_| normal(rng, sd));
    let w = (0..4)
        .map(|_| base.mapv(|v| f64::from((v + normal(rng, 0.5 * sd)) as f32)))
        .collect();
    let b = (0..4)
        .map(|_| Array1::from_shape_fn(rows, |_| normal(rng, 0.1)))
        .collect();
    ExpertLayer { w, b }
}

/// Generates the default model (deterministic on every platform).
pub fn generate() -> Net {
    let mut rng = ChaCha8Rng::seed_from_u64(SEED);
    let xmean = Array1::from_shape_fn(INPUT, |_| normal(&mut rng, 2.0));
    let xstd = Array1::from_shape_fn(INPUT, |_| uniform(&mut rng, 0.2, 5.0));
    let ymean = Array1::from_shape_fn(OUTPUT, |_| normal(&mut rng, 5.0));
    let ystd = Array1::from_shape_fn(OUTPUT, |_| uniform(&mut rng, 0.05, 20.0));
    let layers = [
        layer(&mut rng, HIDDEN, INPUT, 1.5),
        layer(&mut rng, HIDDEN, HIDDEN, 1.5),
        layer(&mut rng, OUTPUT, HIDDEN, 1.0),
    ];
    Net {
        mode: GatingMode::Cubic,
        xmean,
        xstd,
        ymean,
        ystd,
        layers: layers.into_iter().map(NetLayer::Dense).collect(),
        wiring: exporter::net::Wiring::Chain,
    }
}

/// The checked-in float source, loaded.
pub fn float_model() -> anyhow::Result<Net> {
    exporter::npz::pfnn_from_npz_bytes(
        NPZ,
        std::path::Path::new("embedded model.npz"),
        GatingMode::Cubic,
    )
}
