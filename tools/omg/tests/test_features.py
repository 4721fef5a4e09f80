"""Feature layout, kinematic consistency, costs and local phases (spec §1.2, §3.3, §3.4)."""

import json

import numpy as np
import pytest
from scipy import signal
from scipy.spatial.transform import Rotation

from tools.omg import features
from tools.omg.generate import main as generate_main
from tools.omg.generate import split_clips
from tools.omg.ik import FPS
from tools.omg.rigs import DEFAULT_RIGS, K, build_rig
from tools.omg.simulate import CONTACT_RADIUS, FRAMES
from tools.omg.targets import CYLINDER_HEIGHT, N_POINTS, RADII, plan_clips, spawn_points


# ---------------------------------------------------------------------------- layout


@pytest.mark.parametrize("name", DEFAULT_RIGS)
def test_layout_sizes_match_spec(name):
    rig = build_rig(name)
    J = rig.n_joints
    lay = features.layout(rig)
    assert K == 4
    sizes = {b["name"]: b["size"] for b in lay["blocks"]}
    assert sizes == {
        "phase": 2 * K, "pos": 3 * J, "rot": 6 * J, "vel": 3 * J, "pos_cost": 3 * K,
        "rot_cost": 3 * K, "target_pos": 3 * K, "target_rot": 6 * K, "contact": K,
        "dof": rig.n_dofs,
    }
    # Spec §1.2 with 6-D target rotation: n = 12J + 17K (440 for R1); contact and the
    # joint angles after it.
    assert lay["model_width"] == 12 * J + 17 * K
    assert lay["width"] == 12 * J + 18 * K + rig.n_dofs
    off = 0
    for b in lay["blocks"]:  # contiguous, in the spec's order
        assert b["offset"] == off
        off += b["size"]
    assert [b["name"] for b in lay["blocks"]][:4] == ["phase", "pos", "rot", "vel"]
    assert all(b["model_input"] for b in lay["blocks"][:-2])
    assert not any(b["model_input"] for b in lay["blocks"][-2:])
    json.dumps(lay)  # serialisable


def test_r1_width_is_440():
    assert features.layout(build_rig("R1"))["model_width"] == 440


def test_data_shapes(sample_data, sample_plans):
    for rig, frames, _ in sample_data.values():
        assert frames.shape == (len(sample_plans), FRAMES, features.layout(rig)["width"])
        assert frames.dtype == np.float32
        assert np.isfinite(frames).all()


# ---------------------------------------------------------------------- kinematics


def _blocks(rig, frames):
    sl = features.slices(features.layout(rig))
    B, T = frames.shape[:2]
    J = rig.n_joints
    f = frames.astype(np.float64)
    return dict(
        pos=f[..., sl["pos"]].reshape(B, T, J, 3),
        fwd=f[..., sl["rot"]].reshape(B, T, J, 6)[..., :3],
        up=f[..., sl["rot"]].reshape(B, T, J, 6)[..., 3:],
        vel=f[..., sl["vel"]].reshape(B, T, J, 3),
        pos_cost=f[..., sl["pos_cost"]].reshape(B, T, K, 3),
        rot_cost=f[..., sl["rot_cost"]].reshape(B, T, K, 3),
        tpos=f[..., sl["target_pos"]].reshape(B, T, K, 3),
        tfwd=f[..., sl["target_rot"]].reshape(B, T, K, 6)[..., :3],
        tup=f[..., sl["target_rot"]].reshape(B, T, K, 6)[..., 3:],
        contact=f[..., sl["contact"]],
        phase=f[..., sl["phase"]].reshape(B, T, K, 2),
    )


def test_velocities_are_finite_differences(sample_data):
    for rig, frames, sim in sample_data.values():
        d = _blocks(rig, frames)
        fd = np.diff(d["pos"], axis=1) * FPS
        assert np.allclose(d["vel"][:, 1:], fd, atol=5e-4)  # float32 positions ~1e-7 m
        assert np.allclose(d["vel"][:, 0], (d["pos"][:, 0] - sim["rest_pos"]) * FPS, atol=5e-4)


def test_forward_and_up_unit_and_orthogonal(sample_data):
    for rig, frames, _ in sample_data.values():
        d = _blocks(rig, frames)
        for f, u in ((d["fwd"], d["up"]), (d["tfwd"], d["tup"])):
            assert np.allclose(np.linalg.norm(f, axis=-1), 1.0, atol=1e-5)
            assert np.allclose(np.linalg.norm(u, axis=-1), 1.0, atol=1e-5)
            assert np.abs(np.sum(f * u, axis=-1)).max() < 1e-5


def test_motion_is_smooth_and_feet_planted(sample_data):
    for rig, frames, sim in sample_data.values():
        d = _blocks(rig, frames)
        speed = np.linalg.norm(d["vel"], axis=-1)
        assert speed.max() < 10.0, "no teleporting joints"
        # Pelvis and legs never move; feet stay at their rest pose.
        legs = [j for j, n in enumerate(rig.joint_names) if "Leg" in n or "Foot" in n or "Toe" in n or n == "Hips"]
        assert np.allclose(d["pos"][:, :, legs], sim["rest_pos"][legs], atol=1e-6)
        assert (d["contact"][..., 2:] == 1).all()


def test_hand_contact_matches_distance(sample_data):
    for rig, frames, _ in sample_data.values():
        d = _blocks(rig, frames)
        dist = np.linalg.norm(d["tpos"] - d["pos"][:, :, rig.key_joints], axis=-1)
        agree = (dist < CONTACT_RADIUS) == (d["contact"] > 0.5)
        # Float32 rounding may flip a flag only within a micrometre of the threshold.
        assert agree[np.abs(dist - CONTACT_RADIUS) > 1e-5].all()


def test_clips_start_and_end_at_rest(sample_data):
    for rig, frames, sim in sample_data.values():
        d = _blocks(rig, frames)
        hands = rig.key_joints[:2]
        assert np.allclose(d["pos"][:, 0, hands], sim["rest_pos"][hands], atol=0.05)
        # Most clips are back at rest by frame 300 (some run out of time on hard targets).
        back = np.linalg.norm(d["pos"][:, -1, hands] - sim["rest_pos"][hands], axis=-1) < CONTACT_RADIUS
        assert back.mean() > 0.7


# ---------------------------------------------------------------------------- costs


def test_costs_zero_at_target():
    rng = np.random.default_rng(0)
    R = Rotation.random(50, random_state=rng).as_matrix()
    p = rng.normal(size=(50, 3))
    assert np.array_equal(features.position_cost(p, p), np.zeros_like(p))
    assert np.allclose(features.rotation_cost(R, R), 0.0, atol=1e-6)
    f, u = R[..., 2], R[..., 1]
    assert np.allclose(features.rotation_cost_from_vectors(f, u, 3 * f, 0.5 * u), 0.0, atol=1e-6)
    # Opposite axes give 1 (angle pi, normalised by pi); a quarter turn about up gives 1/2
    # for side and forward and 0 for up.
    flip = R @ np.diag([-1.0, 1.0, -1.0])
    assert np.allclose(features.rotation_cost(R, flip), [1.0, 0.0, 1.0], atol=1e-6)
    quarter = R @ Rotation.from_euler("y", 90, degrees=True).as_matrix()
    assert np.allclose(features.rotation_cost(R, quarter), [0.5, 0.0, 0.5], atol=1e-6)


def test_costs_in_data_match_definition(sample_data):
    for rig, frames, _ in sample_data.values():
        d = _blocks(rig, frames)
        key_pos = d["pos"][:, :, rig.key_joints]
        assert np.allclose(d["pos_cost"], d["tpos"] - key_pos, atol=1e-5)
        rc = features.rotation_cost_from_vectors(
            d["tfwd"], d["tup"], d["fwd"][:, :, rig.key_joints], d["up"][:, :, rig.key_joints]
        )
        assert np.allclose(d["rot_cost"], rc, atol=2e-3)  # acos is steep near 0
        # Feet sit on their targets: zero cost.
        assert np.abs(d["pos_cost"][..., 2:, :]).max() < 1e-6
        assert np.abs(d["rot_cost"][..., 2:, :]).max() < 1e-3


# --------------------------------------------------------------------------- phases


def reference_phase(G):
    """Independent eq 3.1-3.3: explicit window loop, transfer-function Butterworth."""
    G = np.asarray(G, dtype=float)
    T = len(G)
    norm = np.empty(T)
    for t in range(T):
        idx = [min(max(i, 0), T - 1) for i in range(t - 15, t + 15)]
        w = G[idx]
        sd = w.std()
        norm[t] = (G[t] - w.mean()) / (sd if sd != 0 else 1.0)
    b, a = signal.butter(3, 0.1, btype="lowpass")
    gb = signal.lfilter(b, a, norm)
    s, c = np.sin(gb), np.cos(gb)
    ds = np.concatenate([[0.0], s[1:] - s[:-1]])
    dc = np.concatenate([[0.0], c[1:] - c[:-1]])
    return np.stack([s * ds, c * dc], axis=-1)


def contact_patterns():
    T = 300
    pats = {"never": np.zeros(T), "always": np.ones(T)}
    three = np.zeros(T)
    for start in (50, 130, 210):
        three[start : start + 5] = 1
    pats["three 5-frame contacts"] = three
    hold = np.zeros(T)
    hold[40:60] = 1
    hold[200:] = 1
    pats["contact then return to rest"] = hold
    start_end = np.zeros(T)
    start_end[:10] = 1
    start_end[-3:] = 1
    pats["at both ends"] = start_end
    pats["random"] = (np.random.default_rng(5).random(T) < 0.3).astype(float)
    return pats


@pytest.mark.parametrize("name", list(contact_patterns()))
def test_local_phase_matches_scipy_reference(name):
    G = contact_patterns()[name]
    ours = features.local_phase(G)
    ref = reference_phase(G)
    assert ours.shape == (len(G), 2)
    assert np.allclose(ours, ref, atol=1e-10)
    assert np.array_equal(ours[0], [0.0, 0.0])  # d(0) = 0


def test_local_phase_properties():
    pats = contact_patterns()
    # Constant block functions normalise to 0, so the phase is exactly 0.
    assert np.array_equal(features.local_phase(pats["always"]), np.zeros((300, 2)))
    assert np.array_equal(features.local_phase(pats["never"]), np.zeros((300, 2)))
    th = features.local_phase(pats["three 5-frame contacts"])
    # Spec §3.4 [M]: small, bounded, non-zero only around contacts.
    assert -0.2 < th.min() < 0 < th.max() < 0.25
    assert np.abs(th[:35]).max() == 0.0  # the first contact enters the window at t = 36
    # Batched over leading axes equals one at a time.
    stacked = np.stack([pats["random"], pats["three 5-frame contacts"]])
    assert np.allclose(features.local_phase(stacked)[1], th)


def test_butterworth_coefficients_match_spec():
    sos = features.butter_sos()
    spec = [[0.00289819, 0.00579639, 0.00289819, 1, -0.72654253, 0],
            [1, 1, 0, 1, -1.64755222, 0.73233892]]
    assert np.allclose(sos, spec, atol=1e-7)


def test_phase_block_in_data_matches_contacts(sample_data):
    for rig, frames, _ in sample_data.values():
        d = _blocks(rig, frames)
        for b in range(frames.shape[0]):
            for k in range(K):
                assert np.allclose(d["phase"][b, :, k], reference_phase(d["contact"][b, :, k]), atol=1e-6)


# --------------------------------------------------------------- targets and split


def test_spawn_points():
    for r in RADII:
        pts = spawn_points(r, 1.0)
        assert pts.shape == (N_POINTS, 3) == (40, 3)
        assert np.allclose(np.hypot(pts[:, 0], pts[:, 2]), r)
        levels = np.unique(pts[:, 1].round(9))
        assert len(levels) == 5
        assert np.allclose(np.diff(levels), CYLINDER_HEIGHT / 5)
        assert levels.max() == pytest.approx(1.0 + CYLINDER_HEIGHT / 2)
        angles = np.arctan2(pts[:8, 0], pts[:8, 2])
        assert np.allclose(np.diff(np.unwrap(angles)), 2 * np.pi / 8)


def test_plan_design():
    every = plan_clips(0)
    plans = [p for p in every if p["kind"] == "cylinder"]
    cont = [p for p in every if p["kind"] == "continuous"]
    assert len(plans) == len(cont) == 240 and every[:240] == plans
    full = plan_clips(0, full=True)
    assert sum(p["kind"] == "cylinder" for p in full) == 960
    assert len(plan_clips(0, continuous=5)) == 245
    for p in cont:
        assert p["pairs"] is None and p["reps"] in (1, 2, 3) and len(p["draw_seed"]) == 3
        assert (p["rotations"] is not None) == p["rotate"]
    for p in plans:
        assert len(p["pairs"]) == p["reps"] in (1, 2, 3)
        assert all(0 <= i < 40 for pair in p["pairs"] for i in pair)
        for a, b in p["pairs"]:
            la, ma = divmod(a, 8)
            lb, mb = divmod(b, 8)
            assert la == lb
            assert (ma - mb) % 8 in ((1, 7) if p["mode"] == "adjacent" else (4,))
        assert (p["rotations"] is not None) == p["rotate"]
    # Balanced: each (rotation, reps) group covers all 40 points, 10 per radius/mode pair.
    for rot in (False, True):
        for reps in (1, 2, 3):
            g = [p for p in plans if p["rotate"] == rot and p["reps"] == reps]
            assert len(g) == 40
            combos = [(p["radius"], p["mode"]) for p in g]
            assert all(combos.count(c) == 10 for c in set(combos)) and len(set(combos)) == 4


def test_split_80_10_10():
    s = split_clips(240)
    assert [len(s[k]) for k in ("train", "val", "test")] == [192, 24, 24]
    allc = np.concatenate(list(s.values()))
    assert np.array_equal(np.sort(allc), np.arange(240))
    assert np.array_equal(split_clips(240)["test"], s["test"])


# ------------------------------------------------------------------- determinism


def test_generation_is_deterministic(tmp_path):
    args = ["--rigs", "R4", "--clips", "10", "--batch", "5"]
    generate_main(["--out", str(tmp_path / "a"), "--seed", "3"] + args)
    generate_main(["--out", str(tmp_path / "b"), "--seed", "3"] + args)
    generate_main(["--out", str(tmp_path / "c"), "--seed", "4"] + args)
    for f in ("train.npy", "val.npy", "test.npy", "clips.json", "layout.json", "rig.json"):
        assert (tmp_path / "a/R4" / f).read_bytes() == (tmp_path / "b/R4" / f).read_bytes(), f
    a = np.load(tmp_path / "a/R4/train.npy")
    c = np.load(tmp_path / "c/R4/train.npy")
    assert a.shape == c.shape and not np.array_equal(a, c)
    lay = json.loads((tmp_path / "a/R4/layout.json").read_text())
    assert lay["width"] == a.shape[-1] and lay["frames_per_clip"] == a.shape[1] == 300
    clips = json.loads((tmp_path / "a/R4/clips.json").read_text())
    assert sum(c["split"] == "train" for c in clips) == a.shape[0]
