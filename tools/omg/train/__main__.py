"""Train and export one OMG model.

    python3 -m tools.omg.train --data data/omg --rig R1 --variant FE --size tiny \
        --mode grounded --seed 0 --out models/omg/tiny_fe_r1

Rig transfer (spec §2.5): ``--init-from models/omg/tiny_fe_r1 --freeze-shared`` ('Frozen':
new AE against the source's frozen CostEnc/gate/experts) or no ``--init-from`` ('Raw');
``--train-share 0.2`` keeps that share of the training clips.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from safetensors.torch import load_file  # noqa: E402

from .core import (  # noqa: E402
    Frame,
    open_log,
    config_dict,
    count_params,
    load_rig,
    model_slices,
    norm_stats,
    pretrain_ae,
    train_omg,
)
from .model import OMG  # noqa: E402
from .references import save_weights, write_references  # noqa: E402


def parse(argv=None):
    a = argparse.ArgumentParser(prog="python3 -m tools.omg.train", description=__doc__.split("\n")[0])
    a.add_argument("--data", default="data/omg")
    a.add_argument("--rig", default="R1")
    a.add_argument("--variant", default="FE", choices=["FE", "RBF-CAT", "FS"])
    a.add_argument("--fs-joints", default="Hips,Head,LeftHand,RightHand,LeftFoot,RightFoot",
                   help="FS: the joints the encoder sees (the author's README: hands, feet, head, pelvis)")
    a.add_argument("--size", default="tiny", choices=["tiny", "small"])
    a.add_argument("--mode", default="grounded", choices=["grounded", "faithful"])
    a.add_argument("--seed", type=int, default=0)
    a.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (default 1)")
    a.add_argument("--epochs", type=int, default=51)
    a.add_argument("--ar-every", type=int, default=20, help="epochs between autoregression steps")
    a.add_argument("--ar-inc", type=float, default=0.5)
    a.add_argument("--ae-epochs", type=int, default=20)
    a.add_argument("--ae-batch", type=int, default=256, help="poses per AE pre-training batch")
    a.add_argument("--batch", type=int, default=32, help="clips per batch (x 23 chunks of 13 frames)")
    a.add_argument("--lr", type=float, default=1e-3)
    a.add_argument("--lr-step", type=int, default=240, help="StepLR step (optimiser steps), gamma 0.9")
    a.add_argument("--train-share", type=float, default=1.0, help="share of the training clips used")
    a.add_argument("--init-from", default=None, help="model dir whose shared modules start this one")
    a.add_argument("--freeze-shared", action="store_true", help="train only the AE ('Frozen' transfer)")
    a.add_argument("--ref-clips", default="0,1", help="test rows for the reference outputs")
    a.add_argument("--ref-one-step-frames", type=int, default=60)
    a.add_argument("--weights-dtype", default="float32", choices=["float32", "float16"],
                   help="storage of the layer weights in model.safetensors (normalisation stays float32)")
    a.add_argument("--weight-noise", type=float, default=0.0,
                   help="int8 steps of uniform noise (peak to peak) on every weight matrix in each "
                   "training step of the OMG stage (0: off); see models/omg/README.md")
    a.add_argument("--pose-form", default="dof_velocity", choices=["dof_velocity", "absolute"],
                   help="what the decoder outputs (docs/omg-joint-velocity.md): the joints' desired "
                   "velocities, trained by teacher forcing then DAgger on the data's IK (default), or "
                   "the absolute pose with scheduled autoregression (the thesis's recipe)")
    a.add_argument("--tf-steps", type=int, default=1500, help="dof_velocity: teacher-forced optimiser steps")
    a.add_argument("--dagger", type=int, default=6, help="dof_velocity: DAgger iterations")
    a.add_argument("--dagger-steps", type=int, default=1500, help="dof_velocity: optimiser steps after each rollout")
    a.add_argument("--keep", type=int, default=4, help="dof_velocity: DAgger rollouts kept for training")
    a.add_argument("--lr-end", type=float, default=1e-4,
                   help="dof_velocity: learning rate after the last DAgger iteration (geometric decay)")
    a.add_argument("--train-batch", type=int, default=512, help="dof_velocity: frames per batch")
    a.add_argument("--rollout-labels", default="ik", choices=["ik", "data"],
                   help="dof_velocity: label the frames the model visits with the IK's velocity there "
                   "(DAgger) or with the data's label of the same frame")
    a.add_argument("--pos-loss", type=float, default=1.0,
                   help="dof_velocity: weight of the joint positions one frame on (1 cm units)")
    a.add_argument("--out", required=True)
    return a.parse_args(argv)




def load_shared(model: OMG, tensors: dict):
    with torch.no_grad():
        for k, p in model.named_tensors(shared_only=True).items():
            assert tensors[k].shape == p.shape, (k, tensors[k].shape, p.shape)
            p.copy_(tensors[k])


def main(argv=None):
    args = parse(argv)
    if args.pose_form == "dof_velocity":
        from .dof_main import main_dof

        return main_dof(args, argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    out = Path(args.out)
    log = open_log(out, "train.log")

    t_start = time.time()
    lay, sp = load_rig(args.data, args.rig)
    sl = model_slices(lay)
    train = sp["train"]
    if args.train_share < 1.0:
        n_share = int(args.train_share * train.shape[0])
        rows = np.sort(np.random.default_rng(args.seed).permutation(train.shape[0])[:n_share])
        train = train[rows]
    else:
        rows = np.arange(train.shape[0])
    mean, std = norm_stats(train)
    src_cfg = None
    if args.init_from:
        src_cfg = json.loads((Path(args.init_from) / "config.json").read_text())
        # the frozen shared part expects its own statistics for phase, costs and targets
        smean = np.asarray(src_cfg["normalisation"]["mean"], np.float32)
        sstd = np.asarray(src_cfg["normalisation"]["std"], np.float32)
        for b in ("phase", "cost", "target"):
            s = slice(*sl[b])
            ss = slice(*src_cfg["slices"][b])
            mean[s], std[s] = smean[ss], sstd[ss]
    log(f"rig {args.rig}: {train.shape[0]} training clips, model width {lay['model_width']}")

    enc_cols = None
    if args.variant == "FS":
        names = json.loads((Path(args.data) / args.rig / "rig.json").read_text())["joints"]
        js = [names.index(n) for n in args.fs_joints.split(",")]
        enc_cols = [sl["pos"][0] + 3 * j + c for j in js for c in range(3)]
        enc_cols += [sl["rot"][0] + 6 * j + c for j in js for c in range(6)]
        enc_cols += [sl["vel"][0] + 3 * j + c for j in js for c in range(3)]
    model = OMG(sl, variant=args.variant, size=args.size, enc_cols=enc_cols)
    if args.init_from:
        load_shared(model, load_file(str(Path(args.init_from) / "model.safetensors")))
    params = None
    if args.freeze_shared:
        for m in model.shared_modules():
            m.requires_grad_(False)
        params = list(model.ae.parameters())
    n_params = count_params(model)
    macs = model.macs_per_frame()
    log(f"{args.variant} {args.size}: {n_params} parameters, {macs['total']} MACs/frame")

    fr = Frame(sl, mean, std, lay["key_joint_indices"], lay["joints"], args.mode)
    train_n = (torch.from_numpy(train) - fr.mean) / fr.std
    val_n = (torch.from_numpy(sp["val"]) - fr.mean) / fr.std

    t0 = time.time()
    pose = slice(*sl["pose"])
    ae_mse = pretrain_ae(model, train_n.reshape(-1, train_n.shape[-1]), args.ae_epochs, args.lr, args.ae_batch, gen, log)
    t_ae = time.time() - t0
    log(f"AE pre-training {t_ae:.1f} s")
    t0 = time.time()
    hist = train_omg(model, fr, train_n, val_n, args, gen, log, params)
    t_omg = time.time() - t0
    log(f"OMG training {t_omg:.1f} s")
    model.eval()

    # -- export -------------------------------------------------------------------------
    tensors = model.export_tensors()
    tensors["norm.mean"] = fr.mean.float().contiguous()
    tensors["norm.std"] = fr.std.float().contiguous()
    save_weights(tensors, out / "model.safetensors", args.weights_dtype)
    cmd = "python3 -m tools.omg.train " + " ".join(sys.argv[1:] if argv is None else argv)
    extra = dict(
        training=dict(
            command=cmd,
            seed=args.seed,
            args=vars(args),
            train_clips=int(train.shape[0]),
            train_rows=[int(r) for r in rows] if args.train_share < 1.0 else "all",
            ae_pretrain_s=round(t_ae, 1),
            omg_train_s=round(t_omg, 1),
            total_wall_s=None,
            threads=args.threads,
            final_ae_mse=ae_mse,
            final_train_loss=hist[-1]["train"],
            final_val_one_step=hist[-1]["val_one_step"],
            torch=torch.__version__,
            python=platform.python_version(),
            data_manifest=str(Path(args.data) / "manifest.json"),
            shared_from=args.init_from,
            frozen_shared=args.freeze_shared,
        )
    )
    cfg = config_dict(model, lay, fr.mean.numpy(), fr.std.numpy(), args.mode, extra)

    cfg["weights_dtype"] = args.weights_dtype

    # reference outputs (tools/omg/train/references.py): the stored weights in float64, on
    # the first frames of some test clips (one step) and their grounded 300-frame rollouts
    ref_rows = [int(r) for r in args.ref_clips.split(",")]
    clips = torch.from_numpy(sp["test"][ref_rows])
    ref_inputs = clips[:, : args.ref_one_step_frames].numpy()
    ref_targets = clips[:, :, fr.tgt].numpy()
    cfg["reference"] = dict(
        test_rows=ref_rows,
        precision="float64",
        arrays=dict(
            inputs="(clips, frames, n) raw test frames 0..F-1 (first frames of the clips)",
            rollout_targets="(clips, 300, 9K) the target block of every frame",
            one_step="(clips, frames, n) raw one-step outputs Y for inputs",
            rollout_grounded="(clips, 300, n) grounded rollout: frame 0 = inputs[:, 0], "
            "then the model's outputs with targets overwritten and costs recomputed",
        ),
    )
    cfg["training"]["total_wall_s"] = round(time.time() - t_start, 1)
    (out / "config.json").write_text(json.dumps(cfg, indent=1) + "\n")
    (out / "history.json").write_text(json.dumps(hist) + "\n")
    write_references(out, ref_inputs, ref_targets)
    log(f"wrote {out} ({time.time() - t_start:.1f} s total)")


if __name__ == "__main__":
    main()
