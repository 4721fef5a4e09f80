//! `PfnnController`: the loop on the fixed-point runtime, for the device.

use super::command::Command;
use super::layout::{INPUTS, OUTPUTS};
use super::locomotion::{Locomotion, Network};
use super::pose::Pose;
use crate::error::{Error, Result};
use crate::fixed::phase::Phase;
use crate::model::Model;
use crate::runtime::Runtime;
use crate::style::StyledRuntime;

/// A PFNN locomotion controller: a validated PFNN blob, its activation
/// buffers (`W` elements each, at least the widest layer: 512 for the
/// published PFNN) and the loop's state, all in one statically sized value.
/// Nothing is allocated; put it in a `static` or on a large enough stack.
///
/// ```text
/// let mut ctl: PfnnController<'_, 512> = PfnnController::new(Model::from_bytes(BLOB)?)?;
/// loop {
///     let pose = ctl.step(&Command::moving([0.0, 2.5], Gait::Walk))?;
///     drive(pose.joint_rotations);
/// }
/// ```
pub struct PfnnController<'a, const W: usize> {
    net: Runtime<'a, W>,
    state: Locomotion<f32>,
}

impl<'a, const W: usize> PfnnController<'a, W> {
    /// Bytes of RAM the whole controller occupies (the runtime's activation
    /// buffers and copied header included; the weights stay in flash).
    pub const RAM_BYTES: usize = core::mem::size_of::<Self>();

    /// Bytes of the loop's own state (trajectory, joints, input and output
    /// vectors, the pose), without the runtime.
    pub const STATE_RAM_BYTES: usize = core::mem::size_of::<Locomotion<f32>>();

    /// Refuses models that are not PFNN-shaped (342 inputs, 311 outputs) or
    /// do not fit the buffers; starts in the demo's reset pose.
    pub fn new(model: Model<'a>) -> Result<Self> {
        let (inputs, outputs) = (model.input_dim(), model.output_dim());
        if inputs != INPUTS || outputs != OUTPUTS {
            return Err(Error::NotPfnn {
                inputs: inputs as u32,
                outputs: outputs as u32,
            });
        }
        let net = Runtime::new(model)?;
        let state = Locomotion::new(&net)?;
        Ok(PfnnController { net, state })
    }

    /// One frame: command in, pose out. See [`Locomotion::step`].
    pub fn step(&mut self, command: &Command) -> Result<&Pose<f32>> {
        self.state.step(&mut self.net, command)
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

    /// The runtime.
    pub fn runtime(&self) -> &Runtime<'a, W> {
        &self.net
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

impl<const W: usize> Network<f32> for Runtime<'_, W> {
    fn predict(&mut self, phase: f32, x: &[f32; INPUTS], y: &mut [f32; OUTPUTS]) -> Result<()> {
        self.run(phase_from_cycles(phase), x, y)
    }

    fn mean_output(&self, y: &mut [f32; OUTPUTS]) -> Result<()> {
        mean_output_of(self.model(), y)
    }
}

/// A styled runtime drives the same loop: set its mix between two
/// [`Locomotion::step`]s to switch or blend styles. The loop's state (the
/// phase included) is the caller's and no style touches it.
impl<const W: usize, const S: usize, const N: usize> Network<f32> for StyledRuntime<'_, W, S, N> {
    fn predict(&mut self, phase: f32, x: &[f32; INPUTS], y: &mut [f32; OUTPUTS]) -> Result<()> {
        self.run(phase_from_cycles(phase), x, y)
    }

    /// The base's mean output: the loop starts from the same pose whatever
    /// the style.
    fn mean_output(&self, y: &mut [f32; OUTPUTS]) -> Result<()> {
        mean_output_of(self.model(), y)
    }
}

/// The output stage's offsets: the exporter stores `Ymean` there (a zero
/// network output de-quantises to it).
fn mean_output_of(model: &Model<'_>, y: &mut [f32; OUTPUTS]) -> Result<()> {
    let mut n = 0;
    for (o, (_, offset)) in y.iter_mut().zip(model.output_stage()) {
        *o = offset;
        n += 1;
    }
    if n == OUTPUTS {
        Ok(())
    } else {
        Err(Error::NotPfnn {
            inputs: model.input_dim() as u32,
            outputs: n as u32,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::controller::command::{Gait, GaitWeights};

    /// The embedded default model of host-sim (random weights, PFNN-shaped).
    const BLOB: &[u8] = include_bytes!("../../../tests/golden/default/model.blob");

    fn controller() -> PfnnController<'static, 512> {
        PfnnController::new(Model::from_bytes(BLOB).unwrap()).unwrap()
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
            PfnnController::<'static, 512>::RAM_BYTES,
            PfnnController::<'static, 512>::STATE_RAM_BYTES,
        );
        println!("controller RAM: {all} bytes, of which loop state {state}");
        assert!(all >= state + Runtime::<'static, 512>::CAPACITY_BYTES);
        // Too small buffers are refused, not overrun.
        let m = Model::from_bytes(BLOB).unwrap();
        assert!(matches!(
            PfnnController::<'static, 16>::new(m),
            Err(Error::BufferTooSmall { .. })
        ));
    }

    #[test]
    fn phase_conversion_is_exact_on_binary_fractions() {
        assert_eq!(phase_from_cycles(0.5).to_bits(), 1 << 31);
        assert_eq!(phase_from_cycles(0.0).to_bits(), 0);
        assert_eq!(phase_from_cycles(0.999_999_94).to_bits(), 0xFFFF_FF00);
    }
}
