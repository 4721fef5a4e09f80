//! Fixed-point arithmetic: rounding shifts, the ELU table, phase and gates.

pub mod elu;
pub mod gate;
pub mod phase;
pub mod softmax;

use core::num::NonZeroU64;

/// `v / 2^shift` rounded half up, without the overflow of adding `2^(shift-1)`
/// first. Shifts of 64 or more give 0 (`|v| / 2^64` is below one half).
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

/// `sat_i32(round_shift(v, shift))`: the same bits, with 32-bit word
/// operations for the shifts of 1 to 32 (a requantisation's first step,
/// every output row), where a 64-bit shift by an amount the compiler
/// cannot bound costs a Cortex-M4 about twice as many instructions.
#[inline(always)]
pub fn round_shift_sat_i32(v: i64, shift: u8) -> i32 {
    if !(1..=32).contains(&shift) {
        return round_shift_sat_i32_rest(v, shift);
    }
    let a = u32::from(shift - 1);
    let (lo, hi) = (v as u32, (v >> 32) as i32);
    // `h = v >> a` as two words; `hi << 1 << (31 - a)` is `hi << (32 - a)`
    // without a shift by 32 when `a` is 0.
    let h_lo = lo.wrapping_shr(a) | (hi as u32).wrapping_shl(1).wrapping_shl(31 - a);
    let h_hi = hi.wrapping_shr(a);
    // The result `(h >> 1) + (h & 1)` is an i32 exactly when `h` lies in
    // [-2^32, 2^32 - 2]: its high word is 0 or -1 and the rounding
    // increment does not carry past i32::MAX.
    if h_hi.wrapping_add(1) as u32 <= 1 {
        let half = ((h_hi as u32).wrapping_shl(31) | (h_lo >> 1)) as i32;
        half.checked_add((h_lo & 1) as i32).unwrap_or(i32::MAX)
    } else if hi < 0 {
        i32::MIN
    } else {
        i32::MAX
    }
}

/// `sat_i16(round_shift(v, shift))`: the same bits, from the high word
/// alone for the shifts of 33 to 63 (a requantisation's last step, whose
/// shift is mostly in that range), where `v >> (shift - 1)` is the high
/// word shifted by `shift - 33`.
#[inline(always)]
pub fn round_shift_sat_i16(v: i64, shift: u8) -> i16 {
    if !(33..=63).contains(&shift) {
        return round_shift_sat_i16_rest(v, shift);
    }
    let h = ((v >> 32) as i32).wrapping_shr(u32::from(shift - 33));
    // `|h| <= 2^31`, so neither the halving nor the increment overflows.
    ((h >> 1) + (h & 1)).clamp(i32::from(i16::MIN), i32::from(i16::MAX)) as i16
}

/// [`round_shift_sat_i32`] for the shifts it does not take in words: one
/// out-of-line copy for every inlined fast path (`.text`).
#[cold]
#[inline(never)]
fn round_shift_sat_i32_rest(v: i64, shift: u8) -> i32 {
    sat_i32(round_shift(v, shift))
}

/// [`round_shift_sat_i16`] for the shifts it does not take from the high
/// word: one out-of-line copy.
#[cold]
#[inline(never)]
fn round_shift_sat_i16_rest(v: i64, shift: u8) -> i16 {
    sat_i16(round_shift(v, shift))
}

/// `n / d` when the quotient is below `2^18` (`2^18 - 1` when it is not),
/// by restoring division: 18 compare-and-subtract steps. The softmax gate's
/// coefficients (at most 2^16) need no more, and the Cortex-M4 build then
/// links no 64-bit division routine (about 1 KB of `.text`).
pub(crate) fn div_short(n: u64, d: NonZeroU64) -> u64 {
    let d = d.get();
    let (mut q, mut r) = (0u64, n);
    for b in (0..18).rev() {
        // `d << b` past 2^64 is above `r`: no step to take.
        let step = d << b;
        if step >> b == d && r >= step {
            r -= step;
            q |= 1 << b;
        }
    }
    q
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

    /// `floor((v + 2^(s-1)) / 2^s)` in i128, where the addition cannot
    /// overflow: the definition `round_shift` must meet for every shift.
    fn round_shift_reference(v: i64, s: u8) -> i64 {
        match s {
            0 => v,
            1..=127 => ((i128::from(v) + (1i128 << (s - 1))) >> s) as i64,
            _ => 0,
        }
    }

    proptest::proptest! {
        /// Every shift, including both sides of 32 and past 63, on values
        /// drawn across the whole range and near the word boundaries:
        /// `round_shift` meets the i128 definition, and its word-level
        /// saturating forms give the bits of the plain composition.
        #[test]
        fn round_shift_and_its_fused_forms_match_the_definition(
            v in proptest::prop_oneof![
                proptest::num::i64::ANY,
                -(1i64 << 34)..(1i64 << 34),
                -(1i64 << 40)..(1i64 << 40),
                (i64::MAX - 1024)..=i64::MAX,
                i64::MIN..(i64::MIN + 1024),
            ],
            s in 0u8..=80,
        ) {
            proptest::prop_assert_eq!(round_shift(v, s), round_shift_reference(v, s), "{} >> {}", v, s);
            proptest::prop_assert_eq!(round_shift_sat_i32(v, s), sat_i32(round_shift(v, s)), "{} >> {}", v, s);
            proptest::prop_assert_eq!(round_shift_sat_i16(v, s), sat_i16(round_shift(v, s)), "{} >> {}", v, s);
        }
    }

    proptest::proptest! {
        /// Exact below its quotient bound, saturated at `2^18 - 1` above.
        #[test]
        fn div_short_is_division_below_its_bound(
            n in proptest::prop_oneof![proptest::num::u64::ANY, 0u64..(1 << 52)],
            d in proptest::prop_oneof![1u64..=u64::MAX, 1u64..(1 << 36), 1u64..64],
        ) {
            let d = NonZeroU64::new(d).unwrap();
            proptest::prop_assert_eq!(div_short(n, d), (n / d).min((1 << 18) - 1));
        }
    }

    #[test]
    fn div_short_edges() {
        let one = NonZeroU64::MIN;
        assert_eq!(div_short((1 << 18) - 1, one), (1 << 18) - 1);
        assert_eq!(div_short(1 << 18, one), (1 << 18) - 1);
        assert_eq!(div_short(u64::MAX, NonZeroU64::MAX), 1);
        assert_eq!(div_short(u64::MAX - 1, NonZeroU64::MAX), 0);
        let big = NonZeroU64::new(1 << 63).unwrap();
        assert_eq!(div_short(u64::MAX, big), 1);
        for (n, d) in [
            (65536u64 << 17, 2u64),
            ((1 << 48) + (1 << 34), 1 << 35),
            (12345, 7),
        ] {
            let d = NonZeroU64::new(d).unwrap();
            assert_eq!(div_short(n, d), (n / d).min((1 << 18) - 1), "{n} / {d}");
        }
    }

    #[test]
    fn round_shift_edges_match_the_i128_definition() {
        let mut values = vec![i64::MIN, i64::MIN + 1, i64::MAX, i64::MAX - 1, 0, 1, -1];
        for k in 0..63 {
            for d in -2i64..=2 {
                values.push((1i64 << k).wrapping_add(d));
                values.push((-(1i64 << k)).wrapping_add(d));
            }
        }
        // Where the i32 and i16 results start to saturate: `(b << k) + 2^(k-1)`.
        for k in 1..=62u32 {
            for b in [i32::MAX, i32::MIN]
                .map(i64::from)
                .into_iter()
                .chain([i64::from(i16::MAX), i64::from(i16::MIN)])
            {
                for d in -2i64..=2 {
                    let v = b
                        .wrapping_shl(k)
                        .wrapping_add(1i64 << (k - 1))
                        .wrapping_add(d);
                    values.push(v);
                }
            }
        }
        for &v in &values {
            for s in 0u8..=255 {
                assert_eq!(round_shift(v, s), round_shift_reference(v, s), "{v} >> {s}");
                let exact = round_shift_reference(v, s);
                assert_eq!(
                    i64::from(round_shift_sat_i32(v, s)),
                    exact.clamp(i32::MIN.into(), i32::MAX.into()),
                    "{v} >> {s}"
                );
                assert_eq!(
                    i64::from(round_shift_sat_i16(v, s)),
                    exact.clamp(i16::MIN.into(), i16::MAX.into()),
                    "{v} >> {s}"
                );
            }
        }
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
