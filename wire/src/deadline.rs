//! The frame deadline on the wire (controller mode only; `docs/deadline.md`).
//!
//! Host -> firmware: an optional 16-byte **deadline block** right after the
//! input image's records (not counted in the header: an image without one
//! reads as before, and a firmware that does not look for it ignores it):
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 4 | magic `PGDL` |
//! | 4 | 4 | budget, SysTick ticks per frame (non-zero) |
//! | 8 | 4 | policy: 0 report, 1 hold next ([`OverrunPolicy::to_u32`]) |
//! | 12 | 4 | CRC-32 of bytes 0..12 |
//!
//! Anything else where the block would start (zeros: the HOSTIO region is
//! zero-filled) means no deadline.
//!
//! Firmware -> host: every controller-mode output record carries a u32
//! [`FrameStatus`] word (bit 0 overran, bit 1 held, bit 2 the status pin's
//! level read back from the board after the frame).

use phasegate_controller::{DeadlineConfig, FrameBudget, OverrunPolicy};

use crate::{crc32, put_u32, u32_at, WireError};

/// Magic of the deadline block.
pub const DEADLINE_MAGIC: [u8; 4] = *b"PGDL";
/// Bytes of the deadline block.
pub const DEADLINE_BLOCK_LEN: usize = 16;

/// The deadline block of a budget and a policy.
pub fn encode_deadline(budget: FrameBudget, policy: OverrunPolicy) -> [u8; DEADLINE_BLOCK_LEN] {
    let mut b = [0u8; DEADLINE_BLOCK_LEN];
    b[..4].copy_from_slice(&DEADLINE_MAGIC);
    put_u32(&mut b, 4, budget.ticks());
    put_u32(&mut b, 8, policy.to_u32());
    let crc = crc32(&b[..12]);
    put_u32(&mut b, 12, crc);
    b
}

/// The deadline in the bytes after the records: [`DeadlineConfig::NONE`]
/// when they do not start with the magic; [`WireError::BadDeadline`] for
/// a block that does but is damaged or names no valid budget or policy.
pub fn parse_deadline(after_records: &[u8]) -> Result<DeadlineConfig, WireError> {
    if after_records.get(..4) != Some(&DEADLINE_MAGIC[..]) {
        return Ok(DeadlineConfig::NONE);
    }
    let block = after_records
        .get(..DEADLINE_BLOCK_LEN)
        .ok_or(WireError::BadDeadline)?;
    if crc32(block.get(..12).ok_or(WireError::BadDeadline)?) != u32_at(block, 12) {
        return Err(WireError::BadDeadline);
    }
    let policy = OverrunPolicy::from_u32(u32_at(block, 8)).map_err(|_| WireError::BadDeadline)?;
    DeadlineConfig::new(u32_at(block, 4), policy).map_err(|_| WireError::BadDeadline)
}

/// What the deadline did in one controller frame, as written in its record.
#[derive(Clone, Copy, Debug, Default, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FrameStatus {
    /// The frame took more ticks than the budget.
    pub overrun: bool,
    /// The frame was held (no inference, the last pose again).
    pub held: bool,
    /// The status pin's level after the frame, read back from the board.
    pub pin_high: bool,
}

impl FrameStatus {
    /// The u32 word (bit 0 overrun, bit 1 held, bit 2 pin).
    pub fn to_u32(self) -> u32 {
        u32::from(self.overrun) | u32::from(self.held) << 1 | u32::from(self.pin_high) << 2
    }

    /// The status of a word; `None` when a bit above 2 is set.
    pub fn from_u32(v: u32) -> Option<Self> {
        (v < 8).then_some(FrameStatus {
            overrun: v & 1 != 0,
            held: v & 2 != 0,
            pin_high: v & 4 != 0,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deadline_block_round_trips_and_damage_is_refused() {
        let b = encode_deadline(
            FrameBudget::from_ticks(1234).unwrap(),
            OverrunPolicy::HoldNext,
        );
        let c = parse_deadline(&b).unwrap();
        assert_eq!(c.budget.unwrap().ticks(), 1234);
        assert_eq!(c.policy, OverrunPolicy::HoldNext);
        // Zeros (no block) and a short region without the magic: no deadline.
        assert_eq!(parse_deadline(&[0; 16]), Ok(DeadlineConfig::NONE));
        assert_eq!(parse_deadline(&[]), Ok(DeadlineConfig::NONE));
        // Any flipped bit after the magic, or a cut block, is refused.
        for i in 4..DEADLINE_BLOCK_LEN {
            let mut d = b;
            d[i] ^= 1;
            assert_eq!(parse_deadline(&d), Err(WireError::BadDeadline), "byte {i}");
        }
        assert_eq!(parse_deadline(&b[..15]), Err(WireError::BadDeadline));
        // A zero budget or an unknown policy with a valid CRC: refused too.
        for (ticks, policy) in [(0u32, 0u32), (5, 2)] {
            let mut d = b;
            put_u32(&mut d, 4, ticks);
            put_u32(&mut d, 8, policy);
            let crc = crc32(&d[..12]);
            put_u32(&mut d, 12, crc);
            assert_eq!(parse_deadline(&d), Err(WireError::BadDeadline));
        }
    }

    #[test]
    fn status_words_round_trip() {
        for v in 0..8 {
            assert_eq!(FrameStatus::from_u32(v).unwrap().to_u32(), v);
        }
        assert_eq!(FrameStatus::from_u32(8), None);
    }
}
