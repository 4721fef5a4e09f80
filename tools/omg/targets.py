"""Target spawning (spec §3.2): 40 points on a cylinder around the character.

The cylinder is centred on the vertical axis through the pivot. Its height is the
thesis's 0.7 m; following the author's level formula ``y = -H/2 + i*H/5`` for
i = 1..5 relative to the pelvis, the five levels sit at -0.21, -0.07, 0.07, 0.21
and 0.35 m from the pelvis height. Eight points per level, 2*pi/8 apart, angle 0
straight in front (+z), increasing towards the character's left (+x).
Point id = level * 8 + m.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial.transform import Rotation

CYLINDER_HEIGHT = 0.7
RADII = (0.35, 0.7)
LEVELS = 5
POINTS_PER_LEVEL = 8
N_POINTS = LEVELS * POINTS_PER_LEVEL
MODES = ("adjacent", "opposite")
REPETITIONS = (1, 2, 3)
MAX_REPS = max(REPETITIONS)


def spawn_points(radius: float, pelvis_height: float) -> np.ndarray:
    """(40, 3) spawn positions in root space."""
    pts = np.zeros((N_POINTS, 3))
    for level in range(LEVELS):
        y = pelvis_height - CYLINDER_HEIGHT / 2 + (level + 1) * CYLINDER_HEIGHT / LEVELS
        for m in range(POINTS_PER_LEVEL):
            phi = 2 * np.pi * m / POINTS_PER_LEVEL
            pts[level * POINTS_PER_LEVEL + m] = (radius * np.sin(phi), y, radius * np.cos(phi))
    return pts


def partner(point: int, mode: str) -> int:
    """The other hand's spawn point: same level, adjacent (one step clockwise) or opposite."""
    level, m = divmod(point, POINTS_PER_LEVEL)
    step = -1 if mode == "adjacent" else POINTS_PER_LEVEL // 2
    return level * POINTS_PER_LEVEL + (m + step) % POINTS_PER_LEVEL


def plan_clips(seed: int, full: bool = False) -> list[dict]:
    """The clip plan, shared by every rig.

    ``full``: the thesis's factorial design, 2 radii x 2 modes x 2 rotation settings x
    3 repetition counts x 40 first spawn points = 960 clips. Default: spec §3.7's
    "a few hundred", 2 rotation settings x 3 repetition counts x 40 points = 240 clips,
    with radius and mode balanced over each group of 40 (10 clips of each of the
    four radius/mode pairs, assigned by a seeded permutation).

    Each clip lists, per repetition, the pair of spawn points (left-hand point,
    right-hand point): the first pair starts at the clip's point, later first points
    are drawn at random without repeats; the pair's other point is the partner
    (adjacent or opposite) and the pair is ordered so that the point further to the
    character's left (+x) goes to the left hand (ties drawn at random). Target
    rotations are uniform over SO(3) when ``rotate`` and the hand's rest rotation
    (identity) otherwise.
    """
    rng = np.random.default_rng([seed, 7])
    combos = list(itertools.product(RADII, MODES))
    plans = []
    for rotate, reps in itertools.product((False, True), REPETITIONS):
        if full:
            groups = [(r, m) for r, m in combos for _ in range(N_POINTS)]
            points = list(range(N_POINTS)) * len(combos)
        else:
            assignment = rng.permutation(np.repeat(np.arange(len(combos)), N_POINTS // len(combos)))
            groups = [combos[a] for a in assignment]
            points = list(range(N_POINTS))
        for (radius, mode), first in zip(groups, points):
            used = {first}
            firsts = [first]
            while len(firsts) < reps:
                p = int(rng.integers(N_POINTS))
                if p not in used:
                    used.add(p)
                    firsts.append(p)
            pairs = []
            for p in firsts:
                q = partner(p, mode)
                xp = np.sin(2 * np.pi * (p % POINTS_PER_LEVEL) / POINTS_PER_LEVEL)
                xq = np.sin(2 * np.pi * (q % POINTS_PER_LEVEL) / POINTS_PER_LEVEL)
                if abs(xp - xq) < 1e-9:
                    left_first = bool(rng.integers(2))
                else:
                    left_first = xp > xq
                pairs.append((p, q) if left_first else (q, p))
            rots = None
            if rotate:
                # Two hands x reps rotations, as quaternions (x, y, z, w).
                rots = Rotation.random(2 * reps, random_state=rng).as_quat().reshape(reps, 2, 4)
                rots = np.round(rots, 8).tolist()
            plans.append(
                dict(radius=radius, mode=mode, rotate=rotate, reps=reps, pairs=pairs, rotations=rots)
            )
    for i, p in enumerate(plans):
        p["clip"] = i
    return plans


def clip_target_arrays(plans: list[dict], pelvis_height: float, rest_hand_pos: np.ndarray):
    """Hand target sequences for a batch of clips.

    Returns ``pos`` (B, 2, MAX_REPS + 1, 3), ``rot`` (B, 2, MAX_REPS + 1, 3, 3) and
    ``n_reps`` (B,). Slot ``n_reps`` and later hold the rest pose (the targets
    return to their initial positions and orientations after the last one).
    """
    B = len(plans)
    pos = np.broadcast_to(rest_hand_pos[None, :, None, :], (B, 2, MAX_REPS + 1, 3)).copy()
    rot = np.broadcast_to(np.eye(3), (B, 2, MAX_REPS + 1, 3, 3)).copy()
    n_reps = np.zeros(B, dtype=np.int64)
    cache = {r: spawn_points(r, pelvis_height) for r in RADII}
    for b, p in enumerate(plans):
        pts = cache[p["radius"]]
        n_reps[b] = p["reps"]
        for k, pair in enumerate(p["pairs"]):
            for h in range(2):
                pos[b, h, k] = pts[pair[h]]
                if p["rotations"] is not None:
                    rot[b, h, k] = Rotation.from_quat(p["rotations"][k][h]).as_matrix()
    return pos, rot, n_reps
