"""Writes reach_metrics.json: hand-made reaching trajectories and what
``tools/omg/metrics.py`` (and ``tools/omg/evaluate.py: unreachable_report``) computes
for them, for ``host-sim/tests/reach_metrics.rs`` to compare ``host_sim::reach_metrics``
with. Regenerate from the repository root (NumPy only) after changing the metrics::

    PYTHONPATH=. python3 host-sim/tests/data/reach_metrics_fixture.py

The rig: 7 joints (root, spine, head, a shoulder and a hand per side), both hands key
joints. Three clips of 60 frames, the arms swinging smoothly; frames carry a 2-value
prefix before the positions, so the slices are not at 0. What they hold:

* clip 0: data-clip intervals (``metrics.clip_intervals``, spawned [3, 2]): a target the
  hand starts near, one it reaches first on frames where its bone is stretched by 3 cm
  (implausible) and then plausibly, one it never reaches;
* clip 1: the same kinds, spawned [2, 3], without stretched bones, rotation vectors
  scaled off unit length (the roughness normalises them);
* clip 2: script-like intervals given directly: a moving target (each frame's target is
  where the hand will be a few frames later; it gets there only with a stretched bone),
  a held one, and an ``unreachable`` target reported apart.

Values are rounded to 1e-5 before they are judged, so the file holds exactly what was.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))

from tools.omg import metrics  # noqa: E402
from tools.omg.evaluate import unreachable_report  # noqa: E402

OUT = Path(__file__).resolve().parent / "reach_metrics.json"

PARENTS = [-1, 0, 1, 1, 3, 1, 5]
OFFSETS = [[0.0, 0.9, 0.0], [0.0, 0.5, 0.0], [0.0, 0.25, 0.0], [0.18, 0.0, 0.0], [0.55, 0.0, 0.0],
           [-0.18, 0.0, 0.0], [-0.55, 0.0, 0.0]]
KEY = [4, 6]
J = len(PARENTS)
PREFIX = 2
SL = {"pos": slice(PREFIX, PREFIX + 3 * J), "rot": slice(PREFIX + 3 * J, PREFIX + 9 * J)}
WIDTH = PREFIX + 9 * J
T = 60


def rot(yaw, pitch):
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cp, -sp, 0], [sp, cp, 0], [0, 0, 1]])
    return ry @ rz


def clip(rng, stretch=None, scale_rot=False):
    """(T, WIDTH) frames: the arms swing along smooth random angles."""
    t = np.arange(T)[:, None]
    phase = rng.uniform(0, 2 * np.pi, size=4)
    ang = (np.array([0.3, -0.5, -0.3, 0.5]) + 0.8 * np.sin(2 * np.pi * t / 50 + phase)
           + np.cumsum(rng.normal(0, 0.01, size=(T, 4)), axis=0))
    frames = np.zeros((T, WIDTH))
    frames[:, :PREFIX] = rng.normal(size=(T, PREFIX))
    for t in range(T):
        P = np.zeros((J, 3))
        G = [np.eye(3) for _ in range(J)]
        for j in range(J):
            p = PARENTS[j]
            off = np.array(OFFSETS[j])
            if p < 0:
                P[j] = off
                continue
            if j in (4, 6):  # a hand: its arm's swing
                side = 0 if j == 4 else 2
                G[j] = rot(ang[t, side], ang[t, side + 1])
                o = G[j] @ off
                if stretch is not None and j == 4 and stretch[0] <= t < stretch[1]:
                    o = o * (1 + 0.03 / np.linalg.norm(off))
                P[j] = P[p] + o
            else:
                P[j] = P[p] + off
        P += rng.normal(0, 5e-4, size=P.shape)  # 0.5 mm of noise: plausible bones
        frames[t, SL["pos"]] = P.reshape(-1)
        r = np.concatenate([np.stack([g[:, 2] for g in G]), np.stack([g[:, 1] for g in G])], axis=-1)
        r = r + rng.normal(0, 1e-3, size=r.shape)
        if scale_rot:
            r = r * rng.uniform(0.8, 1.2, size=(J, 1))
        frames[t, SL["rot"]] = r.reshape(-1)
    return frames


def hand(frames, h):
    return frames[:, SL["pos"]].reshape(T, J, 3)[:, KEY[h]]


def held_targets(rng, frames, plan):
    """(T, 2, 3) constant targets per hand: ``plan[h]`` is [(start, kind, frame)]; kind
    "near" (the hand's position at the start, 3 cm off), "at" (where the hand is at
    ``frame``, 3 cm off) or "far" (1.2 m off)."""
    tp = np.zeros((T, 2, 3))
    for h in range(2):
        path = hand(frames, h)
        for i, (start, kind, at) in enumerate(plan[h]):
            end = plan[h][i + 1][0] if i + 1 < len(plan[h]) else T
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            base = path[start] if kind == "near" else path[at]
            tp[start:end, h] = base + d * (1.2 if kind == "far" else 0.03)
    return tp


def main():
    rng = np.random.default_rng(11)
    rest_len = metrics.rest_bone_lengths(OFFSETS, PARENTS)
    clips, cases = [], []

    f0 = clip(rng, stretch=(26, 31))
    tp0 = held_targets(rng, f0, [[(0, "near", 0), (20, "at", 30), (40, "far", 0)],
                                 [(0, "at", 15), (30, "far", 0), (45, "at", 55)]])
    clips.append((f0, tp0, metrics.clip_intervals(tp0, [3, 2]), [], [3, 2]))

    f1 = clip(rng, scale_rot=True)
    tp1 = held_targets(rng, f1, [[(0, "at", 12), (25, "near", 25), (42, "at", 50)],
                                 [(0, "near", 0), (18, "at", 40), (40, "far", 0)]])
    clips.append((f1, tp1, metrics.clip_intervals(tp1, [2, 3]), [], [2, 3]))

    f2 = clip(rng, stretch=(50, 60))
    tp2 = np.zeros((T, 2, 3))
    lead = hand(f2, 0)
    for t in range(T):
        tp2[t, 0] = lead[min(t + 6, T - 1)] + np.array([0.02, -0.01, 0.0])
    tp2[:, 1] = hand(f2, 1)[35] + np.array([0.0, 0.04, 0.0])
    tp2[30:, 1] = hand(f2, 1)[30] + np.array([1.0, 0.8, 0.0])
    ivs2 = [(0, 0, 60), (1, 0, 30)]
    far2 = [(1, 30, 60)]
    clips.append((f2, tp2, ivs2, far2, None))

    # Stored (and judged) to 10 micrometres: a small file, the same numbers on both sides.
    clips = [(np.round(f, 5), np.round(tp, 5), ivs, far, sp) for f, tp, ivs, far, sp in clips]
    counts = metrics.ReachCounts()
    per_clip = []
    for f, tp, ivs, far, spawned in clips:
        metrics.add_clip(counts, f, tp, ivs, SL, KEY, PARENTS, rest_len)
        blocks = np.concatenate([tp[:, 0], tp[:, 1]], axis=1)  # K = 2 positions first
        rep = unreachable_report(f, blocks, far, SL, KEY, PARENTS, rest_len)
        per_clip.append(dict(frames=f.tolist(), target_pos=tp.tolist(), spawned=spawned,
                             intervals=[list(map(int, iv)) for iv in ivs],
                             unreachable=[list(map(int, iv)) for iv in far], unreachable_report=rep))
    out = dict(
        about="host-sim/tests/data/reach_metrics_fixture.py wrote this from tools/omg/metrics.py",
        parents=PARENTS, offsets=OFFSETS, key_joints=KEY,
        pos=[SL["pos"].start, SL["pos"].stop], rot=[SL["rot"].start, SL["rot"].stop],
        clips=per_clip,
        reached=counts.reached, plausible=counts.plausible, frames=counts.frames,
        final=counts.final, near_start=counts.near_start, roughness=counts.rough,
        summary=counts.summary(),
    )
    OUT.write_text(json.dumps(out) + "\n")
    for f, tp, ivs, far, _ in clips:
        pos = f[:, SL["pos"]].reshape(T, -1, 3)
        ok = (np.abs(metrics.bone_lengths(pos, PARENTS) - rest_len) <= metrics.BONE_TOL).all(axis=1)
        for h, s, e in ivs:
            d = np.linalg.norm(pos[:, KEY[h]] - tp[:, h], axis=-1)
            print(h, s, e, "start %.3f" % d[s], "hits", np.nonzero(d[s:e] < 0.1)[0] + s,
                  "implausible", np.nonzero(~ok[s:e])[0] + s)
    print(f"{OUT}: reached {counts.reached}, plausible {counts.plausible}, frames {counts.frames}, "
          f"near start {counts.near_start}")
    print(json.dumps(out["summary"], indent=1))
    for c in per_clip:
        print(c["unreachable_report"])


if __name__ == "__main__":
    main()
