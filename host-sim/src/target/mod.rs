//! `host-sim target`: runs the Cortex-M4 firmware (`firmware/`) under
//! `qemu-system-arm -machine mps2-an386 -icount shift=0` with a model blob
//! (and optionally style blobs) flashed on their own, feeds it frames, each
//! with its mix of styles, and checks every output bit for bit against the
//! styled runtime on the host with the same mix per frame. Reports
//! instructions per frame, MACs per frame (base and adapters), flash and RAM
//! use, and the firmware's decoded defmt log.
//!
//! How the pieces talk (see `docs/firmware.md`):
//! - the blob goes to the MODEL region (BIGMODEL, in PSRAM, when it does not
//!   fit), the style blobs (packed into one
//!   image, [`styles::pack_styles`]) to STYLES, the input image to HOSTIO,
//!   all with `-device loader,...,force-raw=on`; their addresses come from
//!   the ELF's `_phasegate_*` symbols, which memory.x defines;
//! - the firmware logs defmt frames on semihosting stdout, writes its outputs
//!   and timings to `phasegate-out.bin` in QEMU's working directory
//!   (`wire.rs`, shared with the firmware), and exits through semihosting
//!   with a code from `wire::exit`.
//!
//! With `--controller SCRIPT` ([`controller`]) the firmware built with its
//! `controller` feature runs the locomotion loop on the script's commands
//! and every pose is compared with the same loop on the host; with
//! `--reach SCRIPT` ([`reach`]) the firmware built with its `reach` feature
//! runs the OMG reaching loop and every frame is compared likewise.
//!
//! By concern: [`build`] (cargo), [`elf`] (symbols, sections), [`frames`]
//! (inputs, golden vectors), [`layers`] (per-stage figures), [`styles`] (style images, mix schedules),
//! [`qemu`] and [`run`] (booting, outputs, the host's side), [`log`]
//! (defmt), [`report`] (figures and budgets), [`cycles`] (cycle estimates), [`snapshot`] (log
//! snapshots), [`controller`] (controller mode), [`synthetic`] (test
//! models), [`self_test`] (the boot self-test, passing and corrupted).

pub mod bars;
pub mod build;
pub mod controller;
pub mod cycles;
pub mod elf;
pub mod frames;
pub mod layers;
pub mod log;
pub mod qemu;
pub mod reach;
pub mod report;
pub mod run;
pub mod self_test;
pub mod snapshot;
pub mod styles;
pub mod synthetic;
#[cfg(test)]
mod tests;
/// The host <-> firmware wire format (the `phasegate-wire` crate the
/// firmware also depends on).
pub use phasegate_wire as wire;

use std::path::PathBuf;

pub use build::{
    build_controller_firmware, build_firmware, build_inference_core, build_reach_firmware,
    cargo_build, firmware_dir, repo_root,
};
pub use elf::ElfInfo;
pub use frames::Frames;
pub use qemu::qemu_available;
pub use styles::{MixGroup, MixSpec, RigFile, StyleFile};

/// Activation arena of the host runtime, i16 elements (the firmware's is 1,536).
pub(crate) const HOST_W: usize = 16384;
/// Adapter scratch of the host runtime (the firmware's is 2 x 512 + 64).
pub(crate) const HOST_S: usize = 2 * HOST_W;
/// Style bank of the host runtime (the firmware's holds 4).
pub(crate) const HOST_N: usize = 16;

/// Arguments of `host-sim target`.
#[derive(Clone, Debug, Default)]
pub struct TargetArgs {
    /// The model blob to flash at the MODEL region.
    pub model: PathBuf,
    /// Run only the first N frames (or N generated frames).
    pub frames: Option<usize>,
    /// float32 (N, input_dim) inputs in model units.
    pub inputs: Option<PathBuf>,
    /// float32 (N,) phases in radians.
    pub phases: Option<PathBuf>,
    /// Style blobs, packed in this order into the STYLES region (style id =
    /// position).
    pub styles: Vec<PathBuf>,
    /// A rig blob for the model (a motion blob), flashed at the start of
    /// the STYLES region instead of styles: the firmware runs the pair.
    pub rig: Option<PathBuf>,
    /// Per-frame mix schedule (default: [`MixSpec::default_for`] the number
    /// of styles).
    pub mix: Option<MixSpec>,
    /// Also estimate Cortex-M4 cycles from an execution trace ([`cycles`]).
    pub cycles: bool,
    /// Also check the boot self-test both ways with this many vectors
    /// ([`self_test`]): passing, and corrupted.
    pub self_test: Option<usize>,
}

pub(crate) use report::{check_calibration, memory_lines, memory_use};
pub use report::{
    FlashUse, Mismatch, RamUse, Stats, TargetReport, FIRMWARE, INSTRUCTIONS_PER_TICK, RAM_BUDGET,
    REACH_FIRMWARE, TEXT_BUDGET,
};
pub(crate) use run::time_limit;
pub use run::{boot, execute, host_outputs, run_target, Booted};
