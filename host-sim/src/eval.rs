//! Batch evaluation: the fixed-point runtime and the float reference over
//! the same inputs and phases.

use anyhow::{anyhow, bail, Result};
use exporter::net::Net;
use phasegate::{Model, Phase, Runtime};

use crate::npy::Matrix;

/// Activation buffer capacity of host runs (elements per buffer); large
/// enough for any layer width a blob header can declare.
pub const HOST_CAPACITY: usize = u16::MAX as usize;

/// A runtime with the host capacity, boxed (2 x 128 KiB of buffers).
pub fn host_runtime(model: Model<'_>) -> Result<Box<Runtime<'_, HOST_CAPACITY>>> {
    Ok(Box::new(Runtime::new(model).map_err(|e| anyhow!("{e}"))?))
}

/// Outputs of the fixed-point runtime: float (model units) and raw i16.
pub struct FixedRun {
    /// De-quantised outputs.
    pub outputs: Matrix<f32>,
    /// Raw i16 outputs of the last layer.
    pub raw: Matrix<i16>,
}

fn check_rows(inputs: &Matrix<f32>, phases: &[f32]) -> Result<()> {
    if inputs.rows != phases.len() {
        bail!("{} input rows but {} phases", inputs.rows, phases.len());
    }
    Ok(())
}

/// Runs the blob on every row.
pub fn run_fixed(blob: &[u8], inputs: &Matrix<f32>, phases: &[f32]) -> Result<FixedRun> {
    check_rows(inputs, phases)?;
    let model = Model::from_bytes(blob).map_err(|e| anyhow!("model blob: {e}"))?;
    let (n_in, n_out) = (model.input_dim(), model.output_dim());
    if inputs.cols != n_in {
        bail!(
            "inputs have {} columns, the model takes {n_in}",
            inputs.cols
        );
    }
    let mut rt = host_runtime(model)?;
    let mut outputs = Matrix {
        rows: inputs.rows,
        cols: n_out,
        data: vec![0.0; inputs.rows * n_out],
    };
    let mut raw = Matrix {
        rows: inputs.rows,
        cols: n_out,
        data: vec![0i16; inputs.rows * n_out],
    };
    let mut q = vec![0i16; n_in];
    for (i, (x, &p)) in inputs.iter_rows().zip(phases).enumerate() {
        let phase = Phase::from_radians(p).map_err(|e| anyhow!("phase {i}: {e}"))?;
        rt.quantise_input(x, &mut q)
            .map_err(|e| anyhow!("input row {i}: {e}"))?;
        let y = rt
            .run_quantised(phase, &q)
            .map_err(|e| anyhow!("row {i}: {e}"))?;
        raw.data[i * n_out..(i + 1) * n_out].copy_from_slice(y);
        let y = raw.row(i).to_vec();
        rt.dequantise_output(&y, &mut outputs.data[i * n_out..(i + 1) * n_out])
            .map_err(|e| anyhow!("row {i}: {e}"))?;
    }
    Ok(FixedRun { outputs, raw })
}

/// Runs the float reference (f64 inside, f32 out) on every row.
pub fn run_reference(net: &Net, inputs: &Matrix<f32>, phases: &[f32]) -> Result<Matrix<f32>> {
    check_rows(inputs, phases)?;
    if inputs.cols != net.input_dim() {
        bail!(
            "inputs have {} columns, the model takes {}",
            inputs.cols,
            net.input_dim()
        );
    }
    if let Some(i) = inputs
        .data
        .iter()
        .chain(phases)
        .position(|v| !v.is_finite())
    {
        bail!("non-finite value at flat index {i} of the inputs or phases");
    }
    let n_out = net.output_dim();
    let mut out = Matrix {
        rows: inputs.rows,
        cols: n_out,
        data: Vec::with_capacity(inputs.rows * n_out),
    };
    for (x, &p) in inputs.iter_rows().zip(phases) {
        let x: Vec<f64> = x.iter().map(|&v| f64::from(v)).collect();
        out.data
            .extend(net.forward(&x, f64::from(p)).into_iter().map(|v| v as f32));
    }
    Ok(out)
}
