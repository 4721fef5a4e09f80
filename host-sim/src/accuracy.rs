//! Fixed-point vs float accuracy on a PFNN, over inputs drawn from its
//! normalisation statistics at several spreads: the figures of the
//! foundation issue, point 6.

use anyhow::Result;
use exporter::calibrate::normal_inputs;
use exporter::export::{export, ExportReport};
use exporter::net::{GatingMode, Net};
use exporter::pfnn_dir::PfnnTables;
use exporter::quantise::QuantOptions;
use phasegate::blob::WeightFormat;
use serde::Serialize;

use crate::compare::{compare, Comparison};
use crate::eval::{run_fixed, run_reference};
use crate::npy::Matrix;

/// Errors at one input spread.
#[derive(Clone, Debug, Serialize)]
pub struct SpreadRow {
    /// Inputs are `mean + std * N(0,1) * spread`.
    pub spread: f64,
    /// int16-weight cubic blob vs float cubic.
    pub int16: Comparison,
    /// int8-weight cubic blob vs float cubic.
    pub int8: Comparison,
    /// The demo's constant mode (50 tables) vs float cubic.
    pub demo_constant: Comparison,
}

/// The whole measurement.
#[derive(Clone, Debug, Serialize)]
pub struct Accuracy {
    /// Samples per spread.
    pub samples: usize,
    /// Seed of the sampler.
    pub seed: u64,
    /// One row per spread.
    pub rows: Vec<SpreadRow>,
    /// Export reports of the two blobs.
    pub int16_report: ExportReport,
    /// Export report of the int8 blob.
    pub int8_report: ExportReport,
}

/// Spreads of the foundation issue.
pub const SPREADS: [f64; 4] = [0.0, 0.25, 0.5, 1.0];

/// Builds the samples of one spread as f32 matrices.
pub fn sample_matrix(net: &Net, n: usize, spread: f64, seed: u64) -> (Matrix<f32>, Vec<f32>) {
    let s = normal_inputs(&net.xmean.to_vec(), &net.xstd.to_vec(), n, spread, seed);
    let cols = net.input_dim();
    let data = s.inputs.iter().flatten().map(|&v| v as f32).collect();
    (
        Matrix {
            rows: n,
            cols,
            data,
        },
        s.phases.iter().map(|&p| p as f32).collect(),
    )
}

/// Measures int16 and int8 cubic blobs and the demo's constant mode against
/// the exact cubic float reference.
pub fn measure(
    tables: &PfnnTables,
    samples: usize,
    seed: u64,
    int8: &crate::quant_knobs::Int8Knobs,
) -> Result<Accuracy> {
    let (cubic, residual) = Net::from_pfnn_tables(tables, GatingMode::Cubic);
    let (constant, _) = Net::from_pfnn_tables(tables, GatingMode::Constant);
    let opts16 = QuantOptions {
        weights: WeightFormat::I16,
        ..QuantOptions::default()
    };
    let opts8 = QuantOptions {
        weights: WeightFormat::I8,
        ..QuantOptions::default()
    };
    let (blob16, int16_report) = exporter::progress::during("exporting the int16 blob", || {
        export(&cubic, residual, &opts16)
    })?;
    let (blob8, int8_report) = int8.export(&cubic, residual, opts8)?;
    let mut rows = Vec::new();
    for (i, &spread) in SPREADS.iter().enumerate() {
        let (x, p) = sample_matrix(&cubic, samples, spread, seed.wrapping_add(i as u64));
        let reference = run_reference(&cubic, &x, &p)?;
        rows.push(SpreadRow {
            spread,
            int16: compare(&run_fixed(&blob16, &x, &p)?.outputs, &reference)?,
            int8: compare(&run_fixed(&blob8, &x, &p)?.outputs, &reference)?,
            demo_constant: compare(&run_reference(&constant, &x, &p)?, &reference)?,
        });
    }
    Ok(Accuracy {
        samples,
        seed,
        rows,
        int16_report,
        int8_report,
    })
}

impl Accuracy {
    /// The table printed by `host-sim accuracy`.
    pub fn table(&self) -> String {
        let mut s = format!(
            "{:>6} | {:>10} {:>10} | {:>10} {:>10} | {:>10} {:>10} | {:>9} {:>9}\n",
            "spread",
            "i16 rms",
            "i16 max",
            "i8 rms",
            "i8 max",
            "demo rms",
            "demo max",
            "i8/demo r",
            "i8/demo m"
        );
        for r in &self.rows {
            let (a, b, c) = (&r.int16.overall, &r.int8.overall, &r.demo_constant.overall);
            s += &format!(
                "{:>6.2} | {:>10.5} {:>10.5} | {:>10.5} {:>10.5} | {:>10.5} {:>10.5} | {:>9.3} {:>9.3}\n",
                r.spread, a.rms, a.max_abs, b.rms, b.max_abs, c.rms, c.max_abs,
                b.rms / c.rms.max(1e-30), b.max_abs / c.max_abs.max(1e-30)
            );
        }
        s
    }
}
