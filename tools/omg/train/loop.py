"""The reaching controller's loop for joint-velocity models, in PyTorch
(docs/omg-joint-velocity.md; the Rust loop is ``phasegate_controller::reach``, the NumPy
one ``tools.omg.omg_np``).

State per clip: the frame ``x`` (raw), joint angles ``q`` and velocities ``v``. One step:
the network's output ``[phase', u, cost']`` (normalised) is denormalised, ``u / dt`` is
limited like the IK's last stage (joint limits, acceleration), ``q`` integrated, and the
pose block rebuilt by forward kinematics; targets are written and, grounded, the costs
recomputed.
"""

from __future__ import annotations

import torch

from .fk import RigFK, grounded_costs, pose_block


class DofLoop:
    """The loop for one model: its slices, normalisation and skeleton."""

    def __init__(self, sl: dict, mean, std, dof_mean, dof_std, key, fk: RigFK, a_max: float, fps: float,
                 mode: str = "grounded"):
        self.sl = {k: slice(*v) for k, v in sl.items()}
        self.mean = torch.as_tensor(mean)
        self.std = torch.as_tensor(std)
        self.dof_mean = torch.as_tensor(dof_mean)
        self.dof_std = torch.as_tensor(dof_std)
        self.key = list(key)
        self.fk = fk
        self.a_max = float(a_max)
        self.dt = 1.0 / float(fps)
        self.fps = float(fps)
        self.mode = mode
        n_phase = self.sl["phase"].stop - self.sl["phase"].start
        n_cost = self.sl["cost"].stop - self.sl["cost"].start
        D = fk.D
        self.out = dict(phase=slice(0, n_phase), u=slice(n_phase, n_phase + D),
                        cost=slice(n_phase + D, n_phase + D + n_cost))

    def to(self, dtype):
        for k in ("mean", "std", "dof_mean", "dof_std"):
            setattr(self, k, getattr(self, k).to(dtype))
        return self

    def normalise(self, x):
        return (x - self.mean) / self.std

    def u_raw(self, out_n):
        """The desired per-frame joint velocity u (radians per frame) of a network output."""
        return out_n[:, self.out["u"]] * self.dof_std + self.dof_mean

    def _stop(self, room):
        h = 0.5 * self.a_max * self.dt
        return torch.sqrt(h * h + 2 * self.a_max * room.clamp_min(0.0)) - h

    def limit(self, q, v, w):
        """One frame of motion towards velocity ``w`` (rad/s) from (q, v), as ``HandIK.limit``."""
        lo, hi = self.fk.lower.to(q.dtype), self.fk.upper.to(q.dtype)
        w = torch.minimum(w, self._stop(hi - q))
        w = torch.maximum(w, -self._stop(q - lo))
        step = self.a_max * self.dt
        v1 = v + (w - v).clamp(-step, step)
        q1 = torch.maximum(torch.minimum(q + v1 * self.dt, hi), lo)
        return q1, (q1 - q) / self.dt

    def frame(self, q, p_before, phase, cost, target):
        """The raw frame of state ``q`` (pose by FK; velocities against ``p_before``, the
        positions of the frame before), with its phase, target and cost blocks (grounded:
        the costs are recomputed and ``cost`` is ignored). Returns (frame, positions)."""
        P, G = self.fk(q)
        x = torch.empty(q.shape[0], self.mean.shape[0], dtype=q.dtype)
        x[:, self.sl["phase"]] = phase
        x[:, self.sl["pose"]] = pose_block(P, G, p_before)
        x[:, self.sl["target"]] = target
        K = len(self.key)
        if self.mode == "grounded":
            x[:, self.sl["cost"]] = grounded_costs(P, G, self.key, target[:, : 3 * K], target[:, 3 * K :])
        else:
            x[:, self.sl["cost"]] = cost
        return x, P

    def step(self, out_n, x, q, v, target):
        """The next (x, q, v, positions) from the network output ``out_n`` for frame ``x``
        (state q, v) and the targets of the next frame."""
        raw_phase = out_n[:, self.out["phase"]] * self.std[self.sl["phase"]] + self.mean[self.sl["phase"]]
        raw_cost = out_n[:, self.out["cost"]] * self.std[self.sl["cost"]] + self.mean[self.sl["cost"]]
        q1, v1 = self.limit(q, v, self.u_raw(out_n) / self.dt)
        p_before = x[:, self.sl["pos"]].reshape(q.shape[0], -1, 3)
        x1, P = self.frame(q1, p_before, raw_phase, raw_cost, target)
        return x1, q1, v1, P

    def rollout(self, model, first, q0, v0, targets, record_q=False):
        """Frames (B, T, n) of the loop from ``first`` (B, n) with state (q0, v0), driven by
        ``targets`` (B, T, 9K) (frame t gets targets[:, t]); with ``record_q`` also the joint
        angles (B, T, D). Gradients flow unless called under ``torch.no_grad``."""
        B, T = targets.shape[:2]
        xs, qs = [first], [q0]
        x, q, v = first, q0, v0
        for t in range(1, T):
            out = model(self.normalise(x))
            x, q, v, _ = self.step(out, x, q, v, targets[:, t])
            xs.append(x)
            qs.append(q)
        frames = torch.stack(xs, 1)
        return (frames, torch.stack(qs, 1)) if record_q else frames
