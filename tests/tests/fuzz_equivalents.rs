//! Stable-Rust equivalents of the fuzz targets in `fuzz/` (which need
//! nightly and run by hand, see `fuzz/README.md`): each runs the very code
//! its target runs (`phasegate_tests::fuzz::exercise_*`) on the target's
//! seeds mutated by proptest, with a fixed seed and a fixed number of
//! cases, so that `cargo test --workspace --release` spends a few seconds on
//! each and always the same inputs. The blob targets use the same
//! structure-aware mutation as the fuzzers (`mutate_chain`: mutate the
//! header or the payload of one blob of the chain, then recompute both CRCs
//! and the payload length and re-bind styles to their base), with random
//! byte edits in place of libFuzzer's mutator.
//!
//! The findings of the fuzz runs are regression tests next to the code
//! they concern (listed in `fuzz/README.md`), not here.

use phasegate_tests::fuzz::{self, seeds};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestRng, TestRunner};
use std::sync::OnceLock;

type Seeds = Vec<(&'static str, String, Vec<u8>)>;

fn all_seeds() -> &'static Seeds {
    static S: OnceLock<Seeds> = OnceLock::new();
    S.get_or_init(|| seeds(false))
}

fn seeds_of(target: &str) -> Vec<Vec<u8>> {
    let v: Vec<Vec<u8>> = all_seeds()
        .iter()
        .filter(|(t, _, _)| *t == target)
        .map(|(_, _, b)| b.clone())
        .collect();
    assert!(!v.is_empty(), "no seeds for {target}");
    v
}

/// One byte edit: overwrite, xor, insert or delete at a position taken
/// modulo the length, or an "interesting" value written little-endian.
#[derive(Clone, Debug)]
enum Edit {
    Set(u32, u8),
    Xor(u32, u8),
    Insert(u32, u8),
    Delete(u32),
    Interesting(u32, u8),
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        (any::<u32>(), any::<u8>()).prop_map(|(p, b)| Edit::Set(p, b)),
        (any::<u32>(), 1..=255u8).prop_map(|(p, b)| Edit::Xor(p, b)),
        (any::<u32>(), any::<u8>()).prop_map(|(p, b)| Edit::Insert(p, b)),
        any::<u32>().prop_map(Edit::Delete),
        (any::<u32>(), any::<u8>()).prop_map(|(p, b)| Edit::Interesting(p, b)),
    ]
}

fn apply(bytes: &mut Vec<u8>, edits: &[Edit]) {
    const INTERESTING: [u32; 10] = [
        0,
        1,
        0x7f,
        0x80,
        0xff,
        0x7fff,
        0x8000,
        0xffff,
        0x7fff_ffff,
        0xffff_ffff,
    ];
    for e in edits {
        let at = |p: u32, len: usize| (p as usize) % len.max(1);
        match *e {
            Edit::Set(p, b) if !bytes.is_empty() => {
                let i = at(p, bytes.len());
                bytes[i] = b;
            }
            Edit::Xor(p, b) if !bytes.is_empty() => {
                let i = at(p, bytes.len());
                bytes[i] ^= b;
            }
            Edit::Insert(p, b) => {
                let i = at(p, bytes.len() + 1);
                bytes.insert(i, b);
            }
            Edit::Delete(p) if !bytes.is_empty() => {
                let i = at(p, bytes.len());
                bytes.remove(i);
            }
            Edit::Interesting(p, b) if !bytes.is_empty() => {
                let v = INTERESTING[usize::from(b) % INTERESTING.len()].to_le_bytes();
                let i = at(p, bytes.len());
                for (k, x) in v.iter().take(1 + usize::from(b >> 6)).enumerate() {
                    if let Some(slot) = bytes.get_mut(i + k) {
                        *slot = *x;
                    }
                }
            }
            _ => {}
        }
    }
}

/// A runner with a fixed seed: the same cases on every run.
fn runner(cases: u32, seed: u8) -> TestRunner {
    let config = Config {
        cases,
        failure_persistence: None,
        ..Config::default()
    };
    TestRunner::new_with_rng(
        config,
        TestRng::from_seed(RngAlgorithm::ChaCha, &[seed; 32]),
    )
}

/// The structure-aware cases of a blob target: a seed, one or two rounds
/// of mutation (each: edits within one region of one blob, then resealed).
fn blob_cases(target: &str, cases: u32, seed: u8, exercise: fn(&[u8]) -> usize) {
    let corpus = seeds_of(target);
    let n = corpus.len();
    let strategy = (
        0..n,
        proptest::collection::vec(
            (any::<u64>(), proptest::collection::vec(edit(), 1..6)),
            1..3,
        ),
    );
    let frames = std::cell::Cell::new(0usize);
    runner(cases, seed)
        .run(&strategy, |(i, rounds)| {
            let mut data = corpus[i].clone();
            for (choice, edits) in &rounds {
                data = fuzz::mutate_chain(&data, *choice, &mut |r: &mut Vec<u8>| apply(r, edits));
            }
            frames.set(frames.get() + exercise(&data));
            Ok(())
        })
        .unwrap();
    // Some mutants get as far as running frames.
    assert!(frames.get() > 0, "{target}: no mutant ran a frame");
}

/// Raw byte edits of a target's seeds (no framing to keep).
fn byte_cases(target: &str, cases: u32, seed: u8, exercise: fn(&[u8]) -> usize) {
    let corpus = seeds_of(target);
    let n = corpus.len();
    let strategy = (0..n, proptest::collection::vec(edit(), 0..8));
    runner(cases, seed)
        .run(&strategy, |(i, edits)| {
            let mut data = corpus[i].clone();
            apply(&mut data, &edits);
            exercise(&data);
            Ok(())
        })
        .unwrap();
}

#[test]
fn model_target_equivalent() {
    blob_cases("model", 2000, 1, fuzz::exercise_model);
}

#[test]
fn styled_target_equivalent() {
    blob_cases("styled", 400, 2, fuzz::exercise_styled);
}

#[test]
fn rig_target_equivalent() {
    blob_cases("rig", 300, 9, fuzz::exercise_rig);
}

#[test]
fn controller_target_equivalent() {
    // Arbitrary command bytes, and the seeds edited.
    let strategy = proptest::collection::vec(any::<u8>(), 0..400);
    runner(150, 3)
        .run(&strategy, |bytes| {
            fuzz::exercise_controller(&bytes);
            Ok(())
        })
        .unwrap();
    byte_cases("controller", 100, 4, fuzz::exercise_controller);
}

#[test]
fn reach_target_equivalent() {
    let strategy = proptest::collection::vec(any::<u8>(), 0..600);
    runner(120, 8)
        .run(&strategy, |bytes| {
            fuzz::exercise_reach(&bytes);
            Ok(())
        })
        .unwrap();
    byte_cases("reach", 80, 9, fuzz::exercise_reach);
}

#[test]
fn weights_target_equivalent() {
    byte_cases("weights", 2000, 5, fuzz::exercise_weights);
}

#[test]
fn configs_target_equivalent() {
    byte_cases("configs", 2000, 6, fuzz::exercise_configs);
}

#[test]
fn omg_model_target_equivalent() {
    byte_cases("omg_model", 300, 8, fuzz::exercise_omg_model);
}

#[test]
fn self_test_target_equivalent() {
    byte_cases("self_test", 2000, 9, fuzz::exercise_self_test);
}

#[test]
fn pfnn_dir_target_equivalent() {
    byte_cases("pfnn_dir", 1000, 7, fuzz::exercise_pfnn_dir);
}

/// The seeds themselves: each is valid for its target (a model loads and
/// runs, styles attach, the weight files and configs parse), except the
/// hostile weight files, which every parser refuses.
#[test]
fn seeds_are_valid_files() {
    for (target, name, bytes) in all_seeds() {
        let ok = match *target {
            "model" => {
                if name.starts_with("style-") {
                    phasegate::Style::from_bytes(bytes).is_ok()
                } else {
                    fuzz::exercise_model(bytes) > 0
                }
            }
            "styled" => fuzz::exercise_styled(bytes) > 0,
            "rig" => fuzz::exercise_rig(bytes) > 0,
            "controller" => fuzz::exercise_controller(bytes) > 0,
            "reach" => fuzz::exercise_reach(bytes) > 0,
            "weights" => (fuzz::exercise_weights(bytes) > 0) != name.starts_with("hostile-"),
            "configs" => fuzz::exercise_configs(bytes) > 0,
            "pfnn_dir" => fuzz::exercise_pfnn_dir(bytes) == 2,
            "omg_model" => {
                fuzz::exercise_omg_model(bytes) == if name.contains("export") { 3 } else { 1 }
            }
            "self_test" => fuzz::exercise_self_test(bytes) == 1,
            other => panic!("unknown target {other}"),
        };
        assert!(ok, "{target}/{name} is not a valid seed");
    }
}

/// Resealing a valid blob changes nothing; resealing a mutated one makes
/// both CRCs right again.
#[test]
fn reseal_is_the_identity_on_valid_blobs_and_fixes_crcs() {
    for (target, name, bytes) in all_seeds() {
        if *target != "model" {
            continue;
        }
        assert_eq!(&fuzz::reseal(bytes, None), bytes, "{name}");
        let mut d = bytes.clone();
        let last = d.len() - 1;
        d[last] ^= 0x55;
        let fixed = fuzz::reseal(&d, None);
        let r = if name.starts_with("style-") {
            phasegate::Style::from_bytes(&fixed).map(|_| ())
        } else {
            phasegate::Model::from_bytes(&fixed).map(|_| ())
        };
        assert!(
            !matches!(
                r,
                Err(phasegate::Error::PayloadCorrupt | phasegate::Error::HeaderCorrupt)
            ),
            "{name}: {r:?}"
        );
    }
}
