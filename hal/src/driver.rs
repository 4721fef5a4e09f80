//! The frame loop: latency pin around the inference, servo outputs, and
//! deadline-based pacing with `DelayNs`.

use embedded_hal::delay::DelayNs;
use embedded_hal::digital::OutputPin;
use embedded_hal::pwm::SetDutyCycle;

use crate::servo::{AngleFate, Servo};

/// A monotonic time source in nanoseconds (a cycle counter, a timer).
/// embedded-hal 1.0 has no clock trait; `DelayNs` alone can only wait, so
/// the driver reads the time to wait exactly the rest of the period.
pub trait Clock {
    /// Nanoseconds since an arbitrary origin; never decreases.
    fn now_ns(&mut self) -> u64;
}

/// Why a frame failed. Whatever failed, the latency pin was driven low
/// again if the pin allowed it.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum FrameError<PinE, PwmE, InferE> {
    /// The latency pin could not be set.
    Pin(PinE),
    /// A servo's PWM channel refused its duty.
    Pwm {
        /// Index of the servo in the driver.
        servo: usize,
        /// The channel's error.
        error: PwmE,
    },
    /// The inference failed (no servo was moved).
    Inference(InferE),
    /// The pose has no angle for a servo's joint (no servo was moved).
    PoseTooShort {
        /// Joint index the servo needs.
        joint: usize,
        /// Length of the pose.
        len: usize,
    },
}

/// What one frame did.
#[derive(Clone, Copy, Debug, Default, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FrameReport {
    /// Time with the latency pin high (the inference), ns.
    pub inference_ns: u64,
    /// Time from the frame's start to the end of the servo writes, ns.
    pub busy_ns: u64,
    /// Time slept to the next frame's start, ns.
    pub slept_ns: u64,
    /// The frame ran past its period (no sleep; the schedule restarts).
    pub overrun: bool,
    /// Angles clamped to their limits this frame.
    pub clamped: u8,
    /// NaN angles whose servo held its position this frame.
    pub held: u8,
}

/// Runs frames at a fixed period: pin high, inference, pin low, servos,
/// sleep until the next frame is due.
pub struct FrameDriver<D, P, C, S, const N: usize> {
    delay: D,
    pin: P,
    clock: C,
    servos: [Servo<S>; N],
    period_ns: u32,
    next_start: Option<u64>,
    frames: u32,
    overruns: u32,
}

impl<D, P, C, S, const N: usize> FrameDriver<D, P, C, S, N>
where
    D: DelayNs,
    P: OutputPin,
    C: Clock,
    S: SetDutyCycle,
{
    /// A driver running one frame every `period_ns` (non-zero; e.g.
    /// 16,666,667 for 60 Hz).
    pub fn new(delay: D, pin: P, clock: C, servos: [Servo<S>; N], period_ns: u32) -> Self {
        FrameDriver {
            delay,
            pin,
            clock,
            servos,
            period_ns: period_ns.max(1),
            next_start: None,
            frames: 0,
            overruns: 0,
        }
    }

    /// The frame period, ns.
    pub fn period_ns(&self) -> u32 {
        self.period_ns
    }

    /// Frames run so far.
    pub fn frames(&self) -> u32 {
        self.frames
    }

    /// Frames that overran their period.
    pub fn overruns(&self) -> u32 {
        self.overruns
    }

    /// The servos.
    pub fn servos(&self) -> &[Servo<S>; N] {
        &self.servos
    }

    /// Runs one frame. `infer` computes the pose (it is called with the
    /// latency pin high); each servo then follows `pose[servo.joint()]`.
    /// Finally sleeps until one period after this frame's scheduled start.
    pub fn frame<'a, E>(
        &mut self,
        infer: impl FnOnce() -> Result<&'a [f32], E>,
    ) -> Result<FrameReport, FrameError<P::Error, S::Error, E>> {
        let start = self.clock.now_ns();
        let scheduled = *self.next_start.get_or_insert(start);
        self.pin.set_high().map_err(FrameError::Pin)?;
        let pose = infer();
        let pin_low = self.pin.set_low();
        let inference_end = self.clock.now_ns();
        pin_low.map_err(FrameError::Pin)?;
        let pose = pose.map_err(FrameError::Inference)?;
        let mut report = FrameReport {
            inference_ns: inference_end.saturating_sub(start),
            ..FrameReport::default()
        };
        // Check every joint first so a short pose moves no servo at all.
        for s in &self.servos {
            if s.joint() >= pose.len() {
                return Err(FrameError::PoseTooShort {
                    joint: s.joint(),
                    len: pose.len(),
                });
            }
        }
        for (i, s) in self.servos.iter_mut().enumerate() {
            let angle = pose.get(s.joint()).copied().unwrap_or(f32::NAN);
            let (_, fate) = s
                .set_angle(angle)
                .map_err(|error| FrameError::Pwm { servo: i, error })?;
            match fate {
                AngleFate::Exact => {}
                AngleFate::Clamped => report.clamped = report.clamped.saturating_add(1),
                AngleFate::Held => report.held = report.held.saturating_add(1),
            }
        }
        let now = self.clock.now_ns();
        report.busy_ns = now.saturating_sub(start);
        let due = scheduled.saturating_add(u64::from(self.period_ns));
        if now < due {
            // Less than one period (a u32) by construction.
            let wait = u32::try_from(due - now).unwrap_or(self.period_ns);
            self.delay.delay_ns(wait);
            report.slept_ns = u64::from(wait);
            self.next_start = Some(due);
        } else {
            report.overrun = true;
            self.overruns = self.overruns.saturating_add(1);
            // Do not try to catch up with a burst of frames: restart the
            // schedule from now.
            self.next_start = Some(now);
        }
        self.frames = self.frames.saturating_add(1);
        Ok(report)
    }

    /// Gives the peripherals back.
    pub fn release(self) -> (D, P, C, [Servo<S>; N]) {
        (self.delay, self.pin, self.clock, self.servos)
    }
}
