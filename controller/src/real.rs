//! The scalar the controller loop is written over.
//!
//! One loop, two precisions: the device runs it in `f32`, the host's float
//! reference in `f64` (and `f32`), so fixed and float differ only in the
//! network and in rounding, never in the glue. `f32`'s functions are
//! [`crate::f32_math`]'s: `f32` operations only (the Cortex-M4F's FPU has no
//! `f64`), none fused, each IEEE-exact, so the same inputs give the same bits
//! on x86-64 and on the device. `f64`'s (the host's reference) are libm's.

use core::fmt::Debug;
use core::ops::{Add, AddAssign, Div, Mul, Neg, Sub, SubAssign};

use crate::f32_math;

/// A real number type the controller can run on (`f32` or `f64`).
pub trait Real:
    Copy
    + Debug
    + Default
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + AddAssign
    + SubAssign
{
    /// 0.
    const ZERO: Self;
    /// 1.
    const ONE: Self;
    /// A constant, rounded to this type (IEEE round to nearest).
    fn lit(v: f64) -> Self;
    /// From an `f32` (exact for both types).
    fn from_f32(v: f32) -> Self;
    /// To `f32` (rounded to nearest).
    fn to_f32(self) -> f32;
    /// To `f64` (exact for both types).
    fn to_f64(self) -> f64;
    /// Correctly rounded square root; NaN below zero.
    fn sqrt(self) -> Self;
    /// Sine of radians.
    fn sin(self) -> Self;
    /// Cosine of radians.
    fn cos(self) -> Self;
    /// Arccosine, radians in `[0, pi]`; NaN outside `[-1, 1]`.
    fn acos(self) -> Self;
    /// Four-quadrant arctangent of `self / x`, radians in `[-pi, pi]`.
    fn atan2(self, x: Self) -> Self;
    /// `self` to the power `e`, for `self >= 0`.
    fn powf(self, e: Self) -> Self;
    /// A count, exactly (below 2^24).
    fn from_u32(n: u32) -> Self;
    /// Largest integer not above `self`.
    fn floor(self) -> Self;
    /// Neither NaN nor infinite.
    fn is_finite(self) -> bool;

    /// `(sin self, cos self)`, the same bits as [`Real::sin`] and
    /// [`Real::cos`] (one reduction where the type can share it).
    fn sin_cos(self) -> (Self, Self) {
        (self.sin(), self.cos())
    }

    /// Absolute value.
    fn abs(self) -> Self {
        if self < Self::ZERO {
            -self
        } else {
            self
        }
    }

    /// `self` limited to `[lo, hi]`; NaN becomes `lo`.
    fn clamp_to(self, lo: Self, hi: Self) -> Self {
        if self >= lo {
            if self > hi {
                hi
            } else {
                self
            }
        } else {
            lo
        }
    }

    /// `self * (1 - a) + b * a` (GLSL `mix`, the demo's blend).
    fn mix(self, b: Self, a: Self) -> Self {
        self * (Self::ONE - a) + b * a
    }
}

impl Real for f32 {
    const ZERO: Self = 0.0;
    const ONE: Self = 1.0;
    fn lit(v: f64) -> Self {
        v as f32
    }
    fn from_f32(v: f32) -> Self {
        v
    }
    fn to_f32(self) -> f32 {
        self
    }
    fn to_f64(self) -> f64 {
        f64::from(self)
    }
    fn sqrt(self) -> Self {
        f32_math::sqrt(self)
    }
    fn sin(self) -> Self {
        f32_math::sin_cos(self).0
    }
    fn cos(self) -> Self {
        f32_math::sin_cos(self).1
    }
    fn sin_cos(self) -> (Self, Self) {
        f32_math::sin_cos(self)
    }
    fn acos(self) -> Self {
        f32_math::acos(self)
    }
    fn atan2(self, x: Self) -> Self {
        f32_math::atan2(self, x)
    }
    fn powf(self, e: Self) -> Self {
        f32_math::powf(self, e)
    }
    fn from_u32(n: u32) -> Self {
        n as f32
    }
    fn floor(self) -> Self {
        libm::floorf(self)
    }
    fn is_finite(self) -> bool {
        f32::is_finite(self)
    }
}

impl Real for f64 {
    const ZERO: Self = 0.0;
    const ONE: Self = 1.0;
    fn lit(v: f64) -> Self {
        v
    }
    fn from_f32(v: f32) -> Self {
        f64::from(v)
    }
    fn to_f32(self) -> f32 {
        self as f32
    }
    fn to_f64(self) -> f64 {
        self
    }
    fn sqrt(self) -> Self {
        libm::sqrt(self)
    }
    fn sin(self) -> Self {
        libm::sin(self)
    }
    fn cos(self) -> Self {
        libm::cos(self)
    }
    fn acos(self) -> Self {
        libm::acos(self)
    }
    fn atan2(self, x: Self) -> Self {
        libm::atan2(self, x)
    }
    fn powf(self, e: Self) -> Self {
        libm::pow(self, e)
    }
    fn from_u32(n: u32) -> Self {
        f64::from(n)
    }
    fn floor(self) -> Self {
        libm::floor(self)
    }
    fn is_finite(self) -> bool {
        f64::is_finite(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clamp_and_mix() {
        assert_eq!(f32::NAN.clamp_to(0.0, 1.0), 0.0);
        assert_eq!(2.0f32.clamp_to(0.0, 1.0), 1.0);
        assert_eq!((-2.0f64).clamp_to(0.0, 1.0), 0.0);
        assert_eq!(1.0f32.mix(3.0, 0.5), 2.0);
        assert_eq!((-3.0f64).abs(), 3.0);
    }

    #[test]
    fn f32_is_accurate_where_the_loop_needs_it() {
        // A root turn of 0.01 rad per frame must not be distorted: this is
        // why the loop does not use a coarse approximation library.
        let a = 0.01f32;
        assert!((Real::sin(a) - 0.009_999_833).abs() < 1e-9);
        assert_eq!(Real::sqrt(2.0f32), core::f32::consts::SQRT_2);
        assert!((Real::atan2(1.0f32, 1.0) - core::f32::consts::FRAC_PI_4).abs() < 1e-7);
        assert!((Real::powf(0.5f32, 0.25) - 0.840_896_4).abs() < 1e-7);
    }
}
