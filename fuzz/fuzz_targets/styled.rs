//! A base model blob followed by style blobs (as they lie in flash): the
//! base loads as a region, every style that loads is added to a bank of
//! four, and every mix (none, each style, each ordered pair blended at
//! weights 0, 1/2, 1 and the largest, and ids that are not attached) runs
//! every extreme input. The custom mutator mutates one blob of the chain,
//! reseals every blob and re-binds the styles to the base (not always).
#![no_main]

use libfuzzer_sys::{fuzz_mutator, fuzz_target, fuzzer_mutate};
use phasegate_tests::fuzz;

fuzz_target!(|data: &[u8]| {
    fuzz::exercise_styled(data);
});

fuzz_mutator!(|data: &mut [u8], size: usize, max_size: usize, seed: u32| {
    phasegate_fuzz_mutate(data, size, max_size, seed)
});

fn phasegate_fuzz_mutate(data: &mut [u8], size: usize, max_size: usize, seed: u32) -> usize {
    let choice = u64::from(seed).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 8;
    let out = fuzz::mutate_chain(&data[..size], choice, &mut |region: &mut Vec<u8>| {
        let len = region.len();
        region.resize(len * 2 + 64, 0);
        let cap = region.len();
        let n = fuzzer_mutate(region, len, cap);
        region.truncate(n);
    });
    if out.len() > max_size {
        return fuzzer_mutate(data, size, max_size);
    }
    data[..out.len()].copy_from_slice(&out);
    out.len()
}
