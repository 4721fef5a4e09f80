//! The OMG reaching loop (`Reach<f32>` over the runtime, the committed
//! tiny_fe_r1 at int8) fed arbitrary targets, whole target blocks and
//! steps: NaN, infinities, huge values, unknown key joints
//! (`phasegate_tests::fuzz::exercise_reach`).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    phasegate_tests::fuzz::exercise_reach(data);
});
