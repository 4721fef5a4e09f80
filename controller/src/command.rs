//! What the user asks for each frame, and how hostile values are handled.

use crate::error::{Error, Result};

/// Speed limit of a command, capture units per frame. The demo's stick gives
/// at most 5 (a jog, about 3 m/s); twice that is still inside what the
/// network saw, anything above is clamped to it.
pub const MAX_SPEED: f32 = 10.0;

/// A facing shorter than this means "no facing: face where you go".
pub const MIN_FACING: f32 = 1e-3;

/// A requested gait, for the common one-hot case of [`GaitWeights`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Gait {
    /// Stand still (the requested velocity is ignored; facing still turns).
    Stand,
    /// Walk.
    Walk,
    /// Jog.
    Jog,
    /// Crouched walk.
    Crouch,
}

/// Requested gait weights, each in `[0, 1]`.
///
/// `stand` is the absence of motion rather than a style of it: it scales the
/// requested speed by `1 - stand`, and the stand weight the network sees
/// then follows the speed exactly as in the demo (full stand below 0.1 units
/// per frame). `walk`, `jog` and `crouch` are the targets the network's gait
/// inputs blend toward while moving (the demo uses them one-hot).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct GaitWeights {
    /// Stand.
    pub stand: f32,
    /// Walk.
    pub walk: f32,
    /// Jog.
    pub jog: f32,
    /// Crouch.
    pub crouch: f32,
}

impl From<Gait> for GaitWeights {
    fn from(g: Gait) -> Self {
        let mut w = GaitWeights::default();
        match g {
            Gait::Stand => w.stand = 1.0,
            Gait::Walk => w.walk = 1.0,
            Gait::Jog => w.jog = 1.0,
            Gait::Crouch => w.crouch = 1.0,
        }
        w
    }
}

/// One frame's command, in world space on the ground plane `(x, z)`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Command {
    /// Desired root velocity, capture units per frame (at 60 frames per
    /// second; about 2.5 walks, 5 jogs). Clamped to [`MAX_SPEED`].
    pub velocity: [f32; 2],
    /// Desired facing. Zero (shorter than [`MIN_FACING`]) means "face where
    /// you go"; any other vector is normalised and the character strafes
    /// toward it, as with the demo's strafe trigger held.
    pub facing: [f32; 2],
    /// Requested gait.
    pub gait: GaitWeights,
}

impl Command {
    /// A command with no explicit facing.
    pub fn moving(velocity: [f32; 2], gait: Gait) -> Self {
        Command {
            velocity,
            facing: [0.0; 2],
            gait: gait.into(),
        }
    }

    /// Standing still, facing where the character already faces.
    pub fn stand() -> Self {
        Command::moving([0.0; 2], Gait::Stand)
    }
}

/// A command the controller can use: finite, speed within [`MAX_SPEED`],
/// weights in `[0, 1]`, facing unit or absent.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Checked {
    /// Velocity after the stand scaling and the speed clamp.
    pub velocity: [f32; 2],
    /// Unit facing, if one was given.
    pub facing: Option<[f32; 2]>,
    /// Walk, jog and crouch targets, clamped to `[0, 1]`.
    pub walk: f32,
    pub jog: f32,
    pub crouch: f32,
}

/// Field numbers used by [`Error::BadCommand`].
pub mod field {
    /// `velocity[0]`, `velocity[1]`.
    pub const VELOCITY: u8 = 0;
    /// `facing[0]`, `facing[1]`.
    pub const FACING: u8 = 2;
    /// `gait.stand`, `.walk`, `.jog`, `.crouch`.
    pub const GAIT: u8 = 4;
}

impl Command {
    /// Refuses NaN and infinities (there is no sensible value to clamp them
    /// to: the frame is refused and the state left untouched), clamps
    /// everything else into range.
    pub(crate) fn check(&self) -> Result<Checked> {
        let g = &self.gait;
        let all = [
            self.velocity[0],
            self.velocity[1],
            self.facing[0],
            self.facing[1],
            g.stand,
            g.walk,
            g.jog,
            g.crouch,
        ];
        if let Some(i) = all.iter().position(|v| !v.is_finite()) {
            return Err(Error::BadCommand { field: i as u8 });
        }
        let unit = |v: f32| v.clamp(0.0, 1.0);
        let moving = 1.0 - unit(g.stand);
        let v = clamp_length(self.velocity, MAX_SPEED);
        Ok(Checked {
            velocity: [v[0] * moving, v[1] * moving],
            facing: unit_or_none(self.facing),
            walk: unit(g.walk),
            jog: unit(g.jog),
            crouch: unit(g.crouch),
        })
    }
}

/// `v` shortened to at most `max`, without overflow for huge components
/// (scaled by its largest component first).
fn clamp_length(v: [f32; 2], max: f32) -> [f32; 2] {
    let m = v[0].abs().max(v[1].abs());
    if m <= max * core::f32::consts::FRAC_1_SQRT_2 {
        return v; // |v| <= sqrt(2) m <= max: nothing to do
    }
    let u = [v[0] / m, v[1] / m];
    let n = crate::f32_math::sqrt(u[0] * u[0] + u[1] * u[1]); // in [1, sqrt 2]
    if m * n <= max {
        v
    } else {
        [u[0] * (max / n), u[1] * (max / n)]
    }
}

fn unit_or_none(v: [f32; 2]) -> Option<[f32; 2]> {
    let m = v[0].abs().max(v[1].abs());
    if m < MIN_FACING {
        return None;
    }
    let u = [v[0] / m, v[1] / m];
    let n = crate::f32_math::sqrt(u[0] * u[0] + u[1] * u[1]);
    if n * m < MIN_FACING {
        None
    } else {
        Some([u[0] / n, u[1] / n])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hostile_values_are_refused_or_clamped() {
        let mut c = Command::moving([1e30, -1e38], Gait::Walk);
        let k = c.check().unwrap();
        let n = (k.velocity[0] * k.velocity[0] + k.velocity[1] * k.velocity[1]).sqrt();
        assert!((n - MAX_SPEED).abs() < 1e-5, "{n}");
        c.velocity = [f32::MAX, f32::MAX];
        assert!(c.check().unwrap().velocity[0].is_finite());
        c.velocity = [f32::NAN, 0.0];
        assert_eq!(c.check(), Err(Error::BadCommand { field: 0 }));
        c.velocity = [0.0, 0.0];
        c.facing = [0.0, f32::INFINITY];
        assert_eq!(c.check(), Err(Error::BadCommand { field: 3 }));
        c.facing = [0.0, 0.0];
        c.gait = GaitWeights {
            stand: -3.0,
            walk: 7.0,
            jog: -0.5,
            crouch: 2.0,
        };
        let k = c.check().unwrap();
        assert_eq!((k.walk, k.jog, k.crouch), (1.0, 0.0, 1.0));
        c.gait.crouch = f32::NEG_INFINITY;
        assert_eq!(c.check(), Err(Error::BadCommand { field: 7 }));
    }

    #[test]
    fn stand_scales_the_speed_and_facing_is_normalised() {
        let mut c = Command::moving([0.0, 2.0], Gait::Stand);
        assert_eq!(c.check().unwrap().velocity, [0.0, 0.0]);
        c.gait = GaitWeights {
            stand: 0.5,
            walk: 1.0,
            ..Default::default()
        };
        assert_eq!(c.check().unwrap().velocity, [0.0, 1.0]);
        c.facing = [3.0, 4.0];
        assert_eq!(c.check().unwrap().facing, Some([0.6, 0.8]));
        c.facing = [1e-4, 0.0];
        assert_eq!(c.check().unwrap().facing, None);
        c.facing = [1e38, 1e38];
        let f = c.check().unwrap().facing.unwrap();
        assert!((f[0] - core::f32::consts::FRAC_1_SQRT_2).abs() < 1e-6);
    }
}
