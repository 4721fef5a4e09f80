//! Target scripts for OMG reaching rollouts: timed targets for the key
//! joints, from a JSON file, a built-in script, or a held-out clip's own
//! target sequence (docs/omg.md, "Target scripts").
//!
//! ```json
//! {
//!   "frames": 300,
//!   "targets": [
//!     { "frame": 0,   "joint": "LeftHand",  "position": [0.25, 1.2, 0.35] },
//!     { "frame": 0,   "joint": "RightHand", "position": [-0.25, 1.2, 0.35],
//!       "forward": [0, 0, 1], "up": [0, 1, 0] },
//!     { "frame": 150, "joint": "LeftHand",  "position": [0.316, 1.036, -0.01] }
//!   ]
//! }
//! ```
//!
//! Positions are metres in the character's root space (x to its left, y
//! up, z forward, as the data); `joint` is a key joint's name from the
//! model's `config.json` (`key_joints`) or its index among them (0 and 1 are
//! the hands). A target holds until the script changes it; `forward` and
//! `up` default to the joint's current target axes; key joints the script
//! never names keep the start frame's targets. `frames` (default 300) is
//! the rollout's length unless `--frames` is given.

use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use exporter::net::omg::OmgConfig;
use phasegate_controller::reach::MAX_TARGET_M;
use serde::Deserialize;

/// Frames of a script that does not say.
pub const DEFAULT_FRAMES: usize = 300;

/// Longest rollout: an hour at 60 frames per second (the frames are kept
/// in memory, about 3.5 KB each for `tiny_fe_r1`).
pub const MAX_FRAMES: usize = 60 * 60 * 60;

/// One timed target.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TimedTarget {
    /// First frame it holds.
    pub frame: usize,
    /// Key joint: a name from `key_joints` or an index among them.
    pub joint: serde_json::Value,
    /// Root-space position, metres.
    pub position: [f64; 3],
    /// Target forward axis (default: the joint's current one).
    #[serde(default)]
    pub forward: Option<[f64; 3]>,
    /// Target up axis (default: the joint's current one).
    #[serde(default)]
    pub up: Option<[f64; 3]>,
}

/// A target script.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TargetScript {
    /// Length of the rollout.
    #[serde(default)]
    pub frames: Option<usize>,
    /// The targets, in any order.
    pub targets: Vec<TimedTarget>,
}

/// Built-in scripts for rigs whose hands are key joints 0 and 1 (every
/// rig of `tools/omg`): name, description, JSON.
pub const BUILT_IN: [(&str, &str, &str); 2] = [
    (
        "reach-front",
        "both hands forward at chest height, then one up and one down, then back to rest",
        r#"{"frames": 300, "targets": [
            {"frame": 0,   "joint": 0, "position": [0.25, 1.20, 0.35]},
            {"frame": 0,   "joint": 1, "position": [-0.25, 1.20, 0.35]},
            {"frame": 100, "joint": 0, "position": [0.20, 1.40, 0.30]},
            {"frame": 100, "joint": 1, "position": [-0.20, 0.90, 0.30]},
            {"frame": 200, "joint": 0, "position": [0.316, 1.036, -0.01]},
            {"frame": 200, "joint": 1, "position": [-0.316, 1.036, -0.01]}]}"#,
    ),
    (
        "alternate",
        "the left hand reaches out and returns, then the right hand",
        r#"{"frames": 300, "targets": [
            {"frame": 0,   "joint": 0, "position": [0.35, 1.10, 0.25]},
            {"frame": 75,  "joint": 0, "position": [0.316, 1.036, -0.01]},
            {"frame": 150, "joint": 1, "position": [-0.35, 1.10, 0.25]},
            {"frame": 225, "joint": 1, "position": [-0.316, 1.036, -0.01]}]}"#,
    ),
];

impl TargetScript {
    /// A built-in script by name, or a JSON file.
    pub fn load(spec: &str) -> Result<TargetScript> {
        if let Some((_, _, json)) = BUILT_IN.iter().find(|(n, _, _)| *n == spec) {
            return serde_json::from_str(json).with_context(|| format!("built-in script {spec}"));
        }
        let path = Path::new(spec);
        let bytes = std::fs::read(path).with_context(|| {
            let names: Vec<&str> = BUILT_IN.iter().map(|b| b.0).collect();
            format!(
                "cannot read target script {spec} (built-in scripts: {}, ref:N, clip:N)",
                names.join(", ")
            )
        })?;
        serde_json::from_slice(&bytes).with_context(|| format!("{}: not a target script", spec))
    }

    /// The target block of each of `frames` frames (the data's layout: K
    /// positions, then K forward + up pairs), starting from `start` (the
    /// start frame's block); targets past `frames` are cut off. Refuses
    /// unknown joints, frames past the script's end, non-finite or
    /// absurd values and axes of no length, naming the entry.
    pub fn blocks(&self, cfg: &OmgConfig, start: &[f64], frames: usize) -> Result<Vec<Vec<f64>>> {
        let k = cfg.key;
        if frames > MAX_FRAMES || self.frames.is_some_and(|f| f > MAX_FRAMES) {
            bail!("more than {MAX_FRAMES} frames (an hour at 60 per second)");
        }
        if start.len() != 9 * k {
            bail!(
                "target block of {} values, the model has {k} key joints",
                start.len()
            );
        }
        let mut events: Vec<(usize, usize, &TimedTarget)> = Vec::new();
        for (i, t) in self.targets.iter().enumerate() {
            let at = || format!("target {i} (frame {}, joint {})", t.frame, t.joint);
            let key = key_index(cfg, &t.joint).with_context(at)?;
            // Past the script's own end is a mistake; past a shorter
            // --frames only cut off.
            let end = self.frames.map_or(frames, |f| f.max(frames));
            if t.frame >= end {
                bail!("{}: the script has {end} frames", at());
            }
            let values = t
                .position
                .iter()
                .chain(t.forward.iter().flatten())
                .chain(t.up.iter().flatten());
            if let Some(v) = values.clone().find(|v| !v.is_finite()) {
                bail!("{}: value {v} is not finite", at());
            }
            if t.position.iter().any(|v| v.abs() > MAX_TARGET_M) {
                bail!("{}: position beyond {MAX_TARGET_M} m", at());
            }
            for axis in [t.forward, t.up].into_iter().flatten() {
                if axis.iter().map(|v| v * v).sum::<f64>() < 1e-12 {
                    bail!("{}: an axis of no length", at());
                }
            }
            events.push((t.frame, key, t));
        }
        events.sort_by_key(|&(f, k, _)| (f, k));
        let mut block = start.to_vec();
        let mut out = Vec::with_capacity(frames);
        let mut next = events.iter().peekable();
        for f in 0..frames {
            while let Some(&&(_, key, t)) = next.peek().filter(|e| e.0 == f) {
                block[3 * key..3 * key + 3].copy_from_slice(&t.position);
                let r = 3 * k + 6 * key;
                if let Some(fw) = t.forward {
                    block[r..r + 3].copy_from_slice(&unit(fw));
                }
                if let Some(up) = t.up {
                    block[r + 3..r + 6].copy_from_slice(&unit(up));
                }
                next.next();
            }
            out.push(block.clone());
        }
        Ok(out)
    }
}

fn unit(v: [f64; 3]) -> [f64; 3] {
    let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
    v.map(|x| x / n)
}

/// A key joint named or numbered in a script.
fn key_index(cfg: &OmgConfig, joint: &serde_json::Value) -> Result<usize> {
    let found = match joint {
        serde_json::Value::String(name) => cfg.key_joints.iter().position(|n| n == name),
        serde_json::Value::Number(n) => n
            .as_u64()
            .and_then(|i| usize::try_from(i).ok())
            .filter(|&i| i < cfg.key),
        _ => None,
    };
    found.ok_or_else(|| {
        anyhow!(
            "unknown key joint {joint}: the model's key joints are {:?} (or 0..{})",
            cfg.key_joints,
            cfg.key
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cfg() -> OmgConfig {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/omg/tiny_fe_r1");
        exporter::net::omg::read_omg(&dir.join("model.safetensors"), &dir.join("config.json"))
            .unwrap()
            .config
    }

    #[test]
    fn targets_hold_until_changed_and_default_their_axes() {
        let cfg = cfg();
        let start: Vec<f64> = (0..36).map(|i| i as f64 / 100.0).collect();
        let s: TargetScript = serde_json::from_str(
            r#"{"targets": [
                {"frame": 2, "joint": "RightHand", "position": [1, 2, 3], "up": [0, 2, 0]},
                {"frame": 0, "joint": 0, "position": [4, 5, 6]}]}"#,
        )
        .unwrap();
        let b = s.blocks(&cfg, &start, 4).unwrap();
        assert_eq!(b.len(), 4);
        assert_eq!(&b[0][0..3], &[4.0, 5.0, 6.0]);
        assert_eq!(
            &b[1][3..6],
            &start[3..6],
            "the right hand waits for frame 2"
        );
        assert_eq!(&b[2][3..6], &[1.0, 2.0, 3.0]);
        assert_eq!(&b[3][3..6], &[1.0, 2.0, 3.0], "and holds");
        let r = 12 + 6;
        assert_eq!(&b[3][r..r + 3], &start[r..r + 3], "forward kept");
        assert_eq!(&b[3][r + 3..r + 6], &[0.0, 1.0, 0.0], "up normalised");
        assert_eq!(
            &b[3][6..12],
            &start[6..12],
            "the feet keep the start targets"
        );
    }

    #[test]
    fn bad_entries_are_refused_naming_them() {
        let cfg = cfg();
        let start = vec![0.0; 36];
        for (json, needle) in [
            (
                r#"{"targets": [{"frame": 0, "joint": "Tail", "position": [0,0,0]}]}"#,
                "unknown key joint",
            ),
            (
                r#"{"targets": [{"frame": 0, "joint": 9, "position": [0,0,0]}]}"#,
                "unknown key joint",
            ),
            (
                r#"{"targets": [{"frame": 10, "joint": 0, "position": [0,0,0]}]}"#,
                "has 10 frames",
            ),
            (
                r#"{"targets": [{"frame": 0, "joint": 0, "position": [1e9,0,0]}]}"#,
                "beyond",
            ),
            (
                r#"{"targets": [{"frame": 0, "joint": 0, "position": [0,0,0], "up": [0,0,0]}]}"#,
                "no length",
            ),
        ] {
            let s: TargetScript = serde_json::from_str(json).unwrap();
            let e = format!("{:#}", s.blocks(&cfg, &start, 10).unwrap_err());
            assert!(e.contains(needle) && e.contains("target 0"), "{json}: {e}");
        }
        assert!(serde_json::from_str::<TargetScript>(r#"{"targets": [], "extra": 1}"#).is_err());
        let long: TargetScript =
            serde_json::from_str(r#"{"frames": 1000000000000, "targets": []}"#).unwrap();
        let e = format!("{:#}", long.blocks(&cfg, &start, 10).unwrap_err());
        assert!(e.contains("an hour"), "{e}");
        let e = format!(
            "{:#}",
            s_empty().blocks(&cfg, &start, MAX_FRAMES + 1).unwrap_err()
        );
        assert!(e.contains("an hour"), "{e}");
    }

    fn s_empty() -> TargetScript {
        TargetScript {
            frames: None,
            targets: Vec::new(),
        }
    }

    #[test]
    fn built_in_scripts_load_and_fit_their_length() {
        let cfg = cfg();
        for (name, _, _) in BUILT_IN {
            let s = TargetScript::load(name).unwrap();
            let n = s.frames.unwrap_or(DEFAULT_FRAMES);
            s.blocks(&cfg, &vec![0.0; 36], n).unwrap();
        }
        let e = format!("{:#}", TargetScript::load("no-such-script").unwrap_err());
        assert!(e.contains("reach-front"), "{e}");
    }
}
