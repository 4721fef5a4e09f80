"""Batched damped-least-squares IK for both hands, stepped once per frame.

One call of :meth:`HandIK.step` advances every clip of a batch by one frame (60 fps):

1. forward kinematics and the analytic Jacobian of both hands' positions and
   orientations with respect to every upper-body DOF (spine, clavicles, shoulders,
   elbows with forearm twist, wrists);
2. one weighted damped-least-squares step in two priorities: both hands' positions
   first (error clamped to ``max_pos_err``), then both hands' orientations inside
   the exact null space of the positions (error scaled by ``rot_weight`` metres per
   radian, so the damping makes this level cautious), then a pull towards the rest
   pose inside the null space of both; DOFs at a joint limit that a level pushes
   further out are taken out of that level;
3. the step becomes a joint velocity under per-DOF limits: speed at most
   ``v_max`` rad/s, and low enough to stop in the remaining distance with
   deceleration ``a_max`` (the whole vector is scaled, so the direction is kept);
   no DOF may approach its joint limit faster than it can stop there; each DOF's
   change of velocity is at most ``a_max`` rad/s^2 per frame; finally q is clamped
   to the limits.

Pelvis and legs have no DOF, so the feet stay planted (spec §3.7).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .rigs import Rig, ancestor_mask, forward_kinematics

FPS = 60
DT = 1.0 / FPS
POS_ROWS = [0, 1, 2, 6, 7, 8]  # rows of the task Jacobian: left, right hand position
ROT_ROWS = [3, 4, 5, 9, 10, 11]  # left, right hand orientation (times rot_weight)


@dataclass(frozen=True)
class IKParams:
    v_max: float = 5.0  # rad/s, per DOF (Bio-IK "Maximum velocity 5", unit assumed)
    a_max: float = 5.0  # rad/s^2, per DOF (Bio-IK "Maximum acceleration 5", unit assumed)
    damping: float = 0.08  # DLS lambda (metres)
    rot_weight: float = 0.05  # metres per radian of orientation error (priority 2)
    max_pos_err: float = 0.3  # m, clamp of the positional error per step
    max_rot_err: float = 1.0  # rad, clamp of the orientation error per step
    rest_gain: float = 0.05  # pull towards the rest pose, per frame, in the exact null space of the task

    def to_json(self) -> dict:
        return dict(self.__dict__)


def rotation_error(target: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) taking ``current`` to ``target`` (world frame)."""
    rel = target @ np.swapaxes(current, -1, -2)
    shape = rel.shape[:-2]
    return Rotation.from_matrix(rel.reshape(-1, 3, 3)).as_rotvec().reshape(shape + (3,))


def rot6_to_matrix(t6: np.ndarray) -> np.ndarray:
    """(..., 6) forward/up vectors (a frame's target rotations) -> (..., 3, 3) rotations
    with columns side, up, forward."""
    fw, up = t6[..., :3], t6[..., 3:]
    return np.stack([np.cross(up, fw), up, fw], axis=-1)


def _clamp_norm(x: np.ndarray, limit: float) -> np.ndarray:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return x * np.minimum(1.0, limit / np.maximum(n, 1e-12))


class HandIK:
    """IK for the two hands of ``rig`` (the first two key joints)."""

    def __init__(self, rig: Rig, params: IKParams = IKParams()):
        self.rig = rig
        self.p = params
        self.effectors = rig.key_joints[:2]
        self.mask = ancestor_mask(rig, self.effectors)  # (2, D)

    def jacobian(self, P, G, axes):
        """Task Jacobian (B, 12, D): rows [pos L, w*rot L, pos R, w*rot R]."""
        rig = self.rig
        pe = P[:, self.effectors]  # (B, 2, 3)
        piv = P[:, rig.dof_joint]  # (B, D, 3)
        lever = pe[:, :, None, :] - piv[:, None, :, :]  # (B, 2, D, 3)
        ax = np.broadcast_to(axes[:, None], lever.shape)
        m = self.mask[None, :, :, None]
        Jp = np.cross(ax, lever) * m  # (B, 2, D, 3)
        Jr = ax * m * self.p.rot_weight
        Jt = np.concatenate([Jp, Jr], axis=-1)  # (B, 2, D, 6)
        return np.swapaxes(Jt, 2, 3).reshape(P.shape[0], 12, rig.n_dofs)

    def _dls(self, J, e, pull, q):
        """Two-priority weighted DLS step with joint-limit clamping (all batched).

        Priority 1: both hands' positions. Priority 2: both hands' orientations, inside
        the null space of priority 1 (so an orientation the wrist cannot take never
        pulls the hand away from a reachable position). Then ``pull`` (towards the
        rest pose) inside the null space of both. A DOF sitting at a joint limit that a
        level's step pushes further out is taken out of that level's solve (weight 0),
        and the level is solved again, so that a clamped DOF neither absorbs the step
        nor dominates the velocity scaling in :meth:`step`.
        """
        rig = self.rig
        lam2 = self.p.damping**2
        Jp, ep = J[:, POS_ROWS], e[:, POS_ROWS]
        Jr, er = J[:, ROT_ROWS], e[:, ROT_ROWS]
        D = J.shape[2]
        at_hi = q >= rig.upper - 1e-6
        at_lo = q <= rig.lower + 1e-6

        def outward(dq):
            return (at_hi & (dq > 0)) | (at_lo & (dq < 0))

        def pinv_solve(A_rows, rhs, W):
            # W A^T (A W A^T + lam^2 I)^-1 rhs
            AW = A_rows * W[:, None, :]
            M = AW @ np.swapaxes(A_rows, 1, 2) + lam2 * np.eye(A_rows.shape[1])
            return np.swapaxes(AW, 1, 2) @ np.linalg.solve(M, rhs)

        W = np.broadcast_to(rig.dof_weight, q.shape).copy()
        dq1 = pinv_solve(Jp, ep[..., None], W)[..., 0]
        for _ in range(2):
            blocked = outward(dq1)
            if not blocked.any():
                break
            W[blocked] = 0.0
            dq1 = pinv_solve(Jp, ep[..., None], W)[..., 0]
        # An exact (undamped, SVD-truncated) projector, so that priority 2 cannot leak
        # into priority 1 near singular arm poses.
        wh = np.sqrt(W)[:, :, None]  # (B, D, 1)
        N1 = np.eye(D) - wh * (np.linalg.pinv(Jp * np.swapaxes(wh, 1, 2), rcond=1e-3) @ Jp)
        r2 = er - (Jr @ dq1[..., None])[..., 0]
        W2 = W.copy()
        for _ in range(2):
            dq2 = pinv_solve(Jr @ N1, r2[..., None], W2)[..., 0]
            dq = dq1 + (N1 @ dq2[..., None])[..., 0]
            blocked = outward(dq) & ~outward(dq1)
            if not blocked.any():
                break
            W2[blocked] = 0.0
        # Posture pull in the exact (undamped, SVD-truncated) null space of the whole task:
        # it returns the redundant joints (the spine, above all) towards rest without moving
        # either hand; a damped projector leaked part of it into the task and held hands
        # short of their targets.
        whj = np.sqrt(W)[:, :, None]
        proj = whj * (np.linalg.pinv(J * np.swapaxes(whj, 1, 2), rcond=1e-3) @ J)
        dq = dq + (pull * (W > 0)) - (proj @ (pull * (W > 0))[..., None])[..., 0]
        return np.where(outward(dq), 0.0, dq)

    def _stop_speed(self, room):
        """Largest speed from which steps slowing by a_max*DT per frame stop within room."""
        h = 0.5 * self.p.a_max * DT
        return np.sqrt(h * h + 2 * self.p.a_max * np.maximum(room, 0.0)) - h

    def desired_velocity(self, q, t_pos, t_rot):
        """The joint velocity (B, D) the IK asks for at q (rad/s): the DLS step of one frame
        as a velocity, scaled as a whole so that no DOF is faster than ``v_max`` nor than
        ``sqrt(2 a_max |step|)`` (a speed it can stop from within the step). A function of
        the configuration and the targets only; :meth:`limit` turns it into motion."""
        rig, p = self.rig, self.p
        P, G, axes = forward_kinematics(rig, q, with_axes=True)
        e_pos = _clamp_norm(t_pos - P[:, self.effectors], p.max_pos_err)
        e_rot = _clamp_norm(rotation_error(t_rot, G[:, self.effectors]), p.max_rot_err)
        e = np.concatenate([e_pos, e_rot * p.rot_weight], axis=-1).reshape(-1, 12)
        J = self.jacobian(P, G, axes)
        pull = p.rest_gain * (-q)  # rest pose is q = 0
        dq = self._dls(J, e, pull, q)
        peak = np.abs(dq).max(axis=1, keepdims=True)
        v_cap = np.minimum(p.v_max, np.sqrt(2 * p.a_max * peak))
        v_des = dq / DT
        v_des *= np.minimum(1.0, v_cap / np.maximum(np.abs(v_des).max(axis=1, keepdims=True), 1e-12))
        return v_des

    def limit(self, q, v, v_des):
        """One frame of motion towards ``v_des`` (B, D) from (q, v): no DOF approaches its
        joint limit faster than it can stop there at ``a_max``; each DOF's velocity changes
        by at most ``a_max`` per second; q is clamped to the limits. Returns (q, v)."""
        rig, p = self.rig, self.p
        v_des = np.minimum(v_des, self._stop_speed(rig.upper - q))
        v_des = np.maximum(v_des, -self._stop_speed(q - rig.lower))
        dv = v_des - v
        v_new = v + np.clip(dv, -p.a_max * DT, p.a_max * DT)
        q_new = np.clip(q + v_new * DT, rig.lower, rig.upper)
        v_new = (q_new - q) / DT
        return q_new, v_new

    def step(self, q, v, t_pos, t_rot):
        """One frame. q, v: (B, D); t_pos (B, 2, 3); t_rot (B, 2, 3, 3). Returns q, v."""
        return self.limit(q, v, self.desired_velocity(q, t_pos, t_rot))
