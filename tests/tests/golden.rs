//! Golden io bundles, one per op kind and weight width (the embedded
//! default model among them): the runtime must give exactly the checked-in
//! outputs, and the checked-in files must be exactly what the documented
//! command regenerates.

use std::path::{Path, PathBuf};

fn golden_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("golden")
}

fn golden_dir() -> PathBuf {
    golden_root().join("default")
}

#[test]
fn runtime_matches_every_golden_bundle_bit_for_bit() {
    for case in host_sim::golden::CASES {
        let frames = host_sim::golden::check(&golden_root().join(case)).unwrap();
        assert_eq!(frames, host_sim::golden::FRAMES, "{case}");
    }
    let all = host_sim::golden::check(&golden_root()).unwrap();
    assert_eq!(
        all,
        host_sim::golden::FRAMES * host_sim::golden::CASES.len()
    );
}

#[test]
fn the_bundles_cover_every_op_kind() {
    let mut ops = std::collections::BTreeSet::new();
    for case in host_sim::golden::CASES {
        let blob = std::fs::read(golden_root().join(case).join("model.blob")).unwrap();
        let model = phasegate::Model::from_bytes(&blob).unwrap();
        for n in model.header().nodes.iter() {
            let Some(l) = n.layer() else {
                ops.insert("Softmax".to_string());
                continue;
            };
            ops.insert(
                format!("{:?}", l.op)
                    .split([' ', '{'])
                    .next()
                    .unwrap()
                    .to_string(),
            );
            ops.insert(format!("{:?}", l.weights));
        }
    }
    let want: std::collections::BTreeSet<String> = [
        "Dense",
        "Cp",
        "Diagonal",
        "Rbf",
        "Dec",
        "Softmax",
        "I8",
        "I8Interleaved",
        "I16",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    assert_eq!(ops, want);
}

#[test]
fn golden_files_regenerate_byte_for_byte() {
    let tmp = tempfile::tempdir().unwrap();
    for case in host_sim::golden::CASES {
        host_sim::golden::write_case(case, &tmp.path().join(case)).unwrap();
        for name in host_sim::golden::files(case) {
            let fresh = std::fs::read(tmp.path().join(case).join(name)).unwrap();
            let checked_in = std::fs::read(golden_root().join(case).join(name)).unwrap();
            assert!(
                fresh == checked_in,
                "{case}/{name} differs from a fresh `host-sim golden --write tests/golden`: \
                 regenerate the golden files and review the change"
            );
        }
    }
}

#[test]
fn embedded_float_source_is_the_generator_output() {
    let generated = host_sim::default_model::generate();
    let embedded = host_sim::default_model::float_model().unwrap();
    assert_eq!(generated, embedded);
}

#[test]
fn a_changed_output_is_caught() {
    let tmp = tempfile::tempdir().unwrap();
    for e in std::fs::read_dir(golden_dir()).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), tmp.path().join(e.file_name())).unwrap();
    }
    let q = tmp.path().join("expected_q.npy");
    let mut bytes = std::fs::read(&q).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    std::fs::write(&q, bytes).unwrap();
    let err = host_sim::golden::check(tmp.path()).unwrap_err().to_string();
    assert!(err.contains("golden mismatch"), "{err}");
}

#[test]
fn clipped_inputs_are_counted() {
    let model = phasegate::Model::from_bytes(host_sim::default_model::BLOB).unwrap();
    let mut rt = host_sim::eval::host_runtime(model).unwrap();
    let x = host_sim::npy::read_matrix_f32(&golden_dir().join("inputs.npy"), 342).unwrap();
    let phase = phasegate::Phase::from_bits(0);
    let mut y = vec![0.0f32; 311];
    rt.run(phase, x.row(0), &mut y).unwrap();
    assert_eq!(
        rt.clipped_inputs(),
        0,
        "golden inputs lie inside the declared range"
    );
    let mut far = x.row(0).to_vec();
    far[3] = 1e9;
    far[7] = -1e9;
    rt.run(phase, &far, &mut y).unwrap();
    assert_eq!(rt.clipped_inputs(), 2);
    assert!(y.iter().all(|v| v.is_finite()));
}
