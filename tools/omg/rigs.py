"""Procedurally built humanoid rigs and batched forward kinematics.

Coordinate frame (root space): right-handed, metres, y up, the character faces +z,
so +x is the character's left. The root joint (pelvis) sits above the pivot (the
origin, on the ground between the feet) and never moves.

Every joint's rest orientation is the identity, so at rest each joint's forward is
+z and its up is +y. A joint's local rotation is intrinsic Euler x-y-z,
``R_local = Rx(q_x) @ Ry(q_y) @ Rz(q_z)``, over whichever of the three angles the joint
has as degrees of freedom (DOF); the others stay 0. Joints without DOF (legs, neck,
head, end sites) keep their rest rotation: pelvis and feet are fixed (spec §3.7).

At rest the three local axes are: x = the character's left (flexion axis: a positive
x rotation tilts a bone pointing up forward and a bone pointing down backward),
y = vertical (twist of the spine and of a hanging arm), z = forward (side bend,
arm abduction).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Key joints, in this order everywhere (features, costs, phases): K = 4 (spec §1.1).
KEY_JOINT_NAMES = ("LeftHand", "RightHand", "LeftFoot", "RightFoot")
K = len(KEY_JOINT_NAMES)


@dataclass
class Rig:
    """A humanoid rig: hierarchy, rest offsets and per-DOF limits."""

    name: str
    joint_names: list[str]
    parents: np.ndarray  # (J,) int, -1 for the root; parents come before children
    offsets: np.ndarray  # (J, 3) rest offset from the parent (root: from the pivot)
    dof_joint: np.ndarray  # (D,) joint of each DOF
    dof_axis: np.ndarray  # (D,) 0 = x, 1 = y, 2 = z Euler angle
    lower: np.ndarray  # (D,) radians
    upper: np.ndarray  # (D,) radians
    dof_weight: np.ndarray  # (D,) mobility in the weighted IK (1 = arm joint)
    key_joints: np.ndarray  # (K,) joint indices of KEY_JOINT_NAMES
    source: str = ""
    meta: dict = field(default_factory=dict)

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    @property
    def n_dofs(self) -> int:
        return len(self.dof_joint)

    def index(self, name: str) -> int:
        return self.joint_names.index(name)

    def mean_bone_length(self) -> float:
        return float(np.linalg.norm(self.offsets[1:], axis=1).mean())

    def to_json(self) -> dict:
        """Everything the Rust side or a plot needs about the rig."""
        return {
            "name": self.name,
            "source": self.source,
            "joints": self.joint_names,
            "parents": self.parents.tolist(),
            "rest_offsets": np.round(self.offsets, 6).tolist(),
            "rest_positions": np.round(rest_positions(self), 6).tolist(),
            "key_joints": {n: int(j) for n, j in zip(KEY_JOINT_NAMES, self.key_joints)},
            "dofs": [
                {
                    "joint": self.joint_names[j],
                    "axis": "xyz"[a],
                    "lower": round(float(lo), 6),
                    "upper": round(float(hi), 6),
                    "ik_weight": float(w),
                }
                for j, a, lo, hi, w in zip(
                    self.dof_joint, self.dof_axis, self.lower, self.upper, self.dof_weight
                )
            ],
            "mean_bone_length_m": round(self.mean_bone_length(), 6),
            **self.meta,
        }


# ----------------------------------------------------------------------------------
# Rig templates (spec §3.1: joint counts 31/31/29/24/32, mean bone lengths
# 0.175/0.191/0.189/0.210/0.169 m). Lengths below are proportions in metres for a
# ~1.75 m human; each rig is then scaled uniformly so its mean bone length matches.
# ----------------------------------------------------------------------------------

RIG_SPECS = {
    "R1": dict(
        source="Mixamo-like", joints=31, mean_bone=0.175, n_spine=4, n_neck=2,
        head_end=True, arm=("Clavicle", "UpperArm", "ForeArm", "Hand", "Finger", "FingerEnd"),
        leg=("UpLeg", "Leg", "Foot", "Toe", "ToeEnd"),
        pelvis_h=0.98, spine=0.50, neck=0.12, head=0.12, head_top=0.17,
        clav=(0.03, 0.02, 0.0), shoulder_w=0.14, upper_arm=0.28, forearm=0.26,
        hand=0.09, finger=0.05, finger_end=0.04, hip_w=0.09, thigh=0.44, shin=0.42,
        ankle_h=0.08, foot=0.14, toe_end=0.05, arm_abd=0.25,
    ),
    "R2": dict(
        source="monster-like: long arms, short legs, wide shoulders", joints=31,
        mean_bone=0.191, n_spine=3, n_neck=3, head_end=True,
        arm=("Clavicle", "UpperArm", "ForeArm", "Hand", "Finger", "FingerEnd"),
        leg=("UpLeg", "Leg", "Foot", "Toe", "ToeEnd"),
        pelvis_h=0.88, spine=0.52, neck=0.16, head=0.12, head_top=0.16,
        clav=(0.05, 0.03, 0.0), shoulder_w=0.19, upper_arm=0.33, forearm=0.32,
        hand=0.10, finger=0.06, finger_end=0.05, hip_w=0.12, thigh=0.40, shin=0.38,
        ankle_h=0.09, foot=0.16, toe_end=0.06, arm_abd=0.30,
    ),
    "R3": dict(
        source="Unity-default-like", joints=29, mean_bone=0.189, n_spine=3, n_neck=1,
        head_end=True, arm=("Clavicle", "UpperArm", "ForeArm", "Hand", "Finger", "FingerEnd"),
        leg=("UpLeg", "Leg", "Foot", "Toe", "ToeEnd"),
        pelvis_h=1.00, spine=0.48, neck=0.10, head=0.12, head_top=0.18,
        clav=(0.03, 0.02, 0.0), shoulder_w=0.15, upper_arm=0.29, forearm=0.27,
        hand=0.09, finger=0.05, finger_end=0.04, hip_w=0.10, thigh=0.45, shin=0.43,
        ankle_h=0.08, foot=0.15, toe_end=0.05, arm_abd=0.22,
    ),
    "R4": dict(
        source="NSM-like", joints=24, mean_bone=0.210, n_spine=2, n_neck=1,
        head_end=True, arm=("Clavicle", "UpperArm", "ForeArm", "Hand", "HandEnd"),
        leg=("UpLeg", "Leg", "Foot", "Toe"),
        pelvis_h=0.96, spine=0.46, neck=0.12, head=0.12, head_top=0.18,
        clav=(0.04, 0.03, 0.0), shoulder_w=0.14, upper_arm=0.27, forearm=0.25,
        hand=0.08, finger=0.10, finger_end=0.0, hip_w=0.10, thigh=0.43, shin=0.42,
        ankle_h=0.08, foot=0.14, toe_end=0.0, arm_abd=0.20,
    ),
    "R5": dict(
        source="game-studio-like, long spine chain", joints=32, mean_bone=0.169,
        n_spine=5, n_neck=2, head_end=True,
        arm=("Clavicle", "UpperArm", "ForeArm", "Hand", "Finger", "FingerEnd"),
        leg=("UpLeg", "Leg", "Foot", "Toe", "ToeEnd"),
        pelvis_h=1.02, spine=0.52, neck=0.12, head=0.11, head_top=0.17,
        clav=(0.03, 0.02, 0.0), shoulder_w=0.15, upper_arm=0.29, forearm=0.27,
        hand=0.09, finger=0.05, finger_end=0.04, hip_w=0.09, thigh=0.46, shin=0.44,
        ankle_h=0.08, foot=0.15, toe_end=0.05, arm_abd=0.25,
    ),
}

DEFAULT_RIGS = ("R1", "R2", "R3", "R4", "R5")

# Total spine range (radians, split evenly over the spine joints that carry DOF).
SPINE_FLEX = (-0.35, 1.25)  # x: back / forward
SPINE_TWIST = (-1.00, 1.00)  # y
SPINE_BEND = (-0.55, 0.55)  # z
# Left-arm limits per DOF (the right arm mirrors them: x kept, y and z negated).
LEFT_ARM_LIMITS = {
    "Clavicle": {1: (-0.30, 0.30), 2: (-0.15, 0.45)},
    "UpperArm": {0: (-2.90, 0.80), 1: (-1.20, 1.20), 2: (-0.70, 2.40)},
    "ForeArm": {0: (-2.50, 0.0), 1: (-1.30, 1.30)},
    "Hand": {0: (-1.20, 1.20), 2: (-0.40, 0.50)},
}
IK_WEIGHT = {"Spine": 0.25, "Clavicle": 0.3, "UpperArm": 1.0, "ForeArm": 1.0, "Hand": 1.0}


def build_rig(name: str) -> Rig:
    """Build rig ``name`` (one of RIG_SPECS) and scale it to its mean bone length."""
    s = RIG_SPECS[name]
    names: list[str] = []
    parents: list[int] = []
    offsets: list[np.ndarray] = []

    def add(jname: str, parent: int, off) -> int:
        names.append(jname)
        parents.append(parent)
        offsets.append(np.asarray(off, dtype=np.float64))
        return len(names) - 1

    pelvis = add("Hips", -1, (0.0, s["pelvis_h"], 0.0))
    prev = pelvis
    spine_joints = []
    for i in range(s["n_spine"]):
        # A slight backward curve in the lower spine, forward in the upper.
        z = (-0.01 if i < s["n_spine"] // 2 else 0.005) * (4 / s["n_spine"])
        prev = add(f"Spine{i}", prev, (0.0, s["spine"] / s["n_spine"], z))
        spine_joints.append(prev)
    chest = prev
    for i in range(s["n_neck"]):
        prev = add(f"Neck{i}", prev, (0.0, s["neck"] / s["n_neck"], 0.01 / s["n_neck"]))
    head = add("Head", prev, (0.0, s["head"], 0.0))
    if s["head_end"]:
        add("HeadTop", head, (0.0, s["head_top"], 0.01))

    abd = s["arm_abd"]
    down = np.array([np.sin(abd), -np.cos(abd), 0.0])  # left arm direction at rest
    for side, sx in (("Left", 1.0), ("Right", -1.0)):
        mirror = np.array([sx, 1.0, 1.0])
        prev = chest
        for part in s["arm"]:
            if part == "Clavicle":
                off = np.array(s["clav"])
            elif part == "UpperArm":
                off = np.array([s["shoulder_w"], 0.0, 0.0])
            elif part == "ForeArm":
                off = down * s["upper_arm"]
            elif part == "Hand":
                off = down * s["forearm"]
            elif part in ("Finger", "HandEnd"):
                off = down * (s["hand"] if part == "Finger" else s["hand"] + s["finger"])
            elif part == "FingerEnd":
                off = down * (s["finger"] + s["finger_end"])
            else:
                raise ValueError(part)
            prev = add(side + part, prev, off * mirror)
        prev = pelvis
        for part in s["leg"]:
            if part == "UpLeg":
                off = np.array([s["hip_w"], -0.06, 0.0])
            elif part == "Leg":
                off = np.array([0.0, -s["thigh"], 0.01])
            elif part == "Foot":
                off = np.array([0.0, -s["shin"], -0.02])
            elif part == "Toe":
                off = np.array([0.0, -s["ankle_h"] + 0.02, s["foot"]])
            elif part == "ToeEnd":
                off = np.array([0.0, 0.0, s["toe_end"]])
            else:
                raise ValueError(part)
            prev = add(side + part, prev, off * mirror)

    offsets_arr = np.stack(offsets)
    # The feet's soles: put the lowest joint (toe) on the ground before scaling.
    J = len(names)
    if J != s["joints"]:
        raise AssertionError(f"{name}: built {J} joints, spec says {s['joints']}")
    parents_arr = np.array(parents, dtype=np.int64)
    scale = s["mean_bone"] / np.linalg.norm(offsets_arr[1:], axis=1).mean()
    offsets_arr *= scale
    # Put the lowest joint (ankle or toe) 2 cm above the ground; the root's offset
    # from the pivot is not a bone, so this keeps the mean bone length.
    tmp = Rig(name, names, parents_arr, offsets_arr, *(np.zeros(0),) * 5, np.zeros(0))
    offsets_arr[0, 1] -= rest_positions(tmp)[:, 1].min() - 0.02

    # Degrees of freedom.
    dof_joint, dof_axis, lower, upper, weight = [], [], [], [], []
    n_sp = len(spine_joints)
    for j in spine_joints:
        for axis, (lo, hi) in ((0, SPINE_FLEX), (1, SPINE_TWIST), (2, SPINE_BEND)):
            dof_joint.append(j)
            dof_axis.append(axis)
            lower.append(lo / n_sp)
            upper.append(hi / n_sp)
            weight.append(IK_WEIGHT["Spine"] / n_sp * 3)
    for side, sgn in (("Left", 1.0), ("Right", -1.0)):
        for part, lims in LEFT_ARM_LIMITS.items():
            j = names.index(side + part)
            for axis, (lo, hi) in lims.items():
                if sgn < 0 and axis in (1, 2):
                    lo, hi = -hi, -lo
                dof_joint.append(j)
                dof_axis.append(axis)
                lower.append(lo)
                upper.append(hi)
                weight.append(IK_WEIGHT[part])

    key = np.array([names.index(n) for n in KEY_JOINT_NAMES], dtype=np.int64)
    rig = Rig(
        name=name,
        joint_names=names,
        parents=parents_arr,
        offsets=offsets_arr,
        dof_joint=np.array(dof_joint, dtype=np.int64),
        dof_axis=np.array(dof_axis, dtype=np.int64),
        lower=np.array(lower),
        upper=np.array(upper),
        dof_weight=np.array(weight),
        key_joints=key,
        source=s["source"],
    )
    rest = rest_positions(rig)
    rig.meta = {
        "height_m": round(float(rest[:, 1].max()), 4),
        "pelvis_height_m": round(float(rest[0, 1]), 4),
        "scale": round(float(scale), 6),
    }
    return rig


def rest_positions(rig: Rig) -> np.ndarray:
    """Rest joint positions (J, 3); all rest rotations are the identity."""
    pos = np.zeros((len(rig.parents), 3))
    for j, p in enumerate(rig.parents):
        pos[j] = rig.offsets[j] if p < 0 else pos[p] + rig.offsets[j]
    return pos


# ----------------------------------------------------------------------------------
# Batched rotations and forward kinematics
# ----------------------------------------------------------------------------------


def axis_rotation(angle: np.ndarray, axis: int) -> np.ndarray:
    """Rotation matrices (..., 3, 3) about coordinate axis 0/1/2 by ``angle`` (...)."""
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros(angle.shape + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[..., axis, axis] = 1.0
    R[..., i, i] = c
    R[..., j, j] = c
    R[..., i, j] = -s
    R[..., j, i] = s
    return R


def euler_angles(rig: Rig, q: np.ndarray) -> np.ndarray:
    """Scatter DOF values q (B, D) into per-joint Euler angles (B, J, 3)."""
    eul = np.zeros((q.shape[0], rig.n_joints, 3))
    eul[:, rig.dof_joint, rig.dof_axis] = q
    return eul


def forward_kinematics(rig: Rig, q: np.ndarray, with_axes: bool = False):
    """Global positions (B, J, 3) and rotations (B, J, 3, 3) for DOF values q (B, D).

    With ``with_axes`` also returns the world axis of every DOF (B, D, 3), i.e. the
    axis the Euler angle rotates about given the angles applied before it.
    """
    eul = euler_angles(rig, q)
    Rx = axis_rotation(eul[..., 0], 0)
    Ry = axis_rotation(eul[..., 1], 1)
    Rz = axis_rotation(eul[..., 2], 2)
    Rxy = Rx @ Ry
    Rloc = Rxy @ Rz
    B, J = q.shape[0], rig.n_joints
    G = np.empty((B, J, 3, 3))
    P = np.empty((B, J, 3))
    Gpar = np.empty((B, J, 3, 3))
    eye = np.broadcast_to(np.eye(3), (B, 3, 3))
    for j, p in enumerate(rig.parents):
        if p < 0:
            Gpar[:, j] = eye
            P[:, j] = rig.offsets[j]
        else:
            Gpar[:, j] = G[:, p]
            P[:, j] = P[:, p] + G[:, p] @ rig.offsets[j]
        G[:, j] = Gpar[:, j] @ Rloc[:, j]
    if not with_axes:
        return P, G
    # Axis of Euler angle a of joint j: Gpar @ (Rx, Rx Ry)[..] column a.
    ax_x = Gpar[..., :, 0]
    ax_y = (Gpar @ Rx)[..., :, 1]
    ax_z = (Gpar @ Rxy)[..., :, 2]
    axes = np.stack([ax_x, ax_y, ax_z], axis=2)  # (B, J, 3 euler, 3 xyz)
    dof_axes = axes[:, rig.dof_joint, rig.dof_axis]  # (B, D, 3)
    return P, G, dof_axes


def ancestor_mask(rig: Rig, joints) -> np.ndarray:
    """(len(joints), D) bool: DOF d moves joint e (d's joint is e or an ancestor of e)."""
    out = np.zeros((len(joints), rig.n_dofs), dtype=bool)
    for i, e in enumerate(joints):
        chain = set()
        j = int(e)
        while j >= 0:
            chain.add(j)
            j = int(rig.parents[j])
        out[i] = [int(dj) in chain for dj in rig.dof_joint]
    return out
