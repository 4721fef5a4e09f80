"""Per-frame feature vectors (spec §1.2, §3.3, §3.4) and their layout.

Frame layout (all in root space; J joints in rig order, K = 4 key joints in the order
LeftHand, RightHand, LeftFoot, RightFoot):

=============  ======  ============================================================
block          size    content
=============  ======  ============================================================
phase          2K      per key joint [sin(G_B)*dsin, cos(G_B)*dcos] (eq 3.3)
pos            3J      per joint x, y, z (m)
rot            6J      per joint forward x, y, z then up x, y, z (unit vectors)
vel            3J      per joint (p_t - p_{t-1}) * 60 (m/s); frame 0 against rest
pos_cost       3K      per key joint target position - joint position (eq 3.4)
rot_cost       3K      per key joint angle/pi between (side, up, forward) axes of
                       target and joint, side = up x forward (eq 3.5, 3 angles)
target_pos     3K      per key joint target position
target_rot     6K      per key joint target forward x, y, z then up x, y, z
contact        K       per key joint 1 if within 0.1 m of its target (not a model
                       input; the block function G of the phases)
dof            D       the IK's joint angles q (radians, rig DOF order: rigs.py);
                       not a model input: what the pose was made from (forward
                       kinematics of q gives pos and rot), and the training target
                       of models that output joint-angle changes
=============  ======  ============================================================

The model vector X_i of spec §1.2 is the first ``12J + 17K`` values (phase .. target_rot);
``contact`` and ``dof`` follow it. Width = 12J + 18K + D.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import butter, sosfilt

from .ik import FPS
from .rigs import KEY_JOINT_NAMES, K

PHASE_WINDOW = 30  # frames, centred: t-15 .. t+14 (eq 3.1)
BUTTER_ORDER = 3
BUTTER_CUTOFF = 0.1  # fraction of Nyquist (eq 3.2: "threshold 0.1")

BLOCKS = (
    # name, per ("key" or "joint"), components per item, model input?
    ("phase", "key", ("sin", "cos"), True),
    ("pos", "joint", ("x", "y", "z"), True),
    ("rot", "joint", ("fx", "fy", "fz", "ux", "uy", "uz"), True),
    ("vel", "joint", ("x", "y", "z"), True),
    ("pos_cost", "key", ("x", "y", "z"), True),
    ("rot_cost", "key", ("side", "up", "forward"), True),
    ("target_pos", "key", ("x", "y", "z"), True),
    ("target_rot", "key", ("fx", "fy", "fz", "ux", "uy", "uz"), True),
    ("contact", "key", ("flag",), False),
    ("dof", "dof", ("q",), False),
)


def layout(rig) -> dict:
    """Offsets and sizes of every block for ``rig`` (also written as layout.json)."""
    J = rig.n_joints
    blocks = []
    off = 0
    model_width = 0
    for name, per, comps, model in BLOCKS:
        items = {"joint": J, "key": K, "dof": rig.n_dofs}[per]
        size = items * len(comps)
        names = {
            "joint": rig.joint_names,
            "key": list(KEY_JOINT_NAMES),
            "dof": [f"{rig.joint_names[j]}.{'xyz'[a]}" for j, a in zip(rig.dof_joint, rig.dof_axis)],
        }[per]
        blocks.append(
            dict(
                name=name,
                offset=off,
                size=size,
                per=per,
                components=list(comps),
                items=names,
                model_input=model,
            )
        )
        off += size
        if model:
            model_width = off
    return dict(
        rig=rig.name,
        joints=J,
        key_joints=list(KEY_JOINT_NAMES),
        key_joint_indices=[int(j) for j in rig.key_joints],
        K=K,
        width=off,
        model_width=model_width,
        frames_per_clip=None,
        fps=FPS,
        units=dict(pos="m", vel="m/s", rot_cost="angle/pi in [0, 1]", phase="dimensionless"),
        frame="root space: right-handed, y up, character faces +z, +x is its left; "
        "origin at the pivot (ground, between the feet)",
        order="item-major: block[item * len(components) + component]",
        blocks=blocks,
    )


def slices(lay: dict) -> dict:
    return {b["name"]: slice(b["offset"], b["offset"] + b["size"]) for b in lay["blocks"]}


# ----------------------------------------------------------------------------------
# Local motion phases (eq 3.1-3.3)
# ----------------------------------------------------------------------------------


def butter_sos() -> np.ndarray:
    return butter(BUTTER_ORDER, BUTTER_CUTOFF, btype="low", output="sos")


def local_phase(contact: np.ndarray) -> np.ndarray:
    """Local motion phase vectors of block functions ``contact`` (..., T) -> (..., T, 2).

    1. eq 3.1: z-score in a 30-frame window centred at t (t-15 .. t+14, edge values
       repeated beyond the clip; population std, set to 1 where it is 0);
    2. eq 3.2: causal 3rd-order Butterworth low-pass (cut-off 0.1 x Nyquist), zero
       initial state (``sosfilt``);
    3. eq 3.3: [sin(G_B) * dsin, cos(G_B) * dcos] with d(t) = f(t) - f(t-1) and d(0) = 0.
    """
    G = np.asarray(contact, dtype=np.float64)
    half = PHASE_WINDOW // 2
    pad = [(0, 0)] * (G.ndim - 1) + [(half, PHASE_WINDOW - half - 1)]
    padded = np.pad(G, pad, mode="edge")
    win = np.lib.stride_tricks.sliding_window_view(padded, PHASE_WINDOW, axis=-1)
    mean = win.mean(axis=-1)
    std = win.std(axis=-1)
    std = np.where(std == 0, 1.0, std)
    g_norm = (G - mean) / std
    g_b = sosfilt(butter_sos(), g_norm, axis=-1)
    s, c = np.sin(g_b), np.cos(g_b)
    ds = np.diff(s, axis=-1, prepend=s[..., :1])
    dc = np.diff(c, axis=-1, prepend=c[..., :1])
    return np.stack([s * ds, c * dc], axis=-1)


# ----------------------------------------------------------------------------------
# Costs (eq 3.4, 3.5)
# ----------------------------------------------------------------------------------


def position_cost(target_pos: np.ndarray, joint_pos: np.ndarray) -> np.ndarray:
    return target_pos - joint_pos


def rotation_cost(target_rot: np.ndarray, joint_rot: np.ndarray) -> np.ndarray:
    """(..., 3): angle/pi between the side (x), up (y) and forward (z) axes.

    Rotation matrices hold the axes as columns; side = up x forward.
    """
    dots = np.einsum("...ij,...ij->...j", target_rot, joint_rot)
    return np.arccos(np.clip(dots, -1.0, 1.0)) / np.pi


def rotation_cost_from_vectors(t_fwd, t_up, fwd, up) -> np.ndarray:
    """Same as :func:`rotation_cost` from (possibly unnormalised) forward/up vectors."""

    def frame(f, u):
        f = f / np.linalg.norm(f, axis=-1, keepdims=True)
        u = u / np.linalg.norm(u, axis=-1, keepdims=True)
        return np.stack([np.cross(u, f), u, f], axis=-1)

    return rotation_cost(frame(t_fwd, t_up), frame(fwd, up))


# ----------------------------------------------------------------------------------
# Assembly
# ----------------------------------------------------------------------------------


def assemble(rig, sim: dict, dtype=np.float32) -> np.ndarray:
    """Feature frames (B, T, width) from a :func:`simulate.simulate` result."""
    pos, rot = sim["pos"], sim["rot"]
    B, T, J = pos.shape[:3]
    key = rig.key_joints
    lay = layout(rig)
    sl = slices(lay)
    out = np.empty((B, T, lay["width"]), dtype=np.float64)

    contact = sim["contact"].astype(np.float64)  # (B, T, K)
    phase = local_phase(np.swapaxes(contact, 1, 2))  # (B, K, T, 2)
    out[..., sl["phase"]] = np.swapaxes(phase, 1, 2).reshape(B, T, 2 * K)
    out[..., sl["pos"]] = pos.reshape(B, T, 3 * J)
    fwd_up = np.concatenate([rot[..., :, 2], rot[..., :, 1]], axis=-1)  # (B, T, J, 6)
    out[..., sl["rot"]] = fwd_up.reshape(B, T, 6 * J)
    prev = np.concatenate([np.broadcast_to(sim["rest_pos"], (B, 1, J, 3)), pos[:, :-1]], axis=1)
    out[..., sl["vel"]] = ((pos - prev) * FPS).reshape(B, T, 3 * J)
    tpos, trot = sim["target_pos"], sim["target_rot"]
    out[..., sl["pos_cost"]] = position_cost(tpos, pos[:, :, key]).reshape(B, T, 3 * K)
    out[..., sl["rot_cost"]] = rotation_cost(trot, rot[:, :, key]).reshape(B, T, 3 * K)
    out[..., sl["target_pos"]] = tpos.reshape(B, T, 3 * K)
    t_fwd_up = np.concatenate([trot[..., :, 2], trot[..., :, 1]], axis=-1)
    out[..., sl["target_rot"]] = t_fwd_up.reshape(B, T, 6 * K)
    out[..., sl["contact"]] = contact
    out[..., sl["dof"]] = sim["q"]
    return out.astype(dtype)
