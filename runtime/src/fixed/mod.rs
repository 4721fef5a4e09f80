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
    match fits_i32(v) {
        // An i32 clamp is one `SSAT` on the Cortex-M4.
        Some(lo) => lo.clamp(i32::from(i16::MIN), i32::from(i16::MAX)) as i16,
        None if v < 0 => i16::MIN,
        None => i16::MAX,
    }
}

/// Saturates to the i32 range.
#[inline(always)]
pub fn sat_i32(v: i64) -> i32 {
    match fits_i32(v) {
        Some(lo) => lo,
        None if v < 0 => i32::MIN,
        None => i32::MAX,
    }
}

/// `v` as an i32 if it is one: its high word is then its low word's sign.
/// Word compares instead of 64-bit ones, and an i32 result the compiler
/// multiplies with one `SMULL`.
#[inline(always)]
fn fits_i32(v: i64) -> Option<i32> {
    let lo = v as i32;
    ((v >> 32) as i32 == lo >> 31).then_some(lo)
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

    #[test]
    fn saturation_is_clamping() {
        let edges = [i64::MIN, i64::MAX, 0, 1, -1, 1 << 32, -(1 << 32)];
        let near = |b: i64| (b - 2..=b + 2).collect::<Vec<_>>();
        let mut values: Vec<i64> = edges.to_vec();
        for b in [i32::MIN, i32::MAX].map(i64::from) {
            values.extend(near(b));
        }
        for b in [i16::MIN, i16::MAX].map(i64::from) {
            values.extend(near(b));
        }
        values.extend((-40..40).map(|k: i64| k.wrapping_mul(0x1234_5678_9ABC)));
        for v in values {
            assert_eq!(
                i64::from(sat_i32(v)),
                v.clamp(i32::MIN.into(), i32::MAX.into()),
                "{v}"
            );
            assert_eq!(
                i64::from(sat_i16(v)),
                v.clamp(i16::MIN.into(), i16::MAX.into()),
                "{v}"
            );
        }
    }
}
