//! An OMG model directory (`config.json`, `model.safetensors`) given to
//! the exporter's OMG importer; what builds runs, and is exported.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    phasegate_tests::fuzz::exercise_omg_model(data);
});
