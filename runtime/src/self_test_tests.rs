//! The self-test section through the loader and `Runtime::run_self_test`:
//! a passing section, a mismatch (an expected output changed and the
//! payload CRC re-sealed), malformed sections, and blobs without one.

use crate::blob::{
    crc32, Framed, Header, FORMAT_VERSION, MAGIC, PAYLOAD_ALIGN, SELF_TEST_MAGIC, SELF_TEST_VERSION,
};
use crate::{Error, Model, Phase, Runtime};

const EXAMPLE: &[u8] = include_bytes!("../../tests/fixtures/example-v2.blob");
const DEFAULT: &[u8] = include_bytes!("../../tests/golden/default/model.blob");
const SOFTMAX: &[u8] = include_bytes!("../../tests/golden/softmax-graph/model.blob");

/// `blob` with its payload replaced by `payload`: header re-encoded with
/// the new length and CRC, both CRCs re-sealed.
fn reseal(blob: &[u8], payload: &[u8]) -> Vec<u8> {
    let f = Framed::parse(blob, true).unwrap();
    let h = f.header;
    let header = Header {
        kind: h.kind,
        gating: h.gating,
        input_dim: h.input_dim,
        output_dim: h.output_dim,
        nodes: h.nodes.to_vec(),
        input: h.input,
        output: h.output,
        input_stage: h.input_stage,
        output_stage: h.output_stage,
        ram_bytes: h.ram_bytes,
        macs_per_frame: h.macs_per_frame,
        payload_len: payload.len() as u32,
        payload_crc: crc32(payload),
    };
    let hb = postcard::to_allocvec(&header).unwrap();
    let mut out = MAGIC.to_vec();
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&(hb.len() as u16).to_le_bytes());
    let mut crc_in = out.clone();
    crc_in.extend_from_slice(&hb);
    out.extend_from_slice(&crc32(&crc_in).to_le_bytes());
    out.extend_from_slice(&hb);
    out.resize(out.len().next_multiple_of(PAYLOAD_ALIGN), 0);
    out.extend_from_slice(payload);
    out
}

/// The payload of `blob` with a self-test section of `n` vectors appended
/// (deterministic inputs, the runtime's own outputs), and where the
/// records start.
fn with_section(blob: &[u8], n: u16) -> (Vec<u8>, usize) {
    let model = Model::from_bytes(blob).unwrap();
    let (ins, outs) = (model.input_dim(), model.output_dim());
    let mut payload = model.payload().to_vec();
    payload.resize(payload.len().next_multiple_of(4), 0);
    let start = payload.len();
    let mut rt: Box<Runtime<'_, 4096>> = Box::new(Runtime::new(model).unwrap());
    let mut seed = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = move || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 32) as u32
    };
    for _ in 0..n {
        let phase = next();
        let x: Vec<i16> = (0..ins).map(|_| (next() as i16) >> 3).collect();
        let y = rt
            .run_quantised(Phase::from_bits(phase), &x)
            .unwrap()
            .to_vec();
        assert_eq!(y.len(), outs);
        payload.extend_from_slice(&phase.to_le_bytes());
        for v in x.iter().chain(&y) {
            payload.extend_from_slice(&v.to_le_bytes());
        }
    }
    payload.resize(payload.len().next_multiple_of(4), 0);
    payload.extend_from_slice(&(start as u32).to_le_bytes());
    payload.extend_from_slice(&n.to_le_bytes());
    payload.extend_from_slice(&(ins as u16).to_le_bytes());
    payload.extend_from_slice(&(outs as u16).to_le_bytes());
    payload.extend_from_slice(&SELF_TEST_VERSION.to_le_bytes());
    payload.extend_from_slice(&SELF_TEST_MAGIC);
    (payload, start)
}

fn run(blob: &[u8]) -> crate::Result<u16> {
    let model = Model::from_bytes(blob)?;
    let mut rt: Box<Runtime<'_, 4096>> = Box::new(Runtime::new(model)?);
    rt.run_self_test()
}

#[test]
fn a_blob_without_a_section_has_no_self_test() {
    for blob in [EXAMPLE, DEFAULT, SOFTMAX] {
        assert!(Model::from_bytes(blob).unwrap().self_test().is_none());
        assert_eq!(run(blob), Ok(0));
    }
}

#[test]
fn stored_vectors_pass_on_the_runtime_that_computed_them() {
    for (blob, n) in [(EXAMPLE, 1), (EXAMPLE, 5), (DEFAULT, 8), (SOFTMAX, 3)] {
        let (payload, _) = with_section(blob, n);
        let sealed = reseal(blob, &payload);
        let model = Model::from_bytes(&sealed).unwrap();
        assert_eq!(model.self_test().unwrap().count(), n);
        assert_eq!(run(&sealed), Ok(n));
        // In a flash region with bytes after it, too.
        let mut region = sealed.clone();
        region.extend_from_slice(&[0xFF; 64]);
        assert_eq!(
            Model::from_region(&region)
                .unwrap()
                .self_test()
                .unwrap()
                .count(),
            n
        );
        // The section changes no output of a frame.
        let plain = Model::from_bytes(blob).unwrap();
        let mut a: Box<Runtime<'_, 4096>> = Box::new(Runtime::new(plain).unwrap());
        let mut b: Box<Runtime<'_, 4096>> = Box::new(Runtime::new(model).unwrap());
        let x = vec![123i16; a.model().input_dim()];
        let ya = a
            .run_quantised(Phase::from_bits(7 << 28), &x)
            .unwrap()
            .to_vec();
        assert_eq!(b.run_quantised(Phase::from_bits(7 << 28), &x).unwrap(), ya);
    }
}

#[test]
fn a_changed_expected_output_is_named_by_vector_and_output() {
    let (ins, outs) = (342usize, 311usize);
    let rec = 4 + 2 * ins + 2 * outs;
    let (mut payload, start) = with_section(DEFAULT, 8);
    let (vector, output) = (5usize, 17usize);
    let at = start + vector * rec + 4 + 2 * ins + 2 * output;
    let stored = i16::from_le_bytes([payload[at], payload[at + 1]]);
    let wrong = stored.wrapping_add(1);
    payload[at..at + 2].copy_from_slice(&wrong.to_le_bytes());
    let sealed = reseal(DEFAULT, &payload);
    // It loads (CRC re-sealed, the section well-formed) ...
    assert!(Model::from_bytes(&sealed).is_ok());
    // ... and only the self-test catches it.
    assert_eq!(
        run(&sealed),
        Err(Error::SelfTestFailed {
            vector: 5,
            output: 17,
            expected: wrong,
            got: stored,
        })
    );
    let msg = run(&sealed).unwrap_err().to_string();
    assert!(msg.contains("vector 5 output 17"), "{msg}");
}

#[test]
fn a_changed_input_fails_too() {
    let (mut payload, start) = with_section(EXAMPLE, 4);
    // Vector 2's first input: 4 + 2 * 2 + 2 * 1 = 10 bytes a record.
    let at = start + 2 * 10 + 4;
    payload[at] ^= 0x40;
    let r = run(&reseal(EXAMPLE, &payload));
    assert!(
        matches!(
            r,
            Err(Error::SelfTestFailed {
                vector: 2,
                output: 0,
                ..
            })
        ),
        "{r:?}"
    );
}

#[test]
fn a_flipped_byte_is_a_crc_refusal_not_a_self_test_failure() {
    let (payload, start) = with_section(EXAMPLE, 3);
    let sealed = reseal(EXAMPLE, &payload);
    let p = sealed.len() - payload.len();
    for at in [
        p + start,
        p + start + 12,
        sealed.len() - 1,
        sealed.len() - 16,
    ] {
        let mut damaged = sealed.clone();
        damaged[at] ^= 1;
        assert_eq!(
            Model::from_bytes(&damaged).err(),
            Some(Error::PayloadCorrupt),
            "byte {at}"
        );
    }
}

#[test]
fn malformed_sections_are_refused_at_load() {
    let (payload, _) = with_section(DEFAULT, 2);
    let n = payload.len();
    let edit = |at: usize, bytes: &[u8]| {
        let mut p = payload.clone();
        p[n - 16 + at..n - 16 + at + bytes.len()].copy_from_slice(bytes);
        Model::from_bytes(&reseal(DEFAULT, &p)).err()
    };
    let bad = Some(Error::SelfTestMalformed);
    assert_eq!(edit(6, &341u16.to_le_bytes()), bad, "input_dim");
    assert_eq!(edit(8, &312u16.to_le_bytes()), bad, "output_dim");
    assert_eq!(edit(10, &9u16.to_le_bytes()), bad, "version");
    assert_eq!(edit(4, &0u16.to_le_bytes()), bad, "no vectors");
    assert_eq!(
        edit(4, &3u16.to_le_bytes()),
        bad,
        "more vectors than stored"
    );
    assert_eq!(edit(0, &2u32.to_le_bytes()), bad, "misaligned");
    assert_eq!(edit(0, &(u32::MAX - 3).to_le_bytes()), bad, "overflow");
    // A footer with nothing before it.
    let footer = &payload[n - 16..];
    let mut p = Model::from_bytes(DEFAULT).unwrap().payload().to_vec();
    p.extend_from_slice(footer);
    let l = p.len();
    p[l - 16..l - 12].copy_from_slice(&((l - 16) as u32).to_le_bytes());
    assert_eq!(Model::from_bytes(&reseal(DEFAULT, &p)).err(), bad);
}

#[test]
fn the_golden_blobs_do_not_end_with_the_footer_magic() {
    // A loader with the self-test feature reads every existing blob as one
    // without a section: none of their payloads ends with `PGST` (each ends
    // with its last layer's requantisation records, reserved byte 0).
    for blob in [
        EXAMPLE,
        DEFAULT,
        SOFTMAX,
        include_bytes!("../../tests/golden/cp-diagonal/model.blob").as_slice(),
        include_bytes!("../../tests/golden/dense-int16/model.blob").as_slice(),
        include_bytes!("../../tests/golden/omg-tiny-fe-r1/model.blob").as_slice(),
        include_bytes!("../../tests/golden/omg-small-rbfcat-r1/model.blob").as_slice(),
        include_bytes!("../../tests/golden/dec-graph/model.blob").as_slice(),
        include_bytes!("../../tests/fixtures/rig-motion-v2.blob").as_slice(),
    ] {
        let m = Model::from_bytes(blob).unwrap();
        assert!(!m.payload().ends_with(&SELF_TEST_MAGIC));
        assert_eq!(m.payload().last(), Some(&0));
        assert!(m.self_test().is_none());
    }
}

#[test]
fn the_documented_example_section_loads_and_passes() {
    // docs/blob-format.md, "Self-test section", "Example".
    let mut payload = Model::from_bytes(EXAMPLE).unwrap().payload().to_vec();
    assert_eq!(payload.len(), 40);
    let section = [
        0x00, 0x00, 0x00, 0x00, 0x80, 0x01, 0x60, 0xff, 0x77, 0x0e, 0x00,
        0x00, // record, padding
        0x28, 0x00, 0x00, 0x00, 0x01, 0x00, 0x02, 0x00, 0x01, 0x00, 0x01, 0x00, // footer
        0x50, 0x47, 0x53, 0x54,
    ];
    payload.extend_from_slice(&section);
    assert_eq!(payload.len(), 68);
    assert_eq!(run(&reseal(EXAMPLE, &payload)), Ok(1));
    payload[48] = 0x78;
    assert_eq!(
        run(&reseal(EXAMPLE, &payload)),
        Err(Error::SelfTestFailed {
            vector: 0,
            output: 0,
            expected: 3704,
            got: 3703
        })
    );
}
