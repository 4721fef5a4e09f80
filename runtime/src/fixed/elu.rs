//! ELU in fixed point: identity above zero, `exp(x) - 1` below it, read
//! from a Q15 table sampled every 1/64 on [-16, 0] and interpolated linearly.
//! Below -16 the result is -1 (the true value is within 1.2e-7 of it).

#[path = "elu_table.rs"]
mod table;
use table::ELU_TABLE;

/// Table samples per unit of x.
const STEPS_PER_UNIT_LOG2: u32 = 6;
/// Last table index.
const LAST: usize = ELU_TABLE.len() - 1;
/// Shift that turns a magnitude `u` in Q0 into its table position, Q16 of a
/// table step: `pos = (u_q << POS_SHIFT) >> frac` for `u_q` in Q`frac`.
/// Exact (no bit dropped) for `frac <= 15 < POS_SHIFT`.
pub(crate) const POS_SHIFT: u32 = STEPS_PER_UNIT_LOG2 + 16;

/// `exp(-u) - 1` in Q31 for `u >= 0` given as its table position `pos`
/// (Q16 of a table step, see [`POS_SHIFT`]): the two Q15 entries around `u`
/// interpolated linearly and *not* rounded, so callers pick their own
/// precision (ELU rounds to Q15, the softmax gate keeps Q31). At and beyond
/// the last entry (`u >= 16`) it is exactly `-2^31`, i.e. `exp(-u) = 0`; the
/// true value is below 1.2e-7 there, under half a Q15 LSB like the entries.
/// Always in `[-2^31, 0]`.
#[inline]
pub(crate) fn expm1_neg_q31(pos: u64) -> i64 {
    // A position past usize (only on 16/32-bit targets) is past the table too.
    let idx = usize::try_from(pos >> 16).unwrap_or(LAST);
    let t = (pos & 0xFFFF) as i64;
    match (ELU_TABLE.get(idx), ELU_TABLE.get(idx.saturating_add(1))) {
        (Some(&a), Some(&b)) if idx < LAST => {
            let (a, b) = (i64::from(a), i64::from(b));
            (a << 16) + (b - a) * t
        }
        _ => i64::from(i16::MIN) << 16,
    }
}

/// ELU of `x`, a Q`frac` number, as a Q`frac` number; `frac` must be at
/// most 15 (so that -1 fits), which the loader checks.
///
/// The arithmetic is `expm1_neg_q31`'s interpolation rounded to Q15, then
/// to Q`frac` (the specified, reference-checked double rounding), done in
/// 32-bit words: with `u = -x <= 2^15` and `frac <= 15` the table position
/// `(u << 22) >> frac` splits exactly into the index `(u << 6) >> frac`
/// and the fraction's low 16 bits, the table's steps are below 2^10 (a
/// test checks it) so a step times the fraction stays below 2^26, and
/// `q15 << frac` is at least -2^30. Every output row with an ELU runs it.
#[inline]
pub fn elu_q(x: i16, frac: u8) -> i16 {
    if x >= 0 {
        return x;
    }
    let frac = u32::from(frac.min(15));
    let u = u32::from(x.unsigned_abs());
    let idx = ((u << STEPS_PER_UNIT_LOG2) >> frac) as usize;
    let t = (u.wrapping_shl(POS_SHIFT - frac) & 0xFFFF) as i32;
    let q15 = match (ELU_TABLE.get(idx), ELU_TABLE.get(idx.saturating_add(1))) {
        // `round((a 2^16 + (b - a) t) / 2^16)` is `a + round((b - a) t / 2^16)`.
        (Some(&a), Some(&b)) if idx < LAST => {
            let step = (i32::from(b) - i32::from(a)).wrapping_mul(t);
            i32::from(a) + (step.wrapping_add(1 << 15) >> 16)
        }
        // `round(-2^31 / 2^16)`.
        _ => i32::from(i16::MIN),
    };
    let h = (q15 << frac) >> 14;
    ((h >> 1) + (h & 1)).clamp(i32::from(i16::MIN), i32::from(i16::MAX)) as i16
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_matches_exp() {
        for (i, &v) in ELU_TABLE.iter().enumerate() {
            let exact = ((-(i as f64) / 64.0).exp() - 1.0) * 32768.0;
            assert!((f64::from(v) - exact).abs() <= 0.5 + 1e-9, "entry {i}");
        }
    }

    /// Error bound over every i16 input for every supported format: half an
    /// output LSB from the final rounding, plus the table's (half a Q15 LSB
    /// from rounding, h^2/8 = 3.1e-5 from interpolation), scaled to Q`frac`.
    #[test]
    fn elu_error_is_bounded_for_every_input_and_format() {
        for frac in 0u8..=15 {
            let lsb = f64::from(1u32 << frac);
            let table_err = (0.5 / 32768.0 + 1.0 / (8.0 * 64.0 * 64.0) + 0.5 / 32768.0) * lsb;
            let bound = 0.5 + table_err + 1e-9;
            let mut worst = 0.0f64;
            for x in i16::MIN..=i16::MAX {
                let xr = f64::from(x) / lsb;
                let exact = if xr > 0.0 { xr } else { xr.exp() - 1.0 } * lsb;
                let err = (f64::from(elu_q(x, frac)) - exact).abs();
                worst = worst.max(err);
            }
            assert!(
                worst <= bound,
                "frac {frac}: worst {worst} LSB > bound {bound}"
            );
        }
    }

    /// `elu_q` as it was before the table lookup moved into
    /// `expm1_neg_q31`, verbatim.
    fn elu_q_before_refactor(x: i16, frac: u8) -> i16 {
        if x >= 0 {
            return x;
        }
        let frac = u32::from(frac.min(15));
        // Table position of -x in Q16: (-x / 2^frac) * 64 * 2^16.
        let pos = (u64::from(x.unsigned_abs()) << (STEPS_PER_UNIT_LOG2 + 16)) >> frac;
        let idx = (pos >> 16) as usize;
        let t = (pos & 0xFFFF) as i64;
        let q15 = match (ELU_TABLE.get(idx), ELU_TABLE.get(idx + 1)) {
            (Some(&a), Some(&b)) if idx < LAST => {
                let (a, b) = (i64::from(a), i64::from(b));
                a + super::super::round_shift((b - a) * t, 16)
            }
            _ => i64::from(i16::MIN),
        };
        super::super::sat_i16(super::super::round_shift(q15 << frac, 15))
    }

    /// The refactor must not move a single output bit: every i16 input, every
    /// supported format, and a few unsupported ones (clamped to Q15).
    #[test]
    fn elu_is_bit_identical_to_the_pre_refactor_version() {
        for frac in (0u8..=16).chain([17, 31, 200, 255]) {
            for x in i16::MIN..=i16::MAX {
                assert_eq!(
                    elu_q(x, frac),
                    elu_q_before_refactor(x, frac),
                    "x {x}, frac {frac}"
                );
            }
        }
    }

    /// What `elu_q`'s 32-bit arithmetic relies on: neighbouring entries
    /// differ by less than 2^10 (the largest step is about 32768 / 64).
    #[test]
    fn table_steps_are_small() {
        for w in ELU_TABLE.windows(2) {
            let step = (i32::from(w[1]) - i32::from(w[0])).abs();
            assert!(step < 1 << 10, "{w:?}");
        }
    }

    #[test]
    fn expm1_is_exact_at_zero_and_minus_one_past_the_table() {
        assert_eq!(expm1_neg_q31(0), 0);
        assert_eq!(expm1_neg_q31((LAST as u64) << 16), -(1 << 31));
        assert_eq!(expm1_neg_q31(u64::MAX), -(1 << 31));
        let mut prev = 0;
        for pos in (0..(LAST as u64 + 2) << 16).step_by(977) {
            let v = expm1_neg_q31(pos);
            assert!((-(1 << 31)..=0).contains(&v) && v <= prev, "pos {pos}");
            prev = v;
        }
    }

    #[test]
    fn elu_is_monotonic() {
        for frac in [4u8, 10, 15] {
            let mut prev = elu_q(i16::MIN, frac);
            for x in i16::MIN + 1..=i16::MAX {
                let y = elu_q(x, frac);
                assert!(y >= prev, "frac {frac}, x {x}");
                prev = y;
            }
        }
    }
}
