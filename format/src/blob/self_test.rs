//! The self-test section (`docs/blob-format.md`, "Self-test section"):
//! input vectors and the integer outputs the runtime computed for them,
//! at the end of a model blob's payload, found by the 16-byte footer that
//! ends the payload.
//!
//! ```text
//! payload offset S        N records, each RECORD(in, out) bytes:
//!                           phase u32 LE, in x i16 LE (quantised input),
//!                           out x i16 LE (expected output, before the output stage)
//! payload_len - 16        footer:
//!   +0  u32 LE  S (a multiple of 4)
//!   +4  u16 LE  N, 1 ..= MAX_SELF_TEST_VECTORS
//!   +6  u16 LE  input_dim  (the header's)
//!   +8  u16 LE  output_dim (the header's)
//!  +10  u16 LE  self-test version, 1
//!  +12  "PGST"
//! ```
//!
//! The payload CRC covers all of it; a loader that does not know the
//! section never reads it (no header field or section points at it).

#![deny(clippy::arithmetic_side_effects)]

use crate::error::{Error, Result};

/// The last four bytes of a payload that ends with a self-test section.
pub const SELF_TEST_MAGIC: [u8; 4] = *b"PGST";
/// The self-test layout this runtime writes and reads.
pub const SELF_TEST_VERSION: u16 = 1;
/// Bytes of the footer that ends the payload.
pub const SELF_TEST_FOOTER_LEN: usize = 16;
/// Most vectors a section holds.
pub const MAX_SELF_TEST_VECTORS: u16 = 1024;

/// Bytes of one vector's record: a u32 phase, `input_dim` inputs and
/// `output_dim` expected outputs, i16 each (at most 262,144).
pub fn record_len(input_dim: u16, output_dim: u16) -> usize {
    // u16 widened: 4 + 2 * 65535 + 2 * 65535 cannot overflow a usize >= 32 bits.
    #[allow(clippy::arithmetic_side_effects)]
    let n = 4 + 2 * usize::from(input_dim) + 2 * usize::from(output_dim);
    n
}

/// A validated self-test section: `count` records in the payload.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct SelfTest<'a> {
    records: &'a [u8],
    count: u16,
    input_dim: u16,
    output_dim: u16,
}

/// One stored vector: its phase, its quantised input and the outputs the
/// runtime must compute for them, borrowed from the payload.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
pub struct Vector<'a> {
    /// The frame's phase (Q0.32 of a cycle, as `Phase::from_bits`).
    pub phase: u32,
    input: &'a [u8],
    expected: &'a [u8],
}

fn le16(b: &[u8]) -> Option<[u8; 2]> {
    Some([*b.first()?, *b.get(1)?])
}

impl<'a> Vector<'a> {
    /// Input `j` (i16, the quantised input the input stage would give).
    pub fn inputs(&self) -> impl Iterator<Item = i16> + 'a {
        self.input
            .chunks_exact(2)
            .filter_map(le16)
            .map(i16::from_le_bytes)
    }

    /// The expected outputs (i16, what `run_quantised` returns).
    pub fn expected(&self) -> impl Iterator<Item = i16> + 'a {
        self.expected
            .chunks_exact(2)
            .filter_map(le16)
            .map(i16::from_le_bytes)
    }
}

impl<'a> SelfTest<'a> {
    /// Finds the section at the end of `payload` (a model's, CRC already
    /// checked) of a model with `input_dim` inputs and `output_dim`
    /// outputs: `Ok(None)` when the payload does not end with
    /// [`SELF_TEST_MAGIC`], `Err(SelfTestMalformed)` when it does but the
    /// footer's version, count, dimensions or records are not as stated.
    pub fn find(payload: &'a [u8], input_dim: u16, output_dim: u16) -> Result<Option<Self>> {
        let Some(footer_at) = payload.len().checked_sub(SELF_TEST_FOOTER_LEN) else {
            return Ok(None);
        };
        let footer = payload.get(footer_at..).ok_or(Error::SelfTestMalformed)?;
        if footer.get(12..16) != Some(&SELF_TEST_MAGIC[..]) {
            return Ok(None);
        }
        let u16_at =
            |at: usize| -> Option<u16> { Some(u16::from_le_bytes(le16(footer.get(at..)?)?)) };
        let bad = Error::SelfTestMalformed;
        let start: [u8; 4] = footer
            .get(0..4)
            .and_then(|b| b.try_into().ok())
            .ok_or(bad)?;
        let start = u32::from_le_bytes(start) as usize;
        let (Some(count), Some(ins), Some(outs), Some(version)) =
            (u16_at(4), u16_at(6), u16_at(8), u16_at(10))
        else {
            return Err(bad);
        };
        if version != SELF_TEST_VERSION
            || count == 0
            || count > MAX_SELF_TEST_VECTORS
            || ins != input_dim
            || outs != output_dim
            || !start.is_multiple_of(4)
        {
            return Err(bad);
        }
        let len = record_len(ins, outs)
            .checked_mul(usize::from(count))
            .ok_or(bad)?;
        let end = start.checked_add(len).ok_or(bad)?;
        if end > footer_at {
            return Err(bad);
        }
        let records = payload.get(start..end).ok_or(bad)?;
        Ok(Some(SelfTest {
            records,
            count,
            input_dim: ins,
            output_dim: outs,
        }))
    }

    /// How many vectors the section holds.
    pub fn count(&self) -> u16 {
        self.count
    }

    /// The vectors in stored order.
    pub fn vectors(&self) -> impl Iterator<Item = Vector<'a>> + 'a {
        let ins = usize::from(self.input_dim);
        let outs = usize::from(self.output_dim);
        self.records
            .chunks_exact(record_len(self.input_dim, self.output_dim))
            .filter_map(move |r| {
                let phase: [u8; 4] = r.get(0..4)?.try_into().ok()?;
                let (input, expected) = r.get(4..)?.split_at_checked(ins.checked_mul(2)?)?;
                (expected.len() == outs.checked_mul(2)?).then_some(Vector {
                    phase: u32::from_le_bytes(phase),
                    input,
                    expected,
                })
            })
    }
}

#[cfg(test)]
#[allow(clippy::arithmetic_side_effects)]
mod tests {
    use super::*;

    /// A payload of `pre` zero bytes, then `n` records of a 2 -> 1 model
    /// and the footer.
    fn payload(pre: usize, n: u16) -> Vec<u8> {
        let mut p = vec![0u8; pre];
        let start = p.len() as u32;
        for i in 0..n {
            p.extend_from_slice(&(u32::from(i) << 20).to_le_bytes());
            for v in [i as i16, -(i as i16), 7 * i as i16] {
                p.extend_from_slice(&v.to_le_bytes());
            }
        }
        p.resize(p.len().next_multiple_of(4), 0);
        p.extend_from_slice(&start.to_le_bytes());
        p.extend_from_slice(&n.to_le_bytes());
        p.extend_from_slice(&2u16.to_le_bytes());
        p.extend_from_slice(&1u16.to_le_bytes());
        p.extend_from_slice(&SELF_TEST_VERSION.to_le_bytes());
        p.extend_from_slice(&SELF_TEST_MAGIC);
        p
    }

    #[test]
    fn a_section_reads_back() {
        let p = payload(40, 3);
        let t = SelfTest::find(&p, 2, 1).unwrap().unwrap();
        assert_eq!(t.count(), 3);
        let v: Vec<_> = t.vectors().collect();
        assert_eq!(v.len(), 3);
        assert_eq!(v[2].phase, 2 << 20);
        assert_eq!(v[2].inputs().collect::<Vec<_>>(), [2, -2]);
        assert_eq!(v[2].expected().collect::<Vec<_>>(), [14]);
    }

    #[test]
    fn a_payload_without_the_magic_has_none() {
        assert_eq!(SelfTest::find(&[0u8; 40], 2, 1), Ok(None));
        assert_eq!(SelfTest::find(&[], 2, 1), Ok(None));
        assert_eq!(SelfTest::find(b"PGST", 2, 1), Ok(None));
        let mut p = payload(40, 3);
        let n = p.len();
        p[n - 1] = b'U';
        assert_eq!(SelfTest::find(&p, 2, 1), Ok(None));
    }

    #[test]
    fn every_malformed_footer_is_refused() {
        let bad = Err::<Option<u16>, _>(Error::SelfTestMalformed);
        let p = payload(40, 3);
        let count = |t: Option<SelfTest<'_>>| t.map(|t| t.count());
        // Dimensions other than the model's.
        assert_eq!(SelfTest::find(&p, 3, 1).map(count), bad);
        assert_eq!(SelfTest::find(&p, 2, 2).map(count), bad);
        let n = p.len();
        let edit = |at: usize, bytes: &[u8]| {
            let mut q = p.clone();
            q[n - 16 + at..n - 16 + at + bytes.len()].copy_from_slice(bytes);
            SelfTest::find(&q, 2, 1).map(count)
        };
        assert_eq!(edit(10, &2u16.to_le_bytes()), bad, "version");
        assert_eq!(edit(4, &0u16.to_le_bytes()), bad, "no vectors");
        assert_eq!(
            edit(4, &4u16.to_le_bytes()),
            bad,
            "records run into the footer"
        );
        assert_eq!(edit(4, &1025u16.to_le_bytes()), bad, "above the maximum");
        assert_eq!(edit(4, &u16::MAX.to_le_bytes()), bad);
        assert_eq!(edit(0, &42u32.to_le_bytes()), bad, "misaligned");
        assert_eq!(edit(0, &u32::MAX.to_le_bytes()), bad, "overflow");
        assert_eq!(edit(0, &(u32::MAX - 3).to_le_bytes()), bad, "overflow");
        assert_eq!(edit(0, &(n as u32).to_le_bytes()), bad, "past the payload");
        // Fewer vectors than there are is well-formed (the rest is a gap).
        assert_eq!(edit(4, &2u16.to_le_bytes()), Ok(Some(2)));
        // A footer alone, claiming records, in a 16-byte payload.
        assert_eq!(SelfTest::find(&p[n - 16..], 2, 1).map(count), bad);
    }
}
