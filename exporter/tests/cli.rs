//! The `exporter` command line: outputs, reports, and one-line errors that
//! leave nothing behind.

use exporter::pfnn_dir::{write_pfnn_dir, LayerTables, PfnnTables};
use ndarray::{Array1, Array2};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn exporter(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_exporter"))
        .args(args)
        .output()
        .expect("exporter runs")
}

/// A small PFNN-format directory (6 -> 8 -> 8 -> 5, 50 tables) whose
/// tables are a Catmull-Rom spline of 4 control points, like the real one.
fn small_pfnn(dir: &Path) {
    let mut seed = 1u32;
    let mut rnd = move || {
        seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        (seed >> 8) as f32 / (1u32 << 24) as f32 - 0.5
    };
    let shapes = [(8usize, 6usize), (8, 8), (5, 8)];
    let layers = shapes.map(|(r, c)| {
        let cw: Vec<Array2<f64>> = (0..4)
            .map(|_| Array2::from_shape_fn((r, c), |_| f64::from(rnd())))
            .collect();
        let cb: Vec<Array1<f64>> = (0..4)
            .map(|_| Array1::from_shape_fn(r, |_| f64::from(rnd()) * 0.1))
            .collect();
        let mut t = LayerTables {
            w: Vec::new(),
            b: Vec::new(),
        };
        for i in 0..50 {
            let s = exporter::control_points::table_position(i, 50);
            let mut w = Array2::<f64>::zeros((r, c));
            let mut b = Array1::<f64>::zeros(r);
            for (k, g) in exporter::control_points::catmull_rom_weights(s) {
                w.scaled_add(g, &cw[k]);
                b.scaled_add(g, &cb[k]);
            }
            t.w.push(w.mapv(|v| v as f32));
            t.b.push(b.mapv(|v| v as f32));
        }
        t
    });
    let tables = PfnnTables {
        xmean: Array1::from_shape_fn(6, |i| i as f32 * 0.1),
        xstd: Array1::from_elem(6, 1.5),
        ymean: Array1::from_elem(5, 0.5),
        ystd: Array1::from_elem(5, 2.0),
        layers,
    };
    write_pfnn_dir(&tables, dir).unwrap();
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn files_in(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    v.sort();
    v
}

#[test]
fn exports_a_pfnn_directory_with_report_and_inspects_it() {
    let tmp = tempfile::tempdir().unwrap();
    let weights = tmp.path().join("net");
    small_pfnn(&weights);
    let out = tmp.path().join("out");
    std::fs::create_dir(&out).unwrap();
    for (gating, bits) in [
        ("cubic", "8"),
        ("cubic", "16"),
        ("linear", "8"),
        ("constant", "16"),
    ] {
        let blob = out.join(format!("{gating}{bits}.blob"));
        let report = out.join(format!("{gating}{bits}.json"));
        let o = exporter(&[
            "pfnn",
            "--weights",
            weights.to_str().unwrap(),
            "--gating",
            gating,
            "--weight-bits",
            bits,
            "-o",
            blob.to_str().unwrap(),
            "--report",
            report.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{gating} {bits}: {}", stderr(&o));
        let bytes = std::fs::read(&blob).unwrap();
        let model = phasegate::Model::from_bytes(&bytes).unwrap();
        let experts = match gating {
            "cubic" => 4,
            "linear" => 10,
            _ => 50,
        };
        assert_eq!(
            model.header().decoded().nodes[0].layer().unwrap().experts,
            experts
        );
        let r: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
        assert_eq!(r["blob_bytes"].as_u64().unwrap() as usize, bytes.len());
        assert_eq!(r["overflow_proof"], serde_json::Value::Bool(true));
        assert_eq!(r["layers"].as_array().unwrap().len(), 3);
        assert!(
            r["layers"][0]["weight_sqnr_db"].as_f64().unwrap()
                > if bits == "8" { 30.0 } else { 80.0 }
        );
        if gating == "cubic" {
            // Tables made from f32-rounded spline values: recovery is exact to f32 rounding.
            assert!(
                r["control_point_residual"]["rel_frobenius"]
                    .as_f64()
                    .unwrap()
                    < 1e-6
            );
        } else {
            assert!(r["control_point_residual"].is_null());
        }
        let i = exporter(&["inspect", blob.to_str().unwrap()]);
        assert!(i.status.success());
        let text = String::from_utf8_lossy(&i.stdout);
        assert!(
            text.contains("MACs per frame") && text.contains(&format!("{}", bytes.len())),
            "{text}"
        );
    }
    // Only the blobs and reports: no temporary files left behind.
    assert_eq!(files_in(&out).len(), 8);
}

/// Each broken directory gives one line on stderr naming the file, a
/// non-zero exit, and no output.
#[test]
fn bad_weight_directories_fail_cleanly() {
    let tmp = tempfile::tempdir().unwrap();
    type Break = fn(&Path);
    let cases: [(&str, Break, &str); 5] = [
        (
            "missing file",
            |d| std::fs::remove_file(d.join("W1_007.bin")).unwrap(),
            "W1_007.bin",
        ),
        (
            "wrong size",
            |d| {
                let p = d.join("W2_030.bin");
                let b = std::fs::read(&p).unwrap();
                std::fs::write(&p, &b[..b.len() - 4]).unwrap();
            },
            "W2_030.bin",
        ),
        (
            "NaN",
            |d| {
                let p = d.join("b1_012.bin");
                let mut b = std::fs::read(&p).unwrap();
                b[8..12].copy_from_slice(&f32::NAN.to_le_bytes());
                std::fs::write(&p, b).unwrap();
            },
            "b1_012.bin",
        ),
        (
            "inf",
            |d| {
                let p = d.join("Xstd.bin");
                let mut b = std::fs::read(&p).unwrap();
                b[0..4].copy_from_slice(&f32::INFINITY.to_le_bytes());
                std::fs::write(&p, b).unwrap();
            },
            "Xstd.bin",
        ),
        (
            "not a directory",
            |d| std::fs::remove_dir_all(d).unwrap(),
            "net",
        ),
    ];
    for (what, break_it, names) in cases {
        let weights = tmp.path().join("net");
        let _ = std::fs::remove_dir_all(&weights);
        small_pfnn(&weights);
        break_it(&weights);
        let out_dir = tmp.path().join(format!("out-{}", what.replace(' ', "-")));
        std::fs::create_dir(&out_dir).unwrap();
        let blob = out_dir.join("m.blob");
        let report = out_dir.join("m.json");
        let o = exporter(&[
            "pfnn",
            "--weights",
            weights.to_str().unwrap(),
            "--gating",
            "cubic",
            "-o",
            blob.to_str().unwrap(),
            "--report",
            report.to_str().unwrap(),
        ]);
        let err = stderr(&o);
        assert!(!o.status.success(), "{what}: succeeded");
        assert_eq!(err.trim_end().lines().count(), 1, "{what}: {err}");
        assert!(
            err.starts_with("error: ") && err.contains(names),
            "{what}: {err}"
        );
        assert!(
            files_in(&out_dir).is_empty(),
            "{what}: left {:?}",
            files_in(&out_dir)
        );
    }
}

#[test]
fn unwritable_output_fails_cleanly() {
    let tmp = tempfile::tempdir().unwrap();
    let weights = tmp.path().join("net");
    small_pfnn(&weights);
    let blob = tmp.path().join("no-such-dir").join("m.blob");
    let o = exporter(&[
        "pfnn",
        "--weights",
        weights.to_str().unwrap(),
        "--gating",
        "cubic",
        "-o",
        blob.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    let err = stderr(&o);
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(err.contains("m.blob"), "{err}");
    assert!(!blob.exists());
    // A report that can be written but a blob that cannot: neither stays.
    let report = tmp.path().join("r.json");
    let o = exporter(&[
        "pfnn",
        "--weights",
        weights.to_str().unwrap(),
        "--gating",
        "cubic",
        "-o",
        blob.to_str().unwrap(),
        "--report",
        report.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(!report.exists());
    // The output path is an existing directory.
    let o = exporter(&[
        "pfnn",
        "--weights",
        weights.to_str().unwrap(),
        "--gating",
        "cubic",
        "-o",
        tmp.path().to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert_eq!(stderr(&o).trim_end().lines().count(), 1);
}

#[test]
fn inspect_rejects_bad_files_in_one_line() {
    let tmp = tempfile::tempdir().unwrap();
    let weights = tmp.path().join("net");
    small_pfnn(&weights);
    let blob = tmp.path().join("m.blob");
    let o = exporter(&[
        "pfnn",
        "--weights",
        weights.to_str().unwrap(),
        "--gating",
        "cubic",
        "-o",
        blob.to_str().unwrap(),
    ]);
    assert!(o.status.success());
    let good = std::fs::read(&blob).unwrap();
    let mut flipped = good.clone();
    let last = flipped.len() - 1;
    flipped[last] ^= 0x10;
    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        ("empty", Vec::new(), "truncated"),
        ("text", b"hello, world".to_vec(), "bad magic"),
        ("truncated", good[..good.len() / 2].to_vec(), "truncated"),
        ("payload flip", flipped, "payload is corrupt"),
    ];
    for (what, bytes, expect) in cases {
        let p = tmp.path().join(format!("{what}.blob"));
        std::fs::write(&p, bytes).unwrap();
        let o = exporter(&["inspect", p.to_str().unwrap()]);
        let err = stderr(&o);
        assert!(!o.status.success(), "{what}");
        assert_eq!(err.trim_end().lines().count(), 1, "{what}: {err}");
        assert!(err.contains(expect), "{what}: {err}");
    }
    let o = exporter(&["inspect", tmp.path().join("absent.blob").to_str().unwrap()]);
    assert!(!o.status.success() && stderr(&o).contains("absent.blob"));
}

/// A synthetic "rollout" data set for `small_pfnn`: inputs on a closed
/// curve through input space (far narrower than the normal samples), the
/// phase advancing with them, like a controller's.
fn rollout_data(path: &Path, rows: usize) {
    let mut x = Vec::new();
    let mut phase = Vec::new();
    for t in 0..rows {
        let a = t as f32 * 0.05;
        for j in 0..6 {
            let j = j as f32;
            x.push(j * 0.1 + 1.5 * (0.8 * (a + j).sin() + 0.3 * (2.0 * a - j).cos()));
        }
        phase.push((2.0 * a) % std::f32::consts::TAU);
    }
    exporter::npz::write_npz(
        path,
        &[
            ("X", vec![rows as u64, 6], x),
            ("phase", vec![rows as u64], phase),
        ],
    )
    .unwrap();
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

/// `cp --distill --distill-data`: training on the rollout rows lowers the
/// loss on their held-out blocks, and more than training on normal samples
/// alone does; `--distill-normal-fraction 1` is exactly the normal-only
/// distillation (same samples, same steps) with the rollout rows evaluated.
#[test]
fn cp_distill_on_rollout_data_lowers_its_loss() {
    let tmp = tempfile::tempdir().unwrap();
    let weights = tmp.path().join("net");
    small_pfnn(&weights);
    let data = tmp.path().join("rollouts.npz");
    rollout_data(&data, 480);
    let run = |name: &str, extra: &[&str]| {
        let blob = tmp.path().join(format!("{name}.blob"));
        let report = tmp.path().join(format!("{name}.json"));
        let mut args = vec![
            "cp",
            "--weights",
            weights.to_str().unwrap(),
            "--cp-rank",
            "2",
            "--distill",
            "600",
            "--distill-samples",
            "1024",
            "--distill-lr",
            "3e-3",
            "-o",
            blob.to_str().unwrap(),
            "--report",
            report.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let o = exporter(&args);
        assert!(o.status.success(), "{name}: {}", stderr(&o));
        (
            json(&report),
            String::from_utf8_lossy(&o.stdout).into_owned(),
        )
    };
    let d = data.to_str().unwrap();
    let (plain, _) = run("plain", &[]);
    let (normal, _) = run(
        "normal",
        &["--distill-data", d, "--distill-normal-fraction", "1"],
    );
    let (rollout, text) = run(
        "rollout",
        &["--distill-data", d, "--distill-normal-fraction", "0"],
    );
    let (mixed, _) = run("mixed", &["--distill-data", d]);
    let f = |v: &serde_json::Value, path: &[&str]| -> f64 {
        let mut v = v;
        for p in path {
            v = &v[*p];
        }
        v.as_f64()
            .unwrap_or_else(|| panic!("{path:?} missing in {v}"))
    };
    // Fraction 1: the same training as without data.
    let dist = |v: &serde_json::Value, k: &str| f(v, &["distill", k]);
    assert_eq!(
        dist(&plain, "held_out_after"),
        dist(&normal, "held_out_after")
    );
    assert!(plain["distill"]["rollout_held_out"].is_null());
    assert_eq!(dist(&normal, "rollout_samples"), 0.0);
    assert_eq!(dist(&rollout, "normal_samples"), 0.0);
    assert_eq!(dist(&rollout, "rollout_samples"), 1024.0);
    assert_eq!(dist(&mixed, "normal_samples"), 512.0);
    // 480 rows: blocks of 60, the 8th held out.
    assert_eq!(dist(&rollout, "rollout_rows"), 420.0);
    let held = |v: &serde_json::Value, k: &str| f(v, &["distill", "rollout_held_out", k]);
    assert_eq!(f(&rollout, &["distill", "rollout_held_out", "rows"]), 60.0);
    // The rollout distribution improves with its own data, and more than
    // with normal samples only.
    let (before, after) = (held(&rollout, "before"), held(&rollout, "after"));
    assert!(after < 0.5 * before, "{before} -> {after}");
    assert!(
        after < held(&normal, "after"),
        "{after} vs {}",
        held(&normal, "after")
    );
    assert!(held(&mixed, "after") < held(&normal, "after"));
    // Printed, and the same figures in the output-unit table.
    assert!(text.contains("rollout rows held out (60)"), "{text}");
    assert!(text.contains("normal samples (512)"), "{text}");
    let set = &rollout["rollout_sets"][0];
    assert_eq!(set["rows"], 60);
    assert!(
        set["float_vs_dense"]["rel_normalised"].as_f64().unwrap()
            < set["float_vs_dense_before_distill"]["rel_normalised"]
                .as_f64()
                .unwrap()
    );
    // Evaluation-only sets are reported too.
    let (with_eval, _) = run(
        "eval",
        &[
            "--distill-data",
            d,
            "--distill-normal-fraction",
            "0",
            "--eval-data",
            d,
        ],
    );
    assert_eq!(with_eval["distill"]["eval"][0]["rows"], 480, "{with_eval}");
    assert_eq!(with_eval["rollout_sets"].as_array().unwrap().len(), 2);
}

/// Name, shape and values of one array to write.
type Array = (&'static str, Vec<u64>, Vec<f32>);

/// Bad rollout data sets fail before any work, in one line naming the
/// file, and write nothing.
#[test]
fn cp_refuses_bad_rollout_data_in_one_line() {
    let tmp = tempfile::tempdir().unwrap();
    let weights = tmp.path().join("net");
    small_pfnn(&weights);
    let bad = tmp.path().join("bad.npz");
    let blob = tmp.path().join("out.blob");
    let cp = |extra: &[&str]| {
        let mut args = vec![
            "cp",
            "--weights",
            weights.to_str().unwrap(),
            "--cp-rank",
            "2",
            "-o",
            blob.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        exporter(&args)
    };
    let b = bad.to_str().unwrap();
    let cases: Vec<(Vec<Array>, &str)> = vec![
        (
            vec![
                ("X", vec![4, 5], vec![0.0; 20]),
                ("phase", vec![4], vec![0.0; 4]),
            ],
            "X has 5 columns, the model has 6 inputs",
        ),
        (
            vec![
                ("X", vec![4, 6], vec![0.0; 24]),
                ("phase", vec![3], vec![0.0; 3]),
            ],
            "phase has shape [3], expected (4,)",
        ),
        (
            vec![
                ("X", vec![1, 6], vec![0.0, 1.0, f32::NAN, 0.0, 0.0, 0.0]),
                ("phase", vec![1], vec![0.0]),
            ],
            "non-finite value at index 2",
        ),
        (vec![("X", vec![1, 6], vec![0.0; 6])], "missing array phase"),
    ];
    for (arrays, want) in cases {
        exporter::npz::write_npz(&bad, &arrays).unwrap();
        for flag in ["--distill-data", "--eval-data"] {
            let o = cp(&["--distill", "5", flag, b]);
            let err = stderr(&o);
            assert!(!o.status.success(), "{want}");
            assert_eq!(err.trim_end().lines().count(), 1, "{err}");
            assert!(err.contains(want) && err.contains("bad.npz"), "{err}");
            assert!(!blob.exists());
        }
    }
    rollout_data(&bad, 16);
    // Evaluation only, no distillation: allowed.
    let o = cp(&["--eval-data", b]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(
        text.contains("bad.npz (16)") && !text.contains("distillation:"),
        "{text}"
    );
    std::fs::remove_file(&blob).unwrap();
    let o = cp(&["--distill-data", b]);
    assert!(!o.status.success() && stderr(&o).contains("needs --distill"));
    let o = cp(&[
        "--distill",
        "5",
        "--distill-data",
        b,
        "--distill-normal-fraction",
        "1.5",
    ]);
    assert!(!o.status.success() && stderr(&o).contains("between 0 and 1"));
    assert!(!blob.exists());
}

/// `inspect` shows each layer's op and MACs, and reads style blobs.
#[test]
fn inspect_shows_ops_macs_and_styles() {
    let tmp = tempfile::tempdir().unwrap();
    let weights = tmp.path().join("net");
    small_pfnn(&weights);
    let w = weights.to_str().unwrap();
    let path = |n: &str| tmp.path().join(n).to_str().unwrap().to_owned();
    let base = path("base.blob");
    let o = exporter(&["pfnn", "--weights", w, "--gating", "cubic", "-o", &base]);
    assert!(o.status.success(), "{}", stderr(&o));
    let cp = path("cp.blob");
    let o = exporter(&[
        "cp",
        "--weights",
        w,
        "--cp-rank",
        "3",
        "--cp-layers",
        "1",
        "-o",
        &cp,
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let inspect = |p: &str| {
        let o = exporter(&["inspect", p]);
        assert!(o.status.success(), "{}", stderr(&o));
        String::from_utf8_lossy(&o.stdout).into_owned()
    };
    let row = |text: &str, layer: usize| -> Vec<String> {
        let start = text.lines().position(|l| l.contains("requant@")).unwrap();
        text.lines()
            .nth(start + 1 + layer)
            .unwrap()
            .split_whitespace()
            .map(str::to_owned)
            .collect()
    };
    let text = inspect(&base);
    // Dense cubic layer 0: 4 active experts x 6 x 8.
    assert_eq!(
        &row(&text, 0)[..6],
        ["0", "6", "8", "4", "dense", "192"],
        "{text}"
    );
    let text = inspect(&cp);
    assert_eq!(&row(&text, 0)[4..6], ["dense", "192"], "{text}");
    // CP layer 1: rank 3 x (8 + 8 + 4).
    assert_eq!(
        &row(&text, 1)[..8],
        ["1", "8", "8", "4", "cp", "rank", "3", "60"],
        "{text}"
    );
    assert!(text.contains("MACs per frame   412"), "{text}");
    // A style blob: a diagonal adapter beside layer 1.
    let adapter = path("ad.npz");
    exporter::npz::write_npz(
        Path::new(&adapter),
        &[(
            "w",
            vec![4, 8],
            (0..32).map(|i| (i % 5) as f32 * 0.05).collect(),
        )],
    )
    .unwrap();
    let style = path("s.style");
    let o = exporter(&[
        "style",
        "--base",
        &base,
        "--base-weights",
        w,
        "--adapter",
        &adapter,
        "--name",
        "lean",
        "-o",
        &style,
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = inspect(&style);
    let crc = phasegate::Model::from_bytes(&std::fs::read(&base).unwrap())
        .unwrap()
        .header()
        .payload_crc;
    assert!(text.contains("style name       \"lean\""), "{text}");
    assert!(
        text.contains(&format!("payload CRC-32 {crc:#010x}")),
        "{text}"
    );
    assert!(text.contains("beside layer     1"), "{text}");
    assert_eq!(
        &row(&text, 0)[..6],
        ["0", "8", "8", "4", "diagonal", "32"],
        "{text}"
    );
}

#[test]
fn calibration_rollouts_reach_the_quantiser_and_the_report() {
    let tmp = tempfile::tempdir().unwrap();
    let weights = tmp.path().join("net");
    small_pfnn(&weights);
    let data = tmp.path().join("rollouts.npz");
    rollout_data(&data, 300);
    // `verbose`: the summary a terminal gets (PHASEGATE_VERBOSE).
    let export_shown = |name: &str, extra: &[&str], verbose: bool| {
        let blob = tmp.path().join(format!("{name}.blob"));
        let report = tmp.path().join(format!("{name}.json"));
        let mut args = vec![
            "pfnn",
            "--weights",
            weights.to_str().unwrap(),
            "--gating",
            "cubic",
            "-o",
            blob.to_str().unwrap(),
            "--report",
            report.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        let mut c = Command::new(env!("CARGO_BIN_EXE_exporter"));
        if verbose {
            c.env("PHASEGATE_VERBOSE", "1");
        }
        let o = c.args(&args).output().expect("exporter runs");
        (o, blob, report)
    };
    let export = |name: &str, extra: &[&str]| export_shown(name, extra, false);
    let (o, plain, _) = export("plain", &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    let d = data.to_str().unwrap();
    let (o, calibrated, report) = export(
        "calibrated",
        &["--calibration", d, "--compensation-samples", "256"],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let r = json(&report);
    assert_eq!(r["options"]["calibration_data"]["rows"], 300, "{r}");
    assert_eq!(r["options"]["calibration_data"]["source"], d);
    let (a, b) = (
        std::fs::read(&plain).unwrap(),
        std::fs::read(calibrated).unwrap(),
    );
    assert_eq!(a.len(), b.len(), "same settings, same size");
    assert_ne!(a, b, "the recorded rows changed the rounding");
    assert_eq!(r["options"]["calibration_weight"], 0.7, "{r}");

    // Their share of the rounding's objective is a knob of its own.
    let (o, reweighted, report) = export(
        "reweighted",
        &[
            "--calibration",
            d,
            "--compensation-samples",
            "256",
            "--calibration-weight",
            "0.2",
        ],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(json(&report)["options"]["calibration_weight"], 0.2);
    assert_ne!(
        b,
        std::fs::read(reweighted).unwrap(),
        "the share moved the rounding"
    );
    for (name, extra) in [
        (
            "share-1",
            vec!["--calibration", d, "--calibration-weight", "1"],
        ),
        (
            "share-nan",
            vec!["--calibration", d, "--calibration-weight", "NaN"],
        ),
        ("share-alone", vec!["--calibration-weight", "0.5"]),
        (
            "share-nearest",
            vec![
                "--calibration",
                d,
                "--rounding",
                "nearest",
                "--calibration-weight",
                "0.5",
            ],
        ),
    ] {
        let (o, blob, report) = export(name, &extra);
        assert!(!o.status.success(), "{name}");
        let e = stderr(&o);
        assert_eq!(e.trim().lines().count(), 1, "{e}");
        assert!(e.contains("--calibration-weight"), "{e}");
        assert!(!blob.exists() && !report.exists());
    }

    // A data set of another model's width is refused in one line naming
    // the file, and nothing is written.
    let wrong = tmp.path().join("wrong.npz");
    exporter::npz::write_npz(
        &wrong,
        &[
            ("X", vec![2, 4], vec![0.0; 8]),
            ("phase", vec![2], vec![0.0; 2]),
        ],
    )
    .unwrap();
    let (o, blob, report) = export("wrong", &["--calibration", wrong.to_str().unwrap()]);
    assert!(!o.status.success());
    let e = stderr(&o);
    assert_eq!(e.trim().lines().count(), 1, "{e}");
    assert!(e.contains("wrong.npz") && e.contains("4 columns"), "{e}");
    assert!(!blob.exists() && !report.exists());

    // The int16 budget: spent (and reported) on an int8 blob, refused on
    // an int16 one.
    let (o, _, report) = export("budget", &["--int16-budget", "100000"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let b = &json(&report)["int16_budget"];
    assert!(b["spent_bytes"].as_u64().unwrap() <= 100_000, "{b}");
    assert_eq!(b["trials"][0]["round"], 0, "{b}");
    assert_eq!(b["unaffordable"].as_array().unwrap().len(), 0, "{b}");
    // A budget below every layer's int16 weights exports nothing more: the
    // plain blob, no trial, every layer listed with its floor, and the
    // summary names them.
    let (o, tiny, report) = export("tiny-budget", &["--int16-budget", "50"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(
        std::fs::read(&tiny).unwrap(),
        std::fs::read(&plain).unwrap()
    );
    let b = &json(&report)["int16_budget"];
    assert_eq!(b["trials"].as_array().unwrap().len(), 0, "{b}");
    let floors: Vec<u64> = b["unaffordable"]
        .as_array()
        .unwrap()
        .iter()
        .map(|u| u["min_extra_bytes"].as_u64().unwrap())
        .collect();
    assert_eq!(floors.len(), 3, "{b}");
    assert!(floors.iter().all(|&f| f > 50), "{b}");
    let (o, _, _) = export_shown("tiny-shown", &["--int16-budget", "50"], true);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(out.contains("int16 budget: 0 of 50 bytes spent"), "{out}");
    assert!(out.contains("layer 1 not tried"), "{out}");
    let (o, blob, _) = export("wide", &["--int16-budget", "1000", "--weight-bits", "16"]);
    assert!(!o.status.success() && !blob.exists());
    assert!(stderr(&o).contains("--int16-budget"), "{}", stderr(&o));
}

#[test]
fn omg_exports_the_committed_model_and_refuses_a_bad_config_without_writing() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/omg/tiny_fe_r4_frozen");
    let dir = tempfile::tempdir().unwrap();
    let blob = dir.path().join("m.blob");
    let report = dir.path().join("m.json");
    let (w, c) = (root.join("model.safetensors"), root.join("config.json"));
    let (w, c) = (w.to_str().unwrap(), c.to_str().unwrap());
    let o = exporter(&[
        "omg",
        "--weights",
        w,
        "--config",
        c,
        "-o",
        blob.to_str().unwrap(),
        "--weight-bits",
        "16",
        "--report",
        report.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let bytes = std::fs::read(&blob).unwrap();
    let m = phasegate::Model::from_bytes(&bytes).unwrap();
    // Out: the phases (2K = 8), the rig's 24 DOF velocities, the costs (6K = 24).
    assert_eq!((m.input_dim(), m.output_dim()), (356, 56));
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    assert_eq!(r["weight_format"], "int16");
    assert_eq!(r["overflow_proof"], true);
    // An unknown variant is refused in one line naming the config; nothing
    // written.
    let mut cfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(c).unwrap()).unwrap();
    cfg["variant"] = "VAE".into();
    let bad = dir.path().join("config.json");
    std::fs::write(&bad, cfg.to_string()).unwrap();
    let out = dir.path().join("x.blob");
    let o = exporter(&[
        "omg",
        "--weights",
        w,
        "--config",
        bad.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    let e = stderr(&o);
    assert!(
        e.starts_with(&format!(
            "error: {}: variant \"VAE\" (expected FE, FS, RBF-CAT or DEC-CAT)",
            bad.display()
        )),
        "{e}"
    );
    assert_eq!(e.lines().count(), 1, "{e}");
    assert!(!out.exists());
}

/// Blobs of other format versions (the kept fixtures, `tests/fixtures/`)
/// are refused by `exporter inspect` with a message that names the version
/// found and the version supported.
#[test]
fn inspect_names_the_version_found_and_the_version_supported() {
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures");
    for (file, found) in [("example-v1.blob", 1), ("version0.blob", 0)] {
        let o = exporter(&["inspect", fixtures.join(file).to_str().unwrap()]);
        assert!(!o.status.success(), "{file} inspected");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains(&format!("blob format version {found} is not supported"))
                && err.contains(&format!(
                    "reads version {}",
                    phasegate::blob::FORMAT_VERSION
                )),
            "{file}: {err}"
        );
    }
    let o = exporter(&[
        "inspect",
        fixtures.join("example-v2.blob").to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// `--budget-instructions`: above the estimate, one warning line on stderr
/// naming the output, `frame_budget` in the report, the blob written and
/// exit status 0; at or below it, no warning.
#[test]
fn budget_instructions_warns_without_failing() {
    let tmp = tempfile::tempdir().unwrap();
    let weights = tmp.path().join("net");
    small_pfnn(&weights);
    let blob = tmp.path().join("m.blob");
    let report = tmp.path().join("m.json");
    let run = |budget: &str| {
        exporter(&[
            "pfnn",
            "--weights",
            weights.to_str().unwrap(),
            "--gating",
            "cubic",
            "-o",
            blob.to_str().unwrap(),
            "--report",
            report.to_str().unwrap(),
            "--budget-instructions",
            budget,
        ])
    };
    let o = run("1000");
    assert!(o.status.success(), "{}", stderr(&o));
    let err = stderr(&o);
    let warnings: Vec<&str> = err.lines().filter(|l| l.contains("warning:")).collect();
    assert_eq!(warnings.len(), 1, "{err}");
    assert!(
        warnings[0].contains("m.blob") && warnings[0].contains("exceed --budget-instructions 1000"),
        "{err}"
    );
    assert!(blob.exists());
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let fb = &json["frame_budget"];
    assert_eq!(fb["budget_instructions"], 1000);
    assert_eq!(fb["exceeds"], true);
    let estimate = fb["estimated_instructions"].as_u64().unwrap();
    let bytes = std::fs::read(&blob).unwrap();
    let model = phasegate::Model::from_bytes(&bytes).unwrap();
    assert_eq!(estimate, exporter::cost::estimate_instructions(&model));

    let o = run(&estimate.to_string());
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(!stderr(&o).contains("warning:"), "{}", stderr(&o));
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    assert_eq!(json["frame_budget"]["exceeds"], false);
    assert!(json["frame_budget"].get("warning").is_none());
}

/// `exporter omg --snap-out` on the committed tiny_fe_r1, a model
/// fine-tuned for its int8 blob (`tools.omg.train.qat`), writes back the
/// committed weights: they are the blob's own, to float32 storage.
/// `--grid-out` names every weight tensor with one power of two per input
/// column; with `--int16-budget` both are refused and nothing is written.
#[test]
fn omg_snap_of_the_committed_model_is_the_committed_model() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/omg/tiny_fe_r1");
    let dir = tempfile::tempdir().unwrap();
    let (snap, grid, blob) = (
        dir.path().join("snap.safetensors"),
        dir.path().join("grid.json"),
        dir.path().join("m.blob"),
    );
    let (w, c) = (root.join("model.safetensors"), root.join("config.json"));
    let (w, c) = (w.to_str().unwrap(), c.to_str().unwrap());
    let args = |extra: &[&str]| {
        let mut a = vec![
            "omg",
            "--weights",
            w,
            "--config",
            c,
            "-o",
            blob.to_str().unwrap(),
        ];
        a.extend_from_slice(extra);
        a.iter().map(|s| s.to_string()).collect::<Vec<_>>()
    };
    let run = |a: Vec<String>| exporter(&a.iter().map(String::as_str).collect::<Vec<_>>());
    let o = run(args(&[
        "--snap-out",
        snap.to_str().unwrap(),
        "--grid-out",
        grid.to_str().unwrap(),
    ]));
    assert!(o.status.success(), "{}", stderr(&o));
    let read =
        |p: &Path| exporter::cp::import::parse_safetensors(&std::fs::read(p).unwrap()).unwrap();
    let (committed, snapped) = (read(Path::new(w)), read(&snap));
    assert_eq!(
        committed.keys().collect::<Vec<_>>(),
        snapped.keys().collect::<Vec<_>>()
    );
    for (name, a) in &committed {
        let b = &snapped[name];
        assert_eq!(a.shape, b.shape, "{name}");
        let most = a
            .data
            .iter()
            .zip(&b.data)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max);
        assert!(most <= 1e-6, "{name}: the blob moves a weight by {most}");
    }
    let g = json(&grid);
    assert_eq!(g["weight_bits"], 8);
    let scales = g["column_scales"].as_object().unwrap();
    assert_eq!(scales.len(), 15, "four MLPs and three expert stacks");
    for (name, u) in scales {
        let cols = committed[name].shape[1] as usize;
        let u = u.as_array().unwrap();
        assert_eq!(u.len(), cols, "{name}");
        assert!(
            u.iter().all(|v| v.as_f64().unwrap().log2().fract() == 0.0),
            "{name}"
        );
    }
    let (snap2, blob2) = (dir.path().join("s2"), dir.path().join("b2.blob"));
    let o = exporter(&[
        "omg",
        "--weights",
        w,
        "--config",
        c,
        "-o",
        blob2.to_str().unwrap(),
        "--int16-budget",
        "1000",
        "--snap-out",
        snap2.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("leave out --int16-budget"),
        "{}",
        stderr(&o)
    );
    assert_eq!(stderr(&o).lines().count(), 1);
    assert!(!snap2.exists() && !blob2.exists());
}

/// The same for the committed Frozen R4 model, whose deployment is a rig
/// blob against tiny_fe_r1's motion blob: `exporter omg-rig --snap-out`
/// gives back its weights, the shared nodes on the motion blob's grid and
/// the autoencoder on the rig blob's.
#[test]
fn omg_rig_snap_of_the_committed_r4_model_is_the_committed_model() {
    let models = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/omg");
    let dir = tempfile::tempdir().unwrap();
    let (motion, rig, snap) = (
        dir.path().join("motion.blob"),
        dir.path().join("r4.rig"),
        dir.path().join("snap.safetensors"),
    );
    let path = |m: &str, f: &str| models.join(m).join(f).to_str().unwrap().to_string();
    let o = exporter(&[
        "omg",
        "--weights",
        &path("tiny_fe_r1", "model.safetensors"),
        "--config",
        &path("tiny_fe_r1", "config.json"),
        "-o",
        motion.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let w4 = path("tiny_fe_r4_frozen", "model.safetensors");
    let o = exporter(&[
        "omg-rig",
        "--base",
        motion.to_str().unwrap(),
        "--weights",
        &w4,
        "--config",
        &path("tiny_fe_r4_frozen", "config.json"),
        "-o",
        rig.to_str().unwrap(),
        "--snap-out",
        snap.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let read =
        |p: &Path| exporter::cp::import::parse_safetensors(&std::fs::read(p).unwrap()).unwrap();
    let (committed, snapped) = (read(Path::new(&w4)), read(&snap));
    for (name, a) in &committed {
        let most = a
            .data
            .iter()
            .zip(&snapped[name].data)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max);
        assert!(
            most <= 1e-6,
            "{name}: the rig blob moves a weight by {most}"
        );
    }
    assert!(rig.exists());
}

fn written_together_or_not_at_all(prefix: &[String], outputs: &[(&str, &str)], inputs: &[PathBuf]) {
    exporter::cli_contract::written_together_or_not_at_all(
        Path::new(env!("CARGO_BIN_EXE_exporter")),
        false,
        prefix,
        outputs,
        inputs,
    );
}

/// The commands with several outputs write them together or not at all
/// (`written_together_or_not_at_all`): `omg` with a report, snapped
/// weights and a grid; `omg-rig` the same against a motion blob; `npz`
/// and `style` a blob and its report.
#[test]
fn several_outputs_are_written_together_or_not_at_all() {
    let models = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/omg");
    let tmp = tempfile::tempdir().unwrap();
    let copy = |model: &str| {
        let dir = tmp.path().join(model);
        std::fs::create_dir(&dir).unwrap();
        for f in ["model.safetensors", "config.json"] {
            std::fs::copy(models.join(model).join(f), dir.join(f)).unwrap();
        }
        (dir.join("model.safetensors"), dir.join("config.json"))
    };
    let s = |p: &Path| p.display().to_string();
    let (w, c) = copy("tiny_fe_r1");
    let grid = [
        ("--snap-out", "m.safetensors"),
        ("--grid-out", "m.grid.json"),
    ];
    let prefix = vec![
        "omg".into(),
        "--weights".into(),
        s(&w),
        "--config".into(),
        s(&c),
    ];
    let omg_outputs = [("-o", "m.blob"), ("--report", "m.json"), grid[0], grid[1]];
    written_together_or_not_at_all(&prefix, &omg_outputs, &[w.clone(), c.clone()]);

    let motion = tmp.path().join("motion.blob");
    let o = exporter(&[
        "omg",
        "--weights",
        &s(&w),
        "--config",
        &s(&c),
        "-o",
        &s(&motion),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (rw, rc) = copy("tiny_fe_r4_frozen");
    let prefix = vec![
        "omg-rig".into(),
        "--base".into(),
        s(&motion),
        "--weights".into(),
        s(&rw),
        "--config".into(),
        s(&rc),
    ];
    let rig_outputs = [("-o", "r4.rig"), ("--report", "r4.json"), grid[0], grid[1]];
    written_together_or_not_at_all(&prefix, &rig_outputs, &[motion.clone(), rw, rc]);

    let golden = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/golden/default");
    let npz = tmp.path().join("model.npz");
    std::fs::copy(golden.join("model.npz"), &npz).unwrap();
    let blob_outputs = [("-o", "m.blob"), ("--report", "m.json")];
    let prefix = vec![
        "npz".into(),
        "--weights".into(),
        s(&npz),
        "--gating".into(),
        "cubic".into(),
    ];
    written_together_or_not_at_all(&prefix, &blob_outputs, std::slice::from_ref(&npz));

    let base = tmp.path().join("base.blob");
    std::fs::copy(golden.join("model.blob"), &base).unwrap();
    let adapter = tmp.path().join("adapter.npz");
    exporter::npz::write_npz(&adapter, &[("w", vec![4, 32], vec![0.01; 128])]).unwrap();
    let prefix = vec![
        "style".into(),
        "--base".into(),
        s(&base),
        "--base-weights".into(),
        s(&npz),
        "--adapter".into(),
        s(&adapter),
        "--name".into(),
        "lean".into(),
    ];
    let style_outputs = [("-o", "s.style"), ("--report", "s.json")];
    written_together_or_not_at_all(&prefix, &style_outputs, &[base, npz, adapter]);
}

/// Every count option has a maximum (`exporter::cli_args::bounds`),
/// refused when the command line is parsed, before anything is read: one
/// value above it fails at once, the first line naming the option and the
/// largest value accepted, and nothing is written.
#[test]
fn count_options_refuse_values_above_their_maximum() {
    use exporter::cli_args::bounds;
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("m.blob");
    let o = out.to_str().unwrap();
    let w = "tests/golden/default/model.npz";
    let cases: &[(&[&str], &str, usize)] = &[
        (
            &["npz", "--weights", w, "--gating", "cubic"],
            "--compensation-samples",
            bounds::SAMPLES,
        ),
        (
            &["npz", "--weights", w, "--gating", "cubic"],
            "--int16-budget",
            bounds::BYTES,
        ),
        (&["cp", "--weights", w], "--cp-rank", bounds::RANK),
        (
            &["cp", "--weights", w, "--cp-rank", "8"],
            "--cp-max-rank",
            bounds::RANK,
        ),
        (
            &["cp", "--weights", w, "--cp-rank", "8"],
            "--distill",
            bounds::STEPS,
        ),
        (
            &["cp", "--weights", w, "--cp-rank", "8"],
            "--distill-samples",
            bounds::SAMPLES,
        ),
        (
            &["cp", "--weights", w, "--cp-rank", "8"],
            "--als-iters",
            bounds::STEPS,
        ),
        (
            &["cp", "--weights", w, "--cp-rank", "8"],
            "--samples",
            bounds::SAMPLES,
        ),
        (
            &["cp", "--weights", w, "--cp-rank", "8"],
            "--compensation-samples",
            bounds::SAMPLES,
        ),
        (
            &["npz", "--weights", w, "--gating", "cubic"],
            "--self-test",
            bounds::SELF_TEST,
        ),
        (
            &["cp", "--weights", w, "--cp-rank", "8"],
            "--self-test",
            bounds::SELF_TEST,
        ),
        (
            &[
                "omg",
                "--weights",
                "models/omg/tiny_fe_r1/model.safetensors",
                "--config",
                "models/omg/tiny_fe_r1/config.json",
            ],
            "--self-test",
            bounds::SELF_TEST,
        ),
    ];
    for (prefix, option, max) in cases {
        let too_many = (max + 1).to_string();
        let mut args: Vec<&str> = prefix.to_vec();
        args.extend([*option, too_many.as_str(), "-o", o]);
        let r = Command::new(env!("CARGO_BIN_EXE_exporter"))
            .current_dir(Path::new(env!("CARGO_MANIFEST_DIR")).join(".."))
            .args(&args)
            .output()
            .unwrap();
        let err = stderr(&r);
        let first = err.lines().next().unwrap_or("");
        assert_eq!(r.status.code(), Some(2), "{args:?}: {err}");
        assert!(first.contains(option), "{args:?}: {first}");
        assert!(
            first.contains(&format!("largest accepted, {max}")),
            "{args:?}: {first}"
        );
        assert!(!out.exists());
    }
}

/// `--self-test N` on every command that writes a model blob: the blob is
/// the one without it plus a section at the end of its payload (same
/// header but for the payload's length and CRC), the section holds N
/// vectors that pass on the host runtime, the report and `inspect` say
/// so; `--self-test 0` is the blob without the option, byte for byte.
#[test]
fn self_test_is_stored_in_every_kind_of_model_blob() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let r = |p: &str| root.join(p).to_str().unwrap().to_string();
    let tmp = tempfile::tempdir().unwrap();
    let commands: Vec<(&str, Vec<String>)> = vec![
        (
            "npz",
            vec![
                "npz".into(),
                "--weights".into(),
                r("tests/golden/default/model.npz"),
                "--gating".into(),
                "cubic".into(),
            ],
        ),
        (
            "graph",
            vec![
                "graph".into(),
                "--graph".into(),
                r("tests/golden/softmax-graph/model.json"),
                "--weights".into(),
                r("tests/golden/softmax-graph/model.npz"),
            ],
        ),
        (
            "omg",
            vec![
                "omg".into(),
                "--weights".into(),
                r("models/omg/tiny_fe_r1/model.safetensors"),
                "--config".into(),
                r("models/omg/tiny_fe_r1/config.json"),
            ],
        ),
        (
            "cp",
            vec![
                "cp".into(),
                "--weights".into(),
                r("tests/golden/default/model.npz"),
                "--cp-rank".into(),
                "4".into(),
                "--samples".into(),
                "16".into(),
            ],
        ),
    ];
    for (name, args) in commands {
        let run = |extra: &[&str], out: &Path, report: Option<&Path>| {
            let mut a: Vec<&str> = args.iter().map(String::as_str).collect();
            a.extend(extra);
            a.extend(["-o", out.to_str().unwrap()]);
            if let Some(rep) = report {
                a.extend(["--report", rep.to_str().unwrap()]);
            }
            let o = exporter(&a);
            assert!(o.status.success(), "{name}: {}", stderr(&o));
            std::fs::read(out).unwrap()
        };
        let plain = run(&[], &tmp.path().join("plain.blob"), None);
        let zero = run(&["--self-test", "0"], &tmp.path().join("zero.blob"), None);
        assert_eq!(plain, zero, "{name}: --self-test 0 changes the blob");
        let rep = tmp.path().join("t.json");
        let with = run(
            &["--self-test", "5"],
            &tmp.path().join("t.blob"),
            Some(&rep),
        );
        let a = phasegate::Model::from_bytes(&plain).unwrap();
        let b = phasegate::Model::from_bytes(&with).unwrap();
        assert!(a.self_test().is_none(), "{name}");
        assert_eq!(b.self_test().map(|t| t.count()), Some(5), "{name}");
        assert!(b.payload().starts_with(a.payload()), "{name}");
        assert_eq!(
            b.header().nodes.to_vec(),
            a.header().nodes.to_vec(),
            "{name}"
        );
        let mut rt: Box<phasegate::Runtime<'_, 16384>> =
            Box::new(phasegate::Runtime::new(b).unwrap());
        assert_eq!(rt.run_self_test(), Ok(5), "{name}");
        let j = json(&rep);
        let blob_report = if j.get("blob").is_some() {
            &j["blob"]
        } else {
            &j
        };
        assert_eq!(blob_report["self_test"]["vectors"], 5, "{name}");
        assert_eq!(blob_report["blob_bytes"], with.len(), "{name}");
        let o = exporter(&["inspect", tmp.path().join("t.blob").to_str().unwrap()]);
        let text = String::from_utf8_lossy(&o.stdout);
        assert!(
            text.contains("self-test        5 vectors"),
            "{name}: {text}"
        );
        // A report without the option says nothing of a self-test.
        run(&[], &tmp.path().join("p.blob"), Some(&rep));
        assert!(json(&rep).to_string().find("self_test").is_none(), "{name}");
    }
}

/// Every count option at its largest accepted value (the others at their
/// defaults), under the 4 GiB cap of
/// `exporter::cli_contract::runs_under_a_memory_cap` for 3 seconds: each
/// finishes or is still running within the cap, and then an interrupt
/// leaves no output. An up-front allocation sized by the count would fail
/// at once (an allocation failure aborts: exit 134).
#[cfg(unix)]
#[test]
fn every_count_option_at_its_largest_value_runs_under_a_memory_cap() {
    use exporter::cli_args::bounds;
    use exporter::cli_contract::{each_under_a_memory_cap, CappedRun};
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let tmp = tempfile::tempdir().unwrap();
    let w = "tests/golden/default/model.npz";
    let base = "tests/golden/default/model.blob";
    let adapter = tmp.path().join("adapter.npz");
    exporter::npz::write_npz(&adapter, &[("w", vec![4, 32], vec![0.01; 128])]).unwrap();
    let adapter = adapter.display().to_string();
    let omg = [
        "omg",
        "--weights",
        "models/omg/tiny_fe_r1/model.safetensors",
        "--config",
        "models/omg/tiny_fe_r1/config.json",
    ];
    let (samples, rank, steps) = (
        bounds::SAMPLES.to_string(),
        bounds::RANK.to_string(),
        bounds::STEPS.to_string(),
    );
    let (bytes, self_test) = (bounds::BYTES.to_string(), bounds::SELF_TEST.to_string());
    let npz = ["npz", "--weights", w, "--gating", "cubic"];
    let cp = ["cp", "--weights", w, "--cp-rank", "8"];
    let style = [
        "style",
        "--base",
        base,
        "--base-weights",
        w,
        "--adapter",
        &adapter,
        "--name",
        "lean",
    ];
    let cases: Vec<Vec<&str>> = vec![
        [
            &npz[..],
            &[
                "--rounding",
                "compensated",
                "--compensation-samples",
                &samples,
            ],
        ]
        .concat(),
        [&npz[..], &["--int16-budget", &bytes]].concat(),
        [&npz[..], &["--self-test", &self_test]].concat(),
        vec!["cp", "--weights", w, "--cp-rank", &rank],
        [&cp[..], &["--cp-max-rank", &rank]].concat(),
        [&cp[..], &["--distill", &steps]].concat(),
        [&cp[..], &["--distill", "10", "--distill-samples", &samples]].concat(),
        [&cp[..], &["--als-iters", &steps]].concat(),
        [&cp[..], &["--samples", &samples]].concat(),
        [
            &cp[..],
            &[
                "--rounding",
                "compensated",
                "--compensation-samples",
                &samples,
            ],
        ]
        .concat(),
        [&cp[..], &["--self-test", &self_test]].concat(),
        [&omg[..], &["--self-test", &self_test]].concat(),
        [&style[..], &["--samples", &samples]].concat(),
    ];
    let bin = Path::new(env!("CARGO_BIN_EXE_exporter"));
    let three_s = std::time::Duration::from_secs(3);
    let cases: Vec<Vec<&str>> = cases
        .iter()
        .map(|c| [&c[..], &["-o", "{out}/m.blob"]].concat())
        .collect();
    let capped = each_under_a_memory_cap(bin, &root, &cases, three_s, None, |r, args, out| {
        if r.outcome == CappedRun::Finished {
            assert!(out.join("m.blob").exists(), "{args:?}: no blob");
        }
    });
    if !capped {
        return;
    }
    // cp-report writes a table (and --json), not a blob.
    let reports: Vec<Vec<&str>> = [
        ["--ranks", rank.as_str()],
        ["--samples", samples.as_str()],
        ["--als-iters", steps.as_str()],
    ]
    .iter()
    .map(|extra| {
        [
            &["cp-report", "--weights", w][..],
            extra,
            &["--json", "{out}/r.json"],
        ]
        .concat()
    })
    .collect();
    each_under_a_memory_cap(bin, &root, &reports, three_s, None, |_, _, _| {});
}

/// The options whose memory grows with their value (samples drawn or
/// measured) at their largest, run to the end under the 4 GiB cap: the
/// 3-second runs above catch an up-front allocation, these the growth.
/// (The steps, iterations, ranks and self-test vectors finish or take
/// time, not memory: see the runs above.)
#[cfg(unix)]
#[test]
fn the_largest_sample_counts_run_to_the_end_under_a_memory_cap() {
    use exporter::cli_args::bounds;
    use exporter::cli_contract::{each_under_a_memory_cap, CappedRun};
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let tmp = tempfile::tempdir().unwrap();
    let w = "tests/golden/default/model.npz";
    let adapter = tmp.path().join("adapter.npz");
    exporter::npz::write_npz(&adapter, &[("w", vec![4, 32], vec![0.01; 128])]).unwrap();
    let adapter = adapter.display().to_string();
    let samples = bounds::SAMPLES.to_string();
    let cases: Vec<Vec<&str>> = vec![
        vec![
            "npz",
            "--weights",
            w,
            "--gating",
            "cubic",
            "--rounding",
            "compensated",
            "--compensation-samples",
            &samples,
        ],
        vec![
            "cp",
            "--weights",
            w,
            "--cp-rank",
            "8",
            "--samples",
            &samples,
        ],
        vec![
            "cp",
            "--weights",
            w,
            "--cp-rank",
            "8",
            "--distill",
            "10",
            "--distill-samples",
            &samples,
        ],
        vec![
            "cp",
            "--weights",
            w,
            "--cp-rank",
            "8",
            "--rounding",
            "compensated",
            "--compensation-samples",
            &samples,
        ],
        vec![
            "style",
            "--base",
            "tests/golden/default/model.blob",
            "--base-weights",
            w,
            "--adapter",
            &adapter,
            "--name",
            "lean",
            "--samples",
            &samples,
        ],
    ];
    let cases: Vec<Vec<&str>> = cases
        .iter()
        .map(|c| [&c[..], &["-o", "{out}/m.blob"]].concat())
        .collect();
    each_under_a_memory_cap(
        Path::new(env!("CARGO_BIN_EXE_exporter")),
        &root,
        &cases,
        std::time::Duration::from_secs(600),
        None,
        |r, args, out| {
            assert_eq!(r.outcome, CappedRun::Finished, "{args:?}");
            assert!(out.join("m.blob").exists(), "{args:?}: no blob");
        },
    );
}
