//! JSON text given to the exporter's graph-description reader (with the
//! softmax-graph golden's weights) and to host-sim's command-script reader.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    phasegate_tests::fuzz::exercise_configs(data);
});
