//! Property tests: random bytes, mutations, lying headers and payload values
//! of dense, CP and style blobs never make the loader or a frame panic.

mod hostile;

use hostile::*;

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
        loads_and_runs(&bytes);
        // The same bytes behind a valid preamble start (magic and version).
        let mut b = b"PGMB\x01\x00".to_vec();
        b.extend(&bytes);
        loads_and_runs(&b);
    }

    #[test]
    fn random_mutations_of_a_valid_blob_never_panic(
        edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..8),
        cut in proptest::option::of(any::<usize>()),
        extra in proptest::collection::vec(any::<u8>(), 0..4),
    ) {
        let blob = hand_blob();
        let mut b = blob.clone();
        for &(at, v) in &edits {
            let i = at % b.len();
            b[i] = v;
        }
        if let Some(c) = cut {
            b.truncate(c % (b.len() + 1));
        }
        b.extend(&extra);
        let changed = b != blob;
        loads_and_runs(&b);
        if changed {
            prop_assert!(Model::from_bytes(&b).is_err());
        }
    }

    /// Headers that lie with valid CRCs, and payloads edited and resealed:
    /// refused or loaded, never a panic; what loads runs on extreme inputs.
    #[test]
    fn lying_headers_with_valid_crcs_never_panic(
        edits in proptest::collection::vec(arb_edit(), 1..5),
        refigure in any::<bool>(),
    ) {
        let mut p = Parts::of(&hand_blob());
        for e in &edits {
            apply(&mut p, e);
        }
        p.reseal();
        if refigure {
            p.refigure();
        }
        loads_and_runs(&p.blob());
    }

    /// Random weights, biases and requantisation records in a valid layout.
    #[test]
    fn random_payload_values_never_panic(seed in any::<u64>(), density in 1usize..64) {
        let mut p = Parts::of(&hand_blob());
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        for _ in 0..density {
            let at = rng.gen_range(0..p.payload.len());
            p.payload[at] = rng.gen();
        }
        // Keep the requantisation records loadable half of the time.
        if seed % 2 == 0 {
            for l in 0..3 {
                for r in 0..usize::from(layer_of(&p.header, l).out_dim) {
                    let rec = p.requant_at(l, r);
                    rec[4] %= 63;
                    rec[5] %= 63;
                    rec[6] %= 16;
                    rec[7] = 0;
                }
            }
        }
        p.reseal();
        loads_and_runs(&p.blob());
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Random edits of a CP model's or a style's header bytes, framed with a
    /// valid header CRC (so the header decoder and every check behind it
    /// see them): refused with an error, or loaded and then run with
    /// extreme inputs at any phase and every mix, never a panic.
    #[test]
    fn lying_cp_and_style_headers_never_panic(
        which in 0usize..4,
        edits in proptest::collection::vec((any::<u16>(), any::<u8>()), 1..6),
    ) {
        let b = cp_and_styles_cached();
        let blob = if which == 0 { &b.cp } else { &b.styles[which - 1] };
        let (mut header, payload) = raw_parts(blob);
        for (at, v) in edits {
            let i = usize::from(at) % header.len();
            header[i] = v;
        }
        let damaged = frame_raw(&header, &payload);
        let few = [0, 0x4000_0000, u32::MAX];
        if which == 0 {
            for m in [Model::from_bytes(&damaged), Model::from_region(&damaged)].into_iter().flatten() {
                hammer::<64>(m, &few);
            }
        } else if let Ok(style) = Style::from_bytes(&damaged) {
            hammer_styled(Model::from_bytes(&b.base).unwrap(), &[style], &few);
        }
        let _ = Style::from_region(&damaged);
        let _ = blob_len_from_prefix(&damaged);
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Random factors, cores, middle and requantisation records, biases
    /// (a CP model's or a style's payload bytes edited, the payload CRC
    /// resealed): the loader's overflow proof refuses what could wrap or
    /// saturate; what loads runs on extreme inputs, never a panic.
    #[test]
    fn random_cp_and_style_payload_values_never_panic(
        which in 0usize..4,
        seed in any::<u64>(),
        density in 1usize..32,
    ) {
        let b = cp_and_styles_cached();
        let blob = if which == 0 { &b.cp } else { &b.styles[which - 1] };
        let mut header = phasegate::blob::Framed::parse(blob, true).unwrap().header.decoded();
        let mut payload = raw_parts(blob).1;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        for _ in 0..density {
            let at = rng.gen_range(0..payload.len());
            payload[at] = rng.gen();
        }
        header.payload_crc = crc32(&payload);
        let damaged = frame(&header, &payload);
        let few = [0, 0x4000_0000, u32::MAX];
        if which == 0 {
            if let Ok(m) = Model::from_bytes(&damaged) {
                hammer::<64>(m, &few);
            }
        } else if let Ok(style) = Style::from_bytes(&damaged) {
            hammer_styled(Model::from_bytes(&b.base).unwrap(), &[style], &few);
        }
    }
}
