//! A model blob (any kind: dense, CP, diagonal, softmax-gated graph, or a
//! style blob, which must be refused as a model) loaded exactly and as a
//! region, then every extreme input at every edge phase. The custom
//! mutator keeps both CRCs and the payload length valid after mutating the
//! header or the payload, so mutations reach the structural checks and the
//! kernels; one mutation in eight is left unsealed.
#![no_main]

use libfuzzer_sys::{fuzz_mutator, fuzz_target, fuzzer_mutate};
use phasegate_tests::fuzz;

fuzz_target!(|data: &[u8]| {
    fuzz::exercise_model(data);
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
