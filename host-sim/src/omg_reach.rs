//! `host-sim omg-reach`: the OMG models reaching on the held-out clips of
//! their rig and on the hand-written target scripts, in f64 and as int16
//! and int8 blobs (or rig blobs) on the host runtime, judged by the
//! metrics of [`crate::reach_metrics`] (the definitions of
//! `tools/omg/metrics.py`; `tools/omg/evaluate.py` applies them the same
//! way, so the f64 figures can be checked against its output).
//!
//! **Held-out clips.** Every clip is rolled out grounded from its frame 0
//! for its 300 frames (a joint-velocity model with that frame's joint
//! angles from the data's `dof` block and `v0 = q0 * fps`), driven only by
//! the data's targets. The hand targets are each hand's first `spawned[h]`
//! constant-target intervals (`clips.json`; `reps` for data written before
//! `spawned`). Rows: the data itself, holding frame 0 still, f64, the
//! blobs (and any input-noise rows).
//!
//! **Target scripts** (`--scripts DIR`, R1 joint-velocity models): every
//! `*.json` of `DIR` but `expected.json` (`tools/omg/scripts` is the
//! committed set), each rolled out from rest for its own length, its frame-0
//! target block in the start frame ([`crate::omg_rollout::script_start`]),
//! the hand targets of [`TargetScript::intervals`]; the one marked
//! `unreachable` is reported apart ([`crate::reach_metrics::unreachable`]).
//! Rows: holding the rest frame still, f64, the blobs, summed over all
//! scripts.
//!
//! Every row: targets (and those the hand started within reach of, counted
//! apart), reach and plausible reach, frames to a plausible reach, final
//! distance, bone-length error p50 / p99, roughness; the joint position
//! error against the data (held-out clips) and, for the blobs, the joint
//! position difference to the f64 rollout.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use phasegate::blob::WeightFormat;
use serde::Serialize;

use crate::omg::{diff, load_dir, rollout, Diff, FixedOmg, FloatOmg, Mode, OmgDir, Start};
use crate::omg_rollout::script::{TargetScript, DEFAULT_FRAMES};
use crate::quant_knobs::Int8Knobs;
use crate::reach_metrics::{
    clip_intervals, script_intervals, unreachable, Bones, FrameLayout, HandTarget, ReachCounts,
    ReachSummary, Unreachable,
};
use crate::saturation::{saturated, Saturation};
use exporter::net::omg::{OmgConfig, OmgNet};
use exporter::quantise::{QuantOptions, Recorded};

pub use crate::reach_metrics::{median, CONTACT_RADIUS_M};

/// The held-out clips of one rig: its test and validation splits.
pub struct HeldOut {
    /// `(clip, frame)` rows of the model's width.
    pub clips: Vec<Vec<Vec<f64>>>,
    /// Hand targets spawned per hand in each clip (`clips.json`
    /// `spawned`, or `reps` for both hands where it has no `spawned`).
    pub spawned: Vec<[usize; 2]>,
    /// Each clip's joint angles at frame 0 (the data's `dof` block,
    /// `layout.json`), where the data has them.
    pub q0: Vec<Option<Vec<f64>>>,
}

impl HeldOut {
    /// Where clip `c`'s rollout of `omg` starts ([`Start::clip`]).
    pub fn start(&self, omg: &OmgNet, c: usize) -> Result<Start> {
        Start::clip(omg, &self.clips[c][0], self.q0[c].as_deref())
    }
}

/// The columns of the `dof` block (joint angles) of the rig's data files,
/// from `data/<rig>/layout.json`; `None` when it has none.
fn dof_columns(dir: &Path) -> Result<Option<std::ops::Range<usize>>> {
    let path = dir.join("layout.json");
    let Ok(bytes) = exporter::atomic::read_input(&path) else {
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
    #[serde(default)]
    reps: Option<usize>,
    #[serde(default)]
    spawned: Option<[usize; 2]>,
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
            &exporter::atomic::read_input(&meta_path)
                .with_context(|| format!("{}", meta_path.display()))?,
        )
        .with_context(|| format!("{}", meta_path.display()))?;
        let dof = dof_columns(&dir)?;
        let mut out = HeldOut {
            clips: Vec::new(),
            spawned: Vec::new(),
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
                let m = meta
                    .iter()
                    .find(|m| m.split == split && m.row == c)
                    .with_context(|| {
                        format!("{}: no {split} clip with row {c}", meta_path.display())
                    })?;
                let spawned = m.spawned.or(m.reps.map(|r| [r, r])).with_context(|| {
                    format!(
                        "{}: {split} clip {c} has neither \"spawned\" nor \"reps\"",
                        meta_path.display()
                    )
                })?;
                out.spawned.push(spawned);
                out.clips.push(clip_rows(&path, &data, c, t, w, width)?);
                out.q0.push(clip_q0(&data, c, t, w, &dof));
            }
        }
        Ok(out)
    }
}

/// Clip `c`'s `t` frames of a `(clips, t, w)` array read from `path`,
/// their first `width` columns; a value that is not finite is refused
/// here, naming the file, clip, frame and column (found in a rollout, it
/// would name a frame of no file).
fn clip_rows(
    path: &Path,
    data: &[f32],
    c: usize,
    t: usize,
    w: usize,
    width: usize,
) -> Result<Vec<Vec<f64>>> {
    (0..t)
        .map(|f| {
            let row = &data[(c * t + f) * w..][..width];
            if let Some((col, v)) = row.iter().enumerate().find(|(_, v)| !v.is_finite()) {
                bail!(
                    "{}: clip {c}, frame {f}, column {col} is {v}: clip data must be finite",
                    path.display()
                );
            }
            Ok(row.iter().map(|&v| f64::from(v)).collect())
        })
        .collect()
}

/// The key joints' target positions on every frame (`[t][k]`) of frames
/// holding a target block.
pub fn target_positions(cfg: &OmgConfig, frames: &[Vec<f64>]) -> Vec<Vec<[f64; 3]>> {
    let tp = cfg.slice("target_pos").start;
    frames
        .iter()
        .map(|f| {
            (0..cfg.key)
                .map(|k| [f[tp + 3 * k], f[tp + 3 * k + 1], f[tp + 3 * k + 2]])
                .collect()
        })
        .collect()
}

/// The key joints' target positions on every frame of target blocks (K
/// positions first).
pub fn block_positions(cfg: &OmgConfig, blocks: &[Vec<f64>]) -> Vec<Vec<[f64; 3]>> {
    blocks
        .iter()
        .map(|b| {
            (0..cfg.key)
                .map(|k| [b[3 * k], b[3 * k + 1], b[3 * k + 2]])
                .collect()
        })
        .collect()
}

/// The bones and rest lengths of `omg`'s rig: a joint-velocity model's
/// `controller.skeleton`, else `data/<rig>/rig.json`, else the model
/// directory's `rig.json`.
pub fn rest_bones(omg: &OmgNet, dir: &Path, data: &Path, rig: &str) -> Result<Bones> {
    if let Some(form) = &omg.dof {
        let sk = &form.skeleton;
        return Bones::new(&sk.parents, &sk.offsets).context("controller.skeleton");
    }
    for path in [data.join(rig).join("rig.json"), dir.join("rig.json")] {
        if let Ok(bytes) = exporter::atomic::read_input(&path) {
            return Bones::from_rig_json(&bytes).with_context(|| format!("{}", path.display()));
        }
    }
    bail!(
        "no rest bone lengths for {}: an absolute model needs {} or {}",
        dir.display(),
        data.join(rig).join("rig.json").display(),
        dir.join("rig.json").display()
    )
}

/// One way of running a model, on every clip (or every script).
#[derive(Clone, Debug, Serialize)]
pub struct ReachRow {
    /// "data", "hold still", "f64", "int16", "int8", "int16 rig", "int8
    /// rig" or an input-noise row's name.
    pub run: String,
    /// Blob bytes (the rig blob's for rig blobs; 0 for the others).
    pub blob_bytes: usize,
    /// Targets counted and reached, frames to reach, final distance, bone
    /// error and roughness (JSON: the same keys, at the row's top level).
    #[serde(flatten)]
    pub summary: ReachSummary,
    /// Mean joint position error against the data, cm (NaN on the target
    /// scripts, which have no data; left out of the JSON there).
    #[serde(skip_serializing_if = "is_nan")]
    pub joint_vs_data_cm: f64,
    /// Against the f64 rollout (blobs and input-noise rows only).
    pub vs_f64: Option<Diff>,
    /// The blob's rows that the f64 rollout's frames drive beyond their
    /// format's range (blobs on the held-out clips only; empty: none).
    pub saturated: Option<Saturation>,
    /// The input noise of an [`input_noise_rows`] row (share of each
    /// feature's std).
    pub input_noise: Option<f64>,
}

impl ReachRow {
    /// A row of `s`'s figures.
    fn new(run: &str, blob_bytes: usize, s: ReachSummary, joint_vs_data_cm: f64) -> ReachRow {
        ReachRow {
            run: run.into(),
            blob_bytes,
            summary: s,
            joint_vs_data_cm,
            vs_f64: None,
            saturated: None,
            input_noise: None,
        }
    }
}

fn is_nan(v: &f64) -> bool {
    v.is_nan()
}

/// One `unreachable` script target in one run.
#[derive(Clone, Debug, Serialize)]
pub struct UnreachableRow {
    /// The run ("f64", "int8", ...).
    pub run: String,
    /// The script's file stem.
    pub script: String,
    /// How the hand did.
    #[serde(flatten)]
    pub report: Unreachable,
}

/// The rows on the target scripts.
#[derive(Clone, Debug, Serialize)]
pub struct ScriptsReach {
    /// The scripts' directory.
    pub dir: String,
    /// The scripts run (file stems, sorted).
    pub scripts: Vec<String>,
    /// Frames over all scripts.
    pub frames: usize,
    /// Hold still, f64 and the blobs, summed over the scripts.
    pub rows: Vec<ReachRow>,
    /// Every run on every `unreachable` target.
    pub unreachable: Vec<UnreachableRow>,
    /// Why no rows were measured (not an R1 joint-velocity model).
    pub skipped: Option<String>,
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
    /// Data, hold still, f64, int16, int8 (or the rig blobs).
    pub rows: Vec<ReachRow>,
    /// The rows on the target scripts (`--scripts`).
    pub scripts: Option<ScriptsReach>,
}

/// Mean joint position error between two sets of clips' frames, metres.
fn joint_error(pos: &std::ops::Range<usize>, ys: &[Vec<Vec<f64>>], clips: &[Vec<Vec<f64>>]) -> f64 {
    let errs = ys.iter().zip(clips).flat_map(|(y, c)| {
        y.iter().zip(c).flat_map(move |(a, b)| {
            (0..pos.len() / 3).map(move |j| {
                let p = pos.start + 3 * j;
                (0..3)
                    .map(|k| (a[p + k] - b[p + k]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
        })
    });
    crate::reach_metrics::mean(errs)
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
        clips: (0..n)
            .map(|c| clip_rows(&path, &values, c, t, w, width))
            .collect::<Result<_>>()?,
        spawned: vec![[0, 0]; n],
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
        &exporter::atomic::read_input(&path).with_context(|| format!("{}", path.display()))?,
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
    layout: FrameLayout,
    bones: Bones,
    /// Per clip, the hands' target positions on every frame.
    targets: Vec<Vec<Vec<[f64; 3]>>>,
    /// Per clip, its counted hand targets.
    intervals: Vec<Vec<HandTarget>>,
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
        let bones = rest_bones(&d.omg, dir, data, &rig)?;
        let cfg = &d.omg.config;
        let targets: Vec<_> = held
            .clips
            .iter()
            .map(|c| target_positions(cfg, c))
            .collect();
        let intervals = targets
            .iter()
            .zip(&held.spawned)
            .map(|(t, &s)| clip_intervals(t, s))
            .collect();
        let float = rollouts(&d, &held, &mut FloatOmg(&d.omg), "f64")?;
        Ok(Judged {
            dir: dir.to_path_buf(),
            data: data.to_path_buf(),
            train_clips,
            layout: FrameLayout::of(cfg),
            bones,
            targets,
            intervals,
            d,
            rig,
            held,
            float,
        })
    }

    /// The row of rollouts `ys` of every clip.
    fn row(&self, run: &str, blob_bytes: usize, ys: &[Vec<Vec<f64>>]) -> ReachRow {
        let mut c = ReachCounts::default();
        for ((y, t), iv) in ys.iter().zip(&self.targets).zip(&self.intervals) {
            c.add_clip(y, t, iv, &self.layout, &self.bones);
        }
        let joint = joint_error(&self.layout.pos, ys, &self.held.clips);
        ReachRow::new(run, blob_bytes, c.summary(), 100.0 * joint)
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
    measure_with_scripts(j, opts, int8, motion_from, None)
}

/// A blob (or a motion blob and a rig blob) to judge.
struct Deployment {
    name: &'static str,
    blob: Vec<u8>,
    rig: Option<Vec<u8>>,
}

impl Deployment {
    fn net(&self) -> Result<FixedOmg<'_>> {
        match &self.rig {
            None => FixedOmg::new(&self.blob),
            Some(r) => FixedOmg::with_rig(&self.blob, r),
        }
    }

    /// The blob's bytes (the rig blob's for a pair).
    fn bytes(&self) -> usize {
        self.rig.as_ref().map_or(self.blob.len(), Vec::len)
    }
}

/// The int16 and int8 blobs of `j`'s model, or with `motion_from` its rig
/// blobs against that model's motion blobs.
fn deployments(
    j: &Judged,
    opts: &QuantOptions,
    int8: &Int8Knobs,
    motion_from: Option<&Path>,
) -> Result<Vec<Deployment>> {
    let (d, dir) = (&j.d, &j.dir);
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
                .map(|n| train_rollouts(d, &j.data, &j.rig, n))
                .transpose()?;
            let (int8, _) = int8.export_with(&d.omg.net, None, int8_opts, recorded)?;
            Ok(vec![
                Deployment {
                    name: "int16",
                    blob: int16,
                    rig: None,
                },
                Deployment {
                    name: "int8",
                    blob: int8,
                    rig: None,
                },
            ])
        }
        Some(m) => {
            if int8.is_set() {
                bail!("--motion-from builds rig blobs as exporter omg-rig does; leave out the int8 knobs");
            }
            let source = load_dir(m)?;
            let mask = exporter::rig::rig_mask(&d.omg.net, &exporter::rig::OMG_RIG_NODES)?;
            let mut out = Vec::new();
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
                out.push(Deployment {
                    name,
                    blob: motion,
                    rig: Some(rig_blob),
                });
            }
            Ok(out)
        }
    }
}

/// [`measure_judged`], and with `scripts` the same deployments on every
/// target script of that directory ([`ScriptsReach`]).
pub fn measure_with_scripts(
    j: &Judged,
    opts: &QuantOptions,
    int8: &Int8Knobs,
    motion_from: Option<&Path>,
    scripts: Option<&Path>,
) -> Result<OmgReach> {
    let (d, held, float) = (&j.d, &j.held, &j.float);
    let hold: Vec<Vec<Vec<f64>>> = held
        .clips
        .iter()
        .map(|c| vec![c[0].clone(); c.len()])
        .collect();
    let mut rows = vec![
        j.row("data", 0, &held.clips),
        j.row("hold still", 0, &hold),
        j.row("f64", 0, float),
    ];
    let flat_float = float.concat();
    let deployed = deployments(j, opts, int8, motion_from)?;
    for dep in &deployed {
        let mut fx = dep.net()?;
        let ys = rollouts(d, held, &mut fx, dep.name)?;
        let mut r = j.row(dep.name, dep.bytes(), &ys);
        r.vs_f64 = Some(diff(&d.omg, &ys.concat(), &flat_float));
        r.saturated = Some(exporter::progress::during(
            &format!("checking {}'s ranges on the f64 frames", dep.name),
            || saturated(fx.model(), &d.omg.net, &flat_float),
        )?);
        rows.push(r);
    }
    let scripts = scripts
        .map(|dir| measure_scripts(j, dir, &deployed))
        .transpose()?;
    Ok(OmgReach {
        dir: j.dir.display().to_string(),
        rig: j.rig.clone(),
        clips: held.clips.len(),
        split: if j.train_clips.is_some() {
            "training"
        } else {
            "held-out"
        }
        .into(),
        rows,
        scripts,
    })
}

/// The target scripts of a directory, ready to run on one model.
struct ScriptSet {
    /// File stems.
    names: Vec<String>,
    /// Each script's start (from rest).
    starts: Vec<Start>,
    /// Each frame's target block.
    blocks: Vec<Vec<Vec<f64>>>,
    /// The hands' target positions on every frame.
    targets: Vec<Vec<Vec<[f64; 3]>>>,
    /// The counted hand targets.
    counted: Vec<Vec<HandTarget>>,
    /// The `unreachable` ones.
    far: Vec<Vec<HandTarget>>,
}

/// The scripts of `dir` (every `*.json` but `expected.json`, sorted by
/// name) for `omg`, each from rest for its own length.
fn load_scripts(omg: &OmgNet, dir: &Path) -> Result<ScriptSet> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("cannot read the scripts' directory {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension().is_some_and(|x| x == "json")
                && p.file_name().is_some_and(|n| n != "expected.json")
        })
        .collect();
    paths.sort();
    if paths.is_empty() {
        bail!("{}: no target scripts (*.json)", dir.display());
    }
    let mut set = ScriptSet {
        names: Vec::new(),
        starts: Vec::new(),
        blocks: Vec::new(),
        targets: Vec::new(),
        counted: Vec::new(),
        far: Vec::new(),
    };
    for p in &paths {
        let spec = p.to_string_lossy();
        let s = TargetScript::load(&spec)?;
        let n = s.frames.unwrap_or(DEFAULT_FRAMES);
        let (start, blocks) = crate::omg_rollout::script_start(omg, &[], &s, n)
            .with_context(|| p.display().to_string())?;
        let (counted, far) = script_intervals(&s.intervals(&omg.config, n)?);
        set.names.push(
            p.file_stem()
                .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
        );
        set.targets.push(block_positions(&omg.config, &blocks));
        set.starts.push(start);
        set.blocks.push(blocks);
        set.counted.push(counted);
        set.far.push(far);
    }
    Ok(set)
}

/// The rows of `j`'s model on the scripts of `dir`: hold still, f64 and
/// each of `deployed`.
fn measure_scripts(j: &Judged, dir: &Path, deployed: &[Deployment]) -> Result<ScriptsReach> {
    let d = &j.d;
    let mut out = ScriptsReach {
        dir: dir.display().to_string(),
        scripts: Vec::new(),
        frames: 0,
        rows: Vec::new(),
        unreachable: Vec::new(),
        skipped: None,
    };
    if d.omg.dof.is_none() || j.rig != "R1" {
        out.skipped = Some(format!(
            "the target scripts are for R1 joint-velocity models (from rest); {} is {} {}",
            j.dir.display(),
            j.rig,
            if d.omg.dof.is_some() {
                "joint-velocity"
            } else {
                "absolute"
            }
        ));
        return Ok(out);
    }
    let set = load_scripts(&d.omg, dir)?;
    out.scripts = set.names.clone();
    out.frames = set.blocks.iter().map(Vec::len).sum();
    let hold = set
        .starts
        .iter()
        .zip(&set.blocks)
        .map(|(st, b)| vec![st.first.clone(); b.len()])
        .collect();
    let float = roll_scripts(d, &set, &mut FloatOmg(&d.omg))?;
    let mut runs: Vec<(String, usize, Rollouts)> = vec![
        ("hold still".into(), 0, hold),
        ("f64".into(), 0, float.clone()),
    ];
    for dep in deployed {
        let ys = roll_scripts(d, &set, &mut dep.net()?)?;
        runs.push((dep.name.into(), dep.bytes(), ys));
    }
    let flat_float = float.concat();
    for (name, bytes, ys) in runs {
        let mut c = ReachCounts::default();
        for (i, y) in ys.iter().enumerate() {
            c.add_clip(y, &set.targets[i], &set.counted[i], &j.layout, &j.bones);
            for &t in &set.far[i] {
                out.unreachable.push(UnreachableRow {
                    run: name.clone(),
                    script: set.names[i].clone(),
                    report: unreachable(y, &set.targets[i], t, &j.layout, &j.bones),
                });
            }
        }
        let mut r = ReachRow::new(&name, bytes, c.summary(), f64::NAN);
        if bytes > 0 {
            r.vs_f64 = Some(diff(&d.omg, &ys.concat(), &flat_float));
        }
        out.rows.push(r);
    }
    Ok(out)
}

/// Every frame of several rollouts.
type Rollouts = Vec<Vec<Vec<f64>>>;

/// Grounded rollouts of every script of `set` by `net`.
fn roll_scripts(
    d: &OmgDir,
    set: &ScriptSet,
    net: &mut impl phasegate_controller::Network<f64>,
) -> Result<Vec<Vec<Vec<f64>>>> {
    (0..set.names.len())
        .map(|i| {
            let t: Vec<&[f64]> = set.blocks[i].iter().map(Vec::as_slice).collect();
            rollout(&d.omg, &set.starts[i], &t, Mode::Grounded, net)
                .with_context(|| format!("script {}", set.names[i]))
        })
        .collect()
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
            let mut r = j.row(&name, 0, &ys);
            r.vs_f64 = Some(diff(&d.omg, &ys.concat(), &float));
            r.input_noise = Some(a);
            rows.push(r);
        }
    }
    Ok(rows)
}

/// The columns' header of [`rows_table`].
const HEADER: &str = "run          bytes  targets (near start)  reach %  plausible %  frames to reach  \
                      final m  bone err p50/p99 cm  roughness  joint vs data cm | vs f64: joint p99 cm  max cm\n";

/// The rows as table lines.
fn rows_table(rows: &[ReachRow]) -> String {
    let mut s = String::from(HEADER);
    for r in rows {
        let vs = r.vs_f64.as_ref().map_or("-".to_string(), |v| {
            format!("{:.3}  {:.3}", 100.0 * v.p99_joint_m, 100.0 * v.max_joint_m)
        });
        let joint = if r.joint_vs_data_cm.is_nan() {
            "-".to_string()
        } else {
            format!("{:.2}", r.joint_vs_data_cm)
        };
        s += &format!(
            "{:<11} {:>7} {:>10} ({:>4}) {:>8.1} {:>12.1} {:>16} {:>8.3} {:>11.2} / {:<6.2} {:>10.4} {:>17} | {}\n",
            r.run,
            r.blob_bytes,
            r.summary.targets,
            r.summary.near_start,
            100.0 * r.summary.reach,
            100.0 * r.summary.plausible_reach,
            r.summary.frames_median.map_or("-".to_string(), |f| format!("{f:.1}")),
            r.summary.final_m,
            r.summary.bone_err_p50_cm,
            r.summary.bone_err_p99_cm,
            r.summary.roughness,
            joint,
            vs
        );
    }
    s
}

/// The issue's bars for every blob row against the f64 row: plausible
/// reach within 2 percentage points, p99 joint difference to f64 within
/// 1 cm (int16) or 2 cm (int8).
fn bars(rows: &[ReachRow], on: &str) -> String {
    let mut s = String::new();
    let Some(f) = rows.iter().find(|r| r.run == "f64") else {
        return s;
    };
    for r in rows.iter().filter(|r| r.blob_bytes > 0) {
        let Some(v) = &r.vs_f64 else {
            continue;
        };
        let pp = 100.0 * (r.summary.plausible_reach - f.summary.plausible_reach);
        let bar_cm = if r.run.starts_with("int16") { 1.0 } else { 2.0 };
        let p99 = 100.0 * v.p99_joint_m;
        let verdict = |ok: bool| if ok { "met" } else { "NOT met" };
        s += &format!(
            "{} ({on}): plausible reach {pp:+.1} pp vs f64 (bar: within 2) {}; p99 joint vs f64 {p99:.3} cm (bar: <= {bar_cm}) {}\n",
            r.run,
            verdict(pp.abs() <= 2.0 + 1e-9),
            verdict(p99 <= bar_cm)
        );
    }
    s
}

impl ScriptsReach {
    /// The rows as a table, the bars and one line per `unreachable`
    /// target and run.
    pub fn table(&self) -> String {
        if let Some(why) = &self.skipped {
            return format!("target scripts of {}: skipped: {why}\n", self.dir);
        }
        let mut s = format!(
            "target scripts of {} ({} scripts, {} frames, each from rest; summed over the scripts)\n",
            self.dir,
            self.scripts.len(),
            self.frames
        );
        s += &rows_table(&self.rows);
        s += &bars(&self.rows, "scripts");
        for u in &self.unreachable {
            let r = &u.report;
            s += &format!(
                "unreachable target ({}, {} hand, frames {}..{}), {}: distance at start {:.3} m, closest {:.3} m, last {:.3} m; largest bone error on its frames {:.2} cm\n",
                u.script,
                ["left", "right"][r.hand.min(1)],
                r.start,
                r.end,
                u.run,
                r.start_m,
                r.closest_m,
                r.last_m,
                r.bone_err_max_cm
            );
        }
        s
    }
}

impl OmgReach {
    /// The figures as a table, with the issue's bars for the blobs.
    pub fn table(&self) -> String {
        let mut s = format!(
            "{} (rig {}, {} {} clips, grounded rollouts of 300 frames; a target counts if the hand starts \
             more than {CONTACT_RADIUS_M} m from it, plausible: every bone within 1 cm of the rig's)\n",
            self.dir, self.rig, self.clips, self.split
        );
        s += &rows_table(&self.rows);
        s += &bars(&self.rows, &self.split);
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
        if let Some(sc) = &self.scripts {
            s += &sc.table();
        }
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

    fn row(run: &str, bytes: usize, plausible: f64, p99_m: f64) -> ReachRow {
        let s = ReachSummary {
            targets: 10,
            plausible_reach: plausible,
            ..ReachSummary::default()
        };
        let mut r = ReachRow::new(run, bytes, s, f64::NAN);
        if bytes > 0 {
            r.vs_f64 = Some(Diff {
                p99_joint_m: p99_m,
                ..Diff::default()
            });
        }
        r
    }

    /// The JSON uses `metrics.py`'s names (`roughness`) and leaves out the
    /// joint error where there is no data; the bars judge plausible reach
    /// and the p99 joint difference per weight width.
    /// A NaN in a data clip is refused when the clips are read, naming the
    /// file, the clip, the frame and the column.
    #[test]
    fn a_bad_value_in_a_data_clip_names_the_file_and_the_place() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("R1");
        std::fs::create_dir(&dir).unwrap();
        std::fs::write(
            dir.join("clips.json"),
            r#"[{"split": "test", "row": 0, "spawned": [1, 1]},
                {"split": "test", "row": 1, "spawned": [1, 1]}]"#,
        )
        .unwrap();
        let (clips, t, w) = (2, 3, 4);
        let mut data = vec![0.5f32; clips * t * w];
        data[(t + 2) * w + 1] = f32::NAN; // clip 1, frame 2, column 1
        let path = dir.join("test.npy");
        let bytes = crate::npy::npy_bytes(&[clips as u64, t as u64, w as u64], &data).unwrap();
        std::fs::write(&path, bytes).unwrap();
        let e = format!(
            "{:#}",
            HeldOut::read_splits(tmp.path(), "R1", 4, &["test"], 2)
                .err()
                .unwrap()
        );
        assert_eq!(
            e,
            format!(
                "{}: clip 1, frame 2, column 1 is NaN: clip data must be finite",
                path.display()
            )
        );
    }

    #[test]
    fn rows_are_named_as_metrics_py_names_them_and_the_bars_judge_them() {
        let rows = [
            row("f64", 0, 0.80, 0.0),
            row("int16", 100, 0.79, 0.009),
            row("int8", 50, 0.77, 0.015),
        ];
        let v = serde_json::to_value(&rows[0]).unwrap();
        assert!(v.get("roughness").is_some() && v.get("rms").is_none());
        assert!(v.get("joint_vs_data_cm").is_none(), "no data: left out");
        assert!(v.get("plausible_reach").is_some() && v.get("near_start").is_some());
        let b = bars(&rows, "scripts");
        assert!(
            b.contains(
                "int16 (scripts): plausible reach -1.0 pp vs f64 (bar: within 2) met; \
                        p99 joint vs f64 0.900 cm (bar: <= 1) met"
            ),
            "{b}"
        );
        assert!(
            b.contains(
                "int8 (scripts): plausible reach -3.0 pp vs f64 (bar: within 2) NOT met; \
                        p99 joint vs f64 1.500 cm (bar: <= 2) met"
            ),
            "{b}"
        );
        let t = rows_table(&rows);
        assert_eq!(t.lines().count(), 4, "{t}");
    }

    /// The committed target scripts for an R1 joint-velocity model (the
    /// embedded one if it is, else `omg::tests::dof_model`): each from
    /// rest with its frame-0 targets in the start frame, the hands'
    /// intervals counted, the one `unreachable` target apart.
    #[test]
    fn the_committed_scripts_start_from_rest_with_the_unreachable_target_apart() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let embedded = root.join("models/omg/tiny_fe_r1");
        let d = load_dir(&embedded).unwrap();
        assert!(
            d.omg.dof.is_some(),
            "the embedded default is a joint-velocity model"
        );
        let set = load_scripts(&d.omg, &root.join("tools/omg/scripts")).unwrap();
        assert_eq!(set.names.len(), 28);
        assert_eq!(set.names[0], "01-front-chest-both");
        let tb = d.omg.config.slice("target");
        for (i, (st, b)) in set.starts.iter().zip(&set.blocks).enumerate() {
            assert!(st.q0.iter().chain(&st.v0).all(|&v| v == 0.0), "from rest");
            assert_eq!(st.first[tb.clone()], b[0][..], "{}", set.names[i]);
            assert!(set.counted[i]
                .iter()
                .chain(&set.far[i])
                .all(|t| t.hand < 2 && t.start < t.end && t.end <= b.len()));
        }
        let far: Vec<(&String, &Vec<HandTarget>)> = set
            .names
            .iter()
            .zip(&set.far)
            .filter(|(_, f)| !f.is_empty())
            .collect();
        assert_eq!(far.len(), 1);
        assert_eq!(far[0].0, "26-unreachable-front-left");
        assert_eq!(far[0].1.len(), 1);
        let e = load_scripts(&d.omg, &root.join("host-sim/src/omg_rollout"))
            .err()
            .unwrap();
        assert!(e.to_string().contains("no target scripts"), "{e}");
    }
}
