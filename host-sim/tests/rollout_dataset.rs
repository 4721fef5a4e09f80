//! `host-sim rollout-dataset` on the default model (PFNN-shaped, random
//! weights): deterministic, readable by `exporter cp --distill-data`, the
//! rows the float controller fed its network, and one-line errors.

use exporter::cp::distill::read_distill_data;
use host_sim::controller::{reference_f64, Controller};
use host_sim::rollout::dataset::collect;
use host_sim::rollout::Script;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn host_sim(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_host-sim"))
        .args(args)
        .output()
        .expect("host-sim runs")
}

fn model() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/golden/default/model.npz")
}

/// The default model with every weight scaled by 0.05: its float loop,
/// which diverges within a few frames on the default model's random
/// weights, stays bounded.
fn calm_model() -> exporter::net::Net {
    let mut net = host_sim::default_model::float_model().unwrap();
    for l in net.layers.iter_mut() {
        for w in l.as_dense_mut().unwrap().w.iter_mut() {
            w.mapv_inplace(|v| v * 0.05);
        }
    }
    net
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A script that moves from the first frame, so its rows differ from
/// idle's at once.
const MOVING: &str = r#"{"name": "moving", "commands": [
    {"at": 0.0, "velocity": [1.0, 2.0], "gait": "jog", "turn": 0.5}]}"#;

#[test]
fn dataset_is_deterministic_readable_and_the_controllers_inputs() {
    let tmp = tempfile::tempdir().unwrap();
    let script = tmp.path().join("moving.json");
    std::fs::write(&script, MOVING).unwrap();
    let scripts = format!("idle,{}", script.display());
    let m = tmp.path().join("calm.npz");
    let net = calm_model();
    exporter::npz::pfnn_to_npz(&net, &m).unwrap();
    let run = |out: &Path| {
        let o = host_sim(&[
            "rollout-dataset",
            "--pfnn",
            m.to_str().unwrap(),
            "--scripts",
            &scripts,
            "--frames",
            "60",
            "-o",
            out.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        String::from_utf8_lossy(&o.stdout).into_owned()
    };
    let (a, b) = (tmp.path().join("a.npz"), tmp.path().join("b.npz"));
    let text = run(&a);
    run(&b);
    assert!(text.contains("120 rows (2 scripts x 60 frames)"), "{text}");
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());

    // What the exporter reads.
    let s = read_distill_data(&a, 342).unwrap();
    assert_eq!((s.inputs.len(), s.phases.len()), (120, 120));
    let all = exporter::npz::read_npz(&a).unwrap();
    let script_col: Vec<f64> = (0..120).map(|i| (i / 60) as f64).collect();
    let frame_col: Vec<f64> = (0..120).map(|i| (i % 60) as f64).collect();
    assert_eq!(all["script"].data, script_col);
    assert_eq!(all["frame"].data, frame_col);

    // Row by row, the float controller's own inputs and phases (f32).
    // (The model as the command read it: float32 in the .npz.)
    let net = exporter::npz::pfnn_from_npz(&m, exporter::net::GatingMode::Cubic).unwrap();
    let moving = Script::load(script.to_str().unwrap()).unwrap();
    let mut ctl = reference_f64(&net).unwrap();
    for f in 0..60 {
        let pose = ctl.step(&moving.command(f)).unwrap();
        let row = 60 + f;
        let want: Vec<f64> = ctl
            .state()
            .last_input()
            .iter()
            .map(|&v| f64::from(v as f32))
            .collect();
        assert_eq!(s.inputs[row], want, "frame {f}");
        let p = f64::from((pose.phase * std::f64::consts::TAU) as f32);
        assert_eq!(s.phases[row], p, "frame {f}");
        assert!((0.0..std::f64::consts::TAU).contains(&p));
    }
    // The scripts differ, so do their rows; each starts at phase 0.
    assert_ne!(s.inputs[10], s.inputs[70]);
    assert_eq!((s.phases[0], s.phases[60]), (0.0, 0.0));
    assert!(s.phases[119] > 0.0);
    // The library function is what the command wrote.
    let idle = Script::builtin("idle").unwrap();
    let d = collect(&net, &[idle, moving], 60).unwrap();
    let arrays = d.arrays();
    assert_eq!(arrays[0].0, "X");
    assert_eq!(arrays[0].1, vec![120, 342]);
    let from_lib: Vec<f64> = arrays[0].2.iter().map(|&v| f64::from(v)).collect();
    assert_eq!(all["X"].data, from_lib);
}

/// `--blob B`: the fixed-point controller of `B` runs the same scripts
/// and its own inputs follow the float controller's rows.
#[test]
fn blob_rows_are_the_fixed_point_controllers_own_inputs() {
    let tmp = tempfile::tempdir().unwrap();
    let m = tmp.path().join("calm.npz");
    exporter::npz::pfnn_to_npz(&calm_model(), &m).unwrap();
    let net = exporter::npz::pfnn_from_npz(&m, exporter::net::GatingMode::Cubic).unwrap();
    let (blob, _) =
        exporter::export::export(&net, None, &exporter::quantise::QuantOptions::default()).unwrap();
    let b = tmp.path().join("calm.blob");
    std::fs::write(&b, &blob).unwrap();
    let out = tmp.path().join("d.npz");
    let run = |blob: &Path| {
        host_sim(&[
            "rollout-dataset",
            "--pfnn",
            m.to_str().unwrap(),
            "--scripts",
            "idle",
            "--tours",
            "1",
            "--frames",
            "50",
            "--blob",
            blob.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ])
    };
    let o = run(&b);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("200 rows (4 scripts x 50 frames)"), "{text}");
    assert!(
        text.contains("script 3: tour-1-0, the fixed-point controller of"),
        "{text}"
    );

    let all = exporter::npz::read_npz(&out).unwrap();
    let script_col: Vec<f64> = (0..200).map(|i| (i / 50) as f64).collect();
    assert_eq!(all["script"].data, script_col);
    let s = read_distill_data(&out, 342).unwrap();
    // The first 100 rows are the float controller's, as without --blob.
    let scripts = [
        Script::builtin("idle").unwrap(),
        Script::load("tour-1-0").unwrap(),
    ];
    let float = collect(&net, &scripts, 50).unwrap();
    assert_eq!(
        all["X"].data[..100 * 342],
        float.arrays()[0]
            .2
            .iter()
            .map(|&v| f64::from(v))
            .collect::<Vec<_>>()[..]
    );
    // The rest, row by row, the device controller's inputs and phases.
    let mut ctl = host_sim::controller::FixedController::new(&blob, "calm").unwrap();
    for f in 0..50 {
        let pose = ctl.step(&scripts[1].command(f)).unwrap();
        let want: Vec<f64> = ctl
            .inner()
            .state()
            .last_input()
            .iter()
            .map(|&v| f64::from(v))
            .collect();
        assert_eq!(s.inputs[150 + f], want, "frame {f}");
        let p = f64::from((pose.phase * std::f64::consts::TAU) as f32);
        assert_eq!(s.phases[150 + f], p, "frame {f}");
    }
    // Both loops start from the reset pose; after that fixed point is
    // not float, and every later row differs.
    for r in 0..100 {
        let same = s.inputs[r] == s.inputs[100 + r];
        assert_eq!(same, r % 50 == 0, "row {r}");
    }

    // A blob that is not one: one line naming it, nothing written.
    let bad = tmp.path().join("bad.blob");
    std::fs::write(&bad, b"not a blob").unwrap();
    std::fs::remove_file(&out).unwrap();
    let o = run(&bad);
    let err = stderr(&o);
    assert!(!o.status.success());
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(
        err.contains("bad.blob") && err.contains("model blob"),
        "{err}"
    );
    assert!(!out.exists());
}

#[test]
fn dataset_errors_are_one_line_and_write_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("d.npz");
    let m = model();
    let small = tmp.path().join("small.npz");
    let mut net = host_sim::default_model::float_model().unwrap();
    // A model that is not PFNN-shaped: drop an output.
    let keep = net.output_dim() - 1;
    net.ymean = net.ymean.slice(ndarray::s![..keep]).to_owned();
    net.ystd = net.ystd.slice(ndarray::s![..keep]).to_owned();
    let last = net.layers[2].as_dense_mut().unwrap();
    for (w, b) in last.w.iter_mut().zip(last.b.iter_mut()) {
        *w = w.slice(ndarray::s![..keep, ..]).to_owned();
        *b = b.slice(ndarray::s![..keep]).to_owned();
    }
    exporter::npz::pfnn_to_npz(&net, &small).unwrap();
    let (m, small) = (m.to_str().unwrap(), small.to_str().unwrap());
    let cases: [(&str, &[&str], &str); 4] = [
        (m, &["--frames", "0"], "--frames must be at least 1"),
        (
            m,
            &["--frames", "10", "--scripts", "walk,moonwalk"],
            "moonwalk is neither",
        ),
        (small, &["--frames", "10"], "PFNN-shaped"),
        // The random default model's float loop overflows within ~40
        // frames of moving.
        (
            m,
            &["--frames", "200", "--scripts", "walk"],
            "script walk: frame",
        ),
    ];
    for (pfnn, extra, want) in cases {
        let mut args = vec![
            "rollout-dataset",
            "--pfnn",
            pfnn,
            "-o",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let o = host_sim(&args);
        let err = stderr(&o);
        assert!(!o.status.success(), "{extra:?}");
        assert_eq!(err.trim_end().lines().count(), 1, "{err}");
        assert!(err.contains(want), "{want}: {err}");
        assert!(!out.exists());
    }
}
