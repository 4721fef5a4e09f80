//! `host-sim demo`: a few hundred frames of a model through the fixed-point
//! runtime and the float reference, side by side.

use anyhow::Result;
use exporter::net::Net;
use std::f64::consts::TAU;

use crate::accuracy::sample_matrix;
use crate::compare::{compare, Comparison};
use crate::eval::{run_fixed, run_reference};

/// What the demo measured.
pub struct DemoReport {
    /// Frames run.
    pub frames: usize,
    /// Bytes of the blob.
    pub blob_bytes: usize,
    /// Activation RAM the model needs.
    pub ram_bytes: usize,
    /// MACs per frame from the header.
    pub macs_per_frame: u32,
    /// Fixed vs float.
    pub comparison: Comparison,
}

/// Frames whose phase walks through the cycle (a gait cycle every 60
/// frames) with inputs drawn from the model's normalisation statistics.
pub fn run_demo(blob: &[u8], net: &Net, frames: usize, seed: u64) -> Result<DemoReport> {
    let (x, _) = sample_matrix(net, frames, 1.0, seed);
    let phases: Vec<f32> = (0..frames)
        .map(|i| ((i as f64 * TAU / 60.0) % TAU) as f32)
        .collect();
    let fixed = run_fixed(blob, &x, &phases)?;
    let float = run_reference(net, &x, &phases)?;
    let model = phasegate::Model::from_bytes(blob).map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(DemoReport {
        frames,
        blob_bytes: blob.len(),
        ram_bytes: model.ram_bytes(),
        macs_per_frame: model.macs_per_frame(),
        comparison: compare(&fixed.outputs, &float)?,
    })
}

impl DemoReport {
    /// The text `host-sim demo` prints.
    pub fn render(&self, title: &str) -> String {
        format!(
            "{title}\n{} frames, fixed point (runtime) vs float reference, absolute error in output units:\n\n{}\nblob size        {} bytes\nRAM needed       {} bytes of activations\nMACs per frame   {}\n",
            self.frames,
            self.comparison.table(),
            self.blob_bytes,
            self.ram_bytes,
            self.macs_per_frame
        )
    }
}
