"""Committed OMG models (models/omg/*/): config consistency, and the NumPy forward pass
(tools/omg/omg_np.py) reproduces the committed PyTorch reference outputs. No PyTorch."""

import json
from pathlib import Path

import numpy as np
import pytest

from tools.omg.omg_np import NumpyOMG, costs_from_frame

ROOT = Path(__file__).resolve().parents[3]
MODEL_DIRS = sorted(p.parent for p in (ROOT / "models" / "omg").glob("*/config.json"))
IDS = [p.name for p in MODEL_DIRS]


def test_models_present():
    # the committed set: tiny FE, small FE, small RBF-CAT and tiny FS on R1, the Frozen and Raw
    # transfers on R4; all joint-velocity models (docs/omg-joint-velocity.md)
    assert {"tiny_fe_r1", "small_fe_r1", "small_rbfcat_r1", "tiny_fs_r1", "tiny_fe_r4_frozen",
            "tiny_fe_r4_raw"} <= set(IDS)


@pytest.fixture(scope="module", params=MODEL_DIRS, ids=IDS)
def model(request):
    return NumpyOMG(request.param), request.param


def _lin(i, o):
    return i * o + o


def test_config_slices_sizes(model):
    m, _ = model
    cfg = m.cfg
    J, K, n = cfg["J"], cfg["K"], cfg["model_width"]
    s = cfg["slices"]
    order = ["phase", "pos", "rot", "vel", "pos_cost", "rot_cost", "target_pos", "target_rot"]
    sizes = dict(phase=2 * K, pos=3 * J, rot=6 * J, vel=3 * J, pos_cost=3 * K, rot_cost=3 * K,
                 target_pos=3 * K, target_rot=6 * K)
    off = 0
    for b in order:
        assert s[b] == [off, off + sizes[b]], b
        off += sizes[b]
    assert off == n == 12 * J + 17 * K
    assert s["pose"] == [s["pos"][0], s["vel"][1]]
    assert s["cost"] == [s["pos_cost"][0], s["rot_cost"][1]]
    assert s["target"] == [s["target_pos"][0], s["target_rot"][1]]
    assert len(cfg["key_joint_indices"]) == K == 4
    sz = cfg["sizes"]
    L = sz["latent"]
    o = cfg["out_slices"]
    assert o["dphase"] == [0, 2 * K] and o["z"] == [2 * K, 2 * K + L] and o["cost"] == [2 * K + L, 2 * K + L + 6 * K]
    assert cfg["pose_form"] == "dof_velocity"
    D = sz["dof"]
    assert o["u"] == [2 * K, 2 * K + D] and len(cfg["controller"]["skeleton"]["dofs"]) == D
    assert cfg["phase_update"]["a"] == 0.9
    assert cfg["mode"] in ("grounded", "faithful")


def test_tensor_shapes_params_macs(model):
    m, _ = model
    cfg, t = m.cfg, m.t
    J, K = cfg["J"], cfg["K"]
    sz = cfg["sizes"]
    h, L, Hc, H, G, k = sz["ae_hidden"], sz["latent"], sz["cost_hidden"], sz["expert_hidden"], sz["gate_hidden"], sz["experts"]
    C = sz["clusters"] if cfg["variant"] == "RBF-CAT" else 0
    dout = 2 * K + L + 6 * K
    cols = cfg.get("encoder_columns")
    enc_in = 12 * J if cols is None else len(cols)
    assert sz.get("enc_in", 12 * J) == enc_in
    dims = dict(enc=(enc_in, h, h, L), dec=(L, h, h, sz["dof"]), cost=(15 * K, Hc, Hc, Hc), gate=(2 * K, G, G, k))
    params = macs = 0
    for name, d in dims.items():
        for i in range(3):
            assert t[f"{name}.{i}.w"].shape == (d[i + 1], d[i])
            assert t[f"{name}.{i}.b"].shape == (d[i + 1],)
            params += _lin(d[i], d[i + 1])
            macs += d[i] * d[i + 1]
    ex = [(C + L + Hc, H), (C + H, H), (C + H, dout)]
    for i, (a, b) in enumerate(ex):
        assert t[f"experts.w{i}"].shape == (k, a, b)
        assert t[f"experts.b{i}"].shape == (k, b)
        params += k * _lin(a, b)
        macs += k * a * b
    if C:
        assert t["rbf.centres"].shape == (C, L) and t["rbf.scales"].shape == (C,)
        params += C * L + C
        macs += C * L
    assert params == cfg["params"]
    assert macs == cfg["macs_per_frame"]["total"]
    n_tensor = sum(v.size for kk, v in t.items() if not kk.startswith("norm."))
    assert n_tensor == params


def test_normalisation(model):
    m, _ = model
    cfg = m.cfg
    n = cfg["model_width"]
    assert m.mean.shape == (n,) and m.std.shape == (n,)
    assert np.all(m.std > 0)
    np.testing.assert_allclose(m.mean, cfg["normalisation"]["mean"], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(m.std, cfg["normalisation"]["std"], rtol=1e-6, atol=1e-7)
    D = cfg["sizes"]["dof"]
    assert m.dof_mean.shape == (D,) and np.all(m.dof_std > 0)
    np.testing.assert_allclose(m.dof_std, cfg["normalisation"]["dof_std"], rtol=1e-6, atol=1e-9)


def test_skeleton_is_the_rigs(model):
    """The controller's skeleton is the generator's rig (rig.json beside the model)."""
    m, d = model
    rig = json.loads((d / "rig.json").read_text())
    sk = m.cfg["controller"]["skeleton"]
    assert sk["parents"] == rig["parents"] and sk["offsets"] == rig["rest_offsets"]
    assert [(rig["joints"][x["joint"]], "xyz"[x["axis"]], x["lower"], x["upper"]) for x in sk["dofs"]] == [
        (x["joint"], x["axis"], x["lower"], x["upper"]) for x in rig["dofs"]]
    assert m.cfg["controller"]["fps"] == 60 and m.cfg["controller"]["a_max"] == 5.0


def _refs(d):
    with np.load(d / "references.npz") as z:
        return {k: z[k] for k in z.files}


# The references are the stored weights run in float64 by PyTorch, saved as float32
# (tools/omg/train/references.py). The float64 NumPy forward is a second implementation of
# that model and agrees to the files' own rounding; the float32 one adds float32 arithmetic.
@pytest.mark.parametrize("dtype,rtol,atol", [(np.float64, 1.2e-7, 1e-9), (np.float32, 0, 2e-5)])
def test_one_step_matches_reference(model, dtype, rtol, atol):
    _, d = model
    m = NumpyOMG(d, dtype=dtype)
    r = _refs(d)
    x = r["inputs"]
    y = m.step(x.reshape(-1, x.shape[-1])).reshape(x.shape[:2] + (-1,))
    np.testing.assert_allclose(y, r["one_step"], rtol=rtol, atol=atol)


@pytest.mark.parametrize("dtype,rtol,atol", [(np.float64, 1.2e-7, 1e-7), (np.float32, 0, 5e-4)])
def test_grounded_rollout_matches_reference(model, dtype, rtol, atol):
    """300 frames fed back: float64 NumPy stays within the files' rounding; float32 NumPy
    departs by float32 rounding amplified in sensitive stretches."""
    _, d = model
    m = NumpyOMG(d, dtype=dtype)
    r = _refs(d)
    ro = r["rollout_grounded"]
    assert ro.shape[1] == 300
    out, qs = m.rollout_dof(r["inputs"][:, 0], r["rollout_q0"], r["rollout_v0"], r["rollout_targets"])
    np.testing.assert_array_equal(out[:, 0], ro[:, 0])
    np.testing.assert_allclose(out, ro, rtol=rtol, atol=atol)
    np.testing.assert_allclose(qs, r["rollout_dof"], rtol=rtol, atol=atol)
    # forward kinematics keeps every bone and every joint limit
    from tools.omg.metrics import bone_lengths, rest_bone_lengths

    sk = m.cfg["controller"]["skeleton"]
    pos = out[:, :, slice(*m.cfg["slices"]["pos"])].reshape(out.shape[0], 300, -1, 3)
    err = np.abs(bone_lengths(pos, sk["parents"]) - rest_bone_lengths(sk["offsets"], sk["parents"]))
    # frame 0 is the stored (float32) start frame; the rest come from forward kinematics
    assert err[:, 0].max() < 2e-6
    assert err[:, 1:].max() < (1e-9 if dtype == np.float64 else 1e-5)
    # float32 joint angles clamped to a limit sit within one float32 rounding of it
    tol = 1e-12 if dtype == np.float64 else 1e-6
    assert (qs >= m.rig.lower - tol).all() and (qs <= m.rig.upper + tol).all()
    # the rollout's cost block is the recomputed one (from float32-stored frames here: acos
    # near 0 amplifies a 1e-7 difference of a dot product to about 1e-4)
    np.testing.assert_allclose(costs_from_frame(ro[:, 1:].astype(np.float64), m.cfg),
                               ro[:, 1:, slice(*m.cfg["slices"]["cost"])], atol=1e-3)


def test_weights_storage_type_is_recorded(model):
    """config.json names the layer weights' storage type; the normalisation stays float32."""
    _, d = model
    from safetensors import safe_open

    want = {"float32": "F32", "float16": "F16"}[json.loads((d / "config.json").read_text())["weights_dtype"]]
    with safe_open(str(d / "model.safetensors"), "np") as f:
        for k in f.keys():
            dt = f.get_slice(k).get_dtype()
            assert dt == ("F32" if k.startswith("norm.") else want), k


def test_grounded_costs_agree_with_data(model):
    """On ground-truth frames the grounded cost formula gives the data's cost block."""
    m, d = model
    x = _refs(d)["inputs"].astype(np.float64)
    np.testing.assert_allclose(costs_from_frame(x, m.cfg), x[..., slice(*m.cfg["slices"]["cost"])], atol=1e-5)


def test_config_records_reproduction(model):
    m, d = model
    tr = m.cfg["training"]
    assert tr["command"].startswith("python3 -m tools.omg.train")
    assert isinstance(tr["seed"], int)
    assert (d / "README.md").exists()
    json.dumps(m.cfg)
