//! A self-test section appended to a model blob (resealed): the loader's
//! section checks, then the self-test and the model it must leave alone.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    phasegate_tests::fuzz::exercise_self_test(data);
});
