//! A base model blob followed by style blobs (as they lie in flash): the
//! base loads as a region, every style that loads is added to a bank of
//! four, and every mix (none, each style, each ordered pair blended at
//! weights 0, 1/2, 1 and the largest, and ids that are not attached) runs
//! every extreme input. The custom mutator mutates one blob of the chain,
//! reseals every blob and re-binds the styles to the base (not always).
#![no_main]

use libfuzzer_sys::fuzz_target;
use phasegate_tests::fuzz;

fuzz_target!(|data: &[u8]| {
    fuzz::exercise_styled(data);
});

#[path = "../src/sealing_mutator.rs"]
mod sealing_mutator;
