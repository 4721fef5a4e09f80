"""The reference outputs of a trained OMG model directory, and its weights' storage type.

A model directory carries one ``references.npz`` (compressed: smooth motion deflates to about
half) of float32 arrays:

* ``inputs`` (clips, frames, n): raw held-out test frames, the first frames of some clips;
* ``rollout_targets`` (clips, 300, 9K): the target block of every frame of those clips;
* ``one_step`` (clips, frames, n): the model's raw outputs for ``inputs``;
* ``rollout_grounded`` (clips, 300, n): the grounded rollout from frame 0 of each clip,
  driven by ``rollout_targets`` (targets overwritten, costs recomputed every frame).

The outputs are PyTorch's, computed in float64 from the weights exactly as stored in
``model.safetensors`` and saved as float32 (the storage rounding, 6e-8 of a value, is far
below any tolerance they are checked to).

Float64, not float32: over a 300-frame rollout float32 rounding grows to a few 1e-4 of a
feature's spread, which would hide whether an f64 implementation (host-sim's, NumPy's)
follows the model. No data set is needed: everything comes from the model directory, so
training calls this once its weights are written, and it can be rerun on a committed model.

``--weights float16`` first stores the layer weights as float16 (``norm.mean`` and
``norm.std`` stay float32): half the bytes, a relative rounding of at most 4.9e-4 per weight,
finer than what int16 blobs keep of the larger weights of a row. Training's
``--weights-dtype float16`` does the same at the end of a run, so a model converted here is
byte-identical to one trained with that flag.

    python3 -m tools.omg.train.references models/omg/tiny_fe_r1 models/omg/tiny_fe_r4_frozen
    python3 -m tools.omg.train.references --weights float16 models/omg/small_fe_r1
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

# One thread unless asked otherwise: on a busy 2-core machine two threads ran far slower.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from safetensors.torch import load_file, save_file  # noqa: E402

from .core import Frame, one_step, rollout  # noqa: E402
from .model import OMG  # noqa: E402

DTYPES = {"float32": torch.float32, "float16": torch.float16}


def storage_tensors(tensors: dict, dtype: str) -> dict:
    """``tensors`` as they are stored: layer weights in ``dtype``, normalisation in float32."""
    want = DTYPES[dtype]
    return {
        k: (v.float() if k.startswith("norm.") else v.to(want)).contiguous() for k, v in tensors.items()
    }


def save_weights(tensors: dict, path: Path, dtype: str) -> dict:
    """Writes ``model.safetensors`` whole or not at all (a temporary file renamed over it);
    returns the tensors as stored."""
    stored = storage_tensors(tensors, dtype)
    tmp = path.with_name(path.name + ".tmp")
    save_file(stored, str(tmp))
    os.replace(tmp, path)
    return stored


def load_model(model_dir: Path, dtype=torch.float64) -> tuple[OMG, Frame, dict]:
    """The stored model in ``dtype`` (float64: the references' precision) and its grounded
    feed-back rule."""
    cfg = json.loads((model_dir / "config.json").read_text())
    args = cfg["training"]["args"]
    slices = {k: tuple(v) for k, v in cfg["slices"].items()}
    experts = cfg["sizes"]["experts"]
    model = OMG(slices, variant=cfg["variant"], size=args["size"], k=experts, enc_cols=cfg.get("encoder_columns"),
                pose_form=cfg.get("pose_form", "absolute"), dof=cfg["sizes"].get("dof", 0))
    tensors = load_file(str(model_dir / "model.safetensors"))
    live = model.named_tensors()
    missing = sorted(set(live) - set(tensors))
    if missing:
        raise SystemExit(f"{model_dir / 'model.safetensors'}: missing tensors {missing}")
    model = model.to(dtype).eval()
    live = model.named_tensors()
    with torch.no_grad():
        for name, p in live.items():
            if tuple(tensors[name].shape) != tuple(p.shape):
                raise SystemExit(
                    f"{model_dir / 'model.safetensors'}: {name} has shape {tuple(tensors[name].shape)}, "
                    f"the config wants {tuple(p.shape)}"
                )
            # float16/float32 -> float64 (or float32 -> float32) is exact: the model is the stored one.
            p.copy_(tensors[name].to(dtype))
    mean = tensors["norm.mean"].double()
    std = tensors["norm.std"].double()
    fr = Frame(slices, mean, std, cfg["key_joint_indices"], cfg["J"], "grounded")
    return model, fr, cfg


ARRAYS = ("inputs", "rollout_targets", "one_step", "rollout_grounded")
DOF_ARRAYS = ARRAYS + ("rollout_q0", "rollout_v0", "rollout_dof")


def dof_loop(model_dir: Path, cfg: dict, tensors: dict, dtype=torch.float64):
    """The controller loop of a joint-velocity model (:class:`.loop.DofLoop`) from its
    directory, in ``dtype``."""
    from .fk import RigFK
    from .loop import DofLoop

    c = cfg["controller"]
    sk = c["skeleton"]
    rig = dict(parents=sk["parents"], rest_offsets=sk["offsets"], joints=[str(j) for j in range(len(sk["parents"]))],
               dofs=[dict(joint=str(d["joint"]), axis="xyz"[d["axis"]], lower=d["lower"], upper=d["upper"])
                     for d in sk["dofs"]])
    fk = RigFK(rig, dtype=dtype)
    return DofLoop(cfg["slices"], tensors["norm.mean"].to(dtype), tensors["norm.std"].to(dtype),
                   tensors["norm.dof_mean"].to(dtype), tensors["norm.dof_std"].to(dtype),
                   cfg["key_joint_indices"], fk, c["a_max"], c["fps"], "grounded")


def write_references_dof(model_dir: Path, inputs=None, targets=None, q0=None, v0=None):
    """``references.npz`` of a joint-velocity model (docs/omg-joint-velocity.md): one-step
    network outputs and the controller loop's rollouts from (inputs[:, 0], q0, v0), by
    default the directory's own; float64, saved as float32."""
    if inputs is None:
        with np.load(model_dir / "references.npz") as z:
            inputs, targets, q0, v0 = z["inputs"], z["rollout_targets"], z["rollout_q0"], z["rollout_v0"]
    inputs, targets, q0, v0 = (np.asarray(a, dtype=np.float32) for a in (inputs, targets, q0, v0))
    model, _, cfg = load_model(model_dir)
    tensors = load_file(str(model_dir / "model.safetensors"))
    loop = dof_loop(model_dir, cfg, tensors)
    x = torch.from_numpy(inputs.astype(np.float64))
    clips, frames, n = x.shape
    with torch.no_grad():
        o = model(loop.normalise(x.reshape(-1, n)))
        ph, co = loop.sl["phase"], loop.sl["cost"]
        raw = torch.cat([o[:, loop.out["phase"]] * loop.std[ph] + loop.mean[ph], loop.u_raw(o),
                         o[:, loop.out["cost"]] * loop.std[co] + loop.mean[co]], 1)
        one = raw.reshape(clips, frames, -1)
        q0t = torch.from_numpy(q0.astype(np.float64))
        roll, qs = loop.rollout(model, x[:, 0], q0t, torch.from_numpy(v0.astype(np.float64)),
                                torch.from_numpy(targets.astype(np.float64)), record_q=True)
    arrays = dict(
        inputs=inputs,
        rollout_targets=targets,
        one_step=one.numpy().astype(np.float32),
        rollout_grounded=roll.numpy().astype(np.float32),
        rollout_q0=q0,
        rollout_v0=v0,
        rollout_dof=qs.numpy().astype(np.float32),
    )
    tmp = model_dir / "references.tmp.npz"
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, model_dir / "references.npz")
    return one.numpy(), roll.numpy()


def read_references(model_dir: Path) -> dict:
    """The arrays of ``references.npz``."""
    with np.load(model_dir / "references.npz") as z:
        missing = sorted(set(ARRAYS) - set(z.files))
        if missing:
            raise SystemExit(f"{model_dir / 'references.npz'}: missing arrays {missing}")
        return {k: z[k] for k in ARRAYS}


def write_references(model_dir: Path, inputs=None, targets=None) -> tuple[np.ndarray, np.ndarray]:
    """Writes ``references.npz`` (whole or not at all) for ``inputs`` and ``targets``, by
    default the directory's own; returns the outputs in float64."""
    if inputs is None or targets is None:
        old = read_references(model_dir)
        inputs, targets = old["inputs"], old["rollout_targets"]
    inputs = np.asarray(inputs, dtype=np.float32)
    targets = np.asarray(targets, dtype=np.float32)
    model, fr, _ = load_model(model_dir)
    x = torch.from_numpy(inputs.astype(np.float64))
    clips, frames, n = x.shape
    with torch.no_grad():
        one = one_step(model, fr, x.reshape(-1, n)).reshape(clips, frames, n)
        # The rollout reads frame 0 and every frame's target block only.
        seeds = torch.zeros((clips, targets.shape[1], n), dtype=torch.float64)
        seeds[:, 0] = x[:, 0]
        seeds[:, :, fr.tgt] = torch.from_numpy(targets.astype(np.float64))
        roll = rollout(model, fr, seeds)
    arrays = dict(
        inputs=inputs,
        rollout_targets=targets,
        one_step=one.numpy().astype(np.float32),
        rollout_grounded=roll.numpy().astype(np.float32),
    )
    tmp = model_dir / "references.tmp.npz"
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, model_dir / "references.npz")
    return one.numpy(), roll.numpy()


def convert_weights(model_dir: Path, dtype: str) -> float:
    """Rewrites the layer weights in ``dtype``; returns the largest change relative to the
    largest magnitude of its tensor (per weight, a tiny value flushed to zero says nothing)."""
    path = model_dir / "model.safetensors"
    tensors = load_file(str(path))
    stored = save_weights(tensors, path, dtype)
    worst = 0.0
    for k, v in tensors.items():
        a, b = v.double(), stored[k].double()
        scale = float(a.abs().max())
        if scale > 0:
            worst = max(worst, float((a - b).abs().max()) / scale)
    cfg_path = model_dir / "config.json"
    cfg = json.loads(cfg_path.read_text())
    cfg["weights_dtype"] = dtype
    cfg_path.write_text(json.dumps(cfg, indent=1) + "\n")
    return worst


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("models", nargs="+", type=Path, help="trained model directories (tools.omg.train --out)")
    p.add_argument("--weights", choices=sorted(DTYPES), help="first store the layer weights in this type")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    for m in args.models:
        if args.weights:
            worst = convert_weights(m, args.weights)
            print(f"{m}: layer weights stored as {args.weights} (largest change {worst:.2e} of a tensor's largest magnitude)")
        cfg = json.loads((m / "config.json").read_text())
        write = write_references_dof if cfg.get("pose_form") == "dof_velocity" else write_references
        one, roll = write(m)
        print(f"{m}: wrote references.npz: one_step {one.shape}, rollout_grounded {roll.shape} (float64 PyTorch)")


if __name__ == "__main__":
    sys.exit(main())
