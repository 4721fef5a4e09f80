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
from . import reachable
from .simulate import CONTACT_FRAMES, CONTACT_RADIUS, FRAMES, LAST_SPAWN, TARGET_TIMEOUT, simulate
from .targets import CONTINUOUS_HEIGHT, CONTINUOUS_RADIUS, CYLINDER_HEIGHT, KINDS, plan_clips

SPLIT_SEED = 2021  # the thesis's split seed; the split is by clip and the same for every rig
SPLIT = (0.8, 0.1, 0.1)
FORMAT_VERSION = 2  # 2: reachable targets in synchronised pairs, continuous clips, the dof block


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

    Returns (rig, frames (N, T, W) float32, stats dict, per-clip records: the targets
    each hand was given and how many were spawned)."""
    rig = build_rig(rig_name)
    chunks = []
    per_kind = {k: dict(hand_targets=0, reached=0, given_up=0, pending=0, moved=0) for k in KINDS}
    reach_frames: list[int] = []
    records = []
    by_radius: dict[str, list[int]] = {}
    for i in range(0, len(plans), batch):
        part = plans[i : i + batch]
        sim = simulate(rig, part, params)
        chunks.append(features.assemble(rig, sim))
        reach_frames += sim["reach_frames"]
        for b, p in enumerate(part):
            acc = per_kind[p["kind"]]
            acc["hand_targets"] += int(sim["spawned"][b].sum())
            acc["reached"] += int(sim["reached"][b].sum())
            acc["given_up"] += int(sim["given_up"][b].sum())
            acc["pending"] += int(sim["pending"][b].sum())
            acc["moved"] += int(sim["moved"][b, :, : p["reps"]].sum())
            if p["kind"] == "cylinder":
                r = by_radius.setdefault(f"{p['radius']:.2f} m", [0, 0])
                r[0] += int(sim["reached"][b].sum())
                r[1] += int(sim["spawned"][b].sum())
            n = int(sim["spawned"][b, 0])
            records.append(dict(
                spawned=[n, n],
                targets=np.round(sim["targets"][b, :, :n], 6).tolist(),
                moved=sim["moved"][b, :, :n].tolist(),
            ))
    frames = np.concatenate(chunks, axis=0)
    total = sum(a["hand_targets"] for a in per_kind.values())
    reached = sum(a["reached"] for a in per_kind.values())
    rf = np.array(reach_frames) if reach_frames else np.zeros(1)
    for a in per_kind.values():
        a["reach_rate"] = round(a["reached"] / max(a["hand_targets"], 1), 4)
    stats = dict(
        hand_targets=total,
        reached=reached,
        given_up=sum(a["given_up"] for a in per_kind.values()),
        pending_at_clip_end=sum(a["pending"] for a in per_kind.values()),
        reach_rate=round(reached / max(total, 1), 4),
        reach_rate_by_kind={k: a["reach_rate"] for k, a in per_kind.items()},
        by_kind=per_kind,
        frames_to_contact_median=float(np.median(rf)),
        frames_to_contact_p90=float(np.percentile(rf, 90)),
        reach_rate_by_radius={k: round(a / b, 4) for k, (a, b) in sorted(by_radius.items())},
    )
    return rig, frames, stats, records


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("data/omg"), help="output directory (git-ignored)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the clip plan (targets, rotations)")
    ap.add_argument("--rigs", default=",".join(DEFAULT_RIGS), help="comma-separated rig names")
    ap.add_argument("--full", action="store_true", help="the thesis's 960 cylinder clips per rig instead of 240")
    ap.add_argument("--continuous", type=int, default=None,
                    help="continuous clips per rig (default: as many as cylinder clips)")
    ap.add_argument("--clips", type=int, default=0, help="only the first N clips of the plan (for quick runs)")
    ap.add_argument("--batch", type=int, default=120, help="clips simulated together")
    args = ap.parse_args(argv)

    rig_names = [r.strip() for r in args.rigs.split(",") if r.strip()]
    for r in rig_names:
        if r not in RIG_SPECS:
            ap.error(f"unknown rig {r!r}; known: {', '.join(RIG_SPECS)}")
    plans = plan_clips(args.seed, full=args.full, continuous=args.continuous)
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
        last_spawn_frames=LAST_SPAWN,
        cylinder_height_m=CYLINDER_HEIGHT,
        continuous_shell=dict(radius_m=CONTINUOUS_RADIUS, height_from_pelvis_m=CONTINUOUS_HEIGHT),
        reachability=dict(tol_m=reachable.TOL, spine_share=reachable.SPINE_SHARE,
                          iterations=reachable.ITERATIONS, starts=reachable.STARTS,
                          rule="tools/omg/reachable.py: pairs certified together; continuous "
                          "pairs certified from the rest pose alone"),
        ik=params.to_json(),
        versions=dict(python=platform.python_version(), numpy=np.__version__, scipy=scipy.__version__),
        rigs={},
    )
    t_all = time.time()
    for name in rig_names:
        t0 = time.time()
        rig, frames, stats, records = generate_rig(name, plans, args.batch, params)
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
        clips = [dict(p, split=split_of[i], **records[i]) for i, p in enumerate(plans)]
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
            f"{name}: J={rig.n_joints} width={lay['width']} clips={len(plans)} reach rate "
            f"{stats['reach_rate']:.3f} (cylinder {stats['reach_rate_by_kind']['cylinder']:.3f}, "
            f"continuous {stats['reach_rate_by_kind']['continuous']:.3f}; {secs:.1f} s)",
            flush=True,
        )
    manifest["seconds_total"] = round(time.time() - t_all, 1)
    (args.out / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    print(f"wrote {args.out} in {manifest['seconds_total']:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
