"""Float64 PyTorch references for a trained OMG model directory.

The training run commits its reference outputs from PyTorch in float32
(``ref_one_step.npy``, ``ref_rollout_grounded.npy``). Over a 300-frame
rollout that float32 rounding grows to a few 1e-4 of a feature's spread, which
hides whether an f64 implementation (host-sim's) follows the model or not.
This reruns the same PyTorch modules in float64 on the committed inputs
(``ref_inputs.npy``, frame 0 of each clip and ``ref_rollout_targets.npy``) and
writes ``ref64_one_step.npy`` and ``ref64_rollout_grounded.npy`` beside them,
stored as float32 like the other references (the committed models are kept to
a few MB; the storage rounding, 6e-8 of a value, is far below any tolerance
they are checked to). No data set is needed: everything comes from the model
directory.

    python3 -m tools.omg.train.references64 models/omg/tiny_fe_r1 models/omg/tiny_fe_r4_frozen
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
from safetensors.torch import load_file  # noqa: E402

from .core import Frame, one_step, rollout  # noqa: E402
from .model import OMG  # noqa: E402


def load_model(model_dir: Path) -> tuple[OMG, Frame, dict]:
    """The trained model in float64 and its grounded feed-back rule."""
    cfg = json.loads((model_dir / "config.json").read_text())
    args = cfg["training"]["args"]
    slices = {k: tuple(v) for k, v in cfg["slices"].items()}
    experts = cfg["sizes"]["experts"]
    model = OMG(slices, variant=cfg["variant"], size=args["size"], k=experts, enc_cols=cfg.get("encoder_columns"))
    tensors = load_file(str(model_dir / "model.safetensors"))
    live = model.named_tensors()
    missing = sorted(set(live) - set(tensors))
    if missing:
        raise SystemExit(f"{model_dir / 'model.safetensors'}: missing tensors {missing}")
    with torch.no_grad():
        for name, p in live.items():
            if tuple(tensors[name].shape) != tuple(p.shape):
                raise SystemExit(
                    f"{model_dir / 'model.safetensors'}: {name} has shape {tuple(tensors[name].shape)}, "
                    f"the config wants {tuple(p.shape)}"
                )
            p.copy_(tensors[name])
    model = model.double().eval()
    mean = tensors["norm.mean"].double()
    std = tensors["norm.std"].double()
    fr = Frame(slices, mean, std, cfg["key_joint_indices"], cfg["J"], "grounded")
    return model, fr, cfg


def references(model_dir: Path) -> None:
    model, fr, _ = load_model(model_dir)
    inputs = torch.from_numpy(np.load(model_dir / "ref_inputs.npy").astype(np.float64))
    targets = torch.from_numpy(np.load(model_dir / "ref_rollout_targets.npy").astype(np.float64))
    clips, frames, n = inputs.shape
    one = one_step(model, fr, inputs.reshape(-1, n)).reshape(clips, frames, n)
    # The rollout reads frame 0 and every frame's target block only.
    seeds = torch.zeros((clips, targets.shape[1], n), dtype=torch.float64)
    seeds[:, 0] = inputs[:, 0]
    seeds[:, :, fr.tgt] = targets
    roll = rollout(model, fr, seeds)
    np.save(model_dir / "ref64_one_step.npy", one.numpy().astype(np.float32))
    np.save(model_dir / "ref64_rollout_grounded.npy", roll.numpy().astype(np.float32))
    f32 = np.load(model_dir / "ref_rollout_grounded.npy").astype(np.float64)
    print(
        f"{model_dir}: wrote ref64_one_step.npy {tuple(one.shape)} and ref64_rollout_grounded.npy "
        f"{tuple(roll.shape)}; float32 references differ by up to {np.abs(f32 - roll.numpy()).max():.2e} (raw units)"
    )


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("models", nargs="+", type=Path, help="trained model directories (tools.omg.train --out)")
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    for m in args.models:
        references(m)


if __name__ == "__main__":
    sys.exit(main())
