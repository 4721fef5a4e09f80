//! A model blob (any kind: dense, CP, diagonal, softmax-gated graph, or a
//! style blob, which must be refused as a model) loaded exactly and as a
//! region, then every extreme input at every edge phase. The custom
//! mutator keeps both CRCs and the payload length valid after mutating the
//! header or the payload, so mutations reach the structural checks and the
//! kernels; one mutation in eight is left unsealed.
#![no_main]

use libfuzzer_sys::fuzz_target;
use phasegate_tests::fuzz;

fuzz_target!(|data: &[u8]| {
    fuzz::exercise_model(data);
});

#[path = "../src/sealing_mutator.rs"]
mod sealing_mutator;
