//! A motion blob followed by a rig blob (each in its own flash region on a
//! device): the pair loads exactly and as regions, and what loads runs
//! every extreme input at the edge phases. The custom mutator mutates one
//! blob of the pair, reseals both and re-binds the rig to the motion blob
//! (not always).
#![no_main]

use libfuzzer_sys::fuzz_target;
use phasegate_tests::fuzz;

fuzz_target!(|data: &[u8]| {
    fuzz::exercise_rig(data);
});

#[path = "../src/sealing_mutator.rs"]
mod sealing_mutator;
