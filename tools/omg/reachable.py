"""Geometric reachability of hand targets: can a hand get to a point at all?

A target is *reachable* by a hand when some configuration within the rig's joint limits
(pelvis and legs fixed, as in the data; the spine and that hand's arm free) puts the hand
joint within ``tol`` of it. The spine may use only ``SPINE_SHARE`` of its range (towards rest) in a certificate. A *pair* of targets, one per hand, is reachable when one
configuration puts both hands within ``tol`` of theirs: the hands share the spine, and
about 30 % of the spec's first target pairs that each hand can reach alone, bending the
spine its own way, cannot be reached together (:func:`pair_reach`). The check is constructive: :func:`closest_reach` minimises the
hand-target distance by box-constrained damped Gauss-Newton from several fixed starting
configurations (batched over targets), and returns the best configuration it found, a
**witness**. A target is certified reachable when the witness is within ``tol``; a miss is
"not shown reachable" (the search can miss a configuration, never invent one), so spawning
only certified targets is safe.

``pull_in`` moves a target that is not reachable towards the hand's shoulder along the
straight line until it is, so the spec's cylinder points keep their direction.
"""

from __future__ import annotations

import numpy as np

from .rigs import Rig, ancestor_mask, forward_kinematics

TOL = 0.02  # m: certified reachable when the witness hand is this close
ITERATIONS = 80
STARTS = 6  # the rest pose + 5 fixed random configurations
DAMPING = 1e-3
# The spine's share of its range a certificate may use (limits scaled towards rest). The
# data's IK weights the spine low and moves it only as much as the arms need; a pair that
# only a fully twisted and bent spine can serve (left hand behind the right shoulder,
# say) it finds only now and then, so such targets are not spawned.
SPINE_SHARE = 0.5


def hand_dofs(rig: Rig, hand: int) -> np.ndarray:
    """(D,) bool: the DOFs that move hand ``hand`` (0 left, 1 right): spine and its arm."""
    return ancestor_mask(rig, [rig.key_joints[hand]])[0]


def search_limits(rig: Rig, spine_share: float = SPINE_SHARE):
    """(lower, upper) of the DOFs in a certificate: the rig's, the spine's scaled by
    ``spine_share`` towards rest (0)."""
    spine = np.array([rig.joint_names[j].startswith("Spine") for j in rig.dof_joint])
    share = np.where(spine, spine_share, 1.0)
    return rig.lower * share, rig.upper * share


def _starts(rig: Rig, n: int, spine_share: float = SPINE_SHARE) -> np.ndarray:
    """(n, D) starting configurations: rest, then seeded draws within the limits (shrunk
    to their middle 60 % so that no start sits at a limit)."""
    rng = np.random.default_rng(20261202)
    lo, hi = search_limits(rig, spine_share)
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    draws = mid + 0.6 * half * rng.uniform(-1, 1, size=(n - 1, rig.n_dofs))
    return np.concatenate([np.zeros((1, rig.n_dofs)), draws])


def _chain(rig: Rig, joint: int) -> list[int]:
    """Joints from the root to ``joint``, in order."""
    out = []
    j = int(joint)
    while j >= 0:
        out.append(j)
        j = int(rig.parents[j])
    return out[::-1]


def chain_kinematics(rig: Rig, chain: list[int], q: np.ndarray):
    """Position (M, 3) of the chain's last joint and, per DOF of the chain's joints (in
    rig DOF order), its pivot (M, d, 3) and world axis (M, d, 3), for DOF values q (M, D).
    The same rotations as :func:`tools.omg.rigs.forward_kinematics` on the chain only."""
    from .rigs import axis_rotation

    M = q.shape[0]
    G = np.broadcast_to(np.eye(3), (M, 3, 3))
    P = np.broadcast_to(rig.offsets[chain[0]], (M, 3))
    pivots, axes, order = [], [], []
    for n, j in enumerate(chain):
        if n > 0:
            P = P + G @ rig.offsets[j]
        dofs = [d for d in range(rig.n_dofs) if rig.dof_joint[d] == j]
        by_axis = {int(rig.dof_axis[d]): d for d in dofs}
        for a in range(3):
            if a not in by_axis:
                continue
            d = by_axis[a]
            axes.append(G[:, :, a])
            pivots.append(P)
            order.append(d)
            G = G @ axis_rotation(q[:, d], a)
    if not order:
        return P, np.zeros((M, 0, 3)), np.zeros((M, 0, 3)), np.zeros(0, dtype=int)
    return P, np.stack(pivots, 1), np.stack(axes, 1), np.array(order)


def closest_reach(rig: Rig, hand: int, targets: np.ndarray, iterations: int = ITERATIONS,
                  starts: int = STARTS, spine_share: float = SPINE_SHARE):
    """For targets (N, 3): the closest distance found (N,) and its witness configuration
    (N, D) (only the hand's DOFs move; the others stay 0). ``spine_share`` 1: the whole
    spine range (plain geometric reachability)."""
    targets = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    N, D = targets.shape[0], rig.n_dofs
    mask = hand_dofs(rig, hand)
    chain = _chain(rig, rig.key_joints[hand])
    q0 = _starts(rig, starts, spine_share) * mask
    q = np.repeat(q0[None], N, axis=0).reshape(-1, D)  # (N * S, D)
    t = np.repeat(targets, starts, axis=0)
    best_d = np.full(N, np.inf)
    best_q = np.zeros((N, D))
    lo, hi = search_limits(rig, spine_share)
    for it in range(iterations + 1):
        P, piv, ax, idx = chain_kinematics(rig, chain, q)
        free = mask[idx]
        piv, ax, idx = piv[:, free], ax[:, free], idx[free]
        e = t - P
        d = np.linalg.norm(e, axis=-1).reshape(N, starts)
        k = d.argmin(axis=1)
        dk = d[np.arange(N), k]
        better = dk < best_d
        best_d[better] = dk[better]
        best_q[better] = q.reshape(N, starts, D)[np.arange(N), k][better]
        if it == iterations:
            break
        J = np.swapaxes(np.cross(ax, P[:, None, :] - piv), 1, 2)  # (M, 3, d)
        A = J @ np.swapaxes(J, 1, 2) + DAMPING * np.eye(3)
        dq = (np.swapaxes(J, 1, 2) @ np.linalg.solve(A, e[..., None]))[..., 0]
        q[:, idx] = np.clip(q[:, idx] + dq, lo[idx], hi[idx])
    return best_d, best_q


def is_reachable(rig: Rig, hand: int, targets: np.ndarray, tol: float = TOL,
                 spine_share: float = SPINE_SHARE) -> np.ndarray:
    """(N,) bool: certified reachable by hand ``hand`` within ``tol``."""
    d, _ = closest_reach(rig, hand, targets, spine_share=spine_share)
    return d <= tol


def shoulder(rig: Rig, hand: int) -> np.ndarray:
    """Rest position of the hand's upper-arm joint (the shoulder)."""
    from .rigs import rest_positions

    name = ("Left", "Right")[hand] + "UpperArm"
    return rest_positions(rig)[rig.index(name)]


def pull_in(rig: Rig, hand: int, targets: np.ndarray, tol: float = TOL, margin: float = 0.05):
    """Targets (N, 3), each one that is not certified reachable replaced by the closest
    point the hand was shown to reach (its witness's hand position), moved ``margin``
    further towards the shoulder when that point is certified too (so that it is not on the
    edge of the workspace). Returns (targets, moved mask)."""
    targets = np.asarray(targets, dtype=np.float64).reshape(-1, 3).copy()
    d, q = closest_reach(rig, hand, targets)
    moved = d > tol
    if not moved.any():
        return targets, moved
    P, _ = forward_kinematics(rig, q[moved])
    edge = P[:, rig.key_joints[hand]]
    s = shoulder(rig, hand)
    towards = s - edge
    inner = edge + margin * towards / np.maximum(np.linalg.norm(towards, axis=-1, keepdims=True), 1e-9)
    ok = is_reachable(rig, hand, inner, tol)
    targets[moved] = np.where(ok[:, None], inner, edge)
    return targets, moved


def _pair_search(rig: Rig, left, right, q0, iterations, tol, spine_share):
    """Damped Gauss-Newton for both hands from each start of ``q0`` (S, D); returns the
    best max-distance (N,) and configuration (N, D). A start stops once it is within
    ``tol`` (it cannot get better than certified)."""
    N, D, S = left.shape[0], rig.n_dofs, q0.shape[0]
    chains = [_chain(rig, rig.key_joints[h]) for h in range(2)]
    q = np.repeat(q0[None], N, axis=0).reshape(-1, D)
    owner = np.repeat(np.arange(N), S)
    t = [np.repeat(left, S, axis=0), np.repeat(right, S, axis=0)]
    best_d = np.full(N, np.inf)
    best_q = np.zeros((N, D))
    live = np.arange(N * S)
    lo, hi = search_limits(rig, spine_share)
    for it in range(iterations + 1):
        qa = q[live]
        rows, errs, dist = [], [], []
        for h in range(2):
            P, piv, ax, idx = chain_kinematics(rig, chains[h], qa)
            e = t[h][live] - P
            Jh = np.zeros((len(live), 3, D))
            Jh[:, :, idx] = np.swapaxes(np.cross(ax, P[:, None, :] - piv), 1, 2)
            rows.append(Jh)
            errs.append(e)
            dist.append(np.linalg.norm(e, axis=-1))
        d = np.maximum(dist[0], dist[1])
        # The best per target among its live starts (np.minimum.at keeps it order-free).
        cand = np.full(N, np.inf)
        np.minimum.at(cand, owner[live], d)
        better = cand < best_d
        if better.any():
            for i in np.nonzero(better)[0]:
                rows_i = np.nonzero(owner[live] == i)[0]
                j = rows_i[np.argmin(d[rows_i])]
                best_d[i] = d[j]
                best_q[i] = qa[j]
        if it == iterations:
            break
        J = np.concatenate(rows, axis=1)  # (M, 6, D)
        e = np.concatenate(errs, axis=1)
        A = J @ np.swapaxes(J, 1, 2) + DAMPING * np.eye(6)
        dq = (np.swapaxes(J, 1, 2) @ np.linalg.solve(A, e[..., None]))[..., 0]
        q[live] = np.clip(qa + dq, lo, hi)
        keep = best_d[owner[live]] > tol
        live = live[keep]
        if len(live) == 0:
            break
    return best_d, best_q


def pair_reach(rig: Rig, left: np.ndarray, right: np.ndarray, iterations: int = ITERATIONS,
               starts: int = STARTS, tol: float = TOL, spine_share: float = SPINE_SHARE):
    """For target pairs left (N, 3), right (N, 3): the larger of the two hand-target
    distances at the best configuration found (N,) and that configuration (N, D). Pairs
    are first searched from the rest pose alone, and those not within ``tol`` from all
    ``starts`` starts (a search stops early once within ``tol``)."""
    left = np.asarray(left, dtype=np.float64).reshape(-1, 3)
    right = np.asarray(right, dtype=np.float64).reshape(-1, 3)
    q0 = _starts(rig, starts, spine_share)
    d, q = _pair_search(rig, left, right, q0[:1], iterations, tol, spine_share)
    again = np.nonzero(d > tol)[0]
    if len(again) and starts > 1:
        d2, q2 = _pair_search(rig, left[again], right[again], q0[1:], iterations, tol, spine_share)
        b = d2 < d[again]
        d[again[b]] = d2[b]
        q[again[b]] = q2[b]
    return d, q


def is_pair_reachable(rig: Rig, left, right, tol: float = TOL,
                      spine_share: float = SPINE_SHARE) -> np.ndarray:
    """(N,) bool: both targets of each pair certified reachable together."""
    return pair_reach(rig, left, right, tol=tol, spine_share=spine_share)[0] <= tol


def anchor(rig: Rig, hand: int) -> np.ndarray:
    """A point every hand reaches comfortably: 0.25 m below and 0.25 m in front of its
    shoulder (elbow bent, the arm in front of the body)."""
    return shoulder(rig, hand) + np.array([0.0, -0.25, 0.25])


def pull_in_pairs(rig: Rig, left, right, tol: float = TOL, steps: int = 8):
    """Target pairs moved towards their hands' :func:`anchor`, both by the same fraction
    of their distance to it, just far enough that the pair is certified reachable
    (bisection over the fraction, ``steps`` halvings, up to the anchors themselves, which
    are checked). Returns (left, right, moved mask); a pair not certified even at the
    anchors keeps its targets and a ``moved`` of False, and is reported by the caller."""
    left = np.asarray(left, dtype=np.float64).reshape(-1, 3).copy()
    right = np.asarray(right, dtype=np.float64).reshape(-1, 3).copy()
    ok = is_pair_reachable(rig, left, right, tol)
    moved = ~ok
    if not moved.any():
        return left, right, moved
    sl, sr = anchor(rig, 0), anchor(rig, 1)
    L, Rt = left[moved], right[moved]
    at = lambda f: (L + f[:, None] * (sl - L), Rt + f[:, None] * (sr - Rt))  # noqa: E731
    lo = np.ones(len(L))  # a fraction known reachable (checked below)
    hi = np.zeros(len(L))  # a fraction known not reachable
    good = is_pair_reachable(rig, *at(lo), tol)
    for _ in range(steps):
        mid = (lo + hi) / 2
        r = is_pair_reachable(rig, *at(mid), tol)
        lo = np.where(r, mid, lo)
        hi = np.where(r, hi, mid)
    nl, nr = at(lo)
    idx = np.nonzero(moved)[0]
    left[idx[good]] = nl[good]
    right[idx[good]] = nr[good]
    moved[idx[~good]] = False
    return left, right, moved
