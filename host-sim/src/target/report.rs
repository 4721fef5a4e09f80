//! What a run on the target measured and how it is judged: frame
//! statistics, mismatches, flash and RAM use against the budgets, and the
//! printed report.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, ensure, Result};

use super::{wire, ElfInfo, MixGroup, MixSpec, StyleFile};

/// Instructions per SysTick tick under `-icount shift=0`: the MPS2 SysTick
/// runs from the 25 MHz system clock (40 ns) and each instruction takes 1 ns.
pub const INSTRUCTIONS_PER_TICK: u64 = 40;
/// Issue 4's budget for static RAM (.data + .bss + .uninit) plus the
/// measured stack.
pub const RAM_BUDGET: u64 = 64 * 1024;
/// The firmware's .text budget: issue 4's 64 KiB became issue 12's
/// budget table, the one place budgets are set
/// ([`crate::footprint::TEXT_BUDGETS`]).
pub const TEXT_BUDGET: u64 = crate::footprint::TEXT_BUDGETS.firmware;
/// The inference firmware's name in reports.
pub const FIRMWARE: &str = "firmware";
/// The reach firmware's (the OMG build: the reaching loop and rig pairs).
pub const REACH_FIRMWARE: &str = "reach firmware";
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
    /// The region the blob was loaded at (`MODEL`, or `BIGMODEL` for a blob
    /// too large for it) and its size, bytes.
    pub model_region: (&'static str, u64),
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
    /// Each stage of the frame (input, gate, each node, output), averaged
    /// over the frames, from the firmware's profile file.
    pub stages: Vec<super::layers::StageRow>,
    /// The style blobs that were flashed.
    pub styles: Vec<StyleFile>,
    /// The rig blob that was flashed (the model is then its motion blob).
    pub rig: Option<super::styles::RigFile>,
    /// Whether the reach build ran (a rig pair, or a model with a DEC
    /// node: the OMG firmware carries the `rig` and `dec` features).
    pub reach_build: bool,
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
    /// Cortex-M4 cycle estimate from an execution trace (`--cycles`).
    pub cycles: Option<super::cycles::CycleReport>,
    /// The boot self-test, passing and corrupted (`--self-test N`).
    pub self_test: Option<super::self_test::SelfTestCheck>,
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
    /// The firmware build that ran (the reach build for a rig pair or a
    /// DEC node: the one with the `rig` and `dec` features) and its .text
    /// budget.
    pub fn build(&self) -> (&'static str, u64) {
        if self.reach_build {
            (
                REACH_FIRMWARE,
                crate::footprint::TEXT_BUDGETS.reach_firmware,
            )
        } else {
            (FIRMWARE, TEXT_BUDGET)
        }
    }

    /// .text within its build's budget ([`TargetReport::build`]).
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
        let (build, budget) = self.build();
        if self.flash.text > budget {
            failures.push(format!(
                ".text = {} B exceeds the {budget} B budget of the {build}",
                self.flash.text
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
            "model: {} ({} B of the {} KiB {} region, {} B activation RAM)",
            self.model.display(),
            self.blob_len,
            self.model_region.1 / 1024,
            self.model_region.0,
            self.model_ram_bytes
        );
        if let Some(t) = &self.self_test {
            s.push_str(&t.render());
        }
        if let Some(r) = &self.rig {
            let _ = writeln!(
                s,
                "rig: {} ({:?}, {} B at the start of the {} KiB STYLES region, nodes {:#x} of the pair, for the motion blob with payload CRC {:#010x}); the activation RAM above is the pair's",
                r.path.display(),
                r.name,
                r.bytes.len(),
                self.styles_image.1 / 1024,
                r.nodes,
                r.base_crc
            );
        }
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
        if !self.stages.is_empty() {
            s += &super::layers::render(&self.stages, self.frames);
        }
        if let Some(c) = &self.cycles {
            s += &c.render(u64::from(self.macs_per_frame));
        }
        s += &memory_lines("", self.calibration, &self.flash, &self.ram);
        let budget = match self.check_budgets() {
            Ok(()) => "ok".to_string(),
            Err(e) => format!("FAILED: {e}"),
        };
        let (build, text_budget) = self.build();
        let which = if build == FIRMWARE {
            String::new()
        } else {
            format!(" ({build})")
        };
        let _ = writeln!(
            s,
            "budgets{which}: static RAM + stack {} B <= {} B, .text {} B <= {} B: {budget}",
            self.ram.total(),
            RAM_BUDGET,
            self.flash.text,
            text_budget
        );
        let _ = writeln!(s, "QEMU wall time: {:.2} s", self.wall.as_secs_f64());
        s
    }
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

/// The budget verdict of an opt-in firmware build (controller, reach):
/// its static RAM and stack against [`RAM_BUDGET`], its `.text` against
/// `text_budget`; printed, not enforced.
pub fn budget_verdict(ram: &RamUse, flash: &FlashUse, text_budget: u64) -> String {
    let mut over = Vec::new();
    if ram.total() > RAM_BUDGET {
        over.push(format!(
            "static RAM + stack {} B > {RAM_BUDGET} B",
            ram.total()
        ));
    }
    if flash.text > text_budget {
        over.push(format!(
            ".text {} B > {text_budget} B by {} B",
            flash.text,
            flash.text - text_budget
        ));
    }
    if over.is_empty() {
        "within budget".into()
    } else {
        format!("OVER BUDGET: {}", over.join("; "))
    }
}

/// The head of a loop report (controller, reach): the firmware log, then
/// the model line.
pub fn render_head(log: &[String], model: &Path, blob_len: usize, macs_per_frame: u32) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "firmware log:");
    for line in log {
        let _ = writeln!(s, "  {line}");
    }
    let _ = writeln!(
        s,
        "model: {} ({blob_len} B, {macs_per_frame} MACs per frame)",
        model.display()
    );
    s
}
