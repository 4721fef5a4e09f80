//! phasegate firmware for the MPS2-AN386 board (Cortex-M4F) under QEMU.
//!
//! Boot sequence:
//! 1. paint the free stack, start SysTick, time a calibration loop;
//! 2. validate the model blob flashed on its own at the MODEL region
//!    (memory.x); a bad or missing blob is refused with the runtime's typed
//!    error and exit code [`wire::exit::BAD_MODEL`], never a panic. With
//!    the `rig` feature (the reach build), if the STYLES region starts with
//!    a rig blob (an OMG rig's autoencoder, bound to the motion blob in
//!    MODEL by its payload CRC), the two run as one model
//!    (`Model::with_rig_region`) and step 4 is skipped; a refused rig
//!    (built for another motion blob, incompatible, damaged) exits with
//!    [`wire::exit::BAD_RIG`];
//! 3. with the `self-test` feature (every QEMU build but the inference
//!    core), if the blob has a self-test section, run its vectors through
//!    the base model and compare every output; a mismatch is logged naming
//!    the vector and output and exits with [`wire::exit::SELF_TEST_FAILED`]
//!    (skipped, with a log line, when a rig is loaded: the section is the
//!    motion blob's alone);
//! 4. add every style blob flashed in the STYLES region (blobs back to
//!    back at 16-byte aligned offsets, up to the first offset without the
//!    blob magic) to the styled runtime; a refused style (damaged, built
//!    for another base, incompatible, too big, bank full) is logged with
//!    the runtime's typed error and exits with [`wire::exit::BAD_STYLE`];
//! 5. if the host loaded an input image at the HOSTIO region, run every
//!    frame (mix -> `set_mix`; phase in radians and f32 inputs -> quantise
//!    -> integer inference with the frame's adapters -> de-quantise),
//!    timing each with SysTick, and write the outputs and timings to
//!    `phasegate-out.bin` through semihosting, and (except in the
//!    controller build) each frame's SysTick ticks per stage (input, gate,
//!    each node, output) to `phasegate-profile.bin`;
//! 6. write the stack high-water mark and exit through semihosting.
//!
//! Logs are defmt frames on semihosting stdout; `host-sim target` decodes
//! them. The wire formats and exit codes are in the `phasegate-wire` crate
//! (`wire/`, shared with host-sim) and `docs/firmware.md`.
#![no_std]
#![no_main]
#![deny(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    clippy::indexing_slicing
)]

mod measure;
mod region;
mod slot;
mod staging;
use region::{model_region, region};
#[cfg(feature = "reach")]
mod reach;
#[cfg(feature = "controller")]
mod status_pin;
// The wire format, shared with host-sim.
use phasegate_wire as wire;

use slot::Slot;
use staging::{Staging, W};

use cortex_m_rt::{entry, exception, ExceptionFrame};
#[cfg(feature = "controller")]
use defmt::warn;
use defmt::{error, info, Display2Format};
use defmt_semihosting as _;
use phasegate::blob::{LayerOp, Nodes as _, MAGIC};
use phasegate::{Model, Phase, Runtime, Style};
#[cfg(any(feature = "controller", feature = "reach"))]
use phasegate_controller::Network;
#[cfg(feature = "controller")]
use phasegate_controller::{layout, Deadline, Locomotion, TickSource};
use semihosting::fs::File;
use semihosting::io::Write as _;

/// Capacity (i16 elements) of the activation arena. The real PFNN's plan
/// needs 1,024 (a 512-wide layer's input and output); a CP layer of rank
/// up to 512 between two 512-wide layers needs 1,536 (input, middle vector
/// and output live together).
#[cfg(not(feature = "oversize-buffers"))]
const A: usize = 1536;
/// The must-fail case: 2^20 elements is 2 MiB of activations alone, far
/// beyond the 256 KiB RAM region, so this build does not link.
#[cfg(feature = "oversize-buffers")]
const A: usize = 1 << 20;

/// Capacity (i16 elements) of the styled runtime's adapter scratch buffer:
/// a style needs two adapter outputs (for blending) plus a CP adapter's
/// middle vector, so this holds a rank-64 CP adapter beside a 512-wide
/// layer (any full or diagonal adapter up to 512 wide). A bigger style is
/// refused at boot with `BufferTooSmall`.
const S: usize = 2 * 512 + 64;

/// Styles the bank holds (the STYLES region may hold more; the fifth is
/// refused with `TooManyStyles`).
const N: usize = 4;

/// Byte alignment of each style blob's offset in the STYLES region.
const STYLE_ALIGN: usize = 16;

/// The runtime: the base model, its activation arena, the adapter scratch
/// buffer and the bank of styles.
type Rt = Runtime<'static, A, S, N>;

/// Staging buffers for one frame (in .bss, not on the stack).
struct Io {
    staging: Staging,
    /// The frame's stage timings (its profile record).
    timer: measure::StageTimer,
}

static RUNTIME: Slot<Rt> = Slot::empty();
static IO: Slot<Io> = Slot::with(Io {
    staging: Staging::ZERO,
    timer: measure::StageTimer::new(),
});

extern "C" {
    static _phasegate_model_start: u8;
    static _phasegate_model_end: u8;
    static _phasegate_styles_start: u8;
    static _phasegate_styles_end: u8;
    static _phasegate_hostio_start: u8;
    static _phasegate_hostio_end: u8;
    static _phasegate_bigmodel_start: u8;
    static _phasegate_bigmodel_end: u8;
}

fn exit(code: i32) -> ! {
    semihosting::process::exit(code)
}

#[entry]
fn main() -> ! {
    measure::paint_stack();
    let mut cp = match cortex_m::Peripherals::take() {
        Some(cp) => cp,
        None => exit(wire::exit::PANIC),
    };
    measure::start_ticks(&mut cp.SYST);
    info!(
        "phasegate firmware {=str} on MPS2-AN386 (Cortex-M4F)",
        env!("CARGO_PKG_VERSION")
    );
    let calib_ticks = measure::calibrate();
    info!(
        "SysTick calibration: {=u32} instructions took {=u32} ticks",
        measure::CALIB_INSTRUCTIONS,
        calib_ticks
    );

    // SAFETY: the MODEL, BIGMODEL, STYLES and HOSTIO regions are reserved
    // in memory.x, filled by the loader before reset and never written by
    // the firmware.
    let (model_region, styles_region, hostio) = unsafe {
        (
            model_region(
                region(
                    &raw const _phasegate_model_start,
                    &raw const _phasegate_model_end,
                ),
                region(
                    &raw const _phasegate_bigmodel_start,
                    &raw const _phasegate_bigmodel_end,
                ),
            ),
            region(
                &raw const _phasegate_styles_start,
                &raw const _phasegate_styles_end,
            ),
            region(
                &raw const _phasegate_hostio_start,
                &raw const _phasegate_hostio_end,
            ),
        )
    };
    let model_addr = model_region.as_ptr() as u32;

    let model = match Model::from_region(model_region) {
        Ok(m) => m,
        Err(e) => {
            error!(
                "model blob at {=u32:#010x} refused: {} ({})",
                model_addr,
                e,
                Display2Format(&e)
            );
            exit(wire::exit::BAD_MODEL);
        }
    };
    info!(
        "model blob at {=u32:#010x}: {=usize} bytes, {}",
        model_addr,
        model.blob_len(),
        model.header()
    );
    #[cfg(feature = "self-test")]
    let motion_test = model.self_test().is_some();
    let (model, rigged) = with_rig(model, styles_region);
    #[cfg(feature = "self-test")]
    if rigged && motion_test {
        info!("self-test not run: it is the motion blob's alone, and a rig is loaded");
    }
    let (input_dim, output_dim) = (model.input_dim(), model.output_dim());
    let rt = match init_runtime(model) {
        Ok(rt) => rt,
        Err(e) => {
            error!(
                "model refused by the runtime: {} ({})",
                e,
                Display2Format(&e)
            );
            exit(wire::exit::BAD_MODEL);
        }
    };
    info!(
        "runtime ready: {=usize} B activation and adapter buffers, {=usize} B with the bank of {=usize} styles; the model needs {=usize} B",
        Rt::CAPACITY_BYTES,
        core::mem::size_of::<Rt>(),
        N,
        rt.model().ram_bytes()
    );
    #[cfg(feature = "self-test")]
    run_self_test(rt);
    if !rigged {
        load_styles(rt, styles_region);
    }

    let (input, records) = match wire::InputHeader::parse(hostio) {
        Ok(v) => v,
        Err(wire::WireError::BadMagic) => {
            info!(
                "no input image at {=u32:#010x}: model validated, no frames to run",
                hostio.as_ptr() as u32
            );
            finish(0, calib_ticks, None);
        }
        Err(e) => {
            error!(
                "input image at {=u32:#010x} refused: {}",
                hostio.as_ptr() as u32,
                e
            );
            exit(wire::exit::BAD_INPUT);
        }
    };
    // Controller and reach modes share one entry, so the inference build
    // (which refuses both) keeps one refusal.
    if input.mode != wire::Mode::Network {
        let after = hostio.get(input.image_len() as usize..).unwrap_or(&[]);
        run_controller(rt, &input, records, after, calib_ticks);
    }
    if input.input_dim as usize != input_dim || input.output_dim as usize != output_dim {
        error!(
            "input image is for a {=u32} -> {=u32} model, the blob is {=usize} -> {=usize}",
            input.input_dim, input.output_dim, input_dim, output_dim
        );
        exit(wire::exit::BAD_INPUT);
    }
    info!("input image: {=u32} frames", input.frames);

    // SAFETY: IO is made with `Slot::with`.
    let Some(io) = (unsafe { IO.take() }) else {
        exit(wire::exit::PANIC)
    };
    let out_header = wire::OutputHeader {
        frames: input.frames,
        output_dim: input.output_dim,
        input_crc: input.crc,
        mode: input.mode,
    };
    let mut file = create_output(&out_header);
    let profile_header = wire::ProfileHeader {
        frames: input.frames,
        stages: wire::ProfileHeader::stages_for(rt.model().header().nodes.count()),
        input_crc: input.crc,
    };
    let mut profile_file = PROFILE.then(|| create_profile(&profile_header));

    // Checked here rather than trusted, so no slice panics: a model wider
    // than the staging buffers is refused.
    let record_len = out_header.record_len();
    let timer = &mut io.timer;
    let (Some(inputs), Some(inputs_q), Some(outputs_q), Some(outputs), Some(record)) = (
        io.staging.inputs.get_mut(..input_dim),
        io.staging.inputs_q.get_mut(..input_dim),
        io.staging.outputs_q.get_mut(..output_dim),
        io.staging.outputs.get_mut(..output_dim),
        io.staging.record.get_mut(..record_len),
    ) else {
        error!(
            "model dimensions exceed the firmware's {=usize}-element buffers",
            W
        );
        exit(wire::exit::BAD_MODEL);
    };
    let mut frames_done = 0u32;
    for (i, rec) in records.chunks_exact(input.record_len()).enumerate() {
        let t0 = measure::now();
        let Some(input_record) = wire::read_record(rec, inputs) else {
            exit(wire::exit::BAD_INPUT)
        };
        let mix = match wire::decode_mix(&input_record.mix) {
            Ok(mix) => mix,
            Err(e) => {
                // defmt's own formatting only: `WireError`'s `Display`
                // pulls in u64 formatting (about 1.5 KB of .text).
                error!("frame {=usize}: mix field refused: {}", i, e);
                exit(wire::exit::FRAME_ERROR);
            }
        };
        if let Err(e) = rt.set_mix(mix) {
            // (Not `mix` itself: its defmt impl formats the blend weight
            // through `core::fmt` and `fixed`, about 5 KB of .text.)
            error!(
                "frame {=usize}: mix refused: {} ({})",
                i,
                e,
                Display2Format(&e)
            );
            exit(wire::exit::FRAME_ERROR);
        }
        // The profile's stages: input from here, then the runtime's marks
        // (gate, each node's preparation and op), then output.
        timer.start();
        let prepared = Phase::from_radians(input_record.phase).and_then(|phase| {
            rt.quantise_input(inputs, inputs_q)?;
            Ok(phase)
        });
        let phase = match prepared {
            Ok(p) => p,
            Err(e) => {
                error!(
                    "frame {=usize}: input refused: {} ({})",
                    i,
                    e,
                    Display2Format(&e)
                );
                exit(wire::exit::FRAME_ERROR);
            }
        };
        measure::phasegate_trace_mark();
        let t1 = measure::now();
        let result = infer(rt, phase, inputs_q, timer).map(|q| outputs_q.copy_from_slice(q));
        let t2 = measure::now();
        measure::phasegate_trace_mark();
        if let Err(e) = result.and_then(|()| rt.dequantise_output(outputs_q, outputs)) {
            error!("frame {=usize}: {} ({})", i, e, Display2Format(&e));
            exit(wire::exit::FRAME_ERROR);
        }
        timer.close(wire::StageKind::Output, 0);
        let t3 = measure::now();
        if let Some(f) = profile_file.as_mut() {
            write_profile(timer, profile_header.record_len(), f);
        }
        let head = wire::RecordHead {
            infer_ticks: measure::elapsed(t1, t2),
            frame_ticks: measure::elapsed(t0, t3),
        };
        if wire::encode_record(head, outputs_q, outputs, record).is_none()
            || file.write_all(record).is_err()
        {
            error!("frame {=usize}: cannot write {=str}", i, wire::OUTPUT_FILE);
            exit(wire::exit::OUTPUT_ERROR);
        }
        frames_done += 1;
    }
    info!(
        "{=u32} frames run, outputs written to {=str}",
        frames_done,
        wire::OUTPUT_FILE
    );
    drop(profile_file);
    finish(frames_done, calib_ticks, Some(file));
}

/// Whether network frames are timed stage by stage and written to the
/// profile file: not in the controller build, whose loop runs the executor
/// through `Runtime::run` already, so probing here too would link a second
/// copy of it (about 3 KB of `.text`).
const PROFILE: bool = cfg!(not(any(feature = "controller", feature = "reach")));

/// One frame's integer inference, its stages timed by `timer`.
#[cfg(not(any(feature = "controller", feature = "reach")))]
#[inline(always)]
fn infer<'r>(
    rt: &'r mut Rt,
    phase: Phase,
    inputs_q: &[i16],
    timer: &mut measure::StageTimer,
) -> phasegate::Result<&'r [i16]> {
    rt.run_quantised_probed(phase, inputs_q, timer)
}

/// One frame's integer inference, untimed ([`PROFILE`]).
#[cfg(any(feature = "controller", feature = "reach"))]
#[inline(always)]
fn infer<'r>(
    rt: &'r mut Rt,
    phase: Phase,
    inputs_q: &[i16],
    _: &mut measure::StageTimer,
) -> phasegate::Result<&'r [i16]> {
    rt.run_quantised(phase, inputs_q)
}

/// Writes the frame's profile record (`len` bytes: the model's stage
/// count) to the profile file; exits with [`wire::exit::OUTPUT_ERROR`] when
/// the count differs or the write fails.
#[inline(never)]
fn write_profile(timer: &measure::StageTimer, len: usize, file: &mut File) {
    let Some(record) = timer.record().filter(|r| r.len() == len) else {
        error!("unexpected number of stages in a frame");
        exit(wire::exit::OUTPUT_ERROR);
    };
    if file.write_all(record).is_err() {
        error!("cannot write {=str}", wire::PROFILE_FILE);
        exit(wire::exit::OUTPUT_ERROR);
    }
}

/// Creates the profile file and writes its header; exits with
/// [`wire::exit::OUTPUT_ERROR`] on failure.
fn create_profile(header: &wire::ProfileHeader) -> File {
    let mut file = match File::create(c"phasegate-profile.bin") {
        Ok(f) => f,
        Err(_) => {
            error!("cannot create {=str} on the host", wire::PROFILE_FILE);
            exit(wire::exit::OUTPUT_ERROR);
        }
    };
    if file.write_all(&header.encode()).is_err() {
        error!("cannot write {=str}", wire::PROFILE_FILE);
        exit(wire::exit::OUTPUT_ERROR);
    }
    file
}

/// Creates the output file and writes its header; exits with
/// [`wire::exit::OUTPUT_ERROR`] on failure.
fn create_output(header: &wire::OutputHeader) -> File {
    let mut file = match File::create(c"phasegate-out.bin") {
        Ok(f) => f,
        Err(_) => {
            error!(
                "cannot create {=str} on the host (semihosting)",
                wire::OUTPUT_FILE
            );
            exit(wire::exit::OUTPUT_ERROR);
        }
    };
    if file.write_all(&header.encode()).is_err() {
        error!("cannot write {=str}", wire::OUTPUT_FILE);
        exit(wire::exit::OUTPUT_ERROR);
    }
    file
}

/// Controller and reach modes without the `controller` or `reach`
/// feature: refused.
#[cfg(not(any(feature = "controller", feature = "reach")))]
#[inline(never)]
fn run_controller(_: &mut Rt, _: &wire::InputHeader, _: &[u8], _: &[u8], _: u32) -> ! {
    error!("controller mode is not built into this firmware (cargo build --release --features controller)");
    exit(wire::exit::NO_CONTROLLER);
}

/// The loop's state, in .bss (about 6 KB: trajectory, joint velocities,
/// the network's input and output vectors, the pose).
#[cfg(feature = "controller")]
static LOCOMOTION: Slot<Locomotion<f32>> = Slot::empty();

/// The styled runtime as the loop's network, timing each inference.
#[cfg(any(feature = "controller", feature = "reach"))]
struct Timed<'r> {
    rt: &'r mut Rt,
    ticks: u32,
}

#[cfg(any(feature = "controller", feature = "reach"))]
impl Network<f32> for Timed<'_> {
    fn input_dim(&self) -> usize {
        self.rt.model().input_dim()
    }

    fn output_dim(&self) -> usize {
        self.rt.model().output_dim()
    }

    fn predict(
        &mut self,
        phase: f32,
        x: &[f32],
        y: &mut [f32],
    ) -> phasegate_controller::Result<()> {
        let t0 = measure::now();
        let r = self.rt.predict(phase, x, y);
        self.ticks = self
            .ticks
            .wrapping_add(measure::elapsed(t0, measure::now()));
        r
    }

    fn mean_output(&self, y: &mut [f32]) -> phasegate_controller::Result<()> {
        self.rt.mean_output(y)
    }
}

/// Makes the loop's state (reset from the model's mean output) and moves
/// it into its static. Not inlined, for the same reason as
/// [`init_runtime`].
#[cfg(feature = "controller")]
#[inline(never)]
fn init_locomotion(rt: &Rt) -> phasegate_controller::Result<&'static mut Locomotion<f32>> {
    let state = Locomotion::new(rt)?;
    match LOCOMOTION.init(state) {
        Some(s) => Ok(s),
        None => exit(wire::exit::PANIC),
    }
}

/// SysTick as the deadline's tick source.
#[cfg(feature = "controller")]
struct SysTicks;

#[cfg(feature = "controller")]
impl TickSource for SysTicks {
    fn now_ticks(&mut self) -> u64 {
        measure::now()
    }
}

/// Controller and reach modes in a firmware built with the `controller`
/// feature (the locomotion loop, mode 1), the `reach` feature (the
/// reaching loop, mode 2: [`reach::run_reach`]) or both; a mode not built
/// in is refused.
#[cfg(any(feature = "controller", feature = "reach"))]
#[inline(never)]
fn run_controller(
    rt: &mut Rt,
    input: &wire::InputHeader,
    records: &[u8],
    after: &[u8],
    calib_ticks: u32,
) -> ! {
    #[cfg(not(feature = "controller"))]
    let _ = after;
    match input.mode {
        #[cfg(feature = "reach")]
        wire::Mode::Reach => reach::run_reach(rt, input, records, calib_ticks),
        #[cfg(feature = "controller")]
        wire::Mode::Controller => run_locomotion(rt, input, records, after, calib_ticks),
        _ => {
            error!("this mode is not built into this firmware (features controller: locomotion, reach: reaching)");
            exit(wire::exit::NO_CONTROLLER);
        }
    }
}

/// Controller mode: per record, `set_mix`
/// then `Locomotion::frame` with
/// the record's command, timed by the deadline read from the block after
/// the records (`after`; none: frames are timed, nothing overruns); writes
/// each pose, its timings and its deadline status; never returns.
#[cfg(feature = "controller")]
#[inline(never)]
fn run_locomotion(
    rt: &mut Rt,
    input: &wire::InputHeader,
    records: &[u8],
    after: &[u8],
    calib_ticks: u32,
) -> ! {
    let model = rt.model();
    let (inputs, outputs) = (model.input_dim(), model.output_dim());
    if inputs != layout::INPUTS || outputs != layout::OUTPUTS {
        let e = phasegate_controller::Error::NotPfnn {
            inputs: inputs as u32,
            outputs: outputs as u32,
        };
        error!("controller refused: {} ({})", e, Display2Format(&e));
        exit(wire::exit::NOT_PFNN);
    }
    if input.input_dim as usize != inputs || input.output_dim as usize != outputs {
        error!(
            "input image is for a {=u32} -> {=u32} model, the blob is {=usize} -> {=usize}",
            input.input_dim, input.output_dim, inputs, outputs
        );
        exit(wire::exit::BAD_INPUT);
    }
    let config = match wire::parse_deadline(after) {
        Ok(c) => c,
        Err(e) => {
            error!("input image's deadline block refused: {}", e);
            exit(wire::exit::BAD_INPUT);
        }
    };
    let state = match init_locomotion(rt) {
        Ok(s) => s,
        Err(e) => {
            error!("controller refused: {} ({})", e, Display2Format(&e));
            exit(wire::exit::NOT_PFNN);
        }
    };
    info!(
        "controller mode: {=u32} commands, loop state {=usize} B",
        input.frames,
        core::mem::size_of::<Locomotion<f32>>()
    );
    if let Some(b) = config.budget {
        info!(
            "deadline: {=u32} ticks per frame, on overrun {}; status pin FPGAIO LED0",
            b.ticks(),
            config.policy
        );
    }
    // SAFETY: IO is made with `Slot::with`.
    let Some(io) = (unsafe { IO.take() }) else {
        exit(wire::exit::PANIC)
    };
    let Some(record) = io.staging.record.get_mut(..wire::POSE_RECORD_LEN) else {
        exit(wire::exit::PANIC)
    };
    let mut file = create_output(&wire::OutputHeader {
        frames: input.frames,
        output_dim: input.output_dim,
        input_crc: input.crc,
        mode: input.mode,
    });
    // The pin's error type is `Infallible`.
    let Ok(mut deadline) = Deadline::new(config, status_pin::FpgaioLed::new(0), SysTicks);
    let mut net = Timed { rt, ticks: 0 };
    let mut frames_done = 0u32;
    for (i, rec) in records.chunks_exact(input.record_len()).enumerate() {
        let Some((mix, command)) = wire::read_command_record(rec) else {
            exit(wire::exit::BAD_INPUT)
        };
        let mix = match wire::decode_mix(&mix) {
            Ok(mix) => mix,
            Err(e) => {
                error!("frame {=usize}: mix field refused: {}", i, e);
                exit(wire::exit::FRAME_ERROR);
            }
        };
        if let Err(e) = net.rt.set_mix(mix) {
            error!(
                "frame {=usize}: mix refused: {} ({})",
                i,
                e,
                Display2Format(&e)
            );
            exit(wire::exit::FRAME_ERROR);
        }
        net.ticks = 0;
        let timed = deadline.frame(|action| state.frame_dyn(&mut net, action, &command));
        let o = timed.outcome;
        let pose = match timed.result {
            Ok(p) => p,
            Err(e) => {
                error!("frame {=usize}: {} ({})", i, e, Display2Format(&e));
                exit(wire::exit::FRAME_ERROR);
            }
        };
        if o.overrun {
            warn!(
                "frame {=usize} overran its budget: {=u32} ticks > {=u32}; next frame: {}",
                i,
                o.ticks,
                config.budget.map_or(0, |b| b.ticks()),
                o.next
            );
        }
        let head = wire::RecordHead {
            infer_ticks: net.ticks,
            frame_ticks: o.ticks,
        };
        let status = wire::FrameStatus {
            overrun: o.overrun,
            held: o.held,
            pin_high: deadline.pin().is_set_high(),
        };
        if wire::encode_pose_record(head, status, pose, record).is_none()
            || file.write_all(record).is_err()
        {
            error!("frame {=usize}: cannot write {=str}", i, wire::OUTPUT_FILE);
            exit(wire::exit::OUTPUT_ERROR);
        }
        frames_done += 1;
    }
    info!(
        "{=u32} controller steps run, poses written to {=str}",
        frames_done,
        wire::OUTPUT_FILE
    );
    if config.budget.is_some() {
        info!(
            "deadline: {=u32} of {=u32} frames overran, {=u32} held; status pin {=bool}",
            deadline.overruns(),
            deadline.frames(),
            deadline.held(),
            deadline.pin().is_set_high()
        );
    }
    finish(frames_done, calib_ticks, Some(file));
}

/// Makes the runtime and moves it into its static. Not inlined, so the
/// transient `Runtime` value lives in this short-lived frame rather
/// than in `main`'s, which stays on the stack for the whole run.
#[inline(never)]
/// Boot step 3: the blob's self-test (`docs/blob-format.md`, "Self-test
/// section"), before any style is added: every stored vector through the
/// base model, compared with the outputs the exporter's runtime computed.
/// Nothing is logged for a blob without one; a mismatch is logged naming
/// the vector and output and exits with [`wire::exit::SELF_TEST_FAILED`]:
/// the model is never run.
#[cfg(feature = "self-test")]
fn run_self_test(rt: &mut Rt) {
    let t0 = measure::now();
    let result = rt.run_self_test();
    let ticks = measure::elapsed(t0, measure::now());
    match result {
        Ok(0) => {}
        Ok(n) => info!(
            "self-test: {=u16} vectors passed, bit for bit ({=u32} SysTick ticks)",
            n, ticks
        ),
        Err(phasegate::Error::SelfTestFailed {
            vector,
            output,
            expected,
            got,
        }) => {
            error!(
                "self-test failed: vector {=u16} output {=u16}: expected {=i16}, got {=i16}; the model is refused",
                vector,
                output,
                expected,
                got
            );
            exit(wire::exit::SELF_TEST_FAILED);
        }
        Err(e) => {
            error!("self-test could not run: {} ({})", e, Display2Format(&e));
            exit(wire::exit::SELF_TEST_FAILED);
        }
    }
}

fn init_runtime(model: Model<'static>) -> Result<&'static mut Rt, phasegate::Error> {
    let rt = Rt::new(model)?;
    match RUNTIME.init(rt) {
        Some(rt) => Ok(rt),
        None => exit(wire::exit::PANIC),
    }
}

/// Without the `rig` feature: the model alone (a rig blob in STYLES is
/// then refused as a style, `NotAStyle`).
#[cfg(not(feature = "rig"))]
fn with_rig(motion: Model<'static>, _companion: &'static [u8]) -> (Model<'static>, bool) {
    (motion, false)
}

/// `motion` with the rig blob that starts `companion` (the STYLES region),
/// if its header says it is one; `true` if so. Exits with
/// [`wire::exit::BAD_RIG`] when the rig is refused.
#[cfg(feature = "rig")]
fn with_rig(motion: Model<'static>, companion: &'static [u8]) -> (Model<'static>, bool) {
    let is_rig = matches!(
        phasegate::blob::header_from_prefix(companion),
        Ok(h) if matches!(h.kind, phasegate::blob::ModelKind::Rig { .. })
    );
    if !is_rig {
        return (motion, false);
    }
    let addr = companion.as_ptr() as u32;
    let info = phasegate::blob::blob_len_from_prefix(companion)
        .and_then(|len| phasegate::RigInfo::from_bytes(companion.get(..len).unwrap_or(companion)));
    match info.and_then(|info| Ok((motion.with_rig_region(companion)?, info))) {
        Ok((pair, info)) => {
            info!(
                "rig blob at {=u32:#010x}: \"{=str}\", {=usize} bytes, for the motion blob with payload CRC {=u32:#010x}; the pair needs {=usize} B",
                addr,
                info.name,
                info.blob_len,
                info.base_crc,
                pair.ram_bytes()
            );
            (pair, true)
        }
        Err(e) => {
            error!(
                "rig blob at {=u32:#010x} refused: {} ({})",
                addr,
                e,
                Display2Format(&e)
            );
            exit(wire::exit::BAD_RIG);
        }
    }
}

/// Adds every style blob in the STYLES region to the runtime, in order
/// (style id = position): blobs start at 16-byte aligned offsets, and the
/// list ends at the first offset that does not start with the blob magic
/// (erased or zero memory) or at the end of the region. Logs each style;
/// exits with [`wire::exit::BAD_STYLE`] on the first one refused.
#[inline(never)]
fn load_styles(rt: &mut Rt, styles: &'static [u8]) {
    let base = styles.as_ptr() as u32;
    let mut offset = 0usize;
    while let Some(rest) = styles.get(offset..) {
        if rest.get(..MAGIC.len()) != Some(&MAGIC[..]) {
            break;
        }
        let addr = base.wrapping_add(offset as u32);
        let index = rt.styles().len();
        let added = Style::from_region(rest).and_then(|s| Ok((rt.add_style(s)?, s)));
        let (id, style) = match added {
            Ok(v) => v,
            Err(e) => {
                error!(
                    "style {=usize} at {=u32:#010x} refused: {} ({})",
                    index,
                    addr,
                    e,
                    Display2Format(&e)
                );
                exit(wire::exit::BAD_STYLE);
            }
        };
        let desc = style.kernel().desc();
        info!(
            "style {=u8} at {=u32:#010x}: \"{=str}\", {=usize} bytes, beside layer {=u8}, {=u64} MACs per frame",
            id.0,
            addr,
            style.name(),
            style.blob_len(),
            style.layer(),
            style.macs_per_frame()
        );
        match desc.op {
            LayerOp::Cp { rank, .. } => info!(
                "style {=u8}: CP adapter {=u16} -> {=u16}, rank {=u16}, {} weights",
                id.0, desc.in_dim, desc.out_dim, rank, desc.weights
            ),
            LayerOp::Diagonal => info!(
                "style {=u8}: diagonal adapter {=u16} -> {=u16}, {} weights",
                id.0, desc.in_dim, desc.out_dim, desc.weights
            ),
            #[cfg(feature = "dec")]
            LayerOp::Dec { .. } => info!(
                "style {=u8}: DEC adapter {=u16} -> {=u16}, {} weights",
                id.0, desc.in_dim, desc.out_dim, desc.weights
            ),
            LayerOp::Dense | LayerOp::Rbf { .. } => info!(
                "style {=u8}: {=str} adapter {=u16} -> {=u16}, {} weights",
                id.0,
                if desc.op == LayerOp::Dense {
                    "full"
                } else {
                    "RBF"
                },
                desc.in_dim,
                desc.out_dim,
                desc.weights
            ),
        }
        let next = offset
            .checked_add(style.blob_len())
            .and_then(|end| end.checked_next_multiple_of(STYLE_ALIGN));
        match next {
            Some(n) => offset = n,
            None => break,
        }
    }
    info!(
        "{=usize} styles in the STYLES region at {=u32:#010x}",
        rt.styles().len(),
        base
    );
}

/// Measures the stack, writes the trailer (when there is an output file) and
/// exits with success.
fn finish(frames_done: u32, calib_ticks: u32, file: Option<File>) -> ! {
    let trailer = wire::Trailer {
        frames_done,
        stack_high_water: measure::stack_high_water(),
        stack_size: measure::stack_size(),
        calib_ticks,
        calib_instructions: measure::CALIB_INSTRUCTIONS,
    };
    if let Some(mut file) = file {
        if file.write_all(&trailer.encode()).is_err() {
            error!("cannot write {=str}", wire::OUTPUT_FILE);
            exit(wire::exit::OUTPUT_ERROR);
        }
        drop(file);
    }
    exit(wire::exit::OK)
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    error!("panic: {}", Display2Format(info));
    exit(wire::exit::PANIC)
}

#[exception]
unsafe fn HardFault(frame: &ExceptionFrame) -> ! {
    error!("hard fault at pc {=u32:#010x}", frame.pc());
    exit(wire::exit::HARD_FAULT)
}

#[exception]
unsafe fn DefaultHandler(irqn: i16) {
    error!("unexpected exception or interrupt {=i16}", irqn);
    exit(wire::exit::HARD_FAULT)
}
