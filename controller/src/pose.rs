//! What the controller produces every frame.

use crate::geom::{yaw_quat, Quat, Vec2, Vec3};
use crate::layout::JOINTS;
use crate::real::Real;

/// The character at one frame, world space (`y` up, ground at `y = 0`).
#[derive(Clone, Debug, PartialEq)]
pub struct Pose<R> {
    /// Frames stepped since the last reset (this pose is frame `frame - 1`;
    /// 0 for the reset pose).
    pub frame: u32,
    /// Root position `(x, 0, z)`: the trajectory point the joints were
    /// placed from this frame.
    pub root_position: Vec3<R>,
    /// Root facing, a unit `(x, z)`; its yaw is [`Pose::yaw`].
    pub facing: Vec2<R>,
    /// Joint positions.
    pub joint_positions: [Vec3<R>; JOINTS],
    /// Joint rotations, unit quaternions `[x, y, z, w]` with `w >= 0`.
    pub joint_rotations: [Quat<R>; JOINTS],
    /// Foot contact values (left heel, left toe, right heel, right toe), as
    /// the network predicts them: about 0 in the air, about 1 planted.
    pub contacts: [R; 4],
    /// The phase this pose was inferred at, cycles in `[0, 1)`.
    pub phase: R,
    /// Gait weights the network saw at the current frame: stand, walk, jog,
    /// crouch.
    pub gaits: [R; 4],
}

impl<R: Real> Pose<R> {
    /// Everything at zero, identity rotations, facing `+z`.
    pub fn zero() -> Self {
        Pose {
            frame: 0,
            root_position: [R::ZERO; 3],
            facing: [R::ZERO, R::ONE],
            joint_positions: [[R::ZERO; 3]; JOINTS],
            joint_rotations: [[R::ZERO, R::ZERO, R::ZERO, R::ONE]; JOINTS],
            contacts: [R::ZERO; 4],
            phase: R::ZERO,
            gaits: [R::ZERO; 4],
        }
    }

    /// Root yaw, radians in `[-pi, pi]` (0 faces `+z`, positive turns left
    /// toward `+x`).
    pub fn yaw(&self) -> R {
        self.facing[0].atan2(self.facing[1])
    }

    /// Root rotation, a quaternion `[x, y, z, w]` about `y`.
    pub fn root_rotation(&self) -> Quat<R> {
        yaw_quat(self.facing)
    }

    /// The phase in radians, `[0, 2 pi)`.
    pub fn phase_radians(&self) -> R {
        self.phase * R::lit(core::f64::consts::TAU)
    }

    /// Every value is finite (the controller guarantees it; this is for
    /// callers that want to check anyway).
    pub fn is_finite(&self) -> bool {
        let scalars = self
            .root_position
            .iter()
            .chain(&self.facing)
            .chain(self.joint_positions.iter().flatten())
            .chain(self.joint_rotations.iter().flatten())
            .chain(&self.contacts)
            .chain(&self.gaits);
        scalars.chain([&self.phase]).all(|v| v.is_finite())
    }
}

impl<R: Real> Default for Pose<R> {
    fn default() -> Self {
        Self::zero()
    }
}
