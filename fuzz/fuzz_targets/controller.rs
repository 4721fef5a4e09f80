//! The locomotion loop on the embedded default model, plain and with two
//! styles switched per frame, fed arbitrary commands: NaN, infinities,
//! huge and tiny values (`phasegate_tests::fuzz::commands`).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    phasegate_tests::fuzz::exercise_controller(data);
});
