//! Random command scripts ("tours") for calibration: what a player might
//! ask of a locomotion controller, drawn from a seeded stream, so that
//! `host-sim rollout-dataset --tours N` records the inputs the network
//! meets in closed loop without anyone writing scripts, and without
//! reusing the built-in scripts that `host-sim fidelity` scores.
//!
//! A tour stands still at first, starts moving after 0.3 to 0.8 s, then
//! holds each command for 0.8 to 2.5 s until `seconds` have passed:
//!
//! | draw | distribution |
//! |---|---|
//! | gait | stand, walk, walk, jog, jog, crouch (uniform over the six) |
//! | speed, units per frame | stand 0, walk 1.5–3, jog 3.5–5.5, crouch 1–2.5 |
//! | direction | uniform angle |
//! | facing (strafe) | a quarter of moving commands: a uniform angle |
//! | turn | four in ten commands: uniform in ±0.8 rad/s |
//! | gait blend | a fifth of walk and jog commands: 30–70 % of walk, jog or crouch |
//!
//! Tour `i` of seed `s` depends only on `(s, i)`: the same on every run
//! and platform (ChaCha8).

use phasegate_controller::{Gait, GaitWeights};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::f64::consts::PI;

use super::script::{Script, Segment};

/// The gaits a tour draws from (walk and jog twice: the common ones).
const GAITS: [Gait; 6] = [
    Gait::Stand,
    Gait::Walk,
    Gait::Walk,
    Gait::Jog,
    Gait::Jog,
    Gait::Crouch,
];

/// Speed range of a gait, units per frame.
fn speeds(g: Gait) -> (f64, f64) {
    match g {
        Gait::Stand => (0.0, 0.0),
        Gait::Walk => (1.5, 3.0),
        Gait::Jog => (3.5, 5.5),
        Gait::Crouch => (1.0, 2.5),
    }
}

/// A unit vector at a uniform angle, `(x, z)`.
fn direction(rng: &mut ChaCha8Rng) -> [f64; 2] {
    let a = rng.gen_range(-PI..PI);
    [a.sin(), a.cos()]
}

fn set(w: &mut GaitWeights, g: Gait, v: f32) {
    match g {
        Gait::Stand => w.stand = v,
        Gait::Walk => w.walk = v,
        Gait::Jog => w.jog = v,
        Gait::Crouch => w.crouch = v,
    }
}

/// Tour `index` of `seed`, `seconds` long.
pub fn tour(seed: u64, index: usize, seconds: f64) -> Script {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(index as u64);
    let mut commands = vec![Segment {
        at: 0.0,
        velocity: [0.0; 2],
        facing: None,
        gait: Gait::Stand.into(),
        turn: 0.0,
    }];
    let mut at = rng.gen_range(0.3..0.8);
    while at < seconds {
        let gait = GAITS[rng.gen_range(0..GAITS.len())];
        let (lo, hi) = speeds(gait);
        let speed = if hi > lo { rng.gen_range(lo..hi) } else { lo };
        let d = direction(&mut rng);
        let moving = gait != Gait::Stand;
        let facing = (moving && rng.gen_bool(0.25)).then(|| {
            let f = direction(&mut rng);
            [f[0] as f32, f[1] as f32]
        });
        let turn = if rng.gen_bool(0.4) {
            rng.gen_range(-0.8..0.8)
        } else {
            0.0
        };
        let mut weights: GaitWeights = gait.into();
        if matches!(gait, Gait::Walk | Gait::Jog) && rng.gen_bool(0.2) {
            let other = [Gait::Walk, Gait::Jog, Gait::Crouch][rng.gen_range(0..3)];
            if other != gait {
                let share = rng.gen_range(0.3..0.7);
                weights = GaitWeights::default();
                set(&mut weights, gait, share as f32);
                set(&mut weights, other, (1.0 - share) as f32);
            }
        }
        commands.push(Segment {
            at,
            velocity: [(speed * d[0]) as f32, (speed * d[1]) as f32],
            facing,
            gait: weights,
            turn,
        });
        at += rng.gen_range(0.8..2.5);
    }
    Script {
        name: format!("tour-{seed}-{index}"),
        commands,
    }
}

/// The tour a name `tour-SEED-INDEX` (as [`tour`] names them) stands
/// for, so that recorded tours can be replayed by name. It is drawn an
/// hour long: a tour's commands do not depend on its length, only how
/// many there are, so every frame of a recording of any length up to an
/// hour gets the same command.
pub fn by_name(name: &str) -> Option<Script> {
    let (seed, index) = name.strip_prefix("tour-")?.split_once('-')?;
    Some(tour(seed.parse().ok()?, index.parse().ok()?, 3600.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tours_are_reproducible_and_differ() {
        assert_eq!(tour(1, 0, 10.0), tour(1, 0, 10.0));
        assert_ne!(tour(1, 0, 10.0), tour(1, 1, 10.0));
        assert_ne!(tour(1, 0, 10.0), tour(2, 0, 10.0));
    }

    #[test]
    fn tours_replay_by_name() {
        let (short, long) = (tour(12, 3, 10.0), tour(12, 3, 40.0));
        assert_eq!(short.name, "tour-12-3");
        let replay = by_name(&short.name).unwrap();
        assert_eq!(Script::load("tour-12-3").ok().as_ref(), Some(&replay));
        // A longer tour starts as the shorter one does.
        assert_eq!(long.commands[..short.commands.len()], short.commands[..]);
        // The replay gives a recording of either length its commands.
        for (t, frames) in [(&short, 600), (&long, 2400)] {
            for f in 0..frames {
                assert_eq!(replay.command(f), t.command(f), "frame {f} of {frames}");
            }
        }
        for bad in ["tour-12", "tour--3", "tour-a-3", "tour-1-2-3", "walk"] {
            assert_eq!(by_name(bad), None, "{bad}");
        }
    }

    #[test]
    fn tours_start_standing_and_stay_in_range() {
        let mut gaits = [0usize; 4];
        for i in 0..40 {
            let t = tour(7, i, 10.0);
            assert_eq!(t.command(0).gait.stand, 1.0);
            assert!(t.commands.windows(2).all(|w| w[0].at < w[1].at));
            assert!(t.commands.last().is_some_and(|c| c.at < 10.0));
            for c in &t.commands[1..] {
                let v = f64::from(c.velocity[0]).hypot(f64::from(c.velocity[1]));
                assert!(v <= 5.5 + 1e-5, "{v}");
                assert!(c.turn.abs() <= 0.8);
                let g = c.gait;
                assert!((g.stand + g.walk + g.jog + g.crouch - 1.0).abs() < 1e-6);
                for (n, w) in gaits.iter_mut().zip([g.stand, g.walk, g.jog, g.crouch]) {
                    *n += usize::from(w > 0.0);
                }
            }
        }
        // Every gait turns up.
        assert!(gaits.iter().all(|&n| n > 10), "{gaits:?}");
    }
}
