//! The DSP dense kernels' self-test under QEMU (`--features kernel-check`):
//! runs [`CASES`] seeded random cases through the assembly kernels and the
//! portable reference (`phasegate::ops::dense::kernel_check`), then
//! [`CP_CASES`] random CP layers through the runtime and a scalar
//! reference (`phasegate::ops::cp::cp_check`), logs every
//! mismatching seed and exits 0 when all agree, 1 otherwise (a hard fault,
//! e.g. a misaligned `LDM`, exits with `wire::exit::HARD_FAULT`).
//! `host-sim/tests/kernel_check.rs` builds and runs it.
#![no_std]
#![no_main]

// The single-core critical section defmt needs.
use cortex_m as _;
use cortex_m_rt::{entry, exception, ExceptionFrame};
use defmt::{error, info};
use defmt_semihosting as _;
use phasegate::ops::cp::cp_check;
use phasegate::ops::dense::kernel_check;
use phasegate_wire as wire;

/// Random cases per run (about 40 M instructions under QEMU).
const CASES: u64 = 20_000;
/// Random CP layers per run (`phasegate::ops::cp::cp_check`).
const CP_CASES: u64 = 2_000;

#[entry]
fn main() -> ! {
    let mut bad = 0u32;
    for seed in 0..CASES {
        if !kernel_check(seed) {
            error!("kernel mismatch: seed {=u64}", seed);
            bad += 1;
        }
    }
    info!("kernel check: {=u64} cases, {=u32} mismatches", CASES, bad);
    let mut cp_bad = 0u32;
    for seed in 0..CP_CASES {
        if !cp_check(seed) {
            error!("CP layer mismatch: seed {=u64}", seed);
            cp_bad += 1;
        }
    }
    info!(
        "CP check: {=u64} cases, {=u32} mismatches",
        CP_CASES, cp_bad
    );
    bad += cp_bad;
    semihosting::process::exit(if bad == 0 { 0 } else { 1 })
}

#[panic_handler]
fn panic(_: &core::panic::PanicInfo) -> ! {
    semihosting::process::exit(wire::exit::PANIC)
}

#[exception]
unsafe fn HardFault(frame: &ExceptionFrame) -> ! {
    error!("hard fault at pc {=u32:#010x}", frame.pc());
    semihosting::process::exit(wire::exit::HARD_FAULT)
}
