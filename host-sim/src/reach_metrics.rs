//! Reaching metrics: the Rust twin of `tools/omg/metrics.py` (the
//! definitions; `tools/omg/evaluate.py` applies them), used by
//! `host-sim omg-reach` ([`crate::omg_reach`]), its target scripts and
//! `host-sim demo` ([`crate::demo_omg`]).
//!
//! Per **hand target** ([`HandTarget`]: an interval `[start, end)` of frames
//! during which one hand is asked for one target, which may move; in a data
//! clip each hand's first `spawned[h]` constant-target intervals,
//! [`clip_intervals`]; in a target script the entries of
//! [`TargetScript::intervals`](crate::omg_rollout::script::TargetScript::intervals)
//! for the hands, [`script_intervals`], the one marked `unreachable`
//! reported apart, [`unreachable()`]); the distance on frame `t` is to frame
//! `t`'s target position:
//!
//! * **near start**: the hand is within [`CONTACT_RADIUS_M`] of the target
//!   on `start`. Such a target says nothing about reaching: it is counted
//!   apart and left out of every rate below;
//! * **reached**: the hand is within [`CONTACT_RADIUS_M`] on some frame of
//!   the interval;
//! * **plausibly reached**: on some frame of the interval the hand is
//!   within [`CONTACT_RADIUS_M`] *and* every bone's length is within
//!   [`BONE_TOL_M`] of the rig's rest length ([`Bones`]);
//! * **frames to reach**: from `start` to the first plausible reach (the
//!   median over the targets plausibly reached);
//! * **final distance**: on frame `end - 1` (the mean).
//!
//! Over whole rollouts: the **bone-length error** `|length - rest length|`
//! of every bone on every frame (p50 and p99 in cm, NumPy's linear
//! percentile, [`percentile`]) and the **roughness**: per clip
//! `sqrt(mean_t dr_t^2)`, `dr_t` the mean angle between frames `t` and
//! `t + 1` of every joint's forward and up vectors (radians per frame;
//! eq 3.9 in the author's code's form), averaged over clips ([`roughness`]).
//!
//! The Rust and the Python figures agree to rounding (NumPy sums means
//! pairwise, Rust in order): `host-sim/tests/reach_metrics.rs` checks them
//! on the trajectories of `host-sim/tests/data/reach_metrics.json`.

use std::ops::Range;

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use crate::omg_rollout::script::TargetInterval;

/// A hand this close to its target reaches it, metres (the data's contact
/// threshold; `metrics.CONTACT_RADIUS`).
pub const CONTACT_RADIUS_M: f64 = 0.1;

/// A bone this close to its rest length is plausible, metres
/// (`metrics.BONE_TOL`).
pub const BONE_TOL_M: f64 = 0.01;

/// The bones of a rig (joint to parent) and their rest lengths.
#[derive(Clone, Debug, PartialEq)]
pub struct Bones {
    /// `(child, parent)` of every joint that has a parent, in joint order.
    pub pairs: Vec<(usize, usize)>,
    /// Each bone's rest length, metres (the length of its child's rest
    /// offset).
    pub rest_m: Vec<f64>,
}

impl Bones {
    /// The bones of a rig of `parents` (`None`: a root) and rest `offsets`
    /// from the parent (`metrics.rest_bone_lengths`).
    pub fn new(parents: &[Option<usize>], offsets: &[[f64; 3]]) -> Result<Bones> {
        if parents.len() != offsets.len() {
            bail!(
                "{} parents and {} rest offsets",
                parents.len(),
                offsets.len()
            );
        }
        let mut b = Bones {
            pairs: Vec::new(),
            rest_m: Vec::new(),
        };
        for (j, (p, o)) in parents.iter().zip(offsets).enumerate() {
            if let Some(p) = *p {
                if p >= parents.len() {
                    bail!("joint {j}: parent {p} of a rig of {} joints", parents.len());
                }
                b.pairs.push((j, p));
                b.rest_m.push(norm(*o));
            }
        }
        Ok(b)
    }

    /// The bones of a `rig.json` as `tools/omg/generate` writes it
    /// (`parents`, -1 a root, and `rest_offsets`).
    pub fn from_rig_json(bytes: &[u8]) -> Result<Bones> {
        #[derive(Deserialize)]
        struct Rig {
            parents: Vec<i64>,
            rest_offsets: Vec<[f64; 3]>,
        }
        let rig: Rig = serde_json::from_slice(bytes)
            .context("not a rig.json with \"parents\" and \"rest_offsets\"")?;
        let parents: Vec<Option<usize>> = rig
            .parents
            .iter()
            .map(|&p| usize::try_from(p).ok())
            .collect();
        Bones::new(&parents, &rig.rest_offsets)
    }

    /// `|length - rest length|` of every bone in a pose of joint
    /// positions, metres.
    pub fn errors(&self, pos: &[[f64; 3]]) -> Vec<f64> {
        self.pairs
            .iter()
            .zip(&self.rest_m)
            .map(|(&(c, p), &rest)| (norm(sub(pos[c], pos[p])) - rest).abs())
            .collect()
    }
}

/// Where a frame holds the joint positions and rotations, and which joints
/// the hands are.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FrameLayout {
    /// Joint positions (3 per joint).
    pub pos: Range<usize>,
    /// Joint forward and up vectors (6 per joint).
    pub rot: Range<usize>,
    /// The key joints (0 and 1: the hands).
    pub key_joints: Vec<usize>,
}

impl FrameLayout {
    /// The layout of an OMG model's frames.
    pub fn of(cfg: &exporter::net::omg::OmgConfig) -> FrameLayout {
        FrameLayout {
            pos: cfg.slice("pos"),
            rot: cfg.slice("rot"),
            key_joints: cfg.key_joint_indices.clone(),
        }
    }

    /// The joint positions of a frame.
    pub fn positions(&self, frame: &[f64]) -> Vec<[f64; 3]> {
        frame[self.pos.clone()]
            .chunks_exact(3)
            .map(|c| [c[0], c[1], c[2]])
            .collect()
    }
}

/// One hand target: hand `hand`'s target on frames `start..end`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct HandTarget {
    /// Key joint: 0 the left hand, 1 the right.
    pub hand: usize,
    /// Its first frame.
    pub start: usize,
    /// One past its last frame.
    pub end: usize,
}

/// `[start, end)` of the first `count` constant-target intervals of one
/// hand's target positions (a new interval wherever the target moves more
/// than 1e-6 m from one frame to the next; `metrics.hand_intervals`).
pub fn hand_intervals(tpos: &[[f64; 3]], count: usize) -> Vec<(usize, usize)> {
    let mut bounds = vec![0];
    for t in 1..tpos.len() {
        if norm(sub(tpos[t], tpos[t - 1])) > 1e-6 {
            bounds.push(t);
        }
    }
    bounds.push(tpos.len());
    bounds
        .windows(2)
        .map(|w| (w[0], w[1]))
        .take(count)
        .collect()
}

/// The hand targets of a data clip: each hand's first `spawned[h]`
/// constant-target intervals (`metrics.clip_intervals`); `targets[t][h]`
/// is hand `h`'s target on frame `t`.
pub fn clip_intervals(targets: &[Vec<[f64; 3]>], spawned: [usize; 2]) -> Vec<HandTarget> {
    let mut out = Vec::new();
    for (hand, &count) in spawned.iter().enumerate() {
        let tpos: Vec<[f64; 3]> = targets.iter().map(|f| f[hand]).collect();
        for (start, end) in hand_intervals(&tpos, count) {
            out.push(HandTarget { hand, start, end });
        }
    }
    out
}

/// The hand targets of a target script's intervals: the hands' entries
/// (key joints 0 and 1), those counted and, apart, those marked
/// `unreachable` (as `tools/omg/evaluate.py: script_set`).
pub fn script_intervals(intervals: &[TargetInterval]) -> (Vec<HandTarget>, Vec<HandTarget>) {
    let (mut counted, mut far) = (Vec::new(), Vec::new());
    for iv in intervals.iter().filter(|iv| iv.key < 2) {
        let t = HandTarget {
            hand: iv.key,
            start: iv.start,
            end: iv.end,
        };
        if iv.unreachable {
            far.push(t);
        } else {
            counted.push(t);
        }
    }
    (counted, far)
}

/// The hand positions of target positions per frame (`targets[t][h]`):
/// hand `hand`'s distance to its target on every frame.
pub fn hand_distances(
    frames: &[Vec<f64>],
    targets: &[Vec<[f64; 3]>],
    layout: &FrameLayout,
    hand: usize,
) -> Vec<f64> {
    let at = layout.pos.start + 3 * layout.key_joints[hand];
    frames
        .iter()
        .zip(targets)
        .map(|(f, t)| norm(sub([f[at], f[at + 1], f[at + 2]], t[hand])))
        .collect()
}

/// Per-target outcomes and per-rollout figures, gathered over clips or
/// scripts (`metrics.ReachCounts`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ReachCounts {
    /// Whether each counted target was reached.
    pub reached: Vec<bool>,
    /// Whether each counted target was plausibly reached.
    pub plausible: Vec<bool>,
    /// Frames from start to the first plausible reach, of the targets
    /// plausibly reached.
    pub frames: Vec<usize>,
    /// Each counted target's distance on its last frame, metres.
    pub final_m: Vec<f64>,
    /// Targets the hand started within reach of (not counted).
    pub near_start: usize,
    /// Every bone's length error on every frame, metres.
    pub bone_err_m: Vec<f64>,
    /// Each rollout's roughness, radians per frame.
    pub roughness: Vec<f64>,
}

impl ReachCounts {
    /// One target on frames `start..end`: `d` the hand-target distance and
    /// `bones_ok` whether every bone is within [`BONE_TOL_M`], per frame
    /// (`ReachCounts.add_target`).
    pub fn add_target(&mut self, d: &[f64], bones_ok: &[bool], start: usize, end: usize) {
        if d[start] < CONTACT_RADIUS_M {
            self.near_start += 1;
            return;
        }
        let hit = |t: usize| d[t] < CONTACT_RADIUS_M;
        self.reached.push((start..end).any(hit));
        let first = (start..end).find(|&t| hit(t) && bones_ok[t]);
        self.plausible.push(first.is_some());
        self.frames.extend(first.map(|t| t - start));
        self.final_m.push(d[end - 1]);
    }

    /// One rollout (`metrics.add_clip`): `frames` in raw units, `targets[t][h]`
    /// hand `h`'s target on frame `t`, its counted hand targets.
    pub fn add_clip(
        &mut self,
        frames: &[Vec<f64>],
        targets: &[Vec<[f64; 3]>],
        intervals: &[HandTarget],
        layout: &FrameLayout,
        bones: &Bones,
    ) {
        let mut ok = Vec::with_capacity(frames.len());
        for f in frames {
            let e = bones.errors(&layout.positions(f));
            ok.push(e.iter().all(|&v| v <= BONE_TOL_M));
            self.bone_err_m.extend(e);
        }
        for t in intervals {
            let d = hand_distances(frames, targets, layout, t.hand);
            self.add_target(&d, &ok, t.start, t.end);
        }
        self.roughness.push(roughness(frames, &layout.rot));
    }

    /// The figures (`ReachCounts.summary`).
    pub fn summary(&self) -> ReachSummary {
        let n = self.reached.len();
        let share = |v: &[bool]| mean(v.iter().map(|&b| f64::from(u8::from(b))));
        let mut be = self.bone_err_m.clone();
        if be.is_empty() {
            be.push(0.0);
        }
        be.sort_by(f64::total_cmp);
        ReachSummary {
            targets: n,
            near_start: self.near_start,
            reach: share(&self.reached),
            plausible_reach: share(&self.plausible),
            frames_median: median(&self.frames),
            final_m: mean(self.final_m.iter().copied()),
            bone_err_p50_cm: 100.0 * percentile(&be, 50.0),
            bone_err_p99_cm: 100.0 * percentile(&be, 99.0),
            roughness: mean(self.roughness.iter().copied()),
        }
    }

    /// The number of targets plausibly reached.
    pub fn plausibly_reached(&self) -> usize {
        self.plausible.iter().filter(|&&p| p).count()
    }
}

/// The figures of [`ReachCounts`], named as `metrics.py` names them.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ReachSummary {
    /// Counted targets (the hand started farther than the radius).
    pub targets: usize,
    /// Targets the hand started within reach of.
    pub near_start: usize,
    /// Share of the counted targets reached (0 with none).
    pub reach: f64,
    /// Share plausibly reached (0 with none).
    pub plausible_reach: f64,
    /// Median frames to a plausible reach (`None`: none reached).
    pub frames_median: Option<f64>,
    /// Mean distance on the targets' last frames, metres (0 with none).
    pub final_m: f64,
    /// Median bone-length error, cm.
    pub bone_err_p50_cm: f64,
    /// 99th percentile of the bone-length error, cm.
    pub bone_err_p99_cm: f64,
    /// Mean roughness over the rollouts, radians per frame.
    pub roughness: f64,
}

/// How a rollout did on one `unreachable` target
/// (`tools/omg/evaluate.py: unreachable_report`): approached, not chased
/// into a broken pose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Unreachable {
    /// The hand.
    pub hand: usize,
    /// Its frames.
    pub start: usize,
    /// One past its last frame.
    pub end: usize,
    /// Hand-target distance on its first frame, metres.
    pub start_m: f64,
    /// The closest the hand got on its frames, metres.
    pub closest_m: f64,
    /// On its last frame, metres.
    pub last_m: f64,
    /// The largest bone-length error on its frames, cm.
    pub bone_err_max_cm: f64,
}

/// [`Unreachable`] of target `t` in a rollout.
pub fn unreachable(
    frames: &[Vec<f64>],
    targets: &[Vec<[f64; 3]>],
    t: HandTarget,
    layout: &FrameLayout,
    bones: &Bones,
) -> Unreachable {
    let d = hand_distances(frames, targets, layout, t.hand);
    let err = frames[t.start..t.end]
        .iter()
        .flat_map(|f| bones.errors(&layout.positions(f)))
        .fold(0.0, f64::max);
    Unreachable {
        hand: t.hand,
        start: t.start,
        end: t.end,
        start_m: d[t.start],
        closest_m: d[t.start..t.end]
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min),
        last_m: d[t.end - 1],
        bone_err_max_cm: 100.0 * err,
    }
}

/// `sqrt(mean_t dr_t^2)` of one rollout (`metrics.roughness`): `dr_t` the
/// mean over joints and over the forward and up vectors (`rot`, 3 values
/// each) of the angle between frames `t` and `t + 1`, each vector divided
/// by `max(|v|, 1e-8)`. 0 for fewer than two frames.
pub fn roughness(frames: &[Vec<f64>], rot: &Range<usize>) -> f64 {
    let unit = |v: &[f64]| {
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-8);
        [v[0] / n, v[1] / n, v[2] / n]
    };
    if frames.len() < 2 {
        return 0.0;
    }
    let mut sq = 0.0;
    for w in frames.windows(2) {
        let (a, b) = (&w[0][rot.clone()], &w[1][rot.clone()]);
        let vectors = a.len() / 3;
        let mut sum = 0.0;
        for v in 0..vectors {
            let (p, q) = (unit(&a[3 * v..3 * v + 3]), unit(&b[3 * v..3 * v + 3]));
            let c = p[0] * q[0] + p[1] * q[1] + p[2] * q[2];
            sum += c.clamp(-1.0, 1.0).acos();
        }
        let dr = sum / vectors.max(1) as f64;
        sq += dr * dr;
    }
    (sq / (frames.len() - 1) as f64).sqrt()
}

/// The median of `v` (the mean of the two middle values of an even
/// count); `None` when empty.
pub fn median(v: &[usize]) -> Option<f64> {
    let mut v = v.to_vec();
    v.sort_unstable();
    let n = v.len();
    match n {
        0 => None,
        _ if n % 2 == 1 => Some(v[n / 2] as f64),
        _ => Some((v[n / 2 - 1] as f64 + v[n / 2] as f64) / 2.0),
    }
}

/// The `q`-th percentile (0..=100) of `sorted` (ascending, not empty) as
/// `numpy.percentile` computes it by default (linear interpolation, in
/// NumPy's arithmetic: index `(n - 1) * (q / 100)`, and from the upper
/// neighbour when the fraction is at least one half).
pub fn percentile(sorted: &[f64], q: f64) -> f64 {
    let n = sorted.len();
    assert!(n > 0, "the percentile of nothing");
    let vi = (n - 1) as f64 * (q / 100.0);
    if vi >= (n - 1) as f64 {
        return sorted[n - 1];
    }
    if vi <= 0.0 {
        return sorted[0];
    }
    let lo = vi.floor();
    let g = vi - lo;
    let (a, b) = (sorted[lo as usize], sorted[lo as usize + 1]);
    let d = b - a;
    if g >= 0.5 {
        b - d * (1.0 - g)
    } else {
        a + d * g
    }
}

/// The mean of `v`; 0 when empty.
pub fn mean(v: impl IntoIterator<Item = f64>) -> f64 {
    let (s, n) = v
        .into_iter()
        .fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 {
        0.0
    } else {
        s / n as f64
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 3-joint rig: root at the origin, a shoulder 1 m up, a hand 0.5 m
    /// along x from it (the hand is key joint 0 and 1 both, so the two
    /// hands are the same joint).
    fn rig() -> (Bones, FrameLayout) {
        let bones = Bones::new(
            &[None, Some(0), Some(1)],
            &[[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.5, 0.0, 0.0]],
        )
        .unwrap();
        let layout = FrameLayout {
            pos: 0..9,
            rot: 9..27,
            key_joints: vec![2, 2],
        };
        (bones, layout)
    }

    /// A frame with the hand at angle `a` (radians, about z from +x) and
    /// `stretch` metres beyond its bone; every rotation the identity's
    /// forward (z) and up (y), the hand's turned by `a` about z.
    fn frame(a: f64, stretch: f64) -> Vec<f64> {
        let r = 0.5 + stretch;
        let mut f = vec![0.0, 0.0, 0.0, 0.0, 1.0, 0.0];
        f.extend([r * a.cos(), 1.0 + r * a.sin(), 0.0]);
        for j in 0..3 {
            let up = if j == 2 {
                [-a.sin(), a.cos(), 0.0]
            } else {
                [0.0, 1.0, 0.0]
            };
            f.extend([0.0, 0.0, 1.0]);
            f.extend(up);
        }
        f
    }

    fn hand(f: &[f64]) -> [f64; 3] {
        [f[6], f[7], f[8]]
    }

    #[test]
    fn rest_lengths_errors_and_the_rig_json() {
        let (b, _) = rig();
        assert_eq!(b.pairs, vec![(1, 0), (2, 1)]);
        assert_eq!(b.rest_m, vec![1.0, 0.5]);
        let pos = [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.7, 0.0]];
        let e = b.errors(&pos);
        assert_eq!(e[0], 0.0);
        assert!((e[1] - 0.2).abs() < 1e-12);
        let json = br#"{"parents": [-1, 0, 1], "rest_offsets": [[0,0,0],[0,1,0],[0.5,0,0]]}"#;
        assert_eq!(Bones::from_rig_json(json).unwrap(), b);
        assert!(Bones::new(&[None, Some(5)], &[[0.0; 3]; 2]).is_err());
        assert!(Bones::from_rig_json(b"{}").is_err());
    }

    /// The hand starts within reach of the first target (near start, not
    /// counted), then gets a second target 0.5 m away that it reaches on
    /// frame 4 only with a stretched bone (reached, not plausibly) and
    /// plausibly on frame 6: frames to reach 6 - 3 = 3; the last frame's
    /// distance is the final one.
    #[test]
    fn near_start_stretched_bone_frames_and_final_distance() {
        use std::f64::consts::FRAC_PI_2;
        let (bones, layout) = rig();
        let far = [0.0, 1.5, 0.0]; // straight up from the shoulder
        let angles = [0.0, 0.0, 0.0, 0.3, FRAC_PI_2, 1.0, 1.5, 1.5];
        let frames_with = |stretch: &dyn Fn(usize) -> f64| -> Vec<Vec<f64>> {
            (0..8).map(|t| frame(angles[t], stretch(t))).collect()
        };
        // Frame 4: 0.05 m beyond its bone, straight up: 0.05 m from far.
        let frames = frames_with(&|t| if t == 4 { 0.05 } else { 0.0 });
        let first = hand(&frames[0]);
        let targets: Vec<Vec<[f64; 3]>> = (0..8)
            .map(|t| vec![if t < 3 { first } else { far }; 2])
            .collect();
        let ivs = clip_intervals(&targets, [5, 0]);
        let ht = |start, end| HandTarget {
            hand: 0,
            start,
            end,
        };
        assert_eq!(ivs, vec![ht(0, 3), ht(3, 8)]);
        assert_eq!(clip_intervals(&targets, [1, 0]), vec![ht(0, 3)]);
        let d = hand_distances(&frames, &targets, &layout, 0);
        assert!(d[3] > CONTACT_RADIUS_M && d[5] > CONTACT_RADIUS_M);
        assert!(d[4] < CONTACT_RADIUS_M && d[6] < CONTACT_RADIUS_M);
        let mut c = ReachCounts::default();
        c.add_clip(&frames, &targets, &ivs, &layout, &bones);
        assert_eq!(c.near_start, 1);
        assert_eq!(c.reached, vec![true]);
        assert_eq!(c.plausible, vec![true]);
        assert_eq!(c.frames, vec![3], "frame 6 (plausible), not 4 (stretched)");
        let s = c.summary();
        assert_eq!((s.targets, s.near_start), (1, 1));
        assert_eq!((s.reach, s.plausible_reach), (1.0, 1.0));
        assert_eq!(s.frames_median, Some(3.0));
        assert_eq!(s.final_m, d[7]);
        // 16 bone lengths, one 0.05 m too long: p99 interpolates between
        // 0 and 0.05 at index 14.85 of 15.
        assert_eq!(c.bone_err_m.len(), 16);
        assert!((s.bone_err_p99_cm - 100.0 * 0.05 * 0.85).abs() < 1e-9);
        assert_eq!(s.bone_err_p50_cm, 0.0);
        assert!(s.roughness > 0.0);

        // Stretched on every frame within reach: reached, not plausibly.
        let stretched = frames_with(&|t| if t >= 4 { 0.05 } else { 0.0 });
        let d = hand_distances(&stretched, &targets, &layout, 0);
        assert!(d[4] < CONTACT_RADIUS_M && d[6] < CONTACT_RADIUS_M);
        let mut c = ReachCounts::default();
        c.add_clip(&stretched, &targets, &ivs[1..], &layout, &bones);
        assert_eq!(
            (c.reached.clone(), c.plausible.clone()),
            (vec![true], vec![false])
        );
        let s = c.summary();
        assert_eq!(
            (s.reach, s.plausible_reach, s.frames_median),
            (1.0, 0.0, None)
        );
    }

    /// A moving target: the distance on each frame is to that frame's
    /// target position. The hand holds still at its start; the target
    /// starts 0.3 m away and comes to it, so it is reached when it comes
    /// within the radius, not before.
    #[test]
    fn a_moving_target_is_judged_frame_by_frame() {
        let (bones, layout) = rig();
        let frames = vec![frame(0.0, 0.0); 10];
        let h = hand(&frames[0]);
        let targets: Vec<Vec<[f64; 3]>> = (0..10)
            .map(|t| {
                let s = 0.06 * (5 - t.min(5)) as f64;
                vec![[h[0], h[1] + s, h[2]]; 2]
            })
            .collect();
        let ivs = [HandTarget {
            hand: 1,
            start: 0,
            end: 10,
        }];
        let mut c = ReachCounts::default();
        c.add_clip(&frames, &targets, &ivs, &layout, &bones);
        // Distances 0.3, 0.24, 0.18, 0.12, 0.06: frame 4.
        assert_eq!(c.frames, vec![4]);
        assert_eq!(c.final_m, vec![0.0]);
        assert_eq!(c.roughness, vec![0.0], "a still pose");
        // A moving target cut into intervals would be one per frame.
        let tpos: Vec<[f64; 3]> = targets.iter().map(|f| f[1]).collect();
        assert_eq!(hand_intervals(&tpos, 99).len(), 6);
    }

    #[test]
    fn unreachable_targets_report_start_closest_last_and_bones() {
        let (bones, layout) = rig();
        let frames: Vec<Vec<f64>> = [0.0, 0.5, 1.0, 1.2, 1.1]
            .iter()
            .zip([0.0, 0.0, 0.03, 0.0, 0.0])
            .map(|(&a, s)| frame(a, s))
            .collect();
        let goal = [0.0, 3.0, 0.0];
        let targets = vec![vec![goal; 2]; 5];
        let d = hand_distances(&frames, &targets, &layout, 0);
        let u = unreachable(
            &frames,
            &targets,
            HandTarget {
                hand: 0,
                start: 1,
                end: 5,
            },
            &layout,
            &bones,
        );
        assert_eq!(u.start_m, d[1]);
        assert_eq!(u.last_m, d[4]);
        assert_eq!(u.closest_m, d[3]);
        assert!((u.bone_err_max_cm - 3.0).abs() < 1e-9);
    }

    #[test]
    fn script_intervals_keep_the_hands_and_set_the_unreachable_apart() {
        let iv = |key, start, end, unreachable| TargetInterval {
            index: 0,
            key,
            start,
            end,
            moving: false,
            unreachable,
        };
        let (c, f) =
            script_intervals(&[iv(0, 0, 10, false), iv(2, 0, 10, false), iv(1, 5, 10, true)]);
        assert_eq!(
            c,
            vec![HandTarget {
                hand: 0,
                start: 0,
                end: 10
            }]
        );
        assert_eq!(
            f,
            vec![HandTarget {
                hand: 1,
                start: 5,
                end: 10
            }]
        );
    }

    #[test]
    fn median_percentile_and_empty_summaries() {
        assert_eq!(median(&[3, 1, 2]), Some(2.0));
        assert_eq!(median(&[4, 1, 2, 3]), Some(2.5));
        assert_eq!(median(&[]), None);
        let v = [0.0, 1.0, 2.0, 10.0];
        assert_eq!(percentile(&v, 50.0), 1.5);
        assert!((percentile(&v, 99.0) - (10.0 - 8.0 * 0.03)).abs() < 1e-12);
        assert_eq!(percentile(&v, 100.0), 10.0);
        assert_eq!(percentile(&[7.0], 99.0), 7.0);
        let s = ReachCounts::default().summary();
        assert_eq!(
            (
                s.targets,
                s.reach,
                s.final_m,
                s.bone_err_p99_cm,
                s.frames_median
            ),
            (0, 0.0, 0.0, 0.0, None)
        );
    }
}
