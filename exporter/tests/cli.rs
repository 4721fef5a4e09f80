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
        assert_eq!(model.header().layers[0].experts, experts);
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
