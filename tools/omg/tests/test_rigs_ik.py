"""Rigs match spec §3.1; the IK reaches reachable targets smoothly."""

import numpy as np
import pytest

from tools.omg.ik import DT, HandIK, IKParams
from tools.omg.rigs import DEFAULT_RIGS, RIG_SPECS, build_rig, forward_kinematics, rest_positions
from tools.omg.targets import N_POINTS, spawn_points

SPEC = {"R1": (31, 0.175), "R2": (31, 0.191), "R3": (29, 0.189), "R4": (24, 0.210), "R5": (32, 0.169)}


@pytest.mark.parametrize("name", DEFAULT_RIGS)
def test_rig_matches_spec(name):
    rig = build_rig(name)
    joints, bone = SPEC[name]
    assert rig.n_joints == joints == RIG_SPECS[name]["joints"]
    assert rig.mean_bone_length() == pytest.approx(bone, abs=1e-9)
    # Parents come before children; exactly one root.
    assert (rig.parents[1:] < np.arange(1, joints)).all() and rig.parents[0] == -1
    assert (rig.lower <= 0).all() and (rig.upper >= 0).all(), "rest pose (q = 0) must be inside the limits"
    assert 1.6 < rig.meta["height_m"] < 2.1
    # Rest pose: feet on the ground, symmetric about x = 0.
    rest = rest_positions(rig)
    assert rest[:, 1].min() == pytest.approx(0.02, abs=1e-6)
    assert rest[rig.key_joints[0], 0] == pytest.approx(-rest[rig.key_joints[1], 0])


def test_rigs_differ_in_topology():
    counts = {n: build_rig(n).n_joints for n in DEFAULT_RIGS}
    assert len(set(counts.values())) >= 4


def test_forward_kinematics_rest_and_rotation():
    rig = build_rig("R3")
    P, G = forward_kinematics(rig, np.zeros((1, rig.n_dofs)))
    assert np.allclose(P[0], rest_positions(rig))
    assert np.allclose(G[0], np.eye(3))
    q = np.random.default_rng(1).uniform(rig.lower, rig.upper, size=(4, rig.n_dofs))
    P, G = forward_kinematics(rig, q)
    # Bone lengths are preserved and rotations stay orthonormal.
    for j, p in enumerate(rig.parents):
        if p >= 0:
            assert np.allclose(np.linalg.norm(P[:, j] - P[:, p], axis=-1), np.linalg.norm(rig.offsets[j]))
    assert np.allclose(G @ np.swapaxes(G, -1, -2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(G), 1.0)


def test_jacobian_matches_finite_differences():
    rig = build_rig("R1")
    ik = HandIK(rig)
    q = np.random.default_rng(2).uniform(rig.lower, rig.upper, size=(1, rig.n_dofs)) * 0.5
    P, G, axes = forward_kinematics(rig, q, with_axes=True)
    J = ik.jacobian(P, G, axes)[0]
    eps = 1e-6
    for d in range(rig.n_dofs):
        dq = np.zeros_like(q)
        dq[0, d] = eps
        P2, _ = forward_kinematics(rig, q + dq)
        num = (P2[0, rig.key_joints[:2]] - P[0, rig.key_joints[:2]]) / eps
        assert np.allclose(J[[0, 1, 2], d], num[0], atol=1e-5)
        assert np.allclose(J[[6, 7, 8], d], num[1], atol=1e-5)


@pytest.mark.parametrize("name", DEFAULT_RIGS)
def test_ik_reaches_reachable_targets(name):
    """Front spawn points at 0.35 m, middle levels: both hands within 3 cm (contact: 10 cm)."""
    rig = build_rig(name)
    rest = rest_positions(rig)
    pts = spawn_points(0.35, rest[0, 1])
    # Per level 1..3: left hand at 45 deg (front-left), right hand at -45 deg (front-right).
    left = [pts[level * 8 + 1] for level in (1, 2, 3)]
    right = [pts[level * 8 + 7] for level in (1, 2, 3)]
    t_pos = np.stack([np.stack(left), np.stack(right)], axis=1)  # (3, 2, 3)
    t_rot = np.broadcast_to(np.eye(3), (3, 2, 3, 3))
    ik = HandIK(rig)
    q = np.zeros((3, rig.n_dofs))
    v = np.zeros_like(q)
    for _ in range(120):  # 2 s
        q, v = ik.step(q, v, t_pos, t_rot)
    P, G = forward_kinematics(rig, q)
    err = np.linalg.norm(P[:, rig.key_joints[:2]] - t_pos, axis=-1)
    assert err.max() < 0.03, err
    assert np.abs(v).max() < 0.5, "should have come to rest"


def test_ik_respects_velocity_acceleration_and_joint_limits():
    rig = build_rig("R2")
    p = IKParams()
    rest = rest_positions(rig)
    pts = spawn_points(0.7, rest[0, 1])
    rng = np.random.default_rng(3)
    B = 8
    ids = rng.choice(N_POINTS, size=(B, 2))
    t_pos = pts[ids]
    from scipy.spatial.transform import Rotation

    t_rot = Rotation.random(2 * B, random_state=rng).as_matrix().reshape(B, 2, 3, 3)
    ik = HandIK(rig, p)
    q = np.zeros((B, rig.n_dofs))
    v = np.zeros_like(q)
    qs = [q]
    for _ in range(90):
        q, v = ik.step(q, v, t_pos, t_rot)
        assert (q >= rig.lower - 1e-12).all() and (q <= rig.upper + 1e-12).all()
        qs.append(q)
    qs = np.stack(qs, axis=1)
    vel = np.diff(qs, axis=1) / DT
    acc = np.diff(vel, axis=1) / DT
    assert np.abs(vel).max() <= p.v_max + 1e-9
    # Acceleration bound up to the last frame's discretisation at a joint limit.
    assert np.abs(acc).max() <= 1.25 * p.a_max
