//! Frame deadlines: a budget per frame, every frame timed against it, and
//! a documented policy for the frames that overrun it.
//!
//! [`Deadline`] wraps each frame: it reads a [`TickSource`] before and
//! after, compares the elapsed ticks with the [`FrameBudget`], counts and
//! reports overruns (a [`FrameOutcome`], and a status pin driven through
//! `embedded_hal::digital::OutputPin`), and tells the caller what the next
//! frame may do ([`FrameAction`]) according to the [`OverrunPolicy`].
//! [`crate::Locomotion::frame`] is the one place that says what a held
//! frame does to the controller's state (nothing: see
//! [`OverrunPolicy::HoldNext`]). `docs/deadline.md` has the whole design.

use core::num::NonZeroU32;

use embedded_hal::digital::OutputPin;

use crate::error::{Error, Result};

/// A monotonic tick counter (SysTick with its wraps counted, a cycle
/// counter, a timer). embedded-hal 1.0 has no clock trait.
pub trait TickSource {
    /// Ticks since an arbitrary origin; never decreases.
    fn now_ticks(&mut self) -> u64;
}

/// The time one frame may take, in ticks of the [`TickSource`] (non-zero).
/// A frame overruns when it takes strictly more ticks than this.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FrameBudget(NonZeroU32);

impl FrameBudget {
    /// A budget of `ticks`; [`Error::BadBudget`] for 0 (no frame could
    /// meet it: use no budget instead).
    pub const fn from_ticks(ticks: u32) -> Result<Self> {
        match NonZeroU32::new(ticks) {
            Some(t) => Ok(FrameBudget(t)),
            None => Err(Error::BadBudget { ticks }),
        }
    }

    /// A budget of `instructions` on a timer counting one tick every
    /// `instructions_per_tick` instructions (40 for SysTick under QEMU's
    /// `-icount shift=0`), rounded down to whole ticks so the budget is
    /// never more generous than asked; [`Error::BadBudget`] when that is 0
    /// ticks or more than `u32::MAX`.
    pub fn from_instructions(instructions: u64, instructions_per_tick: u32) -> Result<Self> {
        let ticks = instructions
            .checked_div(u64::from(instructions_per_tick))
            .unwrap_or(0);
        let ticks = u32::try_from(ticks).map_err(|_| Error::BadBudget { ticks: u32::MAX })?;
        Self::from_ticks(ticks)
    }

    /// The budget in ticks.
    pub const fn ticks(self) -> u32 {
        self.0.get()
    }
}

/// What happens after a frame overran its budget. Every overrun is
/// counted and reported whatever the policy.
#[derive(Clone, Copy, Debug, Default, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum OverrunPolicy {
    /// Report only: the next frame runs its inference as usual.
    #[default]
    Report,
    /// Hold the last pose and skip the next frame's inference, so the
    /// frame after an overrun is short and the schedule catches up. The
    /// held frame changes nothing in the controller's state: the pose
    /// (its `frame` counter included), the phase, the trajectory, the
    /// joint velocities and the smoothed command targets stay as they
    /// were, and the held frame's command is not applied (not even
    /// checked). Time stands still for the character for one frame; the
    /// next inferred frame continues from exactly where the overrunning
    /// frame left it. The held frame is timed and reported too, but never
    /// causes another hold (with a budget below even a held frame's cost,
    /// holding again would stop the character for good): at least every
    /// other frame infers.
    HoldNext,
}

impl OverrunPolicy {
    /// The policy's number on the wire (0 report, 1 hold next).
    pub const fn to_u32(self) -> u32 {
        match self {
            OverrunPolicy::Report => 0,
            OverrunPolicy::HoldNext => 1,
        }
    }

    /// The policy numbered `v` ([`OverrunPolicy::to_u32`]), or
    /// [`Error::BadPolicy`].
    pub const fn from_u32(v: u32) -> Result<Self> {
        match v {
            0 => Ok(OverrunPolicy::Report),
            1 => Ok(OverrunPolicy::HoldNext),
            _ => Err(Error::BadPolicy { value: v }),
        }
    }
}

/// The deadline part of a controller's configuration.
#[derive(Clone, Copy, Debug, Default, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct DeadlineConfig {
    /// The frame budget; `None`: no deadline (frames are still timed,
    /// none ever overruns, the pin stays low).
    pub budget: Option<FrameBudget>,
    /// What an overrun does to the next frame.
    pub policy: OverrunPolicy,
}

impl DeadlineConfig {
    /// No deadline.
    pub const NONE: DeadlineConfig = DeadlineConfig {
        budget: None,
        policy: OverrunPolicy::Report,
    };

    /// A budget of `ticks` (validated by [`FrameBudget::from_ticks`]) and
    /// `policy`.
    pub const fn new(ticks: u32, policy: OverrunPolicy) -> Result<Self> {
        match FrameBudget::from_ticks(ticks) {
            Ok(b) => Ok(DeadlineConfig {
                budget: Some(b),
                policy,
            }),
            Err(e) => Err(e),
        }
    }
}

/// What a frame may do, decided before it starts.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum FrameAction {
    /// Run the inference as usual.
    Infer,
    /// Skip the inference and hold the last pose
    /// ([`OverrunPolicy::HoldNext`] after an overrun).
    Hold,
}

/// What one timed frame did.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FrameOutcome {
    /// Ticks the frame took (saturated to `u32`).
    pub ticks: u32,
    /// It took more than the budget.
    pub overrun: bool,
    /// It was a held frame (no inference).
    pub held: bool,
    /// What the next frame will do.
    pub next: FrameAction,
}

/// A frame's result, what the deadline made of it, and whether the status
/// pin could be driven (the frame's result is kept either way; a pin that
/// failed is tried again at the next frame).
#[derive(Debug)]
pub struct TimedFrame<R, E> {
    /// What the frame's closure returned.
    pub result: R,
    /// Its timing and the policy's decision.
    pub outcome: FrameOutcome,
    /// The status pin's write, when one was needed.
    pub pin: core::result::Result<(), E>,
}

/// Times frames against a [`DeadlineConfig`], applies its policy and
/// drives a status pin: high from the end of a frame that overran to the
/// end of the next frame that met its budget (written only when that
/// changes).
pub struct Deadline<P, T> {
    config: DeadlineConfig,
    pin: P,
    clock: T,
    next: FrameAction,
    pin_high: bool,
    frames: u32,
    overruns: u32,
    held: u32,
}

impl<P: OutputPin, T: TickSource> Deadline<P, T> {
    /// A deadline over `pin` (driven low here) and `clock`.
    pub fn new(
        config: DeadlineConfig,
        mut pin: P,
        clock: T,
    ) -> core::result::Result<Self, P::Error> {
        pin.set_low()?;
        Ok(Deadline {
            config,
            pin,
            clock,
            next: FrameAction::Infer,
            pin_high: false,
            frames: 0,
            overruns: 0,
            held: 0,
        })
    }

    /// Runs one frame: `frame` is called with what it may do (infer, or
    /// hold after an overrun under [`OverrunPolicy::HoldNext`]) and timed.
    pub fn frame<R>(&mut self, frame: impl FnOnce(FrameAction) -> R) -> TimedFrame<R, P::Error> {
        let action = self.next;
        let t0 = self.clock.now_ticks();
        let result = frame(action);
        let t1 = self.clock.now_ticks();
        let ticks = u32::try_from(t1.saturating_sub(t0)).unwrap_or(u32::MAX);
        let overrun = self.config.budget.is_some_and(|b| ticks > b.ticks());
        let held = action == FrameAction::Hold;
        // A held frame that overran is not followed by another hold: that
        // could hold forever, and at least every other frame must infer.
        self.next = if overrun && !held && self.config.policy == OverrunPolicy::HoldNext {
            FrameAction::Hold
        } else {
            FrameAction::Infer
        };
        self.frames = self.frames.saturating_add(1);
        self.overruns = self.overruns.saturating_add(u32::from(overrun));
        self.held = self.held.saturating_add(u32::from(held));
        let pin = if overrun == self.pin_high {
            Ok(())
        } else if overrun {
            self.pin.set_high()
        } else {
            self.pin.set_low()
        };
        if pin.is_ok() {
            self.pin_high = overrun;
        }
        TimedFrame {
            result,
            outcome: FrameOutcome {
                ticks,
                overrun,
                held,
                next: self.next,
            },
            pin,
        }
    }

    /// The configuration.
    pub fn config(&self) -> DeadlineConfig {
        self.config
    }

    /// Frames timed so far.
    pub fn frames(&self) -> u32 {
        self.frames
    }

    /// Frames that overran.
    pub fn overruns(&self) -> u32 {
        self.overruns
    }

    /// Frames held (inference skipped).
    pub fn held(&self) -> u32 {
        self.held
    }

    /// Whether the status pin was last driven high.
    pub fn pin_high(&self) -> bool {
        self.pin_high
    }

    /// The status pin (e.g. to read an output register back).
    pub fn pin(&self) -> &P {
        &self.pin
    }

    /// Gives the pin and the clock back.
    pub fn release(self) -> (P, T) {
        (self.pin, self.clock)
    }
}

#[cfg(test)]
mod tests;
