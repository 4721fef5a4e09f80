//! OMG reaching rollouts driven by target scripts: `host-sim rollout --omg
//! DIR --script SCRIPT` runs a model (its f64 graph, or a blob on the
//! fixed-point runtime with `--model`) through the controller's reaching
//! loop (`phasegate_controller::Reach`) from a rest frame (a joint-velocity
//! model: from rest, `q = v = 0`), with the targets
//! of a target script ([`script`]), of a committed reference clip
//! (`ref:N`) or of a held-out clip of the generated data (`clip:N`), and
//! records the rollout ([`record`]); `rollout-compare` and `render` take
//! those records ([`compare`], [`picture`]).

pub mod picture;
pub mod record;
pub mod script;

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use serde::Serialize;

use crate::omg::{load_dir, rollout, FixedOmg, FloatOmg, Mode, Start};
use crate::omg_reach::HeldOut;
pub use crate::reach_metrics::CONTACT_RADIUS_M;
use crate::reach_metrics::{hand_intervals, median};
use record::OmgRecord;
use script::{TargetScript, DEFAULT_FRAMES};

/// What `host-sim rollout --omg` runs.
#[derive(Clone, Debug)]
pub struct OmgRolloutArgs {
    /// The model directory (`config.json`, `model.safetensors`,
    /// `rig.json`, `references.npz`).
    pub dir: PathBuf,
    /// A blob of the model: run it on the fixed-point runtime.
    pub model: Option<PathBuf>,
    /// A rig blob for `model` (then a motion blob): run the pair.
    pub rig: Option<PathBuf>,
    /// A target script: a built-in name, a JSON file, `ref:N` or `clip:N`.
    pub script: String,
    /// The generated data (`tools/omg/generate --out`), for `clip:N`.
    pub data: Option<PathBuf>,
    /// Frames (default: the script's, or its clip's).
    pub frames: Option<usize>,
    /// Costs recomputed (grounded) or fed back (faithful).
    pub mode: Mode,
}

/// The parents of the rig the model in `dir` was trained on (`rig.json`).
pub fn rig_parents(dir: &Path) -> Result<Vec<i32>> {
    let path = dir.join("rig.json");
    let bytes = exporter::atomic::read_input(&path)
        .with_context(|| format!("cannot read {}", path.display()))?;
    parents_of(&bytes).with_context(|| format!("{}", path.display()))
}

/// The `parents` of a `rig.json` (as `tools/omg/generate` writes it).
pub fn parents_of(rig_json: &[u8]) -> Result<Vec<i32>> {
    let rig: serde_json::Value = serde_json::from_slice(rig_json)?;
    rig["parents"]
        .as_array()
        .context("no \"parents\"")?
        .iter()
        .map(|v| {
            v.as_i64()
                .and_then(|p| i32::try_from(p).ok())
                .with_context(|| format!("bad parent {v}"))
        })
        .collect()
}

/// Where the rollout of `args.script` starts and each frame's target
/// block: `ref:N` from the reference clip's start, `clip:N` from the
/// held-out clip's frame 0 (a joint-velocity model with its joint angles,
/// [`crate::omg::Start::clip`]), a script from the rest frame of the
/// model's first reference clip (absolute) or from rest (joint velocity:
/// [`crate::omg::Start::rest`], the key joints the script does not name
/// targeting their own rest pose) with the script's first targets.
pub(crate) fn targets(
    args: &OmgRolloutArgs,
    d: &crate::omg::OmgDir,
) -> Result<(Start, Vec<Vec<f64>>)> {
    let cfg = &d.omg.config;
    let tb = cfg.slice("target");
    let clip_index = |s: &str, n: usize, what: &str| -> Result<usize> {
        let c: usize = s
            .parse()
            .map_err(|_| anyhow!("{}: {s} is not a clip number", args.script))?;
        if c >= n {
            bail!("{}: {what} has {n} clips", args.script);
        }
        Ok(c)
    };
    let (start, blocks): (Start, Vec<Vec<f64>>) = if let Some(c) = args.script.strip_prefix("ref:")
    {
        let refs = &d.refs;
        let c = clip_index(c, refs.targets.dims[0], "the committed reference")?;
        let n = args.frames.unwrap_or(refs.targets.dims[1]);
        if n > refs.targets.dims[1] {
            bail!(
                "{}: the clip has {} frames",
                args.script,
                refs.targets.dims[1]
            );
        }
        let blocks = (0..n).map(|t| refs.targets.row(c, t).to_vec()).collect();
        (crate::omg::reference_start(d, c), blocks)
    } else if let Some(c) = args.script.strip_prefix("clip:") {
        let data = args
            .data
            .as_deref()
            .context("clip:N needs --data (the directory tools/omg/generate wrote)")?;
        let rig = crate::omg_reach::rig_of(&args.dir)?;
        let held = HeldOut::read(data, &rig, cfg.model_width)?;
        let c = clip_index(c, held.clips.len(), "the held-out set")?;
        let clip = &held.clips[c];
        let n = args.frames.unwrap_or(clip.len());
        if n > clip.len() {
            bail!("{}: the clip has {} frames", args.script, clip.len());
        }
        let blocks = clip[..n].iter().map(|f| f[tb.clone()].to_vec()).collect();
        (held.start(&d.omg, c)?, blocks)
    } else {
        let s = TargetScript::load(&args.script)?;
        let n = args.frames.or(s.frames).unwrap_or(DEFAULT_FRAMES);
        return script_start(&d.omg, d.refs.inputs.row(0, 0), &s, n)
            .with_context(|| args.script.clone());
    };
    if blocks.is_empty() {
        bail!("--frames must be at least 1");
    }
    let mut start = start;
    start.first[tb].copy_from_slice(&blocks[0]);
    Ok((start, blocks))
}

/// Where `omg`'s rollout of the target script `s` over `frames` frames
/// starts, and each frame's target block: a joint-velocity model from rest
/// ([`crate::omg::Start::rest`], the key joints the script does not name
/// targeting their own rest pose, [`Start::rest_targets`]), an absolute
/// model from `reference_first` (the rest frame every committed absolute
/// model starts its references from, its own targets for the joints the
/// script does not name); the start frame holds the script's frame-0
/// target block.
pub fn script_start(
    omg: &exporter::net::omg::OmgNet,
    reference_first: &[f64],
    s: &TargetScript,
    frames: usize,
) -> Result<(Start, Vec<Vec<f64>>)> {
    let cfg = &omg.config;
    let tb = cfg.slice("target");
    if frames == 0 {
        bail!("--frames must be at least 1");
    }
    let mut start = match omg.dof {
        None => {
            let start = Start::frame(reference_first);
            if start.first.len() != cfg.model_width {
                bail!(
                    "a reference frame of {} values, the model's are {}",
                    start.first.len(),
                    cfg.model_width
                );
            }
            start
        }
        // From rest; its frame built on the first targets below.
        Some(_) => Start::frame(&[]),
    };
    let own = match omg.dof {
        None => start.first[tb.clone()].to_vec(),
        Some(_) => Start::rest_targets(omg)?,
    };
    let blocks = s.blocks(cfg, &own, frames)?;
    if start.first.is_empty() {
        start = Start::rest(omg, &blocks[0])?
            .context("an absolute model starts from a reference frame")?;
    }
    start.first[tb].copy_from_slice(&blocks[0]);
    Ok((start, blocks))
}

/// Runs the rollout; returns its record and a description of what ran.
pub fn run(args: &OmgRolloutArgs) -> Result<(OmgRecord, String)> {
    let d = load_dir(&args.dir)?;
    let parents = rig_parents(&args.dir)?;
    let (start, blocks) = targets(args, &d)?;
    let t: Vec<&[f64]> = blocks.iter().map(Vec::as_slice).collect();
    let (frames, label) = match &args.model {
        Some(path) => {
            let blob = exporter::atomic::read_input(path)
                .with_context(|| format!("cannot read {}", path.display()))?;
            let rig = match &args.rig {
                Some(r) => Some((
                    r,
                    exporter::atomic::read_input(r)
                        .with_context(|| format!("cannot read {}", r.display()))?,
                )),
                None => None,
            };
            let (mut net, label) = match &rig {
                None => (
                    FixedOmg::new(&blob).with_context(|| format!("{}", path.display()))?,
                    format!("fixed point ({})", path.display()),
                ),
                Some((r, bytes)) => {
                    let m = phasegate::Model::with_rig(&blob, bytes).map_err(|e| {
                        anyhow::anyhow!("{} with {}: {e}", r.display(), path.display())
                    })?;
                    let label = format!(
                        "fixed point ({} with rig {}; activation RAM {} bytes)",
                        path.display(),
                        r.display(),
                        m.ram_bytes()
                    );
                    (FixedOmg::with_rig(&blob, bytes)?, label)
                }
            };
            let frames = rollout(&d.omg, &start, &t, args.mode, &mut net)?;
            (frames, label)
        }
        None => {
            let frames = rollout(&d.omg, &start, &t, args.mode, &mut FloatOmg(&d.omg))?;
            (frames, "float (f64 graph)".to_string())
        }
    };
    let roughness = crate::reach_metrics::roughness(&frames, &d.omg.config.slice("rot"));
    let record = OmgRecord::new(&d.omg.config, &parents, frames)?;
    let label = format!(
        "{label}, {} {} mode, RMS roughness {roughness:.5} rad",
        args.dir.display(),
        match args.mode {
            Mode::Grounded => "grounded",
            Mode::Faithful => "faithful",
        }
    );
    Ok((record, label))
}

/// One hand target of a rollout.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct TargetReach {
    /// Key joint (0: left hand, 1: right hand).
    pub hand: usize,
    /// First and one-past-last frame the target held.
    pub frames: (usize, usize),
    /// Frames from its first frame to the first within reach, if reached.
    pub reached_after: Option<usize>,
    /// Hand-target distance on its last frame, metres.
    pub final_m: f64,
}

/// Every hand target of `r` (each interval of a constant target position,
/// the last one included) and how the hand did.
pub fn reach(r: &OmgRecord) -> Vec<TargetReach> {
    let mut out = Vec::new();
    if r.is_empty() {
        return out;
    }
    for hand in 0..r.key_joints.len().min(2) {
        let targets: Vec<[f64; 3]> = r.targets.iter().map(|f| f[hand]).collect();
        let dist: Vec<f64> = (0..r.len())
            .map(|t| {
                let p = r.key_position(t, hand);
                (0..3)
                    .map(|d| (p[d] - targets[t][d]).powi(2))
                    .sum::<f64>()
                    .sqrt()
            })
            .collect();
        for (a, b) in hand_intervals(&targets, usize::MAX) {
            out.push(TargetReach {
                hand,
                frames: (a, b),
                reached_after: dist[a..b].iter().position(|&v| v < CONTACT_RADIUS_M),
                final_m: dist[b - 1],
            });
        }
    }
    out
}

/// The reach lines printed for a rollout.
pub fn reach_table(r: &OmgRecord) -> String {
    let rows = reach(r);
    let mut s = String::from("  hand   frames      reached after   final distance (m)\n");
    for t in &rows {
        s += &format!(
            "  {:<6} {:>4}..{:<4}  {:>13}   {:.3}\n",
            ["left", "right"][t.hand],
            t.frames.0,
            t.frames.1,
            t.reached_after
                .map_or_else(|| "not reached".to_string(), |f| format!("{f} frames")),
            t.final_m
        );
    }
    let hit: Vec<usize> = rows.iter().filter_map(|t| t.reached_after).collect();
    s += &format!(
        "  reached {}/{} targets, median {} frames, mean final distance {:.3} m\n",
        hit.len(),
        rows.len(),
        median(&hit).map_or_else(|| "-".to_string(), |m| format!("{m:.0}")),
        rows.iter().map(|t| t.final_m).sum::<f64>() / rows.len().max(1) as f64
    );
    s
}

/// Joint position differences between two rollouts of the same targets.
#[derive(Clone, Debug, Serialize)]
pub struct Comparison {
    /// Largest joint position difference of each frame, metres.
    pub frame_max_m: Vec<f64>,
    /// 99th percentile over every (frame, joint), metres.
    pub p99_m: f64,
    /// Largest, metres.
    pub max_m: f64,
    /// Mean, metres.
    pub mean_m: f64,
}

/// Compares `a` and `b` joint by joint, frame by frame.
pub fn compare(a: &OmgRecord, b: &OmgRecord) -> Result<Comparison> {
    if a.len() != b.len() || a.parents != b.parents {
        bail!(
            "the rollouts differ in shape: {} and {} frames, {} and {} joints",
            a.len(),
            b.len(),
            a.parents.len(),
            b.parents.len()
        );
    }
    // Within f32 storage of the same targets.
    let same = a.targets.iter().flatten().zip(b.targets.iter().flatten());
    if same
        .flat_map(|(p, q)| p.iter().zip(q))
        .any(|(p, q)| (p - q).abs() > 1e-5)
    {
        bail!("the rollouts followed different targets");
    }
    let mut all = Vec::new();
    let mut frame_max_m = Vec::new();
    for (fa, fb) in a.positions.iter().zip(&b.positions) {
        let d: Vec<f64> = fa
            .iter()
            .zip(fb)
            .map(|(p, q)| (0..3).map(|i| (p[i] - q[i]).powi(2)).sum::<f64>().sqrt())
            .collect();
        frame_max_m.push(d.iter().copied().fold(0.0, f64::max));
        all.extend(d);
    }
    all.sort_by(f64::total_cmp);
    let n = all.len().max(1);
    Ok(Comparison {
        p99_m: all.get((n - 1) * 99 / 100).copied().unwrap_or(0.0),
        max_m: all.last().copied().unwrap_or(0.0),
        mean_m: all.iter().sum::<f64>() / n as f64,
        frame_max_m,
    })
}

impl Comparison {
    /// The table `rollout-compare` prints.
    pub fn table(&self, every: usize) -> String {
        let mut s = String::from("frame  largest joint difference (cm)\n");
        for (t, m) in self.frame_max_m.iter().enumerate() {
            if t % every.max(1) == 0 || t + 1 == self.frame_max_m.len() {
                s += &format!("{t:>5}  {:.3}\n", m * 100.0);
            }
        }
        s += &format!(
            "joint positions, every frame and joint: p99 {:.3} cm, max {:.3} cm, mean {:.3} cm\n",
            self.p99_m * 100.0,
            self.max_m * 100.0,
            self.mean_m * 100.0
        );
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/omg/tiny_fe_r1")
    }

    fn args(script: &str) -> OmgRolloutArgs {
        OmgRolloutArgs {
            dir: dir(),
            model: None,
            rig: None,
            script: script.into(),
            data: None,
            frames: Some(40),
            mode: Mode::Grounded,
        }
    }

    /// `ref:N` reproduces the committed reference rollout's path: the same
    /// loop `host-sim omg-accuracy` checks against PyTorch.
    #[test]
    fn reference_targets_replay_the_float_reference_rollout() {
        let (r, label) = run(&args("ref:0")).unwrap();
        assert!(label.contains("float"), "{label}");
        let d = load_dir(&dir()).unwrap();
        let want = crate::omg::reference_rollout(&d, 0, &mut FloatOmg(&d.omg)).unwrap();
        assert_eq!(r.len(), 40);
        for (t, (got, want)) in r.frames.iter().zip(&want).enumerate() {
            assert_eq!(got, want, "frame {t}");
        }
    }

    #[test]
    fn a_script_rollout_follows_its_targets_and_round_trips() {
        let (r, _) = run(&args("reach-front")).unwrap();
        assert_eq!(r.len(), 40);
        assert_eq!(r.targets[5][0], [0.25, 1.20, 0.35]);
        assert_eq!(r.targets[5][1], [-0.25, 1.20, 0.35]);
        let rows = reach(&r);
        assert_eq!(rows.len(), 2, "one target per hand in 40 frames");
        assert!(rows.iter().all(|t| t.final_m.is_finite()));
        let path = std::env::temp_dir().join(format!("omg-rollout-{}.npz", std::process::id()));
        r.write(&path).unwrap();
        assert!(OmgRecord::is_record(&path).unwrap());
        let back = OmgRecord::read(&path).unwrap();
        let _ = std::fs::remove_file(&path);
        assert_eq!(back.len(), r.len());
        assert_eq!(back.parents, r.parents);
        assert_eq!(back.key_joints, r.key_joints);
        let c = compare(&r, &back).unwrap();
        assert!(c.max_m < 1e-5, "f32 storage only: {}", c.max_m);
        let empty = OmgRecord {
            frames: Vec::new(),
            positions: Vec::new(),
            targets: Vec::new(),
            axes: Vec::new(),
            ..r.clone()
        };
        assert!(reach(&empty).is_empty());
        let path = std::env::temp_dir().join(format!("omg-empty-{}.npz", std::process::id()));
        empty.write(&path).unwrap();
        let read = OmgRecord::read(&path);
        let _ = std::fs::remove_file(&path);
        assert!(read.is_err(), "a rollout of no frames is refused");
    }

    #[test]
    fn fixed_point_follows_float_and_the_comparison_says_how_closely() {
        let d = load_dir(&dir()).unwrap();
        let i16 = phasegate::blob::WeightFormat::I16;
        let blob = crate::omg::export(&d, i16, &crate::omg::exporter_options(i16)).unwrap();
        let path = std::env::temp_dir().join(format!("omg-rollout-{}.blob", std::process::id()));
        std::fs::write(&path, &blob).unwrap();
        let fixed = run(&OmgRolloutArgs {
            model: Some(path.clone()),
            ..args("ref:1")
        });
        let _ = std::fs::remove_file(&path);
        let (fixed, label) = fixed.unwrap();
        assert!(label.contains("fixed point"), "{label}");
        let (float, _) = run(&args("ref:1")).unwrap();
        let c = compare(&float, &fixed).unwrap();
        // Issue 11's int16 bar, on a held-out clip's own targets.
        assert!(c.max_m > 0.0 && c.p99_m < 0.01, "int16 within 1 cm: {c:?}");
        assert_eq!(c.frame_max_m.len(), 40);
    }

    #[test]
    fn bad_sources_are_refused_in_one_line() {
        for (script, needle) in [
            ("ref:9", "has 2 clips"),
            ("ref:x", "not a clip number"),
            ("clip:0", "needs --data"),
            ("nope.json", "cannot read target script"),
        ] {
            let e = format!("{:#}", run(&args(script)).unwrap_err());
            assert!(e.contains(needle), "{script}: {e}");
        }
    }
}
