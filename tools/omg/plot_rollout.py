"""Draw an OMG rollout next to the ground truth: skeletons, targets, hand paths, distances.

    python3 -m tools.omg.plot_rollout --model models/omg/tiny_fe_r1 --data data/omg \
        --split test --row 0 --mode grounded --out models/omg/figures/tiny_fe_r1_test0.png

NumPy inference (tools/omg/omg_np.py) plus matplotlib (requirements-plot.txt).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from .omg_np import CONTACT_RADIUS, NumpyOMG


def main(argv=None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", type=Path, required=True)
    ap.add_argument("--data", type=Path, default=Path("data/omg"))
    ap.add_argument("--split", default="test")
    ap.add_argument("--row", type=int, default=0)
    ap.add_argument("--mode", default="grounded", choices=["grounded", "faithful"])
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)

    m = NumpyOMG(args.model)
    cfg = m.cfg
    J, K, n = cfg["J"], cfg["K"], cfg["model_width"]
    d = args.data / cfg["rig"]
    rig = json.loads((d / "rig.json").read_text())
    parents = rig["parents"]
    clip = np.load(d / f"{args.split}.npy", mmap_mode="r")[args.row, :, :n].astype(np.float64)
    roll = m.rollout(clip[None], mode=args.mode)[0]
    T = clip.shape[0]
    sl = m.sl
    gt = clip[:, sl["pos"]].reshape(T, J, 3)
    gen = roll[:, sl["pos"]].reshape(T, J, 3)
    tpos = clip[:, sl["target_pos"]].reshape(T, K, 3)
    hands = cfg["key_joint_indices"][:2]
    colours = ["tab:blue", "tab:red"]
    frames = [0, 75, 150, 225, T - 1]

    fig = plt.figure(figsize=(15, 9))
    views = [("front view (x = character's left, y = up)", 0, 1), ("top view (x = character's left, z = forward)", 0, 2)]
    for vi, (title, a, b) in enumerate(views):
        ax = fig.add_subplot(2, 2, vi + 1)
        for fi, f in enumerate(frames):
            al = 0.25 + 0.75 * fi / (len(frames) - 1)
            for j, p in enumerate(parents):
                if p < 0:
                    continue
                ax.plot(gen[f, [p, j], a], gen[f, [p, j], b], "-", color="k", alpha=al, lw=1.5)
                if f == T - 1:
                    ax.plot(gt[f, [p, j], a], gt[f, [p, j], b], "--", color="tab:green", alpha=0.8, lw=1)
        for h, (hj, c) in enumerate(zip(hands, colours)):
            ax.plot(gen[:, hj, a], gen[:, hj, b], "-", color=c, lw=1.2, label=f"{'LR'[h]} hand, model")
            ax.plot(gt[:, hj, a], gt[:, hj, b], ":", color=c, lw=1.2, label=f"{'LR'[h]} hand, data")
            ch = np.nonzero(np.linalg.norm(np.diff(tpos[:, h], axis=0), axis=1) > 1e-6)[0] + 1
            for i, s in enumerate([0] + ch.tolist()):
                ax.plot(tpos[s, h, a], tpos[s, h, b], "*", color=c, ms=12, mec="k")
                ax.annotate(str(i), (tpos[s, h, a], tpos[s, h, b]), textcoords="offset points", xytext=(5, 5), color=c)
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=9)
        if vi == 0:
            ax.legend(fontsize=7, loc="lower left")
    fig.suptitle(f"model skeleton (black) at frames {frames}, darker = later; data skeleton at frame {T - 1} "
                 "(green dashed); stars = the hands' targets in spawn order", fontsize=9)
    ax = fig.add_subplot(2, 1, 2)
    for h, (hj, c) in enumerate(zip(hands, colours)):
        ax.plot(np.linalg.norm(gen[:, hj] - tpos[:, h], axis=-1), "-", color=c, label=f"{'LR'[h]} hand, model ({args.mode})")
        ax.plot(np.linalg.norm(gt[:, hj] - tpos[:, h], axis=-1), ":", color=c, label=f"{'LR'[h]} hand, data")
    ax.axhline(CONTACT_RADIUS, color="grey", lw=0.8)
    ax.set_xlabel("frame (60 fps)")
    ax.set_ylabel("hand-target distance (m)")
    err = 100 * np.linalg.norm(gen - gt, axis=-1).mean()
    ax.set_title(f"{args.model.name} on {cfg['rig']} {args.split} row {args.row}: {args.mode} rollout from frame 0, "
                 f"driven by the data's targets; mean joint error vs data {err:.1f} cm", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=80)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
