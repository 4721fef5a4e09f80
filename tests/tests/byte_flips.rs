//! Every byte of a small blob of every model kind (dense, CP + diagonal,
//! softmax-gated graph, the three style forms, a rig blob) and of the kept fixtures of
//! other format versions flipped, one at a time: each damaged blob is
//! refused, exactly and as a region, with the error of the framing region
//! the byte lies in (`docs/blob-format.md`, "What the loader checks",
//! checks 1 to 12):
//!
//! | bytes | error |
//! |---|---|
//! | magic `0..4` | `BadMagic` |
//! | version `4..6` | `UnsupportedVersion { found, supported: 2 }` |
//! | header length `6..8` | `Truncated { needed: 12 + H }` when the blob is shorter, else `HeaderCorrupt` |
//! | header CRC `8..12`, header `12..12+H` | `HeaderCorrupt` |
//! | padding | `HeaderMalformed` |
//! | payload | `PayloadCorrupt` |
//!
//! A blob of another version is refused with `UnsupportedVersion` naming
//! that version whatever byte after the version is flipped (its header is
//! never read). Each byte is flipped twice: all eight bits (`^ 0xff`) and a
//! seeded single bit.

mod hostile;

use hostile::*;
use phasegate::blob::FORMAT_VERSION;
use phasegate_tests::fuzz::{fixture, golden, seeds};

/// The blobs flipped: `(name, bytes, is a style)`.
fn blobs() -> Vec<(String, Vec<u8>, bool)> {
    let mut v: Vec<(String, Vec<u8>, bool)> = seeds(false)
        .into_iter()
        .filter(|(t, _, _)| *t == "model")
        .map(|(_, name, b)| {
            let style = name.starts_with("style-");
            (name, b, style)
        })
        .collect();
    // The small seeds cover dense, CP + diagonal and the style forms; the
    // softmax graph is the golden one (19 KB, the smallest graph kept).
    assert!(v.iter().any(|(n, _, _)| n == "softmax-graph.blob"));
    v.retain(|(n, _, _)| n != "cp-diagonal.blob");
    v
}

fn expected(blob: &[u8], damaged: &[u8], pos: usize) -> Error {
    single_flip_error(blob, damaged, pos)
}

fn check_all_bytes(name: &str, blob: &[u8], load: fn(&[u8], bool) -> Result<(), Error>) -> usize {
    let mut rng = ChaCha8Rng::seed_from_u64(blob.len() as u64);
    let mut n = 0;
    let mut classes = std::collections::BTreeMap::<String, usize>::new();
    for pos in 0..blob.len() {
        for mask in [0xffu8, 1 << rng.gen_range(0..8)] {
            let mut d = blob.to_vec();
            d[pos] ^= mask;
            let want = expected(blob, &d, pos);
            let class = format!("{want:?}");
            let class = class
                .split([' ', '{'])
                .next()
                .unwrap_or_default()
                .to_string();
            *classes.entry(class).or_default() += 1;
            for exact in [true, false] {
                let got = load(&d, exact).expect_err("a flipped byte loaded");
                assert_eq!(
                    got, want,
                    "{name}: byte {pos} ^ {mask:#04x} (exact {exact})"
                );
            }
            n += 1;
        }
    }
    // For the record (`--nocapture`): the flips per error class.
    println!("{name}: {} bytes, {n} flips, {classes:?}", blob.len());
    n
}

#[test]
fn every_byte_of_a_blob_of_every_kind_is_refused_with_the_error_of_its_region() {
    let mut kinds = Vec::new();
    let mut flips = 0;
    for (name, blob, style) in blobs() {
        let load = if style { load_style } else { load_model };
        load(&blob, true).unwrap_or_else(|e| panic!("{name} loads undamaged: {e}"));
        flips += check_all_bytes(&name, &blob, load);
        kinds.push(name);
    }
    for k in [
        "example-v2.blob",
        "dense-small.blob",
        "cp-diagonal-small.blob",
        "softmax-graph.blob",
        "style-cp.blob",
        "style-diagonal.blob",
        "style-full.blob",
    ] {
        assert!(kinds.iter().any(|n| n == k), "{k} missing from {kinds:?}");
    }
    assert!(flips > 40_000, "{flips}");
}

/// The small motion blob the rig of [`load_rig`] is for.
fn small_motion() -> &'static [u8] {
    static PAIR: std::sync::OnceLock<(Vec<u8>, Vec<u8>)> = std::sync::OnceLock::new();
    &PAIR.get_or_init(phasegate_tests::fuzz::small_rig_pair).0
}

/// Loads a rig blob beside the small motion blob, exactly or from regions.
fn load_rig(bytes: &[u8], exact: bool) -> Result<(), Error> {
    if exact {
        Model::with_rig(small_motion(), bytes).map(|_| ())
    } else {
        Model::with_rig_regions(small_motion(), bytes).map(|_| ())
    }
}

/// Rig blobs have the model blob's framing: every byte of a small one
/// flipped gives the error of its region, its motion blob intact.
#[test]
fn every_byte_of_a_rig_blob_is_refused_with_the_error_of_its_region() {
    let (_, rig) = phasegate_tests::fuzz::small_rig_pair();
    load_rig(&rig, true).unwrap();
    let flips = check_all_bytes("rig.blob", &rig, load_rig);
    assert_eq!(flips, 2 * rig.len());
}

/// The flipped blobs have every framing region: each a header and a
/// payload, and some padding between them (not every header length leaves
/// any).
#[test]
fn the_flipped_blobs_have_every_framing_region() {
    let mut padded = 0;
    for (name, blob, _) in blobs() {
        let h = usize::from(u16::from_le_bytes([blob[6], blob[7]]));
        let p = payload_start(&blob);
        assert!(h > 0 && blob.len() > p, "{name}: no header or payload");
        padded += usize::from(p > 12 + h);
    }
    assert!(padded >= 3, "{padded}");
}

/// The fixtures of format versions 0 and 1 (the version-1 document example
/// and a CP + diagonal golden blob the version-1 exporter wrote): whatever byte after the version
/// is flipped, the refusal names the version found and the one supported;
/// flipping a version byte names the new version; a magic byte, BadMagic.
#[test]
fn every_byte_of_an_old_version_blob_gives_the_version_error() {
    for (file, version) in [
        ("example-v1.blob", 1u16),
        ("cp-diagonal-v1.blob", 1),
        ("version0.blob", 0),
    ] {
        let blob = fixture(file);
        if file == "cp-diagonal-v1.blob" {
            // A record, never regenerated: the bytes the version-1 exporter wrote.
            assert_eq!((blob.len(), crc32(&blob)), (5088, 0xdfa2_5349));
        }
        for pos in 0..blob.len() {
            for mask in [0xffu8, 0x01, 0x80] {
                let mut d = blob.clone();
                d[pos] ^= mask;
                let found = u16::from_le_bytes([d[4], d[5]]);
                let want = match pos {
                    0..4 => Error::BadMagic,
                    _ => Error::UnsupportedVersion {
                        found,
                        supported: FORMAT_VERSION,
                    },
                };
                if found == FORMAT_VERSION {
                    // Flipping version 0 or 1 into 2: the header CRC still
                    // guards the version bytes.
                    assert_eq!(Model::from_bytes(&d).unwrap_err(), Error::HeaderCorrupt);
                    continue;
                }
                assert_eq!(
                    Model::from_bytes(&d).unwrap_err(),
                    want,
                    "{file} byte {pos}"
                );
                assert_eq!(
                    Model::from_region(&d).unwrap_err(),
                    want,
                    "{file} byte {pos}"
                );
                assert_eq!(
                    Style::from_bytes(&d).unwrap_err(),
                    want,
                    "{file} byte {pos}"
                );
                if pos >= 6 {
                    assert_eq!(
                        want,
                        Error::UnsupportedVersion {
                            found: version,
                            supported: 2
                        }
                    );
                }
            }
        }
        // The message names both versions.
        let msg = Model::from_bytes(&blob).unwrap_err().to_string();
        assert!(
            msg.contains(&format!("version {version} is not supported"))
                && msg.contains(&format!("reads version {FORMAT_VERSION}")),
            "{msg}"
        );
    }
    // And the golden blobs, written by the current version, all load.
    for g in ["default", "dense-int16", "cp-diagonal", "softmax-graph"] {
        Model::from_bytes(&golden(&format!("{g}/model.blob"))).unwrap();
    }
}
