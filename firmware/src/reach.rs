//! Reach mode (input images of mode 2, `controller` feature): the OMG
//! reaching loop (`Reach<f32, W>` over the runtime) from the image's first
//! frame, with the image's layout and cost mode (and, for a joint-velocity
//! model, its skeleton and start joint angles and velocities:
//! `Reach::with_dofs`); per record, the hands'
//! targets are set (a refused one is recorded, the previous one holds) and
//! one `Reach::step` runs; every frame `X` is written with its timings.

use defmt::{error, info, Display2Format};
use phasegate_controller::reach::{Skeleton, MAX_DOFS};
use phasegate_controller::{Error, Reach};
use semihosting::io::Write as _;

use crate::staging::W;
use crate::wire::reach::{self as wr, TargetOutcome};
use crate::{create_output, exit, finish, measure, wire, Rt, Slot, Timed, IO};

/// The loop's state, in .bss: three frames of up to [`W`] f32 (the
/// current frame, the network's output, the targets), the layout and room
/// for a skeleton with its joint angles and velocities. Made in place from
/// its idle constant: the 8.8 KB state never passes through the stack.
static REACH: Slot<Reach<f32, W>> = Slot::with(Reach::IDLE);

/// Starts the loop in its static from the setup (`Reach::restart`, or
/// `Reach::restart_dofs` with the setup's skeleton, checked by
/// `Skeleton::new`, and start state); a refusal is logged with its typed
/// error and exits with `BAD_LAYOUT`.
#[inline(never)]
fn init_reach(rt: &Rt, setup: wr::Setup<'_>, first: &mut [f32]) -> &'static mut Reach<f32, W> {
    if wr::read_f32(setup.first, first).is_none() {
        exit(wire::exit::BAD_INPUT);
    }
    // SAFETY: REACH is made with `Slot::with`.
    let Some(state) = (unsafe { REACH.take() }) else {
        exit(wire::exit::PANIC)
    };
    let made = match setup.dofs {
        None => state.restart(rt, setup.layout, setup.mode, first),
        Some(d) => restart_dofs(state, rt, setup.layout, setup.mode, d, first),
    };
    if let Err(e) = made {
        error!("reaching loop refused: {} ({})", e, Display2Format(&e));
        exit(wire::exit::BAD_LAYOUT);
    }
    state
}

/// A joint-velocity model's loop: its skeleton and start state from the
/// setup's section.
#[inline(never)]
fn restart_dofs(
    state: &mut Reach<f32, W>,
    rt: &Rt,
    layout: phasegate_controller::ReachLayout,
    mode: phasegate_controller::CostMode,
    d: wr::DofSetup<'_>,
    first: &[f32],
) -> phasegate_controller::Result<()> {
    let (mut q, mut v) = ([0f32; MAX_DOFS], [0f32; MAX_DOFS]);
    let n = d.dof_count;
    let (Some(q0), Some(v0)) = (q.get_mut(..n), v.get_mut(..n)) else {
        exit(wire::exit::BAD_INPUT);
    };
    if d.start(q0, v0).is_none() {
        exit(wire::exit::BAD_INPUT);
    }
    let sk = Skeleton::new(d.joints(), d.dofs(), d.fps, d.a_max)?;
    info!(
        "joint-velocity model: {=usize} joints, {=usize} DOFs, {=f32} fps",
        sk.joints().len(),
        n,
        d.fps
    );
    state.restart_dofs(rt, layout, mode, first, sk, q0, v0)
}

/// Reach mode: never returns.
#[inline(never)]
pub(crate) fn run_reach(
    rt: &mut Rt,
    input: &wire::InputHeader,
    records: &[u8],
    calib_ticks: u32,
) -> ! {
    let model = rt.model();
    let (inputs, outputs) = (model.input_dim(), model.output_dim());
    let width = input.input_dim as usize;
    if width != inputs || input.output_dim as usize != outputs {
        error!(
            "input image is for a {=u32} -> {=u32} model, the blob is {=usize} -> {=usize}",
            input.input_dim, input.output_dim, inputs, outputs
        );
        exit(wire::exit::BAD_INPUT);
    }
    // SAFETY: IO is made with `Slot::with`.
    let Some(io) = (unsafe { IO.take() }) else {
        exit(wire::exit::PANIC)
    };
    let (Some((setup, targets)), Some(first), Some(record)) = (
        wr::parse_setup(records, width),
        io.staging.inputs.get_mut(..width),
        io.staging.record.get_mut(..wr::frame_record_len(width)),
    ) else {
        error!(
            "reach setup refused, or frames wider than the firmware's {=usize}-value buffers",
            W
        );
        exit(wire::exit::BAD_INPUT);
    };
    let mode = setup.mode;
    let state = init_reach(rt, setup, first);
    info!(
        "reach mode: {=u32} frames of {=usize} values, {} costs, loop state {=usize} B",
        input.frames,
        width,
        mode,
        core::mem::size_of::<Reach<f32, W>>()
    );
    let mut file = create_output(&wire::OutputHeader {
        frames: input.frames,
        output_dim: input.input_dim,
        input_crc: input.crc,
        mode: input.mode,
    });
    let mut net = Timed { rt, ticks: 0 };
    let mut frames_done = 0u32;
    for (i, rec) in targets.chunks_exact(wr::TARGET_RECORD_LEN).enumerate() {
        let Some(hands) = wr::read_target_record(rec) else {
            exit(wire::exit::BAD_INPUT)
        };
        net.ticks = 0;
        let t0 = measure::now();
        let mut outcomes = [TargetOutcome::Kept; wr::HANDS];
        for (h, (t, o)) in hands.iter().zip(&mut outcomes).enumerate() {
            let Some(t) = t else { continue };
            *o = match state.set_target(h, t) {
                Ok(()) => TargetOutcome::Set,
                Err(Error::BadTarget { field }) => TargetOutcome::Refused { field },
                Err(e) => {
                    error!("frame {=usize}: {} ({})", i, e, Display2Format(&e));
                    exit(wire::exit::FRAME_ERROR);
                }
            };
        }
        let stepped = state.step(&mut net).map(|_| ());
        let t1 = measure::now();
        if let Err(e) = stepped {
            error!("frame {=usize}: {} ({})", i, e, Display2Format(&e));
            exit(wire::exit::FRAME_ERROR);
        }
        for (h, o) in outcomes.iter().enumerate() {
            if let TargetOutcome::Refused { field } = *o {
                info!(
                    "frame {=usize}: hand {=usize}'s target refused (field {=u8}); the previous one holds",
                    i, h, field
                );
            }
        }
        let head = wr::FrameHead {
            network_ticks: net.ticks,
            frame_ticks: measure::elapsed(t0, t1),
            frame: i as u32,
            targets: outcomes,
        };
        if wr::encode_frame_record(&head, state.frame(), record).is_none()
            || file.write_all(record).is_err()
        {
            error!("frame {=usize}: cannot write {=str}", i, wire::OUTPUT_FILE);
            exit(wire::exit::OUTPUT_ERROR);
        }
        frames_done += 1;
    }
    info!(
        "{=u32} reaching steps run, frames written to {=str}",
        frames_done,
        wire::OUTPUT_FILE
    );
    finish(frames_done, calib_ticks, Some(file));
}
