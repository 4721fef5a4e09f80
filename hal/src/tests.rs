//! Host tests with embedded-hal-mock and proptest.

#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    clippy::indexing_slicing
)]

use std::cell::{Cell, RefCell};
use std::rc::Rc;

use embedded_hal::delay::DelayNs;
use embedded_hal::pwm::{ErrorType, SetDutyCycle};
use embedded_hal_mock::eh1::delay::{CheckedDelay, Transaction as DelayTx};
use embedded_hal_mock::eh1::digital::{Mock as PinMock, State, Transaction as PinTx};
use embedded_hal_mock::eh1::pwm::{Mock as PwmMock, Transaction as PwmTx};
use proptest::prelude::*;

use super::*;

/// Simulated time shared by the clock, the "inference" and the delay.
#[derive(Clone, Default)]
struct SimTime(Rc<Cell<u64>>);

impl SimTime {
    fn advance(&self, ns: u64) {
        self.0.set(self.0.get() + ns);
    }
}

impl Clock for SimTime {
    fn now_ns(&mut self) -> u64 {
        self.0.get()
    }
}

/// A delay that advances simulated time and records each call.
#[derive(Clone, Default)]
struct SimDelay {
    time: SimTime,
    calls: Rc<RefCell<Vec<u32>>>,
}

impl DelayNs for SimDelay {
    fn delay_ns(&mut self, ns: u32) {
        self.calls.borrow_mut().push(ns);
        self.time.advance(u64::from(ns));
    }
}

/// A PWM channel that records duties (for property tests).
#[derive(Clone, Default)]
struct RecPwm {
    max: u16,
    duties: Rc<RefCell<Vec<u16>>>,
}

impl ErrorType for RecPwm {
    type Error = core::convert::Infallible;
}

impl SetDutyCycle for RecPwm {
    fn max_duty_cycle(&self) -> u16 {
        self.max
    }
    fn set_duty_cycle(&mut self, duty: u16) -> Result<(), Self::Error> {
        self.duties.borrow_mut().push(duty);
        Ok(())
    }
}

const PERIOD: u32 = 10_000_000; // 100 Hz

fn pin_frames(n: usize) -> Vec<PinTx> {
    (0..n)
        .flat_map(|_| [PinTx::set(State::High), PinTx::set(State::Low)])
        .collect()
}

#[test]
fn pin_is_high_exactly_around_each_inference_and_delays_keep_the_period() {
    let time = SimTime::default();
    let mut pin = PinMock::new(&pin_frames(3));
    let delay = SimDelay {
        time: time.clone(),
        ..SimDelay::default()
    };
    let pwm = PwmMock::new(&[
        PwmTx::max_duty_cycle(20_000),
        PwmTx::set_duty_cycle(1_500), // 0 degrees: 1.5 ms of 20 ms
        PwmTx::max_duty_cycle(20_000),
        PwmTx::set_duty_cycle(2_000), // 90 degrees: 2 ms
        PwmTx::max_duty_cycle(20_000),
        PwmTx::set_duty_cycle(1_000), // -90 degrees: 1 ms
    ]);
    let servo = Servo::new(pwm, 1, ServoCalibration::HOBBY_DEGREES).unwrap();
    let mut d = FrameDriver::new(delay.clone(), pin.clone(), time.clone(), [servo], PERIOD);
    let poses = [[7.0f32, 0.0], [7.0, 90.0], [7.0, -90.0]];
    let work = [3_000_000u64, 4_500_000, 1_000];
    let mut starts = Vec::new();
    for (pose, w) in poses.iter().zip(work) {
        starts.push(time.0.get());
        let t = time.clone();
        let r = d.frame(|| -> Result<&[f32], ()> {
            t.advance(w); // the inference takes w ns, with the pin high
            Ok(pose)
        });
        let r = r.unwrap();
        assert_eq!(r.inference_ns, w);
        assert!(!r.overrun);
        assert_eq!(r.busy_ns + r.slept_ns, u64::from(PERIOD));
    }
    starts.push(time.0.get());
    // Frames start exactly one period apart.
    for w in starts.windows(2) {
        assert_eq!(w[1] - w[0], u64::from(PERIOD));
    }
    assert_eq!(*delay.calls.borrow(), vec![7_000_000, 5_500_000, 9_999_000]);
    assert_eq!(d.frames(), 3);
    let (_, _, _, [servo]) = d.release();
    servo.release().done();
    pin.done();
}

/// Everything the driver does, in order, to check the pin brackets the
/// inference exactly and the servos and the sleep come after it.
#[derive(Clone, Debug, PartialEq)]
enum Event {
    PinHigh,
    PinLow,
    Infer,
    Duty(u16),
    Sleep(u32),
}

#[derive(Clone, Default)]
struct EventLog(Rc<RefCell<Vec<Event>>>);

impl EventLog {
    fn push(&self, e: Event) {
        self.0.borrow_mut().push(e);
    }
}

impl embedded_hal::digital::ErrorType for EventLog {
    type Error = core::convert::Infallible;
}

impl embedded_hal::digital::OutputPin for EventLog {
    fn set_high(&mut self) -> Result<(), Self::Error> {
        self.push(Event::PinHigh);
        Ok(())
    }
    fn set_low(&mut self) -> Result<(), Self::Error> {
        self.push(Event::PinLow);
        Ok(())
    }
}

impl ErrorType for EventLog {
    type Error = core::convert::Infallible;
}

impl SetDutyCycle for EventLog {
    fn max_duty_cycle(&self) -> u16 {
        20_000
    }
    fn set_duty_cycle(&mut self, duty: u16) -> Result<(), Self::Error> {
        self.push(Event::Duty(duty));
        Ok(())
    }
}

impl DelayNs for EventLog {
    fn delay_ns(&mut self, ns: u32) {
        self.push(Event::Sleep(ns));
    }
}

#[test]
fn each_frame_is_pin_high_inference_pin_low_servos_sleep() {
    let log = EventLog::default();
    let servos = [
        Servo::new(log.clone(), 0, ServoCalibration::HOBBY_DEGREES).unwrap(),
        Servo::new(log.clone(), 1, ServoCalibration::HOBBY_DEGREES).unwrap(),
    ];
    let time = SimTime::default();
    let mut d = FrameDriver::new(log.clone(), log.clone(), time.clone(), servos, PERIOD);
    let pose = [45.0f32, -45.0];
    for _ in 0..2 {
        let (l, t) = (log.clone(), time.clone());
        d.frame(|| -> Result<&[f32], ()> {
            l.push(Event::Infer);
            t.advance(1_000);
            Ok(&pose)
        })
        .unwrap();
        // This delay only logs: move simulated time through the sleep.
        time.advance(u64::from(PERIOD) - 1_000);
    }
    let frame = [
        Event::PinHigh,
        Event::Infer,
        Event::PinLow,
        Event::Duty(1_750),
        Event::Duty(1_250),
        Event::Sleep(PERIOD - 1_000),
    ];
    assert_eq!(*log.0.borrow(), [frame.clone(), frame].concat());
}

#[test]
fn checked_delay_sees_period_minus_work() {
    // The same with embedded-hal-mock's CheckedDelay: a fixed 2 ms inference.
    let time = SimTime::default();
    let mut pin = PinMock::new(&pin_frames(2));
    let mut delay = CheckedDelay::new(&[
        DelayTx::delay_ns(PERIOD - 2_000_000),
        DelayTx::delay_ns(PERIOD - 2_000_000),
    ]);
    let servos: [Servo<PwmMock>; 0] = [];
    let mut d = FrameDriver::new(delay.clone(), pin.clone(), time.clone(), servos, PERIOD);
    for _ in 0..2 {
        let t = time.clone();
        d.frame(|| -> Result<&[f32], ()> {
            t.advance(2_000_000);
            Ok(&[])
        })
        .unwrap();
        // CheckedDelay does not move simulated time: the delay does.
        time.advance(u64::from(PERIOD) - 2_000_000);
    }
    delay.done();
    pin.done();
}

#[test]
fn an_overrun_does_not_sleep_and_restarts_the_schedule() {
    let time = SimTime::default();
    let mut pin = PinMock::new(&pin_frames(2));
    let delay = SimDelay {
        time: time.clone(),
        ..SimDelay::default()
    };
    let servos: [Servo<RecPwm>; 0] = [];
    let mut d = FrameDriver::new(delay.clone(), pin.clone(), time.clone(), servos, PERIOD);
    let t = time.clone();
    let r = d.frame(|| -> Result<&[f32], ()> {
        t.advance(u64::from(PERIOD) + 5);
        Ok(&[])
    });
    assert!(r.unwrap().overrun);
    let t = time.clone();
    let r = d
        .frame(|| -> Result<&[f32], ()> {
            t.advance(1_000);
            Ok(&[])
        })
        .unwrap();
    assert!(!r.overrun);
    assert_eq!(*delay.calls.borrow(), vec![PERIOD - 1_000]);
    assert_eq!(d.overruns(), 1);
    pin.done();
}

#[test]
fn a_failed_inference_still_lowers_the_pin_and_moves_no_servo() {
    let time = SimTime::default();
    let mut pin = PinMock::new(&pin_frames(2));
    let delay = SimDelay {
        time: time.clone(),
        ..SimDelay::default()
    };
    let pwm = RecPwm {
        max: 1000,
        ..RecPwm::default()
    };
    let servo = Servo::new(pwm.clone(), 3, ServoCalibration::HOBBY_DEGREES).unwrap();
    let mut d = FrameDriver::new(delay, pin.clone(), time, [servo], PERIOD);
    assert_eq!(
        d.frame(|| -> Result<&[f32], &str> { Err("NaN input") }),
        Err(FrameError::Inference("NaN input"))
    );
    let short = [0.0f32; 2];
    assert_eq!(
        d.frame(|| -> Result<&[f32], &str> { Ok(&short) }),
        Err(FrameError::PoseTooShort { joint: 3, len: 2 })
    );
    assert!(pwm.duties.borrow().is_empty());
    pin.done();
}

#[test]
fn pwm_errors_name_the_servo() {
    use embedded_hal::pwm::ErrorKind;
    use embedded_hal_mock::eh1::MockError;
    let mut pin = PinMock::new(&pin_frames(1));
    let bad = PwmMock::new(&[
        PwmTx::max_duty_cycle(100),
        PwmTx::set_duty_cycle(8).with_error(MockError::Io(std::io::ErrorKind::Other)),
    ]);
    let servo = Servo::new(bad, 0, ServoCalibration::HOBBY_DEGREES).unwrap();
    let time = SimTime::default();
    let mut d = FrameDriver::new(
        SimDelay {
            time: time.clone(),
            ..SimDelay::default()
        },
        pin.clone(),
        time,
        [servo],
        PERIOD,
    );
    let pose = [0.0f32];
    match d.frame(|| -> Result<&[f32], ()> { Ok(&pose) }) {
        Err(FrameError::Pwm { servo: 0, error }) => {
            use embedded_hal::pwm::Error as _;
            assert_eq!(error.kind(), ErrorKind::Other);
        }
        other => panic!("{other:?}"),
    }
    let (_, _, _, [servo]) = d.release();
    servo.release().done();
    pin.done();
}

#[test]
fn calibration_maps_direction_limits_and_pulses() {
    let c = ServoCalibration {
        reversed: true,
        limit_min: -45.0,
        limit_max: 60.0,
        ..ServoCalibration::HOBBY_DEGREES
    };
    c.validate().unwrap();
    // Reversed: -90 would be 2 ms, +90 1 ms; limits -45 -> 1.75 ms, 60 -> 1.1667 ms.
    assert_eq!(c.pulse_range(), (1_166_667, 1_750_000));
    assert_eq!(c.duty(0.0, 20_000), 1_500);
    assert_eq!(c.duty(-1e30, 20_000), 1_750);
    assert_eq!(c.duty(f32::INFINITY, 20_000), 1_167);
    assert_eq!(c.duty_range(20_000), (1_167, 1_750));
    let bad = |f: fn(&mut ServoCalibration)| {
        let mut c = ServoCalibration::HOBBY_DEGREES;
        f(&mut c);
        c.validate().unwrap_err()
    };
    assert_eq!(
        bad(|c| c.angle_max = f32::NAN),
        CalibrationError::NonFiniteAngle
    );
    assert_eq!(
        bad(|c| c.angle_max = c.angle_min),
        CalibrationError::EmptyAngleRange
    );
    assert_eq!(bad(|c| c.limit_max = 100.0), CalibrationError::BadLimits);
    assert_eq!(bad(|c| c.limit_min = -100.0), CalibrationError::BadLimits);
    assert_eq!(
        bad(|c| {
            c.limit_min = 50.0;
            c.limit_max = 40.0
        }),
        CalibrationError::BadLimits
    );
    assert_eq!(
        bad(|c| c.pulse_max_ns = c.pulse_min_ns),
        CalibrationError::BadPulseRange
    );
    assert_eq!(
        bad(|c| c.pulse_max_ns = c.period_ns + 1),
        CalibrationError::BadPulseRange
    );
    assert!(Servo::new(
        RecPwm::default(),
        0,
        ServoCalibration {
            limit_min: 99.0,
            ..ServoCalibration::HOBBY_DEGREES
        }
    )
    .is_err());
}

#[test]
fn nan_holds_the_previous_position() {
    let pwm = RecPwm {
        max: 20_000,
        ..RecPwm::default()
    };
    let mut s = Servo::new(pwm.clone(), 0, ServoCalibration::HOBBY_DEGREES).unwrap();
    // NaN first: the midpoint of the limits.
    assert_eq!(s.set_angle(f32::NAN).unwrap(), (1_500, AngleFate::Held));
    assert_eq!(s.set_angle(45.0).unwrap(), (1_750, AngleFate::Exact));
    assert_eq!(s.set_angle(-f32::NAN).unwrap(), (1_750, AngleFate::Held));
    assert_eq!(
        s.set_angle(f32::NEG_INFINITY).unwrap(),
        (1_000, AngleFate::Clamped)
    );
    assert_eq!(*pwm.duties.borrow(), vec![1_500, 1_750, 1_750, 1_000]);
}

/// Any valid calibration (direction, limits, pulses, PWM resolution).
fn calibration() -> impl Strategy<Value = ServoCalibration> {
    (
        -1e4f32..1e4,
        1e-2f32..1e4,
        0.0f32..=1.0,
        0.0f32..=1.0,
        any::<bool>(),
        1u32..5_000_000,
        1u32..5_000_000,
        0u32..20_000_000,
    )
        .prop_map(|(angle_min, span, a, b, reversed, pmin, pwidth, extra)| {
            let angle_max = angle_min + span;
            let (lo, hi) = (a.min(b), a.max(b));
            let limit_min = (angle_min + span * lo).clamp(angle_min, angle_max);
            let limit_max = (angle_min + span * hi).clamp(limit_min, angle_max);
            ServoCalibration {
                pulse_min_ns: pmin,
                pulse_max_ns: pmin + pwidth,
                period_ns: pmin + pwidth + extra,
                angle_min,
                angle_max,
                reversed,
                limit_min,
                limit_max,
            }
        })
}

/// Any f32 at all (every bit pattern: NaNs, infinities, subnormals, huge).
fn any_angle() -> impl Strategy<Value = f32> {
    prop_oneof![
        any::<u32>().prop_map(f32::from_bits),
        Just(f32::NAN),
        Just(f32::INFINITY),
        Just(f32::NEG_INFINITY),
        Just(f32::MAX),
        Just(f32::MIN),
        -1e6f32..1e6,
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    /// Whatever the pose, every duty written lies inside the channel's
    /// calibrated range (the duties of its two limits).
    #[test]
    fn duty_stays_in_the_calibrated_range(
        cals in proptest::array::uniform3(calibration()),
        max in 1u16..=u16::MAX,
        poses in proptest::collection::vec(proptest::array::uniform4(any_angle()), 1..6),
    ) {
        let time = SimTime::default();
        let pwms: Vec<RecPwm> = (0..3).map(|_| RecPwm { max, ..RecPwm::default() }).collect();
        let servos = [0, 1, 2].map(|i| Servo::new(pwms[i].clone(), 3 - i, cals[i]).unwrap());
        let mut pin = PinMock::new(&pin_frames(poses.len()));
        let mut d = FrameDriver::new(SimDelay { time: time.clone(), ..SimDelay::default() }, pin.clone(), time, servos, PERIOD);
        for pose in &poses {
            d.frame(|| -> Result<&[f32], ()> { Ok(pose) }).unwrap();
        }
        for (pwm, cal) in pwms.iter().zip(&cals) {
            let (lo, hi) = cal.duty_range(max);
            let duties = pwm.duties.borrow();
            prop_assert_eq!(duties.len(), poses.len());
            for &duty in duties.iter() {
                prop_assert!(lo <= duty && duty <= hi, "duty {} outside [{}, {}] for {:?}", duty, lo, hi, cal);
            }
        }
        pin.done();
    }

    /// Finite angles within the limits map monotonically (in the servo's
    /// direction) onto the pulse range.
    #[test]
    fn pulses_are_monotonic(cal in calibration(), a in 0.0f32..=1.0, b in 0.0f32..=1.0) {
        let (x, y) = (a.min(b), a.max(b));
        let ax = cal.limit_min + (cal.limit_max - cal.limit_min) * x;
        let ay = cal.limit_min + (cal.limit_max - cal.limit_min) * y;
        let (px, py) = (cal.duty(ax, u16::MAX), cal.duty(ay, u16::MAX));
        if cal.reversed { prop_assert!(px >= py) } else { prop_assert!(px <= py) }
    }
}
