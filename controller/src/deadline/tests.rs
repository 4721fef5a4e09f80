//! Host tests of the deadline policy: pin transactions with
//! embedded-hal-mock, the policy's invariants with proptest.

use std::cell::Cell;
use std::rc::Rc;

use embedded_hal::digital::{ErrorType, OutputPin};
use embedded_hal_mock::eh1::digital::{Mock as PinMock, State, Transaction as PinTx};
use proptest::prelude::*;

use super::*;

/// Simulated ticks, advanced by the "frames".
#[derive(Clone, Default)]
struct SimTicks(Rc<Cell<u64>>);

impl SimTicks {
    fn advance(&self, t: u64) {
        self.0.set(self.0.get() + t);
    }
}

impl TickSource for SimTicks {
    fn now_ticks(&mut self) -> u64 {
        self.0.get()
    }
}

/// A pin that records its level and its writes (for the properties).
#[derive(Clone, Default)]
struct RecPin {
    high: Rc<Cell<bool>>,
    writes: Rc<Cell<u32>>,
}

impl ErrorType for RecPin {
    type Error = core::convert::Infallible;
}

impl OutputPin for RecPin {
    fn set_low(&mut self) -> core::result::Result<(), Self::Error> {
        self.high.set(false);
        self.writes.set(self.writes.get() + 1);
        Ok(())
    }
    fn set_high(&mut self) -> core::result::Result<(), Self::Error> {
        self.high.set(true);
        self.writes.set(self.writes.get() + 1);
        Ok(())
    }
}

fn budget(ticks: u32, policy: OverrunPolicy) -> DeadlineConfig {
    DeadlineConfig::new(ticks, policy).unwrap()
}

#[test]
fn budgets_are_validated() {
    assert_eq!(
        FrameBudget::from_ticks(0),
        Err(Error::BadBudget { ticks: 0 })
    );
    assert_eq!(FrameBudget::from_ticks(7).unwrap().ticks(), 7);
    // 40 instructions a tick, rounded down: never more generous than asked.
    assert_eq!(
        FrameBudget::from_instructions(4_000_039, 40)
            .unwrap()
            .ticks(),
        100_000
    );
    assert!(FrameBudget::from_instructions(39, 40).is_err());
    assert!(FrameBudget::from_instructions(100, 0).is_err());
    assert!(FrameBudget::from_instructions(u64::MAX, 1).is_err());
    assert_eq!(OverrunPolicy::from_u32(1), Ok(OverrunPolicy::HoldNext));
    assert_eq!(
        OverrunPolicy::from_u32(2),
        Err(Error::BadPolicy { value: 2 })
    );
    for p in [OverrunPolicy::Report, OverrunPolicy::HoldNext] {
        assert_eq!(OverrunPolicy::from_u32(p.to_u32()), Ok(p));
    }
}

/// Budget 100 ticks, hold-next: frames of 50, 150 (overrun), then the held
/// frame (2 ticks), 100 (exactly the budget: on time), 101 (overrun), held.
/// The pin goes low at start, high after each overrun, low after the next
/// frame on time: exactly those writes, no others.
#[test]
fn hold_next_skips_one_frame_after_each_overrun_and_drives_the_pin() {
    let clock = SimTicks::default();
    let mut pin = PinMock::new(&[
        PinTx::set(State::Low),
        PinTx::set(State::High),
        PinTx::set(State::Low),
        PinTx::set(State::High),
        PinTx::set(State::Low),
    ]);
    let mut d = Deadline::new(
        budget(100, OverrunPolicy::HoldNext),
        pin.clone(),
        clock.clone(),
    )
    .unwrap();
    // One cost per frame; a held frame ignores its own (0 here).
    let costs = [50u64, 150, 0, 100, 101];
    let mut seen = Vec::new();
    for c in costs {
        let f = d.frame(|action| {
            // A held frame does next to nothing.
            clock.advance(if action == FrameAction::Hold { 2 } else { c });
            action
        });
        f.pin.unwrap();
        seen.push((f.result, f.outcome.ticks, f.outcome.overrun));
    }
    use FrameAction::{Hold, Infer};
    assert_eq!(
        seen,
        vec![
            (Infer, 50, false),
            (Infer, 150, true),
            (Hold, 2, false),
            (Infer, 100, false),
            (Infer, 101, true),
        ]
    );
    // The frame after the last overrun will be held.
    let last = d.frame(|a| a);
    assert_eq!(last.result, Hold);
    assert!(last.outcome.held && !last.outcome.overrun);
    assert_eq!((d.frames(), d.overruns(), d.held()), (6, 2, 2));
    pin.done();
}

/// Report only: every frame infers; overruns are counted and the pin
/// follows them (two overruns in a row: one high write).
#[test]
fn report_only_never_skips() {
    let clock = SimTicks::default();
    let mut pin = PinMock::new(&[
        PinTx::set(State::Low),
        PinTx::set(State::High),
        PinTx::set(State::Low),
    ]);
    let mut d = Deadline::new(
        budget(10, OverrunPolicy::Report),
        pin.clone(),
        clock.clone(),
    )
    .unwrap();
    for c in [11u64, 12, 3, 4] {
        let f = d.frame(|a| {
            clock.advance(c);
            a
        });
        assert_eq!(f.result, FrameAction::Infer);
        assert_eq!(f.outcome.next, FrameAction::Infer);
    }
    assert_eq!((d.overruns(), d.held()), (2, 0));
    pin.done();
}

/// No budget: frames are timed, nothing overruns, the pin is only driven
/// low once.
#[test]
fn no_budget_times_frames_and_never_overruns() {
    let clock = SimTicks::default();
    let mut pin = PinMock::new(&[PinTx::set(State::Low)]);
    let mut d = Deadline::new(DeadlineConfig::NONE, pin.clone(), clock.clone()).unwrap();
    let f = d.frame(|_| clock.advance(u64::MAX / 2));
    assert_eq!(f.outcome.ticks, u32::MAX);
    assert!(!f.outcome.overrun);
    assert_eq!(d.overruns(), 0);
    pin.done();
}

/// A budget below even a held frame's cost: every frame overruns, yet
/// every other frame still infers.
#[test]
fn a_held_frame_that_overruns_is_not_held_again() {
    let clock = SimTicks::default();
    let mut d = Deadline::new(
        budget(1, OverrunPolicy::HoldNext),
        RecPin::default(),
        clock.clone(),
    )
    .unwrap();
    let actions: Vec<FrameAction> = (0..6)
        .map(|_| {
            d.frame(|a| {
                clock.advance(5);
                a
            })
            .result
        })
        .collect();
    use FrameAction::{Hold, Infer};
    assert_eq!(actions, vec![Infer, Hold, Infer, Hold, Infer, Hold]);
    assert_eq!((d.overruns(), d.held()), (6, 3));
}

/// A pin that fails keeps the frame's result and is tried again next frame.
#[test]
fn a_failing_pin_keeps_the_result_and_is_retried() {
    let clock = SimTicks::default();
    let err = embedded_hal_mock::eh1::MockError::Io(std::io::ErrorKind::Other);
    let mut pin = PinMock::new(&[
        PinTx::set(State::Low),
        PinTx::set(State::High).with_error(err),
        PinTx::set(State::High),
    ]);
    let mut d =
        Deadline::new(budget(5, OverrunPolicy::Report), pin.clone(), clock.clone()).unwrap();
    let f = d.frame(|_| {
        clock.advance(9);
        42
    });
    assert_eq!(f.result, 42);
    assert!(f.outcome.overrun && f.pin.is_err() && !d.pin_high());
    let f = d.frame(|_| clock.advance(9));
    assert!(f.pin.is_ok() && d.pin_high());
    pin.done();
}

proptest! {
    /// For any frame costs, budget and policy: a frame overruns iff it
    /// took more ticks than the budget; under hold-next a frame is held
    /// iff the one before was inferred and overran; the pin's level after
    /// each frame is that frame's overrun (a held frame that overran does
    /// not cause another hold); the counters add up.
    #[test]
    fn policy_invariants(
        costs in proptest::collection::vec(0u64..300, 1..80),
        held_cost in 0u64..300,
        ticks in 1u32..250,
        hold in any::<bool>(),
    ) {
        let policy = if hold { OverrunPolicy::HoldNext } else { OverrunPolicy::Report };
        let clock = SimTicks::default();
        let pin = RecPin::default();
        let mut d = Deadline::new(budget(ticks, policy), pin.clone(), clock.clone()).unwrap();
        let (mut prev_overrun, mut prev_held) = (false, false);
        let (mut overruns, mut held) = (0, 0);
        for &c in &costs {
            let f = d.frame(|a| {
                clock.advance(if a == FrameAction::Hold { held_cost } else { c });
                a
            });
            let o = f.outcome;
            let spent = if o.held { held_cost } else { c };
            prop_assert_eq!(o.ticks as u64, spent);
            prop_assert_eq!(o.overrun, spent > u64::from(ticks));
            prop_assert_eq!(o.held, hold && prev_overrun && !prev_held);
            prop_assert_eq!(f.result == FrameAction::Hold, o.held);
            prop_assert_eq!(pin.high.get(), o.overrun);
            overruns += u32::from(o.overrun);
            held += u32::from(o.held);
            prev_overrun = o.overrun;
            prev_held = o.held;
        }
        prop_assert_eq!(d.overruns(), overruns);
        prop_assert_eq!(d.held(), held);
        prop_assert_eq!(d.frames(), costs.len() as u32);
        // Writes only on changes (plus the initial low).
        prop_assert!(pin.writes.get() <= 1 + 2 * overruns);
    }
}
