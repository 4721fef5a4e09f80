//! `host-sim target`: runs the Cortex-M4 firmware (`firmware/`) under
//! `qemu-system-arm -machine mps2-an386 -icount shift=0` with a model blob
//! (and optionally style blobs) flashed on their own, feeds it frames, each
//! with its mix of styles, and checks every output bit for bit against the
//! styled runtime on the host with the same mix per frame. Reports
//! instructions per frame, MACs per frame (base and adapters), flash and RAM
//! use, and the firmware's decoded defmt log.
//!
//! How the pieces talk (see `docs/firmware.md`):
//! - the blob goes to the MODEL region, the style blobs (packed into one
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
//! and every pose is compared with the same loop on the host.

pub mod build;
pub mod controller;
pub mod elf;
pub mod frames;
pub mod log;
pub mod qemu;
pub mod snapshot;
pub mod styles;
pub mod synthetic;
#[cfg(test)]
mod tests;
/// The host <-> firmware wire format (the `phasegate-wire` crate the
/// firmware also depends on).
pub use phasegate_wire as wire;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, ensure, Context, Result};
use phasegate::{Mix, Model, Phase, Runtime, Style};

pub use build::{build_controller_firmware, build_firmware, cargo_build, firmware_dir, repo_root};
pub use elf::ElfInfo;
pub use frames::Frames;
pub use qemu::qemu_available;
pub use styles::{MixGroup, MixSpec, StyleFile};

/// Instructions per SysTick tick under `-icount shift=0`: the MPS2 SysTick
/// runs from the 25 MHz system clock (40 ns) and each instruction takes 1 ns.
pub const INSTRUCTIONS_PER_TICK: u64 = 40;
/// Issue 4's budget for static RAM (.data + .bss + .uninit) plus the
/// measured stack.
pub const RAM_BUDGET: u64 = 64 * 1024;
/// Issue 4's budget for .text.
pub const TEXT_BUDGET: u64 = 64 * 1024;
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
    /// Per-frame mix schedule (default: [`MixSpec::default_for`] the number
    /// of styles).
    pub mix: Option<MixSpec>,
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
    /// Min, median (lower middle) and max of `values`.
    pub fn of(values: &[u64]) -> Stats {
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

/// Refuses a run whose calibration loop did not take one tick per 40
/// instructions: QEMU was not counting instructions, so no figure holds.
pub(crate) fn check_calibration(t: &wire::Trailer) -> Result<()> {
    let ticks = u64::from(t.calib_ticks) * INSTRUCTIONS_PER_TICK;
    let want = u64::from(t.calib_instructions);
    ensure!(
        ticks >= want && ticks <= want + 2 * INSTRUCTIONS_PER_TICK,
        "SysTick calibration: {} instructions took {} ticks, expected {}: QEMU is not counting instructions (-icount shift=0)",
        t.calib_instructions,
        t.calib_ticks,
        t.calib_instructions / INSTRUCTIONS_PER_TICK as u32
    );
    Ok(())
}

/// The report lines every target run ends with: how ticks become
/// instructions, then flash and RAM use, each line starting with `prefix`.
pub(crate) fn memory_lines(
    prefix: &str,
    (calib_ticks, calib_instructions): (u32, u32),
    fl: &FlashUse,
    r: &RamUse,
) -> String {
    format!(
        "  (SysTick under -icount shift=0: 1 tick = {INSTRUCTIONS_PER_TICK} instructions; calibration loop of {calib_instructions} instructions took {calib_ticks} ticks)\n\
         {prefix}flash: .text {} B, .rodata {} B, vector table {} B, .data image {} B; total {} B\n\
         {prefix}RAM: .data {} B, .bss {} B, .uninit {} B, stack high-water {} B (of {} B); total {} B\n",
        fl.text,
        fl.rodata,
        fl.vector_table,
        fl.data_load,
        fl.total(),
        r.data,
        r.bss,
        r.uninit,
        r.stack_high_water,
        r.stack_size,
        r.total()
    )
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
    /// Multiply-accumulates per frame of the base model, from the blob header.
    pub macs_per_frame: u32,
    /// Each frame's inference instructions and multiply-accumulates (base
    /// plus the adapters its mix runs).
    pub per_frame: Vec<(u64, u64)>,
    /// The style blobs that were flashed.
    pub styles: Vec<StyleFile>,
    /// Bytes of the STYLES image, and of the STYLES region.
    pub styles_image: (usize, u64),
    /// The mix schedule.
    pub mix: MixSpec,
    /// Figures per kind of mix.
    pub mix_groups: Vec<MixGroup>,
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

    /// Inference instructions per MAC of each frame (its own MACs: base
    /// plus the adapters of its mix): min, median (lower middle), max.
    pub fn instructions_per_mac_stats(&self) -> (f64, f64, f64) {
        let mut r: Vec<f64> = self
            .per_frame
            .iter()
            .map(|&(i, m)| i as f64 / m.max(1) as f64)
            .collect();
        r.sort_by(f64::total_cmp);
        match (r.first(), r.last()) {
            (Some(&min), Some(&max)) => (min, r[(r.len() - 1) / 2], max),
            _ => (0.0, 0.0, 0.0),
        }
    }

    /// Median inference instructions per MAC (each frame against its own
    /// MACs; without styles, the median inference count over the base's
    /// MACs).
    pub fn instructions_per_mac(&self) -> f64 {
        self.instructions_per_mac_stats().1
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
        for (i, st) in self.styles.iter().enumerate() {
            let _ = writeln!(
                s,
                "style {i}: {} ({:?}, {} B, {} adapter{} beside layer {}, {} MACs per frame)",
                st.path.display(),
                st.name,
                st.bytes.len(),
                st.form,
                st.rank.map(|r| format!(" rank {r}")).unwrap_or_default(),
                st.layer,
                st.macs
            );
        }
        if !self.styles.is_empty() {
            let _ = writeln!(
                s,
                "styles image: {} B of the {} KiB STYLES region; mix schedule: {}",
                self.styles_image.0,
                self.styles_image.1 / 1024,
                self.mix
            );
        }
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
        if self.mix_groups.iter().all(|g| g.label == "base") {
            let _ = writeln!(
                s,
                "MACs per frame: {} ; {:.3} instructions per MAC (median inference)",
                self.macs_per_frame,
                self.instructions_per_mac()
            );
        } else {
            let macs = Stats::of(&self.per_frame.iter().map(|p| p.1).collect::<Vec<_>>());
            let (lo, med, hi) = self.instructions_per_mac_stats();
            let _ = writeln!(
                s,
                "MACs per frame: base {}, with the frame's adapters min {} max {} ; instructions per MAC (each frame's inference / its MACs): min {lo:.3} median {med:.3} max {hi:.3}",
                self.macs_per_frame, macs.min, macs.max
            );
            let _ = writeln!(
                s,
                "per mix: frames, inference instructions per frame (min / median / max), MACs per frame, instructions per MAC (median):"
            );
            for g in &self.mix_groups {
                let weights = if g.weights.is_empty() {
                    String::new()
                } else {
                    format!(
                        " (weights {})",
                        g.weights
                            .iter()
                            .map(|w| w.to_string())
                            .collect::<Vec<_>>()
                            .join(", ")
                    )
                };
                let _ = writeln!(
                    s,
                    "  {:<14} {:>4} frames  {} / {} / {}  {} MACs  {:.3}{weights}",
                    g.label,
                    g.frames,
                    g.infer.min,
                    g.infer.median,
                    g.infer.max,
                    g.macs,
                    g.instructions_per_mac()
                );
            }
        }
        s += &memory_lines("", self.calibration, &self.flash, &self.ram);
        let budget = match self.check_budgets() {
            Ok(()) => "ok".to_string(),
            Err(e) => format!("FAILED: {e}"),
        };
        let _ = writeln!(
            s,
            "budgets: static RAM + stack {} B <= {} B, .text {} B <= {} B: {budget}",
            self.ram.total(),
            RAM_BUDGET,
            self.flash.text,
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
pub(crate) fn time_limit(frames: usize, macs: u32) -> Duration {
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

/// Boots the firmware `elf` with `blob` (if any) at MODEL, the STYLES image
/// `styles` (if any) at STYLES and the input image `image` (if any) at
/// HOSTIO; decodes the log. Does not judge the exit code.
pub fn boot(
    elf: &ElfInfo,
    elf_path: &Path,
    blob: Option<&Path>,
    styles: Option<&[u8]>,
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
    // The images host-sim writes: what, its file name, its region, and what
    // to say when it does not fit.
    let images = [
        (
            styles,
            "styles.bin",
            elf.styles,
            "the style blobs take",
            "STYLES",
            "",
        ),
        (
            image,
            "inputs.bin",
            elf.hostio,
            "the input image is",
            "HOSTIO",
            ": run fewer frames",
        ),
    ];
    for (img, name, (start, end), what, region, hint) in images {
        let Some(img) = img else { continue };
        let room = end - start;
        ensure!(
            img.len() as u64 <= room,
            "{what} {} bytes, the {region} region (memory.x) holds {room} bytes{hint}",
            img.len()
        );
        let path = scratch.path().join(name);
        std::fs::write(&path, img).with_context(|| format!("cannot write {name}"))?;
        loads.push(qemu::Load {
            file: path,
            addr: start,
        });
    }
    let run = qemu::run(elf_path, &loads, timeout)?;
    let log = log::decode(&elf.bytes, &run.stdout)?;
    Ok(Booted { run, log })
}

/// Host reference outputs: (i16, f32) per frame, flattened, from the styled
/// runtime with `styles` added in order and each frame's mix set before it
/// (what the firmware does).
pub fn host_outputs(
    model: Model<'_>,
    styles: &[StyleFile],
    frames: &Frames,
) -> Result<(Vec<i16>, Vec<f32>)> {
    let out_dim = model.output_dim();
    let mut rt = Box::new(
        Runtime::<'_, HOST_W, HOST_S, HOST_N>::new(model)
            .context("the host runtime refuses the model")?,
    );
    for (i, st) in styles.iter().enumerate() {
        let style = Style::from_bytes(&st.bytes)
            .with_context(|| format!("style {i} ({})", st.path.display()))?;
        rt.add_style(style).with_context(|| {
            format!(
                "style {i} ({}) is refused by the host runtime",
                st.path.display()
            )
        })?;
    }
    let mut q_in = vec![0i16; frames.input_dim];
    let mut qs = Vec::with_capacity(frames.len() * out_dim);
    let mut fs = vec![0f32; frames.len() * out_dim];
    for i in 0..frames.len() {
        let mix = frames.mixes.get(i).copied().unwrap_or(Mix::Base);
        rt.set_mix(mix)
            .with_context(|| format!("frame {i}: mix {}", styles::mix_spec_item(mix)))?;
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
        h.mode == wire::Mode::Network,
        "firmware output file is in {:?} mode, expected network mode",
        h.mode
    );
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
pub(crate) fn memory_use(elf: &ElfInfo, trailer: &wire::Trailer) -> (FlashUse, RamUse) {
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
    let style_files = args
        .styles
        .iter()
        .map(|p| StyleFile::read(p))
        .collect::<Result<Vec<_>>>()?;
    let mix = args
        .mix
        .clone()
        .unwrap_or_else(|| MixSpec::default_for(style_files.len()));
    let mut frames = frames::select(
        args.inputs.as_deref(),
        args.phases.as_deref(),
        args.frames,
        &blob,
        &model,
    )?;
    frames.mixes = mix.schedule(frames.len());
    styles::check_schedule(&frames.mixes, style_files.len())?;
    let output_dim = model.output_dim();
    let macs = model.macs_per_frame();
    let model_ram_bytes = model.ram_bytes();
    let (host_q, host_f) = host_outputs(model, &style_files, &frames)?;
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
    let styles_image = styles::pack_styles(
        &style_files
            .iter()
            .map(|s| s.bytes.clone())
            .collect::<Vec<_>>(),
    );
    let frame_macs: Vec<u64> = frames
        .mixes
        .iter()
        .map(|&m| styles::frame_macs(u64::from(macs), &style_files, m))
        .collect();
    let max_macs = frame_macs.iter().copied().max().unwrap_or(u64::from(macs));
    eprintln!("running {} frames under QEMU ...", frames.len());
    let booted = boot(
        &elf,
        &elf_path,
        Some(&args.model),
        (!style_files.is_empty()).then_some(&styles_image[..]),
        Some(&image),
        time_limit(frames.len(), u32::try_from(max_macs).unwrap_or(u32::MAX)),
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
    check_calibration(&t)?;

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
    let infer = ticks_to_instr(&out.infer_ticks);
    let mix_groups = styles::mix_groups(&frames.mixes, &infer, u64::from(macs), &style_files);
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
        infer_instructions: Stats::of(&infer),
        frame_instructions: Stats::of(&ticks_to_instr(&out.frame_ticks)),
        macs_per_frame: macs,
        per_frame: infer.iter().copied().zip(frame_macs).collect(),
        styles_image: (styles_image.len(), elf.styles.1 - elf.styles.0),
        styles: style_files,
        mix,
        mix_groups,
        model_ram_bytes,
        calibration: (t.calib_ticks, t.calib_instructions),
        flash,
        ram,
        log: booted.log,
        wall: booted.run.wall,
    })
}
