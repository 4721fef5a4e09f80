//! The device loop's `f32` functions, in `f32` only.
//!
//! libm's `f32` functions compute in `f64` inside (`rem_pio2f`, `k_sinf`,
//! `powf`, ...), which the Cortex-M4F's single-precision FPU does in
//! software: most of the loop's time and `.text` went there. These use the
//! FPU's own operations only (add, multiply, divide, `vsqrt`), all IEEE
//! correctly rounded, in a fixed order and never fused, so x86-64 and the
//! Cortex-M4F give the same bits; the QEMU controller run checks it.
//!
//! Polynomials are Cephes' (S. L. Moshier, the `f32` library), over the
//! same reductions: `sin`/`cos` by octant (Cody-Waite in three parts up to
//! [`CODY_WAITE_LIMIT`], an exact integer reduction beyond), `atan2` to
//! `[0, tan(pi/8)]`, `acos` through `asin` on `[0, 1/2]`, `powf` as
//! `exp2(e log2 x)` with the series of `ln((1+s)/(1-s))` and of `2^f`.
//! The error of each against `f64` over dense grids is bounded in the
//! tests below and listed in `docs/controller.md`.

use core::f32::consts::{FRAC_PI_2, FRAC_PI_4, LOG2_E, PI};

/// Below this `|x|` (radians) `sin`/`cos` reduce by Cody-Waite: the three
/// parts of pi/4 are exact multiples for octant counts up to 2^14.
pub const CODY_WAITE_LIMIT: f32 = 8192.0;

/// Bits of 2/pi from the first after the point, 32 per word (Payne-Hanek
/// reduction of the largest `f32`, 2^127, reads up to bit 166).
const TWO_OVER_PI: [u32; 7] = [
    0xa2f9_836e,
    0x4e44_1529,
    0xfc27_57d1,
    0xf534_ddc0,
    0xdb62_9599,
    0x3c43_9041,
    0xfe51_63ab,
];

fn abs(x: f32) -> f32 {
    f32::from_bits(x.to_bits() & 0x7fff_ffff)
}

fn negative(x: f32) -> bool {
    x.to_bits() >> 31 != 0
}

/// Correctly rounded square root: the FPU's `vsqrt` on the device, libm's
/// (SSE `sqrtss` on x86-64, also correctly rounded) on the host. libm's
/// own `sqrtf` on Cortex-M is an integer loop.
#[cfg(all(target_arch = "arm", target_abi = "eabihf"))]
pub fn sqrt(x: f32) -> f32 {
    let r: u32;
    // SAFETY: FPU instructions on s0, saved and restored on the stack
    // (eabihf targets have the FPU). Through core registers because Rust's
    // `sreg` operands need the `vfp2` feature, which the single-precision
    // M4F target does not name.
    unsafe {
        core::arch::asm!(
            "vpush {{s0}}",
            "vmov s0, {x}",
            "vsqrt.f32 s0, s0",
            "vmov {r}, s0",
            "vpop {{s0}}",
            x = in(reg) x.to_bits(),
            r = lateout(reg) r,
            options(pure, nomem, preserves_flags)
        );
    }
    f32::from_bits(r)
}

/// Correctly rounded square root (see the device version).
#[cfg(not(all(target_arch = "arm", target_abi = "eabihf")))]
pub fn sqrt(x: f32) -> f32 {
    libm::sqrtf(x)
}

/// `(j, z)`: `|x| = j pi/4 + z` with `j` even (mod 8) and `|z| <= pi/4`
/// (about), for finite `|x|`.
fn reduce_octant(ax: f32) -> (u32, f32) {
    if ax <= CODY_WAITE_LIMIT {
        // pi/4 = DP1 + DP2 + DP3; DP1 and DP2 have few enough bits that
        // `y * DP1` and `y * DP2` are exact below the limit.
        const DP1: f32 = 0.785_156_25;
        #[allow(clippy::excessive_precision)] // the exact value of the part
        const DP2: f32 = 2.418_756_484_985_351_562_5e-4;
        const DP3: f32 = 3.774_895e-8;
        let mut j = (ax * (4.0 / PI)) as u32;
        let mut y = j as f32;
        if j & 1 != 0 {
            j += 1;
            y += 1.0;
        }
        (j & 7, ((ax - y * DP1) - y * DP2) - y * DP3)
    } else {
        reduce_octant_exact(ax)
    }
}

/// Payne-Hanek: `|x| 4/pi mod 8` in integers from 64 bits of 2/pi (good
/// to 2^-37), of which 31 fraction bits are kept: about 4e-10 radians off.
/// `|x| = m 2^e`, `m` the 24-bit significand; bits of 2/pi before bit
/// `e - 1` only add multiples of 8.
fn reduce_octant_exact(ax: f32) -> (u32, f32) {
    let bits = ax.to_bits();
    let m = u128::from((bits & 0x007f_ffff) | 0x0080_0000);
    let e = ((bits >> 23) & 0xff) as i32 - 150;
    let s = e - 1; // first bit of 2/pi kept (1 = just after the point)
    let word = |k: usize| u128::from(TWO_OVER_PI.get(k).copied().unwrap_or(0));
    let w = if s <= 0 {
        // The window starts before the point: leading zeros.
        let top = (word(0) << 32) | word(1);
        (top >> (1 - s).clamp(0, 64)) as u64
    } else {
        let k = ((s - 1) / 32) as usize;
        let o = (s - 1) % 32;
        let v = (word(k) << 64) | (word(k + 1) << 32) | word(k + 2);
        ((v << o) >> 32) as u64
    };
    // |x| 4/pi = m w 2^-61 (mod 8).
    let p = m * u128::from(w);
    let mut j = ((p >> 61) & 7) as u32;
    let mut f = (p & ((1u128 << 61) - 1)) as i64;
    if j & 1 != 0 {
        j = (j + 1) & 7;
        f -= 1i64 << 61;
    }
    // 31 bits of the fraction are plenty for an absolute error of 1e-7, and
    // i32 -> f32 is one FPU instruction (i64 -> f32 is a library routine).
    let z = (f >> 30) as i32 as f32 * (FRAC_PI_4 / (1u64 << 31) as f32);
    (j, z)
}

/// `(sin x, cos x)`, from one reduction. NaN for NaN and infinities.
pub fn sin_cos(x: f32) -> (f32, f32) {
    let ax = abs(x);
    if !ax.is_finite() {
        return (f32::NAN, f32::NAN);
    }
    let (j, z) = reduce_octant(ax);
    let zz = z * z;
    let s = ((-1.951_529_6e-4 * zz + 8.332_161e-3) * zz - 1.666_665_5e-1) * zz * z + z;
    let c =
        ((2.443_315_7e-5 * zz - 1.388_731_6e-3) * zz + 4.166_664_6e-2) * zz * zz - 0.5 * zz + 1.0;
    // Octant j (even) of |x|: 0 -> (s, c), 2 -> (c, -s), 4 -> (-s, -c),
    // 6 -> (-c, s).
    let (sin, cos) = match j {
        0 => (s, c),
        2 => (c, -s),
        4 => (-s, -c),
        _ => (-c, s),
    };
    (if negative(x) { -sin } else { sin }, cos)
}

/// `atan t` for `0 <= t <= tan(pi/8)`.
fn atan_small(t: f32) -> f32 {
    let z = t * t;
    (((8.053_744_5e-2 * z - 1.387_768_6e-1) * z + 1.997_771_1e-1) * z - 3.333_295e-1) * z * t + t
}

/// Four-quadrant arctangent of `y / x`, IEEE's signs and infinities.
#[inline(never)] // called from several places of the loop: one copy
pub fn atan2(y: f32, x: f32) -> f32 {
    if x.is_nan() || y.is_nan() {
        return f32::NAN;
    }
    let (ax, ay) = (abs(x), abs(y));
    let swap = ay > ax;
    let (num, den) = if swap { (ax, ay) } else { (ay, ax) };
    let t = if num == den {
        // Also both zero (0) and both infinite (1).
        if num == 0.0 {
            0.0
        } else {
            1.0
        }
    } else {
        num / den
    };
    let a = if t > core::f32::consts::SQRT_2 - 1.0 {
        FRAC_PI_4 + atan_small((t - 1.0) / (t + 1.0))
    } else {
        atan_small(t)
    };
    let a = if swap { FRAC_PI_2 - a } else { a };
    let a = if negative(x) { PI - a } else { a };
    if negative(y) {
        -a
    } else {
        a
    }
}

/// `asin x` for `0 <= x <= 1/2`, `z = x^2`.
fn asin_small(x: f32, z: f32) -> f32 {
    ((((4.216_32e-2 * z + 2.418_131e-2) * z + 4.547_002_6e-2) * z + 7.495_300_3e-2) * z
        + 1.666_675_2e-1)
        * z
        * x
        + x
}

/// Arccosine in `[0, pi]`; NaN outside `[-1, 1]`.
pub fn acos(x: f32) -> f32 {
    let ax = abs(x);
    if ax.is_nan() || ax > 1.0 {
        return f32::NAN;
    }
    if ax > 0.5 {
        // acos |x| = 2 asin sqrt((1 - |x|) / 2), no cancellation near 1.
        let z = 0.5 * (1.0 - ax);
        let a = 2.0 * asin_small(sqrt(z), z);
        if negative(x) {
            PI - a
        } else {
            a
        }
    } else {
        FRAC_PI_2 - asin_small(x, x * x)
    }
}

/// `log2 x` for finite `x > 0` (subnormals included).
fn log2(x: f32) -> f32 {
    let (mut bits, mut k) = (x.to_bits(), 0i32);
    if bits < 0x0080_0000 {
        bits = (x * 16_777_216.0).to_bits(); // 2^24: subnormal to normal
        k = -24;
    }
    // x = 2^k m with m in [sqrt(1/2), sqrt(2)): the significand's bits
    // from 0x3504f3 up belong to the next power.
    let shifted = bits.wrapping_add(0x3f80_0000 - 0x3f35_04f3);
    k += (shifted >> 23) as i32 - 127;
    let m = f32::from_bits((shifted & 0x007f_ffff) + 0x3f35_04f3);
    // ln m = 2 atanh s, s = (m - 1) / (m + 1) in [-0.172, 0.172].
    let s = (m - 1.0) / (m + 1.0);
    let z = s * s;
    let ln = s * (2.0 + z * (2.0 / 3.0 + z * (0.4 + z * (2.0 / 7.0 + z * (2.0 / 9.0)))));
    k as f32 + ln * LOG2_E
}

/// `2^y`; 0 below -126 (no subnormal results), infinity above 128.
fn exp2(y: f32) -> f32 {
    if y.is_nan() {
        return f32::NAN;
    }
    if y < -126.0 {
        return 0.0;
    }
    if y > 128.0 {
        return f32::INFINITY;
    }
    let k = libm::floorf(y + 0.5);
    let f = y - k; // exact, in [-1/2, 1/2]
                   // 2^f = sum (f ln 2)^n / n!, to n = 7 (remainder below 6e-9).
    const C: [f32; 7] = [
        core::f32::consts::LN_2,
        0.240_226_5,
        5.550_411e-2,
        9.618_129e-3,
        1.333_355_8e-3,
        1.540_353e-4,
        1.525_273_4e-5,
    ];
    let p = C.iter().rev().fold(0.0f32, |acc, &c| acc * f + c);
    let r = 1.0 + f * p;
    // r in [0.70, 1.42]; scale by 2^k in two steps so that k = 128 and
    // k = -126 (r < 1) stay representable on the way.
    let k = k as i32;
    let half = k / 2;
    let scale = |n: i32| f32::from_bits(((n + 127) as u32) << 23);
    r * scale(half) * scale(k - half)
}

/// `x^e` for `x >= 0` (NaN below): `exp2(e log2 x)`; `0^e` is 0 for
/// `e > 0`, 1 for `e = 0`, infinity for `e < 0`.
pub fn powf(x: f32, e: f32) -> f32 {
    if x.is_nan() || e.is_nan() || (negative(x) && x != 0.0) {
        return f32::NAN;
    }
    if x == 0.0 || x == f32::INFINITY {
        let grows = (x == 0.0) == (e < 0.0);
        return if e == 0.0 {
            1.0
        } else if grows {
            f32::INFINITY
        } else {
            0.0
        };
    }
    if e == 0.0 || x == 1.0 {
        return 1.0;
    }
    exp2(e * log2(x))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// `n + 1` evenly spaced `f32` points on `[a, b]`.
    fn grid(a: f64, b: f64, n: u32) -> impl Iterator<Item = f32> {
        (0..=n).map(move |i| (a + (b - a) * f64::from(i) / f64::from(n)) as f32)
    }

    /// Largest absolute error of `f` against `g` (in f64) over `xs`.
    fn max_abs(
        xs: impl Iterator<Item = f32>,
        f: impl Fn(f32) -> f32,
        g: impl Fn(f64) -> f64,
    ) -> f64 {
        xs.map(|x| (f64::from(f(x)) - g(f64::from(x))).abs())
            .fold(0.0, f64::max)
    }

    // The bounds below are the measured maxima rounded up (printed with
    // `-- --nocapture`); docs/controller.md lists them.

    #[test]
    fn sin_cos_error_against_f64() {
        let near = grid(-8.0, 8.0, 2_000_000);
        let es = max_abs(near, |x| sin_cos(x).0, f64::sin);
        let ec = max_abs(grid(-8.0, 8.0, 2_000_000), |x| sin_cos(x).1, f64::cos);
        let far = max_abs(grid(-8192.0, 8192.0, 2_000_000), |x| sin_cos(x).0, f64::sin);
        let huge = max_abs(grid(8192.0, 1e30, 2_000_000), |x| sin_cos(x).1, f64::cos);
        println!("sin {es:e} cos {ec:e} |x|<=8192 {far:e} beyond {huge:e}");
        assert!(es < 1.2e-7 && ec < 1.2e-7, "{es:e} {ec:e}");
        assert!(far < 1.2e-7 && huge < 1.2e-7, "{far:e} {huge:e}");
    }

    #[test]
    fn sin_is_exact_near_zero_and_sin_cos_edge_cases() {
        for x in [1e-30f32, -1e-7, 1e-4, 0.01] {
            let want = f64::from(x).sin();
            assert!((f64::from(sin_cos(x).0) - want).abs() <= want.abs() * 1.2e-7);
        }
        assert!(sin_cos(f32::INFINITY).0.is_nan() && sin_cos(f32::NAN).1.is_nan());
        assert_eq!(sin_cos(0.0), (0.0, 1.0));
        assert_eq!(sin_cos(-0.0).0.to_bits(), (-0.0f32).to_bits());
        let (s, c) = sin_cos(f32::MAX);
        let (ws, wc) = (f64::from(f32::MAX).sin(), f64::from(f32::MAX).cos());
        assert!((f64::from(s) - ws).abs() < 1.2e-7 && (f64::from(c) - wc).abs() < 1.2e-7);
    }

    #[test]
    fn atan2_error_against_f64() {
        let mut worst = 0.0f64;
        for a in grid(-4.0, 4.0, 4_000_000) {
            // Every direction, at radii from 1e-3 to 1e3.
            for r in [1e-3f32, 1.0, 7.5, 1e3] {
                let (y, x) = (f64::from(a).sin() as f32 * r, f64::from(a).cos() as f32 * r);
                let want = f64::from(y).atan2(f64::from(x));
                worst = worst.max((f64::from(atan2(y, x)) - want).abs());
            }
        }
        println!("atan2 {worst:e}");
        assert!(worst < 3e-7, "{worst:e}");
    }

    #[test]
    fn atan2_edge_cases_follow_ieee() {
        assert_eq!(atan2(0.0, 0.0), 0.0);
        assert_eq!(atan2(-0.0, 0.0).to_bits(), (-0.0f32).to_bits());
        assert_eq!(atan2(0.0, -0.0), PI);
        assert_eq!(atan2(-0.0, -1.0), -PI);
        assert_eq!(atan2(1.0, 0.0), FRAC_PI_2);
        assert_eq!(atan2(f32::INFINITY, f32::INFINITY), FRAC_PI_4);
        assert_eq!(atan2(1.0, f32::NEG_INFINITY), PI);
        assert!(atan2(f32::NAN, 1.0).is_nan());
    }

    #[test]
    fn acos_error_against_f64() {
        let e = max_abs(grid(-1.0, 1.0, 4_000_000), acos, f64::acos);
        println!("acos {e:e}");
        assert!(e < 3.2e-7, "{e:e}");
        assert_eq!(acos(1.0), 0.0);
        assert_eq!(acos(-1.0), PI);
        assert!(acos(1.000_001).is_nan() && acos(f32::NAN).is_nan());
    }

    #[test]
    fn powf_error_against_f64() {
        // Relative: the loop's bases are in (0, 1], exponents in [0.25, 2].
        let mut worst = 0.0f64;
        for x in grid(1e-6, 1.0, 1_000_000) {
            for e in [0.25f32, 0.5, 0.75, 1.0, 1.37, 2.0] {
                let want = f64::from(x).powf(f64::from(e));
                worst = worst.max((f64::from(powf(x, e)) - want).abs() / want);
            }
        }
        println!("powf relative {worst:e}");
        assert!(worst < 1.5e-6, "{worst:e}");
    }

    #[test]
    fn powf_edge_cases() {
        assert_eq!(powf(0.0, 0.5), 0.0);
        assert_eq!(powf(0.0, 0.0), 1.0);
        assert_eq!(powf(0.0, -1.0), f32::INFINITY);
        assert_eq!(powf(1.0, 7.0), 1.0);
        assert_eq!(powf(4.0, 0.5), 2.0);
        assert!(powf(-1.0, 2.0).is_nan());
        assert_eq!(powf(2.0, 200.0), f32::INFINITY);
        assert_eq!(powf(0.5, 200.0), 0.0);
        let tiny = f32::from_bits(1); // subnormal base
        let want = f64::from(tiny).powf(0.25);
        assert!((f64::from(powf(tiny, 0.25)) - want).abs() / want < 1e-6);
    }

    #[test]
    fn sqrt_is_correctly_rounded() {
        for x in grid(0.0, 100.0, 100_000) {
            assert_eq!(sqrt(x), f64::from(x).sqrt() as f32, "{x}");
        }
        assert!(sqrt(-1.0).is_nan());
    }

    proptest! {
        #[test]
        fn any_angle_gives_a_bounded_sine(x in proptest::num::f32::NORMAL) {
            let (s, c) = sin_cos(x);
            let (ws, wc) = (f64::from(x).sin(), f64::from(x).cos());
            prop_assert!((f64::from(s) - ws).abs() < 1.2e-7, "{} {} {}", x, s, ws);
            prop_assert!((f64::from(c) - wc).abs() < 1.2e-7, "{} {} {}", x, c, wc);
        }

        #[test]
        fn any_direction_gives_its_angle(y in -1e6f32..1e6, x in -1e6f32..1e6) {
            let want = f64::from(y).atan2(f64::from(x));
            prop_assert!((f64::from(atan2(y, x)) - want).abs() < 3e-7);
        }
    }
}
