"""OMG models in PyTorch (spec §1.3-1.4, §2.1-2.2): FE-OMG and RBF-CAT.

Layout of the per-frame vector X (and Y): ``phase`` (2K), ``pose`` (12J = pos, rot, vel),
``cost`` (6K = pos_cost, rot_cost), ``target`` (9K = target_pos, 6-D target_rot); the cost
encoder sees cost ++ target (15K = 60 inputs). Expert output: dtheta (2K), z' (L), C' (6K).
Phase update (the author's code, spec §1.4): theta' = A * dtheta + (1 - A) * theta, A = 0.9.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

PHASE_A = 0.9

SIZES = {
    # spec §5.2 (K = 4, 6-D target rotation)
    "tiny": dict(ae_hidden=64, latent=32, cost_hidden=32, expert_hidden=64, gate_hidden=16, clusters=16),
    "small": dict(ae_hidden=128, latent=64, cost_hidden=64, expert_hidden=128, gate_hidden=32, clusters=32),
}


class MLP3(nn.Module):
    """in -> h -> h -> out, ELU after the first two layers (eq 3.15)."""

    def __init__(self, i, h, o):
        super().__init__()
        self.layers = nn.ModuleList([nn.Linear(i, h), nn.Linear(h, h), nn.Linear(h, o)])
        for lin in self.layers:
            nn.init.xavier_uniform_(lin.weight)
            nn.init.constant_(lin.bias, 0.01)

    def forward(self, x):
        for n, lin in enumerate(self.layers):
            x = lin(x)
            if n < 2:
                x = F.elu(x)
        return x


class Experts(nn.Module):
    """k experts of 3 layers; per layer the expert outputs are blended with the gate
    coefficients (equal to blending the weights, eq 3.28). ``cat`` > 0: a vector of that
    size (psi) is concatenated in front of every layer's input (RBF-CAT, spec §2.2)."""

    def __init__(self, k, din, h, dout, cat=0):
        super().__init__()
        dims = [(cat + din, h), (cat + h, h), (cat + h, dout)]
        self.w = nn.ParameterList()
        self.b = nn.ParameterList()
        for i, o in dims:
            w = torch.empty(k, i, o)
            nn.init.kaiming_uniform_(w, a=math.sqrt(5))
            self.w.append(nn.Parameter(w))
            self.b.append(nn.Parameter(torch.full((k, o), 0.01)))
        self.dims = dims
        self.k = k

    def forward(self, x, alpha, psi=None):
        h = x
        for n in range(3):
            if psi is not None:
                h = torch.cat([psi, h], dim=1)
            he = torch.einsum("bi,kio->bko", h, self.w[n]) + self.b[n]
            h = torch.einsum("bk,bko->bo", alpha, he)
            if n < 2:
                h = F.elu(h)
        return h


class RBF(nn.Module):
    """Gaussian RBF layer (eq 3.20-3.21): psi_j = exp(-(sigma_j |z - mu_j|)^2)."""

    def __init__(self, C, L):
        super().__init__()
        self.centres = nn.Parameter(torch.randn(C, L))
        self.scales = nn.Parameter(torch.full((C,), 0.01))

    def forward(self, z):
        d2 = ((z[:, None, :] - self.centres[None]) ** 2).sum(-1)
        return torch.exp(-(self.scales**2) * d2)

    def ortho_loss(self):
        m = self.centres @ self.centres.T
        return 0.1 * (m - torch.eye(m.shape[0])).abs().mean()


class AE(nn.Module):
    def __init__(self, pose_dim, h, L):
        super().__init__()
        self.enc = MLP3(pose_dim, h, L)
        self.dec = MLP3(L, h, pose_dim)

    def forward(self, s):
        return self.dec(self.enc(s))


class OMG(nn.Module):
    def __init__(self, slices, variant="FE", size="tiny", k=4, enc_cols=None, pose_form="absolute", dof=0,
                 **over):
        """``enc_cols``: FS only, the model-vector columns the encoder sees (selected joints'
        pos, rot, vel); the decoder still outputs the full pose. ``pose_form``
        "dof_velocity": the decoder outputs the ``dof`` joints' desired velocities instead of
        the pose (docs/omg-joint-velocity.md), and :meth:`forward` returns the network
        output ``[phase', u, cost']`` (normalised) instead of the frame ``Y``."""
        super().__init__()
        if pose_form not in ("absolute", "dof_velocity"):
            raise ValueError(f"pose_form {pose_form!r}")
        self.pose_form = pose_form
        self.dof = dof
        self.enc_cols = None if enc_cols is None else torch.as_tensor(list(enc_cols), dtype=torch.long)
        sz = dict(SIZES[size], **over)
        self.sz, self.k, self.variant = sz, k, variant
        self.sl = {n: slice(*v) for n, v in slices.items()}
        n_phase = self.sl["phase"].stop - self.sl["phase"].start
        n_pose = self.sl["pose"].stop - self.sl["pose"].start
        n_cost = self.sl["cost"].stop - self.sl["cost"].start
        n_target = self.sl["target"].stop - self.sl["target"].start
        L, Hc = sz["latent"], sz["cost_hidden"]
        self.ae = AE(n_pose, sz["ae_hidden"], L)
        if pose_form == "dof_velocity":
            self.ae.dec = MLP3(L, sz["ae_hidden"], dof)
        if self.enc_cols is not None:
            self.ae.enc = MLP3(len(self.enc_cols), sz["ae_hidden"], L)
        self.cost = MLP3(n_cost + n_target, Hc, Hc)
        self.gate = MLP3(n_phase, sz["gate_hidden"], k)
        for lin in self.gate.layers:  # the gate keeps PyTorch's default init [C]
            lin.reset_parameters()
        cat = sz["clusters"] if variant == "RBF-CAT" else 0
        self.rbf = RBF(sz["clusters"], L) if variant == "RBF-CAT" else None
        self.dout = n_phase + L + n_cost
        self.experts = Experts(k, L + Hc, sz["expert_hidden"], self.dout, cat=cat)
        self.out_slices = {
            "dphase": (0, n_phase),
            "z": (n_phase, n_phase + L),
            "cost": (n_phase + L, self.dout),
        }
        # dof_velocity: where the blocks are in forward()'s output [phase', u, cost']
        self.out_slices_dof = {
            "phase": slice(0, n_phase),
            "u": slice(n_phase, n_phase + dof),
            "cost": slice(n_phase + dof, n_phase + dof + n_cost),
        }

    def enc_input(self, x):
        return x[:, self.enc_cols] if self.enc_cols is not None else x[:, self.sl["pose"]]

    def forward(self, x):
        sl = self.sl
        z = self.ae.enc(self.enc_input(x))
        c = self.cost(torch.cat([x[:, sl["cost"]], x[:, sl["target"]]], dim=1))
        alpha = F.softmax(self.gate(x[:, sl["phase"]]), dim=1)
        psi = self.rbf(z) if self.rbf is not None else None
        h = self.experts(torch.cat([z, c], dim=1), alpha, psi)
        o = {n: h[:, a:b] for n, (a, b) in self.out_slices.items()}
        phase = PHASE_A * o["dphase"] + (1 - PHASE_A) * x[:, sl["phase"]]
        pose = self.ae.dec(o["z"])
        if self.pose_form == "dof_velocity":
            return torch.cat([phase, pose, o["cost"]], dim=1)
        return torch.cat([phase, pose, o["cost"], x[:, sl["target"]]], dim=1)

    def extra_loss(self):
        return self.rbf.ortho_loss() if self.rbf is not None else torch.zeros(())

    def shared_modules(self):
        """The rig-independent part (CostEnc, gate, experts, C-layer)."""
        return [m for m in (self.cost, self.gate, self.experts, self.rbf) if m is not None]

    # -- export --------------------------------------------------------------------
    def named_tensors(self, shared_only: bool = False) -> dict:
        """Export name -> parameter (live, not detached); `shared_only`
        leaves out the rig's autoencoder."""
        t = {}
        mlps = (("cost", self.cost), ("gate", self.gate))
        if not shared_only:
            mlps = (("enc", self.ae.enc), ("dec", self.ae.dec)) + mlps
        for name, mlp in mlps:
            for i, lin in enumerate(mlp.layers):
                t[f"{name}.{i}.w"] = lin.weight
                t[f"{name}.{i}.b"] = lin.bias
        for i in range(3):
            t[f"experts.w{i}"] = self.experts.w[i]
            t[f"experts.b{i}"] = self.experts.b[i]
        if self.rbf is not None:
            t["rbf.centres"] = self.rbf.centres
            t["rbf.scales"] = self.rbf.scales
        return t

    def export_tensors(self) -> dict:
        return {k: v.detach().contiguous().float() for k, v in self.named_tensors().items()}

    def macs_per_frame(self) -> dict:
        def mlp(m):
            return sum(l.in_features * l.out_features for l in m.layers)

        ex = self.k * sum(i * o for i, o in self.experts.dims)
        d = dict(enc=mlp(self.ae.enc), dec=mlp(self.ae.dec), cost=mlp(self.cost), gate=mlp(self.gate), experts=ex)
        if self.rbf is not None:
            d["rbf"] = self.rbf.centres.numel()
        d["total"] = sum(d.values())
        return d
