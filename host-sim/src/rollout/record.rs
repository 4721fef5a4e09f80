//! A recorded rollout and its `.npz` form.
//!
//! | array | shape | meaning |
//! |---|---|---|
//! | `root_position` | (N, 3) | root `(x, 0, z)`, world |
//! | `facing` | (N, 2) | unit root facing `(x, z)` |
//! | `yaw` | (N,) | root yaw, radians (`atan2(x, z)`) |
//! | `joint_positions` | (N, 31, 3) | world |
//! | `joint_rotations` | (N, 31, 4) | world, quaternion `[x, y, z, w]`, `w >= 0` |
//! | `contacts` | (N, 4) | left heel, left toe, right heel, right toe |
//! | `phase` | (N,) | radians, `[0, 2 pi)` |
//! | `gaits` | (N, 4) | stand, walk, jog, crouch weights the network saw |
//! | `commands` | (N, 8) | velocity x z, facing x z, gait stand walk jog crouch |
//! | `mean_pose` | (31, 3) | joint positions of the mean output, root space |
//! | `parents` | (31,) | parent joint, -1 for the root |
//! | `frame_rate` | (1,) | frames per second |
//!
//! All float32. Frame `i` is the pose produced by the `i`-th step.

use anyhow::{anyhow, bail, Result};
use exporter::npz::{npz_bytes, read_npz, write_npz, NpArray};
use phasegate_controller::layout::{JOINTS, PARENTS};
use phasegate_controller::{Command, GaitWeights, Pose};
use std::collections::BTreeMap;
use std::f64::consts::TAU;
use std::path::Path;

use super::script::FRAME_RATE;

/// A rollout: one pose per frame and the commands that produced them.
#[derive(Clone, Debug, PartialEq)]
pub struct Rollout {
    /// Poses (f64; exact copies of f32 poses).
    pub poses: Vec<Pose<f64>>,
    /// The command of each frame.
    pub commands: Vec<Command>,
    /// Joint positions of the mean pose, root space.
    pub mean_pose: [[f64; 3]; JOINTS],
    /// Frames per second.
    pub frame_rate: f64,
}

fn flat<const N: usize>(rows: impl Iterator<Item = [f64; N]>) -> Vec<f32> {
    rows.flat_map(|r| r.map(|v| v as f32)).collect()
}

impl Rollout {
    /// Frames.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// No frames.
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// The arrays of the `.npz` form, in the table's order.
    pub fn arrays(&self) -> Vec<(&'static str, Vec<u64>, Vec<f32>)> {
        let n = self.len() as u64;
        let j = JOINTS as u64;
        let p = &self.poses;
        vec![
            (
                "root_position",
                vec![n, 3],
                flat(p.iter().map(|p| p.root_position)),
            ),
            ("facing", vec![n, 2], flat(p.iter().map(|p| p.facing))),
            ("yaw", vec![n], flat(p.iter().map(|p| [p.yaw()]))),
            (
                "joint_positions",
                vec![n, j, 3],
                flat(p.iter().flat_map(|p| p.joint_positions)),
            ),
            (
                "joint_rotations",
                vec![n, j, 4],
                flat(p.iter().flat_map(|p| p.joint_rotations)),
            ),
            ("contacts", vec![n, 4], flat(p.iter().map(|p| p.contacts))),
            ("phase", vec![n], flat(p.iter().map(|p| [p.phase * TAU]))),
            ("gaits", vec![n, 4], flat(p.iter().map(|p| p.gaits))),
            (
                "commands",
                vec![n, 8],
                self.commands
                    .iter()
                    .flat_map(phasegate_wire::command_values)
                    .collect(),
            ),
            (
                "mean_pose",
                vec![j, 3],
                flat(self.mean_pose.iter().copied()),
            ),
            (
                "parents",
                vec![j],
                PARENTS.iter().map(|&p| f32::from(p)).collect(),
            ),
            ("frame_rate", vec![1], vec![self.frame_rate as f32]),
        ]
    }

    /// Writes the `.npz` (atomically).
    pub fn write(&self, path: &Path) -> Result<()> {
        write_npz(path, &self.arrays())
    }

    /// The bytes [`Rollout::write`] writes.
    pub fn to_npz(&self) -> Result<Vec<u8>> {
        npz_bytes(&self.arrays())
    }

    /// Reads a rollout `.npz`.
    pub fn read(path: &Path) -> Result<Rollout> {
        let a = read_npz(path)?;
        Rollout::from_arrays(&a).map_err(|e| anyhow!("{}: {e}", path.display()))
    }

    fn from_arrays(a: &BTreeMap<String, NpArray>) -> Result<Rollout> {
        let get = |name: &str, tail: &[u64]| -> Result<(usize, &[f64])> {
            let arr = a
                .get(name)
                .ok_or_else(|| anyhow!("missing array {name}: not a rollout file"))?;
            let (lead, rest) = arr
                .shape
                .split_at(arr.shape.len().saturating_sub(tail.len()));
            if rest != tail || lead.len() > 1 {
                bail!(
                    "array {name} has shape {:?}, expected (N, {tail:?})",
                    arr.shape
                );
            }
            Ok((lead.first().copied().unwrap_or(1) as usize, &arr.data))
        };
        let (n, root) = get("root_position", &[3])?;
        let arrays = [
            get("facing", &[2])?,
            get("joint_positions", &[JOINTS as u64, 3])?,
            get("joint_rotations", &[JOINTS as u64, 4])?,
            get("contacts", &[4])?,
            get("phase", &[])?,
            get("gaits", &[4])?,
            get("commands", &[8])?,
        ];
        if arrays.iter().any(|(m, _)| *m != n) {
            bail!("arrays disagree on the number of frames");
        }
        let [facing, jp, jr, contacts, phase, gaits, commands] = arrays.map(|(_, d)| d);
        let (_, mean) = get("mean_pose", &[3])?;
        let frame_rate = a
            .get("frame_rate")
            .and_then(|f| f.data.first().copied())
            .unwrap_or(FRAME_RATE);
        let arr = |d: &[f64], i: usize, k: usize| -> Vec<f64> { d[i * k..(i + 1) * k].to_vec() };
        let mut poses = Vec::with_capacity(n);
        let mut cmds = Vec::with_capacity(n);
        for i in 0..n {
            let jp = arr(jp, i, 3 * JOINTS);
            let jr = arr(jr, i, 4 * JOINTS);
            poses.push(Pose {
                frame: i as u32 + 1,
                root_position: [root[3 * i], root[3 * i + 1], root[3 * i + 2]],
                facing: [facing[2 * i], facing[2 * i + 1]],
                joint_positions: std::array::from_fn(|j| [jp[3 * j], jp[3 * j + 1], jp[3 * j + 2]]),
                joint_rotations: std::array::from_fn(|j| {
                    [jr[4 * j], jr[4 * j + 1], jr[4 * j + 2], jr[4 * j + 3]]
                }),
                contacts: std::array::from_fn(|k| contacts[4 * i + k]),
                phase: phase[i] / TAU,
                gaits: std::array::from_fn(|k| gaits[4 * i + k]),
            });
            let c = arr(commands, i, 8)
                .iter()
                .map(|&v| v as f32)
                .collect::<Vec<_>>();
            cmds.push(Command {
                velocity: [c[0], c[1]],
                facing: [c[2], c[3]],
                gait: GaitWeights {
                    stand: c[4],
                    walk: c[5],
                    jog: c[6],
                    crouch: c[7],
                },
            });
        }
        if mean.len() != 3 * JOINTS {
            bail!(
                "mean_pose has {} values, expected {}",
                mean.len(),
                3 * JOINTS
            );
        }
        Ok(Rollout {
            poses,
            commands: cmds,
            mean_pose: std::array::from_fn(|j| [mean[3 * j], mean[3 * j + 1], mean[3 * j + 2]]),
            frame_rate,
        })
    }
}
