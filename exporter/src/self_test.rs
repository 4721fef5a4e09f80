//! `--self-test N`: N input vectors and the integer outputs the host
//! runtime computes for them, stored in the blob's self-test section at
//! the end of its payload (`docs/blob-format.md`, "Self-test section"), so
//! that a device can check at boot that its runtime computes what this
//! one did, bit for bit.
//!
//! The vectors depend on the blob's dimensions alone (nothing of the
//! network or the command): from a ChaCha8 stream seeded by [`SEED`], per
//! vector a phase (a uniform u32, Q0.32 of a cycle) and per input a
//! quantised value `sat16(round(4096 z))`, `z` standard normal: a
//! standard-normal model input at the exporter's default input range (8
//! standard deviations to the i16 limit, `docs/fixed-point.md`). The
//! expected outputs are `phasegate::Runtime::run_quantised` on the blob
//! just written, base mix.

use anyhow::{bail, ensure, Context, Result};
use phasegate::blob::{
    crc32, Header, SelfTest, MAX_SELF_TEST_VECTORS, SELF_TEST_FOOTER_LEN, SELF_TEST_MAGIC,
    SELF_TEST_VERSION,
};
use phasegate::{Model, Phase, Runtime};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::Serialize;

/// Seed of the vectors' stream.
pub const SEED: u64 = 0x5E1F_7E57;
/// Standard deviation of a quantised input, i16 units: 2^12, the Q format
/// of a normalised input at the default `--input-range-sigma` 8.
pub const INPUT_STD: f64 = 4096.0;
/// Most vectors `--self-test` stores (the format's limit).
pub const MAX_VECTORS: usize = MAX_SELF_TEST_VECTORS as usize;

/// Activation arena of the host runtime that computes the outputs (i16
/// elements; a blob's arena is at most 65,535 elements, 2 x its largest
/// span end).
const ARENA: usize = 65_536;

/// What the report says about the section.
#[derive(Clone, Debug, Serialize, PartialEq, Eq)]
pub struct SelfTestReport {
    /// Vectors stored.
    pub vectors: usize,
    /// Bytes the section adds to the blob (records, padding and footer).
    pub bytes: usize,
    /// The seed of the inputs and phases.
    pub seed: u64,
}

/// The `n` vectors for a model of `input_dim` inputs: (phase, inputs).
pub fn vectors(input_dim: usize, n: usize) -> Vec<(u32, Vec<i16>)> {
    let mut rng = ChaCha8Rng::seed_from_u64(SEED);
    (0..n)
        .map(|_| {
            let phase: u32 = rng.gen();
            let x = (0..input_dim)
                .map(|_| {
                    let z: f64 = rng.sample(StandardNormal);
                    (z * INPUT_STD).round().clamp(-32768.0, 32767.0) as i16
                })
                .collect();
            (phase, x)
        })
        .collect()
}

/// `blob` (a model blob, as the exporter wrote it) with a self-test
/// section of `n` vectors appended to its payload, and the section's
/// figures; `n == 0` returns the blob unchanged. The result is checked:
/// it loads and its self-test passes on the host runtime.
pub fn with_self_test(blob: &[u8], n: usize) -> Result<(Vec<u8>, Option<SelfTestReport>)> {
    if n == 0 {
        return Ok((blob.to_vec(), None));
    }
    ensure!(
        n <= MAX_VECTORS,
        "--self-test {n}: a blob holds at most {MAX_VECTORS} self-test vectors"
    );
    let model =
        Model::from_bytes(blob).map_err(|e| anyhow::anyhow!("the blob does not load: {e}"))?;
    if model.self_test().is_some() {
        bail!("the blob has a self-test section already");
    }
    let (ins, outs) = (model.input_dim(), model.output_dim());
    let mut payload = model.payload().to_vec();
    payload.resize(payload.len().next_multiple_of(4), 0);
    let start = u32::try_from(payload.len()).context("payload over 4 GiB")?;
    let mut rt: Box<Runtime<'_, ARENA>> =
        Box::new(Runtime::new(model.clone()).map_err(|e| anyhow::anyhow!("host runtime: {e}"))?);
    for (phase, x) in vectors(ins, n) {
        let y = rt
            .run_quantised(Phase::from_bits(phase), &x)
            .map_err(|e| anyhow::anyhow!("host runtime: {e}"))?;
        ensure!(y.len() == outs, "host runtime: {} outputs", y.len());
        payload.extend_from_slice(&phase.to_le_bytes());
        for v in x.iter().chain(y) {
            payload.extend_from_slice(&v.to_le_bytes());
        }
    }
    payload.resize(payload.len().next_multiple_of(4), 0);
    payload.extend_from_slice(&start.to_le_bytes());
    payload.extend_from_slice(&(n as u16).to_le_bytes());
    payload.extend_from_slice(&(ins as u16).to_le_bytes());
    payload.extend_from_slice(&(outs as u16).to_le_bytes());
    payload.extend_from_slice(&SELF_TEST_VERSION.to_le_bytes());
    payload.extend_from_slice(&SELF_TEST_MAGIC);
    let added = payload.len() - model.payload().len();
    let out = reseal(blob, &payload)?;
    {
        let check = Model::from_bytes(&out)
            .map_err(|e| anyhow::anyhow!("the blob with its self-test does not load back: {e}"))?;
        let mut rt: Box<Runtime<'_, ARENA>> =
            Box::new(Runtime::new(check).map_err(|e| anyhow::anyhow!("host runtime: {e}"))?);
        let passed = rt
            .run_self_test()
            .map_err(|e| anyhow::anyhow!("the blob's own self-test fails on the host: {e}"))?;
        ensure!(
            usize::from(passed) == n,
            "{passed} of {n} self-test vectors ran"
        );
    }
    Ok((
        out,
        Some(SelfTestReport {
            vectors: n,
            bytes: added,
            seed: SEED,
        }),
    ))
}

/// [`with_self_test`] on an exported blob and its report (`blob_bytes`
/// and `self_test` set when `n > 0`): what every command that writes a
/// model blob does with `--self-test N`.
pub fn apply(blob: Vec<u8>, report: &mut crate::export::ExportReport, n: usize) -> Result<Vec<u8>> {
    if n == 0 {
        return Ok(blob);
    }
    let (blob, rep) = with_self_test(&blob, n).context("--self-test")?;
    report.blob_bytes = blob.len();
    report.self_test = rep;
    Ok(blob)
}

/// `blob` with its payload replaced by `payload`: the header re-encoded
/// with the new `payload_len` and `payload_crc` (both CRCs re-sealed);
/// every other header field as it was.
pub fn reseal(blob: &[u8], payload: &[u8]) -> Result<Vec<u8>> {
    let framed = phasegate::blob::Framed::parse(blob, true)
        .map_err(|e| anyhow::anyhow!("the blob does not load: {e}"))?;
    let h = framed.header;
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
        payload_len: u32::try_from(payload.len()).context("payload over 4 GiB")?,
        payload_crc: crc32(payload),
    };
    Ok(crate::encode::frame(&header, payload))
}

/// A copy of `blob` (which has a self-test section) whose stored output
/// `output` of vector `vector` is one more than the runtime computes, the
/// payload CRC re-sealed: it loads, and only the self-test can refuse it
/// (`SelfTestFailed { vector, output, .. }`). For the must-fail checks.
pub fn corrupt_expected(blob: &[u8], vector: usize, output: usize) -> Result<Vec<u8>> {
    let model = Model::from_bytes(blob).map_err(|e| anyhow::anyhow!("{e}"))?;
    let test: SelfTest<'_> = model.self_test().context("the blob has no self-test")?;
    let (ins, outs) = (model.input_dim(), model.output_dim());
    ensure!(
        vector < usize::from(test.count()) && output < outs,
        "no output {output} of vector {vector}"
    );
    let payload = model.payload();
    let footer = payload.len() - SELF_TEST_FOOTER_LEN;
    let start = u32::from_le_bytes(payload[footer..footer + 4].try_into()?) as usize;
    let rec = phasegate::blob::self_test::record_len(ins as u16, outs as u16);
    let at = start + vector * rec + 4 + 2 * ins + 2 * output;
    let mut p = payload.to_vec();
    let v = i16::from_le_bytes([p[at], p[at + 1]]).wrapping_add(1);
    p[at..at + 2].copy_from_slice(&v.to_le_bytes());
    reseal(blob, &p)
}

#[cfg(test)]
mod tests {
    use super::*;

    const DEFAULT: &[u8] = include_bytes!("../../tests/golden/default/model.blob");
    const SOFTMAX: &[u8] = include_bytes!("../../tests/golden/softmax-graph/model.blob");

    #[test]
    fn the_section_passes_and_a_corrupted_copy_fails_where_it_was_changed() {
        for blob in [DEFAULT, SOFTMAX] {
            let (out, rep) = with_self_test(blob, 6).unwrap();
            let rep = rep.unwrap();
            assert_eq!(out.len(), blob.len() + rep.bytes);
            // Deterministic.
            assert_eq!(with_self_test(blob, 6).unwrap().0, out);
            let bad = corrupt_expected(&out, 4, 2).unwrap();
            let m = Model::from_bytes(&bad).unwrap();
            let mut rt: Box<Runtime<'_, ARENA>> = Box::new(Runtime::new(m).unwrap());
            assert!(matches!(
                rt.run_self_test(),
                Err(phasegate::Error::SelfTestFailed {
                    vector: 4,
                    output: 2,
                    ..
                })
            ));
            // The header, but for the payload's length and CRC, is the
            // original's; the payload is the original's with the section after it.
            let a = Model::from_bytes(blob).unwrap();
            let b = Model::from_bytes(&out).unwrap();
            assert!(b.payload().starts_with(a.payload()));
            assert_eq!(b.header().nodes.to_vec(), a.header().nodes.to_vec());
        }
    }

    #[test]
    fn zero_vectors_is_the_blob_unchanged_and_a_second_section_is_refused() {
        assert_eq!(with_self_test(DEFAULT, 0).unwrap().0, DEFAULT);
        let (out, _) = with_self_test(DEFAULT, 2).unwrap();
        assert!(with_self_test(&out, 2).is_err());
        assert!(with_self_test(DEFAULT, MAX_VECTORS + 1).is_err());
    }

    #[test]
    fn inputs_are_normal_in_the_default_input_format() {
        let v = vectors(342, 64);
        let all: Vec<f64> = v
            .iter()
            .flat_map(|(_, x)| x.iter().map(|&q| f64::from(q)))
            .collect();
        let mean = all.iter().sum::<f64>() / all.len() as f64;
        let sd = (all.iter().map(|q| (q - mean).powi(2)).sum::<f64>() / all.len() as f64).sqrt();
        assert!(
            mean.abs() < 60.0 && (sd - INPUT_STD).abs() < 100.0,
            "{mean} {sd}"
        );
        assert_eq!(vectors(342, 64), v);
    }
}
