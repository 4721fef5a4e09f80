//! The controllers on the host: the fixed-point `PfnnController` and the
//! float reference, which is the very same loop (`phasegate_controller::
//! Locomotion`) run in `f64` (or `f32`) over the float network. Fixed and
//! float therefore differ only in the network's arithmetic and in rounding.

mod float_net;

pub use float_net::{FloatNet32, FloatNet64};

use anyhow::{anyhow, Result};
use exporter::net::Net;
use phasegate::{Model, Runtime};
use phasegate_controller::layout::{Outputs, JOINTS, OUTPUTS};
use phasegate_controller::{Command, Locomotion, Network, PfnnController, Pose, Real};

/// Activation arena capacity of host controllers (i16 elements): the
/// published PFNN's plan needs 1,024, CP variants a few hundred more.
pub const HOST_WIDTH: usize = 4096;

/// Something that turns a command stream into poses.
pub trait Controller {
    /// One frame.
    fn step(&mut self, command: &Command) -> Result<Pose<f64>>;
    /// Joint positions of the mean pose (root space), from the network's
    /// mean output: the reference for bone lengths.
    fn mean_pose(&self) -> [[f64; 3]; JOINTS];
    /// A one-line description for reports.
    fn describe(&self) -> String;
}

/// The device controller's type on the host: the loop over a runtime
/// with a [`HOST_WIDTH`]-element arena.
pub type HostController<'a> = PfnnController<Runtime<'a, HOST_WIDTH>>;

/// The device controller, on the host.
pub struct FixedController<'a> {
    inner: Box<HostController<'a>>,
    label: String,
}

impl<'a> FixedController<'a> {
    /// Loads and validates `blob`.
    pub fn new(blob: &'a [u8], label: impl Into<String>) -> Result<Self> {
        let model = Model::from_bytes(blob).map_err(|e| anyhow!("model blob: {e}"))?;
        let inner =
            Box::new(PfnnController::from_model(model).map_err(|e| anyhow!("controller: {e}"))?);
        Ok(FixedController {
            inner,
            label: label.into(),
        })
    }

    /// The controller itself.
    pub fn inner(&self) -> &HostController<'a> {
        &self.inner
    }

    /// RAM of this controller on a device whose arena is sized for the
    /// model (`A` = its planned arena) rather than for any model as on the
    /// host: `PfnnController::<A>::RAM_BYTES`, bytes.
    pub fn device_ram_bytes(&self) -> usize {
        let need = self.inner.network().model().arena_elements();
        device_ram_bytes(need)
    }
}

/// `PfnnController::<A>::RAM_BYTES` for a run-time `A`: the host type's size
/// less the arena bytes it has beyond `A` (the arena's end is padded to the
/// next 8-byte field).
pub fn device_ram_bytes(arena: usize) -> usize {
    let bytes = |elements: usize| (2 * elements).next_multiple_of(8);
    HostController::RAM_BYTES - (bytes(HOST_WIDTH) - bytes(arena.min(HOST_WIDTH)))
}

impl Controller for FixedController<'_> {
    fn step(&mut self, command: &Command) -> Result<Pose<f64>> {
        let p = self.inner.step(command).map_err(|e| anyhow!("{e}"))?;
        Ok(widen(p))
    }

    fn mean_pose(&self) -> [[f64; 3]; JOINTS] {
        let mut y = [0f32; OUTPUTS];
        match Network::mean_output(self.inner.network(), &mut y) {
            Ok(()) => mean_positions(&y),
            Err(_) => [[0.0; 3]; JOINTS],
        }
    }

    fn describe(&self) -> String {
        self.label.clone()
    }
}

/// The float reference: the same loop over the float network.
pub struct FloatController<R, N> {
    state: Locomotion<R>,
    net: N,
    label: String,
}

impl<R: Real, N: Network<R>> FloatController<R, N> {
    /// Starts in the reset pose.
    pub fn new(net: N, label: impl Into<String>) -> Result<Self> {
        let state = Locomotion::new(&net).map_err(|e| anyhow!("{e}"))?;
        Ok(FloatController {
            state,
            net,
            label: label.into(),
        })
    }

    /// The loop's state.
    pub fn state(&self) -> &Locomotion<R> {
        &self.state
    }
}

/// The f64 reference over `net`.
pub fn reference_f64(net: &Net) -> Result<FloatController<f64, FloatNet64<'_>>> {
    FloatController::new(
        FloatNet64(net),
        format!("float reference (f64, {} gating)", net.mode),
    )
}

/// The f32 float controller over `net` (weights rounded to f32).
pub fn reference_f32(net: &Net) -> Result<FloatController<f32, FloatNet32>> {
    FloatController::new(
        FloatNet32::new(net)?,
        format!("float controller (f32, {} gating)", net.mode),
    )
}

impl<R: Real, N: Network<R>> Controller for FloatController<R, N> {
    fn step(&mut self, command: &Command) -> Result<Pose<f64>> {
        let p = self
            .state
            .step(&mut self.net, command)
            .map_err(|e| anyhow!("{e}"))?;
        Ok(widen(p))
    }

    fn mean_pose(&self) -> [[f64; 3]; JOINTS] {
        let mut y = [R::ZERO; OUTPUTS];
        match self.net.mean_output(&mut y) {
            Ok(()) => mean_positions(&y),
            Err(_) => [[0.0; 3]; JOINTS],
        }
    }

    fn describe(&self) -> String {
        self.label.clone()
    }
}

fn mean_positions<R: Real>(y: &[R; OUTPUTS]) -> [[f64; 3]; JOINTS] {
    let mut out = [[0.0; 3]; JOINTS];
    if let Some(o) = Outputs::split(y) {
        for (dst, src) in out.iter_mut().zip(o.positions.chunks_exact(3)) {
            for (d, s) in dst.iter_mut().zip(src) {
                *d = s.to_f64();
            }
        }
    }
    out
}

/// A pose in f64 (exact for f32 poses).
pub fn widen<R: Real>(p: &Pose<R>) -> Pose<f64> {
    let w = |v: R| v.to_f64();
    Pose {
        frame: p.frame,
        root_position: p.root_position.map(w),
        facing: p.facing.map(w),
        joint_positions: p.joint_positions.map(|j| j.map(w)),
        joint_rotations: p.joint_rotations.map(|q| q.map(w)),
        contacts: p.contacts.map(w),
        phase: w(p.phase),
        gaits: p.gaits.map(w),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn device_ram_matches_the_device_type() {
        assert_eq!(
            device_ram_bytes(1024),
            PfnnController::<Runtime<'static, 1024>>::RAM_BYTES
        );
        assert_eq!(
            device_ram_bytes(374),
            PfnnController::<Runtime<'static, 374>>::RAM_BYTES
        );
    }
}
