"""NumPy inference of a trained OMG model (no PyTorch): the float reference that the
committed reference outputs under ``models/omg/<name>/`` are checked against.

A model directory holds ``model.safetensors`` (weights and normalisation statistics) and
``config.json`` (sizes, slices, phase-update constant, mode). Tensor names and shapes:

==================  ======================  ==============================================
name                shape                   meaning
==================  ======================  ==============================================
enc.{0,1,2}.w/.b    (out, in) / (out,)      encoder MLP 12J -> h -> h -> L (ELU, ELU, id); FS:
                                            input = the config's ``encoder_columns``
dec.{0,1,2}.w/.b    (out, in) / (out,)      decoder MLP L -> h -> h -> 12J
cost.{0,1,2}.w/.b   (out, in) / (out,)      cost encoder (6K costs + 9K targets) -> Hc x3
gate.{0,1,2}.w/.b   (out, in) / (out,)      gate 2K -> G -> G -> k, then softmax
experts.w{0,1,2}    (k, in, out)            expert layers (``x @ w[e] + b[e]``)
experts.b{0,1,2}    (k, out)
rbf.centres         (C, L)                  RBF-CAT only: centres mu
rbf.scales          (C,)                    RBF-CAT only: sigma, psi = exp(-(sigma |z-mu|)^2)
norm.mean/.std      (n,)                    per-feature statistics shared by X and Y
==================  ======================  ==============================================

One frame (normalised space, X and Y share the layout of ``config["slices"]``)::

    z = Enc(X[pose]); c = CostEnc(X[cost ++ target]); a = softmax(Gate(X[phase]))
    h = [z, c]; for each expert layer l: h = sum_e a_e (h' @ w_l[e] + b_l[e]), ELU but last
        (RBF-CAT: h' = [psi, h], psi = RBF(z); FE: h' = h)
    dtheta, z', C' = split(h)
    Y = [a_ph * dtheta + (1 - a_ph) * X[phase], Dec(z'), C', X[target]]      a_ph = 0.9
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

CONTACT_RADIUS = 0.1  # m, the data's contact threshold (reach success)


def elu(x):
    return np.where(x > 0, x, np.expm1(np.minimum(x, 0)))


def softmax(x):
    e = np.exp(x - x.max(axis=-1, keepdims=True))
    return e / e.sum(axis=-1, keepdims=True)


class NumpyOMG:
    """Inference-only OMG forward pass in NumPy (float64 by default)."""

    def __init__(self, model_dir, dtype=np.float64):
        model_dir = Path(model_dir)
        from safetensors.numpy import load_file

        self.cfg = json.loads((model_dir / "config.json").read_text())
        self.t = {k: v.astype(dtype) for k, v in load_file(str(model_dir / "model.safetensors")).items()}
        self.dtype = dtype
        self.sl = {k: slice(*v) for k, v in self.cfg["slices"].items()}
        self.osl = {k: slice(*v) for k, v in self.cfg["out_slices"].items()}
        self.mean = self.t["norm.mean"]
        self.std = self.t["norm.std"]
        self.a_ph = self.cfg["phase_update"]["a"]
        self.variant = self.cfg["variant"]
        self.dof_form = self.cfg.get("pose_form", "absolute") == "dof_velocity"
        if self.dof_form:
            c = self.cfg["controller"]
            self.fps, self.a_max = float(c["fps"]), float(c["a_max"])
            self.rig = skeleton_rig(c["skeleton"])
            self.dof_mean, self.dof_std = self.t["norm.dof_mean"], self.t["norm.dof_std"]
            np_, nd = self.sl["phase"].stop - self.sl["phase"].start, self.rig.n_dofs
            nc = self.sl["cost"].stop - self.sl["cost"].start
            self.out = dict(phase=slice(0, np_), u=slice(np_, np_ + nd), cost=slice(np_ + nd, np_ + nd + nc))

    def mlp(self, name, x):
        for i in range(3):
            x = x @ self.t[f"{name}.{i}.w"].T + self.t[f"{name}.{i}.b"]
            if i < 2:
                x = elu(x)
        return x

    def rbf(self, z):
        mu, s = self.t["rbf.centres"], self.t["rbf.scales"]
        d2 = ((z[:, None, :] - mu[None]) ** 2).sum(-1)
        return np.exp(-(s**2) * d2)

    def step_norm(self, x):
        """One frame in normalised space: X (B, n) -> Y (B, n)."""
        sl = self.sl
        cols = self.cfg.get("encoder_columns")
        z = self.mlp("enc", x[:, sl["pose"]] if cols is None else x[:, cols])
        c = self.mlp("cost", np.concatenate([x[:, sl["cost"]], x[:, sl["target"]]], axis=1))
        a = softmax(self.mlp("gate", x[:, sl["phase"]]))
        psi = self.rbf(z) if self.variant == "RBF-CAT" else None
        h = np.concatenate([z, c], axis=1)
        for l in range(3):
            if psi is not None:
                h = np.concatenate([psi, h], axis=1)
            he = np.einsum("bi,kio->bko", h, self.t[f"experts.w{l}"]) + self.t[f"experts.b{l}"][None]
            h = np.einsum("bk,bko->bo", a, he)
            if l < 2:
                h = elu(h)
        phase = self.a_ph * h[:, self.osl["dphase"]] + (1 - self.a_ph) * x[:, sl["phase"]]
        pose = self.mlp("dec", h[:, self.osl["z"]])
        if self.dof_form:
            return np.concatenate([phase, pose, h[:, self.osl["cost"]]], axis=1)
        y = np.empty_like(x)
        y[:, sl["phase"]] = phase
        y[:, sl["pose"]] = pose
        y[:, sl["cost"]] = h[:, self.osl["cost"]]
        y[:, sl["target"]] = x[:, sl["target"]]
        return y

    def normalise(self, raw):
        return (raw - self.mean) / self.std

    def denormalise(self, x):
        return x * self.std + self.mean

    def step(self, raw):
        """One frame in raw units: X (B, n) -> Y (B, n); a joint-velocity model: its raw
        network output [phase', u, cost'] (B, n_out)."""
        y = self.step_norm(self.normalise(np.asarray(raw, self.dtype)))
        if not self.dof_form:
            return self.denormalise(y)
        ph, co = self.sl["phase"], self.sl["cost"]
        return np.concatenate([y[:, self.out["phase"]] * self.std[ph] + self.mean[ph],
                               y[:, self.out["u"]] * self.dof_std + self.dof_mean,
                               y[:, self.out["cost"]] * self.std[co] + self.mean[co]], axis=1)

    def limit(self, q, v, w):
        """The controller's limit stage (docs/omg-joint-velocity.md step 2)."""
        dt, a = 1.0 / self.fps, self.a_max
        h = 0.5 * a * dt

        def stop(room):
            return np.sqrt(h * h + 2 * a * np.maximum(room, 0.0)) - h

        lo, hi = self.rig.lower, self.rig.upper
        w = np.minimum(w, stop(hi - q))
        w = np.maximum(w, -stop(q - lo))
        v1 = v + np.clip(w - v, -a * dt, a * dt)
        q1 = np.clip(q + v1 * dt, lo, hi)
        return q1, (q1 - q) / dt

    def rollout_dof(self, first, q0, v0, targets, mode="grounded"):
        """The controller loop of a joint-velocity model: frames (B, T, n) and joint angles
        (B, T, D) from ``first`` (B, n) with state (q0, v0), frame t getting targets[:, t]."""
        from .rigs import forward_kinematics

        first = np.asarray(first, self.dtype)
        B, T = targets.shape[:2]
        n = first.shape[1]
        sl = self.sl
        frames = np.empty((B, T, n), self.dtype)
        qs = np.empty((B, T, self.rig.n_dofs), self.dtype)
        frames[:, 0], qs[:, 0] = first, q0
        x, q, v = first, np.asarray(q0, self.dtype), np.asarray(v0, self.dtype)
        dt = 1.0 / self.fps
        for t in range(1, T):
            o = self.step(x)
            q, v = self.limit(q, v, o[:, self.out["u"]] / dt)
            P, G = forward_kinematics(self.rig, q)
            y = np.empty_like(x)
            y[:, sl["phase"]] = o[:, self.out["phase"]]
            J = P.shape[1]
            y[:, sl["pos"]] = P.reshape(B, 3 * J)
            y[:, sl["rot"]] = np.concatenate([G[..., :, 2], G[..., :, 1]], axis=-1).reshape(B, 6 * J)
            y[:, sl["vel"]] = (P.reshape(B, 3 * J) - x[:, sl["pos"]]) * self.fps
            y[:, sl["target"]] = targets[:, t]
            y[:, sl["cost"]] = costs_from_frame(y, self.cfg) if mode == "grounded" else o[:, self.out["cost"]]
            frames[:, t], qs[:, t] = y, q
            x = y
        return frames, qs

    def rollout(self, clips, mode=None):
        """Autoregressive rollout driven by the clips' targets: (B, T, n) raw -> (B, T, n).

        Frame 0 is copied from the data; every later frame is the model's output with the
        target block overwritten by the data's targets of that frame and, in grounded mode,
        the cost block recomputed from the decoded pose and those targets.
        """
        mode = mode or self.cfg["mode"]
        clips = np.asarray(clips, self.dtype)
        B, T, n = clips.shape
        out = np.empty_like(clips)
        out[:, 0] = clips[:, 0]
        x = clips[:, 0]
        for t in range(1, T):
            y = self.step(x)
            y[:, self.sl["target"]] = clips[:, t, self.sl["target"]]
            if mode == "grounded":
                y[:, self.sl["cost"]] = costs_from_frame(y, self.cfg)
            out[:, t] = y
            x = y
        return out


def skeleton_rig(sk: dict):
    """A :class:`tools.omg.rigs.Rig` (for its forward kinematics) from a config's
    ``controller.skeleton``."""
    from .rigs import Rig

    J = len(sk["parents"])
    return Rig(name="skeleton", joint_names=[str(j) for j in range(J)], parents=np.asarray(sk["parents"]),
               offsets=np.asarray(sk["offsets"], dtype=np.float64),
               dof_joint=np.asarray([d["joint"] for d in sk["dofs"]]),
               dof_axis=np.asarray([d["axis"] for d in sk["dofs"]]),
               lower=np.asarray([d["lower"] for d in sk["dofs"]], dtype=np.float64),
               upper=np.asarray([d["upper"] for d in sk["dofs"]], dtype=np.float64),
               dof_weight=np.ones(len(sk["dofs"])), key_joints=np.zeros(0, dtype=np.int64))


def _normalised(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-8)


def costs_from_frame(y, cfg):
    """Cost block (6K) recomputed from a raw frame's pose and targets (spec §1.5 mode 2).

    pos_cost = target position - key-joint position; rot_cost = angle/pi between the
    (side, up, forward) axes of target and joint, from the normalised forward/up vectors and
    side = normalise(up x forward).
    """
    sl = {k: slice(*v) for k, v in cfg["slices"].items()}
    key = np.asarray(cfg["key_joint_indices"])
    lead = y.shape[:-1]
    J = cfg["J"]
    K = len(key)
    pos = y[..., sl["pos"]].reshape(*lead, J, 3)[..., key, :]
    rot = y[..., sl["rot"]].reshape(*lead, J, 6)[..., key, :]
    tpos = y[..., sl["target_pos"]].reshape(*lead, K, 3)
    trot = y[..., sl["target_rot"]].reshape(*lead, K, 6)

    def axes(r):
        f = _normalised(r[..., 0:3])
        u = _normalised(r[..., 3:6])
        s = _normalised(np.cross(u, f))
        return np.stack([s, u, f], axis=-2)  # (..., 3 axes, 3)

    dots = (axes(trot) * axes(rot)).sum(-1)
    rc = np.arccos(np.clip(dots, -1.0, 1.0)) / np.pi
    pc = tpos - pos
    return np.concatenate([pc.reshape(*lead, 3 * K), rc.reshape(*lead, 3 * K)], axis=-1)
