"""Evaluate OMG models in closed loop (NumPy only, no PyTorch).

    python3 -m tools.omg.evaluate --data data/omg --models models/omg/tiny_fe_r1 ... \\
        --json models/omg/eval.json --markdown models/omg/eval.md

Two test sets, neither used for training or for choosing a model:

* **held-out clips**: the rig's test and validation splits (96 clips), each rolled out from
  its frame 0 for its 300 frames, driven only by the data's targets (the data's schedule:
  the next pair is due when the IK was done with the last);
* **target scripts** (R1 models): the hand-written scripts of ``tools/omg/scripts``, each
  from the rest pose.

Metrics (``tools.omg.metrics``, the same definitions as ``host-sim omg-reach``): reach and
**plausible** reach of the targets the hand does not start within 0.1 m of (those are
counted apart), median frames to a plausible reach, mean final distance, bone-length error
p50/p99, roughness. Beside every model: the data (the IK that generated it; on the scripts
the same IK driven by the script) and holding the first frame still.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from . import metrics
from . import scripts as sc
from .ik import HandIK, IKParams, rot6_to_matrix
from .omg_np import NumpyOMG, costs_from_frame
from .rigs import KEY_JOINT_NAMES, build_rig, forward_kinematics


def held_out(data: Path, rig: str):
    """Raw frames (B, T, width) of the test then validation split and each clip's spawned
    target counts per hand."""
    d = data / rig
    meta = json.loads((d / "clips.json").read_text())
    X, spawned = [], []
    for split in ("test", "val"):
        X.append(np.load(d / f"{split}.npy").astype(np.float64))
        by_row = {c["row"]: c for c in meta if c["split"] == split}
        spawned += [by_row[r]["spawned"] for r in range(X[-1].shape[0])]
    return np.concatenate(X), spawned, json.loads((d / "layout.json").read_text())


def _blocks(lay):
    return {b["name"]: slice(b["offset"], b["offset"] + b["size"]) for b in lay["blocks"]}


def _summary(frames, target_pos, intervals, sl, key, parents, rest_len):
    c = metrics.ReachCounts()
    for f, tp, iv in zip(frames, target_pos, intervals):
        metrics.add_clip(c, f, tp, iv, sl, key, parents, rest_len)
    return c.summary()


def rollout_clips(m: NumpyOMG, clips: np.ndarray, lay: dict) -> np.ndarray:
    """The model's closed-loop frames (B, T, n) on raw clips with the data's targets."""
    n = m.cfg["model_width"]
    sl = _blocks(lay)
    if m.dof_form:
        q0 = clips[:, 0, sl["dof"]]
        frames, _ = m.rollout_dof(clips[:, 0, :n], q0, q0 * m.fps, clips[:, :, m.sl["target"]])
        return frames
    return m.rollout(clips[:, :, :n], mode="grounded")


def rest_frame(cfg: dict, rig, target_block: np.ndarray) -> np.ndarray:
    """The frame of the rest pose (q = 0, at rest: zero velocities and phases) with a target
    block, its costs grounded."""
    sl = {k: slice(*v) for k, v in cfg["slices"].items()}
    P, G = forward_kinematics(rig, np.zeros((1, rig.n_dofs)))
    J = rig.n_joints
    x = np.zeros((1, cfg["model_width"]))
    x[:, sl["pos"]] = P.reshape(1, 3 * J)
    x[:, sl["rot"]] = np.concatenate([G[..., :, 2], G[..., :, 1]], axis=-1).reshape(1, 6 * J)
    x[:, sl["target"]] = target_block
    x[:, sl["cost"]] = costs_from_frame(x, cfg)
    return x[0]


def ik_rollout(rig, blocks: np.ndarray, K: int):
    """Joint positions (T, J, 3) and rotations (T, J, 3, 3) of the data's IK driven by
    per-frame target blocks (T, 9K) from rest (each frame's step uses that frame's targets,
    as the generator does)."""
    ik = HandIK(rig, IKParams())
    q = np.zeros((1, rig.n_dofs))
    v = np.zeros_like(q)
    P, G = [], []
    for b in blocks:
        q, v = ik.step(q, v, b[None, :6].reshape(1, 2, 3), rot6_to_matrix(b[None, 3 * K : 3 * K + 12].reshape(1, 2, 6)))
        p, g = forward_kinematics(rig, q)
        P.append(p[0])
        G.append(g[0])
    return np.stack(P), np.stack(G)


def script_set(cfg: dict):
    """[(name, blocks (T, 9K), intervals [(hand, start, end)], unreachable [(hand, s, e)])]."""
    out = []
    start = sc.start_block(cfg["rig"])
    for path in sc.script_files():
        s = sc.load(path)
        T = sc.script_frames(s)
        blocks = sc.blocks(s, KEY_JOINT_NAMES, start, T)
        ivs = [iv for iv in sc.intervals(s, KEY_JOINT_NAMES, T) if iv["key"] < 2]
        out.append((path.stem, blocks,
                    [(iv["key"], iv["start"], iv["end"]) for iv in ivs if not iv["unreachable"]],
                    [(iv["key"], iv["start"], iv["end"]) for iv in ivs if iv["unreachable"]]))
    return out


def unreachable_report(frames: np.ndarray, blocks, ivs, sl, key, parents, rest_len) -> list:
    """For each unreachable target: distance at its start, closest and last, and the bone
    errors on its frames (approached, not chased into a broken pose)."""
    out = []
    T = frames.shape[0]
    pos = frames[:, sl["pos"]].reshape(T, -1, 3)
    err = np.abs(metrics.bone_lengths(pos, parents) - rest_len)
    for h, s, e in ivs:
        d = np.linalg.norm(pos[:, key[h]] - blocks[:, 3 * h : 3 * h + 3], axis=-1)
        out.append(dict(hand=h, start_m=float(d[s]), closest_m=float(d[s:e].min()), last_m=float(d[e - 1]),
                        bone_err_max_cm=float(100 * err[s:e].max())))
    return out


def evaluate_scripts(m: NumpyOMG | None, cfg: dict, rig) -> dict:
    """Rows on the target scripts: the model (or, with ``m`` None, the IK and holding still)."""
    sl = {k: slice(*v) for k, v in cfg["slices"].items()}
    key = cfg["key_joint_indices"]
    K = cfg["K"]
    parents = list(rig.parents)
    rest_len = metrics.rest_bone_lengths(rig.offsets, parents)
    rows = {}
    runs = {}
    for name, blocks, ivs, far in script_set(cfg):
        tp = blocks[:, : 3 * K].reshape(len(blocks), K, 3)
        x0 = rest_frame(cfg, rig, blocks[0])
        if m is None:
            P, G = ik_rollout(rig, blocks, K)
            f_ik = np.repeat(x0[None], len(blocks), 0)
            f_ik[:, sl["pos"]] = P.reshape(len(blocks), -1)
            f_ik[:, sl["rot"]] = np.concatenate([G[..., :, 2], G[..., :, 1]], axis=-1).reshape(len(blocks), -1)
            f_hold = np.repeat(x0[None], len(blocks), 0)
            runs.setdefault("data (IK)", []).append((f_ik, tp, ivs, far, blocks))
            runs.setdefault("hold still", []).append((f_hold, tp, ivs, far, blocks))
        else:
            frames, _ = m.rollout_dof(x0[None], np.zeros((1, rig.n_dofs)), np.zeros((1, rig.n_dofs)), blocks[None])
            runs.setdefault("f64", []).append((frames[0], tp, ivs, far, blocks))
    for run, items in runs.items():
        c = metrics.ReachCounts()
        far_rows = []
        for f, tp, ivs, far, blocks in items:
            metrics.add_clip(c, f, tp, ivs, sl, key, parents, rest_len)
            far_rows += unreachable_report(f, blocks, far, sl, key, parents, rest_len)
        r = c.summary()
        r["unreachable"] = far_rows
        rows[run] = r
    return rows


def evaluate_model(model_dir: Path, data: Path) -> dict:
    m = NumpyOMG(model_dir)
    cfg = m.cfg
    clips, spawned, lay = held_out(data, cfg["rig"])
    sl = _blocks(lay)
    key = cfg["key_joint_indices"]
    rig = build_rig(cfg["rig"])
    parents = list(rig.parents)
    rest_len = metrics.rest_bone_lengths(rig.offsets, parents)
    K = cfg["K"]
    B, T = clips.shape[:2]
    tp = clips[:, :, sl["target_pos"]].reshape(B, T, K, 3)
    ivs = [metrics.clip_intervals(tp[b], spawned[b]) for b in range(B)]
    frames = rollout_clips(m, clips, lay)
    res = dict(model=str(model_dir), name=Path(model_dir).name, rig=cfg["rig"], variant=cfg["variant"],
               pose_form=cfg.get("pose_form", "absolute"), params=cfg["params"],
               macs=cfg["macs_per_frame"]["total"], clips=int(B))
    res["held_out"] = {
        "f64": _summary(frames, tp, ivs, sl, key, parents, rest_len),
        "data": _summary(clips, tp, ivs, sl, key, parents, rest_len),
        "hold still": _summary(np.repeat(clips[:, :1], T, 1), tp, ivs, sl, key, parents, rest_len),
    }
    if cfg["rig"] == "R1" and m.dof_form:
        res["scripts"] = dict(evaluate_scripts(None, cfg, rig), **evaluate_scripts(m, cfg, rig))
    return res


def markdown(results) -> str:
    lines = ["| model | set | run | targets (near start) | reach % | plausible reach % | frames to reach | "
             "final dist m | bone err p50 / p99 cm | roughness rad/frame |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        for set_name in ("held_out", "scripts"):
            for run, q in r.get(set_name, {}).items():
                fr = "–" if q["frames_median"] is None else f"{q['frames_median']:.0f}"
                ro = "–" if q["roughness"] is None else f"{q['roughness']:.4f}"
                lines.append(
                    f"| {r['name']} | {set_name.replace('_', '-')} | {run} | {q['targets']} ({q['near_start']}) "
                    f"| {100 * q['reach']:.1f} | {100 * q['plausible_reach']:.1f} | {fr} | {q['final_m']:.3f} "
                    f"| {q['bone_err_p50_cm']:.2f} / {q['bone_err_p99_cm']:.2f} | {ro} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=Path("data/omg"))
    ap.add_argument("--models", nargs="+", type=Path, required=True)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--markdown", type=Path)
    args = ap.parse_args(argv)
    results = [evaluate_model(m, args.data) for m in args.models]
    md = markdown(results)
    print(md)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    if args.markdown:
        args.markdown.write_text(md)


if __name__ == "__main__":
    main()
