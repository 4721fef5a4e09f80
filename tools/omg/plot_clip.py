"""Draw one generated clip: skeleton at a few frames, targets, hand paths, distances, phases.

    python3 -m tools.omg.plot_clip --data data/omg --rig R1 --split test --row 8 \
        --out tools/omg/figures/R1_test_row8.png

Needs matplotlib (``requirements-plot.txt``); reads only the files the generator wrote.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def load_clip(data: Path, rig: str, split: str, row: int):
    d = data / rig
    lay = json.loads((d / "layout.json").read_text())
    rig_json = json.loads((d / "rig.json").read_text())
    clips = json.loads((d / "clips.json").read_text())
    meta = next(c for c in clips if c["split"] == split and c["row"] == row)
    X = np.load(d / f"{split}.npy", mmap_mode="r")[row].astype(np.float64)
    blocks = {}
    for b in lay["blocks"]:
        v = X[:, b["offset"] : b["offset"] + b["size"]]
        blocks[b["name"]] = v.reshape(X.shape[0], len(b["items"]), len(b["components"]))
    return blocks, rig_json, meta


def main(argv=None) -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("data/omg"))
    ap.add_argument("--rig", default="R1")
    ap.add_argument("--split", default="test")
    ap.add_argument("--row", type=int, default=8)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)

    b, rig, meta = load_clip(args.data, args.rig, args.split, args.row)
    pos, tpos, contact, phase = b["pos"], b["target_pos"], b["contact"][..., 0], b["phase"]
    parents = rig["parents"]
    T = pos.shape[0]
    hands = [rig["key_joints"]["LeftHand"], rig["key_joints"]["RightHand"]]
    colours = ["tab:blue", "tab:red"]

    # Frames to draw: start, first contact frame of each new target, end.
    show = [0]
    for h in range(2):
        c = contact[:, h] > 0.5
        starts = np.nonzero(c[1:] & ~c[:-1])[0] + 1
        show += starts.tolist()
    show = sorted(set(show + [T - 1]))
    if len(show) > 6:
        show = [show[i] for i in np.linspace(0, len(show) - 1, 6).round().astype(int)]

    fig = plt.figure(figsize=(14, 10))
    title = (
        f"{args.rig} ({len(parents)} joints), {args.split} clip row {args.row} (plan clip {meta['clip']}): "
        f"{meta['reps']} repetition(s), radius {meta['radius']} m, {meta['mode']}, "
        f"{'random' if meta['rotate'] else 'no'} target rotation"
    )
    fig.suptitle(title, fontsize=11)

    def draw_view(ax, ix, iy, xlabel, ylabel, name):
        cmap = plt.get_cmap("viridis")
        for n, t in enumerate(show):
            col = cmap(n / max(len(show) - 1, 1))
            for j, p in enumerate(parents):
                if p >= 0:
                    ax.plot(pos[t, [p, j], ix], pos[t, [p, j], iy], color=col, lw=1.2, alpha=0.8)
            ax.plot([], [], color=col, label=f"frame {t}")
        for h in range(2):
            ax.plot(pos[:, hands[h], ix], pos[:, hands[h], iy], color=colours[h], lw=1.5, ls="--")
            uniq = np.unique(tpos[:, h].round(6), axis=0)
            ax.scatter(uniq[:, ix], uniq[:, iy], marker="x", s=70, color=colours[h], zorder=5)
        ax.set_aspect("equal")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.set_title(name, fontsize=10)
        ax.grid(alpha=0.3)

    ax1 = fig.add_subplot(2, 2, 1)
    draw_view(ax1, 0, 1, "x (m, character's left)", "y (m, up)", "front view (skeleton at marked frames)")
    ax1.set_xlim(0.8, -0.8)  # seen from the front: the character's left on the viewer's right
    ax1.legend(fontsize=7, loc="lower left")
    ax2 = fig.add_subplot(2, 2, 2)
    draw_view(ax2, 0, 2, "x (m, character's left)", "z (m, forward)", "top view; x = targets, dashed = hand paths (blue left, red right)")
    theta = np.linspace(0, 2 * np.pi, 100)
    ax2.plot(meta["radius"] * np.sin(theta), meta["radius"] * np.cos(theta), color="grey", lw=0.8, ls=":")
    ax2.invert_xaxis()

    t = np.arange(T)
    ax3 = fig.add_subplot(2, 2, 3)
    for h, name in enumerate(("left hand", "right hand")):
        dist = np.linalg.norm(tpos[:, h] - pos[:, hands[h]], axis=-1)
        ax3.plot(t, dist, color=colours[h], label=f"{name} to target")
        ax3.fill_between(t, 0, contact[:, h] * 0.05, color=colours[h], alpha=0.3, step="mid")
    ax3.axhline(0.1, color="k", lw=0.8, ls=":", label="contact radius 0.1 m")
    ax3.set_xlabel("frame (60 fps)")
    ax3.set_ylabel("m")
    ax3.set_title("hand-target distance; shaded = contact flag", fontsize=10)
    ax3.legend(fontsize=8)
    ax3.grid(alpha=0.3)

    ax4 = fig.add_subplot(2, 2, 4)
    for h, name in enumerate(("left hand", "right hand")):
        ax4.plot(t, phase[:, h, 0], color=colours[h], label=f"{name} sin term")
        ax4.plot(t, phase[:, h, 1], color=colours[h], ls="--", label=f"{name} cos term")
    ax4.plot(t, phase[:, 2:].reshape(T, -1).sum(axis=1), color="grey", lw=0.8, label="feet (all terms)")
    ax4.set_xlabel("frame (60 fps)")
    ax4.set_title("local motion phase vector (eq 3.3)", fontsize=10)
    ax4.legend(fontsize=7, ncol=2)
    ax4.grid(alpha=0.3)

    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}; frames drawn: {show}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
