"""Generate the synthetic OMG reaching data set.

    python3 -m tools.omg.generate --out data/omg --seed 0

writes, per rig, ``<out>/<rig>/{train,val,test}.npy`` (float32, clips x 300 x width),
``layout.json`` (block offsets and sizes), ``rig.json`` (hierarchy, rest pose, limits),
``clips.json`` (the plan of every clip and its split), and ``<out>/manifest.json``
(seed, versions, parameters, timings, reach statistics).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import scipy

from . import features
from .ik import IKParams
from .rigs import DEFAULT_RIGS, RIG_SPECS, build_rig
from .simulate import CONTACT_FRAMES, CONTACT_RADIUS, FRAMES, TARGET_TIMEOUT, simulate
from .targets import CYLINDER_HEIGHT, plan_clips

SPLIT_SEED = 2021  # the thesis's split seed; the split is by clip and the same for every rig
SPLIT = (0.8, 0.1, 0.1)
FORMAT_VERSION = 1


def split_clips(n: int) -> dict:
    """80/10/10 split of clip indices by a fixed seed."""
    perm = np.random.default_rng(SPLIT_SEED).permutation(n)
    n_train = int(round(SPLIT[0] * n))
    n_val = int(round(SPLIT[1] * n))
    return {
        "train": np.sort(perm[:n_train]),
        "val": np.sort(perm[n_train : n_train + n_val]),
        "test": np.sort(perm[n_train + n_val :]),
    }


def generate_rig(rig_name: str, plans: list[dict], batch: int, params: IKParams):
    """Simulate and featurise all clips of ``plans`` on one rig.

    Returns (rig, frames (N, T, W) float32, stats dict)."""
    rig = build_rig(rig_name)
    chunks = []
    reached = given_up = pending = 0
    reach_frames: list[int] = []
    by_radius: dict[str, list[int]] = {}
    for i in range(0, len(plans), batch):
        part = plans[i : i + batch]
        sim = simulate(rig, part, params)
        chunks.append(features.assemble(rig, sim))
        reached += int(sim["reached"].sum())
        given_up += int(sim["given_up"].sum())
        pending += int(sim["pending"].sum())
        reach_frames += sim["reach_frames"]
        for p, r in zip(part, sim["reached"].sum(axis=1)):
            acc = by_radius.setdefault(f"{p['radius']:.2f} m", [0, 0])
            acc[0] += int(r)
            acc[1] += 2 * p["reps"]
    frames = np.concatenate(chunks, axis=0)
    total = sum(2 * p["reps"] for p in plans)
    rf = np.array(reach_frames) if reach_frames else np.zeros(1)
    stats = dict(
        hand_targets=total,
        reached=reached,
        given_up=given_up,
        pending_at_clip_end=pending,
        reach_rate=round(reached / total, 4),
        frames_to_contact_median=float(np.median(rf)),
        frames_to_contact_p90=float(np.percentile(rf, 90)),
        reach_rate_by_radius={k: round(a / b, 4) for k, (a, b) in sorted(by_radius.items())},
    )
    return rig, frames, stats


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("data/omg"), help="output directory (git-ignored)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the clip plan (targets, rotations)")
    ap.add_argument("--rigs", default=",".join(DEFAULT_RIGS), help="comma-separated rig names")
    ap.add_argument("--full", action="store_true", help="the thesis's 960 clips per rig instead of 240")
    ap.add_argument("--clips", type=int, default=0, help="only the first N clips of the plan (for quick runs)")
    ap.add_argument("--batch", type=int, default=120, help="clips simulated together")
    args = ap.parse_args(argv)

    rig_names = [r.strip() for r in args.rigs.split(",") if r.strip()]
    for r in rig_names:
        if r not in RIG_SPECS:
            ap.error(f"unknown rig {r!r}; known: {', '.join(RIG_SPECS)}")
    plans = plan_clips(args.seed, full=args.full)
    if args.clips:
        plans = plans[: args.clips]
    splits = split_clips(len(plans))
    split_of = {int(c): name for name, idx in splits.items() for c in idx}
    params = IKParams()
    args.out.mkdir(parents=True, exist_ok=True)

    manifest = dict(
        format_version=FORMAT_VERSION,
        command=" ".join(["python3 -m tools.omg.generate"] + (argv if argv is not None else sys.argv[1:])),
        seed=args.seed,
        split_seed=SPLIT_SEED,
        split=dict(zip(("train", "val", "test"), SPLIT)),
        clips_per_rig=len(plans),
        frames_per_clip=FRAMES,
        contact_radius_m=CONTACT_RADIUS,
        contact_frames=CONTACT_FRAMES,
        target_timeout_frames=TARGET_TIMEOUT,
        cylinder_height_m=CYLINDER_HEIGHT,
        ik=params.to_json(),
        versions=dict(python=platform.python_version(), numpy=np.__version__, scipy=scipy.__version__),
        rigs={},
    )
    t_all = time.time()
    for name in rig_names:
        t0 = time.time()
        rig, frames, stats = generate_rig(name, plans, args.batch, params)
        d = args.out / name
        d.mkdir(parents=True, exist_ok=True)
        for split, idx in splits.items():
            np.save(d / f"{split}.npy", frames[idx])
        lay = features.layout(rig)
        lay["frames_per_clip"] = FRAMES
        lay["files"] = {s: f"{s}.npy" for s in splits}
        lay["dtype"] = "float32"
        (d / "layout.json").write_text(json.dumps(lay, indent=1) + "\n")
        (d / "rig.json").write_text(json.dumps(rig.to_json(), indent=1) + "\n")
        clips = [dict(p, split=split_of[i]) for i, p in enumerate(plans)]
        for split, idx in splits.items():
            for row, c in enumerate(idx):
                clips[c]["row"] = row
        (d / "clips.json").write_text(json.dumps(clips) + "\n")
        secs = time.time() - t0
        manifest["rigs"][name] = dict(
            joints=rig.n_joints,
            dofs=rig.n_dofs,
            width=lay["width"],
            model_width=lay["model_width"],
            clips={s: int(len(i)) for s, i in splits.items()},
            seconds=round(secs, 1),
            **stats,
        )
        print(
            f"{name}: J={rig.n_joints} width={lay['width']} clips={len(plans)} "
            f"reach rate {stats['reach_rate']:.2f} ({secs:.1f} s)",
            flush=True,
        )
    manifest["seconds_total"] = round(time.time() - t_all, 1)
    (args.out / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    print(f"wrote {args.out} in {manifest['seconds_total']:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
