//! Op-count honesty (issue 12, item 7): with the runtime's `mac-count`
//! feature (on for this crate's tests) the kernels count the
//! multiply-accumulates they actually perform, and every model kind's
//! frame must do exactly the header's `macs_per_frame`, the figure
//! `host-sim target` divides instructions by and the exporter's report
//! prints. One test in its own binary: the count is process-wide.

use std::path::{Path, PathBuf};

use phasegate::{mac_count, Model, Phase, Runtime};

fn blobs() -> Vec<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut v: Vec<PathBuf> = host_sim::golden::CASES
        .iter()
        .map(|c| root.join("golden").join(c).join("model.blob"))
        .collect();
    // A blob of the plain int8 layout (before `I8Interleaved`).
    v.push(root.join("fixtures").join("example-v2.blob"));
    v
}

#[test]
fn every_model_kind_performs_exactly_the_header_macs() {
    const { assert!(mac_count::COUNTING, "the mac-count feature is off") };
    let mut kinds = std::collections::BTreeSet::new();
    for path in blobs() {
        let bytes = std::fs::read(&path).unwrap();
        let model = Model::from_bytes(&bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let want = u64::from(model.macs_per_frame());
        for n in model.header().nodes.iter() {
            kinds.insert(match n.layer() {
                Some(l) => format!("{:?}", l.op)
                    .split([' ', '{'])
                    .next()
                    .unwrap()
                    .to_string(),
                None => "Softmax".to_string(),
            });
        }
        let mut rt = Box::new(Runtime::<'_, 16384>::new(model).unwrap());
        let x: Vec<i16> = (0..rt.model().input_dim())
            .map(|i| ((i as i32 * 7919) % 16001 - 8000) as i16)
            .collect();
        // Phase 0 puts the cubic gate on a control point (one weight 1,
        // the others 0): the header still counts four experts, and so
        // must the kernels.
        for phase in [0.0f32, 0.4, 1.3, 2.9, 5.5] {
            mac_count::take();
            rt.run_quantised(Phase::from_radians(phase).unwrap(), &x)
                .unwrap();
            let done = mac_count::take();
            assert_eq!(
                done,
                want,
                "{} at phase {phase}: the kernels did {done} MACs, the header says {want}",
                path.display()
            );
        }
    }
    for k in ["Dense", "Cp", "Diagonal", "Rbf", "Dec", "Softmax"] {
        assert!(kinds.contains(k), "no {k} node among the blobs: {kinds:?}");
    }
}
