//! The blob census: the length and SHA-256 of every blob and side file the
//! `exporter` command line makes, through each of its paths and with its
//! own defaults, on committed sources. The golden bundles pin the library's
//! defaults; this pins what a user gets from the command line, so that a
//! restructuring of the exporter (`../shared/docs/redesign-round3.md`, its
//! step 0) can show it moved no byte.
//!
//! The census is `tests/golden/census.txt`. After a deliberate change to
//! what a command writes, write it again and say so in the commit:
//!
//! ```sh
//! PHASEGATE_CENSUS=write cargo test --release -p exporter --test blob_census
//! ```
//!
//! It lives in the exporter's package rather than `tests/`, because only
//! here does cargo hand a test the path of the `exporter` binary. Rows on
//! the real PFNN skip, saying so, without it (`$PHASEGATE_PFNN_DIR`, else
//! `../shared/pfnn/network`); written without it, the census keeps their
//! old lines.

use sha2::{Digest, Sha256};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

const CENSUS: &str = "tests/golden/census.txt";
/// What stands for the run's output directory in the reports (the
/// `--calibration` file's path is the one path a report records).
const OUT: &str = "$OUT";
/// The default model's input width (`tests/golden/default`).
const DEFAULT_INPUTS: usize = 342;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("the exporter sits in the workspace")
        .to_path_buf()
}

fn real_pfnn_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("PHASEGATE_PFNN_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| root().join("../shared/pfnn/network"));
    dir.join("Xmean.bin").is_file().then_some(dir)
}

/// One way through the command line: its arguments, with `{out}` for the
/// run's output directory, and the files it writes there.
struct Row {
    name: String,
    args: Vec<String>,
    files: Vec<String>,
}

fn row(name: &str, args: &str, files: &[&str]) -> Row {
    Row {
        name: name.to_string(),
        args: args.split_whitespace().map(str::to_string).collect(),
        files: files.iter().map(|f| f.to_string()).collect(),
    }
}

/// A blob and its report, named after the row.
fn blob_row(name: &str, args: &str) -> Row {
    row(
        name,
        &format!("{args} -o {{out}}/{name}.blob --report {{out}}/{name}.json"),
        &[&format!("{name}.blob"), &format!("{name}.json")],
    )
}

fn rows(pfnn: Option<&Path>) -> Vec<Row> {
    let npz = "npz --weights tests/golden/default/model.npz --gating cubic";
    let cal = "--calibration {out}/recorded.npz";
    let mut rows = Vec::new();
    for bits in [8, 16] {
        let b = format!("--weight-bits {bits}");
        rows.push(blob_row(&format!("npz-int{bits}"), &format!("{npz} {b}")));
        rows.push(blob_row(
            &format!("npz-int{bits}-nearest"),
            &format!("{npz} {b} --rounding nearest"),
        ));
        rows.push(blob_row(
            &format!("npz-int{bits}-calibration"),
            &format!("{npz} {b} {cal}"),
        ));
        rows.push(blob_row(
            &format!("npz-int{bits}-calibration-nearest"),
            &format!("{npz} {b} {cal} --rounding nearest"),
        ));
    }
    rows.push(blob_row(
        "npz-int8-int16-budget-8192",
        &format!("{npz} --int16-budget 8192"),
    ));
    let cp = "cp --weights tests/golden/default/model.npz --cp-rank 8";
    rows.push(blob_row("cp-rank8", cp));
    rows.push(blob_row(
        "cp-rank8-distill50",
        &format!("{cp} --distill 50"),
    ));
    rows.push(blob_row(
        "cp-import-cp-diagonal",
        "cp-import --factors tests/golden/cp-diagonal/model.npz",
    ));
    rows.push(blob_row(
        "graph-softmax",
        "graph --graph tests/golden/softmax-graph/model.json \
         --weights tests/golden/softmax-graph/model.npz",
    ));
    for model in ["tiny_fe_r1", "small_rbfcat_r1"] {
        let omg = format!(
            "omg --weights models/omg/{model}/model.safetensors \
             --config models/omg/{model}/config.json"
        );
        for bits in [8, 16] {
            rows.push(blob_row(
                &format!("omg-{model}-int{bits}"),
                &format!("{omg} --weight-bits {bits}"),
            ));
        }
        let name = format!("omg-{model}-grid");
        rows.push(row(
            &name,
            &format!(
                "{omg} -o {{out}}/{name}.blob --snap-out {{out}}/{name}.safetensors \
                 --grid-out {{out}}/{name}.grid.json"
            ),
            &[
                &format!("{name}.blob"),
                &format!("{name}.safetensors"),
                &format!("{name}.grid.json"),
            ],
        ));
    }
    // After `omg-tiny_fe_r1-int8`, whose blob is the motion blob.
    let name = "omg-rig-tiny_fe_r4_frozen";
    rows.push(row(
        name,
        &format!(
            "omg-rig --base {{out}}/omg-tiny_fe_r1-int8.blob \
             --weights models/omg/tiny_fe_r4_frozen/model.safetensors \
             --config models/omg/tiny_fe_r4_frozen/config.json \
             -o {{out}}/{name}.rig --report {{out}}/{name}.json --grid-out {{out}}/{name}.grid.json"
        ),
        &[
            &format!("{name}.rig"),
            &format!("{name}.json"),
            &format!("{name}.grid.json"),
        ],
    ));
    for adapter in ["full", "diagonal", "cp"] {
        let name = format!("style-{adapter}");
        rows.push(row(
            &name,
            &format!(
                "style --base tests/golden/default/model.blob \
                 --base-weights tests/golden/default/model.npz \
                 --adapter {{out}}/adapter-{adapter}.npz --name {adapter} \
                 -o {{out}}/{name}.style --report {{out}}/{name}.json"
            ),
            &[&format!("{name}.style"), &format!("{name}.json")],
        ));
    }
    if let Some(dir) = pfnn {
        let pfnn = format!("pfnn --weights {} --gating cubic", dir.display());
        rows.push(blob_row("real-pfnn-int8", &pfnn));
        rows.push(blob_row(
            "real-pfnn-int8-nearest",
            &format!("{pfnn} --rounding nearest"),
        ));
        rows.push(blob_row(
            "real-pfnn-int16",
            &format!("{pfnn} --weight-bits 16"),
        ));
    }
    rows
}

/// Deterministic values in [-1, 1) (a 32-bit LCG): the sources the test
/// writes itself must not depend on a random crate's version.
fn lcg(seed: u32) -> impl FnMut() -> f32 {
    let mut s = seed;
    move || {
        s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        (s >> 8) as f32 / (1u32 << 23) as f32 - 1.0
    }
}

/// The sources that are not files of the repository: recorded inputs for
/// `--calibration` (the default model's random weights diverge within a
/// few frames of any script, so they are its normalisation statistics
/// spread by half a standard deviation, 256 rows with phases) and the
/// three kinds of style adapter beside its layer 1 (32 -> 32, 4 experts).
fn write_sources(out: &Path) {
    let net = exporter::npz::read_npz(&root().join("tests/golden/default/model.npz")).unwrap();
    let (mean, std) = (&net["Xmean"].data, &net["Xstd"].data);
    assert_eq!(mean.len(), DEFAULT_INPUTS);
    let n = 256;
    let mut r = lcg(0xCE05);
    let x: Vec<f32> = (0..n * DEFAULT_INPUTS)
        .map(|i| {
            let j = i % DEFAULT_INPUTS;
            (mean[j] + 0.5 * std[j] * f64::from(r())) as f32
        })
        .collect();
    let phase: Vec<f32> = (0..n)
        .map(|i| i as f32 * std::f32::consts::TAU / n as f32)
        .collect();
    exporter::npz::write_npz(
        &out.join("recorded.npz"),
        &[
            ("X", vec![n as u64, DEFAULT_INPUTS as u64], x),
            ("phase", vec![n as u64], phase),
        ],
    )
    .unwrap();
    let mut r = lcg(0x57_11E);
    let mut values = |len: usize, scale: f32| (0..len).map(|_| r() * scale).collect::<Vec<f32>>();
    let full = [("W", vec![4, 32, 32], values(4 * 32 * 32, 0.02))];
    let diagonal = [("w", vec![4, 32], values(4 * 32, 0.05))];
    let cp = [
        ("A", vec![32, 4], values(32 * 4, 0.1)),
        ("B", vec![32, 4], values(32 * 4, 0.1)),
        ("D", vec![4, 4], values(4 * 4, 1.0)),
        ("bias", vec![4, 32], values(4 * 32, 0.01)),
    ];
    for (name, arrays) in [
        ("full", &full[..]),
        ("diagonal", &diagonal[..]),
        ("cp", &cp[..]),
    ] {
        exporter::npz::write_npz(&out.join(format!("adapter-{name}.npz")), arrays).unwrap();
    }
}

fn sha256(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Runs every row in `out`; the census lines, `row file bytes sha256`.
fn census(out: &Path, rows: &[Row]) -> BTreeMap<(String, String), String> {
    let dir = out.to_str().expect("a UTF-8 temporary directory");
    let mut lines = BTreeMap::new();
    for r in rows {
        let args: Vec<String> = r.args.iter().map(|a| a.replace("{out}", dir)).collect();
        let o = Command::new(env!("CARGO_BIN_EXE_exporter"))
            .current_dir(root())
            .args(&args)
            .output()
            .expect("exporter runs");
        assert!(
            o.status.success(),
            "{}: exporter {}\n{}",
            r.name,
            args.join(" "),
            String::from_utf8_lossy(&o.stderr)
        );
        for f in &r.files {
            let bytes =
                std::fs::read(out.join(f)).unwrap_or_else(|e| panic!("{}: {f}: {e}", r.name));
            let bytes = if f.ends_with(".json") {
                String::from_utf8(bytes)
                    .expect("JSON is UTF-8")
                    .replace(dir, OUT)
                    .into_bytes()
            } else {
                bytes
            };
            lines.insert(
                (r.name.clone(), f.clone()),
                format!("{} {}", bytes.len(), sha256(&bytes)),
            );
        }
    }
    lines
}

fn parse(text: &str) -> BTreeMap<(String, String), String> {
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            assert_eq!(f.len(), 4, "{CENSUS}: {l}");
            ((f[0].into(), f[1].into()), format!("{} {}", f[2], f[3]))
        })
        .collect()
}

fn render(lines: &BTreeMap<(String, String), String>) -> String {
    let mut s = String::from(
        "# The blob census (exporter/tests/blob_census.rs): row, file, bytes, SHA-256 of what\n\
         # each `exporter` command line writes on committed sources; reports with the output\n\
         # directory as $OUT. Write again only after a deliberate change of the bytes:\n\
         # PHASEGATE_CENSUS=write cargo test --release -p exporter --test blob_census\n",
    );
    for ((row, file), v) in lines {
        s.push_str(&format!("{row} {file} {v}\n"));
    }
    s
}

#[test]
fn every_command_line_writes_the_census_bytes() {
    let pfnn = real_pfnn_dir();
    if pfnn.is_none() {
        eprintln!("skipped: the real-PFNN rows (no weights at $PHASEGATE_PFNN_DIR or ../shared/pfnn/network)");
    }
    let rows = rows(pfnn.as_deref());
    let tmp = tempfile::tempdir().unwrap();
    write_sources(tmp.path());
    let got = census(tmp.path(), &rows);
    let path = root().join(CENSUS);
    let committed = std::fs::read_to_string(&path)
        .map(|t| parse(&t))
        .unwrap_or_default();
    if std::env::var_os("PHASEGATE_CENSUS").is_some_and(|v| v == "write") {
        let mut all = got.clone();
        if pfnn.is_none() {
            for (k, v) in committed
                .iter()
                .filter(|(k, _)| k.0.starts_with("real-pfnn"))
            {
                all.insert(k.clone(), v.clone());
            }
        }
        std::fs::write(&path, render(&all)).unwrap();
        return;
    }
    let expected: BTreeMap<_, _> = committed
        .into_iter()
        .filter(|(k, _)| pfnn.is_some() || !k.0.starts_with("real-pfnn"))
        .collect();
    let mut diffs = Vec::new();
    for (k, v) in &expected {
        match got.get(k) {
            Some(g) if g == v => {}
            Some(g) => diffs.push(format!("{} {}: {v} in the census, now {g}", k.0, k.1)),
            None => diffs.push(format!("{} {}: in the census, not written now", k.0, k.1)),
        }
    }
    for (k, g) in &got {
        if !expected.contains_key(k) {
            diffs.push(format!(
                "{} {}: written now ({g}), not in the census",
                k.0, k.1
            ));
        }
    }
    assert!(
        diffs.is_empty(),
        "{CENSUS} (write it again only for a deliberate change):\n{}",
        diffs.join("\n")
    );
}
