"""The rule that chooses a fine-tuning run on the training clips (``tools.omg.train.choose``):
reach first, then the larger bar ratio, ties to less noise and the larger learning rate; and
the figures it reads from ``host-sim omg-reach --json``; and that every committed fine-tuned
model is the run its ``choice.json`` keeps. No PyTorch needed."""

import json
from pathlib import Path
from types import SimpleNamespace

import pytest

from tools.omg.train.choose import choose, figures, meets_bars, qat, ratio


def run(name, lr, noise, p16_cm, p8_cm, f64=0.10, r16=None, r8=None):
    return dict(name=name, lr=lr, noise=noise, f64_reach=f64,
                int16_reach=f64 if r16 is None else r16, int8_reach=f64 if r8 is None else r8,
                int16_p99_m=p16_cm / 100, int8_p99_m=p8_cm / 100, int16_max_m=0.1, int8_max_m=0.1)


def test_the_larger_ratio_to_its_bar_decides():
    # int8's bar is twice int16's: 1.5 cm at int8 is ratio 0.75, 0.8 cm at int16 is 0.8
    a = run("a", 2e-4, 0.0, 0.8, 0.2)
    b = run("b", 1e-4, 0.0, 0.3, 1.5)
    assert ratio(a) == 0.8 and ratio(b) == 0.75
    assert choose([a, b]) == "b"


def test_a_run_whose_reach_leaves_f64_by_more_than_two_points_is_out():
    best = run("best", 2e-4, 0.0, 0.1, 0.1, f64=0.10, r8=0.125)
    other = run("other", 1e-4, 0.0, 0.9, 1.9)
    assert choose([best, other]) == "other"
    # exactly 2 points is within the bar
    assert choose([run("edge", 2e-4, 0.0, 0.1, 0.1, f64=0.10, r16=0.12), other]) == "edge"
    assert choose([best]) is None


def test_ties_go_to_less_noise_then_to_the_larger_learning_rate():
    noisy = run("noisy", 2e-4, 0.05, 0.5000, 0.2)
    quiet_slow = run("quiet_slow", 1e-4, 0.0, 0.5005, 0.2)
    quiet_fast = run("quiet_fast", 2e-4, 0.0, 0.5008, 0.2)
    assert choose([noisy, quiet_slow, quiet_fast]) == "quiet_fast"
    # more than 0.001 better wins whatever its noise
    assert choose([run("clearly", 1e-4, 0.05, 0.498, 0.2), quiet_fast]) == "clearly"


def test_figures_read_whole_blobs_and_rig_pairs_alike():
    def entry(suffix):
        def row(name, reach, p99=None):
            vs = None if p99 is None else {"p99_joint_m": p99, "max_joint_m": 3 * p99}
            return {"run": name, "reach": reach, "vs_f64": vs}
        return {"clips": 192, "split": "training",
                "rows": [row("data", 0.7), row("f64", 0.1), row("int16" + suffix, 0.11, 0.004),
                         row("int8" + suffix, 0.09, 0.012)]}

    for suffix in ("", " rig"):
        f = figures(entry(suffix))
        assert f["f64_reach"] == 0.1 and f["int16_reach"] == 0.11 and f["int8_reach"] == 0.09
        assert f["int16_p99_m"] == 0.004 and f["int8_max_m"] == 3 * 0.012
        assert abs(ratio(f) - 0.6) < 1e-12 and meets_bars(f)


def test_the_fine_tuning_command_leaves_out_qats_defaults():
    args = SimpleNamespace(source="data/omg/models/x_float", data="data/omg", epochs=30, motion_from=None,
                           exporter="target/release/exporter")
    cmd = qat(args, "2e-4", "0", "out/x")
    assert cmd[1:] == ["-m", "tools.omg.train.qat", "--from", "data/omg/models/x_float", "--data", "data/omg",
                       "--epochs", "30", "--out", "out/x"]
    args.motion_from = "models/omg/m"
    cmd = qat(args, "1e-4", "0.02", "out/y")
    assert cmd[5:8] == ["--motion-from", "models/omg/m", "--freeze-shared"]
    assert cmd[-6:] == ["--lr", "1e-4", "--feedback-noise", "0.02", "--out", "out/y"]


ROOT = Path(__file__).resolve().parents[3]
FINE_TUNED = sorted(p.parent for p in (ROOT / "models" / "omg").glob("*/config.json")
                    if "qat" in json.loads(p.read_text()))


# Runs chosen among candidates by ``tools.omg.train.choose`` (the absolute-pose models of
# earlier rounds); the joint-velocity models are fine-tuned by one fixed recipe
# (``tools.omg.train.qat``'s DAgger on the grid) and carry no ``choice.json``.
CHOSEN = [p for p in FINE_TUNED if (p / "choice.json").exists()]


def test_the_committed_models_are_fine_tuned_and_the_fs_model_is_one():
    assert {"tiny_fe_r1", "small_fe_r1", "small_rbfcat_r1", "tiny_fs_r1", "tiny_fe_r4_frozen",
            "tiny_fe_r4_raw"} <= {p.name for p in FINE_TUNED}
    for p in FINE_TUNED:
        cfg = json.loads((p / "config.json").read_text())
        if cfg.get("pose_form") == "dof_velocity":
            assert cfg["qat"]["dagger"]["iterations"] > 0 and not (p / "choice.json").exists()


@pytest.mark.parametrize("d", CHOSEN, ids=[p.name for p in CHOSEN])
def test_each_committed_model_is_the_run_its_choice_json_keeps(d):
    """``choice.json`` (written by ``tools.omg.train.choose --out``) holds the six runs' figures;
    the rule applied to them keeps the run the record names, and that run's learning rate and
    feed-back noise are the committed model's."""
    rec = json.loads((d / "choice.json").read_text())
    qat_record = json.loads((d / "config.json").read_text())["qat"]
    assert len(rec["runs"]) == 6
    assert {(r["lr"], r["noise"]) for r in rec["runs"]} == {
        (lr, s) for lr in (2e-4, 1e-4) for s in (0.0, 0.02, 0.05)}
    for r in rec["runs"]:
        assert (r["split"], r["clips"]) == ("training", 192)
        assert (r["held_out"]["split"], r["held_out"]["clips"]) == ("held-out", 48)
    assert choose(rec["runs"]) == rec["kept"]
    kept = next(r for r in rec["runs"] if r["name"] == rec["kept"])
    assert kept["lr"] == qat_record["lr"]
    assert kept["noise"] == qat_record["feedback_noise"]
