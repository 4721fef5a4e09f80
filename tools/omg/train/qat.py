"""Quantisation-aware fine-tuning of a trained OMG model for its int8 blob.

    python3 -m tools.omg.train.qat --from models/omg/tiny_fe_r1 --data data/omg \\
        --epochs 30 --out data/omg/models/tiny_fe_r1_qat

Why: a float-trained OMG model's grounded rollouts leave its f64 rollout wherever int8-sized
weight changes act (docs/omg.md), so its int8 blob cannot follow it. Here the model is
fine-tuned with every weight matrix rounded to the int8 blob's own grid in each step (the
gradient at the rounded weights updating the float ones, a straight-through estimate), and
the result is stored **snapped**: every dense weight and bias as the blob computes it. The
model then is the int8 model, and its blob differs from its f64 forward only in the
activations' fixed point.

Steps (made in ``<out>.partial`` and moved into ``--out`` at the end, so that a failed run
leaves ``--out`` as it was):

1. ``exporter omg --grid-out`` gives the grid (the integer units of each weight's input
   column; a row's scale follows its largest weight, as the exporter's).
2. ``--epochs`` epochs of the OMG stage (``core.train_omg``) on the rig's training clips,
   fully autoregressive after the first epoch, from the model's own weights and
   normalisation, at ``--lr``; ``--freeze-shared`` trains only the autoencoder.
3. ``exporter omg --snap-out`` replaces the weights by the blob's, repeated until the
   snapped model snaps to itself (the grid follows the model's calibrated ranges, so the
   first snap can move a row's format); ``--max-snaps`` bounds it.
4. ``references.npz`` for the snapped weights (the source's clips), ``config.json`` (the
   source's, with a ``qat`` record), ``qat_history.json`` and ``qat.log`` beside the
   source's ``history.json`` and ``train.log``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from safetensors.torch import load_file  # noqa: E402

from .core import Frame, grid_round, load_rig, model_slices, open_log, train_omg  # noqa: E402
from .proc import EXPORTER, QAT_LR, run  # noqa: E402
from .references import load_model, read_references, save_weights, write_references, write_references_dof  # noqa: E402

QMAX = {8: 127.0, 16: 32767.0}
# A snapped weight is k * u_j / s_i stored as float32: snapping it again may move it by
# float32 rounding, no more.
SNAP_TOLERANCE = 1e-6


def parse(argv=None):
    a = argparse.ArgumentParser(prog="python3 -m tools.omg.train.qat", description=__doc__.split("\n")[0])
    a.add_argument("--from", dest="source", required=True, help="trained model directory")
    a.add_argument("--data", default="data/omg")
    a.add_argument("--out", required=True)
    a.add_argument("--epochs", type=int, default=30)
    a.add_argument("--lr", type=float, default=QAT_LR, help="AdamW learning rate (the source's last was about 2e-4)")
    a.add_argument("--lr-step", type=int, default=700)
    a.add_argument("--batch", type=int, default=32)
    a.add_argument("--weight-bits", type=int, default=8, choices=sorted(QMAX))
    a.add_argument("--feedback-noise", type=float, default=0.0,
                   help="standard deviation (normalised units) of Gaussian noise on the fed-back frame in "
                   "training, targets excepted (0: off; one of the candidates tools.omg.train.choose judges)")
    a.add_argument("--freeze-shared", action="store_true", help="train only the autoencoder")
    a.add_argument("--train-share", type=float, default=None,
                   help="share of the training clips (default: the source's, with its rows)")
    a.add_argument("--motion-from", default=None,
                   help="a Frozen rig model: the model directory whose int8 blob is the motion blob its "
                   "rig blob is built against (the grid of the shared nodes is that blob's)")
    a.add_argument("--exporter", default=EXPORTER, help="the exporter binary")
    a.add_argument("--max-snaps", type=int, default=6)
    a.add_argument("--seed", type=int, default=0)
    a.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (default 1)")
    # joint-velocity models (docs/omg-joint-velocity.md): DAgger fine-tuning on the grid
    a.add_argument("--dagger", type=int, default=3, help="dof_velocity: DAgger iterations on the grid")
    a.add_argument("--dagger-steps", type=int, default=1000, help="dof_velocity: steps per iteration")
    a.add_argument("--tf-steps", type=int, default=0, help="dof_velocity: teacher-forced steps first")
    a.add_argument("--lr-end", type=float, default=2e-5, help="dof_velocity: last learning rate")
    a.add_argument("--keep", type=int, default=3, help="dof_velocity: rollouts kept")
    a.add_argument("--train-batch", type=int, default=512, help="dof_velocity: frames per batch")
    a.add_argument("--pos-loss", type=float, default=1.0, help="dof_velocity: joint-position loss weight")
    a.add_argument("--rollout-labels", default="ik", choices=["ik", "data"])
    return a.parse_args(argv)


def exporter(args, model_dir: Path, *extra: str) -> None:
    """``exporter omg`` on ``model_dir`` with ``extra``; with ``--motion-from``, ``exporter
    omg-rig`` against that model's blob (the grid of the motion nodes is then the motion
    blob's, which the rig shares)."""
    tmp = Path(tempfile.mkdtemp())
    model = ["--weights", str(model_dir / "model.safetensors"), "--config", str(model_dir / "config.json"),
             "--weight-bits", str(args.weight_bits)]
    try:
        if args.motion_from is None:
            run([args.exporter, "omg", *model, "-o", str(tmp / "model.blob"), *extra])
        else:
            motion = Path(args.motion_from)
            run([args.exporter, "omg", "--weights", str(motion / "model.safetensors"),
                 "--config", str(motion / "config.json"), "--weight-bits", str(args.weight_bits),
                 "-o", str(tmp / "motion.blob")])
            run([args.exporter, "omg-rig", "--base", str(tmp / "motion.blob"), *model,
                 "-o", str(tmp / "rig.blob"), *extra])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def snap_until_fixed(args, out: Path, log) -> list:
    """Replaces ``out``'s weights by their blob's until that changes nothing; returns the
    largest change of each snap."""
    changes = []
    path = out / "model.safetensors"
    for _ in range(args.max_snaps):
        before = load_file(str(path))
        snapped = out / "snapped.safetensors"
        exporter(args, out, "--snap-out", str(snapped))
        after = load_file(str(snapped))
        change = max(float((after[k].double() - before[k].double()).abs().max()) for k in before)
        os.replace(snapped, path)
        changes.append(change)
        log(f"snap {len(changes)}: largest weight change {change:.3e}")
        if change <= SNAP_TOLERANCE:
            return changes
    raise SystemExit(f"{out}: the snapped weights still moved by {changes[-1]:.3e} after {args.max_snaps} snaps")


def main(argv=None):
    args = parse(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    src, final = Path(args.source), Path(args.out)
    if src.resolve() == final.resolve():
        raise SystemExit("--out must differ from --from (the source's weights are read throughout)")
    if shutil.which(args.exporter) is None:
        raise SystemExit(f"{args.exporter}: no exporter binary there (cargo build --release -p exporter, or --exporter PATH)")
    # everything is made beside --out and moved in at the end: a failed run leaves --out as it was
    out = final.with_name(final.name + ".partial")
    shutil.rmtree(out, ignore_errors=True)
    log = open_log(out, "qat.log")

    t_start = time.time()
    cfg = json.loads((src / "config.json").read_text())
    shutil.copy(src / "config.json", out / "config.json")
    # the source's own record stays beside the fine-tuning's
    for extra in ("rig.json", "history.json", "train.log"):
        if (src / extra).exists():
            shutil.copy(src / extra, out / extra)
    model, _, _ = load_model(src, torch.float32)
    tensors = load_file(str(src / "model.safetensors"))
    save_weights({k: v.float() for k, v in tensors.items()}, out / "model.safetensors", "float32")

    grid_path = out / "grid.json"
    exporter(args, out, "--grid-out", str(grid_path))
    grid = json.loads(grid_path.read_text())["column_scales"]
    qmax = QMAX[args.weight_bits]

    params = None
    if args.freeze_shared:
        for m in model.shared_modules():
            m.requires_grad_(False)
        params = list(model.ae.parameters())
    dof_form = cfg.get("pose_form") == "dof_velocity"
    if dof_form:
        from .dof_main import qat_dof

        args.batch = args.train_batch
        log(f"{src} -> {out}: {args.dagger} DAgger iterations of int{args.weight_bits} QAT")
        t0 = time.time()
        hist = qat_dof(model, tensors, cfg, args.data, args, lambda: grid_round(model, grid, qmax), gen, log,
                       params)
        t_train = time.time() - t0
        train = None
    else:
        hist, t_train, train = qat_absolute(args, cfg, tensors, model, grid, qmax, gen, log, params)
    log(f"QAT {t_train:.1f} s")

    stored = model.export_tensors()
    for k in ("norm.mean", "norm.std", "norm.dof_mean", "norm.dof_std"):
        if k in tensors:
            stored[k] = tensors[k].float()
    save_weights(stored, out / "model.safetensors", "float32")
    changes = snap_until_fixed(args, out, log)
    finish(args, argv, cfg, src, out, final, train, t_train, changes, hist, t_start, log, dof_form)


def qat_absolute(args, cfg, tensors, model, grid, qmax, gen, log, params):
    """The absolute-pose models' QAT: the OMG stage (``core.train_omg``) on the grid."""
    lay, sp = load_rig(args.data, cfg["rig"])
    sl = model_slices(lay)
    train = sp["train"]
    rows = cfg["training"].get("train_rows", "all")
    if args.train_share is not None:
        n_share = int(args.train_share * train.shape[0])
        train = train[np.sort(np.random.default_rng(args.seed).permutation(train.shape[0])[:n_share])]
    elif rows != "all":
        train = train[np.asarray(rows)]
    mean, std = tensors["norm.mean"].float(), tensors["norm.std"].float()
    fr = Frame(sl, mean, std, lay["key_joint_indices"], lay["joints"], cfg["mode"])
    train_n = (torch.from_numpy(train) - fr.mean) / fr.std
    val_n = (torch.from_numpy(sp["val"]) - fr.mean) / fr.std
    log(f"{args.source} -> {args.out}: {train.shape[0]} training clips, {args.epochs} epochs of int{args.weight_bits} QAT")

    train_args = argparse.Namespace(
        epochs=args.epochs, lr=args.lr, lr_step=args.lr_step, batch=args.batch,
        # fully autoregressive after the first epoch, as the source's last epochs were
        ar_inc=1.0, ar_every=1, weight_noise=0.0, feedback_noise=args.feedback_noise,
    )
    t0 = time.time()
    hist = train_omg(model, fr, train_n, val_n, train_args, gen, log, params,
                     perturb=lambda: grid_round(model, grid, qmax))
    t_train = time.time() - t0
    return hist, t_train, train


def finish(args, argv, cfg, src, out, final, train, t_train, changes, hist, t_start, log, dof_form):
    """The config's ``qat`` record, the references of the snapped weights, and the move into
    ``--out``."""
    cmd = "python3 -m tools.omg.train.qat " + " ".join(sys.argv[1:] if argv is None else argv)
    cfg["weights_dtype"] = "float32"
    cfg["qat"] = dict(
        command=cmd,
        source=str(src),
        weight_bits=args.weight_bits,
        epochs=args.epochs,
        lr=args.lr,
        lr_step=args.lr_step,
        train_clips=None if train is None else int(train.shape[0]),
        frozen_shared=args.freeze_shared,
        motion_from=args.motion_from,
        feedback_noise=args.feedback_noise,
        qat_s=round(t_train, 1),
        snaps=changes,
        final_val_one_step=hist[-1].get("val_one_step") if hist else None,
        dagger=dict(iterations=args.dagger, steps=args.dagger_steps, lr_end=args.lr_end) if dof_form else None,
        torch=torch.__version__,
        python=platform.python_version(),
        rule="weights and biases stored as the int8 blob computes them (exporter omg --snap-out, "
        "repeated until it changes nothing)",
    )
    cfg["qat"]["total_wall_s"] = round(time.time() - t_start, 1)
    (out / "config.json").write_text(json.dumps(cfg, indent=1) + "\n")
    (out / "qat_history.json").write_text(json.dumps(hist) + "\n")
    if dof_form:
        with np.load(src / "references.npz") as z:
            write_references_dof(out, z["inputs"], z["rollout_targets"], z["rollout_q0"], z["rollout_v0"])
    else:
        ref = read_references(src)
        write_references(out, ref["inputs"], ref["rollout_targets"])
    (out / "grid.json").unlink(missing_ok=True)
    final.mkdir(parents=True, exist_ok=True)
    for f in sorted(out.iterdir()):
        os.replace(f, final / f.name)
    out.rmdir()
    log(f"wrote {final} ({time.time() - t_start:.1f} s total)")


if __name__ == "__main__":
    main()
