"""Reaching metrics, the same definitions as ``host-sim omg-reach`` (host-sim/src/omg_reach.rs).

Per hand target (an interval ``[start, end)`` of frames during which the hand is asked for
one target, which may move; in a data clip the first ``spawned`` constant-target intervals
of each hand, in a target script the entries of ``tools.omg.scripts.intervals``):

* **near start**: the hand is within ``CONTACT_RADIUS`` of the target on the interval's
  first frame. Such a target says nothing about reaching: it is counted apart and left
  out of every rate below;
* **reached**: the hand gets within ``CONTACT_RADIUS`` on some frame of the interval;
* **plausibly reached**: on some frame of the interval the hand is within
  ``CONTACT_RADIUS`` *and* every bone's length is within ``BONE_TOL`` of the rig's;
* **frames to reach**: from the interval's first frame to the first plausible reach;
* **final distance**: hand-target distance on the interval's last frame.

Over whole rollouts: **bone-length error** |length - rest length| of every bone on every
frame (p50 and p99, cm), and **roughness**: per clip sqrt(mean_t dr_t^2) with dr_t the mean
angle between frames t and t+1 of every joint's forward and up vectors (radians per frame;
eq 3.9 in the author's code's form), averaged over clips.
"""

from __future__ import annotations

import numpy as np

CONTACT_RADIUS = 0.1  # m
BONE_TOL = 0.01  # m


def bone_lengths(pos: np.ndarray, parents) -> np.ndarray:
    """(..., J, 3) positions -> (..., J - 1) lengths of the bones joint -> parent."""
    ch = [j for j, p in enumerate(parents) if p >= 0]
    par = [parents[j] for j in ch]
    return np.linalg.norm(pos[..., ch, :] - pos[..., par, :], axis=-1)


def rest_bone_lengths(offsets, parents) -> np.ndarray:
    off = np.asarray(offsets, dtype=np.float64)
    return np.linalg.norm(off[[j for j, p in enumerate(parents) if p >= 0]], axis=-1)


def hand_intervals(tpos: np.ndarray, count: int):
    """[(start, end)] of the first ``count`` constant-target intervals of one hand (T, 3)."""
    T = tpos.shape[0]
    ch = np.nonzero(np.linalg.norm(np.diff(tpos, axis=0), axis=1) > 1e-6)[0] + 1
    bounds = [0] + ch.tolist() + [T]
    return list(zip(bounds[:-1], bounds[1:]))[:count]


class ReachCounts:
    """Per-target outcomes, accumulated over clips or scripts."""

    def __init__(self):
        self.reached, self.plausible, self.frames, self.final = [], [], [], []
        self.near_start = 0
        self.bone_err = []
        self.rough = []

    def add_target(self, d: np.ndarray, bones_ok: np.ndarray, start: int, end: int):
        """``d`` (T,) hand-target distance, ``bones_ok`` (T,) every bone within tolerance."""
        if d[start] < CONTACT_RADIUS:
            self.near_start += 1
            return
        hit = d[start:end] < CONTACT_RADIUS
        ok = hit & bones_ok[start:end]
        self.reached.append(bool(hit.any()))
        self.plausible.append(bool(ok.any()))
        if ok.any():
            self.frames.append(int(np.argmax(ok)))
        self.final.append(float(d[end - 1]))

    def summary(self) -> dict:
        n = len(self.reached)
        be = np.concatenate(self.bone_err) if self.bone_err else np.zeros(1)
        return dict(
            targets=n,
            near_start=self.near_start,
            reach=float(np.mean(self.reached)) if n else 0.0,
            plausible_reach=float(np.mean(self.plausible)) if n else 0.0,
            frames_median=float(np.median(self.frames)) if self.frames else None,
            final_m=float(np.mean(self.final)) if n else 0.0,
            bone_err_p50_cm=float(100 * np.percentile(be, 50)),
            bone_err_p99_cm=float(100 * np.percentile(be, 99)),
            roughness=float(np.mean(self.rough)) if self.rough else 0.0,
        )


def roughness(rot: np.ndarray) -> float:
    """rot (T, 6J) forward/up vectors of one clip -> sqrt(mean_t dr_t^2)."""
    r = rot.reshape(rot.shape[0], -1, 2, 3)
    r = r / np.maximum(np.linalg.norm(r, axis=-1, keepdims=True), 1e-8)
    cos = (r[1:] * r[:-1]).sum(-1)
    dr = np.arccos(np.clip(cos, -1, 1)).mean(axis=(1, 2))
    return float(np.sqrt((dr**2).mean()))


def add_clip(counts: ReachCounts, frames: np.ndarray, target_pos: np.ndarray, intervals, sl: dict, key,
             parents, rest_len: np.ndarray):
    """One rollout: ``frames`` (T, n) raw, ``target_pos`` (T, K, 3) the hands' targets,
    ``intervals`` [(hand, start, end)]."""
    T = frames.shape[0]
    pos = frames[:, sl["pos"]].reshape(T, -1, 3)
    err = np.abs(bone_lengths(pos, parents) - rest_len)
    counts.bone_err.append(err.ravel())
    ok = (err <= BONE_TOL).all(axis=1)
    for h, s, e in intervals:
        d = np.linalg.norm(pos[:, key[h]] - target_pos[:, h], axis=-1)
        counts.add_target(d, ok, s, e)
    counts.rough.append(roughness(frames[:, sl["rot"]]))


def clip_intervals(target_pos: np.ndarray, spawned) -> list:
    """[(hand, start, end)] of a data clip: each hand's first ``spawned[h]`` intervals."""
    return [(h, s, e) for h in range(2) for s, e in hand_intervals(target_pos[:, h], int(spawned[h]))]
