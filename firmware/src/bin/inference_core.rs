//! The inference core: the smallest firmware that does the product's job,
//! for the code-size figures of `host-sim footprint` (docs/performance.md).
//!
//! It validates the model blob in the MODEL region, runs the frames of the
//! input image in the HOSTIO region (network mode, base mix only) and
//! writes the outputs file and its trailer through semihosting, in the
//! format of the full firmware (`phasegate-wire`), so `host-sim` checks it
//! bit for bit the same way. No log, no styles, no controller, no per-stage
//! profile: only what passing data in and out needs. Every op (dense, CP,
//! diagonal, softmax) is compiled in, as the blob chooses at run time.
#![no_std]
#![no_main]
#![deny(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    clippy::indexing_slicing
)]

// The stack painter and SysTick reader of the full firmware; the per-stage
// timer in it is not used here.
#[allow(dead_code)]
#[path = "../measure.rs"]
mod measure;
#[path = "../region.rs"]
mod region;
#[path = "../slot.rs"]
mod slot;
#[path = "../staging.rs"]
mod staging;
use region::region;

use phasegate_wire as wire;

use cortex_m_rt::{entry, exception, ExceptionFrame};
use phasegate::{Mix, Model, Phase, Runtime};
use semihosting::fs::File;
use semihosting::io::Write as _;
use slot::Slot;
use staging::Staging;

/// Activation arena (i16 elements), as the full firmware's.
const A: usize = 1536;

/// The runtime without a style bank.
type Rt = Runtime<'static, A>;

/// The runtime, once loaded.
static RUNTIME: Slot<Rt> = Slot::empty();

/// Staging buffers for one frame.
static IO: Slot<Staging> = Slot::with(Staging::ZERO);

/// defmt needs a global logger at link time (`defmt.x`, shared with the
/// full firmware, asks for one); this one drops everything: the core does
/// not log.
#[defmt::global_logger]
struct NoLog;

// SAFETY: nothing to acquire or release; every byte is dropped.
unsafe impl defmt::Logger for NoLog {
    fn acquire() {}
    unsafe fn flush() {}
    unsafe fn release() {}
    unsafe fn write(_bytes: &[u8]) {}
}

extern "C" {
    static _phasegate_model_start: u8;
    static _phasegate_model_end: u8;
    static _phasegate_hostio_start: u8;
    static _phasegate_hostio_end: u8;
}

fn exit(code: i32) -> ! {
    semihosting::process::exit(code)
}

#[entry]
fn main() -> ! {
    measure::paint_stack();
    let Some(mut cp) = cortex_m::Peripherals::take() else {
        exit(wire::exit::PANIC)
    };
    measure::start_ticks(&mut cp.SYST);
    let calib_ticks = measure::calibrate();
    // SAFETY: reserved in memory.x, filled before reset, never written.
    let (model_region, hostio) = unsafe {
        (
            region(
                &raw const _phasegate_model_start,
                &raw const _phasegate_model_end,
            ),
            region(
                &raw const _phasegate_hostio_start,
                &raw const _phasegate_hostio_end,
            ),
        )
    };
    let Ok(model) = Model::from_region(model_region) else {
        exit(wire::exit::BAD_MODEL)
    };
    let (input_dim, output_dim) = (model.input_dim(), model.output_dim());
    let Ok(rt) = Rt::new(model) else {
        exit(wire::exit::BAD_MODEL)
    };
    let Some(rt) = RUNTIME.init(rt) else {
        exit(wire::exit::PANIC)
    };
    // SAFETY: IO is made with `Slot::with`.
    let Some(io) = (unsafe { IO.take() }) else {
        exit(wire::exit::PANIC)
    };
    let (input, records) = match wire::InputHeader::parse(hostio) {
        Ok(v) => v,
        Err(wire::WireError::BadMagic) => finish(0, calib_ticks, None),
        Err(_) => exit(wire::exit::BAD_INPUT),
    };
    if input.mode != wire::Mode::Network {
        exit(wire::exit::NO_CONTROLLER);
    }
    if input.input_dim as usize != input_dim || input.output_dim as usize != output_dim {
        exit(wire::exit::BAD_INPUT);
    }
    let header = wire::OutputHeader {
        frames: input.frames,
        output_dim: input.output_dim,
        input_crc: input.crc,
        mode: input.mode,
    };
    let Ok(mut file) = File::create(c"phasegate-out.bin") else {
        exit(wire::exit::OUTPUT_ERROR)
    };
    if file.write_all(&header.encode()).is_err() {
        exit(wire::exit::OUTPUT_ERROR);
    }
    let (Some(inputs), Some(inputs_q), Some(outputs_q), Some(outputs), Some(record)) = (
        io.inputs.get_mut(..input_dim),
        io.inputs_q.get_mut(..input_dim),
        io.outputs_q.get_mut(..output_dim),
        io.outputs.get_mut(..output_dim),
        io.record.get_mut(..header.record_len()),
    ) else {
        exit(wire::exit::BAD_MODEL)
    };
    let mut frames_done = 0u32;
    for rec in records.chunks_exact(input.record_len()) {
        let t0 = measure::now();
        let Some(r) = wire::read_record(rec, inputs) else {
            exit(wire::exit::BAD_INPUT)
        };
        if wire::decode_mix(&r.mix) != Ok(Mix::Base) {
            exit(wire::exit::FRAME_ERROR);
        }
        let Ok(phase) = Phase::from_radians(r.phase) else {
            exit(wire::exit::FRAME_ERROR)
        };
        if rt.quantise_input(inputs, inputs_q).is_err() {
            exit(wire::exit::FRAME_ERROR);
        }
        let t1 = measure::now();
        let result = rt
            .run_quantised(phase, inputs_q)
            .map(|q| outputs_q.copy_from_slice(q));
        let t2 = measure::now();
        if result
            .and_then(|()| rt.dequantise_output(outputs_q, outputs))
            .is_err()
        {
            exit(wire::exit::FRAME_ERROR);
        }
        let head = wire::RecordHead {
            infer_ticks: measure::elapsed(t1, t2),
            frame_ticks: measure::elapsed(t0, measure::now()),
        };
        if wire::encode_record(head, outputs_q, outputs, record).is_none()
            || file.write_all(record).is_err()
        {
            exit(wire::exit::OUTPUT_ERROR);
        }
        frames_done += 1;
    }
    finish(frames_done, calib_ticks, Some(file))
}

/// Measures the stack, writes the trailer (when there is an output file)
/// and exits with success.
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
            exit(wire::exit::OUTPUT_ERROR);
        }
    }
    exit(wire::exit::OK)
}

#[panic_handler]
fn panic(_: &core::panic::PanicInfo) -> ! {
    exit(wire::exit::PANIC)
}

#[exception]
unsafe fn HardFault(_: &ExceptionFrame) -> ! {
    exit(wire::exit::HARD_FAULT)
}

#[exception]
unsafe fn DefaultHandler(_: i16) {
    exit(wire::exit::HARD_FAULT)
}
