//! Fixed-point arithmetic: rounding shifts, the ELU table, phase and gates.

pub mod elu;
pub mod gate;
pub mod phase;
pub mod softmax;

/// `v / 2^shift` rounded half up, without the overflow of adding `2^(shift-1)`
/// first. Shifts of 64 or more give the sign (0 or -1) plus rounding.
#[inline(always)]
pub fn round_shift(v: i64, shift: u8) -> i64 {
    match shift {
        0 => v,
        // `v >> shift` is `h >> 1`: one variable 64-bit shift instead of
        // two, which on a 32-bit core is most of the cost.
        1..=63 => {
            let h = v >> (shift - 1);
            (h >> 1) + (h & 1)
        }
        _ => 0,
    }
}

/// Saturates to the i16 range.
#[inline(always)]
pub fn sat_i16(v: i64) -> i16 {
    v.clamp(i64::from(i16::MIN), i64::from(i16::MAX)) as i16
}

/// Saturates to the i32 range.
#[inline(always)]
pub fn sat_i32(v: i64) -> i32 {
    v.clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_shift_is_round_half_up() {
        for v in -4000i64..4000 {
            for s in 1u8..10 {
                let exact = v as f64 / f64::from(1u32 << s);
                assert_eq!(
                    round_shift(v, s),
                    (exact + 0.5).floor() as i64,
                    "{v} >> {s}"
                );
            }
        }
        assert_eq!(round_shift(i64::MAX, 1), 1 << 62);
        assert_eq!(round_shift(i64::MIN, 63), -1);
        assert_eq!(round_shift(5, 0), 5);
    }
}
