//! `PfnnController`: the loop and its network, for the device; and the
//! runtime as a [`Network`].

use phasegate::{Model, Phase, Runtime};

use crate::command::Command;
use crate::deadline::FrameAction;
use crate::error::{Error, Result};
use crate::locomotion::{Locomotion, Network};
use crate::pose::Pose;

/// A PFNN locomotion controller: a network (on the device, the fixed-point
/// [`Runtime`], whose arena holds `W` elements, at least the blob's plan:
/// 1,024 for the published PFNN) and the loop's state, all in one
/// statically sized value. Nothing is allocated; put it in a `static` or on
/// a large enough stack.
///
/// ```text
/// let mut ctl: PfnnController<Runtime<'_, 1024>> =
///     PfnnController::from_model(Model::from_bytes(BLOB)?)?;
/// loop {
///     let pose = ctl.step(&Command::moving([0.0, 2.5], Gait::Walk))?;
///     drive(pose.joint_rotations);
/// }
/// ```
pub struct PfnnController<N> {
    net: N,
    state: Locomotion<f32>,
}

impl<'a, const W: usize, const S: usize, const B: usize> PfnnController<Runtime<'a, W, S, B>> {
    /// A runtime over `model` (refused when it does not fit the buffers)
    /// driving the loop; see [`PfnnController::new`].
    pub fn from_model(model: Model<'a>) -> Result<Self> {
        let (inputs, outputs) = (model.input_dim(), model.output_dim());
        if inputs != crate::layout::INPUTS || outputs != crate::layout::OUTPUTS {
            return Err(Error::NotPfnn {
                inputs: inputs as u32,
                outputs: outputs as u32,
            });
        }
        Self::new(Runtime::new(model)?)
    }
}

impl<N: Network<f32>> PfnnController<N> {
    /// Bytes of RAM the whole controller occupies (for a runtime: its
    /// activation buffers and copied header included; the weights stay in
    /// flash).
    pub const RAM_BYTES: usize = core::mem::size_of::<Self>();

    /// Bytes of the loop's own state (trajectory, joints, input and output
    /// vectors, the pose), without the network.
    pub const STATE_RAM_BYTES: usize = core::mem::size_of::<Locomotion<f32>>();

    /// Refuses networks that are not PFNN-shaped (342 inputs, 311 outputs,
    /// [`Error::NotPfnn`]); starts in the demo's reset pose.
    pub fn new(net: N) -> Result<Self> {
        let state = Locomotion::new(&net)?;
        Ok(PfnnController { net, state })
    }

    /// One frame: command in, pose out. See [`Locomotion::step`].
    pub fn step(&mut self, command: &Command) -> Result<&Pose<f32>> {
        self.state.step(&mut self.net, command)
    }

    /// One frame as a [`crate::Deadline`] allows it: see
    /// [`Locomotion::frame`] (a held frame changes nothing).
    pub fn frame(&mut self, action: FrameAction, command: &Command) -> Result<&Pose<f32>> {
        self.state.frame(&mut self.net, action, command)
    }

    /// Back to the reset pose at the origin.
    pub fn reset(&mut self) -> Result<()> {
        self.state.reset(&self.net)
    }

    /// The last pose.
    pub fn pose(&self) -> &Pose<f32> {
        self.state.pose()
    }

    /// The loop (its last network input and output, for inspection).
    pub fn state(&self) -> &Locomotion<f32> {
        &self.state
    }

    /// The network.
    pub fn network(&self) -> &N {
        &self.net
    }

    /// The network, mutably (for a styled runtime: set its mix between
    /// two steps).
    pub fn network_mut(&mut self) -> &mut N {
        &mut self.net
    }

    /// [`Self::RAM_BYTES`], for callers holding a value.
    pub fn ram_bytes(&self) -> usize {
        Self::RAM_BYTES
    }
}

/// Budget: the loop's state must stay a small fraction of a 256 KiB part.
const _: () = assert!(core::mem::size_of::<Locomotion<f32>>() <= 12 * 1024);

/// The phase of `cycles` in `[0, 1)` as the runtime's U0.32 fraction:
/// scaling by `2^32` is exact in `f32`, the conversion truncates (and
/// saturates), identically on every target.
pub fn phase_from_cycles(cycles: f32) -> Phase {
    let bits = (cycles * 4_294_967_296.0) as u64;
    Phase::from_bits(bits.min(u64::from(u32::MAX)) as u32)
}

/// The runtime drives the loop, plain or styled: set its mix between two
/// [`Locomotion::step`]s to switch or blend styles. The loop's state (the
/// phase included) is the caller's and no style touches it.
impl<const W: usize, const S: usize, const B: usize> Network<f32> for Runtime<'_, W, S, B> {
    fn input_dim(&self) -> usize {
        self.model().input_dim()
    }

    fn output_dim(&self) -> usize {
        self.model().output_dim()
    }

    fn predict(&mut self, phase: f32, x: &[f32], y: &mut [f32]) -> Result<()> {
        Ok(self.run(phase_from_cycles(phase), x, y)?)
    }

    /// The base's mean output (the output stage's offsets: the exporter
    /// stores `Ymean` there, a zero network output de-quantises to it): the
    /// loop starts from the same pose whatever the style.
    fn mean_output(&self, y: &mut [f32]) -> Result<()> {
        let model = self.model();
        let expected = model.output_dim();
        if y.len() != expected {
            return Err(Error::Runtime(phasegate::Error::LengthMismatch {
                expected: expected as u32,
                found: y.len() as u32,
            }));
        }
        for (o, (_, offset)) in y.iter_mut().zip(model.output_stage()) {
            *o = offset;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::command::{Gait, GaitWeights};

    /// The embedded default model of host-sim (random weights, PFNN-shaped).
    const BLOB: &[u8] = include_bytes!("../../tests/golden/default/model.blob");

    fn controller() -> PfnnController<Runtime<'static, 1024>> {
        PfnnController::from_model(Model::from_bytes(BLOB).unwrap()).unwrap()
    }

    #[test]
    fn runs_and_stays_finite_on_the_default_model() {
        let mut c = controller();
        for f in 0..300 {
            let gait = [Gait::Stand, Gait::Walk, Gait::Jog, Gait::Crouch][f / 75];
            let pose = c.step(&Command::moving([0.5, 2.0], gait)).unwrap();
            assert!(pose.is_finite(), "frame {f}");
            assert!((0.0..1.0).contains(&pose.phase));
            assert_eq!(pose.frame, f as u32 + 1);
        }
    }

    #[test]
    fn hostile_commands_never_panic_nor_poison_the_pose() {
        let mut c = controller();
        let hostile = [
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::MAX,
            -f32::MAX,
            1e30,
            -1e-45,
            0.0,
        ];
        let mut refused = 0;
        for (i, &a) in hostile.iter().enumerate() {
            for &b in &hostile {
                let before = c.pose().clone();
                let cmd = Command {
                    velocity: [a, b],
                    facing: [b, a],
                    gait: GaitWeights {
                        stand: a,
                        walk: b,
                        jog: -a,
                        crouch: 7.0 * b,
                    },
                };
                match c.step(&cmd) {
                    Ok(p) => assert!(p.is_finite(), "{cmd:?}"),
                    Err(Error::BadCommand { field }) => {
                        refused += 1;
                        assert!(field < 8);
                        // A refused frame changes nothing.
                        assert_eq!(c.pose(), &before);
                    }
                    Err(e) => panic!("{e} for {cmd:?} ({i})"),
                }
            }
        }
        assert!(refused > 0);
        // And it still walks afterwards.
        let p = c.step(&Command::moving([0.0, 2.5], Gait::Walk)).unwrap();
        assert!(p.is_finite());
    }

    #[test]
    fn same_commands_same_bits() {
        let run = || {
            let mut c = controller();
            let mut trace = Vec::new();
            for f in 0..120 {
                let turn = f as f32 * 0.02;
                let p = c
                    .step(&Command::moving(
                        [2.0 * turn.sin(), 2.0 * turn.cos()],
                        Gait::Walk,
                    ))
                    .unwrap();
                trace.extend(p.joint_positions.iter().flatten().map(|v| v.to_bits()));
                trace.push(p.phase.to_bits());
            }
            trace
        };
        assert_eq!(run(), run());
    }

    #[test]
    fn reset_returns_to_the_first_pose() {
        let mut c = controller();
        let first = c.pose().clone();
        for _ in 0..10 {
            c.step(&Command::moving([1.0, 1.0], Gait::Jog)).unwrap();
        }
        assert_ne!(c.pose(), &first);
        c.reset().unwrap();
        assert_eq!(c.pose(), &first);
    }

    #[test]
    fn refuses_a_model_of_the_wrong_shape_and_reports_its_ram() {
        let (all, state) = (
            PfnnController::<Runtime<'static, 1024>>::RAM_BYTES,
            PfnnController::<Runtime<'static, 1024>>::STATE_RAM_BYTES,
        );
        println!("controller RAM: {all} bytes, of which loop state {state}");
        assert!(all >= state + Runtime::<'static, 1024>::CAPACITY_BYTES);
        // Too small buffers are refused, not overrun.
        let m = Model::from_bytes(BLOB).unwrap();
        assert!(matches!(
            PfnnController::<Runtime<'static, 16>>::from_model(m),
            Err(Error::Runtime(phasegate::Error::BufferTooSmall { .. }))
        ));
    }

    #[test]
    fn phase_conversion_is_exact_on_binary_fractions() {
        assert_eq!(phase_from_cycles(0.5).to_bits(), 1 << 31);
        assert_eq!(phase_from_cycles(0.0).to_bits(), 0);
        assert_eq!(phase_from_cycles(0.999_999_94).to_bits(), 0xFFFF_FF00);
    }
}
