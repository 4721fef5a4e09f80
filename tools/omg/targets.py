"""Target spawning: the spec's 40-point cylinder (§3.2) and targets drawn continuously
over the reachable workspace.

**Cylinder clips** (``kind`` "cylinder"): the cylinder is centred on the vertical axis
through the pivot. Its height is the thesis's 0.7 m; following the author's level formula
``y = -H/2 + i*H/5`` for i = 1..5 relative to the pelvis, the five levels sit at -0.21,
-0.07, 0.07, 0.21 and 0.35 m from the pelvis height. Eight points per level, 2*pi/8
apart, angle 0 straight in front (+z), increasing towards the character's left (+x).
Point id = level * 8 + m. A point that the hand cannot reach (about a quarter of the
0.7 m points: low, behind, or on the far side of a fixed pelvis) or a pair that the two
hands cannot reach together (they share the spine) is moved towards the shoulders, both
targets by the same fraction, just far enough to be certified reachable together
(:func:`tools.omg.reachable.pull_in_pairs`).

**Continuous clips** (``kind`` "continuous"): each pair of hand targets is drawn
uniformly over the volume of a cylindrical shell around the character (radius
``CONTINUOUS_RADIUS``, heights ``CONTINUOUS_HEIGHT`` from the pelvis, any angle, each
hand independently), keeping the first draw that is outside the body
(:func:`inside_body`) and certified reachable by both hands together
(:func:`tools.omg.reachable.is_pair_reachable`): uniform over the reachable part of the
shell. Draws are seeded per clip, and made per rig (the reachable set depends on it).
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
KINDS = ("cylinder", "continuous")
CONTINUOUS_RADIUS = (0.15, 0.8)  # m from the vertical axis through the pivot
CONTINUOUS_HEIGHT = (-0.4, 0.7)  # m from the pelvis height
CONTINUOUS_CANDIDATES = 4  # draws per target tried at once (the first certified one is kept)


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


def plan_clips(seed: int, full: bool = False, continuous: int | None = None) -> list[dict]:
    """The clip plan, shared by every rig: the cylinder clips, then ``continuous``
    continuous clips (default: as many as cylinder clips).

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

    A continuous clip has no spawn points (``pairs`` is None): its ``draw_seed`` seeds the
    draws of its targets (:func:`clip_target_arrays`); repetition counts and rotation
    settings cycle through the same 2 x 3 groups as the cylinder clips.
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
                dict(kind="cylinder", radius=radius, mode=mode, rotate=rotate, reps=reps, pairs=pairs,
                     rotations=rots)
            )
    n_cont = len(plans) if continuous is None else continuous
    groups = list(itertools.product((False, True), REPETITIONS))
    for i in range(n_cont):
        rotate, reps = groups[i % len(groups)]
        rots = None
        if rotate:
            rots = Rotation.random(2 * reps, random_state=rng).as_quat().reshape(reps, 2, 4)
            rots = np.round(rots, 8).tolist()
        plans.append(
            dict(kind="continuous", radius=None, mode=None, rotate=rotate, reps=reps, pairs=None,
                 rotations=rots, draw_seed=[seed, 11, i])
        )
    for i, p in enumerate(plans):
        p["clip"] = i
    return plans


def continuous_draws(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) points uniform over the volume of the continuous shell (pelvis at y = 0)."""
    r0, r1 = CONTINUOUS_RADIUS
    r = np.sqrt(rng.uniform(r0 * r0, r1 * r1, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    y = rng.uniform(*CONTINUOUS_HEIGHT, n)
    return np.stack([r * np.sin(phi), y, r * np.cos(phi)], axis=1)


def inside_body(points: np.ndarray, rest: np.ndarray, rig) -> np.ndarray:
    """(N,) bool: points (N, 3) inside a box around the torso (pelvis to shoulders, 0.2 m
    to either side of the spine, 0.12 m in front, 0.15 m behind) or around the head; a
    hand sent there would have to pass through the body."""
    shoulder_y = rest[rig.index("LeftUpperArm"), 1]
    pelvis_y = rest[0, 1]
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    torso = (np.abs(x) < 0.2) & (z > -0.15) & (z < 0.12) & (y > pelvis_y - 0.1) & (y < shoulder_y + 0.05)
    head = (np.abs(x) < 0.14) & (np.abs(z) < 0.16) & (y >= shoulder_y + 0.05)
    return torso | head


def clip_target_arrays(rig, plans: list[dict]):
    """Hand target sequences of a batch of clips on ``rig``, every one reachable.

    Returns ``pos`` (B, 2, MAX_REPS + 1, 3), ``rot`` (B, 2, MAX_REPS + 1, 3, 3),
    ``n_reps`` (B,) and ``moved`` (B, 2, MAX_REPS) (cylinder pairs that were pulled in to
    be reachable). Every pair (the two hands' k-th targets, which the simulation spawns
    together) is certified reachable together (:func:`tools.omg.reachable.pair_reach`). Slot ``n_reps`` and later hold the rest pose (the targets return to
    their initial positions and orientations after the last one).
    """
    from .reachable import TOL, is_pair_reachable, pair_reach, pull_in_pairs
    from .rigs import rest_positions

    rest = rest_positions(rig)
    pelvis_height = rest[0, 1]
    rest_hand_pos = rest[rig.key_joints[:2]]
    B = len(plans)
    pos = np.broadcast_to(rest_hand_pos[None, :, None, :], (B, 2, MAX_REPS + 1, 3)).copy()
    rot = np.broadcast_to(np.eye(3), (B, 2, MAX_REPS + 1, 3, 3)).copy()
    n_reps = np.zeros(B, dtype=np.int64)
    moved = np.zeros((B, 2, MAX_REPS), dtype=bool)
    cache = {r: spawn_points(r, pelvis_height) for r in RADII}
    cyl = [(b, k) for b, p in enumerate(plans) if p["kind"] == "cylinder" for k in range(p["reps"])]
    cont = [(b, k) for b, p in enumerate(plans) if p["kind"] == "continuous" for k in range(p["reps"])]
    for b, p in enumerate(plans):
        n_reps[b] = p["reps"]
        if p["rotations"] is not None:
            for k in range(p["reps"]):
                for h in range(2):
                    rot[b, h, k] = Rotation.from_quat(p["rotations"][k][h]).as_matrix()
    if cyl:
        pts = [np.array([cache[plans[b]["radius"]][plans[b]["pairs"][k][h]] for b, k in cyl]) for h in range(2)]
        left, right, mv = pull_in_pairs(rig, pts[0], pts[1])
        unreached = ~is_pair_reachable(rig, left, right)
        if unreached.any():
            raise RuntimeError(f"{rig.name}: {int(unreached.sum())} cylinder pairs could not be made reachable")
        for (b, k), pl, pr, m in zip(cyl, left, right, mv):
            pos[b, :, k] = (pl, pr)
            moved[b, :, k] = m
    if cont:
        rngs = {b: np.random.default_rng(plans[b]["draw_seed"]) for b in {b for b, _ in cont}}
        todo = list(cont)
        while todo:
            # (targets, candidates, hand, 3), drawn in a fixed order per clip
            cand = np.stack([
                np.stack([continuous_draws(rngs[b], CONTINUOUS_CANDIDATES) for _ in range(2)], axis=1)
                for b, _ in todo
            ])
            cand[..., 1] += pelvis_height
            flat = cand.reshape(-1, 2, 3)
            ok = ~inside_body(flat[:, 0], rest, rig) & ~inside_body(flat[:, 1], rest, rig)
            sel = np.nonzero(ok)[0]
            ok[sel] = pair_reach(rig, flat[sel, 0], flat[sel, 1], starts=1)[0] <= TOL
            ok = ok.reshape(len(todo), -1)
            left = []
            for (b, k), c, o in zip(todo, cand, ok):
                if o.any():
                    pos[b, :, k] = c[int(np.argmax(o))]
                else:
                    left.append((b, k))
            todo = left
    return pos, rot, n_reps, moved
