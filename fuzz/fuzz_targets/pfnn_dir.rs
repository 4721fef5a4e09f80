//! A PFNN demo directory (`Xmean.bin` ..., `W0_000.bin` ..., packed as a
//! count byte, u16 lengths, contents) read by the exporter with inferred
//! and with fixed dimensions.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    phasegate_tests::fuzz::exercise_pfnn_dir(data);
});
