"""Training joint-velocity OMG models for the loop they run in (docs/omg-joint-velocity.md).

The network learns the data's IK: at a state (pose, targets) its label is the velocity the
IK asks for there (``HandIK.desired_velocity`` times the frame time, a function of the joint
angles and the targets only), and the controller applies the same limits as the IK. Two
stages:

1. **Teacher forcing** on the data's frames: input frame t, labels the IK's desired
   velocity at q_t for the targets of frame t + 1, the data's phase of frame t + 1 and (with
   a small weight, faithful mode only uses them) its costs.
2. **DAgger** (Ross et al. 2011; ``rollout_labels`` "ik"): roll the model out in its own loop from every training
   clip's first frame, driven by the clip's targets; label every visited state with the
   IK's desired velocity there (the IK is the expert, it labels any state); add the visited
   frames to the training set (the data's frames stay; only the last ``keep`` rollouts are
   kept) and train again. The learning rate falls geometrically from ``lr`` to ``lr_end``
   over the iterations. ``rollout_labels`` "data" labels the visited frames with the data's
   label of the same clip and frame instead (long autoregressive rollouts that learn to snap
   back to the data, the thesis's kind of closed-loop training), for comparison.

The per-DOF velocity targets are normalised by their standard deviation over the data's
frames, so the loss weighs each joint by what it changes frame to frame; a second term
(``pos_loss``) compares the joint positions one frame on (forward kinematics of q + u
against q + u*, in centimetres), so that a shoulder's error counts by how far it moves the
hand.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from torch.nn import functional as F

from ..ik import DT, HandIK, rot6_to_matrix
from .loop import DofLoop


def ik_labels(ik: HandIK, q: np.ndarray, targets: np.ndarray, K: int, chunk: int = 8192) -> np.ndarray:
    """The IK's desired per-frame velocity (N, D) at joint angles q (N, D) for target blocks
    (N, 9K) (the hands are key joints 0 and 1), radians per frame."""
    out = []
    for i in range(0, len(q), chunk):
        t = targets[i : i + chunk]
        tp = t[:, :6].reshape(-1, 2, 3)
        t6 = t[:, 3 * K : 3 * K + 12].reshape(-1, 2, 6)
        out.append(ik.desired_velocity(q[i : i + chunk].astype(np.float64), tp, rot6_to_matrix(t6)) * DT)
    return np.concatenate(out)


class Samples:
    """Training rows: normalised inputs, u labels, phase and cost labels, cost weights and
    the rows' joint angles."""

    def __init__(self):
        self.parts = []

    def add(self, x_n, u_n, phase_n, cost_n, cost_w, q):
        self.parts.append((x_n, u_n, phase_n, cost_n, cost_w, q))

    def keep_last(self, first: int, keep: int):
        """Keeps the first ``first`` parts (the data) and the last ``keep`` others."""
        if len(self.parts) > first + keep:
            self.parts = self.parts[:first] + self.parts[len(self.parts) - keep :]

    def tensors(self):
        return [torch.cat([p[i] for p in self.parts]) for i in range(6)]


def train_steps(model, opt, samples: Samples, steps: int, batch: int, gen, log, t0, loop=None,
                pos_loss: float = 0.0, what: str = "", perturb=None):
    """``steps`` optimiser steps on batches drawn at random (without replacement within
    a pass) from ``samples``. ``pos_loss``: weight of the joint positions one frame on,
    forward kinematics of q + u against q + u*, in units of 1 cm (a joint's share of the
    loss by what it moves). ``perturb()``, when given, changes the weights in place before
    every step and returns the clean ones; the step's gradient, taken at the changed
    weights, updates the restored ones (quantisation-aware fine-tuning, ``core.grid_round``)."""
    from .core import restore

    X, U, PH, C, W, Q = samples.tensors()
    N = X.shape[0]
    o = model.out_slices_dof
    tot, perm, at = 0.0, torch.randperm(N, generator=gen), 0
    for _ in range(steps):
        if at + batch > N:
            perm, at = torch.randperm(N, generator=gen), 0
        idx = perm[at : at + batch]
        at += batch
        clean = perturb() if perturb is not None else None
        out = model(X[idx])
        loss = F.mse_loss(out[:, o["u"]], U[idx]) + 0.1 * F.mse_loss(out[:, o["phase"]], PH[idx])
        loss = loss + 0.01 * ((out[:, o["cost"]] - C[idx]) ** 2 * W[idx, None]).mean()
        if pos_loss > 0:
            q = Q[idx]
            p_hat, _ = loop.fk(q + out[:, o["u"]] * loop.dof_std + loop.dof_mean)
            with torch.no_grad():
                p_lab, _ = loop.fk(q + U[idx] * loop.dof_std + loop.dof_mean)
            loss = loss + pos_loss * ((p_hat - p_lab) ** 2).sum(-1).mean() / 0.01**2
        opt.zero_grad()
        loss.backward()
        if clean is not None:
            restore(clean)
        opt.step()
        tot += loss.item()
    log(f"    {what}{steps} steps of {batch} from {N} rows: loss {tot / max(steps, 1):.4f} ({time.time() - t0:.0f} s)")
    return tot / max(steps, 1)


def train_dagger(model, loop: DofLoop, ik: HandIK, train: np.ndarray, sl: dict, dof: slice, args, gen, log,
                 params=None, evaluate=None, perturb=None):
    """Trains ``model`` (``pose_form`` "dof_velocity") on the raw training clips ``train``
    (B, T, width; the ``dof`` columns hold q). ``evaluate(model, tag)``, if given, is called
    after each stage (for the log only; it must not read held-out clips for choices).
    ``perturb``: see :func:`train_steps`; the rollouts then run the perturbed model too (the
    model being trained is the perturbed one). Returns the history."""
    from .core import restore

    def as_trained():
        return perturb() if perturb is not None else None
    t0 = time.time()
    K = len(loop.key)
    n = loop.mean.shape[0]
    B, T = train.shape[:2]
    ph, co, tg = (slice(*sl[k]) for k in ("phase", "cost", "target"))
    x = torch.from_numpy(train[:, :, :n].astype(np.float32))
    q = train[:, :, dof].astype(np.float64)
    x_n = loop.normalise(x)
    # teacher forcing: frame t -> the IK's velocity at q_t for frame t+1's targets
    u = ik_labels(ik, q[:, :-1].reshape(-1, q.shape[-1]), train[:, 1:, tg].reshape(-1, 9 * K), K)
    u_n = (torch.from_numpy(u).float() - loop.dof_mean) / loop.dof_std
    samples = Samples()
    samples.add(
        x_n[:, :-1].reshape(-1, n),
        u_n,
        x_n[:, 1:, ph].reshape(-1, ph.stop - ph.start),
        x_n[:, 1:, co].reshape(-1, co.stop - co.start),
        torch.ones(B * (T - 1)),
        torch.from_numpy(q[:, :-1].reshape(-1, q.shape[-1])).float(),
    )
    params = list(params if params is not None else model.parameters())
    opt = torch.optim.AdamW(params, lr=args.lr)
    history = []
    log(f"  teacher forcing: {B * (T - 1)} frames")
    loss = train_steps(model, opt, samples, args.tf_steps, args.batch, gen, log, t0, loop, args.pos_loss,
                       perturb=perturb)
    history.append(dict(stage="teacher forcing", loss=loss, s=round(time.time() - t0, 1)))
    if evaluate is not None:
        clean = as_trained()
        history[-1].update(evaluate(model, "teacher forcing"))
        if clean is not None:
            restore(clean)
    first = torch.from_numpy(train[:, 0, :n].astype(np.float64)).float()
    q0 = torch.from_numpy(q[:, 0]).float()
    v0 = q0 / loop.dt
    targets = torch.from_numpy(train[:, :, tg].astype(np.float32))
    for it in range(args.dagger):
        lr = args.lr * (args.lr_end / args.lr) ** ((it + 1) / max(args.dagger, 1))
        for g in opt.param_groups:
            g["lr"] = lr
        clean = as_trained()
        with torch.no_grad():
            frames, qs = loop.rollout(model, first, q0, v0, targets, record_q=True)
        if clean is not None:
            restore(clean)
        vis_q = qs[:, :-1].reshape(-1, qs.shape[-1]).double().numpy()
        if args.rollout_labels == "ik":
            lab_n = (torch.from_numpy(ik_labels(ik, vis_q, train[:, 1:, tg].reshape(-1, 9 * K), K)).float()
                     - loop.dof_mean) / loop.dof_std
        else:  # the data's label of the same frame: autoregressive rollouts that snap back
            lab_n = u_n
        vis_n = loop.normalise(frames[:, :-1]).reshape(-1, n)
        samples.add(
            vis_n,
            lab_n,
            x_n[:, 1:, ph].reshape(-1, ph.stop - ph.start),
            torch.zeros(B * (T - 1), co.stop - co.start),
            torch.zeros(B * (T - 1)),
            qs[:, :-1].reshape(-1, qs.shape[-1]).float(),
        )
        samples.keep_last(1, args.keep)
        log(f"  DAgger {it}: rolled out {B} clips, learning rate {lr:.2e}")
        loss = train_steps(model, opt, samples, args.dagger_steps, args.batch, gen, log, t0, loop, args.pos_loss,
                           perturb=perturb)
        history.append(dict(stage=f"dagger {it}", loss=loss, lr=lr, s=round(time.time() - t0, 1)))
        if evaluate is not None:
            clean = as_trained()
            history[-1].update(evaluate(model, f"dagger {it}"))
            if clean is not None:
                restore(clean)
    return history
