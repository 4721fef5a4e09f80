//! The demo's per-frame loop, written once over [`Real`] and [`Network`].
//!
//! Per frame (`pfnn.cpp`'s `pre_render` then `post_render`, on flat ground,
//! without walls, jump areas or foot IK):
//!
//! 1. smooth the command: target velocity, target facing, strafe amount;
//! 2. blend the current gait weights toward the requested gait;
//! 3. bend the future trajectory toward the target velocity and facing;
//! 4. build the 342 inputs in the current root space (joints in the
//!    previous root space, terrain heights zero);
//! 5. run the network at the current phase;
//! 6. place the joints: blend of (previous + predicted velocity) and the
//!    predicted position; rotations from the exponential map;
//! 7. shift the past, move and turn the root by the predicted root motion,
//!    lay the predicted future;
//! 8. advance the phase.

use crate::command::{Checked, Command};
use crate::deadline::FrameAction;
use crate::error::{Error, Result};
use crate::geom::{
    canonical, len2, mix_directions, quat_exp, quat_mul, unyaw3, yaw3, yaw_quat, Vec2, Vec3,
};
use crate::layout::{Inputs, Outputs, INPUTS, JOINTS, OUTPUTS};
use crate::pose::Pose;
use crate::real::Real;
use crate::trajectory::{gait, Gaits, Trajectory, CURRENT};

/// A phase-gated network as a controller sees it: raw model units in and
/// out, the phase as a fraction of a cycle. Its widths are its own (a
/// controller checks them once, when it is made: [`Locomotion`] needs
/// PFNN's 342 -> 311), so the same trait serves other controllers and
/// networks: the fixed-point [`phasegate::Runtime`] (plain or styled) on
/// the device, float references on the host.
pub trait Network<R> {
    /// Width of the input vector.
    fn input_dim(&self) -> usize;
    /// Width of the output vector.
    fn output_dim(&self) -> usize;
    /// Inference at `phase` (cycles, `[0, 1)`); `x` holds
    /// [`Network::input_dim`] values, `y` [`Network::output_dim`].
    fn predict(&mut self, phase: R, x: &[R], y: &mut [R]) -> Result<()>;
    /// The mean output (the data set's `Ymean`): the pose the controller
    /// starts from; `y` holds [`Network::output_dim`] values.
    fn mean_output(&self, y: &mut [R]) -> Result<()>;
}

/// A borrowed network (a `&mut dyn Network` included) is a network.
impl<R, N: Network<R> + ?Sized> Network<R> for &mut N {
    fn input_dim(&self) -> usize {
        (**self).input_dim()
    }
    fn output_dim(&self) -> usize {
        (**self).output_dim()
    }
    fn predict(&mut self, phase: R, x: &[R], y: &mut [R]) -> Result<()> {
        (**self).predict(phase, x, y)
    }
    fn mean_output(&self, y: &mut [R]) -> Result<()> {
        (**self).mean_output(y)
    }
}

/// [`Error::NotPfnn`] unless `net` is 342 -> 311.
fn check_pfnn<R>(net: &impl Network<R>) -> Result<()> {
    let (inputs, outputs) = (net.input_dim(), net.output_dim());
    if inputs == INPUTS && outputs == OUTPUTS {
        Ok(())
    } else {
        Err(Error::NotPfnn {
            inputs: inputs as u32,
            outputs: outputs as u32,
        })
    }
}

/// A layout split that cannot fail (the arrays have the layout's widths).
fn length_error(n: usize) -> Error {
    Error::Runtime(phasegate::Error::LengthMismatch {
        expected: n as u32,
        found: n as u32,
    })
}

/// Smoothing rates per frame, the demo's `Options` defaults.
pub mod rates {
    /// Target velocity toward the command.
    pub const VELOCITY: f64 = 0.9;
    /// Target facing toward the command.
    pub const FACING: f64 = 0.9;
    /// Strafe amount toward 0 (no facing given) or 1.
    pub const STRAFE: f64 = 0.9;
    /// Current gait weights toward the requested ones.
    pub const GAIT: f64 = 0.1;
    /// Joint positions: weight of the predicted position against the
    /// previous position plus the predicted velocity.
    pub const JOINT: f64 = 0.5;
}

/// Below this target speed (units per frame) the stand weight rises.
const STAND_SPEED: f64 = 0.1;
/// Below this target speed the velocity has no direction to face.
const STILL_SPEED: f64 = 1e-5;

/// The loop's whole state. Sized at compile time, no heap.
#[derive(Clone, Debug)]
pub struct Locomotion<R> {
    trajectory: Trajectory<R>,
    /// World-space joint velocities of the last frame (units per frame).
    velocities: [Vec3<R>; JOINTS],
    target_velocity: Vec2<R>,
    target_facing: Vec2<R>,
    /// The last facing the user asked for explicitly.
    requested_facing: Vec2<R>,
    strafe: R,
    /// Cycles, `[0, 1)`.
    phase: R,
    x: [R; INPUTS],
    y: [R; OUTPUTS],
    /// Also the state: joint positions are blended from their last value.
    pose: Pose<R>,
}

impl<R: Real> Locomotion<R> {
    /// The demo's reset: at the origin facing `+z`, joints in the mean pose
    /// (`Ymean`), phase 0.
    /// Refuses a network that is not PFNN-shaped ([`Error::NotPfnn`]).
    pub fn new(net: &impl Network<R>) -> Result<Self> {
        check_pfnn(net)?;
        let mut s = Locomotion {
            trajectory: Trajectory::new(),
            velocities: [[R::ZERO; 3]; JOINTS],
            target_velocity: [R::ZERO; 2],
            target_facing: [R::ZERO, R::ONE],
            requested_facing: [R::ZERO, R::ONE],
            strafe: R::ZERO,
            phase: R::ZERO,
            x: [R::ZERO; INPUTS],
            y: [R::ZERO; OUTPUTS],
            pose: Pose::zero(),
        };
        s.reset(net)?;
        Ok(s)
    }

    /// Back to the state of [`Locomotion::new`].
    pub fn reset(&mut self, net: &impl Network<R>) -> Result<()> {
        check_pfnn(net)?;
        net.mean_output(&mut self.y[..])?;
        let y = Outputs::split(&self.y).ok_or(length_error(OUTPUTS))?;
        self.trajectory = Trajectory::new();
        self.target_velocity = [R::ZERO; 2];
        self.target_facing = [R::ZERO, R::ONE];
        self.requested_facing = [R::ZERO, R::ONE];
        self.strafe = R::ZERO;
        self.phase = R::ZERO;
        self.pose = Pose::zero();
        let joints = self
            .pose
            .joint_positions
            .iter_mut()
            .zip(self.pose.joint_rotations.iter_mut())
            .zip(self.velocities.iter_mut());
        for (((p, q), v), ((yp, yv), yr)) in joints.zip(
            y.positions
                .chunks_exact(3)
                .zip(y.velocities.chunks_exact(3))
                .zip(y.rotations.chunks_exact(3)),
        ) {
            *p = vec3(yp);
            *v = vec3(yv);
            *q = canonical(quat_exp(vec3(yr)));
        }
        Ok(())
    }

    /// The last pose.
    pub fn pose(&self) -> &Pose<R> {
        &self.pose
    }

    /// The last network input (raw model units).
    pub fn last_input(&self) -> &[R; INPUTS] {
        &self.x
    }

    /// The last network output (raw model units).
    pub fn last_output(&self) -> &[R; OUTPUTS] {
        &self.y
    }

    /// One frame. A command with NaN or infinite values is refused with
    /// [`Error::BadCommand`] before anything changes; out-of-range values
    /// are clamped (see [`Command`]). A network error, or a non-finite
    /// network output ([`Error::NonFinite`], which only a float network can
    /// give: fixed-point outputs are bounded), leaves the pose untouched but
    /// the trajectory half-updated: [`Locomotion::reset`] before going on.
    pub fn step(&mut self, net: &mut impl Network<R>, command: &Command) -> Result<&Pose<R>> {
        let cmd = command.check()?;
        self.steer(&cmd);
        self.trajectory
            .bend_future(self.target_velocity, self.target_facing, self.strafe);
        let (root, facing) = self.trajectory.root(CURRENT);
        self.build_inputs(root, facing)?;
        net.predict(self.phase, &self.x[..], &mut self.y[..])?;
        // A float network can overflow; never let it reach the pose.
        if let Some(i) = self.y.iter().position(|v| !v.is_finite()) {
            return Err(Error::NonFinite { index: i as u32 });
        }
        let y = Outputs::split(&self.y).ok_or(length_error(OUTPUTS))?;
        place_joints(&mut self.pose, &mut self.velocities, &y, root, facing);
        self.pose.root_position = [root[0], R::ZERO, root[1]];
        self.pose.facing = facing;
        self.pose.contacts = *y.contacts;
        self.pose.phase = self.phase;
        self.pose.gaits = self.trajectory.current_gaits();
        self.pose.frame = self.pose.frame.wrapping_add(1);

        // How much the character is not standing, the demo's
        // (1 - stand)^0.25 (as two square roots, correctly rounded each): it
        // scales root motion and phase speed.
        let stand = self.pose.gaits[gait::STAND].clamp_to(R::ZERO, R::ONE);
        let moving = (R::ONE - stand).sqrt().sqrt();
        self.trajectory.advance(&y, moving);
        let rate = moving * R::lit(0.9) + R::lit(0.1);
        self.phase = wrap_cycle(self.phase + rate * y.phase_change);
        Ok(&self.pose)
    }

    /// One frame as a [`crate::Deadline`] allows it: [`FrameAction::Infer`]
    /// is [`Locomotion::step`]; [`FrameAction::Hold`] (the frame after an
    /// overrun under [`crate::OverrunPolicy::HoldNext`]) changes nothing
    /// and returns the last pose again: the phase, the trajectory, the
    /// joint velocities, the smoothed targets and the pose's `frame`
    /// counter stay as they were, and `command` is neither checked nor
    /// applied. The firmware and the host's replay both step through
    /// here, so a held frame means the same on both.
    pub fn frame(
        &mut self,
        net: &mut impl Network<R>,
        action: FrameAction,
        command: &Command,
    ) -> Result<&Pose<R>> {
        match action {
            FrameAction::Infer => self.step(net, command),
            FrameAction::Hold => Ok(&self.pose),
        }
    }

    /// Steps 1 and 2: smooth the command into targets, blend the gaits.
    fn steer(&mut self, cmd: &Checked) {
        let v = [R::from_f32(cmd.velocity[0]), R::from_f32(cmd.velocity[1])];
        let tv = &mut self.target_velocity;
        let k = R::lit(rates::VELOCITY);
        *tv = [tv[0].mix(v[0], k), tv[1].mix(v[1], k)];

        let strafe_target = if let Some(f) = cmd.facing {
            self.requested_facing = [R::from_f32(f[0]), R::from_f32(f[1])];
            R::ONE
        } else {
            R::ZERO
        };
        self.strafe = self.strafe.mix(strafe_target, R::lit(rates::STRAFE));
        let speed = len2(self.target_velocity);
        let heading = if speed < R::lit(STILL_SPEED) {
            self.target_facing
        } else {
            self.target_velocity
        };
        let wanted = mix_directions(heading, self.requested_facing, self.strafe);
        self.target_facing = mix_directions(self.target_facing, wanted, R::lit(rates::FACING));

        let target: Gaits<R> = if speed < R::lit(STAND_SPEED) {
            let stand = R::ONE - (speed / R::lit(STAND_SPEED)).clamp_to(R::ZERO, R::ONE);
            [stand, R::ZERO, R::ZERO, R::ZERO]
        } else {
            [
                R::ZERO,
                R::from_f32(cmd.walk),
                R::from_f32(cmd.jog),
                R::from_f32(cmd.crouch),
            ]
        };
        self.trajectory
            .blend_current_gaits(target, R::lit(rates::GAIT));
    }

    /// Step 4: the input vector.
    fn build_inputs(&mut self, root: Vec2<R>, facing: Vec2<R>) -> Result<()> {
        let mut x = Inputs::split(&mut self.x).ok_or(length_error(INPUTS))?;
        self.trajectory.write_inputs(root, facing, &mut x);
        // Joints relative to the previous frame's root (where they were
        // placed from); its height is the ground's, 0.
        let (prev, prev_facing) = self.trajectory.root(CURRENT - 1);
        let joints = self
            .pose
            .joint_positions
            .iter()
            .zip(&self.velocities)
            .zip(x.positions.chunks_exact_mut(3))
            .zip(x.velocities.chunks_exact_mut(3));
        for (((p, v), xp), xv) in joints {
            let rel = unyaw3(prev_facing, [p[0] - prev[0], p[1], p[2] - prev[1]]);
            xp.copy_from_slice(&rel);
            xv.copy_from_slice(&unyaw3(prev_facing, *v));
        }
        x.heights.fill(R::ZERO);
        Ok(())
    }
}

/// Step 6: joints from the network's root-space outputs.
fn place_joints<R: Real>(
    pose: &mut Pose<R>,
    velocities: &mut [Vec3<R>; JOINTS],
    y: &Outputs<'_, R>,
    root: Vec2<R>,
    facing: Vec2<R>,
) {
    let root_rotation = yaw_quat(facing);
    let blend = R::lit(rates::JOINT);
    let joints = pose
        .joint_positions
        .iter_mut()
        .zip(pose.joint_rotations.iter_mut())
        .zip(velocities.iter_mut());
    let outputs = y
        .positions
        .chunks_exact(3)
        .zip(y.velocities.chunks_exact(3))
        .zip(y.rotations.chunks_exact(3));
    for (((p, q), v), ((yp, yv), yr)) in joints.zip(outputs) {
        let local = yaw3(facing, vec3(yp));
        let predicted = [local[0] + root[0], local[1], local[2] + root[1]];
        let vel = yaw3(facing, vec3(yv));
        for ((pi, vi), ti) in p.iter_mut().zip(vel).zip(predicted) {
            *pi = (*pi + vi).mix(ti, blend);
        }
        *v = vel;
        *q = canonical(quat_mul(root_rotation, quat_exp(vec3(yr))));
    }
}

/// `[a, b, c]` from a 3-chunk (zeros if shorter, which `chunks_exact(3)`
/// never gives).
fn vec3<R: Real>(s: &[R]) -> Vec3<R> {
    match s {
        [a, b, c, ..] => [*a, *b, *c],
        _ => [R::ZERO; 3],
    }
}

/// Wraps cycles into `[0, 1)`. The demo wraps radians with C `fmod`, which
/// keeps the sign of a negative phase; this wraps as a phase should.
fn wrap_cycle<R: Real>(c: R) -> R {
    let w = c - c.floor();
    // A tiny negative `c` rounds `c - floor(c)` up to exactly 1.
    if w >= R::ONE || !w.is_finite() {
        R::ZERO
    } else {
        w
    }
}

impl Locomotion<f32> {
    /// [`Locomotion::frame`] with the network behind a vtable (one indirect
    /// call per frame): not generic, so the loop is compiled here, at this
    /// crate's optimisation level, rather than in the caller's crate. The
    /// firmware is built for size but keeps this crate at `opt-level = 2`
    /// (`firmware/Cargo.toml`); through the generic [`Locomotion::frame`]
    /// the loop would be compiled as part of the firmware crate, and its
    /// own work per step measured 62 K instructions instead of 47 K.
    #[inline(never)]
    pub fn frame_dyn(
        &mut self,
        mut net: &mut dyn Network<f32>,
        action: FrameAction,
        command: &Command,
    ) -> Result<&Pose<f32>> {
        self.frame(&mut net, action, command)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cycles_wrap_into_one_turn() {
        assert_eq!(wrap_cycle(1.25f64), 0.25);
        assert_eq!(wrap_cycle(-0.25f64), 0.75);
        assert_eq!(wrap_cycle(-1e-20f32), 0.0);
        assert_eq!(wrap_cycle(f32::NAN), 0.0);
    }

    /// A float network whose output `bad` is `value` from frame `from` on.
    struct Poisoned {
        bad: usize,
        value: f32,
        from: u32,
        frames: u32,
    }

    impl Network<f32> for Poisoned {
        fn input_dim(&self) -> usize {
            INPUTS
        }
        fn output_dim(&self) -> usize {
            OUTPUTS
        }
        fn predict(&mut self, _phase: f32, _x: &[f32], y: &mut [f32]) -> Result<()> {
            y.fill(0.01);
            if self.frames >= self.from {
                y[self.bad] = self.value;
            }
            self.frames += 1;
            Ok(())
        }
        fn mean_output(&self, y: &mut [f32]) -> Result<()> {
            y.fill(0.0);
            Ok(())
        }
    }

    /// A frame whose network output is NaN or infinite is refused with
    /// `NonFinite` naming the output, and never reaches the pose.
    #[test]
    fn a_non_finite_frame_is_refused_and_leaves_the_pose() {
        for value in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let mut net = Poisoned {
                bad: 200,
                value,
                from: 1,
                frames: 0,
            };
            let mut state = Locomotion::new(&net).unwrap();
            let cmd = Command::moving([0.0, 1.0], crate::Gait::Walk);
            state.step(&mut net, &cmd).unwrap();
            let before = state.pose().clone();
            assert_eq!(
                state.step(&mut net, &cmd).unwrap_err(),
                Error::NonFinite { index: 200 }
            );
            let after = state.pose();
            assert_eq!(after.frame, before.frame);
            assert_eq!(after.joint_positions, before.joint_positions);
            assert!(after
                .joint_positions
                .iter()
                .flatten()
                .all(|v| v.is_finite()));
        }
    }
}
