"""``python3 -m tools.omg.train --pose-form dof_velocity`` (the default): train and export one
joint-velocity OMG model (docs/omg-joint-velocity.md; the recipe: :mod:`.dagger`)."""

from __future__ import annotations

import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file

from .. import metrics
from ..ik import FPS, HandIK, IKParams
from ..rigs import build_rig
from .core import config_dict, count_params, model_slices, norm_stats, open_log
from .dagger import ik_labels, train_dagger
from .fk import RigFK
from .loop import DofLoop
from .model import OMG
from .references import save_weights, write_references_dof


def load_full(data_dir, rig):
    """layout, rig.json and the raw splits with every column (the ``dof`` block included)."""
    d = Path(data_dir) / rig
    lay = json.loads((d / "layout.json").read_text())
    rig_json = json.loads((d / "rig.json").read_text())
    splits = {s: np.load(d / f"{s}.npy", mmap_mode="r") for s in ("train", "val", "test")}
    return lay, rig_json, splits


def skeleton(rig_json: dict) -> dict:
    names = rig_json["joints"]
    return dict(
        parents=rig_json["parents"],
        offsets=rig_json["rest_offsets"],
        dofs=[dict(joint=names.index(d["joint"]), axis="xyz".index(d["axis"]), lower=d["lower"], upper=d["upper"])
              for d in rig_json["dofs"]],
    )


def block(lay, name):
    b = next(x for x in lay["blocks"] if x["name"] == name)
    return slice(b["offset"], b["offset"] + b["size"])


def reach_on(model, loop, clips: np.ndarray, spawned, sl, key, parents, rest_len, n) -> dict:
    """Closed-loop reach of ``model`` on raw clips (B, T, width) with the data's targets."""
    K = len(key)
    with torch.no_grad():
        first = torch.from_numpy(clips[:, 0, :n].astype(np.float32))
        q0 = torch.from_numpy(clips[:, 0, loop.dof_cols].astype(np.float32))
        tg = torch.from_numpy(clips[:, :, sl["target"]].astype(np.float32))
        frames = loop.rollout(model, first, q0, q0 / loop.dt, tg).double().numpy()
    c = metrics.ReachCounts()
    for b in range(clips.shape[0]):
        tp = clips[b, :, sl["target_pos"]].reshape(clips.shape[1], K, 3)
        metrics.add_clip(c, frames[b], tp, metrics.clip_intervals(tp, spawned[b]), sl, key, parents, rest_len)
    return c.summary()


def main_dof(args, argv=None):
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    out = Path(args.out)
    log = open_log(out, "train.log")
    t_start = time.time()
    lay, rig_json, sp = load_full(args.data, args.rig)
    n = lay["model_width"]
    sl_t = model_slices(lay)
    sl = {k: slice(*v) for k, v in sl_t.items()}
    dof = block(lay, "dof")
    clips_meta = json.loads((Path(args.data) / args.rig / "clips.json").read_text())
    train_meta = sorted((c for c in clips_meta if c["split"] == "train"), key=lambda c: c["row"])
    train = np.asarray(sp["train"], dtype=np.float32)
    rows = np.arange(train.shape[0])
    if args.train_share < 1.0:
        n_share = int(args.train_share * train.shape[0])
        rows = np.sort(np.random.default_rng(args.seed).permutation(train.shape[0])[:n_share])
        train = train[rows]
    spawned = [train_meta[r]["spawned"] for r in rows]
    mean, std = norm_stats(train[:, :, :n])
    if args.init_from:
        src_cfg = json.loads((Path(args.init_from) / "config.json").read_text())
        smean = np.asarray(src_cfg["normalisation"]["mean"], np.float32)
        sstd = np.asarray(src_cfg["normalisation"]["std"], np.float32)
        for b in ("phase", "cost", "target"):
            s, ss = sl[b], slice(*src_cfg["slices"][b])
            mean[s], std[s] = smean[ss], sstd[ss]
    D = dof.stop - dof.start
    log(f"rig {args.rig}: {train.shape[0]} training clips, model width {n}, {D} DOFs; pose form dof_velocity")

    enc_cols = None
    if args.variant == "FS":
        names = rig_json["joints"]
        js = [names.index(j) for j in args.fs_joints.split(",")]
        enc_cols = [sl_t["pos"][0] + 3 * j + c for j in js for c in range(3)]
        enc_cols += [sl_t["rot"][0] + 6 * j + c for j in js for c in range(6)]
        enc_cols += [sl_t["vel"][0] + 3 * j + c for j in js for c in range(3)]
    model = OMG(sl_t, variant=args.variant, size=args.size, enc_cols=enc_cols, pose_form="dof_velocity", dof=D)
    params = None
    if args.init_from:
        t = load_file(str(Path(args.init_from) / "model.safetensors"))
        with torch.no_grad():
            for k, p in model.named_tensors(shared_only=True).items():
                assert t[k].shape == p.shape, (k, t[k].shape, p.shape)
                p.copy_(t[k])
    if args.freeze_shared:
        for m in model.shared_modules():
            m.requires_grad_(False)
        params = list(model.ae.parameters())
    log(f"{args.variant} {args.size}: {count_params(model)} parameters, {model.macs_per_frame()['total']} MACs/frame")

    ik = HandIK(build_rig(args.rig), IKParams())  # the data's IK, the expert
    K = lay["K"]
    # output statistics of u: the IK's desired velocities over the data's frames
    u = ik_labels(ik, train[:, :-1, dof].reshape(-1, D), train[:, 1:, sl["target"]].reshape(-1, 9 * K), K)
    dof_mean = u.mean(0).astype(np.float32)
    dof_std = np.maximum(u.std(0), 1e-4).astype(np.float32)
    fk = RigFK(rig_json)
    a_max = IKParams().a_max
    loop = DofLoop(sl_t, mean, std, dof_mean, dof_std, lay["key_joint_indices"], fk, a_max, FPS, args.mode)
    loop.dof_cols = dof
    parents = rig_json["parents"]
    rest_len = metrics.rest_bone_lengths(rig_json["rest_offsets"], parents)
    key = lay["key_joint_indices"]
    n_eval = min(64, train.shape[0])

    def evaluate(m, tag):
        r = reach_on(m, loop, train[:n_eval], spawned[:n_eval], sl, key, parents, rest_len, n)
        log(f"  [{tag}] training clips 0-{n_eval - 1}, closed loop: plausible reach {r['plausible_reach']:.3f} "
            f"of {r['targets']}, frames {r['frames_median']}, final {r['final_m']:.3f} m")
        return {"train_clips_reach": r}

    args.batch = args.train_batch
    t0 = time.time()
    hist = train_dagger(model, loop, ik, train, sl_t, dof, args, gen, log, params=params, evaluate=evaluate)
    t_train = time.time() - t0
    log(f"training {t_train:.1f} s")
    model.eval()

    tensors = model.export_tensors()
    tensors["norm.mean"] = torch.as_tensor(mean).float().contiguous()
    tensors["norm.std"] = torch.as_tensor(std).float().contiguous()
    tensors["norm.dof_mean"] = torch.as_tensor(dof_mean).contiguous()
    tensors["norm.dof_std"] = torch.as_tensor(dof_std).contiguous()
    save_weights(tensors, out / "model.safetensors", args.weights_dtype)
    cmd = "python3 -m tools.omg.train " + " ".join(sys.argv[1:] if argv is None else argv)
    extra = dict(
        pose_form="dof_velocity",
        controller=dict(fps=FPS, a_max=a_max, skeleton=skeleton(rig_json)),
        training=dict(
            command=cmd,
            recipe="teacher forcing on the data's frames, then DAgger: labels the IK's desired velocity "
            "at every visited state (tools/omg/train/dagger.py)",
            seed=args.seed,
            args=vars(args),
            train_clips=int(train.shape[0]),
            train_rows=[int(r) for r in rows] if args.train_share < 1.0 else "all",
            train_s=round(t_train, 1),
            total_wall_s=None,
            threads=args.threads,
            final_loss=hist[-1]["loss"],
            torch=torch.__version__,
            python=platform.python_version(),
            data_manifest=str(Path(args.data) / "manifest.json"),
            shared_from=args.init_from,
            frozen_shared=args.freeze_shared,
        ),
    )
    cfg = config_dict(model, lay, mean, std, args.mode, extra)
    cfg["sizes"]["dof"] = D
    cfg["normalisation"]["dof_mean"] = [float(v) for v in dof_mean]
    cfg["normalisation"]["dof_std"] = [float(v) for v in dof_std]
    cfg["out_slices"]["u"] = [model.out_slices_dof["u"].start, model.out_slices_dof["u"].stop]
    cfg["weights_dtype"] = args.weights_dtype
    ref_rows = [int(r) for r in args.ref_clips.split(",")]
    test = np.asarray(sp["test"])[ref_rows]
    cfg["reference"] = dict(
        test_rows=ref_rows,
        precision="float64",
        arrays=dict(
            inputs="(clips, frames, n) raw test frames 0..F-1",
            one_step="(clips, frames, n_out) the network's raw outputs [phase', u, cost'] for inputs",
            rollout_targets="(clips, 300, 9K) the target block of every frame",
            rollout_q0="(clips, D) joint angles of frame 0", rollout_v0="(clips, D) their velocities",
            rollout_grounded="(clips, 300, n) the controller loop's frames from inputs[:, 0]",
            rollout_dof="(clips, 300, D) the loop's joint angles",
        ),
    )
    cfg["training"]["total_wall_s"] = round(time.time() - t_start, 1)
    (out / "config.json").write_text(json.dumps(cfg, indent=1) + "\n")
    (out / "rig.json").write_text(json.dumps(rig_json, indent=1) + "\n")
    (out / "history.json").write_text(json.dumps(hist) + "\n")
    q0 = test[:, 0, dof].astype(np.float32)
    write_references_dof(out, test[:, : args.ref_one_step_frames, :n], test[:, :, sl["target"]], q0, q0 * FPS)
    log(f"wrote {out} ({time.time() - t_start:.1f} s total)")


def qat_dof(model, tensors: dict, cfg: dict, data: str, args, perturb, gen, log, params=None):
    """Quantisation-aware DAgger fine-tuning of a joint-velocity model (``tools.omg.train.qat``):
    the source's normalisation, skeleton and training clips, ``args.dagger`` iterations of
    ``args.dagger_steps`` steps from ``args.lr`` to ``args.lr_end``, every step (and every
    rollout) on the weights ``perturb`` rounds to the blob's grid. Returns the history."""
    lay, rig_json, sp = load_full(data, cfg["rig"])
    n = lay["model_width"]
    sl = {k: slice(*v) for k, v in cfg["slices"].items()}
    dof = block(lay, "dof")
    train = np.asarray(sp["train"], dtype=np.float32)
    rows = cfg["training"].get("train_rows", "all")
    if rows != "all":
        train = train[np.asarray(rows)]
    clips_meta = json.loads((Path(data) / cfg["rig"] / "clips.json").read_text())
    meta = sorted((c for c in clips_meta if c["split"] == "train"), key=lambda c: c["row"])
    spawned = [meta[r]["spawned"] for r in (range(len(meta)) if rows == "all" else rows)]
    c = cfg["controller"]
    loop = DofLoop(cfg["slices"], tensors["norm.mean"].float(), tensors["norm.std"].float(),
                   tensors["norm.dof_mean"].float(), tensors["norm.dof_std"].float(), cfg["key_joint_indices"],
                   RigFK(rig_json), c["a_max"], c["fps"], cfg["mode"])
    loop.dof_cols = dof
    parents = rig_json["parents"]
    rest_len = metrics.rest_bone_lengths(rig_json["rest_offsets"], parents)
    n_eval = min(64, train.shape[0])

    def evaluate(m, tag):
        r = reach_on(m, loop, train[:n_eval], spawned[:n_eval], sl, cfg["key_joint_indices"], parents, rest_len, n)
        log(f"  [{tag}] training clips 0-{n_eval - 1}, closed loop (int{args.weight_bits} grid): plausible reach "
            f"{r['plausible_reach']:.3f} of {r['targets']}, frames {r['frames_median']}, final {r['final_m']:.3f} m")
        return {"train_clips_reach": r}

    ik = HandIK(build_rig(cfg["rig"]), IKParams())
    return train_dagger(model, loop, ik, train, cfg["slices"], dof, args, gen, log, params=params,
                        evaluate=evaluate, perturb=perturb)
