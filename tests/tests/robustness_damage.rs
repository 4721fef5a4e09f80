//! Random damage (single bit flips, multi-byte corruption) of dense, CP and
//! style blobs: refused with the error of the region hit.

mod hostile;

use hostile::*;

#[test]
fn single_bit_flips_are_refused_with_the_error_of_their_region() {
    let blobs = [
        quantised(WeightFormat::I8),
        quantised(WeightFormat::I16),
        hand_blob(),
    ];
    let mut total = 0;
    for (i, blob) in blobs.iter().enumerate() {
        total += flip_all(blob, 100 + i as u64, 10_000);
    }
    assert!(total >= 30_000, "{total}");
}

#[test]
fn multi_byte_corruptions_are_refused() {
    for (seed, blob) in [quantised(WeightFormat::I8), hand_blob()]
        .iter()
        .enumerate()
    {
        let mut rng = ChaCha8Rng::seed_from_u64(seed as u64);
        let start = payload_start(blob);
        for case in 0..400 {
            let mut d = blob.clone();
            // Where: the header region, the payload, or anywhere.
            let (lo, hi) = match case % 4 {
                0 => (0, start),
                1 | 2 => (start, blob.len()),
                _ => (0, blob.len()),
            };
            let mut touched = Vec::new();
            if case % 2 == 0 {
                // A burst: a run of 2..=16 random bytes.
                let len = rng.gen_range(2..=16).min(hi - lo);
                let at = rng.gen_range(lo..=hi - len);
                for (p, byte) in d.iter_mut().enumerate().skip(at).take(len) {
                    *byte = rng.gen();
                    touched.push(p);
                }
            } else {
                // Scattered: 2..=8 random bytes, each xor-ed with a non-zero value.
                for _ in 0..rng.gen_range(2..=8) {
                    let p = rng.gen_range(lo..hi);
                    d[p] ^= rng.gen_range(1..=255u8);
                    touched.push(p);
                }
            }
            if d == *blob {
                continue;
            }
            let e = Model::from_bytes(&d).expect_err("damaged blob loaded");
            let _ = Model::from_region(&d).expect_err("damaged blob loaded");
            if touched.iter().all(|&p| p >= start) {
                assert_eq!(e, Error::PayloadCorrupt, "case {case}");
            } else if touched.iter().all(|&p| p < start) {
                assert!(is_header_class(&e), "case {case}: {e:?}");
            }
        }
    }
}

#[test]
fn single_bit_flips_in_cp_models_and_styles_are_refused() {
    let b = cp_and_styles();
    let mut total = flip_all_with(&b.cp, 200, 4_000, load_model);
    for (i, s) in b.styles.iter().enumerate() {
        total += flip_all_with(s, 210 + i as u64, 2_000, load_style);
    }
    assert!(total >= 10_000, "{total}");
}
