"""Target scripts: the Python twin of ``host-sim/src/omg_rollout/script.rs``.

A target script is a JSON file of timed targets for the key joints (format: the Rust
module's documentation)::

    {"name": "...", "description": "...", "frames": 300, "targets": [
        {"frame": 0, "joint": "LeftHand", "position": [0.25, 1.2, 0.35]},
        {"frame": 90, "joint": "LeftHand", "position": [0.25, 1.2, 0.35],
         "to": [0.25, 1.6, 0.35], "until": 150},
        {"frame": 200, "joint": 0, "position": [0.316, 1.036, -0.01], "unreachable": false}]}

:func:`load`, :func:`blocks` and :func:`intervals` have exactly the Rust semantics: the
same checks (refused with the same one-line messages, as ``ValueError``), the same
defaults (a target holds until changed; ``forward``/``up`` default to the joint's current
target axes and are normalised; key joints never named keep the start block) and the same
arithmetic in float64, in the same order: axes are divided by
``sqrt(((0 + x*x) + y*y) + z*z)`` and a moving target's position at frame ``t`` (``frame
< t < until``) is ``p + (to - p) * ((t - frame) / (until - frame))`` per coordinate, with
the frame quotient formed from two exactly representable integers (Python's int / int and
Rust's ``as f64 / as f64`` are both the correctly rounded quotient), and exactly ``to``
from ``until`` on. The two therefore agree to the last bit.

The committed evaluation scripts are in ``tools/omg/scripts/`` (README there);
``tools/omg/scripts/expected.json`` holds what this module computes for each of them (a
fixed start block, the intervals and checksums of the blocks), and a Rust test compares
``script.rs`` with it. Regenerate it after changing a script::

    PYTHONPATH=. python3 -m tools.omg.scripts --expected tools/omg/scripts/expected.json
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

DEFAULT_FRAMES = 300
MAX_FRAMES = 60 * 60 * 60  # an hour at 60 frames per second
MAX_TARGET_M = 100.0  # phasegate_controller::reach::MAX_TARGET_M

SCRIPT_DIR = Path(__file__).resolve().parent / "scripts"
EXPECTED = SCRIPT_DIR / "expected.json"

_SCRIPT_FIELDS = {"name", "description", "frames", "targets"}
_TARGET_FIELDS = {"frame", "joint", "position", "forward", "up", "to", "until", "unreachable"}


# ----------------------------------------------------------------------------------
# Loading (serde's view of the JSON: unknown fields refused, types checked)
# ----------------------------------------------------------------------------------


def _is_uint(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def _is_vec3(v) -> bool:
    return (isinstance(v, list) and len(v) == 3
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v))


def parse(obj, where: str = "script") -> dict:
    """A script from its parsed JSON: fields checked, optional ones filled with their
    defaults (``None``, ``unreachable`` False), coordinates as floats."""
    if not isinstance(obj, dict):
        raise ValueError(f"{where}: not a target script (not an object)")
    extra = set(obj) - _SCRIPT_FIELDS
    if extra:
        raise ValueError(f"{where}: not a target script (unknown field {sorted(extra)[0]!r})")
    if "targets" not in obj or not isinstance(obj["targets"], list):
        raise ValueError(f"{where}: not a target script (no list of targets)")
    for f in ("name", "description"):
        if obj.get(f) is not None and not isinstance(obj[f], str):
            raise ValueError(f"{where}: not a target script ({f} is not a string)")
    if obj.get("frames") is not None and not _is_uint(obj["frames"]):
        raise ValueError(f"{where}: not a target script (frames is not a count)")
    targets = []
    for i, t in enumerate(obj["targets"]):
        bad = f"{where}: not a target script (targets[{i}]"
        if not isinstance(t, dict):
            raise ValueError(f"{bad} is not an object)")
        extra = set(t) - _TARGET_FIELDS
        if extra:
            raise ValueError(f"{bad}: unknown field {sorted(extra)[0]!r})")
        for f in ("frame", "joint", "position"):
            if f not in t:
                raise ValueError(f"{bad}: no {f})")
        if not _is_uint(t["frame"]):
            raise ValueError(f"{bad}: frame is not a frame number)")
        if t.get("until") is not None and not _is_uint(t["until"]):
            raise ValueError(f"{bad}: until is not a frame number)")
        if not _is_vec3(t["position"]):
            raise ValueError(f"{bad}: position is not 3 numbers)")
        for f in ("forward", "up", "to"):
            if t.get(f) is not None and not _is_vec3(t[f]):
                raise ValueError(f"{bad}: {f} is not 3 numbers)")
        if "unreachable" in t and not isinstance(t["unreachable"], bool):
            raise ValueError(f"{bad}: unreachable is not true or false)")
        vec = lambda v: None if v is None else [float(x) for x in v]  # noqa: E731
        targets.append({
            "frame": t["frame"],
            "joint": t["joint"],
            "position": vec(t["position"]),
            "forward": vec(t.get("forward")),
            "up": vec(t.get("up")),
            "to": vec(t.get("to")),
            "until": t.get("until"),
            "unreachable": t.get("unreachable", False),
        })
    return {
        "name": obj.get("name"),
        "description": obj.get("description"),
        "frames": obj.get("frames"),
        "targets": targets,
    }


def load(path) -> dict:
    """A target script from a JSON file (see :func:`parse`)."""
    path = Path(path)
    with open(path, encoding="utf-8") as f:
        obj = json.load(f)
    return parse(obj, str(path))


def script_frames(script: dict) -> int:
    """The script's own length (DEFAULT_FRAMES when it does not say)."""
    return DEFAULT_FRAMES if script["frames"] is None else script["frames"]


# ----------------------------------------------------------------------------------
# Semantics
# ----------------------------------------------------------------------------------


def _json_value(v) -> str:
    """A joint value as serde_json displays it (for the messages)."""
    return json.dumps(v, separators=(",", ":"), ensure_ascii=False)


def _rust_float(v: float) -> str:
    """A non-finite float as Rust displays it."""
    return "NaN" if math.isnan(v) else repr(v)


def key_index(key_joint_names, joint) -> int:
    """A key joint named (string) or numbered (non-negative integer) in a script."""
    names = list(key_joint_names)
    found = None
    if isinstance(joint, str):
        found = names.index(joint) if joint in names else None
    elif _is_uint(joint) and joint < len(names):
        found = joint
    if found is None:
        listed = "[" + ", ".join(_json_value(n) for n in names) + "]"  # Rust's {:?}
        raise ValueError(f"unknown key joint {_json_value(joint)}: the model's key joints are "
                         f"{listed} (or 0..{len(names)})")
    return found


def position_at(t: dict, frame: int) -> list[float]:
    """Entry ``t``'s target position at ``frame`` (at or after its own frame)."""
    p, to, until = t["position"], t["to"], t["until"]
    if to is None or until is None:
        return list(p)
    if frame >= until or until <= t["frame"]:
        return list(to)
    if frame <= t["frame"]:
        return list(p)
    s = (frame - t["frame"]) / (until - t["frame"])
    return [p[c] + (to[c] - p[c]) * s for c in range(3)]


def _norm2(v) -> float:
    """Squared length, summed as Rust's ``iter().map(|v| v * v).sum()``."""
    return ((0.0 + v[0] * v[0]) + v[1] * v[1]) + v[2] * v[2]


def _unit(v) -> list[float]:
    n = math.sqrt(_norm2(v))
    return [x / n for x in v]


def _check_frames(script: dict, frames: int) -> None:
    if frames > MAX_FRAMES or (script["frames"] is not None and script["frames"] > MAX_FRAMES):
        raise ValueError(f"more than {MAX_FRAMES} frames (an hour at 60 per second)")


def _checked(script: dict, key_joint_names, frames: int) -> list[tuple[int, int, dict]]:
    """(index, key, entry) of every entry, checked, sorted by (frame, key)."""
    _check_frames(script, frames)
    names = list(key_joint_names)
    end = frames if script["frames"] is None else max(script["frames"], frames)
    events = []
    for i, t in enumerate(script["targets"]):
        at = f"target {i} (frame {t['frame']}, joint {_json_value(t['joint'])})"
        try:
            key = key_index(names, t["joint"])
        except ValueError as e:
            raise ValueError(f"{at}: {e}") from None
        if t["frame"] >= end:
            raise ValueError(f"{at}: the script has {end} frames")
        if t["to"] is not None and t["until"] is None:
            raise ValueError(f'{at}: "to" needs "until" (the frame it arrives)')
        if t["until"] is not None and t["to"] is None:
            raise ValueError(f'{at}: "until" needs "to" (where it arrives)')
        values = list(t["position"])
        for f in ("forward", "up", "to"):
            values += t[f] or []
        for v in values:
            if not math.isfinite(v):
                raise ValueError(f"{at}: value {_rust_float(v)} is not finite")
        for p in (t["position"], t["to"]):
            if p is not None and any(abs(v) > MAX_TARGET_M for v in p):
                raise ValueError(f"{at}: position beyond {MAX_TARGET_M:g} m")
        for axis in (t["forward"], t["up"]):
            if axis is not None and _norm2(axis) < 1e-12:
                raise ValueError(f"{at}: an axis of no length")
        if t["until"] is not None:
            if t["until"] <= t["frame"]:
                raise ValueError(f"{at}: until {t['until']} is not after frame {t['frame']}")
            if t["until"] >= end:
                raise ValueError(f"{at}: until {t['until']} is past the script's {end} frames")
        events.append((i, key, t))
    events.sort(key=lambda e: (e[2]["frame"], e[1]))  # stable, as Rust's sort_by_key
    for (ia, ka, a), (ib, kb, b) in zip(events, events[1:]):
        if (a["frame"], ka) == (b["frame"], kb):
            raise ValueError(
                f"target {ib} (frame {b['frame']}, joint {_json_value(b['joint'])}): a second "
                f"target for key joint {names[kb]} at frame {b['frame']} (target {ia} is the first)")
    return events


def blocks(script: dict, key_joint_names, start_block, frames: int) -> np.ndarray:
    """(frames, 9K) float64: the target block of every frame (K positions, then K forward
    + up pairs), starting from ``start_block`` (9K,)."""
    k = len(key_joint_names)
    _check_frames(script, frames)
    start = [float(v) for v in np.asarray(start_block, dtype=np.float64).reshape(-1)]
    if len(start) != 9 * k:
        raise ValueError(f"target block of {len(start)} values, the model has {k} key joints")
    events = _checked(script, key_joint_names, frames)
    block = list(start)
    current: list[dict | None] = [None] * k
    out = np.empty((frames, 9 * k), dtype=np.float64)
    e = 0
    for f in range(frames):
        while e < len(events) and events[e][2]["frame"] == f:
            _, key, t = events[e]
            r = 3 * k + 6 * key
            if t["forward"] is not None:
                block[r:r + 3] = _unit(t["forward"])
            if t["up"] is not None:
                block[r + 3:r + 6] = _unit(t["up"])
            current[key] = t
            e += 1
        for key, t in enumerate(current):
            if t is not None:
                block[3 * key:3 * key + 3] = position_at(t, f)
        out[f] = block
    return out


def intervals(script: dict, key_joint_names, frames: int) -> list[dict]:
    """The frames each entry is its key joint's target, sorted by (start, key): dicts
    ``index`` (entry), ``key``, ``start``, ``end`` (exclusive: the key joint's next entry,
    or ``frames``), ``moving``, ``unreachable``; entries at or past ``frames`` dropped."""
    events = [e for e in _checked(script, key_joint_names, frames) if e[2]["frame"] < frames]
    next_start = [frames] * len(key_joint_names)
    out: list[dict] = [None] * len(events)  # type: ignore[list-item]
    for slot in range(len(events) - 1, -1, -1):
        i, key, t = events[slot]
        out[slot] = {
            "index": i, "key": key, "start": t["frame"], "end": next_start[key],
            "moving": t["to"] is not None, "unreachable": bool(t["unreachable"]),
        }
        next_start[key] = t["frame"]
    return out


# ----------------------------------------------------------------------------------
# The committed scripts: start block, expected results, reachability points
# ----------------------------------------------------------------------------------


def script_files(directory=SCRIPT_DIR) -> list[Path]:
    """The committed scripts (every ``*.json`` but ``expected.json``), sorted by name."""
    return sorted(p for p in Path(directory).glob("*.json") if p.name != "expected.json")


def start_block(rig_name: str = "R1") -> np.ndarray:
    """(9K,) the fixed start block of the expected results: the rig's rest positions of
    the key joints, every forward (0, 0, 1) and up (0, 1, 0)."""
    from .rigs import K, build_rig, rest_positions

    rig = build_rig(rig_name)
    rest = rest_positions(rig)[rig.key_joints]
    axes = np.tile([0.0, 0.0, 1.0, 0.0, 1.0, 0.0], K)
    return np.concatenate([rest.reshape(-1), axes])


def sample_frames(ivs: list[dict], script: dict, frames: int) -> list[int]:
    """Frames whose whole block expected.json records: 0, the last, every interval's
    start and last frame, and for a moving one its midway and arrival frames."""
    out = {0, frames - 1}
    for iv in ivs:
        out.update((iv["start"], iv["end"] - 1))
        if iv["moving"]:
            until = script["targets"][iv["index"]]["until"]
            out.add((iv["start"] + min(until, iv["end"])) // 2)
            if until < iv["end"]:
                out.add(until)
    return sorted(out)


def expected(directory=SCRIPT_DIR) -> dict:
    """What expected.json holds: the start block and, per script file, its frames, its
    intervals, the sum and sum of squares of all its block values (summed frame by
    frame, value by value, in float64) and its block at :func:`sample_frames`."""
    from .rigs import KEY_JOINT_NAMES

    start = start_block("R1")
    out = {
        "about": "Python's results for tools/omg/scripts/*.json (tools/omg/scripts.py); "
                 "regenerate with PYTHONPATH=. python3 -m tools.omg.scripts --expected "
                 "tools/omg/scripts/expected.json; host-sim's script.rs test compares with it",
        "rig": "R1",
        "key_joints": list(KEY_JOINT_NAMES),
        "start_block": [float(v) for v in start],
        "scripts": {},
    }
    for path in script_files(directory):
        s = load(path)
        n = script_frames(s)
        b = blocks(s, KEY_JOINT_NAMES, start, n)
        ivs = intervals(s, KEY_JOINT_NAMES, n)
        total, total_sq = 0.0, 0.0
        for row in b.tolist():
            for v in row:
                total += v
                total_sq += v * v
        out["scripts"][path.name] = {
            "frames": n,
            "intervals": ivs,
            "sum": total,
            "sum_sq": total_sq,
            "samples": [[f, b[f].tolist()] for f in sample_frames(ivs, s, n)],
        }
    return out


def expected_text(directory=SCRIPT_DIR) -> str:
    """expected.json's text: one line per interval, per sampled block and per list."""
    e = expected(directory)
    one = lambda v: json.dumps(v, separators=(", ", ": "))  # noqa: E731
    lines = ["{"]
    for k in ("about", "rig", "key_joints", "start_block"):
        lines.append(f"  {one(k)}: {one(e[k])},")
    lines.append('  "scripts": {')
    names = list(e["scripts"])
    for n, name in enumerate(names):
        r = e["scripts"][name]
        lines.append(f"    {one(name)}: {{")
        lines.append(f'      "frames": {r["frames"]},')
        lines.append(f'      "sum": {one(r["sum"])},')
        lines.append(f'      "sum_sq": {one(r["sum_sq"])},')
        lines.append('      "intervals": [')
        lines += [f"        {one(iv)}" + ("," if i < len(r["intervals"]) - 1 else "")
                  for i, iv in enumerate(r["intervals"])]
        lines.append("      ],")
        lines.append('      "samples": [')
        lines += [f"        {one(sm)}" + ("," if i < len(r["samples"]) - 1 else "")
                  for i, sm in enumerate(r["samples"])]
        lines.append("      ]")
        lines.append("    }" + ("," if n < len(names) - 1 else ""))
    lines += ["  }", "}"]
    text = "\n".join(lines) + "\n"
    assert json.loads(text) == e
    return text


def check_points(script: dict, key_joint_names) -> list[tuple[int, int, np.ndarray]]:
    """(entry index, key, points (M, 3)) for every entry: the points whose reachability
    the committed scripts guarantee: its position, and for a moving target also ``to``
    and its path at every 5th frame after ``frame`` (the whole path to ``until``, even
    when a later entry interrupts it)."""
    out = []
    for i, t in enumerate(script["targets"]):
        key = key_index(key_joint_names, t["joint"])
        pts = [t["position"]]
        if t["to"] is not None:
            pts += [position_at(t, f) for f in range(t["frame"] + 5, t["until"], 5)]
            pts.append(t["to"])
        out.append((i, key, np.asarray(pts, dtype=np.float64)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python3 -m tools.omg.scripts", description=__doc__.split("\n")[0])
    ap.add_argument("--expected", metavar="PATH", help="write the expected results of the committed scripts")
    ap.add_argument("--table", action="store_true", help="print a summary of each committed script")
    args = ap.parse_args(argv)
    if args.expected:
        Path(args.expected).write_text(expected_text(), encoding="utf-8")
        print(f"wrote {args.expected} ({len(script_files())} scripts)")
    if args.table:
        from .rigs import KEY_JOINT_NAMES

        for path in script_files():
            s = load(path)
            ivs = intervals(s, KEY_JOINT_NAMES, script_frames(s))
            per = [sum(1 for iv in ivs if iv["key"] == k) for k in (0, 1)]
            flags = [f for f, on in (("moving", any(iv["moving"] for iv in ivs)),
                                     ("unreachable", any(iv["unreachable"] for iv in ivs))) if on]
            print(f"{path.name:40s} L{per[0]} R{per[1]} {script_frames(s)} {' '.join(flags)}")
    if not (args.expected or args.table):
        ap.print_help()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
