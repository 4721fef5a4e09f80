"""Evaluate trained OMG models on held-out clips (NumPy only, no PyTorch).

    python3 -m tools.omg.evaluate --data data/omg --models models/omg/tiny_fe_r1 ... \
        --json models/omg/eval.json --markdown models/omg/eval.md

Held-out clips: the rig's test and validation splits (48 clips; no model selection uses
the validation split). Metrics (every model in both inference modes):

* one-step: teacher-forced, every frame pair (x_t -> x_{t+1}) of every clip.
  ``re_mse`` = eq 3.6 as the author's code computes it: MSE over the pose slice (12J
  values), here in the model's normalised units (per-feature z-scores);
  ``one_step_pos_cm`` = mean joint position error of the decoded pose (cm).
* rollout: frame 0 from the data, then 299 frames fed back (driven only by the data's
  targets, which overwrite the target block every frame; grounded mode also recomputes the
  costs). Per spawned hand target (clips.json ``reps`` targets per hand; the return to
  rest is not counted): ``reach`` = the hand gets within 0.1 m before the data's next
  target is due (the data's own schedule); ``frames`` = median frames from the target's
  spawn to the first frame within 0.1 m (reached targets); ``final_m`` = mean hand-target
  distance on the target's last frame; ``joint_cm`` = mean joint position error against the
  ground truth over all frames and joints.
* roughness (eq 3.9 in the author's code's form): per frame pair
  dr_t = mean over joints and over the forward and up vectors of acos(cos_sim(r_t, r_t+1));
  RMS = sqrt(mean_t dr_t^2) (radians per frame), per clip, averaged over clips; for the
  rollout and for the ground truth.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from .omg_np import CONTACT_RADIUS, NumpyOMG


def held_out(data: Path, rig: str, n: int):
    d = data / rig
    clips_meta = json.loads((d / "clips.json").read_text())
    X, reps = [], []
    for split in ("test", "val"):
        arr = np.load(d / f"{split}.npy", mmap_mode="r")[:, :, :n].astype(np.float64)
        meta = {c["row"]: c for c in clips_meta if c["split"] == split}
        X.append(arr)
        reps += [meta[r]["reps"] for r in range(arr.shape[0])]
    return np.concatenate(X), np.asarray(reps)


def hand_targets(tpos: np.ndarray, reps: int):
    """[(start, end)] of the first ``reps`` constant-target intervals of one hand (T, 3)."""
    T = tpos.shape[0]
    ch = np.nonzero(np.linalg.norm(np.diff(tpos, axis=0), axis=1) > 1e-6)[0] + 1
    bounds = [0] + ch.tolist() + [T]
    iv = list(zip(bounds[:-1], bounds[1:]))
    return iv[:reps]


def rms_roughness(rot: np.ndarray, J: int) -> float:
    """rot (T, 6J) -> sqrt(mean_t dr_t^2)."""
    r = rot.reshape(rot.shape[0], J, 2, 3)
    r = r / np.maximum(np.linalg.norm(r, axis=-1, keepdims=True), 1e-8)
    cos = (r[1:] * r[:-1]).sum(-1)
    dr = np.arccos(np.clip(cos, -1, 1)).mean(axis=(1, 2))
    return float(np.sqrt((dr**2).mean()))


def reach_stats(gen_pos, clips, cfg, reps):
    """gen_pos (B, T, J, 3); returns per-target lists."""
    sl = {k: slice(*v) for k, v in cfg["slices"].items()}
    key = cfg["key_joint_indices"]
    K = cfg["K"]
    out = dict(reached=[], frames=[], final=[])
    B, T = clips.shape[:2]
    tpos = clips[:, :, sl["target_pos"]].reshape(B, T, K, 3)
    for b in range(B):
        for h in range(2):  # the hands; the feet's targets never move
            d = np.linalg.norm(gen_pos[b, :, key[h]] - tpos[b, :, h], axis=-1)
            for s, e in hand_targets(tpos[b, :, h], int(reps[b])):
                hit = np.nonzero(d[s:e] < CONTACT_RADIUS)[0]
                out["reached"].append(len(hit) > 0)
                if len(hit):
                    out["frames"].append(int(hit[0]))
                out["final"].append(float(d[e - 1]))
    return out


def evaluate_model(model_dir: Path, data: Path, modes=("grounded", "faithful")) -> dict:
    m = NumpyOMG(model_dir)
    cfg = m.cfg
    J, n = cfg["J"], cfg["model_width"]
    sl = m.sl
    clips, reps = held_out(data, cfg["rig"], n)
    B, T = clips.shape[:2]
    res = dict(model=str(model_dir), name=Path(model_dir).name, rig=cfg["rig"], variant=cfg["variant"],
               params=cfg["params"], macs=cfg["macs_per_frame"]["total"], trained_mode=cfg["mode"],
               clips=int(B))
    # one step
    x = clips[:, :-1].reshape(-1, n)
    y = clips[:, 1:].reshape(-1, n)
    yn = m.step_norm(m.normalise(x))
    res["re_mse"] = float(((yn[:, sl["pose"]] - m.normalise(y)[:, sl["pose"]]) ** 2).mean())
    yp = m.denormalise(yn)[:, sl["pos"]].reshape(-1, J, 3)
    res["one_step_pos_cm"] = float(100 * np.linalg.norm(yp - y[:, sl["pos"]].reshape(-1, J, 3), axis=-1).mean())
    gt_pos = clips[:, :, sl["pos"]].reshape(B, T, J, 3)
    gt = reach_stats(gt_pos, clips, cfg, reps)
    res["gt"] = dict(reach=float(np.mean(gt["reached"])), frames=float(np.median(gt["frames"])),
                     final_m=float(np.mean(gt["final"])),
                     rms=float(np.mean([rms_roughness(c[:, sl["rot"]], J) for c in clips])),
                     targets=len(gt["reached"]))
    for mode in modes:
        roll = m.rollout(clips, mode=mode)
        pos = roll[:, :, sl["pos"]].reshape(B, T, J, 3)
        st = reach_stats(pos, clips, cfg, reps)
        res[mode] = dict(
            reach=float(np.mean(st["reached"])),
            frames=float(np.median(st["frames"])) if st["frames"] else None,
            final_m=float(np.mean(st["final"])),
            joint_cm=float(100 * np.linalg.norm(pos - gt_pos, axis=-1).mean()),
            rms=float(np.mean([rms_roughness(c[:, sl["rot"]], J) for c in roll])),
            finite=bool(np.isfinite(roll).all()),
        )
    return res


def evaluate_hold(data: Path, cfg_dir: Path) -> dict:
    """Baseline without a model: every frame keeps frame 0's pose (the hands stay at rest)."""
    cfg = json.loads((cfg_dir / "config.json").read_text())
    J, n = cfg["J"], cfg["model_width"]
    sl = {k: slice(*v) for k, v in cfg["slices"].items()}
    clips, reps = held_out(data, cfg["rig"], n)
    B, T = clips.shape[:2]
    gt_pos = clips[:, :, sl["pos"]].reshape(B, T, J, 3)
    pos = np.repeat(gt_pos[:, :1], T, axis=1)
    st = reach_stats(pos, clips, cfg, reps)
    return dict(name="hold frame 0 (no model)", rig=cfg["rig"], reach=float(np.mean(st["reached"])),
                frames=float(np.median(st["frames"])) if st["frames"] else None,
                final_m=float(np.mean(st["final"])),
                joint_cm=float(100 * np.linalg.norm(pos - gt_pos, axis=-1).mean()))


def markdown(results) -> str:
    lines = [
        "| model | rig | params | MACs/frame | trained for | one-step Re. MSE (pose, norm.) | one-step joint err cm "
        "| rollout mode | reach % (data) | frames to reach, median (data) | final dist m (data) | joint err cm | RMS rad/frame (data) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        g = r["gt"]
        for mode in ("grounded", "faithful"):
            if mode not in r:
                continue
            q = r[mode]
            fr = "–" if q["frames"] is None else f"{q['frames']:.0f}"
            lines.append(
                f"| {r['name']} | {r['rig']} | {r['params']:,} | {r['macs']:,} | {r['trained_mode']} | {r['re_mse']:.4f} "
                f"| {r['one_step_pos_cm']:.2f} | {mode} | {100 * q['reach']:.1f} ({100 * g['reach']:.1f}) "
                f"| {fr} ({g['frames']:.0f}) | {q['final_m']:.3f} ({g['final_m']:.3f}) | {q['joint_cm']:.2f} "
                f"| {q['rms']:.4f} ({g['rms']:.4f}) |"
            )
    for r in results:
        if "hold" in r:
            h = r["hold"]
            fr = "–" if h["frames"] is None else f"{h['frames']:.0f}"
            lines.append(f"| {h['name']} | {h['rig']} | 0 | 0 | – | – | – | – | {100 * h['reach']:.1f} | {fr} "
                         f"| {h['final_m']:.3f} | {h['joint_cm']:.2f} | 0 |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=Path("data/omg"))
    ap.add_argument("--models", nargs="+", type=Path, required=True)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--markdown", type=Path)
    args = ap.parse_args(argv)
    results = [evaluate_model(m, args.data) for m in args.models]
    done = set()
    for r, m in zip(results, args.models):
        if r["rig"] not in done:
            r["hold"] = evaluate_hold(args.data, m)
            done.add(r["rig"])
    md = markdown(results)
    print(md)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    if args.markdown:
        args.markdown.write_text(md)


if __name__ == "__main__":
    main()
