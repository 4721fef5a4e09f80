"""Data, normalisation, training loop (spec §1.6) and export of OMG models."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from .model import OMG, PHASE_A

SEQ_LEN = 13  # frames per training chunk (299 = 23 x 13)
STD_FLOOR = 1e-4  # features with a smaller std over the training frames are constant: std := 1


def open_log(out: Path, name: str):
    """Creates ``out`` and returns ``log(msg)``, which prints a line and appends it to
    ``out / name``."""
    out.mkdir(parents=True, exist_ok=True)
    f = open(out / name, "w")

    def log(msg):
        print(msg, flush=True)
        f.write(msg + "\n")
        f.flush()

    return log


# ----------------------------------------------------------------------------------------
# data


def model_slices(lay: dict) -> dict:
    """Slices of the model vector (first ``model_width`` columns) as (start, stop)."""
    b = {x["name"]: (x["offset"], x["offset"] + x["size"]) for x in lay["blocks"]}
    s = {k: b[k] for k in ("phase", "pos", "rot", "vel", "pos_cost", "rot_cost", "target_pos", "target_rot")}
    s["pose"] = (b["pos"][0], b["vel"][1])
    s["cost"] = (b["pos_cost"][0], b["rot_cost"][1])
    s["target"] = (b["target_pos"][0], b["target_rot"][1])
    assert s["target"][1] == lay["model_width"]
    return s


def load_rig(data_dir, rig):
    d = Path(data_dir) / rig
    lay = json.loads((d / "layout.json").read_text())
    n = lay["model_width"]
    splits = {s: np.load(d / f"{s}.npy", mmap_mode="r")[:, :, :n].astype(np.float32) for s in ("train", "val", "test")}
    return lay, splits


def norm_stats(frames: np.ndarray):
    f = frames.reshape(-1, frames.shape[-1]).astype(np.float64)
    mean = f.mean(0)
    std = f.std(0)
    std = np.where(std < STD_FLOOR, 1.0, std)
    return mean.astype(np.float32), std.astype(np.float32)


# ----------------------------------------------------------------------------------------
# grounded costs (torch mirror of tools.omg.omg_np.costs_from_frame)


def _unit(v):
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-8)


def costs_from_frame(y: torch.Tensor, sl: dict, key, J: int) -> torch.Tensor:
    B = y.shape[0]
    K = len(key)
    pos = y[:, slice(*sl["pos"])].reshape(B, J, 3)[:, key]
    rot = y[:, slice(*sl["rot"])].reshape(B, J, 6)[:, key]
    tpos = y[:, slice(*sl["target_pos"])].reshape(B, K, 3)
    trot = y[:, slice(*sl["target_rot"])].reshape(B, K, 6)

    def axes(r):
        f = _unit(r[..., 0:3])
        u = _unit(r[..., 3:6])
        s = _unit(torch.linalg.cross(u, f, dim=-1))
        return torch.stack([s, u, f], dim=-2)

    dots = (axes(trot) * axes(rot)).sum(-1)
    rc = torch.arccos(dots.clamp(-1.0, 1.0)) / math.pi
    return torch.cat([(tpos - pos).reshape(B, 3 * K), rc.reshape(B, 3 * K)], dim=1)


class Frame:
    """Normalisation and the feed-back rule shared by training and rollouts."""

    def __init__(self, sl, mean, std, key, J, mode):
        self.sl = sl
        self.mean = torch.as_tensor(mean)
        self.std = torch.as_tensor(std)
        self.key = list(key)
        self.J = J
        self.mode = mode
        self.tgt = slice(*sl["target"])
        self.cost = slice(*sl["cost"])

    def feed_back(self, out_n: torch.Tensor, target_n: torch.Tensor) -> torch.Tensor:
        """Model output (normalised) -> next input: current targets in; grounded mode also
        recomputes the costs from the decoded pose and those targets."""
        fb = out_n.detach().clone()
        fb[:, self.tgt] = target_n
        if self.mode == "grounded":
            raw = fb * self.std + self.mean
            c = costs_from_frame(raw, self.sl, self.key, self.J)
            fb[:, self.cost] = (c - self.mean[self.cost]) / self.std[self.cost]
        return fb


# ----------------------------------------------------------------------------------------
# training


def pretrain_ae(model: OMG, frames_n: torch.Tensor, epochs, lr, batch, gen, log):
    """AE pre-training on single normalised frames (B, n): Dec(Enc(encoder input)) -> full
    pose, MSE only (no discriminator, see README)."""
    opt = torch.optim.AdamW(model.ae.parameters(), lr=lr)
    n = frames_n.shape[0]
    pose = model.sl["pose"]
    steps = 0
    for ep in range(epochs):
        perm = torch.randperm(n, generator=gen)
        tot = 0.0
        for i in range(0, n, batch):
            f = frames_n[perm[i : i + batch]]
            loss = F.mse_loss(model.ae.dec(model.ae.enc(model.enc_input(f))), f[:, pose])
            opt.zero_grad()
            loss.backward()
            opt.step()
            tot += loss.item() * f.shape[0]
            steps += 1
        if ep % 5 == 0 or ep == epochs - 1:
            log(f"  ae epoch {ep:3d} mse {tot / n:.5f}")
    return tot / n


def one_step_loss(model, clips_n):
    with torch.no_grad():
        x = clips_n[:, :-1].reshape(-1, clips_n.shape[-1])
        y = clips_n[:, 1:].reshape(-1, clips_n.shape[-1])
        return F.mse_loss(model(x), y).item()


def weight_matrices(model: OMG) -> list:
    """The weight matrices the exporter quantises row by row, each as (tensor, row axis):
    an ``nn.Linear`` weight (out, in) has a row per output, an expert stack (k, in, out)
    one per expert and output."""
    out = []
    for name, t in model.named_tensors().items():
        if name.endswith(".w"):
            out.append((t, 0))
        elif name.startswith("experts.w"):
            out.append((t, 1))
    return out


def int8_noise(model: OMG, amount: float, gen) -> list:
    """Adds to every weight matrix uniform noise of ``amount`` int8 steps peak to peak
    (a step is a row's largest magnitude / 127, the exporter's per-row scale before its
    search), in place; returns the clean weights so that ``restore`` puts them back bit
    for bit. Training through such perturbations asks for rollouts that survive int8
    weights."""
    clean = []
    with torch.no_grad():
        for w, axis in weight_matrices(model):
            clean.append((w, w.detach().clone()))
            step = w.abs().amax(dim=axis, keepdim=True) / 127.0
            w.add_((torch.rand(w.shape, generator=gen) - 0.5) * amount * step)
    return clean


def grid_round(model: OMG, grid: dict, qmax: float) -> list:
    """Rounds, in place, every weight matrix named in ``grid`` to the grid its blob puts it
    on, and returns the clean weights for ``restore``. ``grid`` maps a tensor name to the
    integer units per real unit ``u_j`` of each input column (``exporter omg --grid-out``);
    a row's scale is ``s_i = qmax / max_j |w_ij / u_j|`` (an expert stack's experts share
    their output rows) and ``w_ij`` becomes ``round(w_ij / u_j * s_i) * u_j / s_i``, as the
    exporter rounds to nearest. Training through it (the gradient at the rounded weights
    updating the clean ones, a straight-through estimate) is quantisation-aware training."""
    clean = []
    with torch.no_grad():
        for name, w in model.named_tensors().items():
            if name not in grid:
                continue
            u = torch.as_tensor(grid[name], dtype=w.dtype)
            if name.startswith("experts.w"):  # (k, in, out)
                u = u[None, :, None]
                rows = (0, 1)
            else:  # (out, in)
                u = u[None, :]
                rows = (1,)
            e = w / u
            s = qmax / e.abs().amax(dim=rows, keepdim=True).clamp_min(torch.finfo(w.dtype).tiny)
            clean.append((w, w.detach().clone()))
            w.copy_(torch.round(e * s).clamp(-qmax, qmax) / s * u)
    return clean


def restore(clean: list):
    """Puts back the weights ``int8_noise`` or ``grid_round`` changed."""
    with torch.no_grad():
        for w, c in clean:
            w.copy_(c)


def train_omg(
    model: OMG, fr: Frame, train_n: torch.Tensor, val_n: torch.Tensor, args, gen, log, params=None, perturb=None
):
    """The OMG stage. ``perturb()``, when given, changes the weights in place before every
    step and returns the clean ones (``int8_noise``, ``grid_round``); the step's gradient,
    taken at the changed weights, updates the restored ones (``--weight-noise`` and quantisation-aware
    fine-tuning, ``tools.omg.train.qat``). A given ``perturb`` also applies to the
    validation loss: its model is the one being trained."""
    params = list(params if params is not None else model.parameters())
    noise = getattr(args, "weight_noise", 0.0)
    feedback_noise = getattr(args, "feedback_noise", 0.0)
    # a given perturbation is the model being trained (QAT): validate it too
    validate_perturbed = perturb is not None
    if perturb is None and noise > 0:

        def perturb():
            return int8_noise(model, noise, gen)

    opt = torch.optim.AdamW(params, lr=args.lr)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=args.lr_step, gamma=0.9)
    n_clips = train_n.shape[0]
    n = train_n.shape[-1]
    history = []
    for ep in range(args.epochs):
        p = min(1.0, args.ar_inc * (ep // args.ar_every))
        perm = torch.randperm(n_clips, generator=gen)
        tot, cnt = 0.0, 0
        t0 = time.time()
        for b in range(0, n_clips, args.batch):
            X = train_n[perm[b : b + args.batch]]
            x = X[:, :-1].reshape(-1, SEQ_LEN, n)
            y = X[:, 1:].reshape(-1, SEQ_LEN, n)
            xc = x[:, 0]
            for i in range(1, SEQ_LEN):
                clean = perturb() if perturb is not None else None
                out = model(xc)
                loss = F.mse_loss(out, y[:, i - 1]) + model.extra_loss()
                opt.zero_grad()
                loss.backward()
                if clean is not None:
                    # the gradient at the perturbed weights updates the clean ones
                    restore(clean)
                opt.step()
                sched.step()
                tot += loss.item()
                cnt += 1
                # scheduled autoregression: uniform draw per chunk (spec §1.6 [T])
                fb = fr.feed_back(out, x[:, i, fr.tgt])
                if feedback_noise > 0:
                    # a perturbed state to recover from (the targets stay the data's)
                    kick = torch.randn(fb.shape, generator=gen) * feedback_noise
                    kick[:, fr.tgt] = 0.0
                    fb = fb + kick
                ar = torch.rand(xc.shape[0], generator=gen) < p
                xc = torch.where(ar[:, None], fb, x[:, i])
        clean = perturb() if validate_perturbed else None
        vl = one_step_loss(model, val_n)
        if clean is not None:
            restore(clean)
        history.append(dict(epoch=ep, p=p, train=tot / cnt, val_one_step=vl, s=time.time() - t0))
        log(f"  epoch {ep:3d} p {p:.1f} train {tot / cnt:.5f} val(one-step) {vl:.5f} ({time.time() - t0:.1f} s)")
    return history


# ----------------------------------------------------------------------------------------
# rollouts (torch mirror of tools.omg.omg_np.NumpyOMG.rollout)


@torch.no_grad()
def rollout(model, fr: Frame, clips_raw: torch.Tensor) -> torch.Tensor:
    B, T, n = clips_raw.shape
    out = torch.empty_like(clips_raw)
    out[:, 0] = clips_raw[:, 0]
    x = (clips_raw[:, 0] - fr.mean) / fr.std
    for t in range(1, T):
        y = model(x)
        tgt = (clips_raw[:, t, fr.tgt] - fr.mean[fr.tgt]) / fr.std[fr.tgt]
        x = fr.feed_back(y, tgt)
        out[:, t] = x * fr.std + fr.mean
    return out


@torch.no_grad()
def one_step(model, fr: Frame, frames_raw: torch.Tensor) -> torch.Tensor:
    return model((frames_raw - fr.mean) / fr.std) * fr.std + fr.mean


def count_params(model) -> int:
    return sum(p.numel() for p in model.parameters())


def config_dict(model: OMG, lay, mean, std, mode, extra) -> dict:
    sl = model_slices(lay)
    return dict(
        format="phasegate-omg-1",
        variant=model.variant,
        rig=lay["rig"],
        J=lay["joints"],
        K=lay["K"],
        key_joints=lay["key_joints"],
        key_joint_indices=lay["key_joint_indices"],
        model_width=lay["model_width"],
        sizes=dict(model.sz, experts=model.k, pose=12 * lay["joints"], cost_in=sl["target"][1] - sl["cost"][0],
                   enc_in=12 * lay["joints"] if model.enc_cols is None else len(model.enc_cols)),
        encoder_columns=None if model.enc_cols is None else [int(c) for c in model.enc_cols],
        slices={k: list(v) for k, v in sl.items()},
        out_slices={k: list(v) for k, v in model.out_slices.items()},
        phase_update=dict(formula="theta_next = a * dtheta + (1 - a) * theta (normalised space)", a=PHASE_A),
        mode=mode,
        modes=dict(
            faithful="feed back the whole output; the host overwrites the target block every frame",
            grounded="as faithful, then recompute the cost block from the decoded pose and the "
            "current targets (tools/omg/omg_np.py: costs_from_frame)",
        ),
        normalisation=dict(
            rule="x_n = (x - mean) / std per feature, shared by X and Y; std := 1 where the "
            f"training std < {STD_FLOOR}",
            mean=[float(v) for v in mean],
            std=[float(v) for v in std],
        ),
        activation="ELU(alpha=1) after the first two layers of every MLP and expert stack",
        gate="softmax over the gate MLP's k outputs; expert outputs blended per layer",
        params=count_params(model),
        macs_per_frame=model.macs_per_frame(),
        **extra,
    )
