//! The frames fed to the firmware: loaded from `.npy` files, the golden
//! vectors of the embedded default model, or generated; each with the mix
//! (styles) it uses; and the input image that carries them (see `wire.rs`).

use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Result};
use phasegate::Mix;

use super::wire;

/// Frames run when none are given and there are no golden vectors to use.
pub const DEFAULT_GENERATED_FRAMES: usize = 16;

/// N frames of (phase, inputs).
#[derive(Clone, Debug)]
pub struct Frames {
    /// Phase of each frame, radians.
    pub phases: Vec<f32>,
    /// `N x input_dim` inputs, model units, row-major.
    pub inputs: Vec<f32>,
    /// Inputs per frame.
    pub input_dim: usize,
    /// Mix of each frame (`Mix::Base` unless a schedule is set).
    pub mixes: Vec<Mix>,
    /// Expected quantised outputs (`N x output_dim`), when the frames are
    /// golden vectors.
    pub expected_q: Option<Vec<i16>>,
    /// Where the frames come from, for the report.
    pub source: String,
}

impl Frames {
    /// Frames N.
    pub fn len(&self) -> usize {
        self.phases.len()
    }

    /// Whether there are no frames.
    pub fn is_empty(&self) -> bool {
        self.phases.is_empty()
    }

    /// Inputs of frame `i`.
    pub fn input(&self, i: usize) -> &[f32] {
        &self.inputs[i * self.input_dim..(i + 1) * self.input_dim]
    }

    /// Keeps the first `n` frames.
    pub fn truncate(&mut self, n: usize, output_dim: usize) {
        self.phases.truncate(n);
        self.inputs.truncate(n * self.input_dim);
        self.mixes.truncate(n);
        if let Some(q) = &mut self.expected_q {
            q.truncate(n * output_dim);
        }
    }

    /// The input image (header and records) for the firmware.
    pub fn image(&self, output_dim: usize) -> Vec<u8> {
        let mixes: Vec<[u8; wire::MIX_LEN]> =
            self.mixes.iter().map(|&m| wire::encode_mix(m)).collect();
        self.image_with_mix_fields(output_dim, &mixes)
    }

    /// The input image with the given raw mix fields (one per frame): for
    /// tests of malformed mixes.
    pub fn image_with_mix_fields(
        &self,
        output_dim: usize,
        mixes: &[[u8; wire::MIX_LEN]],
    ) -> Vec<u8> {
        assert_eq!(mixes.len(), self.len(), "one mix field per frame");
        let mut records =
            Vec::with_capacity(self.len() * (wire::RECORD_HEAD_LEN + 4 * self.input_dim));
        for (i, mix) in mixes.iter().enumerate() {
            wire::encode_input_record(mix, self.phases[i], self.input(i), &mut records);
        }
        let header = wire::InputHeader {
            frames: self.len() as u32,
            input_dim: self.input_dim as u32,
            output_dim: output_dim as u32,
            crc: wire::crc32(&records),
            mode: wire::Mode::Network,
        };
        let mut image = header.encode().to_vec();
        image.extend_from_slice(&records);
        image
    }
}

/// Reads an `.npy` array of `T`; returns its shape and data.
pub fn read_npy<T: npyz::Deserialize>(path: &Path) -> Result<(Vec<u64>, Vec<T>)> {
    crate::npy::read_any(path)
}

/// Loads `inputs` (float32, N x input_dim) and `phases` (float32, N).
pub fn from_npy(inputs: &Path, phases: &Path, input_dim: usize) -> Result<Frames> {
    let (xs, x) = read_npy::<f32>(inputs)?;
    let (ps, p) = read_npy::<f32>(phases)?;
    ensure!(
        xs.len() == 2 && xs[1] as usize == input_dim,
        "{}: shape {xs:?}, the model needs (N, {input_dim})",
        inputs.display()
    );
    ensure!(
        ps.len() == 1 && ps[0] == xs[0],
        "{}: shape {ps:?}, needs ({},) to match the inputs",
        phases.display(),
        xs[0]
    );
    Ok(Frames {
        mixes: vec![Mix::Base; p.len()],
        phases: p,
        inputs: x,
        input_dim,
        expected_q: None,
        source: format!("{} + {}", inputs.display(), phases.display()),
    })
}

/// The folder of the golden io bundles (`tests/golden/<case>/`).
pub fn golden_root() -> PathBuf {
    super::build::repo_root().join("tests").join("golden")
}

/// The golden vectors of the bundle whose `model.blob` is `blob` (one per
/// op kind and weight width, [`crate::golden::CASES`]), if there is one.
pub fn golden_for(blob: &[u8], input_dim: usize, output_dim: usize) -> Result<Option<Frames>> {
    let Some(dir) = crate::golden::CASES
        .iter()
        .map(|c| golden_root().join(c))
        .find(|d| std::fs::read(d.join("model.blob")).is_ok_and(|b| b == blob))
    else {
        return Ok(None);
    };
    let mut frames = from_npy(&dir.join("inputs.npy"), &dir.join("phases.npy"), input_dim)?;
    let (qs, q) = read_npy::<i16>(&dir.join("expected_q.npy"))?;
    ensure!(
        qs.len() == 2 && qs[0] as usize == frames.len() && qs[1] as usize == output_dim,
        "{}: shape {qs:?}, expected ({}, {output_dim})",
        dir.join("expected_q.npy").display(),
        frames.len()
    );
    frames.expected_q = Some(q);
    frames.source = format!("golden vectors in {}", dir.display());
    Ok(Some(frames))
}

/// SplitMix64: a small deterministic generator (no dependency).
struct SplitMix(u64);

impl SplitMix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// `n` deterministic frames for a model without golden vectors: phases
/// uniform in [0, 2 pi), and each input `offset + u / scale` with `u`
/// uniform in [-8192, 8192], i.e. spread over a quarter of the input's
/// quantised range (from the model's input stage, `q = (x - offset) * scale`).
pub fn generated(n: usize, input_stage: &[(f32, f32)], seed: u64) -> Frames {
    let mut rng = SplitMix(seed);
    let input_dim = input_stage.len();
    let mut phases = Vec::with_capacity(n);
    let mut inputs = Vec::with_capacity(n * input_dim);
    for _ in 0..n {
        phases.push((rng.unit() * std::f64::consts::TAU) as f32);
        for &(offset, scale) in input_stage {
            let u = (rng.unit() * 2.0 - 1.0) * 8192.0;
            let x = if scale != 0.0 && scale.is_finite() {
                offset as f64 + u / scale as f64
            } else {
                offset as f64
            };
            inputs.push(x as f32);
        }
    }
    Frames {
        mixes: vec![Mix::Base; n],
        phases,
        inputs,
        input_dim,
        expected_q: None,
        source: format!(
            "{n} generated frames (seed {seed:#x}, a quarter of each input's quantised range)"
        ),
    }
}

/// Picks the frames for a run: the given `.npy` files, else the golden
/// vectors when the blob is a golden bundle's, else generated ones;
/// `frames` keeps the first N (or sets N for generated frames).
pub fn select(
    inputs: Option<&Path>,
    phases: Option<&Path>,
    frames: Option<usize>,
    blob: &[u8],
    model: &phasegate::Model<'_>,
) -> Result<Frames> {
    let (input_dim, output_dim) = (model.input_dim(), model.output_dim());
    let mut f = match (inputs, phases) {
        (Some(x), Some(p)) => from_npy(x, p, input_dim)?,
        (None, None) => match golden_for(blob, input_dim, output_dim)? {
            Some(g) => g,
            None => {
                let stage: Vec<(f32, f32)> = model.input_stage().collect();
                generated(
                    frames.unwrap_or(DEFAULT_GENERATED_FRAMES),
                    &stage,
                    0x5EED_F00D,
                )
            }
        },
        _ => bail!("--inputs and --phases go together"),
    };
    if let Some(n) = frames {
        ensure!(
            n <= f.len(),
            "--frames {n}: only {} frames in {}",
            f.len(),
            f.source
        );
        f.truncate(n, output_dim);
    }
    ensure!(!f.is_empty(), "no frames to run");
    Ok(f)
}
