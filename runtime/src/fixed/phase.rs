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
        // `as i64` truncates toward zero and saturates; |turns| < 2^63 here.
        let whole = turns as i64;
        let mut frac = turns - whole as f32;
        if frac < 0.0 {
            frac += 1.0;
        }
        let bits = (frac * 4_294_967_296.0) as u64;
        Ok(Phase::from_bits(bits.min(u64::from(u32::MAX)) as u32))
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

    #[test]
    fn round_trip_radians() {
        for i in 0..1000 {
            let r = i as f32 * 0.00628;
            let p = Phase::from_radians(r).unwrap();
            assert!((p.to_radians() - r).abs() < 1e-5);
        }
    }
}
