//! A recorded OMG reaching rollout and its `.npz` form.
//!
//! | array | shape | meaning |
//! |---|---|---|
//! | `frames` | (N, n) | the model's frames, raw units (frame 0 is the start frame) |
//! | `joint_positions` | (N, J, 3) | root space, metres |
//! | `target_positions` | (N, K, 3) | each key joint's target, root space |
//! | `target_axes` | (N, K, 6) | each target's forward and up axes |
//! | `key_joints` | (K,) | the key joints' indices among the J joints |
//! | `parents` | (J,) | parent joint, -1 for the root |
//! | `frame_rate` | (1,) | frames per second |
//!
//! All float32. `host-sim rollout-compare` and `render` tell it from a
//! locomotion rollout by its `target_positions` array.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{anyhow, bail, Result};
use exporter::net::omg::OmgConfig;
use exporter::npz::{read_npz, write_npz, NpArray};

/// The array that marks an OMG record.
pub const MARKER: &str = "target_positions";

/// A reaching rollout.
#[derive(Clone, Debug, PartialEq)]
pub struct OmgRecord {
    /// The model's frames, raw units.
    pub frames: Vec<Vec<f64>>,
    /// Joint positions per frame, root space.
    pub positions: Vec<Vec<[f64; 3]>>,
    /// Target positions per frame and key joint.
    pub targets: Vec<Vec<[f64; 3]>>,
    /// Target forward and up axes per frame and key joint.
    pub axes: Vec<Vec<[f64; 6]>>,
    /// Key joints' indices.
    pub key_joints: Vec<usize>,
    /// Parent of each joint (-1: root).
    pub parents: Vec<i32>,
    /// Frames per second.
    pub frame_rate: f64,
}

impl OmgRecord {
    /// The record of `frames` (each with its target block in place).
    pub fn new(cfg: &OmgConfig, parents: &[i32], frames: Vec<Vec<f64>>) -> Result<OmgRecord> {
        let (pos, tpos, trot) = (
            cfg.slice("pos"),
            cfg.slice("target_pos"),
            cfg.slice("target_rot"),
        );
        if parents.len() != cfg.joints || pos.len() != 3 * cfg.joints {
            bail!(
                "{} parents and a position slice of {} for a rig of {} joints",
                parents.len(),
                pos.len(),
                cfg.joints
            );
        }
        let k = cfg.key;
        let at3 = |f: &[f64], s: usize| [f[s], f[s + 1], f[s + 2]];
        let positions = frames
            .iter()
            .map(|f| (0..cfg.joints).map(|j| at3(f, pos.start + 3 * j)).collect())
            .collect();
        let targets = frames
            .iter()
            .map(|f| (0..k).map(|i| at3(f, tpos.start + 3 * i)).collect())
            .collect();
        let axes = frames
            .iter()
            .map(|f| {
                (0..k)
                    .map(|i| {
                        let s = trot.start + 6 * i;
                        [f[s], f[s + 1], f[s + 2], f[s + 3], f[s + 4], f[s + 5]]
                    })
                    .collect()
            })
            .collect();
        Ok(OmgRecord {
            frames,
            positions,
            targets,
            axes,
            key_joints: cfg.key_joint_indices.clone(),
            parents: parents.to_vec(),
            frame_rate: 60.0,
        })
    }

    /// Frames.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// No frames.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Position of key joint `k` at frame `t`.
    pub fn key_position(&self, t: usize, k: usize) -> [f64; 3] {
        self.positions[t][self.key_joints[k]]
    }

    /// Writes the `.npz` (atomically).
    pub fn write(&self, path: &Path) -> Result<()> {
        let n = self.len() as u64;
        let j = self.parents.len() as u64;
        let k = self.key_joints.len() as u64;
        let w = self.frames.first().map_or(0, Vec::len) as u64;
        let f32s = |v: &mut dyn Iterator<Item = f64>| v.map(|x| x as f32).collect::<Vec<_>>();
        write_npz(
            path,
            &[
                (
                    "frames",
                    vec![n, w],
                    f32s(&mut self.frames.iter().flatten().copied()),
                ),
                (
                    "joint_positions",
                    vec![n, j, 3],
                    f32s(&mut self.positions.iter().flatten().flatten().copied()),
                ),
                (
                    MARKER,
                    vec![n, k, 3],
                    f32s(&mut self.targets.iter().flatten().flatten().copied()),
                ),
                (
                    "target_axes",
                    vec![n, k, 6],
                    f32s(&mut self.axes.iter().flatten().flatten().copied()),
                ),
                (
                    "key_joints",
                    vec![k],
                    f32s(&mut self.key_joints.iter().map(|&v| v as f64)),
                ),
                (
                    "parents",
                    vec![j],
                    f32s(&mut self.parents.iter().map(|&v| f64::from(v))),
                ),
                ("frame_rate", vec![1], vec![self.frame_rate as f32]),
            ],
        )
    }

    /// Whether the `.npz` at `path` is an OMG record.
    pub fn is_record(path: &Path) -> Result<bool> {
        Ok(read_npz(path)?.contains_key(MARKER))
    }

    /// Reads a record.
    pub fn read(path: &Path) -> Result<OmgRecord> {
        let a = read_npz(path)?;
        OmgRecord::from_arrays(&a).map_err(|e| anyhow!("{}: {e}", path.display()))
    }

    fn from_arrays(a: &BTreeMap<String, NpArray>) -> Result<OmgRecord> {
        let get = |name: &str, rank: usize| -> Result<&NpArray> {
            let arr = a
                .get(name)
                .ok_or_else(|| anyhow!("missing array {name}: not an OMG rollout"))?;
            if arr.shape.len() != rank {
                bail!(
                    "array {name} has shape {:?}, expected rank {rank}",
                    arr.shape
                );
            }
            Ok(arr)
        };
        let frames = get("frames", 2)?;
        let jp = get("joint_positions", 3)?;
        let tp = get(MARKER, 3)?;
        let ta = get("target_axes", 3)?;
        let keys = get("key_joints", 1)?;
        let parents = get("parents", 1)?;
        let rate = get("frame_rate", 1)?;
        let dim = |arr: &NpArray, i: usize| usize::try_from(arr.shape[i]).unwrap_or(usize::MAX);
        let (n, j, k) = (dim(frames, 0), dim(parents, 0), dim(keys, 0));
        if n == 0 || j == 0 || k == 0 || dim(frames, 1) == 0 {
            bail!("a rollout of no frames, joints, key joints or frame width");
        }
        for (name, arr, want) in [
            ("joint_positions", jp, [n, j, 3]),
            (MARKER, tp, [n, k, 3]),
            ("target_axes", ta, [n, k, 6]),
        ] {
            if (0..3).any(|i| dim(arr, i) != want[i]) {
                bail!("array {name} has shape {:?}, expected {want:?}", arr.shape);
            }
        }
        let index = |v: f64, len: usize, what: &str| -> Result<usize> {
            if v.fract() == 0.0 && v >= 0.0 && (v as usize) < len {
                Ok(v as usize)
            } else {
                bail!("{what} {v} is not a joint index below {len}")
            }
        };
        let key_joints = keys
            .data
            .iter()
            .map(|&v| index(v, j, "key joint"))
            .collect::<Result<Vec<_>>>()?;
        let parents = parents
            .data
            .iter()
            .map(|&v| {
                if v == -1.0 {
                    Ok(-1)
                } else {
                    index(v, j, "parent").map(|p| p as i32)
                }
            })
            .collect::<Result<Vec<_>>>()?;
        let w = dim(frames, 1);
        let rows = |d: &[f64], m: usize| -> Vec<Vec<[f64; 3]>> {
            d.chunks(m * 3)
                .map(|r| r.chunks(3).map(|c| [c[0], c[1], c[2]]).collect())
                .collect()
        };
        Ok(OmgRecord {
            frames: frames.data.chunks(w.max(1)).map(<[f64]>::to_vec).collect(),
            positions: rows(&jp.data, j),
            targets: rows(&tp.data, k),
            axes: ta
                .data
                .chunks(k * 6)
                .map(|r| {
                    r.chunks(6)
                        .map(|c| [c[0], c[1], c[2], c[3], c[4], c[5]])
                        .collect()
                })
                .collect(),
            key_joints,
            parents,
            frame_rate: rate.data.first().copied().unwrap_or(60.0),
        })
    }
}
