//! One file given to every weight-file parser of the exporter and
//! host-sim: `.npz` (generic and PFNN layout), `.safetensors`, `.npy`.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    phasegate_tests::fuzz::exercise_weights(data);
});
