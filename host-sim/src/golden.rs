//! Golden vectors of the default model: inputs, phases and the exact i16
//! outputs the runtime must produce, checked in under
//! `tests/golden/default/`. Regenerate with
//! `cargo run --release -p host-sim -- golden --write tests/golden/default`.

use anyhow::{bail, Context, Result};
use exporter::export::export;
use exporter::quantise::QuantOptions;
use std::path::Path;

use crate::accuracy::sample_matrix;
use crate::default_model;
use crate::eval::run_fixed;
use crate::npy::{read_matrix_f32, read_matrix_i16, read_vector_f32, write_matrix, write_vector};

/// Frames in the golden set.
pub const FRAMES: usize = 64;
/// Seed of the golden inputs.
pub const INPUT_SEED: u64 = 0x601D_0001;

/// Writes model.npz, model.blob, inputs.npy, phases.npy, expected_q.npy and
/// expected.npy into `dir`, all derived from the seeds above.
pub fn write(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let net = default_model::generate();
    exporter::npz::pfnn_to_npz(&net, &dir.join("model.npz"))?;
    // Reload so the blob is made from exactly what the .npz holds.
    let net = exporter::npz::pfnn_from_npz(&dir.join("model.npz"), net.mode)?;
    let (blob, _) = export(&net, None, &QuantOptions::default())?;
    exporter::atomic::write_atomic(&dir.join("model.blob"), &blob)?;
    let (x, p) = sample_matrix(&net, FRAMES, 1.0, INPUT_SEED);
    let run = run_fixed(&blob, &x, &p)?;
    write_matrix(&dir.join("inputs.npy"), &x)?;
    write_vector(&dir.join("phases.npy"), &p)?;
    write_matrix(&dir.join("expected_q.npy"), &run.raw)?;
    write_matrix(&dir.join("expected.npy"), &run.outputs)?;
    Ok(())
}

/// Checks the blob in `dir` against its golden vectors, bit for bit.
/// Returns the number of frames compared.
pub fn check(dir: &Path) -> Result<usize> {
    let blob = std::fs::read(dir.join("model.blob"))
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
