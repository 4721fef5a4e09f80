//! Joint angle -> servo pulse -> PWM duty cycle, through a per-channel
//! calibration.

use embedded_hal::pwm::SetDutyCycle;

/// How one servo channel maps angles to pulses.
///
/// Angles are in whatever unit the pose uses (degrees or radians); the
/// calibration's angles are in the same unit. `angle_min` gives
/// `pulse_min_ns` and `angle_max` gives `pulse_max_ns`, linearly in between
/// (the other way round when `reversed`). Angles are first clamped to the
/// mechanical limits `[limit_min, limit_max]`.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ServoCalibration {
    /// Pulse width at `angle_min` (at `angle_max` when reversed), ns.
    pub pulse_min_ns: u32,
    /// Pulse width at `angle_max` (at `angle_min` when reversed), ns.
    pub pulse_max_ns: u32,
    /// PWM period, ns (20 ms for hobby servos).
    pub period_ns: u32,
    /// Angle that maps to `pulse_min_ns`.
    pub angle_min: f32,
    /// Angle that maps to `pulse_max_ns`.
    pub angle_max: f32,
    /// Servo mounted the other way round: `angle_min` maps to `pulse_max_ns`.
    pub reversed: bool,
    /// Smallest angle the mechanism allows (within the angle range).
    pub limit_min: f32,
    /// Largest angle the mechanism allows (within the angle range).
    pub limit_max: f32,
}

/// Why a calibration is refused.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum CalibrationError {
    /// An angle or limit is NaN or infinite.
    NonFiniteAngle,
    /// `angle_min` is not below `angle_max`.
    EmptyAngleRange,
    /// The limits are reversed or outside the angle range.
    BadLimits,
    /// `pulse_min_ns` is not below `pulse_max_ns`, or `pulse_max_ns`
    /// exceeds the period, or the period is zero.
    BadPulseRange,
}

impl core::fmt::Display for CalibrationError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            CalibrationError::NonFiniteAngle => "servo calibration has a NaN or infinite angle",
            CalibrationError::EmptyAngleRange => {
                "servo calibration: angle_min must be below angle_max"
            }
            CalibrationError::BadLimits => {
                "servo calibration: limits reversed or outside the angle range"
            }
            CalibrationError::BadPulseRange => {
                "servo calibration: need 0 < pulse_min < pulse_max <= period"
            }
        })
    }
}

impl core::error::Error for CalibrationError {}

/// What happened to an angle on its way to the servo.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum AngleFate {
    /// Written as given.
    Exact,
    /// Outside the limits (or infinite): clamped to the nearest limit.
    Clamped,
    /// NaN: the previous duty was kept (the limits' midpoint before any).
    Held,
}

impl ServoCalibration {
    /// A typical hobby servo: 1000-2000 us over -90..90 degrees, 20 ms
    /// period, full range allowed.
    pub const HOBBY_DEGREES: ServoCalibration = ServoCalibration {
        pulse_min_ns: 1_000_000,
        pulse_max_ns: 2_000_000,
        period_ns: 20_000_000,
        angle_min: -90.0,
        angle_max: 90.0,
        reversed: false,
        limit_min: -90.0,
        limit_max: 90.0,
    };

    /// Checks the calibration.
    pub fn validate(&self) -> Result<(), CalibrationError> {
        let angles = [
            self.angle_min,
            self.angle_max,
            self.limit_min,
            self.limit_max,
        ];
        if angles.iter().any(|a| !a.is_finite()) {
            return Err(CalibrationError::NonFiniteAngle);
        }
        if self.angle_min >= self.angle_max {
            return Err(CalibrationError::EmptyAngleRange);
        }
        if self.limit_min > self.limit_max
            || self.limit_min < self.angle_min
            || self.limit_max > self.angle_max
        {
            return Err(CalibrationError::BadLimits);
        }
        if self.pulse_min_ns == 0
            || self.pulse_min_ns >= self.pulse_max_ns
            || self.pulse_max_ns > self.period_ns
        {
            return Err(CalibrationError::BadPulseRange);
        }
        Ok(())
    }

    /// Pulse width (ns) for a finite angle already within the limits.
    fn pulse_for(&self, angle: f32) -> u32 {
        let span = self.angle_max - self.angle_min;
        let mut t = ((angle - self.angle_min) / span).clamp(0.0, 1.0);
        if self.reversed {
            t = 1.0 - t;
        }
        let width = (self.pulse_max_ns - self.pulse_min_ns) as f32;
        // `as u32` saturates; t is in [0, 1] so this is in [0, width].
        let offset = (t * width + 0.5) as u32;
        self.pulse_min_ns
            .saturating_add(offset)
            .min(self.pulse_max_ns)
    }

    /// Pulse widths (ns) at the two limits, smaller first: every pulse this
    /// calibration produces lies within.
    pub fn pulse_range(&self) -> (u32, u32) {
        let (a, b) = (
            self.pulse_for(self.limit_min),
            self.pulse_for(self.limit_max),
        );
        (a.min(b), a.max(b))
    }

    /// The duty cycle for a pulse of `pulse_ns`, out of `max_duty`, rounded
    /// to nearest.
    pub fn duty_for_pulse(&self, pulse_ns: u32, max_duty: u16) -> u16 {
        let period = u64::from(self.period_ns.max(1));
        let d = (u64::from(pulse_ns) * u64::from(max_duty) + period / 2) / period;
        u16::try_from(d).unwrap_or(max_duty).min(max_duty)
    }

    /// Duty cycles at the two limits, smaller first: the calibrated range.
    pub fn duty_range(&self, max_duty: u16) -> (u16, u16) {
        let (lo, hi) = self.pulse_range();
        (
            self.duty_for_pulse(lo, max_duty),
            self.duty_for_pulse(hi, max_duty),
        )
    }

    /// Clamps `angle` to the limits: `None` for NaN.
    pub fn clamp(&self, angle: f32) -> Option<(f32, AngleFate)> {
        if angle.is_nan() {
            None
        } else if angle < self.limit_min {
            Some((self.limit_min, AngleFate::Clamped))
        } else if angle > self.limit_max {
            Some((self.limit_max, AngleFate::Clamped))
        } else {
            Some((angle, AngleFate::Exact))
        }
    }

    /// The duty for `angle` (NaN gives the limits' midpoint; use
    /// [`Servo::set_angle`] to hold the previous position instead).
    pub fn duty(&self, angle: f32, max_duty: u16) -> u16 {
        let a = match self.clamp(angle) {
            Some((a, _)) => a,
            None => self.limit_min + (self.limit_max - self.limit_min) * 0.5,
        };
        self.duty_for_pulse(self.pulse_for(a), max_duty)
    }
}

/// One servo: a PWM channel, its calibration and its last duty.
#[derive(Debug)]
pub struct Servo<S> {
    pwm: S,
    calibration: ServoCalibration,
    /// Index of the angle in the pose that drives this servo.
    joint: usize,
    last_duty: Option<u16>,
}

impl<S: SetDutyCycle> Servo<S> {
    /// A servo on `pwm`, driven by `pose[joint]`; refuses a bad calibration.
    pub fn new(
        pwm: S,
        joint: usize,
        calibration: ServoCalibration,
    ) -> Result<Self, CalibrationError> {
        calibration.validate()?;
        Ok(Servo {
            pwm,
            calibration,
            joint,
            last_duty: None,
        })
    }

    /// Index of the pose angle this servo follows.
    pub fn joint(&self) -> usize {
        self.joint
    }

    /// The calibration.
    pub fn calibration(&self) -> &ServoCalibration {
        &self.calibration
    }

    /// The last duty written, if any.
    pub fn last_duty(&self) -> Option<u16> {
        self.last_duty
    }

    /// Moves to `angle`: clamps it to the limits, holds the previous duty
    /// on NaN, writes the duty. Returns the duty written and what happened
    /// to the angle.
    pub fn set_angle(&mut self, angle: f32) -> Result<(u16, AngleFate), S::Error> {
        let max = self.pwm.max_duty_cycle();
        let (duty, fate) = match (self.calibration.clamp(angle), self.last_duty) {
            (Some((a, fate)), _) => (
                self.calibration
                    .duty_for_pulse(self.calibration.pulse_for(a), max),
                fate,
            ),
            (None, Some(last)) => (last, AngleFate::Held),
            (None, None) => (self.calibration.duty(f32::NAN, max), AngleFate::Held),
        };
        self.pwm.set_duty_cycle(duty)?;
        self.last_duty = Some(duty);
        Ok((duty, fate))
    }

    /// Gives the PWM channel back.
    pub fn release(self) -> S {
        self.pwm
    }
}
