//! `host_sim::reach_metrics` against `tools/omg/metrics.py` on the same
//! frames: `tests/data/reach_metrics.json` holds three hand-made clips (a
//! 7-joint rig; near-start targets, a reach first made with a stretched
//! bone, a moving target reached only with one, targets never reached, an
//! `unreachable` target) and what the Python computed for them
//! (`tests/data/reach_metrics_fixture.py` writes it; regenerate with
//! `PYTHONPATH=. python3 host-sim/tests/data/reach_metrics_fixture.py`).
//! Every per-target outcome must be equal, every figure equal to rounding
//! (NumPy sums means pairwise, Rust in order).

use std::path::Path;

use host_sim::reach_metrics::{
    clip_intervals, unreachable, Bones, FrameLayout, HandTarget, ReachCounts, ReachSummary,
};
use serde_json::Value;

fn fixture() -> Value {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/reach_metrics.json");
    serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap()
}

fn f64s(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

fn usizes(v: &Value) -> Vec<usize> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_u64().unwrap() as usize)
        .collect()
}

fn v3(v: &Value) -> [f64; 3] {
    let a = f64s(v);
    [a[0], a[1], a[2]]
}

fn intervals(v: &Value) -> Vec<HandTarget> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|iv| {
            let i = usizes(iv);
            HandTarget {
                hand: i[0],
                start: i[1],
                end: i[2],
            }
        })
        .collect()
}

fn close(a: f64, b: f64, what: &str) {
    assert!(
        (a - b).abs() <= 1e-12 * b.abs().max(1.0),
        "{what}: Rust {a}, Python {b}"
    );
}

#[test]
fn the_rust_metrics_give_the_python_numbers() {
    let fx = fixture();
    let parents: Vec<Option<usize>> = fx["parents"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| usize::try_from(p.as_i64().unwrap()).ok())
        .collect();
    let offsets: Vec<[f64; 3]> = fx["offsets"].as_array().unwrap().iter().map(v3).collect();
    let bones = Bones::new(&parents, &offsets).unwrap();
    let range = |v: &Value| {
        let r = usizes(v);
        r[0]..r[1]
    };
    let layout = FrameLayout {
        pos: range(&fx["pos"]),
        rot: range(&fx["rot"]),
        key_joints: usizes(&fx["key_joints"]),
    };
    let mut counts = ReachCounts::default();
    for (c, clip) in fx["clips"].as_array().unwrap().iter().enumerate() {
        let frames: Vec<Vec<f64>> = clip["frames"]
            .as_array()
            .unwrap()
            .iter()
            .map(f64s)
            .collect();
        let targets: Vec<Vec<[f64; 3]>> = clip["target_pos"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| f.as_array().unwrap().iter().map(v3).collect())
            .collect();
        let ivs = intervals(&clip["intervals"]);
        // A data clip's intervals come from its targets and spawned counts.
        if let Some(s) = clip["spawned"].as_array() {
            let spawned = [
                s[0].as_u64().unwrap() as usize,
                s[1].as_u64().unwrap() as usize,
            ];
            assert_eq!(clip_intervals(&targets, spawned), ivs, "clip {c}");
        }
        counts.add_clip(&frames, &targets, &ivs, &layout, &bones);
        let far = intervals(&clip["unreachable"]);
        let want = clip["unreachable_report"].as_array().unwrap();
        assert_eq!(far.len(), want.len(), "clip {c}");
        for (t, w) in far.iter().zip(want) {
            let u = unreachable(&frames, &targets, *t, &layout, &bones);
            assert_eq!(u.hand as u64, w["hand"].as_u64().unwrap());
            close(
                u.start_m,
                w["start_m"].as_f64().unwrap(),
                "unreachable start_m",
            );
            close(u.closest_m, w["closest_m"].as_f64().unwrap(), "closest_m");
            close(u.last_m, w["last_m"].as_f64().unwrap(), "last_m");
            close(
                u.bone_err_max_cm,
                w["bone_err_max_cm"].as_f64().unwrap(),
                "bone_err_max_cm",
            );
        }
    }
    let bools = |v: &Value| -> Vec<bool> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|b| b.as_bool().unwrap())
            .collect()
    };
    assert_eq!(counts.reached, bools(&fx["reached"]));
    assert_eq!(counts.plausible, bools(&fx["plausible"]));
    assert_eq!(counts.frames, usizes(&fx["frames"]));
    assert_eq!(counts.near_start as u64, fx["near_start"].as_u64().unwrap());
    for (a, b) in counts.final_m.iter().zip(f64s(&fx["final"])) {
        close(*a, b, "final distance");
    }
    for (a, b) in counts.roughness.iter().zip(f64s(&fx["roughness"])) {
        close(*a, b, "roughness");
    }
    // The fixture covers every case it is meant to.
    assert!(counts.near_start > 0);
    assert!(counts
        .reached
        .iter()
        .zip(&counts.plausible)
        .any(|(r, p)| *r && !*p));
    assert!(counts.reached.iter().any(|r| !*r));

    let got = counts.summary();
    let want: ReachSummary = serde_json::from_value(fx["summary"].clone()).unwrap();
    assert_eq!(
        (got.targets, got.near_start, got.frames_median),
        (want.targets, want.near_start, want.frames_median)
    );
    for (a, b, what) in [
        (got.reach, want.reach, "reach"),
        (got.plausible_reach, want.plausible_reach, "plausible reach"),
        (got.final_m, want.final_m, "final_m"),
        (got.bone_err_p50_cm, want.bone_err_p50_cm, "bone_err_p50_cm"),
        (got.bone_err_p99_cm, want.bone_err_p99_cm, "bone_err_p99_cm"),
        (got.roughness, want.roughness, "roughness"),
    ] {
        close(a, b, what);
    }
}
