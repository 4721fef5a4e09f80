//! The custom mutator of the blob targets (`model`, `styled`): libFuzzer
//! mutates one region of one blob of the chain, then
//! [`phasegate_tests::fuzz::mutate_chain`] reseals the blobs (and re-binds
//! styles to their base) so that mutations reach the structural checks and
//! the kernels. Included by each target with `#[path]` (targets are
//! separate binaries).

use libfuzzer_sys::{fuzz_mutator, fuzzer_mutate};
use phasegate_tests::fuzz;

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
