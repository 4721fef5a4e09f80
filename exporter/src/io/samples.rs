//! Network inputs as rows: raw inputs (model units) with their phases.
//! Drawn from a model's normalisation statistics, or recorded (a rollout
//! data set, `host-sim rollout-dataset`'s `.npz`) and split into training
//! and held-out blocks. The quantiser's calibration, error-aware rounding,
//! CP distillation and the accuracy checks all take their rows from here.

#![deny(clippy::arithmetic_side_effects)]

use anyhow::{anyhow, bail, Result};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::Serialize;
use std::f64::consts::TAU;
use std::path::{Path, PathBuf};

/// Raw inputs (model units) and phases (radians).
#[derive(Clone, Debug, Default)]
pub struct Samples {
    /// One input vector per sample.
    pub inputs: Vec<Vec<f64>>,
    /// One phase per sample, uniform in `[0, 2 pi)`.
    pub phases: Vec<f64>,
}

impl Samples {
    /// Appends `other`'s rows.
    pub fn extend(&mut self, other: &Samples) {
        self.inputs.extend_from_slice(&other.inputs);
        self.phases.extend_from_slice(&other.phases);
    }
}

/// `n` inputs `mean + std * N(0, 1) * scale` with uniform random phases,
/// from a ChaCha8 stream seeded by `seed` (same on every platform).
pub fn normal_inputs(mean: &[f64], std: &[f64], n: usize, scale: f64, seed: u64) -> Samples {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut s = Samples::default();
    for _ in 0..n {
        let x = mean
            .iter()
            .zip(std)
            .map(|(&m, &sd)| m + sd * rng.sample::<f64, _>(StandardNormal) * scale)
            .collect();
        s.inputs.push(x);
        s.phases.push(rng.gen_range(0.0..TAU));
    }
    s
}

/// Recorded calibration inputs and where they came from.
#[derive(Clone, Debug)]
pub struct Recorded {
    /// The file, for the report.
    pub source: String,
    /// The rows.
    pub samples: std::sync::Arc<Samples>,
}

impl Recorded {
    /// Reads a rollout data set (`host-sim rollout-dataset`'s `.npz`) for a
    /// model of `input_dim` inputs.
    pub fn read(path: &std::path::Path, input_dim: usize) -> anyhow::Result<Recorded> {
        Ok(Recorded {
            source: path.display().to_string(),
            samples: std::sync::Arc::new(read_distill_data(path, input_dim)?),
        })
    }
}

impl Serialize for Recorded {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeStruct;
        let mut st = s.serialize_struct("Recorded", 2)?;
        st.serialize_field("source", &self.source)?;
        st.serialize_field("rows", &self.samples.inputs.len())?;
        st.end()
    }
}

/// Name of the inputs array of a rollout data set (`N x in`, model units).
pub const DATA_INPUTS: &str = "X";
/// Name of the phases array of a rollout data set (`N`, radians).
pub const DATA_PHASES: &str = "phase";
/// Rows of one held-out block of a rollout data set, at most.
pub const HELD_OUT_BLOCK: usize = 60;
/// One block in this many is held out.
pub const HELD_OUT_EVERY: usize = 8;

/// Reads a rollout data set (`host-sim rollout-dataset`): float32 or
/// float64 arrays [`DATA_INPUTS`] `(N, input_dim)` and [`DATA_PHASES`]
/// `(N,)`, every value finite, `N >= 1`. Other arrays are ignored.
pub fn read_distill_data(path: &Path, input_dim: usize) -> Result<Samples> {
    let arrays = crate::io::tensors::read_npz(path)?;
    let name = path.display();
    let get = |n: &str| {
        arrays.get(n).ok_or_else(|| {
            anyhow!("{name}: missing array {n} (a rollout data set has {DATA_INPUTS} (N, inputs) and {DATA_PHASES} (N,))")
        })
    };
    let (x, p) = (get(DATA_INPUTS)?, get(DATA_PHASES)?);
    let [rows, cols] = x.shape[..] else {
        bail!(
            "{name}: {DATA_INPUTS} has shape {:?}, expected (N, {input_dim})",
            x.shape
        );
    };
    let (rows, cols) = (rows as usize, cols as usize);
    if cols != input_dim {
        bail!("{name}: {DATA_INPUTS} has {cols} columns, the model has {input_dim} inputs");
    }
    if rows == 0 {
        bail!("{name}: {DATA_INPUTS} has no rows");
    }
    if p.shape != [rows as u64] {
        bail!(
            "{name}: {DATA_PHASES} has shape {:?}, expected ({rows},) to match {DATA_INPUTS}",
            p.shape
        );
    }
    Ok(Samples {
        inputs: x.data.chunks(cols).map(<[f64]>::to_vec).collect(),
        phases: p.data.clone(),
    })
}

/// Splits `n` rows in file order into training and held-out rows: blocks
/// of `clamp(n / 8, 1, 60)` consecutive rows (one second of a rollout at
/// most), every 8th block held out. Whole blocks, because consecutive
/// frames of a rollout are nearly the same input.
pub fn held_out_split(n: usize) -> (Vec<usize>, Vec<usize>) {
    let block = (n / HELD_OUT_EVERY).clamp(1, HELD_OUT_BLOCK);
    // `block` is at least 1, so the division never fails.
    (0..n).partition(|&i| {
        i.checked_div(block)
            .is_some_and(|b| b % HELD_OUT_EVERY != HELD_OUT_EVERY - 1)
    })
}

pub(crate) fn pick(s: &Samples, idx: &[usize]) -> Samples {
    Samples {
        inputs: idx.iter().map(|&i| s.inputs[i].clone()).collect(),
        phases: idx.iter().map(|&i| s.phases[i]).collect(),
    }
}

pub(crate) fn extend(into: &mut Samples, from: Samples) {
    into.inputs.extend(from.inputs);
    into.phases.extend(from.phases);
}

/// Rollout inputs for CP distillation (`cp::distill::distill`): training rows, held-out rows (blocks of
/// the same files) and evaluation-only sets.
#[derive(Clone, Debug, Default)]
pub struct DistillData {
    /// Training rows of every `--distill-data` file.
    pub train: Samples,
    /// Their held-out blocks ([`held_out_split`], per file).
    pub held_out: Samples,
    /// Evaluation-only sets (`--eval-data`): name and rows.
    pub eval: Vec<(String, Samples)>,
}

impl DistillData {
    /// Reads and splits `train` files and reads `eval` files (see
    /// [`read_distill_data`]).
    pub fn load(train: &[PathBuf], eval: &[PathBuf], input_dim: usize) -> Result<DistillData> {
        let mut d = DistillData::default();
        for p in train {
            let s = read_distill_data(p, input_dim)?;
            let (t, h) = held_out_split(s.inputs.len());
            extend(&mut d.train, pick(&s, &t));
            extend(&mut d.held_out, pick(&s, &h));
        }
        for p in eval {
            d.eval
                .push((p.display().to_string(), read_distill_data(p, input_dim)?));
        }
        Ok(d)
    }
}

#[cfg(test)]
#[allow(clippy::arithmetic_side_effects)] // test fixtures, not file input
mod tests {
    use super::*;

    /// Name, shape and values of one array to write.
    type Array = (&'static str, Vec<u64>, Vec<f32>);

    fn write(path: &Path, arrays: &[Array]) {
        crate::io::tensors::write_npz(path, arrays).unwrap();
    }

    /// The rollout data-set reader takes exactly `X (N, in)` and `phase
    /// (N,)`, finite, and says in one line what is wrong otherwise.
    #[test]
    fn rollout_data_reader_refuses_bad_files() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("d.npz");
        let x: Vec<f32> = (0..12).map(|i| i as f32 * 0.5).collect();
        let ph = vec![0.0f32, 1.0, 2.0, 3.0];
        write(
            &p,
            &[
                ("X", vec![4, 3], x.clone()),
                ("phase", vec![4], ph.clone()),
                ("frame", vec![4], vec![0.0; 4]),
            ],
        );
        let s = read_distill_data(&p, 3).unwrap();
        assert_eq!(s.inputs.len(), 4);
        assert_eq!(s.inputs[1], vec![1.5, 2.0, 2.5]);
        assert_eq!(s.phases, vec![0.0, 1.0, 2.0, 3.0]);
        let mut nan_x = x.clone();
        nan_x[7] = f32::NAN;
        let mut inf_p = ph.clone();
        inf_p[2] = f32::INFINITY;
        let cases: Vec<(Vec<Array>, &str)> = vec![
            (vec![("X", vec![4, 3], x.clone())], "missing array phase"),
            (vec![("phase", vec![4], ph.clone())], "missing array X"),
            (
                vec![("X", vec![12], x.clone()), ("phase", vec![4], ph.clone())],
                "X has shape [12], expected (N, 3)",
            ),
            (
                vec![
                    ("X", vec![3, 4], x.clone()),
                    ("phase", vec![3], vec![0.0; 3]),
                ],
                "X has 4 columns, the model has 3 inputs",
            ),
            (
                vec![
                    ("X", vec![4, 3], x.clone()),
                    ("phase", vec![3], vec![0.0; 3]),
                ],
                "phase has shape [3], expected (4,)",
            ),
            (
                vec![
                    ("X", vec![4, 3], x.clone()),
                    ("phase", vec![4, 1], ph.clone()),
                ],
                "phase has shape [4, 1], expected (4,)",
            ),
            (
                vec![
                    ("X", vec![0, 3], Vec::new()),
                    ("phase", vec![0], Vec::new()),
                ],
                // Refused by the reader: no input array may be empty.
                "array X: shape [0, 3] has no elements",
            ),
            (
                vec![("X", vec![4, 3], nan_x), ("phase", vec![4], ph.clone())],
                "array X has a non-finite value at index 7",
            ),
            (
                vec![("X", vec![4, 3], x.clone()), ("phase", vec![4], inf_p)],
                "array phase has a non-finite value at index 2",
            ),
        ];
        for (arrays, want) in cases {
            write(&p, &arrays);
            let e = format!("{:#}", read_distill_data(&p, 3).unwrap_err());
            assert!(e.contains(want), "{want}: {e}");
            assert!(e.contains("d.npz") && !e.contains('\n'), "{e}");
        }
        std::fs::write(&p, b"not a zip").unwrap();
        assert!(read_distill_data(&p, 3).is_err());
        let absent = dir.path().join("absent.npz");
        let e = format!("{:#}", read_distill_data(&absent, 3).unwrap_err());
        assert!(e.contains("absent.npz"), "{e}");
    }

    #[test]
    fn held_out_split_takes_whole_blocks() {
        let (t, h) = held_out_split(3000);
        assert_eq!(t.len() + h.len(), 3000);
        assert_eq!(h.len(), 6 * 60);
        assert_eq!(&h[..3], &[420, 421, 422]);
        assert!(h.windows(2).filter(|w| w[1] != w[0] + 1).count() == 5);
        let (t, h) = held_out_split(30);
        assert_eq!(h, vec![21, 22, 23]);
        assert_eq!(t.len(), 27);
        let (t, h) = held_out_split(5);
        assert!(h.is_empty() && t.len() == 5);
    }
}
