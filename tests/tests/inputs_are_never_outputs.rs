//! No output of a command may be one of its inputs (issue 38, point 1):
//! every file a command reads is registered where it is opened
//! (`exporter::atomic::read_input`), and every output path is refused when
//! it names one. For each command of both CLIs that writes files, this
//! test lists its inputs and its outputs and runs it once per (output,
//! input) pair with that output named as that input: each run must fail
//! with one error line (after any progress lines) naming the input, leave
//! the input as it was and write nothing else.
//!
//! Commands that need the real PFNN (`accuracy`, `fidelity`,
//! `style-demo`, `exporter pfnn` on the real weights) or the generated OMG
//! data (`omg-reach`) are covered by the same registry but not run here;
//! `exporter pfnn` runs on a small PFNN directory written below.

use std::path::{Path, PathBuf};
use std::process::Command;

fn bin(name: &str) -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    let dir = exe.parent().unwrap().parent().unwrap();
    let p = dir.join(name);
    assert!(
        p.is_file(),
        "{} not built: run `cargo test --workspace` or `cargo build -p {name}`",
        p.display()
    );
    p
}

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// One command line: the tool, its arguments (`{name}` stands for the
/// input of that name), its inputs and its output options.
struct Case {
    tool: &'static str,
    args: Vec<String>,
    inputs: Vec<PathBuf>,
    outputs: Vec<&'static str>,
}

fn case(tool: &'static str, args: &[&str], inputs: &[&PathBuf], outputs: &[&'static str]) -> Case {
    Case {
        tool,
        args: args.iter().map(|a| a.to_string()).collect(),
        inputs: inputs.iter().map(|p| p.to_path_buf()).collect(),
        outputs: outputs.to_vec(),
    }
}

/// Copies `rel` (from the repository) into `dir`; its new path.
fn copy(dir: &Path, rel: &str, name: &str) -> PathBuf {
    let to = dir.join(name);
    std::fs::copy(root().join(rel), &to).unwrap();
    to
}

/// A PFNN demo directory (6 -> 8 -> 8 -> 5, 4 tables: the importer takes
/// the count from the files), constant weights.
fn small_pfnn(dir: &Path) -> PathBuf {
    let d = dir.join("pfnn");
    std::fs::create_dir(&d).unwrap();
    let f32s = |n: usize, v: f32| -> Vec<u8> { (0..n).flat_map(|_| v.to_le_bytes()).collect() };
    for (name, n, v) in [
        ("Xmean", 6, 0.0),
        ("Xstd", 6, 1.0),
        ("Ymean", 5, 0.0),
        ("Ystd", 5, 1.0),
    ] {
        std::fs::write(d.join(format!("{name}.bin")), f32s(n, v)).unwrap();
    }
    for t in 0..50 {
        for (l, (o, i)) in [(8, 6), (8, 8), (5, 8)].into_iter().enumerate() {
            std::fs::write(d.join(format!("W{l}_{t:03}.bin")), f32s(o * i, 0.01)).unwrap();
            std::fs::write(d.join(format!("b{l}_{t:03}.bin")), f32s(o, 0.0)).unwrap();
        }
    }
    d
}

#[test]
fn no_command_writes_over_one_of_its_inputs() {
    let tmp = tempfile::tempdir().unwrap();
    let t = tmp.path();
    let s = |p: &PathBuf| p.display().to_string();
    let npz = copy(t, "tests/golden/default/model.npz", "model.npz");
    let blob = copy(t, "tests/golden/default/model.blob", "model.blob");
    let inputs = copy(t, "tests/golden/default/inputs.npy", "inputs.npy");
    let phases = copy(t, "tests/golden/default/phases.npy", "phases.npy");
    let graph = copy(t, "tests/golden/softmax-graph/model.json", "graph.json");
    let graph_w = copy(t, "tests/golden/softmax-graph/model.npz", "graph.npz");
    let factors = copy(t, "tests/golden/cp-diagonal/model.npz", "factors.npz");
    let omg = t.join("tiny_fe_r1");
    std::fs::create_dir(&omg).unwrap();
    for f in [
        "model.safetensors",
        "config.json",
        "rig.json",
        "references.npz",
    ] {
        copy(&omg, &format!("models/omg/tiny_fe_r1/{f}"), f);
    }
    let (omg_w, omg_c) = (omg.join("model.safetensors"), omg.join("config.json"));
    let rig_w = copy(
        t,
        "models/omg/tiny_fe_r4_frozen/model.safetensors",
        "r4.safetensors",
    );
    let rig_c = copy(t, "models/omg/tiny_fe_r4_frozen/config.json", "r4.json");
    let pfnn = small_pfnn(t);
    let pfnn_file = pfnn.join("W1_007.bin");
    let script = t.join("walk.json");
    std::fs::write(
        &script,
        r#"{"commands": [{"at": 0.0, "velocity": [0.0, 2.5], "gait": "walk"}]}"#,
    )
    .unwrap();
    // Made by the tools themselves (checked to succeed): a motion blob for
    // omg-rig, an adapter for style, two rollouts.
    let run = |tool: &str, args: &[String]| {
        let o = Command::new(bin(tool)).args(args).output().unwrap();
        assert!(
            o.status.success(),
            "{tool} {args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    };
    let motion = t.join("motion.blob");
    run(
        "exporter",
        &[
            "omg",
            "--weights",
            &s(&omg_w),
            "--config",
            &s(&omg_c),
            "-o",
            &s(&motion),
        ]
        .map(String::from),
    );
    let adapter = t.join("adapter.npz");
    exporter::npz::write_npz(&adapter, &[("w", vec![4, 32], vec![0.01; 128])]).unwrap();
    let (ra, rb) = (t.join("a.npz"), t.join("b.npz"));
    for (r, script) in [(&ra, "walk"), (&rb, "circle-left")] {
        run(
            "host-sim",
            &[
                "rollout",
                "--model",
                &s(&blob),
                "--script",
                script,
                "--frames",
                "30",
                "--out",
                &s(r),
            ]
            .map(String::from),
        );
    }
    let omg_r = t.join("omg-rollout.npz");
    run(
        "host-sim",
        &[
            "rollout",
            "--omg",
            &s(&omg),
            "--script",
            "reach-front",
            "--frames",
            "20",
            "--out",
            &s(&omg_r),
        ]
        .map(String::from),
    );

    let (n, b, x, p) = (s(&npz), s(&blob), s(&inputs), s(&phases));
    let cases = vec![
        case(
            "exporter",
            &["pfnn", "--weights", &s(&pfnn), "--gating", "cubic"],
            &[&pfnn_file],
            &["-o", "--report"],
        ),
        case(
            "exporter",
            &["npz", "--weights", &n, "--gating", "cubic"],
            &[&npz],
            &["-o", "--report"],
        ),
        case(
            "exporter",
            &["graph", "--graph", &s(&graph), "--weights", &s(&graph_w)],
            &[&graph, &graph_w],
            &["-o", "--report"],
        ),
        case(
            "exporter",
            &["omg", "--weights", &s(&omg_w), "--config", &s(&omg_c)],
            &[&omg_w, &omg_c],
            &["-o", "--report", "--snap-out", "--grid-out"],
        ),
        case(
            "exporter",
            &[
                "omg-rig",
                "--base",
                &s(&motion),
                "--weights",
                &s(&rig_w),
                "--config",
                &s(&rig_c),
            ],
            &[&motion, &rig_w, &rig_c],
            &["-o", "--report"],
        ),
        case(
            "exporter",
            &[
                "cp",
                "--weights",
                &n,
                "--cp-rank",
                "2",
                "--als-iters",
                "2",
                "--samples",
                "8",
            ],
            &[&npz],
            &["-o", "--report", "--factors-out"],
        ),
        case(
            "exporter",
            &["cp-import", "--factors", &s(&factors)],
            &[&factors],
            &["-o", "--report"],
        ),
        case(
            "exporter",
            &[
                "cp-report",
                "--weights",
                &n,
                "--ranks",
                "2",
                "--als-iters",
                "2",
                "--samples",
                "8",
            ],
            &[&npz],
            &["--json"],
        ),
        case(
            "exporter",
            &[
                "style",
                "--base",
                &b,
                "--base-weights",
                &n,
                "--adapter",
                &s(&adapter),
                "--name",
                "lean",
            ],
            &[&blob, &npz, &adapter],
            &["-o", "--report"],
        ),
        case(
            "host-sim",
            &["eval", "--model", &b, "--inputs", &x, "--phases", &p],
            &[&blob, &inputs, &phases],
            &["--out", "--raw-out"],
        ),
        case(
            "host-sim",
            &[
                "eval",
                "--reference",
                &n,
                "--gating",
                "cubic",
                "--inputs",
                &x,
                "--phases",
                &p,
            ],
            &[&npz, &inputs, &phases],
            &["--out"],
        ),
        case(
            "host-sim",
            &[
                "rollout",
                "--model",
                &b,
                "--script",
                &s(&script),
                "--frames",
                "10",
            ],
            &[&blob, &script],
            &["--out"],
        ),
        case(
            "host-sim",
            &[
                "rollout",
                "--omg",
                &s(&omg),
                "--script",
                "reach-front",
                "--frames",
                "10",
            ],
            &[&omg_w, &omg_c, &omg.join("rig.json")],
            &["--out"],
        ),
        case(
            "host-sim",
            &["rollout-compare", &s(&ra), &s(&rb)],
            &[&ra, &rb],
            &["--json"],
        ),
        case(
            "host-sim",
            &[
                "rollout-dataset",
                "--pfnn",
                &n,
                "--scripts",
                &s(&script),
                "--frames",
                "10",
                "--blob",
                &b,
            ],
            &[&npz, &script, &blob],
            &["--out"],
        ),
        case("host-sim", &["render", &s(&ra)], &[&ra], &["--out"]),
        case(
            "host-sim",
            &["render", &s(&omg_r)],
            &[&omg_r],
            &["--out", "--gif"],
        ),
        case(
            "host-sim",
            &["plot-errors", &s(&ra), &s(&rb)],
            &[&ra, &rb],
            &["--out"],
        ),
        case(
            "host-sim",
            &["omg-accuracy", &s(&omg)],
            &[&omg_w, &omg_c],
            &["--json"],
        ),
    ];
    let out = t.join("out");
    std::fs::create_dir(&out).unwrap();
    let mut runs = 0;
    for c in &cases {
        for k in 0..c.outputs.len() {
            for input in &c.inputs {
                let before = std::fs::read(input).unwrap();
                let mut args = c.args.clone();
                for (j, other) in c.outputs.iter().enumerate() {
                    let to = if j == k {
                        input.clone()
                    } else {
                        out.join(format!("{}{j}", other.trim_start_matches('-')))
                    };
                    args.extend([other.to_string(), to.display().to_string()]);
                }
                let o = Command::new(bin(c.tool)).args(&args).output().unwrap();
                let err = String::from_utf8_lossy(&o.stderr);
                let what = format!("{} {args:?}", c.tool);
                assert!(!o.status.success(), "{what}: succeeded");
                assert_ne!(o.status.code(), Some(101), "{what}: panicked: {err}");
                // Progress lines may come first; the error is one line, last.
                let last = err.trim_end().lines().last().unwrap_or("");
                assert_eq!(err.matches("error:").count(), 1, "{what}: {err}");
                assert!(
                    last.starts_with("error: ")
                        && last.contains(&input.display().to_string())
                        && last.contains("also an input"),
                    "{what}: {err}"
                );
                assert_eq!(
                    std::fs::read(input).unwrap(),
                    before,
                    "{what}: the input changed"
                );
                let left: Vec<_> = std::fs::read_dir(&out).unwrap().collect();
                assert!(left.is_empty(), "{what}: wrote {left:?}");
                runs += 1;
            }
        }
    }
    println!(
        "{} commands, {runs} runs, every input refused as every output",
        cases.len()
    );
}
