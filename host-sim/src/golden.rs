//! Golden io bundles: for each case, a float source, the blob exported from
//! it, inputs, phases and the exact i16 (and de-quantised) outputs the
//! runtime must produce, checked in under `tests/golden/<case>/`. One case
//! per op kind and weight width:
//!
//! | case | network | ops | weights |
//! |---|---|---|---|
//! | `default` | the embedded default model (342 -> 32 -> 32 -> 311) | dense x3 | int8 |
//! | `dense-int16` | the same network | dense x3 | int16 |
//! | `cp-diagonal` | a synthetic 48 -> 40 -> 40 -> 24 network | CP (rank 12), diagonal, CP (rank 6) | int8 |
//! | `omg-tiny-fe-r1` | the trained tiny FE-OMG model (`models/omg/tiny_fe_r1`, `host-sim demo`'s), 440 -> 404, on its first 64 reference frames | dense x15 (MLPs, 4-expert layers), softmax gate | int8 |
//! | `omg-small-rbfcat-r1` | the committed small RBF-CAT OMG model (`models/omg/small_rbfcat_r1`), 440 -> 404, on the first 64 frames of its reference rollout | dense x15, RBF (32 clusters over the 64-wide latent), softmax gate | int8 (RBF centres int16) |
//! | `dec-graph` | a synthetic graph with OMG's DEC clustering layer (`synthetic::clustering_net`: encoder 6 -> 32, soft assignment to 16 centres, head on `[q, z]` -> 5) | dense x2, DEC | int8 (DEC centres int16) |
//! | `softmax-graph` | the branching proof model (`synthetic::branching_net`: gating MLP -> softmax; two encoders -> concatenation -> three softmax-gated layers -> decoder on a slice), 40 -> 10 | dense x12, softmax gate | int8 |
//!
//! Regenerate them all (after a deliberate change to the arithmetic) with
//! `cargo run --release -p host-sim -- golden --write tests/golden`, or one
//! case with `... golden --write tests/golden/<case>`.

use anyhow::{bail, Context, Result};
use exporter::export::export;
use exporter::net::Net;
use exporter::quantise::QuantOptions;
use phasegate::blob::WeightFormat;
use std::path::Path;

use crate::accuracy::sample_matrix;
use crate::default_model;
use crate::eval::run_fixed;
use crate::npy::{matrix_bytes, read_matrix_f32, read_matrix_i16, read_vector_f32, vector_bytes};
use crate::target::synthetic;

/// Frames in each golden set.
pub const FRAMES: usize = 64;
/// Seed of the golden inputs.
pub const INPUT_SEED: u64 = 0x601D_0001;
/// Every case, by directory name.
pub const CASES: [&str; 7] = [
    "default",
    "dense-int16",
    "cp-diagonal",
    "softmax-graph",
    OMG_CASE,
    RBF_CASE,
    DEC_CASE,
];

/// The trained OMG model `host-sim demo` runs (its float source is the
/// committed `models/omg/tiny_fe_r1`, so the bundle has no `model.npz`; its
/// inputs are the model's first reference frames, phases 0).
pub const OMG_CASE: &str = "omg-tiny-fe-r1";

/// The RBF op's case: a trained RBF-CAT model, read from its committed
/// directory (so no `model.npz` either), on the first frames of its
/// reference rollout.
pub const RBF_CASE: &str = "omg-small-rbfcat-r1";

/// The DEC op's case: no DEC model is trained, so a synthetic graph made
/// in code ([`synthetic::clustering_net`]; no `model.npz`: graph
/// descriptions have no clustering ops), on normal inputs.
pub const DEC_CASE: &str = "dec-graph";

/// The committed model directory of [`RBF_CASE`].
fn rbf_case_model() -> std::path::PathBuf {
    crate::target::build::repo_root().join("models/omg/small_rbfcat_r1")
}

/// The files of a bundle.
pub fn files(case: &str) -> &'static [&'static str] {
    if [OMG_CASE, RBF_CASE, DEC_CASE].contains(&case) {
        &[
            "model.blob",
            "inputs.npy",
            "phases.npy",
            "expected_q.npy",
            "expected.npy",
        ]
    } else {
        &[
            "model.npz",
            "model.blob",
            "inputs.npy",
            "phases.npy",
            "expected_q.npy",
            "expected.npy",
        ]
    }
}

/// The float network of `case` and the options it is exported with.
fn case_source(case: &str) -> Result<(Net, QuantOptions)> {
    Ok(match case {
        "default" => (default_model::generate(), QuantOptions::default()),
        "dense-int16" => (
            default_model::generate(),
            QuantOptions {
                weights: WeightFormat::I16,
                ..QuantOptions::default()
            },
        ),
        "cp-diagonal" => (
            synthetic::cp_net(0x601D_0C9D, 48, 40, 24, 12),
            QuantOptions::default(),
        ),
        "softmax-graph" => (
            synthetic::branching_net(0x601D_5F7A),
            QuantOptions::default(),
        ),
        _ => bail!("no golden case {case:?} (cases: {})", CASES.join(", ")),
    })
}

/// Writes the float source (`model.npz`: the PFNN layout for all-dense
/// chains, the `cp-import` layout for other chains; a graph's
/// `model.json` description beside its `model.npz`), model.blob, inputs.npy,
/// phases.npy, expected_q.npy and expected.npy of `case` into `dir`, all
/// derived from fixed seeds.
pub fn write_case(case: &str, dir: &Path) -> Result<()> {
    if case == OMG_CASE {
        return write_omg_case(dir);
    }
    if case == RBF_CASE {
        return write_rbf_case(dir);
    }
    if case == DEC_CASE {
        return write_dec_case(dir);
    }
    let (net, opts) = case_source(case)?;
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let npz = dir.join("model.npz");
    // Reload so the blob is made from exactly what the .npz holds.
    let net = if matches!(net.wiring, exporter::net::Wiring::Graph(_)) {
        let json = dir.join("model.json");
        exporter::net::json::write_graph(&net, &json, &npz)?;
        exporter::net::json::read_graph(&json, &npz)?
    } else if net.layers.iter().all(|l| l.as_dense().is_some()) {
        exporter::npz::pfnn_to_npz(&net, &npz)?;
        exporter::npz::pfnn_from_npz(&npz, net.mode)?
    } else {
        exporter::cp::import::write_cp_net(&net, &npz)?;
        exporter::cp::import::read_cp_net(&npz, net.mode)?
    };
    let (blob, _) = export(&net, None, &opts)?;
    let (x, p) = sample_matrix(&net, FRAMES, 1.0, INPUT_SEED);
    write_frames(dir, &blob, &x, &p)
}

fn write_omg_case(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let e = crate::demo_omg::embedded()?;
    let blob = crate::demo_omg::int8_blob(&e.omg)?;
    let x = crate::demo_omg::reference_frames(FRAMES)?;
    write_frames(dir, &blob, &x, &vec![0f32; x.rows])
}

fn write_dec_case(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let net = synthetic::clustering_net(0x601D_0DEC, 32, 16, true);
    let (blob, _) = export(&net, None, &QuantOptions::default())?;
    let (x, p) = sample_matrix(&net, FRAMES, 1.0, INPUT_SEED);
    write_frames(dir, &blob, &x, &p)
}

fn write_rbf_case(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let d = crate::omg::load_dir(&rbf_case_model())?;
    let opts = crate::omg::exporter_options(WeightFormat::I8);
    let blob = crate::omg::export(&d, WeightFormat::I8, &opts)?;
    // The grounded rollout's frames (the model's own inputs, 300 of them):
    // the reference clip's one-step frames are only 60.
    let first = &d.refs.rollout;
    let cols = first.dims[2];
    let rows = FRAMES.min(first.dims[1]);
    let x = crate::npy::Matrix {
        rows,
        cols,
        data: first.data[..rows * cols]
            .iter()
            .map(|&v| v as f32)
            .collect(),
    };
    write_frames(dir, &blob, &x, &vec![0f32; x.rows])
}

/// The blob, inputs, phases and the outputs `blob` gives on them, written
/// together (all or none).
fn write_frames(dir: &Path, blob: &[u8], x: &crate::npy::Matrix<f32>, p: &[f32]) -> Result<()> {
    let run = run_fixed(blob, x, p)?;
    let mut out = exporter::atomic::Outputs::new();
    out.add(dir.join("model.blob"), blob.to_vec());
    out.add(dir.join("inputs.npy"), matrix_bytes(x)?);
    out.add(dir.join("phases.npy"), vector_bytes(p)?);
    out.add(dir.join("expected_q.npy"), matrix_bytes(&run.raw)?);
    out.add(dir.join("expected.npy"), matrix_bytes(&run.outputs)?);
    out.commit()
}

/// Writes the case named by `dir`'s last component into `dir`, or, when
/// that names no case, every case into `dir/<case>`.
pub fn write(dir: &Path) -> Result<()> {
    match dir.file_name().and_then(|n| n.to_str()) {
        Some(name) if CASES.contains(&name) => write_case(name, dir),
        _ => CASES.iter().try_for_each(|c| write_case(c, &dir.join(c))),
    }
}

/// Checks `dir` against its golden vectors, bit for bit: one bundle when
/// `dir` holds a `model.blob`, else every case's bundle below it. Returns
/// the number of frames compared.
pub fn check(dir: &Path) -> Result<usize> {
    if dir.join("model.blob").is_file() {
        return check_bundle(dir);
    }
    let mut frames = 0;
    for case in CASES {
        let d = dir.join(case);
        frames += check_bundle(&d).with_context(|| format!("golden case {}", d.display()))?;
    }
    Ok(frames)
}

/// Checks the bundle in `dir` against its golden vectors, bit for bit.
/// Returns the number of frames compared.
fn check_bundle(dir: &Path) -> Result<usize> {
    let blob = exporter::atomic::read_input(&dir.join("model.blob"))
        .with_context(|| format!("cannot read {}/model.blob", dir.display()))?;
    let model =
        phasegate::Model::from_bytes(&blob).map_err(|e| anyhow::anyhow!("model.blob: {e}"))?;
    let x = read_matrix_f32(&dir.join("inputs.npy"), model.input_dim())?;
    let p = read_vector_f32(&dir.join("phases.npy"))?;
    let want_q = read_matrix_i16(&dir.join("expected_q.npy"))?;
    let want = crate::npy::read_matrix_f32_any(&dir.join("expected.npy"))?;
    let run = run_fixed(&blob, &x, &p)?;
    if let Some(i) = run
        .raw
        .data
        .iter()
        .zip(&want_q.data)
        .position(|(a, b)| a != b)
    {
        bail!(
            "golden mismatch: frame {}, output {}: {} != expected {}",
            i / want_q.cols,
            i % want_q.cols,
            run.raw.data[i],
            want_q.data[i]
        );
    }
    if run.raw.data.len() != want_q.data.len() {
        bail!(
            "golden mismatch: {} outputs, expected {}",
            run.raw.data.len(),
            want_q.data.len()
        );
    }
    if let Some(i) = run
        .outputs
        .data
        .iter()
        .zip(&want.data)
        .position(|(a, b)| a.to_bits() != b.to_bits())
    {
        bail!("golden mismatch in de-quantised output {i}");
    }
    Ok(x.rows)
}
