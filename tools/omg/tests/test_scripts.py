"""The committed evaluation target scripts (tools/omg/scripts/) and their loader.

The scripts are a test set written by hand from the rig's geometry; these tests check
that they are what tools/omg/scripts/README.md says (coverage, reachability, timing),
that tools/omg/scripts.py has the semantics of host-sim's script.rs (values written out
by hand here; the Rust test ``committed_scripts_match_the_python_twin`` compares the two
on every script through expected.json) and that expected.json is up to date.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from tools.omg import scripts as sc
from tools.omg.reachable import closest_reach, is_pair_reachable, is_reachable
from tools.omg.rigs import KEY_JOINT_NAMES, build_rig

HANDS = ("LeftHand", "RightHand")
REST = {0: np.array([0.316, 1.036, -0.01]), 1: np.array([-0.316, 1.036, -0.01])}
CHANGED_WITHIN = 30  # frames: a target replaced this soon was changed before arrival


@pytest.fixture(scope="module")
def committed():
    """[(file name, script)] of every committed script."""
    return [(p.name, sc.load(p)) for p in sc.script_files()]


@pytest.fixture(scope="module")
def rig():
    return build_rig("R1")


def _intervals(s):
    return sc.intervals(s, KEY_JOINT_NAMES, sc.script_frames(s))


def _changed_before_arrival(s) -> list[int]:
    """Entries replaced within CHANGED_WITHIN frames of appearing (a moving one: also
    before its ``until``) by an entry of the same hand more than 0.1 m from where the
    replaced target is then (a moving chain's next segment, starting where the last one
    ends, is not a change)."""
    out = []
    ivs = _intervals(s)
    for iv in ivs:
        t = s["targets"][iv["index"]]
        nxt = [j for j in ivs if j["key"] == iv["key"] and j["start"] == iv["end"]]
        if not nxt or iv["end"] - iv["start"] > CHANGED_WITHIN:
            continue
        if t["until"] is not None and t["until"] <= iv["end"]:
            continue  # it arrived
        here = np.array(sc.position_at(t, iv["end"]))
        if np.linalg.norm(np.array(s["targets"][nxt[0]["index"]]["position"]) - here) > 0.1:
            out.append(iv["index"])
    return out


def test_every_script_loads_with_a_name_a_description_and_its_frames(committed):
    assert len(committed) >= 24
    names = [s["name"] for _, s in committed]
    assert len(set(names)) == len(names), "names unique"
    numbers = []
    for fname, s in committed:
        m = re.fullmatch(r"(\d\d)-[a-z0-9-]+\.json", fname)
        assert m, fname
        numbers.append(int(m.group(1)))
        assert s["name"] and s["description"], fname
        assert s["description"].endswith(".") and s["description"].count(". ") == 0, fname
        assert s["frames"] in (300, 360), fname
        assert all(t["joint"] in HANDS for t in s["targets"]), f"{fname}: hands, by name"
        n = sc.script_frames(s)
        b = sc.blocks(s, KEY_JOINT_NAMES, sc.start_block(), n)
        assert b.shape == (n, 36) and np.isfinite(b).all()
        assert _intervals(s)[0]["start"] == 0, f"{fname}: something to do from the start"
    assert sorted(numbers) == list(range(1, len(numbers) + 1)), "numbered 01, 02, ..."


def test_the_set_covers_moving_changed_and_one_unreachable_target(committed):
    moving = [f for f, s in committed if any(t["to"] is not None for t in s["targets"])]
    changed = [f for f, s in committed if _changed_before_arrival(s)]
    unreachable = [(f, i) for f, s in committed for i, t in enumerate(s["targets"]) if t["unreachable"]]
    assert len(moving) >= 4, moving
    assert len(changed) >= 3, changed
    assert len(unreachable) == 1, unreachable
    # Every replacement of a changed target came 10-25 frames after it appeared.
    for f, s in committed:
        for i in _changed_before_arrival(s):
            iv = next(iv for iv in _intervals(s) if iv["index"] == i)
            assert 10 <= iv["end"] - iv["start"] <= 25, (f, i)
    both = [f for f, s in committed if {t["joint"] for t in s["targets"]} == set(HANDS)]
    one = [f for f, s in committed if len({t["joint"] for t in s["targets"]}) == 1]
    assert len(both) >= 6 and len(one) >= 6
    rests = [f for f, s in committed
             if any(np.allclose(t["position"], REST[HANDS.index(t["joint"])], atol=0.01)
                    for t in s["targets"])]
    assert len(rests) >= 10, "several scripts return to rest"
    longest = max(sum(1 for t in s["targets"] if t["joint"] == h and not
                      np.allclose(t["position"], REST[HANDS.index(h)], atol=0.01))
                  for _, s in committed for h in HANDS)
    assert longest >= 4, "a sequence of 4 targets"


def test_every_target_is_reachable_and_the_unreachable_one_is_not(committed, rig):
    """Plain geometric reachability (the whole spine range, ``spine_share=1``): every
    target point of each hand alone, and the two hands' targets together at every 5th
    frame (they share the spine), except while one of them is the marked unreachable one;
    the unreachable one is farther than 0.15 m from anything the hand can reach."""
    pts = {0: [], 1: []}
    where = {0: [], 1: []}
    far = []
    for fname, s in committed:
        for i, key, p in sc.check_points(s, KEY_JOINT_NAMES):
            if s["targets"][i]["unreachable"]:
                far.append((fname, i, key, p))
            else:
                pts[key].append(p)
                where[key] += [(fname, i)] * len(p)
    for key in (0, 1):
        p = np.concatenate(pts[key])
        ok = is_reachable(rig, key, p, spine_share=1.0)
        bad = [(where[key][j], p[j].tolist()) for j in np.nonzero(~ok)[0]]
        assert not bad, f"{HANDS[key]}: not certified reachable: {bad}"
    left, right, at = [], [], []
    start = sc.start_block()
    for fname, s in committed:
        frames = sc.script_frames(s)
        blocks = sc.blocks(s, KEY_JOINT_NAMES, start, frames)
        far_ivs = [iv for iv in _intervals(s) if iv["unreachable"]]
        for t in range(0, frames, 5):
            if any(iv["start"] <= t < iv["end"] for iv in far_ivs):
                continue
            left.append(blocks[t, 0:3])
            right.append(blocks[t, 3:6])
            at.append((fname, t))
    ok = is_pair_reachable(rig, np.array(left), np.array(right), spine_share=1.0)
    bad = [at[j] for j in np.nonzero(~ok)[0]]
    assert not bad, f"target pairs not certified reachable together: {bad}"
    for fname, i, key, p in far:
        d, _ = closest_reach(rig, key, p, spine_share=1.0)
        assert (d > 0.15).all(), (fname, i, d)


def test_no_target_inside_the_torso(committed):
    for fname, s in committed:
        for i, _, p in sc.check_points(s, KEY_JOINT_NAMES):
            torso = (p[:, 1] >= 1.0) & (p[:, 1] <= 1.65)
            inside = torso & (p[:, 2] <= 0.11) & (np.abs(p[:, 0]) <= 0.22)
            assert not inside.any(), (fname, i, p[inside].tolist())


def test_timing_is_human(committed):
    """A held target lasts at least 60 frames unless it is changed before arrival (within
    30); a moving target moves at most 1 m/s (60 frames a second); most targets appear
    more than 0.1 m from the hand (taken to be where its previous target is, or at rest)."""
    away = total = 0
    for fname, s in committed:
        changed = set(_changed_before_arrival(s))
        last = {}
        for iv in _intervals(s):
            t = s["targets"][iv["index"]]
            if t["to"] is not None:
                speed = np.linalg.norm(np.subtract(t["to"], t["position"])) / (t["until"] - t["frame"]) * 60
                assert speed <= 1.0, (fname, iv["index"], speed)
                assert t["until"] <= iv["end"] or iv["index"] in changed, f"{fname}: {iv} cut short"
            elif iv["index"] not in changed:
                assert iv["end"] - iv["start"] >= 60, (fname, iv)
            prev = last.get(iv["key"])
            hand = REST[iv["key"]] if prev is None else np.array(sc.position_at(prev, iv["start"]))
            total += 1
            away += np.linalg.norm(np.array(t["position"]) - hand) > 0.1
            last[iv["key"]] = t
    assert away >= 0.8 * total, (away, total)


def test_expected_json_is_up_to_date():
    """tools/omg/scripts/expected.json is what the scripts give now (regenerate with
    ``PYTHONPATH=. python3 -m tools.omg.scripts --expected tools/omg/scripts/expected.json``)."""
    committed = json.loads(sc.EXPECTED.read_text(encoding="utf-8"))
    assert committed == json.loads(sc.expected_text())
    assert len(committed["start_block"]) == 36
    assert committed["start_block"][:3] == pytest.approx([0.316, 1.036, -0.01], abs=1e-3)
    assert committed["start_block"][6:9] == pytest.approx([0.094, 0.082, -0.01], abs=1e-3)


# ----------------------------------------------------------------------------------
# The loader's semantics, against values written out by hand
# ----------------------------------------------------------------------------------

SMALL = {
    "frames": 12,
    "targets": [
        {"frame": 2, "joint": "RightHand", "position": [1, 2, 3], "up": [0, 2, 0]},
        {"frame": 0, "joint": 0, "position": [4, 5, 6]},
        {"frame": 4, "joint": "LeftHand", "position": [0, 0, 0], "to": [1, -2, 4], "until": 8,
         "forward": [3, 0, 4]},
        {"frame": 6, "joint": 1, "position": [1, 1, 1], "to": [3, 1, 1], "until": 10},
        {"frame": 8, "joint": 1, "position": [9, 9, 9], "unreachable": True},
    ],
}


def test_blocks_of_a_small_script_by_hand():
    s = sc.parse(SMALL)
    start = np.arange(36) / 100.0
    b = sc.blocks(s, KEY_JOINT_NAMES, start, 12)
    assert b.shape == (12, 36) and b.dtype == np.float64
    L, R = b[:, 0:3], b[:, 3:6]
    want_left = ([[4, 5, 6]] * 4 + [[0, 0, 0], [0.25, -0.5, 1], [0.5, -1, 2], [0.75, -1.5, 3]]
                 + [[1, -2, 4]] * 4)
    assert L.tolist() == want_left
    want_right = ([start[3:6].tolist()] * 2 + [[1, 2, 3]] * 4
                  + [[1, 1, 1], [1.5, 1, 1]] + [[9, 9, 9]] * 4)  # interrupted at 8
    assert R.tolist() == want_right
    # Axes: the left forward (3, 0, 4) normalised from frame 4, its up kept; the right up
    # normalised from frame 2, its forward kept; the feet untouched.
    assert b[3, 12:18].tolist() == start[12:18].tolist()
    assert b[4, 12:15].tolist() == [0.6, 0.0, 0.8] and b[11, 15:18].tolist() == start[15:18].tolist()
    assert b[1, 21:24].tolist() == start[21:24].tolist() and b[2, 21:24].tolist() == [0, 1, 0]
    assert b[11, 18:21].tolist() == start[18:21].tolist()
    assert (b[:, 6:12] == start[6:12]).all() and (b[:, 24:36] == start[24:36]).all()
    # A shorter rollout is the same frames, cut off.
    assert (sc.blocks(s, KEY_JOINT_NAMES, start, 5) == b[:5]).all()


def test_intervals_of_a_small_script_by_hand():
    s = sc.parse(SMALL)
    got = [(iv["index"], iv["key"], iv["start"], iv["end"], iv["moving"], iv["unreachable"])
           for iv in sc.intervals(s, KEY_JOINT_NAMES, 12)]
    assert got == [(1, 0, 0, 4, False, False), (0, 1, 2, 6, False, False),
                   (2, 0, 4, 12, True, False), (3, 1, 6, 8, True, False),
                   (4, 1, 8, 12, False, True)]
    assert [iv["index"] for iv in sc.intervals(s, KEY_JOINT_NAMES, 5)] == [1, 0, 2]


def test_the_interpolation_is_the_documented_expression():
    t = {"frame": 5, "position": [0.1, 0.2, 0.3], "to": [0.4, -0.7, 1.1], "until": 8}
    for f in (6, 7):
        w = (f - 5) / (8 - 5)
        assert sc.position_at(t, f) == [p + (q - p) * w for p, q in zip(t["position"], t["to"])]
    assert sc.position_at(t, 8) == t["to"] and sc.position_at(t, 100) == t["to"]
    assert sc.position_at(t, 5) == t["position"]


@pytest.mark.parametrize("target, needle", [
    ({"frame": 0, "joint": 0, "position": [0, 0, 0], "to": [1, 0, 0]}, 'needs "until"'),
    ({"frame": 0, "joint": 0, "position": [0, 0, 0], "until": 5}, 'needs "to"'),
    ({"frame": 4, "joint": 0, "position": [0, 0, 0], "to": [1, 0, 0], "until": 4}, "not after frame 4"),
    ({"frame": 4, "joint": 0, "position": [0, 0, 0], "to": [1, 0, 0], "until": 10},
     "past the script's 10 frames"),
    ({"frame": 4, "joint": 0, "position": [0, 0, 0], "to": [1e9, 0, 0], "until": 6}, "beyond"),
    ({"frame": 4, "joint": 0, "position": [0, 0, 0], "to": [float("nan"), 0, 0], "until": 6}, "not finite"),
    ({"frame": 0, "joint": "Tail", "position": [0, 0, 0]}, "unknown key joint"),
    ({"frame": 10, "joint": 0, "position": [0, 0, 0]}, "has 10 frames"),
    ({"frame": 0, "joint": 0, "position": [0, 0, 0], "up": [0, 0, 0]}, "no length"),
])
def test_bad_entries_are_refused_naming_them(target, needle):
    s = sc.parse({"frames": 10, "targets": [target]})
    for f in (lambda: sc.blocks(s, KEY_JOINT_NAMES, np.zeros(36), 10),
              lambda: sc.intervals(s, KEY_JOINT_NAMES, 10)):
        with pytest.raises(ValueError, match=re.escape(needle)) as e:
            f()
        assert str(e.value).startswith("target 0 (frame ")


def test_two_targets_for_one_joint_at_one_frame_are_refused():
    s = sc.parse({"targets": [
        {"frame": 3, "joint": 1, "position": [0, 0, 0]},
        {"frame": 3, "joint": "LeftHand", "position": [0, 0, 0]},
        {"frame": 3, "joint": 0, "position": [1, 0, 0]}]})
    with pytest.raises(ValueError, match=r'^target 2 \(frame 3, joint 0\): a second target for '
                                         r'key joint LeftHand at frame 3 \(target 1 is the first\)'):
        sc.blocks(s, KEY_JOINT_NAMES, np.zeros(36), 10)
    with pytest.raises(ValueError, match="a second target"):
        sc.intervals(s, KEY_JOINT_NAMES, 10)


def test_unknown_fields_and_wrong_types_are_refused():
    for bad in ({"targets": [], "extra": 1},
                {"targets": [{"frame": 0, "joint": 0, "position": [0, 0, 0], "speed": 1}]},
                {"targets": [{"frame": 0.5, "joint": 0, "position": [0, 0, 0]}]},
                {"targets": [{"frame": 0, "joint": 0, "position": [0, 0]}]},
                {"targets": [{"frame": 0, "joint": 0, "position": [0, 0, 0], "unreachable": 1}]},
                {"frames": 10}):
        with pytest.raises(ValueError, match="not a target script"):
            sc.parse(bad)
