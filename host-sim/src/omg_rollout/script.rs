//! Target scripts for OMG reaching rollouts: timed targets for the key
//! joints, from a JSON file, a built-in script, or a held-out clip's own
//! target sequence (docs/omg.md, "Target scripts").
//!
//! ```json
//! {
//!   "name": "example",
//!   "description": "both hands forward, the left one then slides up and goes back to rest",
//!   "frames": 300,
//!   "targets": [
//!     { "frame": 0,   "joint": "LeftHand",  "position": [0.25, 1.2, 0.35] },
//!     { "frame": 0,   "joint": "RightHand", "position": [-0.25, 1.2, 0.35],
//!       "forward": [0, 0, 1], "up": [0, 1, 0] },
//!     { "frame": 90,  "joint": "LeftHand",  "position": [0.25, 1.2, 0.35],
//!       "to": [0.25, 1.6, 0.35], "until": 150 },
//!     { "frame": 200, "joint": "LeftHand",  "position": [0.316, 1.036, -0.01] }
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
//! the rollout's length unless `--frames` is given. `name` and
//! `description` are for people and reports only.
//!
//! A *moving* target has `to` and `until` (both or neither): its position
//! goes linearly from `position` at `frame` to `to` at `until`, frame t in
//! between getting `p + (to - p) * ((t - frame) / (until - frame))` per
//! coordinate, in this order, in f64 (`tools/omg/scripts.py` computes the
//! same expression in the same order, so the two agree to the last bit),
//! and exactly `to` from `until` on; its axes are set at `frame` and do not
//! move. A later entry for the same joint (before `until` or after) takes
//! over from its own frame: before `until` it interrupts the motion. Two
//! entries for one joint at one frame are refused. `"unreachable": true`
//! marks a target the author knows the hand cannot reach (an evaluation
//! checks that it is approached, not reached); it changes no block.

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
    /// Root-space position, metres (a moving target's start).
    pub position: [f64; 3],
    /// Target forward axis (default: the joint's current one).
    #[serde(default)]
    pub forward: Option<[f64; 3]>,
    /// Target up axis (default: the joint's current one).
    #[serde(default)]
    pub up: Option<[f64; 3]>,
    /// A moving target's end position (with `until`).
    #[serde(default)]
    pub to: Option<[f64; 3]>,
    /// The frame a moving target reaches `to` (with `to`; after `frame`).
    #[serde(default)]
    pub until: Option<usize>,
    /// The author knows the hand cannot reach it (evaluation only).
    #[serde(default)]
    pub unreachable: bool,
}

impl TimedTarget {
    /// The target position at frame `t` (at or after `frame`): `position`,
    /// or for a moving target the point of its path (exactly `to` from
    /// `until` on). The same expression, in the same order, as
    /// `tools/omg/scripts.py`.
    pub fn position_at(&self, t: usize) -> [f64; 3] {
        match (self.to, self.until) {
            (Some(to), Some(until)) if until > self.frame && t < until => {
                if t <= self.frame {
                    return self.position;
                }
                let s = (t - self.frame) as f64 / (until - self.frame) as f64;
                let p = self.position;
                [
                    p[0] + (to[0] - p[0]) * s,
                    p[1] + (to[1] - p[1]) * s,
                    p[2] + (to[2] - p[2]) * s,
                ]
            }
            (Some(to), Some(_)) => to,
            _ => self.position,
        }
    }

    /// Whether it is a moving target.
    pub fn moving(&self) -> bool {
        self.to.is_some()
    }
}

/// A target script.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TargetScript {
    /// A short name (for reports).
    #[serde(default)]
    pub name: Option<String>,
    /// What the character is asked to do, in a sentence.
    #[serde(default)]
    pub description: Option<String>,
    /// Length of the rollout.
    #[serde(default)]
    pub frames: Option<usize>,
    /// The targets, in any order.
    pub targets: Vec<TimedTarget>,
}

/// The frames one entry of a script is the target of its key joint.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TargetInterval {
    /// The entry's index in [`TargetScript::targets`].
    pub index: usize,
    /// Its key joint (index among the model's key joints).
    pub key: usize,
    /// Its first frame.
    pub start: usize,
    /// Exclusive: the frame of the key joint's next entry, or the rollout's
    /// length.
    pub end: usize,
    /// A moving target (`to` and `until`).
    pub moving: bool,
    /// Marked `"unreachable": true`.
    pub unreachable: bool,
}

/// A checked entry: its index, key joint and the entry.
struct Event<'a> {
    index: usize,
    key: usize,
    target: &'a TimedTarget,
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
        let bytes = exporter::atomic::read_input(path).with_context(|| {
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
    /// start frame's block); targets past `frames` are cut off. Moving
    /// targets move (see the module's documentation). Refuses unknown
    /// joints, frames past the script's end, non-finite or absurd values,
    /// axes of no length, a `to` without `until` (or the reverse), an
    /// `until` not after its frame or past the script's end and two entries
    /// for one joint at one frame, naming the entry.
    pub fn blocks(&self, cfg: &OmgConfig, start: &[f64], frames: usize) -> Result<Vec<Vec<f64>>> {
        let k = cfg.key;
        self.check_frames(frames)?;
        if start.len() != 9 * k {
            bail!(
                "target block of {} values, the model has {k} key joints",
                start.len()
            );
        }
        let events = self.checked(cfg, frames)?;
        let mut block = start.to_vec();
        // The entry each key joint follows now (None: the start block's).
        let mut current: Vec<Option<&TimedTarget>> = vec![None; k];
        let mut out = Vec::with_capacity(frames);
        let mut next = events.iter().peekable();
        for f in 0..frames {
            while let Some(e) = next.peek().filter(|e| e.target.frame == f) {
                let (key, t) = (e.key, e.target);
                let r = 3 * k + 6 * key;
                if let Some(fw) = t.forward {
                    block[r..r + 3].copy_from_slice(&unit(fw));
                }
                if let Some(up) = t.up {
                    block[r + 3..r + 6].copy_from_slice(&unit(up));
                }
                current[key] = Some(t);
                next.next();
            }
            for (key, t) in current.iter().enumerate() {
                if let Some(t) = t {
                    block[3 * key..3 * key + 3].copy_from_slice(&t.position_at(f));
                }
            }
            out.push(block.clone());
        }
        Ok(out)
    }

    /// The frames each entry is its key joint's target, sorted by (start,
    /// key); entries at or past `frames` are dropped (as [`Self::blocks`]
    /// cuts them off). Refuses what `blocks` refuses.
    pub fn intervals(&self, cfg: &OmgConfig, frames: usize) -> Result<Vec<TargetInterval>> {
        let events = self.checked(cfg, frames)?;
        let kept: Vec<&Event> = events.iter().filter(|e| e.target.frame < frames).collect();
        let mut next_start = vec![frames; cfg.key];
        let mut out = vec![None; kept.len()];
        for (slot, e) in kept.iter().enumerate().rev() {
            out[slot] = Some(TargetInterval {
                index: e.index,
                key: e.key,
                start: e.target.frame,
                end: next_start[e.key],
                moving: e.target.moving(),
                unreachable: e.target.unreachable,
            });
            next_start[e.key] = e.target.frame;
        }
        Ok(out.into_iter().flatten().collect())
    }

    /// Refuses rollouts longer than [`MAX_FRAMES`].
    fn check_frames(&self, frames: usize) -> Result<()> {
        if frames > MAX_FRAMES || self.frames.is_some_and(|f| f > MAX_FRAMES) {
            bail!("more than {MAX_FRAMES} frames (an hour at 60 per second)");
        }
        Ok(())
    }

    /// The entries, checked (see [`Self::blocks`]), sorted by (frame, key).
    fn checked(&self, cfg: &OmgConfig, frames: usize) -> Result<Vec<Event<'_>>> {
        self.check_frames(frames)?;
        // Past the script's own end is a mistake; past a shorter --frames
        // only cut off.
        let end = self.frames.map_or(frames, |f| f.max(frames));
        let mut events: Vec<Event> = Vec::with_capacity(self.targets.len());
        for (i, t) in self.targets.iter().enumerate() {
            let at = || format!("target {i} (frame {}, joint {})", t.frame, t.joint);
            let key = key_index(cfg, &t.joint).with_context(at)?;
            if t.frame >= end {
                bail!("{}: the script has {end} frames", at());
            }
            match (t.to, t.until) {
                (Some(_), None) => bail!("{}: \"to\" needs \"until\" (the frame it arrives)", at()),
                (None, Some(_)) => bail!("{}: \"until\" needs \"to\" (where it arrives)", at()),
                _ => {}
            }
            let values = t
                .position
                .iter()
                .chain(t.forward.iter().flatten())
                .chain(t.up.iter().flatten())
                .chain(t.to.iter().flatten());
            if let Some(v) = values.clone().find(|v| !v.is_finite()) {
                bail!("{}: value {v} is not finite", at());
            }
            let far = |p: &[f64; 3]| p.iter().any(|v| v.abs() > MAX_TARGET_M);
            if far(&t.position) || t.to.as_ref().is_some_and(far) {
                bail!("{}: position beyond {MAX_TARGET_M} m", at());
            }
            // The controller's own rule (`Reach::set_target`): any finite
            // axis with a non-zero component has a direction.
            for axis in [t.forward, t.up].into_iter().flatten() {
                if phasegate_controller::reach::unit(axis).is_none() {
                    bail!("{}: an axis of no length", at());
                }
            }
            if let Some(until) = t.until {
                if until <= t.frame {
                    bail!("{}: until {until} is not after frame {}", at(), t.frame);
                }
                if until >= end {
                    bail!("{}: until {until} is past the script's {end} frames", at());
                }
            }
            events.push(Event {
                index: i,
                key,
                target: t,
            });
        }
        // Stable: among equal (frame, key) the entries keep their order.
        events.sort_by_key(|e| (e.target.frame, e.key));
        for w in events.windows(2) {
            let (a, b) = (&w[0], &w[1]);
            if (a.target.frame, a.key) == (b.target.frame, b.key) {
                let t = b.target;
                bail!(
                    "target {} (frame {}, joint {}): a second target for key joint {} at frame {} \
                     (target {} is the first)",
                    b.index,
                    t.frame,
                    t.joint,
                    cfg.key_joints.get(b.key).map_or("?", String::as_str),
                    t.frame,
                    a.index
                );
            }
        }
        Ok(events)
    }
}

/// An axis [`TargetScript::checked`] accepted, normalised as the controller
/// normalises (overflow-safe: scaled by its largest component first).
fn unit(v: [f64; 3]) -> [f64; 3] {
    phasegate_controller::reach::unit(v).unwrap_or(v)
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

    fn script(json: &str) -> TargetScript {
        serde_json::from_str(json).unwrap()
    }

    /// Axes whose squares overflow or vanish keep their direction (the
    /// controller's rule, `phasegate_controller::reach::unit`), also where
    /// the f32 network input could not hold the values as written.
    #[test]
    fn axes_of_any_finite_size_keep_their_direction() {
        let cfg = cfg();
        let start = vec![0.0; 36];
        let s = script(
            r#"{"targets": [{"frame": 0, "joint": 0, "position": [0, 1, 0],
                "forward": [1e300, 1e300, 0], "up": [0, 1e-300, 0]}]}"#,
        );
        let b = s.blocks(&cfg, &start, 1).unwrap();
        let h = std::f64::consts::FRAC_1_SQRT_2;
        assert!(
            (b[0][12] - h).abs() < 1e-15 && (b[0][13] - h).abs() < 1e-15,
            "{:?}",
            &b[0][12..18]
        );
        assert_eq!(&b[0][15..18], &[0.0, 1.0, 0.0]);
    }

    #[test]
    fn moving_targets_move_linearly_then_hold() {
        let cfg = cfg();
        let start: Vec<f64> = (0..36).map(|i| i as f64 / 100.0).collect();
        let s = script(
            r#"{"name": "m", "description": "a moving target", "frames": 30, "targets": [
                {"frame": 10, "joint": "LeftHand", "position": [0, 0, 0],
                 "to": [1, 2, -3], "until": 20, "up": [0, 0, 3]},
                {"frame": 5, "joint": 1, "position": [0.1, 0.2, 0.3],
                 "to": [0.4, -0.7, 1.1], "until": 8}]}"#,
        );
        assert_eq!(s.name.as_deref(), Some("m"));
        let b = s.blocks(&cfg, &start, 30).unwrap();
        assert_eq!(&b[9][0..3], &start[0..3], "not before its frame");
        assert_eq!(&b[10][0..3], &[0.0, 0.0, 0.0], "its position at its frame");
        assert_eq!(&b[15][0..3], &[0.5, 1.0, -1.5], "midway");
        assert_eq!(&b[19][0..3], &[0.9, 1.8, -2.7]);
        assert_eq!(&b[20][0..3], &[1.0, 2.0, -3.0], "at until");
        assert_eq!(&b[29][0..3], &[1.0, 2.0, -3.0], "and after");
        assert_eq!(&b[29][15..18], &[0.0, 0.0, 1.0], "axes set at its frame");
        // Inexact steps: the documented expression, in its order.
        let (p, to) = ([0.1, 0.2, 0.3], [0.4, -0.7, 1.1]);
        for (f, want) in [(5, p), (8, to), (29, to)] {
            assert_eq!(&b[f][3..6], &want, "frame {f}");
        }
        for (f, row) in b.iter().enumerate().take(8).skip(6) {
            let w = (f - 5) as f64 / (8 - 5) as f64;
            let want: Vec<f64> = (0..3).map(|c| p[c] + (to[c] - p[c]) * w).collect();
            assert_eq!(&row[3..6], &want[..], "frame {f}");
        }
        assert_eq!(
            b[6][3].to_bits(),
            (0.1f64 + (0.4 - 0.1) * (1.0 / 3.0)).to_bits()
        );
    }

    #[test]
    fn a_later_entry_interrupts_a_moving_target() {
        let cfg = cfg();
        let s = script(
            r#"{"targets": [
                {"frame": 0, "joint": 0, "position": [0, 0, 0], "to": [1, 0, 0], "until": 20},
                {"frame": 10, "joint": 0, "position": [0, 1, 0]},
                {"frame": 15, "joint": 0, "position": [0, 1, 0], "to": [0, 1, 2], "until": 25},
                {"frame": 17, "joint": 1, "position": [5, 5, 5]}]}"#,
        );
        let b = s.blocks(&cfg, &vec![0.0; 36], 30).unwrap();
        assert_eq!(&b[9][0..3], &[0.45, 0.0, 0.0]);
        assert_eq!(&b[10][0..3], &[0.0, 1.0, 0.0], "interrupted at 10");
        assert_eq!(&b[14][0..3], &[0.0, 1.0, 0.0], "and held, not resumed");
        assert_eq!(&b[20][0..3], &[0.0, 1.0, 1.0], "the next motion");
        assert_eq!(&b[29][0..3], &[0.0, 1.0, 2.0]);
        assert_eq!(
            &b[29][3..6],
            &[5.0, 5.0, 5.0],
            "the other hand does not interrupt"
        );
        let iv = s.intervals(&cfg, 30).unwrap();
        let got: Vec<(usize, usize, usize, usize, bool)> = iv
            .iter()
            .map(|i| (i.index, i.key, i.start, i.end, i.moving))
            .collect();
        assert_eq!(
            got,
            [
                (0, 0, 0, 10, true),
                (1, 0, 10, 15, false),
                (2, 0, 15, 30, true),
                (3, 1, 17, 30, false)
            ]
        );
    }

    #[test]
    fn intervals_of_a_small_script() {
        let cfg = cfg();
        let s = script(
            r#"{"frames": 100, "targets": [
                {"frame": 60, "joint": "RightHand", "position": [-0.3, 1.0, 0.0]},
                {"frame": 0, "joint": "RightHand", "position": [-0.2, 1.3, 0.3]},
                {"frame": 20, "joint": "LeftHand", "position": [0.2, 1.3, 1.3], "unreachable": true},
                {"frame": 0, "joint": "LeftHand", "position": [0.2, 1.3, 0.3],
                 "to": [0.3, 1.3, 0.3], "until": 40},
                {"frame": 80, "joint": 0, "position": [0.3, 1.0, 0.0]},
                {"frame": 90, "joint": 1, "position": [-0.3, 1.2, 0.0]}]}"#,
        );
        let iv = |index, key, start, end, moving, unreachable| TargetInterval {
            index,
            key,
            start,
            end,
            moving,
            unreachable,
        };
        assert_eq!(
            s.intervals(&cfg, 100).unwrap(),
            [
                iv(3, 0, 0, 20, true, false),
                iv(1, 1, 0, 60, false, false),
                iv(2, 0, 20, 80, false, true),
                iv(0, 1, 60, 90, false, false),
                iv(4, 0, 80, 100, false, false),
                iv(5, 1, 90, 100, false, false),
            ]
        );
        // A shorter rollout drops the entries it never reaches.
        assert_eq!(
            s.intervals(&cfg, 70).unwrap(),
            [
                iv(3, 0, 0, 20, true, false),
                iv(1, 1, 0, 60, false, false),
                iv(2, 0, 20, 70, false, true),
                iv(0, 1, 60, 70, false, false),
            ]
        );
        let b = s.blocks(&cfg, &vec![0.0; 36], 100).unwrap();
        assert_eq!(
            &b[30][0..3],
            &[0.2, 1.3, 1.3],
            "unreachable changes nothing"
        );
    }

    #[test]
    fn bad_moving_targets_and_duplicates_are_refused_naming_them() {
        let cfg = cfg();
        let start = vec![0.0; 36];
        let mut cases: Vec<(TargetScript, &str)> = [
            (
                r#"{"frame": 0, "joint": 0, "position": [0,0,0], "to": [1,0,0]}"#,
                "needs \"until\"",
            ),
            (
                r#"{"frame": 0, "joint": 0, "position": [0,0,0], "until": 5}"#,
                "needs \"to\"",
            ),
            (
                r#"{"frame": 4, "joint": 0, "position": [0,0,0], "to": [1,0,0], "until": 4}"#,
                "not after frame 4",
            ),
            (
                r#"{"frame": 4, "joint": 0, "position": [0,0,0], "to": [1,0,0], "until": 2}"#,
                "not after frame 4",
            ),
            (
                r#"{"frame": 4, "joint": 0, "position": [0,0,0], "to": [1,0,0], "until": 10}"#,
                "past the script's 10 frames",
            ),
            (
                r#"{"frame": 4, "joint": 0, "position": [0,0,0], "to": [1e9,0,0], "until": 6}"#,
                "beyond",
            ),
        ]
        .into_iter()
        .map(|(t, needle)| {
            (
                script(&format!(r#"{{"frames": 10, "targets": [{t}]}}"#)),
                needle,
            )
        })
        .collect();
        let mut nan = script(
            r#"{"targets": [{"frame": 0, "joint": 0, "position": [0,0,0], "to": [1,0,0], "until": 5}]}"#,
        );
        nan.targets[0].to = Some([0.0, f64::NAN, 0.0]);
        cases.push((nan, "not finite"));
        let dup = script(
            r#"{"targets": [
                {"frame": 3, "joint": 1, "position": [0,0,0]},
                {"frame": 3, "joint": "LeftHand", "position": [0,0,0]},
                {"frame": 3, "joint": 0, "position": [1,0,0]}]}"#,
        );
        cases.push((dup, "a second target for key joint LeftHand at frame 3"));
        for (s, needle) in &cases {
            let e = format!("{:#}", s.blocks(&cfg, &start, 10).unwrap_err());
            let at = if needle.contains("second") {
                "target 2 (frame 3"
            } else {
                "target 0"
            };
            assert!(e.contains(needle) && e.contains(at), "{s:?}: {e}");
            let e2 = format!("{:#}", s.intervals(&cfg, 10).unwrap_err());
            assert_eq!(e, e2, "intervals refuses what blocks refuses");
        }
        assert!(serde_json::from_str::<TargetScript>(
            r#"{"targets": [{"frame": 0, "joint": 0, "position": [0,0,0], "speed": 1}]}"#
        )
        .is_err());
        // until within the script's frames: a shorter --frames only cuts it off.
        let s = script(
            r#"{"frames": 10, "targets": [{"frame": 0, "joint": 0, "position": [0,0,0], "to": [9,0,0], "until": 9}]}"#,
        );
        let b = s.blocks(&cfg, &start, 4).unwrap();
        assert_eq!(&b[3][0..3], &[3.0, 0.0, 0.0]);
    }

    /// `tools/omg/scripts/expected.json` (from `tools/omg/scripts.py`) against
    /// this module: every committed script's intervals exactly, its blocks'
    /// sums and sampled blocks to 1e-12.
    #[test]
    fn committed_scripts_match_the_python_twin() {
        let cfg = cfg();
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tools/omg/scripts");
        let text = std::fs::read_to_string(dir.join("expected.json")).unwrap();
        let expected: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(
            expected["key_joints"].as_array().unwrap(),
            &cfg.key_joints
                .iter()
                .map(|n| serde_json::Value::from(n.as_str()))
                .collect::<Vec<_>>()
        );
        let floats = |v: &serde_json::Value| -> Vec<f64> {
            v.as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect()
        };
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * b.abs().max(1.0);
        let start = floats(&expected["start_block"]);
        let mut files: Vec<String> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .filter(|n| n.ends_with(".json") && n != "expected.json")
            .collect();
        files.sort();
        let scripts = expected["scripts"].as_object().unwrap();
        let mut listed: Vec<&String> = scripts.keys().collect();
        listed.sort();
        assert_eq!(
            listed,
            files.iter().collect::<Vec<_>>(),
            "expected.json is out of date: PYTHONPATH=. python3 -m tools.omg.scripts --expected tools/omg/scripts/expected.json"
        );
        assert!(files.len() >= 24, "{} scripts", files.len());
        for name in &files {
            let s = TargetScript::load(dir.join(name).to_str().unwrap()).unwrap();
            let want = &scripts[name];
            let n = s.frames.unwrap_or(DEFAULT_FRAMES);
            assert_eq!(want["frames"].as_u64(), Some(n as u64), "{name}");
            let got: Vec<serde_json::Value> = s
                .intervals(&cfg, n)
                .unwrap()
                .iter()
                .map(|i| {
                    serde_json::json!({"index": i.index, "key": i.key, "start": i.start,
                        "end": i.end, "moving": i.moving, "unreachable": i.unreachable})
                })
                .collect();
            assert_eq!(
                &got,
                want["intervals"].as_array().unwrap(),
                "{name}: intervals"
            );
            let b = s.blocks(&cfg, &start, n).unwrap();
            let (mut sum, mut sum_sq) = (0.0, 0.0);
            for v in b.iter().flatten() {
                sum += v;
                sum_sq += v * v;
            }
            let (ws, wq) = (
                want["sum"].as_f64().unwrap(),
                want["sum_sq"].as_f64().unwrap(),
            );
            assert!(
                close(sum, ws) && close(sum_sq, wq),
                "{name}: sums {sum} {sum_sq}, Python {ws} {wq}"
            );
            for sample in want["samples"].as_array().unwrap() {
                let f = sample[0].as_u64().unwrap() as usize;
                let w = floats(&sample[1]);
                assert!(
                    b[f].iter().zip(&w).all(|(&a, &b)| close(a, b)) && w.len() == b[f].len(),
                    "{name}: frame {f}: {:?}, Python {w:?}",
                    b[f]
                );
            }
        }
    }

    fn s_empty() -> TargetScript {
        TargetScript {
            name: None,
            description: None,
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
