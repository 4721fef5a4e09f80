//! The controller on the embedded default model: golden rollout (bit for
//! bit), determinism, hostile commands, and the rollout / compare / render
//! commands end to end.

use host_sim::controller::{reference_f32, reference_f64, Controller, FixedController};
use host_sim::render::{plot_errors_cmd, render_cmd, PlotErrorsArgs, RenderArgs};
use host_sim::rollout::{
    compare, rollout_cmd, rollout_compare_cmd, run, Precision, Rollout, RolloutArgs,
    RolloutCompareArgs, Script,
};
use phasegate_controller::{Command, GaitWeights};
use std::path::{Path, PathBuf};

const GOLDEN_FRAMES: usize = 240;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn golden_script() -> Script {
    Script::load(
        repo()
            .join("tests/golden/controller/script.json")
            .to_str()
            .unwrap(),
    )
    .unwrap()
}

fn fixed() -> FixedController<'static> {
    FixedController::new(host_sim::default_model::BLOB, "default").unwrap()
}

/// Every array of a rollout as raw f32 bits.
fn bits(r: &Rollout) -> Vec<(&'static str, Vec<u32>)> {
    r.arrays()
        .into_iter()
        .map(|(name, _, data)| (name, data.iter().map(|v| v.to_bits()).collect()))
        .collect()
}

#[test]
fn golden_rollout_is_bit_exact() {
    let fresh = run(&mut fixed(), &golden_script(), GOLDEN_FRAMES).unwrap();
    let stored =
        exporter::npz::read_npz(&repo().join("tests/golden/controller/default.npz")).unwrap();
    for (name, want) in bits(&fresh) {
        let got: Vec<u32> = stored[name]
            .data
            .iter()
            .map(|&v| (v as f32).to_bits())
            .collect();
        if let Some(i) = got.iter().zip(&want).position(|(a, b)| a != b) {
            panic!(
                "{name}[{i}] differs from tests/golden/controller/default.npz \
                 (regenerate only for an intended change: see tests/golden/controller/README.md)"
            );
        }
        assert_eq!(got.len(), want.len(), "{name} length");
    }
}

#[test]
fn same_script_twice_gives_the_same_bits() {
    let s = golden_script();
    let a = run(&mut fixed(), &s, GOLDEN_FRAMES).unwrap();
    let b = run(&mut fixed(), &s, GOLDEN_FRAMES).unwrap();
    assert!(bits(&a) == bits(&b));
    // The float references are deterministic too (30 frames: on the random
    // default model the float loop overflows within about 40 frames, which
    // the loop reports as an error; the fixed-point one saturates instead).
    let net = host_sim::default_model::float_model().unwrap();
    let x = run(&mut reference_f32(&net).unwrap(), &s, 30).unwrap();
    let y = run(&mut reference_f32(&net).unwrap(), &s, 30).unwrap();
    assert!(bits(&x) == bits(&y));
}

#[test]
fn hostile_commands_are_refused_or_clamped_never_panic() {
    let nan = Command {
        velocity: [f32::NAN, 0.0],
        ..Command::stand()
    };
    let huge = Command {
        velocity: [1e30, -f32::MAX],
        facing: [f32::MAX, 1e-40],
        gait: GaitWeights {
            stand: -5.0,
            walk: 40.0,
            jog: -1e9,
            crouch: 2.0,
        },
    };
    let inf_gait = Command {
        gait: GaitWeights {
            jog: f32::INFINITY,
            ..Default::default()
        },
        ..Command::stand()
    };
    let mut c = fixed();
    for _ in 0..50 {
        assert!(c.step(&nan).is_err());
        assert!(c.step(&inf_gait).is_err());
        let p = c.step(&huge).unwrap();
        assert!(p.is_finite());
    }
    // The float reference refuses the same commands through the same loop.
    let net = host_sim::default_model::float_model().unwrap();
    let mut f = reference_f64(&net).unwrap();
    assert!(f.step(&nan).is_err());
}

#[test]
fn rollout_compare_render_and_plot_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let model = repo().join("tests/golden/default/model.blob");
    let fixed_out = dir.path().join("fixed.npz");
    let args = RolloutArgs {
        model: Some(model),
        reference: None,
        gating: None,
        precision: Precision::F64,
        script: "zigzag".into(),
        frames: Some(90),
        out: fixed_out.clone(),
        omg: None,
        rig: None,
        data: None,
        faithful: false,
    };
    rollout_cmd(&args).unwrap();
    let again = dir.path().join("again.npz");
    rollout_cmd(&RolloutArgs {
        out: again.clone(),
        ..args
    })
    .unwrap();
    let (a, b) = (
        Rollout::read(&fixed_out).unwrap(),
        Rollout::read(&again).unwrap(),
    );
    assert_eq!(a.len(), 90);
    let c = compare(&a, &b).unwrap();
    assert_eq!(c.summary.joint_max, 0.0);
    rollout_compare_cmd(&RolloutCompareArgs {
        a: fixed_out.clone(),
        b: again.clone(),
        every: 30,
        json: Some(dir.path().join("cmp.json")),
    })
    .unwrap();
    let png = dir.path().join("r.png");
    render_cmd(&RenderArgs {
        a: fixed_out.clone(),
        b: Some(again.clone()),
        out: png.clone(),
        snapshots: 6,
        gif: None,
    })
    .unwrap();
    let errs = dir.path().join("e.png");
    plot_errors_cmd(&PlotErrorsArgs {
        a: fixed_out.clone(),
        b: again,
        out: errs.clone(),
    })
    .unwrap();
    for p in [png, errs] {
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n", "{}", p.display());
    }
    // A rollout of a different script is refused by the comparison.
    let other = run(&mut fixed(), &Script::builtin("walk").unwrap(), 90).unwrap();
    assert!(compare(&a, &other).is_err());
    // Bad arguments give errors, not panics.
    assert!(rollout_cmd(&RolloutArgs {
        model: Some(dir.path().join("missing.blob")),
        reference: None,
        gating: None,
        precision: Precision::F64,
        script: "walk".into(),
        frames: Some(10),
        out: dir.path().join("x.npz"),
        omg: None,
        rig: None,
        data: None,
        faithful: false,
    })
    .is_err());
    assert!(Rollout::read(&dir.path().join("cmp.json")).is_err());
}

#[test]
fn float_reference_runs_the_same_loop() {
    // On the default model the f32 float controller and the device agree
    // exactly at the reset pose (both start from Ymean).
    let net = host_sim::default_model::float_model().unwrap();
    let f = reference_f32(&net).unwrap();
    let d = fixed();
    let (a, b) = (f.mean_pose(), d.mean_pose());
    for (x, y) in a.iter().flatten().zip(b.iter().flatten()) {
        assert_eq!(*x as f32, *y as f32);
    }
}

/// An OMG model through the same three commands: a target script rolled
/// out in f64 and as an int16 blob, compared, and drawn.
#[test]
fn omg_rollout_compare_and_render_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let omg = repo().join("models/omg/tiny_fe_r1");
    let d = host_sim::omg::load_dir(&omg).unwrap();
    let i16 = phasegate::blob::WeightFormat::I16;
    let blob = host_sim::omg::export(&d, i16, &host_sim::omg::exporter_options(i16)).unwrap();
    let blob_path = dir.path().join("omg16.blob");
    std::fs::write(&blob_path, blob).unwrap();
    let float_out = dir.path().join("float.npz");
    let args = RolloutArgs {
        model: None,
        reference: None,
        gating: None,
        precision: Precision::F64,
        script: "reach-front".into(),
        frames: Some(60),
        out: float_out.clone(),
        omg: Some(omg.clone()),
        rig: None,
        data: None,
        faithful: false,
    };
    rollout_cmd(&args).unwrap();
    let fixed_out = dir.path().join("fixed.npz");
    rollout_cmd(&RolloutArgs {
        model: Some(blob_path),
        out: fixed_out.clone(),
        ..args
    })
    .unwrap();
    let json = dir.path().join("cmp.json");
    rollout_compare_cmd(&RolloutCompareArgs {
        a: float_out.clone(),
        b: fixed_out.clone(),
        every: 30,
        json: Some(json.clone()),
    })
    .unwrap();
    let c: serde_json::Value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    let p99 = c["p99_m"].as_f64().unwrap();
    assert!(p99 > 0.0 && p99 < 0.01, "int16 vs f64 p99 {p99} m");
    let png = dir.path().join("omg.png");
    render_cmd(&RenderArgs {
        a: fixed_out.clone(),
        b: Some(float_out.clone()),
        out: png.clone(),
        snapshots: 4,
        gif: None,
    })
    .unwrap();
    assert_eq!(&std::fs::read(&png).unwrap()[..8], b"\x89PNG\r\n\x1a\n");
    // A locomotion rollout and an OMG rollout do not compare.
    assert!(rollout_compare_cmd(&RolloutCompareArgs {
        a: float_out,
        b: repo().join("tests/golden/default/model.blob"),
        every: 30,
        json: None,
    })
    .is_err());
}
