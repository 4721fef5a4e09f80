//! The committed OMG models (`models/omg/*`: tiny FE, its Frozen and Raw
//! R4 transfers, small FE, small RBF-CAT, tiny FS; all joint-velocity
//! models, `docs/omg-joint-velocity.md`) through `exporter omg`'s importer:
//! the exporter's f64 graph forward against the PyTorch reference outputs
//! committed beside them (one step and the 300-frame grounded rollout), and
//! int16 / int8 blobs on the host runtime against that forward
//! (`docs/omg.md` has the figures).
//!
//! Relative error: `|a - b| / max(|b|, std_j)` with `std_j` the model's own
//! standard deviation of feature j (relative above the feature's spread,
//! in units of it below, so features near zero do not divide by zero).

use std::path::{Path, PathBuf};

use exporter::net::omg::{read_omg, HEADROOM};
use exporter::quantise::QuantOptions;
use host_sim::omg::{export, fixed_agreement, float_agreement, load_dir};
use phasegate::blob::WeightFormat;

fn model_dir(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../models/omg")
        .join(name)
}

/// The committed tiny models: the embedded default and its Frozen transfer.
const MODELS: [&str; 2] = ["tiny_fe_r1", "tiny_fe_r4_frozen"];

/// All committed models: the small FE, the small RBF-CAT (its clustering
/// layer on the graph's RBF op), the tiny FS and the Raw R4 transfer
/// included.
const ALL_MODELS: [&str; 6] = [
    "tiny_fe_r1",
    "tiny_fe_r4_frozen",
    "tiny_fe_r4_raw",
    "small_fe_r1",
    "small_rbfcat_r1",
    "tiny_fs_r1",
];

/// The references are the same PyTorch modules run in float64 on the
/// stored weights (`tools/omg/train/references.py`, stored as float32):
/// issue 11's 1e-4 holds one step and over the 300 fed-back frames, and
/// what remains is the files' own float32 rounding (measured 6.0e-8).
#[test]
fn the_f64_graph_forward_reproduces_the_pytorch_references() {
    for name in ALL_MODELS {
        let d = load_dir(&model_dir(name)).unwrap();
        let a = float_agreement(&d).unwrap();
        eprintln!("{name}: {a:?}");
        assert!(a.one_step.max_rel <= 1e-4, "{name}: {:?}", a.one_step);
        assert!(a.rollout.max_rel <= 1e-4, "{name}: {:?}", a.rollout);
        assert!(a.rollout.max_joint_m <= 1e-5, "{name}: {:?}", a.rollout);
        assert_eq!(a.rollout.frames, d.refs.rollout.dims[0] * 300);
    }
}

/// The small models' int16 / int8 blobs against the f64 forward (the tiny
/// ones below have their own bars).
#[test]
fn small_model_blobs_follow_the_f64_forward() {
    let opts = QuantOptions {
        headroom: HEADROOM,
        ..QuantOptions::default()
    };
    for name in ["small_fe_r1", "small_rbfcat_r1"] {
        let d = load_dir(&model_dir(name)).unwrap();
        let i16 =
            fixed_agreement(&d, &export(&d, WeightFormat::I16, &opts).unwrap(), "int16").unwrap();
        let i8 =
            fixed_agreement(&d, &export(&d, WeightFormat::I8, &opts).unwrap(), "int8").unwrap();
        eprintln!("{name}: {i16:?}\n{i8:?}");
        assert!(i16.one_step.max_joint_m <= 0.001, "{name}: {i16:?}");
        assert!(i16.rollout.p99_joint_m <= 0.01, "{name}: {i16:?}");
        assert!(i8.one_step.p99_joint_m <= 0.01, "{name}: {i8:?}");
    }
}

#[test]
fn fixed_point_blobs_follow_the_f64_forward() {
    let opts = QuantOptions {
        headroom: HEADROOM,
        ..QuantOptions::default()
    };
    for name in MODELS {
        let d = load_dir(&model_dir(name)).unwrap();
        let i16 =
            fixed_agreement(&d, &export(&d, WeightFormat::I16, &opts).unwrap(), "int16").unwrap();
        let i8 =
            fixed_agreement(&d, &export(&d, WeightFormat::I8, &opts).unwrap(), "int8").unwrap();
        eprintln!("{name}: {i16:?}\n{i8:?}");
        // One step, metres.
        assert!(i16.one_step.max_joint_m <= 0.001, "{name}: {i16:?}");
        assert!(i8.one_step.p99_joint_m <= 0.01, "{name}: {i8:?}");
        // The grounded rollout: p99 joint difference within 1 cm (int16)
        // and 2 cm (int8).
        assert!(i16.rollout.p99_joint_m <= 0.01, "{name}: {i16:?}");
        assert!(i8.rollout.p99_joint_m <= 0.02, "{name}: {i8:?}");
    }
    // tiny_fe_r1's weights are its int8 blob's (fine-tuned and snapped,
    // tools.omg.train.qat): what the int8 blob still differs by is the
    // activations' fixed point, as int16's (measured one step p99 0.013 cm,
    // against 0.70 cm for the float-trained model).
    let d = load_dir(&model_dir("tiny_fe_r1")).unwrap();
    let i8 = fixed_agreement(&d, &export(&d, WeightFormat::I8, &opts).unwrap(), "int8").unwrap();
    assert!(i8.one_step.max_joint_m <= 0.001, "{i8:?}");
}

#[test]
fn import_errors_name_the_file_and_the_tensor() {
    let dir = tempfile::tempdir().unwrap();
    let src = model_dir("tiny_fe_r1");
    let arrays = exporter::cp::import::read_arrays(&src.join("model.safetensors")).unwrap();
    let write = |path: &Path, skip: &str, reshape: Option<(&str, Vec<u64>)>| {
        let list: Vec<(&str, Vec<u64>, Vec<f32>)> = arrays
            .iter()
            .filter(|(n, _)| n.as_str() != skip)
            .map(|(n, a)| {
                let shape = match &reshape {
                    Some((r, s)) if r == n => s.clone(),
                    _ => a.shape.clone(),
                };
                (
                    n.as_str(),
                    shape,
                    a.data.iter().map(|&v| v as f32).collect(),
                )
            })
            .collect();
        exporter::cp::import::write_arrays(path, &list).unwrap();
    };
    let cfg = src.join("config.json");
    let w = dir.path().join("missing.safetensors");
    write(&w, "experts.w1", None);
    let e = format!("{:#}", read_omg(&w, &cfg).unwrap_err());
    assert_eq!(
        e,
        format!(
            "{}: tensor \"experts.w1\" is missing (the weights of {})",
            w.display(),
            cfg.display()
        )
    );
    let w = dir.path().join("shape.safetensors");
    write(&w, "", Some(("gate.1.w", vec![8, 32])));
    let e = format!("{:#}", read_omg(&w, &cfg).unwrap_err());
    assert_eq!(
        e,
        format!(
            "{}: tensor \"gate.1.w\" has shape [8, 32], expected [16, 16] (gate 16 -> 16) (the weights of {})",
            w.display(),
            cfg.display()
        )
    );
    // An inconsistent config names the config.
    let mut c: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&cfg).unwrap()).unwrap();
    c["out_slices"]["z"] = serde_json::json!([8, 41]);
    let bad = dir.path().join("config.json");
    std::fs::write(&bad, c.to_string()).unwrap();
    let e = format!(
        "{:#}",
        read_omg(&src.join("model.safetensors"), &bad).unwrap_err()
    );
    assert!(
        e.starts_with(&format!(
            "{}: out_slices.z 8..41 and out_slices.cost 40..64 overlap",
            bad.display()
        )),
        "{e}"
    );
    assert!(!e.contains('\n'));
}

/// The generated OMG data set (`data/omg`), or `None` with a message
/// saying that `what` is not checked without it.
fn omg_data(what: &str) -> Option<PathBuf> {
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../data/omg");
    if data.join("R1/clips.json").exists() && data.join("R4/clips.json").exists() {
        return Some(data);
    }
    eprintln!(
        "OMG data set absent at {}: {what} not checked \
         (python3 -m tools.omg.generate --out data/omg --seed 0 --rigs R1,R4)",
        data.display()
    );
    None
}

/// `host-sim omg-reach`'s f64 rollouts of the held-out clips (and of the
/// target scripts) give the NumPy evaluation's figures
/// (`models/omg/eval.json`, `python3 -m tools.omg.evaluate`): two
/// implementations of the loop and of the metrics (`tools/omg/metrics.py`,
/// `host_sim::reach_metrics`) agree. Bone errors differ by the rest lengths'
/// rounding (NumPy takes the rig's exact offsets, host-sim the config's,
/// rounded to 1e-6 m). Needs the data set (`python3 -m tools.omg.generate
/// --out data/omg --seed 0 --rigs R1,R4`, about a minute; .ci/run generates
/// it and runs this test again).
#[test]
fn reach_metrics_match_the_numpy_evaluation() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let Some(data) = omg_data("reach metrics") else {
        return;
    };
    let eval: serde_json::Value =
        serde_json::from_slice(&std::fs::read(root.join("models/omg/eval.json")).unwrap()).unwrap();
    let knobs = host_sim::quant_knobs::Int8Knobs::default();
    let opts = QuantOptions {
        headroom: HEADROOM,
        ..QuantOptions::default()
    };
    let scripts = root.join("tools/omg/scripts");
    for name in MODELS {
        let j = host_sim::omg_reach::Judged::new(&model_dir(name), &data, None).unwrap();
        let r = host_sim::omg_reach::measure_with_scripts(&j, &opts, &knobs, None, Some(&scripts))
            .unwrap();
        eprint!("{}", r.table());
        let want = eval
            .as_array()
            .unwrap()
            .iter()
            .find(|m| m["name"] == name)
            .unwrap_or_else(|| panic!("{name} not in eval.json"));
        assert_eq!(r.clips, want["clips"].as_u64().unwrap() as usize, "{name}");
        let mut sets = vec![("held_out", r.rows.clone())];
        if let Some(s) = r.scripts.as_ref().filter(|s| s.skipped.is_none()) {
            sets.push(("scripts", s.rows.clone()));
        }
        for (set, rows) in sets {
            for (run, py) in [
                ("f64", "f64"),
                ("data", "data"),
                ("hold still", "hold still"),
            ] {
                let Some(x) = rows.iter().find(|x| x.run == run) else {
                    continue;
                };
                let w = &want[set][py];
                if w.is_null() {
                    continue;
                }
                let close = |a: f64, key: &str, tol: f64| {
                    let b = w[key].as_f64().unwrap_or(f64::NAN);
                    assert!(
                        (a - b).abs() <= tol,
                        "{name} {set} {run} {key}: host-sim {a}, NumPy {b}"
                    );
                };
                assert_eq!(
                    x.summary.targets,
                    w["targets"].as_u64().unwrap() as usize,
                    "{name} {set} {run}"
                );
                assert_eq!(
                    x.summary.near_start,
                    w["near_start"].as_u64().unwrap() as usize
                );
                close(x.summary.reach, "reach", 1e-9);
                close(x.summary.plausible_reach, "plausible_reach", 1e-9);
                if let Some(f) = x.summary.frames_median {
                    close(f, "frames_median", 1e-9);
                }
                close(x.summary.final_m, "final_m", 1e-5);
                close(x.summary.bone_err_p99_cm, "bone_err_p99_cm", 1e-3);
                close(x.summary.roughness, "roughness", 1e-6);
            }
        }
        // The blobs ran the same clips and were compared with the f64 rollout.
        let f = r.rows.iter().find(|x| x.run == "f64").unwrap();
        for run in ["int16", "int8"] {
            let b = r.rows.iter().find(|x| x.run == run).unwrap();
            assert_eq!(
                b.summary.targets + b.summary.near_start,
                f.summary.targets + f.summary.near_start
            );
            assert!(
                b.vs_f64.as_ref().unwrap().frames == r.clips * 300,
                "{name} {run}"
            );
        }
    }
}

/// Issue 11's bars on the held-out clips (docs/omg.md, "Models trained for
/// their int8 blobs"): each committed model's int16 and int8 deployment
/// (whole blobs; for the Frozen R4 model, rig blobs against tiny_fe_r1's
/// motion blobs of the same width) keeps the f64 model's reach within 2
/// percentage points, and its p99 joint difference to the f64 rollout
/// within 1 cm (int16) and 2 cm (int8) over 96 clips of 300 frames. The
/// models are fine-tuned for their int8 blobs (`tools.omg.train.qat`'s
/// DAgger on the blob's grid, one fixed recipe). No row of the graph's
/// output saturates on the f64 rollout's frames (the exporter keeps them as
/// wide as the input stage: before, small RBF-CAT's int16 blob clipped arm
/// velocities and missed its bar at 1.240 cm). Prints every verdict and
/// the rows that do saturate. Needs the data set, as the test above.
#[test]
fn reach_bars_on_every_committed_model() {
    let Some(data) = omg_data("reach bars") else {
        return;
    };
    let knobs = host_sim::quant_knobs::Int8Knobs::default();
    let opts = QuantOptions {
        headroom: HEADROOM,
        ..QuantOptions::default()
    };
    for (name, motion) in [
        ("tiny_fe_r1", None),
        ("tiny_fe_r4_frozen", Some(model_dir("tiny_fe_r1"))),
        ("tiny_fe_r4_raw", None),
        ("small_fe_r1", None),
        ("small_rbfcat_r1", None),
        ("tiny_fs_r1", None),
    ] {
        let r = host_sim::omg_reach::measure(
            &model_dir(name),
            &data,
            &opts,
            &knobs,
            motion.as_deref(),
            None,
        )
        .unwrap();
        eprint!("{}", r.table());
        let net = host_sim::omg::load_dir(&model_dir(name)).unwrap().omg.net;
        let exporter::net::Wiring::Graph(g) = &net.wiring else {
            panic!("{name}: an OMG model is a graph");
        };
        let phasegate::blob::Source::Node(output_node) = g.output.source else {
            panic!("{name}: the output is a node's");
        };
        let output_node = usize::from(output_node);
        let f = r.rows.iter().find(|x| x.run == "f64").unwrap();
        let blobs: Vec<_> = r.rows.iter().filter(|x| x.vs_f64.is_some()).collect();
        assert_eq!(blobs.len(), 2, "{name}");
        for b in blobs {
            let bar_m = if b.run.starts_with("int16") {
                0.01
            } else {
                0.02
            };
            let p99 = b.vs_f64.as_ref().unwrap().p99_joint_m;
            eprintln!(
                "{name} {}: p99 {:.3} cm, issue 11's bar {} cm: {}",
                b.run,
                p99 * 100.0,
                bar_m * 100.0,
                if p99 <= bar_m { "met" } else { "NOT met" }
            );
            assert!(p99 <= bar_m, "{name} {}: p99 {p99} m", b.run);
            let sat = b.saturated.as_ref().unwrap();
            assert!(
                sat.nodes.iter().all(|n| n.node != output_node),
                "{name} {}: the output node saturates: {}",
                b.run,
                sat.summary()
            );
            assert!(
                (b.summary.plausible_reach - f.summary.plausible_reach).abs() <= 0.02 + 1e-12,
                "{name} {}: plausible reach {} against {}",
                b.run,
                b.summary.plausible_reach,
                f.summary.plausible_reach
            );
        }
    }
}

/// The reaching issue's bars (issue 34; `models/omg/README.md` has the
/// table): the embedded default, tiny FE, as its **int8 blob** on the
/// runtime plausibly reaches at least 60 % of the held-out clips' targets
/// and of the hand-written scripts' (`tools/omg/scripts`, targets the hand
/// does not start at), in at most 1.5 times the data's median frames, ends
/// within 0.12 m on average, keeps every bone within 1 cm (p99) and is at
/// most 1.5 times as rough as the data; R4 through its rig blob on R1's
/// motion blob plausibly reaches at least 50 %, ahead of the Raw R4 model
/// trained from scratch on the same clips. Needs the data set.
#[test]
fn the_reaching_bars_hold() {
    let Some(data) = omg_data("reaching bars") else {
        return;
    };
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let knobs = host_sim::quant_knobs::Int8Knobs::default();
    let opts = QuantOptions {
        headroom: HEADROOM,
        ..QuantOptions::default()
    };
    let j = host_sim::omg_reach::Judged::new(&model_dir("tiny_fe_r1"), &data, None).unwrap();
    let r = host_sim::omg_reach::measure_with_scripts(
        &j,
        &opts,
        &knobs,
        None,
        Some(&root.join("tools/omg/scripts")),
    )
    .unwrap();
    eprint!("{}", r.table());
    let row = |rows: &[host_sim::omg_reach::ReachRow], run: &str| {
        rows.iter().find(|x| x.run == run).unwrap().clone()
    };
    let (int8, data_row) = (row(&r.rows, "int8"), row(&r.rows, "data"));
    assert!(int8.summary.plausible_reach >= 0.60, "{int8:?}");
    assert!(
        int8.summary.frames_median.unwrap() <= 1.5 * data_row.summary.frames_median.unwrap(),
        "{int8:?} {data_row:?}"
    );
    assert!(int8.summary.final_m <= 0.12, "{int8:?}");
    assert!(int8.summary.bone_err_p99_cm <= 1.0, "{int8:?}");
    assert!(
        int8.summary.roughness <= 1.5 * data_row.summary.roughness,
        "{int8:?} {data_row:?}"
    );
    let scripts = r.scripts.as_ref().unwrap();
    assert!(scripts.skipped.is_none());
    let s8 = row(&scripts.rows, "int8");
    assert!(s8.summary.plausible_reach >= 0.60, "{s8:?}");
    assert!(
        s8.summary.targets >= 60,
        "most script targets count: {s8:?}"
    );

    let frozen = host_sim::omg_reach::measure(
        &model_dir("tiny_fe_r4_frozen"),
        &data,
        &opts,
        &knobs,
        Some(&model_dir("tiny_fe_r1")),
        None,
    )
    .unwrap();
    let raw = host_sim::omg_reach::measure(
        &model_dir("tiny_fe_r4_raw"),
        &data,
        &opts,
        &knobs,
        None,
        None,
    )
    .unwrap();
    eprint!("{}{}", frozen.table(), raw.table());
    let (f8, r8) = (row(&frozen.rows, "int8 rig"), row(&raw.rows, "int8"));
    assert!(f8.summary.plausible_reach >= 0.50, "{f8:?}");
    assert!(
        f8.summary.plausible_reach > r8.summary.plausible_reach,
        "Frozen {f8:?} against Raw {r8:?}"
    );
}

/// `omg-reach --train-clips N` judges on the first N clips of the training
/// split (to choose among fine-tuning runs without the held-out clips), and
/// refuses none; `--motion-from` refuses the int8 knobs, which its rig
/// blobs do not take.
#[test]
fn reach_on_training_clips_and_its_refusals() {
    let Some(data) = omg_data("training-clip reach") else {
        return;
    };
    let opts = QuantOptions {
        headroom: HEADROOM,
        ..QuantOptions::default()
    };
    let none = host_sim::quant_knobs::Int8Knobs::default();
    let dir = model_dir("tiny_fe_r1");
    let r = host_sim::omg_reach::measure(&dir, &data, &opts, &none, None, Some(2)).unwrap();
    assert_eq!((r.clips, r.split.as_str()), (2, "training"));
    for b in r.rows.iter().filter(|x| x.vs_f64.is_some()) {
        assert_eq!(b.vs_f64.as_ref().unwrap().frames, 2 * 300, "{}", b.run);
    }
    let e = host_sim::omg_reach::measure(&dir, &data, &opts, &none, None, Some(0)).unwrap_err();
    assert!(e.to_string().contains("--train-clips 0"), "{e}");
    let knobs = host_sim::quant_knobs::Int8Knobs {
        int16_budget: Some(1000),
        ..Default::default()
    };
    let r4 = model_dir("tiny_fe_r4_frozen");
    let e =
        host_sim::omg_reach::measure(&r4, &data, &opts, &knobs, Some(&dir), Some(1)).unwrap_err();
    assert!(e.to_string().contains("leave out the int8 knobs"), "{e}");
}

/// `omg-reach --input-noise A`: the f64 model rolled out with uniform input
/// noise of A standard deviations, against its plain f64 rollout; A = 0
/// is that rollout exactly, a nonzero A moves it, and a negative or
/// non-finite A is refused. Needs the data set, as the test above.
#[test]
fn input_noise_rows_perturb_the_f64_rollout_and_nothing_else() {
    let Some(data) = omg_data("input-noise rollouts") else {
        return;
    };
    let dir = model_dir("tiny_fe_r1");
    let two = host_sim::omg_reach::Judged::new(&dir, &data, Some(2)).unwrap();
    let rows = host_sim::omg_reach::input_noise_rows(&two, &[0.0, 1e-3], 2).unwrap();
    let names: Vec<&str> = rows.iter().map(|r| r.run.as_str()).collect();
    assert_eq!(
        names,
        ["f64~0e0/s0", "f64~0e0/s1", "f64~1e-3/s0", "f64~1e-3/s1"]
    );
    for r in &rows {
        let v = r.vs_f64.as_ref().unwrap();
        assert_eq!(v.frames, 2 * 300, "{}", r.run);
        if r.run.starts_with("f64~0e0") {
            assert_eq!((v.max_abs, v.p99_joint_m), (0.0, 0.0), "{}", r.run);
        } else {
            assert!(v.max_abs > 0.0, "{}", r.run);
        }
        assert!(r.saturated.is_none() && r.blob_bytes == 0);
    }
    assert_ne!(
        rows[2].vs_f64.as_ref().unwrap().max_abs,
        rows[3].vs_f64.as_ref().unwrap().max_abs,
        "seeds draw different noise"
    );
    for bad in [-1e-3, f64::NAN] {
        let e = host_sim::omg_reach::input_noise_rows(&two, &[bad], 1).unwrap_err();
        assert!(e.to_string().contains("--input-noise"), "{e}");
    }
    assert!(host_sim::omg_reach::input_noise_rows(&two, &[1e-3], 0)
        .unwrap()
        .is_empty());
}

/// The device's configuration of the reaching controller: the loop in f32
/// (`Reach<f32, _>` with the model's skeleton) over the fixed-point
/// runtime, sized statically for the model, follows the host's loop over
/// the same blob (f64 glue) on the reference clips; the glue's f32
/// rounding (forward kinematics, the limit stage, the costs) is all that
/// differs. Bound: 1 mm over 100 frames.
#[test]
fn the_f32_reaching_loop_over_the_runtime_follows_the_host_loop() {
    use phasegate_controller::{CostMode, Reach};
    let opts = QuantOptions {
        headroom: HEADROOM,
        ..QuantOptions::default()
    };
    let d = load_dir(&model_dir("tiny_fe_r1")).unwrap();
    let blob = export(&d, WeightFormat::I16, &opts).unwrap();
    let model = phasegate::Model::from_bytes(&blob).unwrap();
    let mut rt: Box<phasegate::Runtime<'_, 2048>> =
        Box::new(phasegate::Runtime::new(model).unwrap());
    let layout = host_sim::omg::reach_layout(&d.omg).unwrap();
    let form = d.omg.dof.as_ref().expect("a joint-velocity model");
    let skeleton = host_sim::omg::skeleton::<f32>(&form.skeleton).unwrap();
    let mut host = host_sim::omg::FixedOmg::new(&blob).unwrap();
    let mut worst = 0f64;
    let f32s = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
    for c in 0..d.refs.targets.dims[0] {
        let want = host_sim::omg::reference_rollout(&d, c, &mut host).unwrap();
        let start = host_sim::omg::reference_start(&d, c);
        let mut r: Box<Reach<f32, 512>> = Box::new(
            Reach::with_dofs(
                &*rt,
                layout.clone(),
                CostMode::Grounded,
                &f32s(&start.first),
                skeleton.clone(),
                &f32s(&start.q0),
                &f32s(&start.v0),
            )
            .unwrap(),
        );
        for (t, w) in want.iter().enumerate().skip(1).take(100) {
            r.set_target_block(&f32s(d.refs.targets.row(c, t))).unwrap();
            let pose = r.step(&mut *rt).unwrap();
            for (a, b) in pose.positions.iter().zip(&w[layout.pos.clone()]) {
                worst = worst.max((f64::from(*a) - b).abs());
            }
        }
    }
    eprintln!(
        "f32 loop vs f64 glue, same int16 blob, 100 frames: max position difference {worst:.2e} m"
    );
    assert!(worst < 1e-3, "{worst}");
}

/// `omg-reach --calibration-clips N`: the int8 blob's recorded calibration
/// rows are the f64 model's grounded rollouts of the first N *training*
/// clips (never the held-out ones it is judged on): 300 rows per clip of
/// the model's width, each clip's first row its data frame 0, f32-rounded;
/// 0 clips or more than the split holds are refused, naming the file. The
/// measured int8 figures are printed (`docs/omg.md`, "int8 and the
/// closed loop"). Needs the data set, as the test above.
#[test]
fn reach_calibration_rollouts_come_from_the_training_clips() {
    let Some(data) = omg_data("calibration rollouts") else {
        return;
    };
    let d = load_dir(&model_dir("tiny_fe_r1")).unwrap();
    let width = d.omg.config.model_width;
    let rec = host_sim::omg_reach::train_rollouts(&d, &data, "R1", 3).unwrap();
    let rows = &rec.samples.inputs;
    assert_eq!(rows.len(), 3 * 300);
    assert_eq!(rec.samples.phases, vec![0.0; rows.len()]);
    assert!(rows.iter().all(|r| r.len() == width
        && r.iter()
            .all(|v| v.is_finite() && *v == f64::from(*v as f32))));
    let (shape, train) = host_sim::npy::read_array_f32(&data.join("R1/train.npy")).unwrap();
    let w = shape[2];
    for c in 0..3 {
        let frame0: Vec<f64> = train[c * shape[1] * w..][..width]
            .iter()
            .map(|&v| f64::from(v))
            .collect();
        assert_eq!(rows[c * 300], frame0, "clip {c}");
    }
    for n in [0, shape[0] + 1] {
        let e = host_sim::omg_reach::train_rollouts(&d, &data, "R1", n)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("at least 1") || e.contains("train.npy"),
            "{n}: {e}"
        );
    }
    // The same rows through a file (`host-sim rollout-dataset --omg DIR
    // --clips 3`, what `exporter omg --calibration` reads): the same
    // rows, and the same int8 blob as the in-memory ones give.
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("omg-rollouts.npz");
    host_sim::rollout::dataset::omg_dataset(&model_dir("tiny_fe_r1"), &data, 3, &file).unwrap();
    let read = exporter::quantise::Recorded::read(&file, width).unwrap();
    assert_eq!(&read.samples.inputs, rows);
    let int8 = QuantOptions {
        weights: WeightFormat::I8,
        headroom: HEADROOM,
        ..QuantOptions::default()
    };
    let compensated = host_sim::quant_knobs::Int8Knobs {
        rounding: Some(exporter::cli_args::RoundingArg::Compensated),
        ..Default::default()
    };
    let from_file = host_sim::quant_knobs::Int8Knobs {
        calibration: Some(file.clone()),
        ..compensated.clone()
    }
    .export(&d.omg.net, None, int8.clone())
    .unwrap()
    .0;
    let in_memory = compensated
        .export_with(&d.omg.net, None, int8, Some(rec))
        .unwrap()
        .0;
    assert!(from_file == in_memory, "the file's blob differs");
    let knobs = host_sim::quant_knobs::Int8Knobs {
        calibration_clips: Some(48),
        ..compensated
    };
    let opts = QuantOptions {
        headroom: HEADROOM,
        ..QuantOptions::default()
    };
    let r =
        host_sim::omg_reach::measure(&model_dir("tiny_fe_r1"), &data, &opts, &knobs, None, None)
            .unwrap();
    eprint!("{}", r.table());
    let int8 = r.rows.iter().find(|x| x.run == "int8").unwrap();
    assert_eq!(int8.vs_f64.as_ref().unwrap().frames, r.clips * 300);
}
