//! `host-sim omg-reach`: the OMG models reaching on the held-out clips of
//! their rig, in f64 and as int16 and int8 blobs on the host runtime.
//!
//! Every clip is rolled out grounded from its frame 0 for its 300 frames
//! (a joint-velocity model with that frame's joint angles from the data's
//! `dof` block and `v0 = q0 * fps`),
//! driven only by the data's targets (as `tools/omg/evaluate.py` does, so
//! the f64 figures can be checked against `models/omg/eval.json`). Per
//! spawned hand target (the first `reps` constant-target intervals of each
//! hand; the return to rest is not counted): reached when the hand gets
//! within [`CONTACT_RADIUS_M`] before the data's next target is due, frames
//! from spawn to the first such frame, and the distance on the target's
//! last frame. Beside them the joint position error against the data and
//! the RMS roughness (spec §3.5, eq 3.9 in the author's code's form), and,
//! for the blobs, the joint position difference to the f64 rollout.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use phasegate::blob::WeightFormat;
use serde::Serialize;

use crate::omg::{diff, load_dir, rollout, Diff, FixedOmg, FloatOmg, Mode, OmgDir, Start};
use crate::quant_knobs::Int8Knobs;
use crate::saturation::{saturated, Saturation};
use exporter::net::omg::OmgConfig;
use exporter::quantise::{QuantOptions, Recorded};

/// The data's contact threshold: a hand this close to its target reached it.
pub const CONTACT_RADIUS_M: f64 = 0.1;

/// The held-out clips of one rig: its test and validation splits.
pub struct HeldOut {
    /// `(clip, frame)` rows of the model's width.
    pub clips: Vec<Vec<Vec<f64>>>,
    /// Hand targets spawned per hand in each clip (`clips.json` `reps`).
    pub reps: Vec<usize>,
    /// Each clip's joint angles at frame 0 (the data's `dof` block,
    /// `layout.json`), where the data has them.
    pub q0: Vec<Option<Vec<f64>>>,
}

impl HeldOut {
    /// Where clip `c`'s rollout of `omg` starts ([`Start::clip`]).
    pub fn start(&self, omg: &exporter::net::omg::OmgNet, c: usize) -> Result<Start> {
        Start::clip(omg, &self.clips[c][0], self.q0[c].as_deref())
    }
}

/// The columns of the `dof` block (joint angles) of the rig's data files,
/// from `data/<rig>/layout.json`; `None` when it has none.
fn dof_columns(dir: &Path) -> Result<Option<std::ops::Range<usize>>> {
    let path = dir.join("layout.json");
    let Ok(bytes) = std::fs::read(&path) else {
        return Ok(None);
    };
    let v: serde_json::Value =
        serde_json::from_slice(&bytes).with_context(|| format!("{}", path.display()))?;
    let block = v["blocks"]
        .as_array()
        .into_iter()
        .flatten()
        .find(|b| b["name"] == "dof");
    Ok(block.map(|b| {
        let at = |k: &str| b[k].as_u64().unwrap_or(0) as usize;
        at("offset")..at("offset") + at("size")
    }))
}

/// Frame 0's `dof` columns of clip `c` of a `(clips, t, w)` array.
fn clip_q0(
    data: &[f32],
    c: usize,
    t: usize,
    w: usize,
    dof: &Option<std::ops::Range<usize>>,
) -> Option<Vec<f64>> {
    let r = dof.clone().filter(|r| r.end <= w)?;
    Some(data[c * t * w..][r].iter().map(|&v| f64::from(v)).collect())
}

#[derive(serde::Deserialize)]
struct ClipMeta {
    split: String,
    row: usize,
    reps: usize,
}

impl HeldOut {
    /// Reads `data/<rig>/{test,val}.npy` (their first `width` columns) and
    /// `clips.json`, as `tools/omg/generate` writes them.
    pub fn read(data: &Path, rig: &str, width: usize) -> Result<HeldOut> {
        Self::read_splits(data, rig, width, &["test", "val"], usize::MAX)
    }

    /// The first `limit` clips of each of `splits` (`"train"`, `"test"`,
    /// `"val"`), as [`HeldOut::read`] reads the held-out ones.
    pub fn read_splits(
        data: &Path,
        rig: &str,
        width: usize,
        splits: &[&str],
        limit: usize,
    ) -> Result<HeldOut> {
        let dir = data.join(rig);
        let meta_path = dir.join("clips.json");
        let meta: Vec<ClipMeta> = serde_json::from_slice(
            &std::fs::read(&meta_path).with_context(|| format!("{}", meta_path.display()))?,
        )
        .with_context(|| format!("{}", meta_path.display()))?;
        let dof = dof_columns(&dir)?;
        let mut out = HeldOut {
            clips: Vec::new(),
            reps: Vec::new(),
            q0: Vec::new(),
        };
        for &split in splits {
            let path = dir.join(format!("{split}.npy"));
            let (shape, data) = crate::npy::read_array_f32(&path)?;
            let [n, t, w] = shape[..] else {
                bail!(
                    "{}: shape {shape:?}, expected (clips, frames, width)",
                    path.display()
                );
            };
            if w < width {
                bail!("{}: width {w}, the model needs {width}", path.display());
            }
            for c in 0..n.min(limit) {
                let reps = meta
                    .iter()
                    .find(|m| m.split == split && m.row == c)
                    .with_context(|| {
                        format!("{}: no {split} clip with row {c}", meta_path.display())
                    })?
                    .reps;
                out.reps.push(reps);
                out.clips.push(clip_rows(&data, c, t, w, width));
                out.q0.push(clip_q0(&data, c, t, w, &dof));
            }
        }
        Ok(out)
    }
}

/// Clip `c`'s `t` frames of a `(clips, t, w)` array, their first `width`
/// columns.
fn clip_rows(data: &[f32], c: usize, t: usize, w: usize, width: usize) -> Vec<Vec<f64>> {
    (0..t)
        .map(|f| {
            data[(c * t + f) * w..][..width]
                .iter()
                .map(|&v| f64::from(v))
                .collect()
        })
        .collect()
}

/// `[start, end)` of the first `reps` constant-target intervals of one
/// hand's target positions.
pub fn hand_targets(tpos: &[[f64; 3]], reps: usize) -> Vec<(usize, usize)> {
    let mut bounds = vec![0];
    for t in 1..tpos.len() {
        let moved = (0..3)
            .map(|d| (tpos[t][d] - tpos[t - 1][d]).powi(2))
            .sum::<f64>()
            .sqrt();
        if moved > 1e-6 {
            bounds.push(t);
        }
    }
    bounds.push(tpos.len());
    bounds.windows(2).map(|w| (w[0], w[1])).take(reps).collect()
}

/// Per target: reached, frames to reach, last-frame distance.
#[derive(Clone, Debug, Default)]
pub struct TargetStats {
    /// Whether each target was reached in time.
    pub reached: Vec<bool>,
    /// Frames from spawn to the first frame within reach, reached targets.
    pub frames: Vec<usize>,
    /// Hand-target distance on each target's last frame, metres.
    pub final_m: Vec<f64>,
}

/// [`TargetStats`] of one clip's frames `y` against the clip's own targets.
pub fn reach_stats(
    cfg: &OmgConfig,
    y: &[Vec<f64>],
    clip: &[Vec<f64>],
    reps: usize,
    s: &mut TargetStats,
) {
    let (pos, tpos) = (cfg.slice("pos"), cfg.slice("target_pos"));
    for h in 0..2.min(cfg.key) {
        let j = cfg.key_joint_indices[h];
        let targets: Vec<[f64; 3]> = clip
            .iter()
            .map(|f| std::array::from_fn(|k| f[tpos.start + 3 * h + k]))
            .collect();
        let dist: Vec<f64> = y
            .iter()
            .zip(&targets)
            .map(|(f, t)| {
                (0..3)
                    .map(|k| (f[pos.start + 3 * j + k] - t[k]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
            .collect();
        for (a, b) in hand_targets(&targets, reps) {
            let hit = dist[a..b].iter().position(|&v| v < CONTACT_RADIUS_M);
            s.reached.push(hit.is_some());
            s.frames.extend(hit);
            s.final_m.push(dist[b - 1]);
        }
    }
}

/// `sqrt(mean_t dr_t^2)` of one clip: dr_t the mean over joints and over
/// the forward and up vectors of the angle between frames t and t + 1.
pub fn rms_roughness(cfg: &OmgConfig, y: &[Vec<f64>]) -> f64 {
    let rot = cfg.slice("rot");
    let unit = |v: &[f64]| {
        let n = v.iter().map(|a| a * a).sum::<f64>().sqrt().max(1e-8);
        [v[0] / n, v[1] / n, v[2] / n]
    };
    let mut sq = 0.0;
    for w in y.windows(2) {
        let (a, b) = (&w[0][rot.clone()], &w[1][rot.clone()]);
        let vectors = a.len() / 3;
        let mut sum = 0.0;
        for v in 0..vectors {
            let (p, q) = (unit(&a[3 * v..3 * v + 3]), unit(&b[3 * v..3 * v + 3]));
            let c: f64 = (0..3).map(|k| p[k] * q[k]).sum();
            sum += c.clamp(-1.0, 1.0).acos();
        }
        let dr = sum / vectors as f64;
        sq += dr * dr;
    }
    (sq / (y.len() - 1).max(1) as f64).sqrt()
}

/// One way of running a model, on every held-out clip.
#[derive(Clone, Debug, Serialize)]
pub struct ReachRow {
    /// "data", "f64", "int16" or "int8".
    pub run: String,
    /// Blob bytes (0 for data and f64).
    pub blob_bytes: usize,
    /// Share of the spawned hand targets reached in time.
    pub reach: f64,
    /// Targets.
    pub targets: usize,
    /// Median frames from spawn to reach, reached targets.
    pub frames_median: Option<f64>,
    /// Mean last-frame distance, metres.
    pub final_m: f64,
    /// Mean joint position error against the data, cm.
    pub joint_vs_data_cm: f64,
    /// RMS roughness, radians per frame, mean over clips.
    pub rms: f64,
    /// Against the f64 rollout (blobs only).
    pub vs_f64: Option<Diff>,
    /// The blob's rows that the f64 rollout's frames drive beyond their
    /// format's range (blobs only; empty: none).
    pub saturated: Option<Saturation>,
    /// The input noise of an [`input_noise_rows`] row (share of each
    /// feature's std).
    pub input_noise: Option<f64>,
}

/// `host-sim omg-reach`'s figures for one model.
#[derive(Clone, Debug, Serialize)]
pub struct OmgReach {
    /// The model directory.
    pub dir: String,
    /// Its rig.
    pub rig: String,
    /// Clips judged.
    pub clips: usize,
    /// Which: `"held-out"` (test and validation) or `"training"`.
    pub split: String,
    /// Data, f64, int16, int8 (or the rig blobs).
    pub rows: Vec<ReachRow>,
}

/// The median of `v`; `None` when empty.
pub fn median(v: &[usize]) -> Option<f64> {
    let mut v = v.to_vec();
    v.sort_unstable();
    let n = v.len();
    match n {
        0 => None,
        _ if n % 2 == 1 => Some(v[n / 2] as f64),
        _ => Some((v[n / 2 - 1] + v[n / 2]) as f64 / 2.0),
    }
}

fn mean(v: impl IntoIterator<Item = f64>) -> f64 {
    let (s, n) = v
        .into_iter()
        .fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    s / n.max(1) as f64
}

fn row(d: &OmgDir, run: &str, blob_bytes: usize, held: &HeldOut, ys: &[Vec<Vec<f64>>]) -> ReachRow {
    let mut s = TargetStats::default();
    for ((y, clip), &reps) in ys.iter().zip(&held.clips).zip(&held.reps) {
        reach_stats(&d.omg.config, y, clip, reps, &mut s);
    }
    let pos = d.omg.config.slice("pos");
    let joint_err = ys.iter().zip(&held.clips).flat_map(|(y, c)| {
        let pos = pos.clone();
        y.iter().zip(c).flat_map(move |(a, b)| {
            (0..pos.len() / 3).map(move |j| {
                (0..3)
                    .map(|k| (a[pos.start + 3 * j + k] - b[pos.start + 3 * j + k]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
        })
    });
    ReachRow {
        run: run.into(),
        blob_bytes,
        reach: mean(s.reached.iter().map(|&r| f64::from(u8::from(r)))),
        targets: s.reached.len(),
        frames_median: median(&s.frames),
        final_m: mean(s.final_m.iter().copied()),
        joint_vs_data_cm: 100.0 * mean(joint_err),
        rms: mean(ys.iter().map(|y| rms_roughness(&d.omg.config, y))),
        vs_f64: None,
        saturated: None,
        input_noise: None,
    }
}

/// Grounded rollouts of every clip of `held` by `net` (`what` names it on
/// the progress bar).
fn rollouts(
    d: &OmgDir,
    held: &HeldOut,
    net: &mut impl phasegate_controller::Network<f64>,
    what: &str,
) -> Result<Vec<Vec<Vec<f64>>>> {
    let t = d.omg.config.slice("target");
    let bar = exporter::progress::bar(
        held.clips.len() as u64,
        &format!("rolling out {what}"),
        "clips",
    );
    let out = held
        .clips
        .iter()
        .enumerate()
        .map(|(c, clip)| {
            let targets: Vec<&[f64]> = clip.iter().map(|f| &f[t.clone()]).collect();
            let y = rollout(
                &d.omg,
                &held.start(&d.omg, c)?,
                &targets,
                Mode::Grounded,
                net,
            );
            bar.inc(1);
            y
        })
        .collect();
    bar.finish_and_clear();
    out
}

/// The float model's grounded rollouts of the first `n` training clips of
/// `rig` (`data/<rig>/train.npy`), every frame's network input as a
/// calibration row (f32-rounded, as a file would hold them; phase 0: the
/// OMG graph's gates are softmax nodes).
pub fn train_rollouts(d: &OmgDir, data: &Path, rig: &str, n: usize) -> Result<Recorded> {
    if n == 0 {
        bail!("the calibration rollouts need at least 1 training clip (0 asked for)");
    }
    let path = data.join(rig).join("train.npy");
    let width = d.omg.config.model_width;
    let (shape, values) = crate::npy::read_array_f32(&path)?;
    let [clips, t, w] = shape[..] else {
        bail!(
            "{}: shape {shape:?}, expected (clips, frames, width)",
            path.display()
        );
    };
    if w < width || clips < n {
        bail!(
            "{}: {clips} clips of width {w}; {n} calibration clips of width {width} asked for",
            path.display()
        );
    }
    let dof = dof_columns(&data.join(rig))?;
    let train = HeldOut {
        clips: (0..n).map(|c| clip_rows(&values, c, t, w, width)).collect(),
        reps: vec![0; n],
        q0: (0..n).map(|c| clip_q0(&values, c, t, w, &dof)).collect(),
    };
    let inputs: Vec<Vec<f64>> = rollouts(d, &train, &mut FloatOmg(&d.omg), "f64 (calibration)")?
        .concat()
        .iter()
        .map(|row| row.iter().map(|v| f64::from(*v as f32)).collect())
        .collect();
    let phases = vec![0.0; inputs.len()];
    Ok(Recorded {
        source: format!("{n} training clips of {rig}, grounded f64 rollouts"),
        samples: std::sync::Arc::new(exporter::calibrate::Samples { inputs, phases }),
    })
}

/// The rig named in `dir`'s `config.json`.
pub(crate) fn rig_of(dir: &Path) -> Result<String> {
    let path = dir.join("config.json");
    let v: serde_json::Value = serde_json::from_slice(
        &std::fs::read(&path).with_context(|| format!("{}", path.display()))?,
    )
    .with_context(|| format!("{}", path.display()))?;
    v["rig"]
        .as_str()
        .map(str::to_owned)
        .with_context(|| format!("{}: no \"rig\"", path.display()))
}

/// A model, the clips it is judged on (its rig's held-out clips under
/// `data`, or its first `train_clips` training clips) and its f64
/// rollouts of them: what every row of [`measure_judged`] and
/// [`input_noise_rows`] is measured against.
pub struct Judged {
    dir: PathBuf,
    data: PathBuf,
    train_clips: Option<usize>,
    d: OmgDir,
    rig: String,
    held: HeldOut,
    float: Vec<Vec<Vec<f64>>>,
}

impl Judged {
    /// Loads `dir`'s model and clips and rolls them out in f64.
    pub fn new(dir: &Path, data: &Path, train_clips: Option<usize>) -> Result<Judged> {
        let d = load_dir(dir)?;
        let rig = rig_of(dir)?;
        let width = d.omg.config.model_width;
        let held = match train_clips {
            None => HeldOut::read(data, &rig, width)?,
            Some(0) => bail!("--train-clips 0: judge on at least one training clip"),
            Some(n) => HeldOut::read_splits(data, &rig, width, &["train"], n)?,
        };
        let float = rollouts(&d, &held, &mut FloatOmg(&d.omg), "f64")?;
        Ok(Judged {
            dir: dir.to_path_buf(),
            data: data.to_path_buf(),
            train_clips,
            d,
            rig,
            held,
            float,
        })
    }
}

/// Measures `dir`'s model on its rig's held-out clips under `data` (or on
/// its first `train_clips` training clips, to choose among training runs
/// without looking at the held-out ones): its own
/// int16 and int8 blobs, or with `motion_from` (a Frozen rig model's
/// source) rig blobs of its autoencoder against that model's blobs of the
/// same width, as `exporter omg-rig` builds them (the int8 knobs do not
/// apply there).
pub fn measure(
    dir: &Path,
    data: &Path,
    opts: &QuantOptions,
    int8: &Int8Knobs,
    motion_from: Option<&Path>,
    train_clips: Option<usize>,
) -> Result<OmgReach> {
    measure_judged(
        &Judged::new(dir, data, train_clips)?,
        opts,
        int8,
        motion_from,
    )
}

/// [`measure`] of a model already loaded and rolled out in f64.
pub fn measure_judged(
    j: &Judged,
    opts: &QuantOptions,
    int8: &Int8Knobs,
    motion_from: Option<&Path>,
) -> Result<OmgReach> {
    let Judged {
        dir,
        data,
        train_clips,
        d,
        rig,
        held,
        float,
    } = j;
    let mut rows = vec![
        row(d, "data", 0, held, &held.clips),
        row(d, "f64", 0, held, float),
    ];
    let flat = |v: &[Vec<Vec<f64>>]| v.concat();
    let mut run = |name: &str, fx: &mut FixedOmg<'_>, bytes: usize| -> Result<()> {
        let ys = rollouts(d, held, fx, name)?;
        let mut r = row(d, name, bytes, held, &ys);
        r.vs_f64 = Some(diff(&d.omg, &flat(&ys), &flat(float)));
        r.saturated = Some(exporter::progress::during(
            &format!("checking {name}'s ranges on the f64 frames"),
            || saturated(fx.model(), &d.omg.net, &flat(float)),
        )?);
        rows.push(r);
        Ok(())
    };
    match motion_from {
        None => {
            let int16 = exporter::progress::during("exporting the int16 blob", || {
                crate::omg::export(d, WeightFormat::I16, opts)
            })?;
            let int8_opts = QuantOptions {
                weights: WeightFormat::I8,
                ..opts.clone()
            };
            let recorded = int8
                .calibration_clips
                .map(|n| train_rollouts(d, data, rig, n))
                .transpose()?;
            let (int8, _) = int8.export_with(&d.omg.net, None, int8_opts, recorded)?;
            for (name, blob) in [("int16", &int16), ("int8", &int8)] {
                run(name, &mut FixedOmg::new(blob)?, blob.len())?;
            }
        }
        Some(m) => {
            if int8.is_set() {
                bail!("--motion-from builds rig blobs as exporter omg-rig does; leave out the int8 knobs");
            }
            let source = load_dir(m)?;
            let mask = exporter::rig::rig_mask(&d.omg.net, &exporter::rig::OMG_RIG_NODES)?;
            for (name, w) in [
                ("int16 rig", WeightFormat::I16),
                ("int8 rig", WeightFormat::I8),
            ] {
                let rig_opts = QuantOptions {
                    weights: w,
                    ..opts.clone()
                };
                let motion = crate::omg::export(&source, w, &rig_opts)?;
                let (rig_blob, _) = exporter::progress::during("exporting the rig blob", || {
                    exporter::rig::export_rig(&d.omg.net, &motion, mask, "rig", &rig_opts)
                })
                .with_context(|| format!("{} against {}'s blob", dir.display(), m.display()))?;
                run(
                    name,
                    &mut FixedOmg::with_rig(&motion, &rig_blob)?,
                    rig_blob.len(),
                )?;
            }
        }
    }
    Ok(OmgReach {
        dir: dir.display().to_string(),
        rig: rig.clone(),
        clips: held.clips.len(),
        split: if train_clips.is_some() {
            "training"
        } else {
            "held-out"
        }
        .into(),
        rows,
    })
}

/// The f64 forward with every input feature moved each frame by uniform
/// noise in `[-a, a]` of that feature's standard deviation: how far the
/// model's own grounded rollout moves under perturbations of a blob's
/// input rounding (`a = 2^-(input_frac + 1)`, half an input step) or of
/// float32 (`a` about 6e-8), whatever the arithmetic that makes them.
struct NoisyInput<'n> {
    net: FloatOmg<'n>,
    a: f64,
    rng: rand_chacha::ChaCha8Rng,
}

impl phasegate_controller::Network<f64> for NoisyInput<'_> {
    fn input_dim(&self) -> usize {
        self.net.input_dim()
    }
    fn output_dim(&self) -> usize {
        self.net.output_dim()
    }
    fn predict(
        &mut self,
        phase: f64,
        x: &[f64],
        y: &mut [f64],
    ) -> phasegate_controller::Result<()> {
        use rand::Rng;
        let std = &self.net.0.net.xstd;
        let moved: Vec<f64> = x
            .iter()
            .zip(std)
            .map(|(v, s)| v + self.rng.gen_range(-self.a..=self.a) * s)
            .collect();
        self.net.predict(phase, &moved, y)
    }
    fn mean_output(&self, y: &mut [f64]) -> phasegate_controller::Result<()> {
        self.net.mean_output(y)
    }
}

/// Rows of `j`'s f64 model rolled out with input noise (`NoisyInput`) of
/// each amount in `amounts` and seeds `0..seeds`, on its clips, each
/// against its unperturbed f64 rollout (`vs_f64`); named `f64~A/sS`.
pub fn input_noise_rows(j: &Judged, amounts: &[f64], seeds: u64) -> Result<Vec<ReachRow>> {
    use rand::SeedableRng;
    if let Some(a) = amounts.iter().find(|a| !(a.is_finite() && **a >= 0.0)) {
        bail!("--input-noise {a}: an amount is a finite share of a feature's std, at least 0");
    }
    let (d, held) = (&j.d, &j.held);
    let float = j.float.concat();
    let mut rows = Vec::new();
    for &a in amounts {
        for seed in 0..seeds {
            let name = format!("f64~{a:e}/s{seed}");
            let mut net = NoisyInput {
                net: FloatOmg(&d.omg),
                a,
                rng: rand_chacha::ChaCha8Rng::seed_from_u64(seed),
            };
            let ys = rollouts(d, held, &mut net, &name)?;
            let mut r = row(d, &name, 0, held, &ys);
            r.vs_f64 = Some(diff(&d.omg, &ys.concat(), &float));
            r.input_noise = Some(a);
            rows.push(r);
        }
    }
    Ok(rows)
}

impl OmgReach {
    /// The figures as a table, with the bars for the blobs.
    pub fn table(&self) -> String {
        let mut s = format!(
            "{} (rig {}, {} {} clips, grounded rollouts of 300 frames)\n\
             run      bytes  reach %  targets  frames to reach (median)  final m  joint vs data cm  RMS rad/frame | vs f64: joint p99 cm  max cm\n",
            self.dir, self.rig, self.clips, self.split
        );
        for r in &self.rows {
            let vs = r.vs_f64.as_ref().map_or("-".to_string(), |v| {
                format!("{:.3}  {:.3}", 100.0 * v.p99_joint_m, 100.0 * v.max_joint_m)
            });
            s += &format!(
                "{:<6} {:>7} {:>8.1} {:>8} {:>25} {:>8.3} {:>17.2} {:>14.4} | {}\n",
                r.run,
                r.blob_bytes,
                100.0 * r.reach,
                r.targets,
                r.frames_median
                    .map_or("-".to_string(), |f| format!("{f:.1}")),
                r.final_m,
                r.joint_vs_data_cm,
                r.rms,
                vs
            );
        }
        let float = self.rows.iter().find(|r| r.run == "f64");
        for r in self.rows.iter().filter(|r| r.blob_bytes > 0) {
            let (Some(f), Some(v)) = (float, &r.vs_f64) else {
                continue;
            };
            let pp = 100.0 * (r.reach - f.reach);
            let bar_cm = if r.run.starts_with("int16") { 1.0 } else { 2.0 };
            let p99 = 100.0 * v.p99_joint_m;
            s += &format!(
                "{}: reach {:+.1} pp vs f64 (bar: within 2) {}; p99 joint vs f64 {:.3} cm (bar: <= {bar_cm}) {}\n",
                r.run,
                pp,
                if pp.abs() <= 2.0 { "met" } else { "NOT met" },
                p99,
                if p99 <= bar_cm { "met" } else { "NOT met" }
            );
        }
        for r in &self.rows {
            if let Some(sat) = &r.saturated {
                s += &format!(
                    "{}: rows saturated on the f64 rollout's frames: {}\n",
                    r.run,
                    sat.summary()
                );
            }
        }
        s += &self.noise_summary();
        s
    }

    /// One line per input-noise amount of [`input_noise_rows`]: the p99
    /// against f64 over its seeds, and how many stay within each bar.
    fn noise_summary(&self) -> String {
        let mut groups: Vec<(f64, Vec<f64>)> = Vec::new();
        for r in &self.rows {
            let (Some(amount), Some(v)) = (r.input_noise, &r.vs_f64) else {
                continue;
            };
            let p99 = 100.0 * v.p99_joint_m;
            match groups.iter_mut().find(|(a, _)| *a == amount) {
                Some((_, ps)) => ps.push(p99),
                None => groups.push((amount, vec![p99])),
            }
        }
        let mut s = String::new();
        for (amount, mut ps) in groups {
            ps.sort_by(f64::total_cmp);
            let n = ps.len();
            let median = if n % 2 == 1 {
                ps[n / 2]
            } else {
                (ps[n / 2 - 1] + ps[n / 2]) / 2.0
            };
            let within = |cm: f64| ps.iter().filter(|&&p| p <= cm).count();
            s += &format!(
                "f64 with input noise {amount:e} std: p99 joint vs f64 {:.3} .. {:.3} cm (median {:.3}) over {} seeds; <= 1 cm on {}, <= 2 cm on {}\n",
                ps[0],
                ps[n - 1],
                median,
                n,
                within(1.0),
                within(2.0)
            );
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hand_targets_split_at_every_move_and_keep_the_first_reps() {
        let a = [0.0, 0.0, 0.0];
        let b = [0.5, 0.0, 0.0];
        let c = [0.5, 0.2, 0.0];
        let t = [a, a, b, b, b, c, a, a];
        assert_eq!(hand_targets(&t, 9), vec![(0, 2), (2, 5), (5, 6), (6, 8)]);
        assert_eq!(hand_targets(&t, 2), vec![(0, 2), (2, 5)]);
        assert_eq!(hand_targets(&[a; 4], 1), vec![(0, 4)]);
    }

    #[test]
    fn median_of_odd_even_and_empty() {
        assert_eq!(median(&[3, 1, 2]), Some(2.0));
        assert_eq!(median(&[4, 1, 2, 3]), Some(2.5));
        assert_eq!(median(&[]), None);
    }
}
