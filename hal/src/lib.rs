#![doc = include_str!("../README.md")]
#![cfg_attr(not(test), no_std)]
#![deny(missing_docs)]
#![cfg_attr(
    not(test),
    deny(clippy::unwrap_used, clippy::expect_used, clippy::panic)
)]

pub mod driver;
pub mod servo;

pub use driver::{Clock, FrameDriver, FrameError, FrameReport};
pub use servo::{AngleFate, CalibrationError, Servo, ServoCalibration};

#[cfg(test)]
mod tests;
