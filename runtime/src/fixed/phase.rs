//! The phase: a fraction of a gait cycle, unsigned Q0.32.

use crate::error::{Error, Result};
use fixed::types::U0F32;

/// Position in the cycle, `[0, 1)` of a turn, as `fixed`'s `U0F32`: the full
/// u32 range is one cycle, so it wraps for free and needs no float.
#[derive(Clone, Copy, Debug, Default, Eq, PartialEq, Hash)]
pub struct Phase(pub U0F32);

#[cfg(feature = "defmt")]
impl defmt::Format for Phase {
    fn format(&self, f: defmt::Formatter) {
        defmt::write!(f, "Phase({=u32:#x})", self.0.to_bits())
    }
}

const TWO_PI: f32 = core::f32::consts::TAU;

impl Phase {
    /// From the raw U0.32 fraction of a cycle.
    pub const fn from_bits(bits: u32) -> Phase {
        Phase(U0F32::from_bits(bits))
    }

    /// The raw U0.32 fraction of a cycle.
    pub const fn to_bits(self) -> u32 {
        self.0.to_bits()
    }

    /// From radians, wrapped into one cycle. Uses only IEEE single-precision
    /// multiply, subtract and conversions, so it gives the same bits on every
    /// target with an IEEE FPU (or soft float).
    pub fn from_radians(radians: f32) -> Result<Phase> {
        if !radians.is_finite() {
            return Err(Error::NonFinite { index: 0 });
        }
        let turns = radians / TWO_PI;
        // The whole turns, truncated toward zero as an i64 conversion would
        // (and saturated at +-2^63 as it would), without the Cortex-M4's
        // software float-to-i64 routines: below 2^24 in magnitude the
        // hardware's i32 conversion is exact, from 2^24 on every f32 is a
        // whole number already.
        let whole = if turns.abs() < 16_777_216.0 {
            (turns as i32) as f32
        } else {
            // `i64::MAX as f32` is 2^63, a constant.
            turns.clamp(-(i64::MAX as f32), i64::MAX as f32)
        };
        let mut frac = turns - whole;
        if frac < 0.0 {
            frac += 1.0;
        }
        // `as u32` saturates (and gives 0 for a negative value) as the
        // `as u64` and clamp to u32::MAX it replaces did.
        Ok(Phase::from_bits((frac * 4_294_967_296.0) as u32))
    }

    /// In radians, `[0, 2 pi)`.
    pub fn to_radians(self) -> f32 {
        self.0.to_num::<f32>() * TWO_PI
    }

    /// Advances by `cycles` (may be negative) with wrap-around.
    pub fn advance(self, cycles: U0F32) -> Phase {
        Phase(self.0.wrapping_add(cycles))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radians_wrap_into_one_cycle() {
        let half = Phase::from_radians(core::f32::consts::PI).unwrap();
        assert_eq!(half.to_bits(), 1 << 31);
        let wrapped = Phase::from_radians(core::f32::consts::PI + 4.0 * TWO_PI).unwrap();
        assert!((i64::from(wrapped.to_bits()) - (1i64 << 31)).abs() < 1 << 12);
        let neg = Phase::from_radians(-core::f32::consts::FRAC_PI_2).unwrap();
        assert_eq!(neg.to_bits(), 3 << 30);
        assert_eq!(Phase::from_radians(0.0).unwrap().to_bits(), 0);
        assert!(Phase::from_radians(f32::NAN).is_err());
        assert!(Phase::from_radians(f32::INFINITY).is_err());
        assert!(Phase::from_radians(1e30).is_ok());
    }

    /// `from_radians` as it was (`as i64` / `as u64` conversions).
    fn from_radians_before(radians: f32) -> u32 {
        let turns = radians / TWO_PI;
        let whole = turns as i64;
        let mut frac = turns - whole as f32;
        if frac < 0.0 {
            frac += 1.0;
        }
        let bits = (frac * 4_294_967_296.0) as u64;
        bits.min(u64::from(u32::MAX)) as u32
    }

    /// Same bits as the i64 conversions it replaced: every 97th f32 bit
    /// pattern (about 44 million values of every sign and exponent) and
    /// the neighbours of the turn counts where the branches meet.
    #[test]
    fn from_radians_matches_the_i64_conversion() {
        let check = |r: f32| {
            if r.is_finite() {
                assert_eq!(
                    Phase::from_radians(r).unwrap().to_bits(),
                    from_radians_before(r),
                    "{r:e}"
                );
            }
        };
        for bits in (0..=u32::MAX).step_by(97) {
            check(f32::from_bits(bits));
        }
        for t in [16_777_216.0f32, 2_147_483_648.0, i64::MAX as f32, 1.0, 0.5] {
            for sign in [1.0f32, -1.0] {
                let r = sign * t * TWO_PI;
                let mut b = r.to_bits().wrapping_sub(64);
                for _ in 0..128 {
                    check(f32::from_bits(b));
                    b = b.wrapping_add(1);
                }
            }
        }
        check(f32::MAX);
        check(f32::MIN);
    }

    #[test]
    fn round_trip_radians() {
        for i in 0..1000 {
            let r = i as f32 * 0.00628;
            let p = Phase::from_radians(r).unwrap();
            assert!((p.to_radians() - r).abs() < 1e-5);
        }
    }
}
