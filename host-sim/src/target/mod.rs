//! `host-sim target`: runs the Cortex-M4 firmware (`firmware/`) under
//! `qemu-system-arm -machine mps2-an386 -icount shift=0` with a model blob
//! flashed on its own, feeds it frames, and checks every output bit for bit
//! against the runtime on the host. Reports instructions per frame, MACs
//! per frame, flash and RAM use, and the firmware's decoded defmt log.
//!
//! How the pieces talk (see `docs/firmware.md`):
//! - the blob goes to the MODEL region, the input image to HOSTIO, both with
//!   `-device loader,...,force-raw=on`; their addresses come from the ELF's
//!   `_phasegate_*` symbols, which memory.x defines;
//! - the firmware logs defmt frames on semihosting stdout, writes its outputs
//!   and timings to `phasegate-out.bin` in QEMU's working directory
//!   (`wire.rs`, shared with the firmware), and exits through semihosting
//!   with a code from `wire::exit`.

pub mod build;
pub mod elf;
pub mod frames;
pub mod log;
pub mod qemu;
pub mod snapshot;
#[cfg(test)]
mod tests;
/// The host <-> firmware wire format; the same source file the firmware compiles.
#[path = "../../../firmware/src/wire.rs"]
pub mod wire;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, ensure, Context, Result};
use phasegate::{Model, Phase, Runtime};

pub use build::{build_firmware, cargo_build, firmware_dir, repo_root};
pub use elf::ElfInfo;
pub use frames::Frames;
pub use qemu::qemu_available;

/// Instructions per SysTick tick under `-icount shift=0`: the MPS2 SysTick
/// runs from the 25 MHz system clock (40 ns) and each instruction takes 1 ns.
pub const INSTRUCTIONS_PER_TICK: u64 = 40;
/// Issue 4's budget for static RAM (.data + .bss + .uninit) plus the
/// measured stack.
pub const RAM_BUDGET: u64 = 64 * 1024;
/// Issue 4's budget for .text.
pub const TEXT_BUDGET: u64 = 64 * 1024;
/// Activation capacity of the host runtime (the firmware's is 512).
const HOST_W: usize = 8192;

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
}

/// Min, median and max of a series.
#[derive(Clone, Copy, Debug, Default, Eq, PartialEq)]
pub struct Stats {
    /// Smallest.
    pub min: u64,
    /// Median (the lower middle value for an even count).
    pub median: u64,
    /// Largest.
    pub max: u64,
}

impl Stats {
    fn of(values: &[u64]) -> Stats {
        let mut v = values.to_vec();
        v.sort_unstable();
        match (v.first(), v.last()) {
            (Some(&min), Some(&max)) => Stats {
                min,
                median: v[(v.len() - 1) / 2],
                max,
            },
            _ => Stats::default(),
        }
    }
}

/// One output that differs between the firmware and the host.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Mismatch {
    /// Frame index.
    pub frame: usize,
    /// Output index.
    pub output: usize,
    /// Host runtime's quantised output.
    pub host: i16,
    /// Firmware's quantised output.
    pub target: i16,
    /// Host runtime's de-quantised output.
    pub host_f32: f32,
    /// Firmware's de-quantised output.
    pub target_f32: f32,
}

/// Flash use of the firmware image, bytes.
#[derive(Clone, Copy, Debug, Default, Eq, PartialEq)]
pub struct FlashUse {
    /// Vector table.
    pub vector_table: u64,
    /// Code.
    pub text: u64,
    /// Constants.
    pub rodata: u64,
    /// Initial values of .data (copied to RAM at boot).
    pub data_load: u64,
}

impl FlashUse {
    /// Everything in the FLASH region.
    pub fn total(&self) -> u64 {
        self.vector_table + self.text + self.rodata + self.data_load
    }
}

/// RAM use of the firmware, bytes.
#[derive(Clone, Copy, Debug, Default, Eq, PartialEq)]
pub struct RamUse {
    /// Initialised statics.
    pub data: u64,
    /// Zeroed statics (the runtime's activation buffers and the firmware's
    /// frame staging buffers).
    pub bss: u64,
    /// Uninitialised statics.
    pub uninit: u64,
    /// Deepest stack use measured by painting (includes up to 64 bytes of
    /// painter margin).
    pub stack_high_water: u64,
    /// Room for the stack (RAM region minus statics).
    pub stack_size: u64,
}

impl RamUse {
    /// Statics.
    pub fn statics(&self) -> u64 {
        self.data + self.bss + self.uninit
    }

    /// Statics plus measured stack: what issue 4 budgets.
    pub fn total(&self) -> u64 {
        self.statics() + self.stack_high_water
    }
}

/// Everything `host-sim target` measured.
#[derive(Clone, Debug)]
pub struct TargetReport {
    /// The blob that ran.
    pub model: PathBuf,
    /// Blob size, bytes.
    pub blob_len: usize,
    /// Size of the MODEL region, bytes.
    pub model_region: u64,
    /// Where the frames came from.
    pub source: String,
    /// Frames run.
    pub frames: usize,
    /// Outputs per frame.
    pub output_dim: usize,
    /// Outputs whose i16 or f32 bits differ from the host runtime (0: bit-exact).
    pub mismatches: usize,
    /// The first few of them.
    pub first_mismatches: Vec<Mismatch>,
    /// For golden vectors: host outputs that differ from `expected_q.npy`.
    pub golden_mismatches: Option<usize>,
    /// Instructions per frame spent in `run_quantised` (integer inference).
    pub infer_instructions: Stats,
    /// Instructions per whole frame (phase and input conversion, inference,
    /// de-quantisation).
    pub frame_instructions: Stats,
    /// Multiply-accumulates per frame, from the blob header.
    pub macs_per_frame: u32,
    /// Activation RAM the model needs (header), bytes.
    pub model_ram_bytes: usize,
    /// SysTick ticks the firmware's 40,000-instruction calibration loop took.
    pub calibration: (u32, u32),
    /// Flash use.
    pub flash: FlashUse,
    /// RAM use.
    pub ram: RamUse,
    /// The firmware's decoded defmt log.
    pub log: Vec<String>,
    /// QEMU's wall time.
    pub wall: Duration,
}

impl TargetReport {
    /// Whether every output of every frame matched the host bit for bit (and
    /// the golden vectors, when used).
    pub fn bit_exact(&self) -> bool {
        self.mismatches == 0 && self.golden_mismatches.unwrap_or(0) == 0
    }

    /// Median inference instructions per MAC.
    pub fn instructions_per_mac(&self) -> f64 {
        self.infer_instructions.median as f64 / f64::from(self.macs_per_frame.max(1))
    }

    /// Issue 4's memory budgets: statics plus stack within [`RAM_BUDGET`],
    /// .text within [`TEXT_BUDGET`].
    pub fn check_budgets(&self) -> Result<()> {
        let mut failures = Vec::new();
        if self.ram.total() > RAM_BUDGET {
            failures.push(format!(
                "static RAM + stack = {} B exceeds the {} B budget (.data {} + .bss {} + .uninit {} + stack {})",
                self.ram.total(),
                RAM_BUDGET,
                self.ram.data,
                self.ram.bss,
                self.ram.uninit,
                self.ram.stack_high_water
            ));
        }
        if self.flash.text > TEXT_BUDGET {
            failures.push(format!(
                ".text = {} B exceeds the {} B budget",
                self.flash.text, TEXT_BUDGET
            ));
        }
        if failures.is_empty() {
            Ok(())
        } else {
            bail!("memory budget exceeded: {}", failures.join("; "))
        }
    }

    /// The human-readable report.
    pub fn render(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "firmware log:");
        for line in &self.log {
            let _ = writeln!(s, "  {line}");
        }
        let _ = writeln!(
            s,
            "model: {} ({} B of the {} KiB MODEL region, {} B activation RAM)",
            self.model.display(),
            self.blob_len,
            self.model_region / 1024,
            self.model_ram_bytes
        );
        let _ = writeln!(s, "frames: {} from {}", self.frames, self.source);
        if self.mismatches == 0 {
            let _ = writeln!(
                s,
                "result: bit-exact: all {} frames x {} outputs equal the host runtime (i16 outputs and their f32 de-quantisation)",
                self.frames, self.output_dim
            );
        } else {
            let _ = writeln!(
                s,
                "result: MISMATCH: {} of {} outputs differ from the host runtime",
                self.mismatches,
                self.frames * self.output_dim
            );
            for m in &self.first_mismatches {
                let _ = writeln!(
                    s,
                    "  frame {} output {}: host {} ({:e}), target {} ({:e})",
                    m.frame, m.output, m.host, m.host_f32, m.target, m.target_f32
                );
            }
        }
        match self.golden_mismatches {
            Some(0) => {
                let _ = writeln!(
                    s,
                    "golden: the host runtime matches expected_q.npy bit for bit"
                );
            }
            Some(n) => {
                let _ = writeln!(
                    s,
                    "golden: MISMATCH: {n} host outputs differ from expected_q.npy"
                );
            }
            None => {}
        }
        let i = self.infer_instructions;
        let f = self.frame_instructions;
        let _ = writeln!(
            s,
            "instructions per frame (inference, run_quantised): min {} median {} max {}",
            i.min, i.median, i.max
        );
        let _ = writeln!(
            s,
            "instructions per frame (whole frame, with input quantisation and output de-quantisation): min {} median {} max {}",
            f.min, f.median, f.max
        );
        let _ = writeln!(
            s,
            "MACs per frame: {} ; {:.3} instructions per MAC (median inference)",
            self.macs_per_frame,
            self.instructions_per_mac()
        );
        let _ = writeln!(
            s,
            "  (SysTick under -icount shift=0: 1 tick = {INSTRUCTIONS_PER_TICK} instructions; calibration loop of {} instructions took {} ticks)",
            self.calibration.1, self.calibration.0
        );
        let fl = self.flash;
        let _ = writeln!(
            s,
            "flash: .text {} B, .rodata {} B, vector table {} B, .data image {} B; total {} B",
            fl.text,
            fl.rodata,
            fl.vector_table,
            fl.data_load,
            fl.total()
        );
        let r = self.ram;
        let _ = writeln!(
            s,
            "RAM: .data {} B, .bss {} B, .uninit {} B, stack high-water {} B (of {} B); total {} B",
            r.data,
            r.bss,
            r.uninit,
            r.stack_high_water,
            r.stack_size,
            r.total()
        );
        let budget = match self.check_budgets() {
            Ok(()) => "ok".to_string(),
            Err(e) => format!("FAILED: {e}"),
        };
        let _ = writeln!(
            s,
            "budgets: static RAM + stack {} B <= {} B, .text {} B <= {} B: {budget}",
            r.total(),
            RAM_BUDGET,
            fl.text,
            TEXT_BUDGET
        );
        let _ = writeln!(s, "QEMU wall time: {:.2} s", self.wall.as_secs_f64());
        s
    }
}

/// `host-sim target`: builds the firmware if needed, runs it, prints the
/// report, and fails on any mismatch.
pub fn run_target(args: &TargetArgs) -> Result<TargetReport> {
    let report = execute(args)?;
    print!("{}", report.render());
    if !report.bit_exact() {
        bail!(
            "the firmware's outputs differ from the host runtime ({} mismatching outputs{})",
            report.mismatches,
            match report.golden_mismatches {
                Some(n) if n > 0 => format!(", {n} golden mismatches"),
                _ => String::new(),
            }
        );
    }
    Ok(report)
}

/// QEMU time limit for `frames` frames of `macs` MACs: generous (QEMU with
/// -icount runs well over 50 million instructions per second here; this
/// allows 10 per MAC at 5 million per second), overridable with
/// `PHASEGATE_QEMU_TIMEOUT` (seconds).
fn time_limit(frames: usize, macs: u32) -> Duration {
    if let Some(secs) = std::env::var("PHASEGATE_QEMU_TIMEOUT")
        .ok()
        .and_then(|v| v.parse::<u64>().ok())
    {
        return Duration::from_secs(secs);
    }
    let instructions = frames as f64 * (f64::from(macs) * 10.0 + 200_000.0) + 50e6;
    Duration::from_secs_f64(60.0 + instructions / 5e6)
}

/// A firmware run with its log decoded.
pub struct Booted {
    /// The QEMU run.
    pub run: qemu::QemuRun,
    /// Decoded defmt lines.
    pub log: Vec<String>,
}

/// Boots the firmware `elf` with `blob` (if any) at MODEL and `image` (if
/// any) at HOSTIO; decodes the log. Does not judge the exit code.
pub fn boot(
    elf: &ElfInfo,
    elf_path: &Path,
    blob: Option<&Path>,
    image: Option<&[u8]>,
    timeout: Duration,
) -> Result<Booted> {
    let scratch = tempfile::Builder::new()
        .prefix("phasegate-io-")
        .tempdir()
        .context("cannot create a temporary directory")?;
    let mut loads = Vec::new();
    if let Some(b) = blob {
        let len = std::fs::metadata(b)
            .with_context(|| format!("cannot read {}", b.display()))?
            .len();
        let room = elf.model.1 - elf.model.0;
        ensure!(
            len <= room,
            "{} is {len} bytes, the MODEL region (memory.x) holds {room} bytes",
            b.display()
        );
        loads.push(qemu::Load {
            file: b.to_path_buf(),
            addr: elf.model.0,
        });
    }
    if let Some(img) = image {
        let room = elf.hostio.1 - elf.hostio.0;
        ensure!(
            img.len() as u64 <= room,
            "the input image is {} bytes, the HOSTIO region (memory.x) holds {room} bytes: run fewer frames",
            img.len()
        );
        let path = scratch.path().join("inputs.bin");
        std::fs::write(&path, img).context("cannot write the input image")?;
        loads.push(qemu::Load {
            file: path,
            addr: elf.hostio.0,
        });
    }
    let run = qemu::run(elf_path, &loads, timeout)?;
    let log = log::decode(&elf.bytes, &run.stdout)?;
    Ok(Booted { run, log })
}

/// Host reference outputs: (i16, f32) per frame, flattened.
fn host_outputs(model: Model<'_>, frames: &Frames) -> Result<(Vec<i16>, Vec<f32>)> {
    let out_dim = model.output_dim();
    let mut rt =
        Box::new(Runtime::<'_, HOST_W>::new(model).context("the host runtime refuses the model")?);
    let mut q_in = vec![0i16; frames.input_dim];
    let mut qs = Vec::with_capacity(frames.len() * out_dim);
    let mut fs = vec![0f32; frames.len() * out_dim];
    for i in 0..frames.len() {
        let phase =
            Phase::from_radians(frames.phases[i]).with_context(|| format!("frame {i}: phase"))?;
        rt.quantise_input(frames.input(i), &mut q_in)
            .with_context(|| format!("frame {i}: inputs"))?;
        let q = rt
            .run_quantised(phase, &q_in)
            .with_context(|| format!("frame {i}"))?
            .to_vec();
        rt.dequantise_output(&q, &mut fs[i * out_dim..(i + 1) * out_dim])?;
        qs.extend_from_slice(&q);
    }
    Ok((qs, fs))
}

/// The firmware's output file, parsed.
struct TargetOutputs {
    q: Vec<i16>,
    f: Vec<f32>,
    infer_ticks: Vec<u64>,
    frame_ticks: Vec<u64>,
    trailer: wire::Trailer,
}

fn parse_outputs(
    file: &[u8],
    frames: usize,
    output_dim: usize,
    input_crc: u32,
) -> Result<TargetOutputs> {
    let h = wire::OutputHeader::parse(file)
        .map_err(|e| anyhow::anyhow!("firmware output file: {e}"))?;
    ensure!(
        h.frames as usize == frames && h.output_dim as usize == output_dim && h.input_crc == input_crc,
        "firmware output file is for {} frames x {} outputs (input CRC {:#x}), expected {frames} x {output_dim} ({input_crc:#x})",
        h.frames,
        h.output_dim,
        h.input_crc
    );
    let rl = h.record_len();
    let body = &file[wire::HEADER_LEN..];
    let expected = frames * rl + wire::HEADER_LEN;
    ensure!(
        body.len() == expected,
        "firmware output file holds {} bytes after its header, expected {expected} ({frames} records and the trailer): the run stopped early",
        body.len()
    );
    let mut out = TargetOutputs {
        q: vec![0; frames * output_dim],
        f: vec![0.0; frames * output_dim],
        infer_ticks: Vec::with_capacity(frames),
        frame_ticks: Vec::with_capacity(frames),
        trailer: wire::Trailer::default(),
    };
    for i in 0..frames {
        let r = &body[i * rl..(i + 1) * rl];
        let span = i * output_dim..(i + 1) * output_dim;
        let head = wire::decode_record(r, &mut out.q[span.clone()], &mut out.f[span])
            .context("firmware output record has the wrong length")?;
        out.infer_ticks.push(u64::from(head.infer_ticks));
        out.frame_ticks.push(u64::from(head.frame_ticks));
    }
    out.trailer = wire::Trailer::parse(&body[frames * rl..])
        .map_err(|e| anyhow::anyhow!("firmware output trailer: {e}"))?;
    ensure!(
        out.trailer.frames_done as usize == frames,
        "the firmware reports {} frames done, expected {frames}",
        out.trailer.frames_done
    );
    Ok(out)
}

/// Flash and RAM figures from the ELF (and the measured stack).
fn memory_use(elf: &ElfInfo, trailer: &wire::Trailer) -> (FlashUse, RamUse) {
    let flash = FlashUse {
        vector_table: elf.size(".vector_table"),
        text: elf.size(".text"),
        rodata: elf.size(".rodata"),
        data_load: elf.size(".data"),
    };
    let ram = RamUse {
        data: elf.size(".data"),
        bss: elf.size(".bss"),
        uninit: elf.size(".uninit"),
        stack_high_water: u64::from(trailer.stack_high_water),
        stack_size: u64::from(trailer.stack_size),
    };
    (flash, ram)
}

/// Does the work of [`run_target`] without printing or judging the result.
pub fn execute(args: &TargetArgs) -> Result<TargetReport> {
    let blob = std::fs::read(&args.model)
        .with_context(|| format!("cannot read the model blob {}", args.model.display()))?;
    let model = Model::from_bytes(&blob)
        .with_context(|| format!("{} is not a valid model blob", args.model.display()))?;
    let frames = frames::select(
        args.inputs.as_deref(),
        args.phases.as_deref(),
        args.frames,
        &blob,
        &model,
    )?;
    let output_dim = model.output_dim();
    let macs = model.macs_per_frame();
    let model_ram_bytes = model.ram_bytes();
    let (host_q, host_f) = host_outputs(model, &frames)?;
    let golden_mismatches = frames.expected_q.as_ref().map(|e| {
        e.iter().zip(&host_q).filter(|(a, b)| a != b).count() + e.len().abs_diff(host_q.len())
    });

    eprintln!(
        "building the firmware (cargo build --release in {}) ...",
        firmware_dir().display()
    );
    let elf_path = build_firmware()?;
    let elf = ElfInfo::read(&elf_path)?;
    let image = frames.image(output_dim);
    let input_crc = wire::InputHeader::parse(&image)
        .map(|(h, _)| h.crc)
        .unwrap_or(0);
    eprintln!("running {} frames under QEMU ...", frames.len());
    let booted = boot(
        &elf,
        &elf_path,
        Some(&args.model),
        Some(&image),
        time_limit(frames.len(), macs),
    )?;
    if booted.run.exit_code != wire::exit::OK {
        let mut msg = format!(
            "the firmware exited with code {} ({})",
            booted.run.exit_code,
            wire::exit::describe(booted.run.exit_code)
        );
        for line in &booted.log {
            msg.push_str("\n  firmware: ");
            msg.push_str(line);
        }
        if !booted.run.stderr.trim().is_empty() {
            msg.push_str("\n  qemu: ");
            msg.push_str(booted.run.stderr.trim());
        }
        bail!(msg);
    }
    let file = booted
        .run
        .output_file
        .as_deref()
        .context("the firmware wrote no output file")?;
    let out = parse_outputs(file, frames.len(), output_dim, input_crc)?;
    let t = out.trailer;
    ensure!(
        u64::from(t.calib_ticks) * INSTRUCTIONS_PER_TICK >= u64::from(t.calib_instructions)
            && u64::from(t.calib_ticks) * INSTRUCTIONS_PER_TICK <= u64::from(t.calib_instructions) + 2 * INSTRUCTIONS_PER_TICK,
        "SysTick calibration: {} instructions took {} ticks, expected {}: QEMU is not counting instructions (-icount shift=0)",
        t.calib_instructions,
        t.calib_ticks,
        t.calib_instructions / INSTRUCTIONS_PER_TICK as u32
    );

    let mut mismatches = 0;
    let mut first_mismatches = Vec::new();
    for (k, ((&hq, &tq), (&hf, &tf))) in host_q
        .iter()
        .zip(&out.q)
        .zip(host_f.iter().zip(&out.f))
        .enumerate()
    {
        if hq != tq || hf.to_bits() != tf.to_bits() {
            mismatches += 1;
            if first_mismatches.len() < 10 {
                first_mismatches.push(Mismatch {
                    frame: k / output_dim,
                    output: k % output_dim,
                    host: hq,
                    target: tq,
                    host_f32: hf,
                    target_f32: tf,
                });
            }
        }
    }
    let ticks_to_instr = |v: &[u64]| {
        v.iter()
            .map(|t| t * INSTRUCTIONS_PER_TICK)
            .collect::<Vec<_>>()
    };
    let (flash, ram) = memory_use(&elf, &t);
    Ok(TargetReport {
        model: args.model.clone(),
        blob_len: blob.len(),
        model_region: elf.model.1 - elf.model.0,
        source: frames.source.clone(),
        frames: frames.len(),
        output_dim,
        mismatches,
        first_mismatches,
        golden_mismatches,
        infer_instructions: Stats::of(&ticks_to_instr(&out.infer_ticks)),
        frame_instructions: Stats::of(&ticks_to_instr(&out.frame_ticks)),
        macs_per_frame: macs,
        model_ram_bytes,
        calibration: (t.calib_ticks, t.calib_instructions),
        flash,
        ram,
        log: booted.log,
        wall: booted.run.wall,
    })
}
