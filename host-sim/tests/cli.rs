//! The `host-sim` command-line contract on the embedded default model.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn host_sim(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_host-sim"))
        .args(args)
        .output()
        .expect("host-sim runs")
}

fn golden(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/golden/default")
        .join(name)
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn eval_model_reproduces_the_golden_outputs() {
    let tmp = tempfile::tempdir().unwrap();
    let (y, q) = (tmp.path().join("y.npy"), tmp.path().join("q.npy"));
    let o = host_sim(&[
        "eval",
        "--model",
        s(&golden("model.blob")),
        "--inputs",
        s(&golden("inputs.npy")),
        "--phases",
        s(&golden("phases.npy")),
        "--out",
        s(&y),
        "--raw-out",
        s(&q),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(
        std::fs::read(&y).unwrap(),
        std::fs::read(golden("expected.npy")).unwrap()
    );
    assert_eq!(
        std::fs::read(&q).unwrap(),
        std::fs::read(golden("expected_q.npy")).unwrap()
    );
}

#[test]
fn eval_reference_and_compare() {
    let tmp = tempfile::tempdir().unwrap();
    let y = tmp.path().join("ref.npy");
    let o = host_sim(&[
        "eval",
        "--reference",
        s(&golden("model.npz")),
        "--gating",
        "cubic",
        "--inputs",
        s(&golden("inputs.npy")),
        "--phases",
        s(&golden("phases.npy")),
        "--out",
        s(&y),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = host_sim(&["compare", s(&golden("expected.npy")), s(&y)]);
    assert!(o.status.success());
    let table = String::from_utf8_lossy(&o.stdout);
    for group in [
        "root motion",
        "phase",
        "contacts",
        "trajectory",
        "joint positions",
        "joint velocities",
        "joint rotations",
        "overall",
    ] {
        assert!(table.contains(group), "{table}");
    }
    let o = host_sim(&["compare", "--json", s(&golden("expected.npy")), s(&y)]);
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let rms = v["overall"]["rms"].as_f64().unwrap();
    let max = v["overall"]["max_abs"].as_f64().unwrap();
    // int8 weights on a random hidden-32 net: errors well under the output stds (up to 20).
    assert!(rms > 0.0 && rms < 0.5, "rms {rms}");
    assert!(max < 10.0, "max {max}");
    assert_eq!(v["groups"].as_array().unwrap().len(), 7);
    // A file compared with itself: exactly zero.
    let o = host_sim(&["compare", "--json", s(&y), s(&y)]);
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["overall"]["max_abs"].as_f64().unwrap(), 0.0);
}

/// `host-sim demo` (without QEMU): the embedded model through the demo's
/// target script, the reach rule in words, float and fixed rows, the demo
/// bar's verdict, the figures and both pictures.
#[test]
fn demo_runs_the_trained_omg_model_and_draws_it() {
    let tmp = tempfile::tempdir().unwrap();
    let png = tmp.path().join("reach.png");
    let gif = tmp.path().join("reach.gif");
    let o = host_sim(&[
        "demo",
        "--no-target",
        "--picture",
        s(&png),
        "--gif",
        s(&gif),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(
        text.starts_with("embedded default model: trained tiny FE-OMG reaching model"),
        "{text}"
    );
    for needle in [
        "host-sim/src/demo/reach-demo.json",
        "600 frames (10.0 s at 60 fps)",
        "reach rule: a target counts if the hand starts more than 0.1 m from it; \
         reached = within 0.1 m with every bone within 1 cm of the rig's",
        "\nfloat   ",
        "\nfixed   ",
        "demo bar (>= 3/4 of the targets away from the hands reached, int8): ",
        "fixed vs float joint positions: p99",
        "blob size ",
        "bytes of activations + ",
        "MACs per frame ",
        "Cortex-M4        not measured here: skipped (--no-target)",
        "picture ",
        "animation ",
    ] {
        assert!(text.contains(needle), "{needle}: {text}");
    }
    assert!(!text.contains("reaches poorly"), "{text}");
    let bytes = std::fs::read(&png).unwrap();
    assert_eq!(&bytes[1..4], b"PNG");
    let bytes = std::fs::read(&gif).unwrap();
    assert_eq!(&bytes[..3], b"GIF");
}

#[test]
fn bad_arguments_fail_in_one_line_and_write_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let y = tmp.path().join("y.npy");
    // Inputs of the wrong width (phases given as inputs).
    let cases: Vec<Vec<String>> = vec![
        vec![
            "eval",
            "--model",
            s(&golden("model.blob")),
            "--inputs",
            s(&golden("phases.npy")),
            "--phases",
            s(&golden("phases.npy")),
            "--out",
            s(&y),
        ],
        vec![
            "eval",
            "--model",
            s(&golden("model.npz")),
            "--inputs",
            s(&golden("inputs.npy")),
            "--phases",
            s(&golden("phases.npy")),
            "--out",
            s(&y),
        ],
        vec![
            "eval",
            "--model",
            s(&golden("model.blob")),
            "--inputs",
            s(&golden("inputs.npy")),
            "--phases",
            s(&golden("expected.npy")),
            "--out",
            s(&y),
        ],
        vec![
            "compare",
            s(&golden("expected.npy")),
            s(&golden("inputs.npy")),
        ],
    ]
    .into_iter()
    .map(|v| v.into_iter().map(String::from).collect())
    .collect();
    for args in cases {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let o = host_sim(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{args:?}");
        assert_eq!(err.trim_end().lines().count(), 1, "{args:?}: {err}");
        assert!(err.starts_with("error: "), "{err}");
        assert!(!y.exists());
    }
}

/// Blobs of other format versions (the kept fixtures, `tests/fixtures/`)
/// are refused by `host-sim eval` with a message that names the version
/// found and the version supported, and nothing is written.
#[test]
fn eval_names_the_version_found_and_the_version_supported() {
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/fixtures");
    let tmp = tempfile::tempdir().unwrap();
    let y = tmp.path().join("y.npy");
    for (file, found) in [("example-v1.blob", 1), ("version0.blob", 0)] {
        let o = host_sim(&[
            "eval",
            "--model",
            s(&fixtures.join(file)),
            "--inputs",
            s(&golden("inputs.npy")),
            "--phases",
            s(&golden("phases.npy")),
            "--out",
            s(&y),
        ]);
        assert!(!o.status.success(), "{file} ran");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains(&format!("blob format version {found} is not supported"))
                && err.contains(&format!(
                    "reads version {}",
                    phasegate::blob::FORMAT_VERSION
                )),
            "{file}: {err}"
        );
        assert!(!y.exists());
    }
}

/// Command and target scripts, and an OMG model's `config.json` and
/// `rig.json`, are inputs: naming one as `--out` is refused in one line and
/// leaves it as it was.
#[test]
fn scripts_and_model_files_are_inputs_no_output_overwrites() {
    let tmp = tempfile::tempdir().unwrap();
    let command = tmp.path().join("walk.json");
    std::fs::write(
        &command,
        r#"{"name": "walk", "commands": [{"at": 0.0, "velocity": [0.0, 2.5], "gait": "walk"}]}"#,
    )
    .unwrap();
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let model = tmp.path().join("tiny_fe_r1");
    std::fs::create_dir(&model).unwrap();
    for f in [
        "model.safetensors",
        "config.json",
        "rig.json",
        "references.npz",
    ] {
        std::fs::copy(root.join("models/omg/tiny_fe_r1").join(f), model.join(f)).unwrap();
    }
    let target = tmp.path().join("reach.json");
    std::fs::copy(
        root.join("tools/omg/scripts/01-front-chest-both.json"),
        &target,
    )
    .unwrap();
    let (blob, config, rig) = (
        golden("model.blob"),
        model.join("config.json"),
        model.join("rig.json"),
    );
    let cases: Vec<(Vec<&str>, &Path)> = vec![
        (
            vec!["rollout", "--model", s(&blob), "--script", s(&command)],
            &command,
        ),
        (
            vec!["rollout", "--omg", s(&model), "--script", s(&target)],
            &target,
        ),
        (
            vec!["rollout", "--omg", s(&model), "--script", "reach-front"],
            &config,
        ),
        (
            vec!["rollout", "--omg", s(&model), "--script", "reach-front"],
            &rig,
        ),
    ];
    for (mut args, input) in cases {
        let before = std::fs::read(input).unwrap();
        args.extend(["--frames", "20", "--out", s(input)]);
        let o = host_sim(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{args:?}: succeeded");
        assert_eq!(err.trim_end().lines().count(), 1, "{args:?}: {err}");
        assert!(err.contains("also an input"), "{args:?}: {err}");
        assert_eq!(std::fs::read(input).unwrap(), before, "{args:?}");
    }
}

/// Every count option has a maximum (`exporter::cli_args::bounds`), refused
/// when the command line is parsed: one above it fails at once, the first
/// line naming the option and the largest value accepted. Data sets whose
/// rows (scripts and tours times frames) would exceed `bounds::ROWS` are
/// refused before any rollout runs.
#[test]
fn count_options_refuse_values_above_their_maximum() {
    use exporter::cli_args::bounds;
    let cases: &[(&str, &str, usize)] = &[
        ("demo", "--frames", bounds::FRAMES),
        ("accuracy", "--samples", bounds::SAMPLES),
        ("omg-reach", "--train-clips", bounds::RUNS),
        ("omg-reach", "--noise-seeds", bounds::RUNS),
        ("target", "--frames", bounds::FRAMES),
        ("target", "--self-test", bounds::SELF_TEST),
        ("rollout", "--frames", bounds::FRAMES),
        ("rollout-compare", "--every", bounds::FRAMES),
        ("rollout-dataset", "--clips", bounds::RUNS),
        ("rollout-dataset", "--tours", bounds::RUNS),
        ("rollout-dataset", "--frames", bounds::FRAMES),
        ("fidelity", "--frames", bounds::FRAMES),
        ("fidelity", "--calibration-tours", bounds::RUNS),
        ("fidelity", "--compensation-samples", bounds::SAMPLES),
        ("fidelity", "--int16-budget", bounds::BYTES),
        ("render", "--snapshots", bounds::RUNS),
        ("style-demo", "--rank", bounds::RANK),
        ("style-demo", "--steps", bounds::STEPS),
        ("style-demo", "--rounds", bounds::RUNS),
        ("style-demo", "--frames", bounds::FRAMES),
    ];
    for (command, option, max) in cases {
        let too_many = (max + 1).to_string();
        let o = host_sim(&[command, option, &too_many]);
        let err = String::from_utf8_lossy(&o.stderr);
        let first = err.lines().next().unwrap_or("");
        assert_eq!(o.status.code(), Some(2), "{command} {option}: {err}");
        assert!(first.contains(option), "{command} {option}: {first}");
        assert!(
            first.contains(&format!("largest accepted, {max}")),
            "{command} {option}: {first}"
        );
    }
    let tmp = tempfile::tempdir().unwrap();
    let o = host_sim(&[
        "style-demo",
        "--pfnn",
        s(&golden("model.npz")),
        "--out",
        s(&tmp.path().join("s")),
        "--frames",
        "216000",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(
        err.contains("make 2160000 rows") && err.contains(&bounds::STYLE_ROWS.to_string()),
        "{err}"
    );
    assert!(!tmp.path().join("s").exists());
    let out = tmp.path().join("d.npz");
    let o = host_sim(&[
        "rollout-dataset",
        "--pfnn",
        s(&golden("model.npz")),
        "--tours",
        "1000",
        "--frames",
        "600",
        "-o",
        s(&out),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(
        err.contains("600000 rows") && err.contains(&bounds::ROWS.to_string()),
        "{err}"
    );
    assert!(!out.exists());
}

/// The commands with several outputs write them together or not at all
/// (`exporter::cli_contract`): `eval` a blob's outputs and its raw integer
/// outputs; `demo` its picture and its animation (whose directories it
/// makes). `fidelity --out-dir --json` and `style-demo --out` stage their
/// files the same way (`exporter::atomic::Outputs`) but need the real PFNN
/// and minutes per run.
#[test]
fn several_outputs_are_written_together_or_not_at_all() {
    let bin = Path::new(env!("CARGO_BIN_EXE_host-sim"));
    let tmp = tempfile::tempdir().unwrap();
    let inputs: Vec<PathBuf> = ["model.blob", "inputs.npy", "phases.npy"]
        .iter()
        .map(|f| {
            let p = tmp.path().join(f);
            std::fs::copy(golden(f), &p).unwrap();
            p
        })
        .collect();
    let mut prefix = vec!["eval".to_string()];
    for (flag, p) in ["--model", "--inputs", "--phases"].iter().zip(&inputs) {
        prefix.extend([flag.to_string(), p.display().to_string()]);
    }
    let outputs = [("--out", "y.npy"), ("--raw-out", "q.npy")];
    exporter::cli_contract::written_together_or_not_at_all(bin, false, &prefix, &outputs, &inputs);

    let prefix = vec!["demo".to_string(), "--no-target".to_string()];
    let outputs = [("--picture", "reach.png"), ("--gif", "reach.gif")];
    exporter::cli_contract::written_together_or_not_at_all(bin, true, &prefix, &outputs, &[]);
}

/// Value errors found after parsing name the file and where in it:
/// `eval`'s inputs and phases (a NaN, one phase per row), `compare`'s pair.
#[test]
fn eval_and_compare_value_errors_name_the_file_and_the_row() {
    use host_sim::npy::{read_matrix_f32_any, write_matrix, write_vector};
    let tmp = tempfile::tempdir().unwrap();
    let mut x = read_matrix_f32_any(&golden("inputs.npy")).unwrap();
    x.data[x.cols + 2] = f32::NAN;
    let (xn, p3, pn) = (
        tmp.path().join("xn.npy"),
        tmp.path().join("p3.npy"),
        tmp.path().join("pn.npy"),
    );
    write_matrix(&xn, &x).unwrap();
    write_vector(&p3, &[0f32; 3]).unwrap();
    let mut p = vec![0f32; x.rows];
    p[5] = f32::INFINITY;
    write_vector(&pn, &p).unwrap();
    let y = tmp.path().join("y.npy");
    let blob = golden("model.blob");
    let (inputs, phases) = (golden("inputs.npy"), golden("phases.npy"));
    for (args, says) in [
        (
            vec!["--inputs", s(&inputs), "--phases", s(&p3)],
            format!(
                "{} has 64 input rows, but {} has 3 phases (one per row)",
                inputs.display(),
                p3.display()
            ),
        ),
        (
            vec!["--inputs", s(&xn), "--phases", s(&phases)],
            format!(
                "{}: row 1, column 2 is NaN: inputs must be finite",
                xn.display()
            ),
        ),
        (
            vec!["--inputs", s(&inputs), "--phases", s(&pn)],
            format!("{}: phase 5 is inf: phases must be finite", pn.display()),
        ),
    ] {
        for source in [
            vec!["--model", s(&blob)],
            vec!["--reference", s(&golden("model.npz")), "--gating", "cubic"],
        ] {
            let mut a = vec!["eval"];
            a.extend(&source);
            a.extend(&args);
            a.extend(["--out", s(&y)]);
            let o = host_sim(&a);
            let err = String::from_utf8_lossy(&o.stderr);
            assert_eq!(err.trim_end(), format!("error: {says}"), "{a:?}");
            assert!(!y.exists());
        }
    }
    let o = host_sim(&["compare", s(&golden("expected.npy")), s(&inputs)]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.starts_with(&format!(
            "error: {} vs {}: shapes differ",
            golden("expected.npy").display(),
            inputs.display()
        )),
        "{err}"
    );
}

/// A long but legal run (an hour of frames) interrupted by Ctrl-C ends at
/// once with exit code 130 and one line, and leaves no output and no
/// temporary file (`exporter::atomic::clean_up_on_interrupt`).
#[cfg(unix)]
#[test]
fn an_interrupted_run_leaves_no_output() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("hour.npz");
    let child = Command::new(env!("CARGO_BIN_EXE_host-sim"))
        .args([
            "rollout",
            "--model",
            s(&golden("model.blob")),
            "--script",
            "walk",
            "--frames",
            "216000",
            "--out",
            s(&out),
        ])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(1500));
    let k = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(k.success());
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(130), "{err}");
    assert_eq!(err.trim_end(), "error: interrupted; no output written");
    let left: Vec<_> = std::fs::read_dir(tmp.path()).unwrap().collect();
    assert!(left.is_empty(), "{left:?}");
}

/// Memory stays bounded by the work asked for: the largest `--frames`
/// accepted (an hour at 60 fps, `bounds::FRAMES`) runs to the end under a
/// 4 GiB address-space cap (`prlimit --as`; about 0.9 GB resident was
/// measured), and its record is written.
#[cfg(unix)]
#[test]
fn the_largest_frame_count_runs_under_a_memory_cap() {
    if Command::new("prlimit").arg("--version").output().is_err() {
        eprintln!("prlimit (util-linux) is not installed: memory-cap test skipped");
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("hour.npz");
    let frames = exporter::cli_args::bounds::FRAMES.to_string();
    let o = Command::new("prlimit")
        .arg(format!("--as={}", exporter::cli_contract::MEMORY_CAP))
        .arg(env!("CARGO_BIN_EXE_host-sim"))
        .args([
            "rollout",
            "--model",
            s(&golden("model.blob")),
            "--script",
            "walk",
        ])
        .args(["--frames", &frames, "--out", s(&out)])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = host_sim::rollout::Rollout::read(&out).unwrap();
    assert_eq!(r.poses.len(), exporter::cli_args::bounds::FRAMES);
}

/// A PFNN weight directory (the demo's `.bin` files) of a network of a
/// PFNN controller's width (342 inputs, 311 outputs) with 8 hidden units,
/// 50 tables.
fn small_pfnn_dir(dir: &Path) {
    use exporter::pfnn_dir::{write_pfnn_dir, LayerTables, PfnnTables};
    use ndarray::{Array1, Array2};
    let (x, h, y) = (342, 8, 311);
    let layers = [(h, x), (h, h), (y, h)].map(|(r, c)| LayerTables {
        w: (0..50)
            .map(|t| {
                Array2::from_shape_fn((r, c), |(i, j)| {
                    ((t + i * c + j) % 7) as f32 * 0.4 / c as f32 - 0.2
                })
            })
            .collect(),
        b: (0..50).map(|_| Array1::from_elem(r, 0.1f32)).collect(),
    });
    let tables = PfnnTables {
        xmean: Array1::zeros(x),
        xstd: Array1::from_elem(x, 1.0),
        ymean: Array1::zeros(y),
        ystd: Array1::from_elem(y, 1.0),
        layers,
    };
    std::fs::create_dir_all(dir).unwrap();
    write_pfnn_dir(&tables, dir).unwrap();
}

/// Every count option of every command at its largest accepted value
/// (with the other counts at their defaults; for the row-bounded ones,
/// the largest combination the row bound accepts), under the 4 GiB cap
/// of `exporter::cli_contract::runs_under_a_memory_cap` for 3 seconds:
/// each either finishes or is still running within the cap, and then an
/// interrupt leaves no output. An up-front allocation sized by the count
/// would fail at once (the abort this issue found: exit 134). Commands
/// that need the OMG data set or QEMU are left out, saying so, when those
/// are absent.
#[cfg(unix)]
#[test]
fn every_count_option_at_its_largest_value_runs_under_a_memory_cap() {
    use exporter::cli_args::bounds;
    use exporter::cli_contract::{each_under_a_memory_cap, CappedRun};
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let tmp = tempfile::tempdir().unwrap();
    let (a, b) = (tmp.path().join("a.npz"), tmp.path().join("b.npz"));
    for (p, script) in [(&a, "walk"), (&b, "walk")] {
        let o = host_sim(&[
            "rollout",
            "--model",
            s(&golden("model.blob")),
            "--script",
            script,
            "--frames",
            "120",
            "--out",
            s(p),
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    let blob = golden("model.blob").display().to_string();
    // A blob without golden vectors: `target` generates its frames.
    let lone_blob = tmp.path().join("model.blob");
    let net = host_sim::target::synthetic::pfnn_base(4, 6, 8, 5);
    let (bytes, _) = exporter::export::export(&net, None, &Default::default()).unwrap();
    std::fs::write(&lone_blob, bytes).unwrap();
    let lone_blob = lone_blob.display().to_string();
    let dir = tmp.path().join("pfnn");
    small_pfnn_dir(&dir);
    let dir = dir.display().to_string();
    let tiny = root.join("models/omg/tiny_fe_r1").display().to_string();
    let data = root.join("data/omg");
    let has_data = data.join("R1/clips.json").exists();
    let data = data.display().to_string();
    let has_qemu = Command::new("qemu-system-arm")
        .arg("--version")
        .output()
        .is_ok();
    let (frames, samples, runs) = (
        bounds::FRAMES.to_string(),
        bounds::SAMPLES.to_string(),
        bounds::RUNS.to_string(),
    );
    let (rank, steps, bytes) = (
        bounds::RANK.to_string(),
        bounds::STEPS.to_string(),
        bounds::BYTES.to_string(),
    );
    let self_test = bounds::SELF_TEST.to_string();
    // The most tours of 600 frames, and the most frames of --tours, the
    // row bound accepts.
    let tours_600 = (bounds::ROWS / 600).to_string();
    let frames_of_tours = (bounds::ROWS / bounds::RUNS).to_string();
    // --clips is bounded by the clips the data set holds: more are refused
    // at once, naming the file and the count, which is then the largest.
    let clips = if has_data {
        let o = host_sim(&[
            "rollout-dataset",
            "--omg",
            &tiny,
            "--data",
            &data,
            "--clips",
            &runs,
            "-o",
            s(&tmp.path().join("x.npz")),
        ]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            !o.status.success() && err.trim_end().lines().count() == 1,
            "{err}"
        );
        let held = err.split(": ").nth(2).and_then(|t| t.split(' ').next());
        held.unwrap_or_else(|| panic!("{err}")).to_string()
    } else {
        String::new()
    };
    // style-demo's rows (scripts x frames x fits) have their own bound:
    // the most frames at the default round, the most rounds at the
    // default 480 frames.
    let scripts = host_sim::style::demo::training_rows(1, 0);
    let style_frames = (bounds::STYLE_ROWS / (scripts * 2)).to_string();
    let style_rounds = (bounds::STYLE_ROWS / (scripts * 480) - 1).to_string();
    // `target --frames` is bounded by the firmware's HOSTIO region too:
    // where 216,000 frames do not fit, they are refused in one line with
    // the image's size and the region's, from which the most frames that
    // fit follow.
    let fitting = |args: &[&str]| -> String {
        if !has_qemu {
            return String::new();
        }
        let o = host_sim(args);
        if o.status.success() {
            return bounds::FRAMES.to_string();
        }
        let err = String::from_utf8_lossy(&o.stderr);
        let last = err.trim_end().lines().last().unwrap_or("");
        assert!(
            !o.status.success() && last.ends_with("run fewer frames"),
            "{err}"
        );
        let number = |after: &str| -> usize {
            let at = last.find(after).unwrap_or_else(|| panic!("{last}")) + after.len();
            last[at..].split(' ').next().unwrap().parse().unwrap()
        };
        let (image, room) = (number("input image is "), number("holds "));
        let per_frame = image / bounds::FRAMES;
        let header = image - per_frame * bounds::FRAMES;
        ((room - header) / per_frame).to_string()
    };
    let target_frames = fitting(&["target", "--model", &lone_blob, "--frames", &frames]);
    let controller_frames = fitting(&[
        "target",
        "--model",
        &blob,
        "--controller",
        "walk",
        "--frames",
        &frames,
    ]);
    let (a, b) = (a.display().to_string(), b.display().to_string());
    let mut cases: Vec<(bool, Vec<&str>)> = vec![
        (
            true,
            vec!["demo", "--pfnn", &dir, "--frames", &frames, "--no-target"],
        ),
        (
            true,
            vec![
                "accuracy",
                "--pfnn",
                &dir,
                "--samples",
                &samples,
                "--json",
                "{out}/a.json",
            ],
        ),
        (
            true,
            vec![
                "accuracy",
                "--pfnn",
                &dir,
                "--rounding",
                "compensated",
                "--compensation-samples",
                &samples,
                "--json",
                "{out}/a.json",
            ],
        ),
        (
            true,
            vec![
                "accuracy",
                "--pfnn",
                &dir,
                "--calibration-tours",
                &tours_600,
                "--json",
                "{out}/a.json",
            ],
        ),
        (
            true,
            vec![
                "accuracy",
                "--pfnn",
                &dir,
                "--int16-budget",
                &bytes,
                "--json",
                "{out}/a.json",
            ],
        ),
        (
            has_qemu,
            vec!["target", "--model", &lone_blob, "--frames", &target_frames],
        ),
        (
            has_qemu,
            vec![
                "target",
                "--model",
                &blob,
                "--controller",
                "walk",
                "--frames",
                &controller_frames,
            ],
        ),
        (
            has_qemu,
            vec!["target", "--model", &blob, "--self-test", &self_test],
        ),
        (
            has_data,
            vec![
                "omg-reach",
                &tiny,
                "--data",
                &data,
                "--train-clips",
                &runs,
                "--json",
                "{out}/r.json",
            ],
        ),
        (
            has_data,
            vec![
                "omg-reach",
                &tiny,
                "--data",
                &data,
                "--input-noise",
                "0.01",
                "--noise-seeds",
                &runs,
                "--json",
                "{out}/r.json",
            ],
        ),
        (
            true,
            vec![
                "rollout-compare",
                &a,
                &b,
                "--every",
                &frames,
                "--json",
                "{out}/c.json",
            ],
        ),
        (
            true,
            vec![
                "rollout-dataset",
                "--pfnn",
                &dir,
                "--tours",
                &runs,
                "--frames",
                &frames_of_tours,
                "-o",
                "{out}/d.npz",
            ],
        ),
        (
            true,
            vec![
                "rollout-dataset",
                "--pfnn",
                &dir,
                "--scripts",
                "walk",
                "--frames",
                &frames,
                "-o",
                "{out}/d.npz",
            ],
        ),
        (
            has_data,
            vec![
                "rollout-dataset",
                "--omg",
                &tiny,
                "--data",
                &data,
                "--clips",
                &clips,
                "-o",
                "{out}/d.npz",
            ],
        ),
        (
            true,
            vec![
                "fidelity",
                "--pfnn",
                &dir,
                "--script",
                "walk",
                "--frames",
                &frames,
                "--json",
                "{out}/f.json",
            ],
        ),
        (
            true,
            vec![
                "fidelity",
                "--pfnn",
                &dir,
                "--calibration-tours",
                &tours_600,
                "--json",
                "{out}/f.json",
            ],
        ),
        (
            true,
            vec![
                "fidelity",
                "--pfnn",
                &dir,
                "--rounding",
                "compensated",
                "--compensation-samples",
                &samples,
                "--json",
                "{out}/f.json",
            ],
        ),
        (
            true,
            vec![
                "fidelity",
                "--pfnn",
                &dir,
                "--int16-budget",
                &bytes,
                "--json",
                "{out}/f.json",
            ],
        ),
        (
            true,
            vec!["render", &a, "--snapshots", &runs, "-o", "{out}/r.png"],
        ),
        (
            true,
            vec![
                "style-demo",
                "--pfnn",
                &dir,
                "--out",
                "{out}/s",
                "--rank",
                &rank,
            ],
        ),
        (
            true,
            vec![
                "style-demo",
                "--pfnn",
                &dir,
                "--out",
                "{out}/s",
                "--steps",
                &steps,
            ],
        ),
        (
            true,
            vec![
                "style-demo",
                "--pfnn",
                &dir,
                "--out",
                "{out}/s",
                "--rounds",
                &style_rounds,
            ],
        ),
        (
            true,
            vec![
                "style-demo",
                "--pfnn",
                &dir,
                "--out",
                "{out}/s",
                "--frames",
                &style_frames,
            ],
        ),
    ];
    let skipped: Vec<String> = cases
        .iter()
        .filter(|(run, _)| !run)
        .map(|(_, args)| args[..2].join(" "))
        .collect();
    if !skipped.is_empty() {
        eprintln!("without the OMG data set or QEMU, not run: {skipped:?}");
    }
    cases.retain(|(run, _)| *run);
    let cases: Vec<Vec<&str>> = cases.into_iter().map(|(_, args)| args).collect();
    let scratch = tempfile::tempdir().unwrap();
    each_under_a_memory_cap(
        Path::new(env!("CARGO_BIN_EXE_host-sim")),
        scratch.path(),
        &cases,
        std::time::Duration::from_secs(3),
        Some("bars missed"),
        |r, args, out| {
            if r.outcome == CappedRun::Finished && args[0] != "fidelity" {
                let n = std::fs::read_dir(out).unwrap().count();
                let o = out.display().to_string();
                let writes = args.iter().any(|a| a.starts_with(&o));
                assert!(n > 0 || !writes, "{args:?}: finished without output");
            }
        },
    );
}

/// An interrupt that comes while an output is being written (its
/// temporary file exists but is not complete) removes that temporary too:
/// a 216,000-frame data set (about 300 MB) is interrupted as soon as its
/// temporary appears.
#[cfg(unix)]
#[test]
fn an_interrupt_during_a_write_leaves_no_temporary() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("pfnn");
    small_pfnn_dir(&dir);
    let out = tmp.path().join("out");
    std::fs::create_dir(&out).unwrap();
    let child = Command::new(env!("CARGO_BIN_EXE_host-sim"))
        .args(["rollout-dataset", "--pfnn", s(&dir), "--scripts", "walk"])
        .args(["--frames", "216000", "-o", s(&out.join("d.npz"))])
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let start = std::time::Instant::now();
    let seen = loop {
        let names: Vec<String> = std::fs::read_dir(&out)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        if names.iter().any(|n| n.ends_with(".tmp")) {
            break true;
        }
        if !names.is_empty() || start.elapsed().as_secs() > 120 {
            break false;
        }
        std::thread::sleep(std::time::Duration::from_millis(1));
    };
    let k = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(k.success());
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(seen, "no temporary seen before the output: {err}");
    assert_eq!(o.status.code(), Some(130), "{err}");
    let left: Vec<_> = std::fs::read_dir(&out).unwrap().collect();
    assert!(left.is_empty(), "{left:?}");
}

/// The options whose memory grows with their value (rows sampled or
/// recorded, frames rolled out) at their largest, run to the end under
/// the 4 GiB cap: the 3-second runs above catch an up-front allocation,
/// these the growth (it was a run to the end that found `style-demo
/// --frames 216000` growing to 24 GB). `style-demo` fits 10 steps, not
/// 1,500: the steps cost time, not memory. About two minutes.
#[cfg(unix)]
#[test]
fn the_largest_data_sizes_run_to_the_end_under_a_memory_cap() {
    use exporter::cli_args::bounds;
    use exporter::cli_contract::{each_under_a_memory_cap, CappedRun};
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("pfnn");
    small_pfnn_dir(&dir);
    let dir = dir.display().to_string();
    let (frames, samples, runs) = (
        bounds::FRAMES.to_string(),
        bounds::SAMPLES.to_string(),
        bounds::RUNS.to_string(),
    );
    let tours_600 = (bounds::ROWS / 600).to_string();
    let frames_of_tours = (bounds::ROWS / bounds::RUNS).to_string();
    let scripts = host_sim::style::demo::training_rows(1, 0);
    let style_frames = (bounds::STYLE_ROWS / (scripts * 2)).to_string();
    let style_rounds = (bounds::STYLE_ROWS / (scripts * 480) - 1).to_string();
    let p = ["--pfnn", dir.as_str()];
    let cases: Vec<Vec<&str>> = vec![
        [&["demo"], &p[..], &["--frames", &frames, "--no-target"]].concat(),
        [
            &["accuracy"],
            &p[..],
            &["--samples", &samples, "--json", "{out}/a.json"],
        ]
        .concat(),
        [
            &["accuracy"],
            &p[..],
            &[
                "--rounding",
                "compensated",
                "--compensation-samples",
                &samples,
                "--json",
                "{out}/a.json",
            ],
        ]
        .concat(),
        [
            &["accuracy"],
            &p[..],
            &["--calibration-tours", &tours_600, "--json", "{out}/a.json"],
        ]
        .concat(),
        [
            &["fidelity"],
            &p[..],
            &[
                "--script",
                "walk",
                "--frames",
                &frames,
                "--json",
                "{out}/f.json",
            ],
        ]
        .concat(),
        [
            &["fidelity"],
            &p[..],
            &["--calibration-tours", &tours_600, "--json", "{out}/f.json"],
        ]
        .concat(),
        [
            &["rollout-dataset"],
            &p[..],
            &[
                "--tours",
                &runs,
                "--frames",
                &frames_of_tours,
                "-o",
                "{out}/d.npz",
            ],
        ]
        .concat(),
        [
            &["rollout-dataset"],
            &p[..],
            &[
                "--scripts",
                "walk",
                "--frames",
                &frames,
                "-o",
                "{out}/d.npz",
            ],
        ]
        .concat(),
        [
            &["style-demo"],
            &p[..],
            &[
                "--out",
                "{out}/s",
                "--steps",
                "10",
                "--frames",
                &style_frames,
            ],
        ]
        .concat(),
        [
            &["style-demo"],
            &p[..],
            &[
                "--out",
                "{out}/s",
                "--steps",
                "10",
                "--rounds",
                &style_rounds,
            ],
        ]
        .concat(),
    ];
    let scratch = tempfile::tempdir().unwrap();
    each_under_a_memory_cap(
        Path::new(env!("CARGO_BIN_EXE_host-sim")),
        scratch.path(),
        &cases,
        std::time::Duration::from_secs(900),
        Some("bars missed"),
        |r, args, _| assert_eq!(r.outcome, CappedRun::Finished, "{args:?}"),
    );
}
