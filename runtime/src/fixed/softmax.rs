//! Integer softmax for gates computed by the network (OMG: a gating MLP
//! gives k <= 8 logits, their softmax blends k experts). The result is in
//! Q16 like every other gate and sums to exactly 65536, so equal experts
//! still blend to themselves.
//!
//! `exp` comes from the ELU table (through `super::elu::expm1_neg_q31`),
//! so there is one table in flash, and the whole computation is integer
//! arithmetic on u64: the same bits on every target.
//!
//! Arithmetic, for `k` logits `x_i` in Q`frac` (specified bit-exactly in
//! `docs/fixed-point.md`, "Softmax gate"):
//!
//! ```text
//! m     = index of the first largest logit
//! d_i   = x_m - x_i                               (0..=65535, Q`frac`)
//! e_i   = 2^31 + expm1_neg_q31((d_i << 22) >> frac)   exp(-d_i) in Q31, exact
//!                                                 at d = 0, 0 at d >= 16
//! S     = sum e_i                                 (2^31..=2^34)
//! c_i   = floor((e_i * 2^17 + S) / (2 S))         i != m: 65536 e_i / S, half up
//! c_m   = 65536 - sum_{i != m} c_i                the remainder
//! ```
//!
//! **Error bound** (Q16 LSB, against `65536 * softmax(x / 2^frac)` exact).
//! Write `E_i = exp(-d_i)` (so `E_m = 1`), `e_i = E_i (1 + h_i) + a_i` in real
//! units, with `0 <= h_i <= eta = e^(1/64) / (8 * 64^2) = 3.10e-5` from
//! linear interpolation of a convex function (one-sided!) and
//! `|a_i| <= alpha = 2^-16` from rounding the Q15 entries (past the table,
//! `a_i = -E_i`, `|a_i| < 1.2e-7`); `h_m = a_m = 0`. With `S = sum E`,
//! `S' = sum e >= 1`, `p_i = E_i / S`:
//!
//! ```text
//! e_i/S' - p_i = [(h_i E_i + a_i)(S - E_i) - E_i sum_{j != i}(h_j E_j + a_j)] / (S S')
//! ```
//!
//! The `h` parts have the same sign and partly cancel: at most
//! `eta p_i (1 - p_i) S/S' <= eta/4 * 1.0002` (`S/S' <= 1/(1 - 7 alpha)`).
//! The `a` parts: for `m`, at most `(k-1) alpha`; for `i != m` (where
//! `p_i <= 1/2`), at most `alpha (1 + (k-3) p_i) <= alpha max(1, (k-1)/2)`.
//! Rounding adds 1/2 to each `c_i`, `i != m`; `c_m` takes their rounding,
//! `(k-1)/2` at most, but none of its own. In Q16 LSB (`alpha` = 1 LSB,
//! `eta/4` = 0.508 LSB) both cases are covered by
//!
//! ```text
//! |c_i - 65536 p_i| <= 1.5 (k - 1) + 0.51   Q16 LSB   (11.0 for k = 8)
//! ```
//!
//! and `tests::error_is_within_the_derived_bound` checks it. The worst
//! error measured there is 10.06 LSB for k = 8 (1.5e-4 of the total), on
//! the maximum's coefficient with the seven others tied at one gap: their
//! entry and division roundings all have one sign then, so the bound is
//! nearly reached. The Q15 table's rounding dominates it, not the method.
//!
//! Every coefficient is in `0..=65536`: `c_i <= 65536` as `e_i <= S`, and
//! `c_m = 65536 e_m / S - (the others' rounding) >= 65536/8 - 7/2 > 0`
//! since `e_m = 2^31 >= S/k`.

use super::elu::{expm1_neg_q31, POS_SHIFT};
use crate::error::{Error, Result};
use core::num::NonZeroU64;

use super::div_short;

/// Most logits a softmax gate takes.
pub const MAX_LOGITS: usize = 8;

/// Q16 one: the coefficients' sum.
const ONE: i32 = 1 << 16;

/// Q16 softmax of `logits` (Q`frac` numbers, `frac <= 15`), written to
/// `coefs[..logits.len()]`: every coefficient >= 0 and they sum to exactly 65536.
///
/// The first largest logit's coefficient takes the rounding remainder, so
/// the result is invariant under adding a constant to every logit (without
/// saturating) and permutes with the logits, except among tied maxima.
/// `coefs[logits.len()..]` is left untouched.
///
/// # Errors
///
/// Checked in this order, before anything is written:
/// * [`Error::LengthMismatch`] `{ expected: MAX_LOGITS, found: logits.len() }`
///   if `logits` is empty or longer than [`MAX_LOGITS`];
/// * [`Error::LengthMismatch`] `{ expected: logits.len(), found: coefs.len() }`
///   if `coefs` is shorter than `logits`;
/// * [`Error::UnsupportedParameter`] `{ layer: 255 }` if `frac > 15`.
pub fn softmax_q16(logits: &[i16], frac: u8, coefs: &mut [i32]) -> Result<()> {
    let k = logits.len();
    if k == 0 || k > MAX_LOGITS {
        return Err(Error::LengthMismatch {
            expected: MAX_LOGITS as u32,
            found: u32::try_from(k).unwrap_or(u32::MAX),
        });
    }
    if coefs.len() < k {
        return Err(Error::LengthMismatch {
            expected: k as u32,
            found: u32::try_from(coefs.len()).unwrap_or(u32::MAX),
        });
    }
    if frac > 15 {
        return Err(Error::UnsupportedParameter { layer: 255 });
    }

    // First maximum: `max_by_key` would return the last one on ties.
    let mut m = 0;
    let mut max = i16::MIN;
    for (i, &x) in logits.iter().enumerate() {
        if i == 0 || x > max {
            (m, max) = (i, x);
        }
    }

    // exp(-d_i) in Q31 in [0, 2^31]; exactly 2^31 for the maximum, so the
    // sum is at least 2^31 and at most 8 * 2^31 = 2^34.
    let mut e = [0u64; MAX_LOGITS];
    let mut sum = 0u64;
    for (ei, &x) in e.iter_mut().zip(logits) {
        // max >= x, so the difference is in 0..=65535 and exact in i32.
        let d = (i32::from(max) - i32::from(x)).unsigned_abs();
        // Exact: frac <= 15 < POS_SHIFT, so no bit of d is shifted out.
        let pos = (u64::from(d) << POS_SHIFT) >> frac;
        *ei = ((1i64 << 31) + expm1_neg_q31(pos)).unsigned_abs();
        sum += *ei;
    }
    // The maximum alone contributes 2^31, so the fallback is never taken.
    let two_sum = NonZeroU64::new(2 * sum).unwrap_or(NonZeroU64::MIN);

    // c_i = round_half_up(65536 e_i / S) = floor((2 * 65536 e_i + S) / (2 S));
    // e_i * 2^17 <= 2^48, far from overflowing u64.
    let mut rest = ONE;
    for (i, (c, &ei)) in coefs.iter_mut().zip(&e).take(k).enumerate() {
        if i != m {
            // <= 65536 since e_i <= S, so the conversion cannot fail.
            *c = i32::try_from(div_short((ei << 17) + sum, two_sum)).unwrap_or(ONE);
            rest -= *c;
        }
    }
    // The others' exact shares sum to at most (1 - 1/k) of 65536, plus at
    // most k/2 of rounding: `rest` stays well above zero.
    if let Some(c) = coefs.get_mut(m) {
        *c = rest;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// `65536 * softmax(x / 2^frac)` in f64.
    fn exact(logits: &[i16], frac: u8) -> Vec<f64> {
        let scale = f64::from(1u32 << frac);
        let max = logits.iter().copied().max().unwrap_or(0);
        let w: Vec<f64> = logits
            .iter()
            .map(|&x| ((f64::from(x) - f64::from(max)) / scale).exp())
            .collect();
        let s: f64 = w.iter().sum();
        w.iter().map(|v| 65536.0 * v / s).collect()
    }

    /// The bound derived in the module documentation, in Q16 LSB.
    fn bound(k: usize) -> f64 {
        1.5 * (k as f64 - 1.0) + 0.51
    }

    fn run(logits: &[i16], frac: u8) -> Vec<i32> {
        let mut c = [i32::MIN; MAX_LOGITS];
        softmax_q16(logits, frac, &mut c).unwrap();
        c[..logits.len()].to_vec()
    }

    /// Checks sum, range and bound for one vector; returns its worst error.
    fn check(logits: &[i16], frac: u8) -> f64 {
        let c = run(logits, frac);
        assert_eq!(c.iter().sum::<i32>(), 65536, "{logits:?} Q{frac}: {c:?}");
        assert!(
            c.iter().all(|v| (0..=65536).contains(v)),
            "{logits:?} Q{frac}: {c:?}"
        );
        let worst = c
            .iter()
            .zip(exact(logits, frac))
            .map(|(&v, x)| (f64::from(v) - x).abs())
            .fold(0.0, f64::max);
        assert!(
            worst <= bound(logits.len()) + 1e-6,
            "{logits:?} Q{frac}: {c:?}, error {worst} > {}",
            bound(logits.len())
        );
        worst
    }

    /// xorshift64*: a fixed, dependency-free stream so the worst case found
    /// is reproducible.
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
        }
        fn below(&mut self, n: u64) -> u64 {
            self.next() % n
        }
    }

    /// Random vectors whose spread is itself random (2^0 to 2^16 LSB), so
    /// that every format sees gaps from nothing to far past the table's 16,
    /// plus the adversarial ones. Worst error found (printed with
    /// `--nocapture`), Q16 LSB, for k = 1..=8: 0, 1.44, 2.82, 4.28, 5.78,
    /// 7.24, 8.70, 10.06 (bound 1.5 (k-1) + 0.51: 0.51, 2.01, ..., 11.01).
    /// From k = 3 on the worst is all the others tied at one gap (e.g. k = 8:
    /// `[0, -405 x 7]` in Q6, gap 6.33); the random vectors alone reach 6.90.
    #[test]
    fn error_is_within_the_derived_bound() {
        let mut rng = Rng(0x9E37_79B9_7F4A_7C15);
        let mut worst = vec![(-1.0f64, Vec::new(), 0u8); MAX_LOGITS + 1];
        let mut note = |k: usize, logits: &[i16], frac: u8, err: f64| {
            if err > worst[k].0 {
                worst[k] = (err, logits.to_vec(), frac);
            }
        };
        for k in 1..=MAX_LOGITS {
            for frac in 0u8..=15 {
                for _ in 0..10_000 {
                    let spread = 1i32 << rng.below(17);
                    let centre = rng.below(65536) as i32 - 32768;
                    let v: Vec<i16> = (0..k)
                        .map(|_| {
                            let off = rng.below(spread as u64) as i32 - spread / 2;
                            (centre + off).clamp(-32768, 32767) as i16
                        })
                        .collect();
                    note(k, &v, frac, check(&v, frac));
                }
                for v in adversarial(k, frac) {
                    note(k, &v, frac, check(&v, frac));
                }
            }
        }
        for (k, (err, v, frac)) in worst.iter().enumerate().skip(1) {
            println!(
                "k = {k}: worst {err:.3} LSB (bound {:.2}) at {v:?} Q{frac}",
                bound(k)
            );
        }
    }

    /// Equal logits, one huge gap, the i16 extremes, ties, and gaps at and
    /// around the table's knots (multiples of 1/64) and its end (16).
    fn adversarial(k: usize, frac: u8) -> Vec<Vec<i16>> {
        let one = 1i32 << frac;
        let mut out = vec![
            vec![0; k],
            vec![i16::MAX; k],
            vec![i16::MIN; k],
            (0..k)
                .map(|i| if i == 0 { i16::MAX } else { i16::MIN })
                .collect(),
            (0..k)
                .map(|i| if i + 1 == k { i16::MAX } else { i16::MIN })
                .collect(),
            (0..k)
                .map(|i| if i % 2 == 0 { i16::MAX } else { i16::MIN })
                .collect(),
            (0..k).map(|i| if i < 2 { 100 } else { 99 }).collect(),
            (0..k).map(|i| (i as i16) * 7).collect(),
        ];
        // All the others tied at one gap below the maximum: their entry
        // rounding and their division rounding then add up in the
        // maximum's coefficient, the worst case of the bound. The gap sweeps
        // 0..=16 (past the table's end) in 4096 steps or every LSB.
        let step = (16 * one / 4096).max(1);
        for gap in (0..=16 * one + 1)
            .step_by(step as usize)
            .chain([one / 128, 3 * one / 128])
        {
            out.push(
                (0..k)
                    .map(|i| if i == 0 { 0 } else { (-gap).max(-32768) as i16 })
                    .collect(),
            );
        }
        out
    }

    #[test]
    fn one_logit_gets_everything() {
        for frac in 0u8..=15 {
            for x in [i16::MIN, -1, 0, 1, i16::MAX] {
                assert_eq!(run(&[x], frac), vec![65536]);
            }
        }
    }

    #[test]
    fn equal_logits_split_evenly_with_the_remainder_first() {
        for k in 1..=MAX_LOGITS {
            let c = run(&vec![1234; k], 10);
            let share = ((65536.0 / k as f64) + 0.5).floor() as i32;
            assert!(c[1..].iter().all(|&v| v == share), "{c:?}");
            assert_eq!(c[0], 65536 - share * (k as i32 - 1));
        }
    }

    #[test]
    fn errors() {
        let mut c = [0i32; 16];
        assert_eq!(
            softmax_q16(&[], 8, &mut c),
            Err(Error::LengthMismatch {
                expected: 8,
                found: 0
            })
        );
        assert_eq!(
            softmax_q16(&[0; 9], 8, &mut c),
            Err(Error::LengthMismatch {
                expected: 8,
                found: 9
            })
        );
        assert_eq!(
            softmax_q16(&[0; 5], 8, &mut c[..4]),
            Err(Error::LengthMismatch {
                expected: 5,
                found: 4
            })
        );
        for frac in [16u8, 17, 255] {
            assert_eq!(
                softmax_q16(&[0; 3], frac, &mut c),
                Err(Error::UnsupportedParameter { layer: 255 })
            );
        }
        // Length errors come first, and nothing is written on error.
        let mut c = [7i32; 4];
        assert!(matches!(
            softmax_q16(&[0; 9], 99, &mut c),
            Err(Error::LengthMismatch { .. })
        ));
        assert_eq!(c, [7; 4]);
        // Longer coefficient slices are fine; the tail is left alone.
        let mut c = [7i32; 6];
        softmax_q16(&[0; 4], 15, &mut c).unwrap();
        assert_eq!(c, [16384, 16384, 16384, 16384, 7, 7]);
    }

    fn logits_and_frac() -> impl Strategy<Value = (Vec<i16>, u8)> {
        (
            prop::collection::vec(-4096i16..=4096, 1..=MAX_LOGITS),
            0u8..=15,
        )
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]

        #[test]
        fn shifting_every_logit_changes_nothing(
            (v, frac) in logits_and_frac(),
            shift in -28000i16..=28000,
        ) {
            let shifted: Vec<i16> = v.iter().map(|&x| x + shift).collect();
            prop_assert_eq!(run(&v, frac), run(&shifted, frac));
        }

        #[test]
        fn permuting_logits_permutes_coefficients(
            (v, frac) in logits_and_frac(),
            seed in any::<u64>(),
        ) {
            // A Fisher-Yates shuffle driven by the seed.
            let mut rng = Rng(seed | 1);
            let mut perm: Vec<usize> = (0..v.len()).collect();
            for i in (1..perm.len()).rev() {
                perm.swap(i, rng.below(i as u64 + 1) as usize);
            }
            let pv: Vec<i16> = perm.iter().map(|&p| v[p]).collect();
            let (c, pc) = (run(&v, frac), run(&pv, frac));
            let max = *v.iter().max().unwrap();
            let tied = v.iter().filter(|&&x| x == max).count() > 1;
            for (i, &p) in perm.iter().enumerate() {
                if !(tied && v[p] == max) {
                    prop_assert_eq!(pc[i], c[p]);
                }
            }
            // Among tied maxima only the remainder moves: to the first one.
            if tied {
                let share = c[v.iter().rposition(|&x| x == max).unwrap()];
                let first = pv.iter().position(|&x| x == max).unwrap();
                for (i, &x) in pv.iter().enumerate() {
                    if x == max && i != first {
                        prop_assert_eq!(pc[i], share);
                    }
                }
            }
        }

        #[test]
        fn sums_to_one_and_stays_in_range_for_any_input(
            v in prop::collection::vec(any::<i16>(), 1..=MAX_LOGITS),
            frac in 0u8..=15,
        ) {
            check(&v, frac);
        }
    }
}
