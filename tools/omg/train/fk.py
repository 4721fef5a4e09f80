"""The rig's forward kinematics in PyTorch, and the OMG frame built from joint angles.

A model with a joint-angle output (``pose_form`` "dof_velocity" in its config) changes the rig's
DOF values ``q`` every frame; the controller clamps them to the joint limits and rebuilds
the frame's pose block by forward kinematics, so every bone keeps its length and every
joint its limits by construction. This module is that rebuild, differentiable and
batched, the same rotations as :func:`tools.omg.rigs.forward_kinematics` (intrinsic
Euler x-y-z per joint, rest rotations the identity).
"""

from __future__ import annotations

import math

import torch

from ..ik import FPS


class RigFK:
    """Forward kinematics of one rig (its ``rig.json`` or a :class:`tools.omg.rigs.Rig`)."""

    def __init__(self, rig, dtype=torch.float32):
        if isinstance(rig, dict):
            self.parents = list(rig["parents"])
            self.offsets = torch.tensor(rig["rest_offsets"], dtype=dtype)
            names = rig["joints"]
            self.dof_joint = torch.tensor([names.index(d["joint"]) for d in rig["dofs"]])
            self.dof_axis = torch.tensor(["xyz".index(d["axis"]) for d in rig["dofs"]])
            self.lower = torch.tensor([d["lower"] for d in rig["dofs"]], dtype=dtype)
            self.upper = torch.tensor([d["upper"] for d in rig["dofs"]], dtype=dtype)
        else:
            self.parents = [int(p) for p in rig.parents]
            self.offsets = torch.as_tensor(rig.offsets, dtype=dtype)
            self.dof_joint = torch.as_tensor(rig.dof_joint)
            self.dof_axis = torch.as_tensor(rig.dof_axis)
            self.lower = torch.as_tensor(rig.lower, dtype=dtype)
            self.upper = torch.as_tensor(rig.upper, dtype=dtype)
        self.J = len(self.parents)
        self.D = len(self.dof_joint)
        self.dtype = dtype
        # Joints by depth: one batched product per level instead of one per joint.
        depth = []
        for p in self.parents:
            depth.append(0 if p < 0 else depth[p] + 1)
        self.levels = [
            (torch.tensor([j for j in range(self.J) if depth[j] == d]),
             torch.tensor([self.parents[j] for j in range(self.J) if depth[j] == d]))
            for d in range(1, max(depth) + 1)
        ]
        roots = [j for j, p in enumerate(self.parents) if p < 0]
        if roots != [0]:
            raise ValueError("the root must be joint 0 and the only one")

    def clamp(self, q):
        return torch.maximum(torch.minimum(q, self.upper), self.lower)

    def __call__(self, q):
        """Global positions (B, J, 3) and rotations (B, J, 3, 3) for DOF values q (B, D)."""
        B = q.shape[0]
        eul = torch.zeros(B, self.J, 3, dtype=q.dtype)
        eul = eul.index_put((torch.arange(B)[:, None], self.dof_joint[None], self.dof_axis[None]), q)
        c, s = torch.cos(eul), torch.sin(eul)
        one, zero = torch.ones_like(c[..., 0]), torch.zeros_like(c[..., 0])

        def rot(a):
            ca, sa = c[..., a], s[..., a]
            if a == 0:
                m = [one, zero, zero, zero, ca, -sa, zero, sa, ca]
            elif a == 1:
                m = [ca, zero, sa, zero, one, zero, -sa, zero, ca]
            else:
                m = [ca, -sa, zero, sa, ca, zero, zero, zero, one]
            return torch.stack(m, dim=-1).reshape(B, self.J, 3, 3)

        rloc = rot(0) @ rot(1) @ rot(2)
        off = self.offsets.to(q.dtype)
        G = rloc[:, :1]
        P = off[:1].expand(B, 1, 3)
        # Level by level; each level's joints are appended, then put back in joint order.
        order = [0]
        for js, ps in self.levels:
            idx = torch.tensor([order.index(int(p)) for p in ps])
            Gp, Pp = G[:, idx], P[:, idx]
            P = torch.cat([P, Pp + (Gp @ off[js][None, :, :, None])[..., 0]], 1)
            G = torch.cat([G, Gp @ rloc[:, js]], 1)
            order += [int(j) for j in js]
        inv = torch.argsort(torch.tensor(order))
        return P[:, inv], G[:, inv]


def pose_block(P, G, P_prev):
    """The frame's pos, rot and vel blocks (B, 12J) from FK of this and the last frame:
    positions, per joint forward (z column) then up (y column), (P - P_prev) * 60."""
    B, J = P.shape[:2]
    rot = torch.cat([G[..., :, 2], G[..., :, 1]], dim=-1)  # (B, J, 6)
    return torch.cat([P.reshape(B, 3 * J), rot.reshape(B, 6 * J), ((P - P_prev) * FPS).reshape(B, 3 * J)], 1)


def unit(v):
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-8)


def grounded_costs(P, G, key, tpos, trot6):
    """Cost block (B, 6K): target - key-joint position, then per key joint angle/pi
    between the target's and the joint's (side, up, forward) axes (eq 3.4-3.5)."""
    B = P.shape[0]
    K = len(key)
    pos = P[:, key]
    f = G[:, key][..., :, 2]
    u = G[:, key][..., :, 1]

    def axes(fw, up):
        fw, up = unit(fw), unit(up)
        return torch.stack([unit(torch.linalg.cross(up, fw, dim=-1)), up, fw], dim=-2)

    tr = trot6.reshape(B, K, 6)
    dots = (axes(tr[..., :3], tr[..., 3:]) * axes(f, u)).sum(-1)
    rc = torch.arccos(dots.clamp(-1.0, 1.0)) / math.pi
    return torch.cat([(tpos.reshape(B, K, 3) - pos).reshape(B, 3 * K), rc.reshape(B, 3 * K)], 1)
