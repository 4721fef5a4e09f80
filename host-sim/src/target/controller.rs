//! `host-sim target --controller SCRIPT`: the locomotion loop
//! (`Locomotion<f32>` over the runtime with its style bank) on the Cortex-M4 firmware
//! under QEMU, every pose compared bit for bit with the same loop on the
//! host (same blob, styles, commands and mixes).
//!
//! The commands are the rollout script's (`host-sim rollout`'s
//! [`Script::command`] for frames 0, 1, ...), carried in a controller-mode
//! input image (`wire.rs`). The firmware is the `controller` feature build
//! ([`build_controller_firmware`]): the loop and its libm glue do not fit
//! the inference firmware's 64 KiB `.text` budget.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, ensure, Context, Result};
use phasegate::{Mix, Model, Runtime, Style};
use phasegate_controller::layout::{INPUTS, JOINTS, OUTPUTS};
use phasegate_controller::{
    Command, Deadline, DeadlineConfig, FrameAction, Locomotion, Pose, TickSource,
};

use super::build::build_controller_firmware;
use super::run::records_and_trailer;
use super::styles::{self, MixGroup, MixSpec, StyleFile};
use super::{
    boot, build_firmware, memory_use, time_limit, wire, ElfInfo, FlashUse, RamUse, Stats, HOST_N,
    HOST_S, HOST_W, INSTRUCTIONS_PER_TICK, RAM_BUDGET,
};
use crate::footprint::TEXT_BUDGETS;

/// The controller firmware's `.text` budget.
const CONTROLLER_TEXT_BUDGET: u64 = TEXT_BUDGETS.controller_firmware;
use crate::rollout::Script;

/// Frames run when `--frames` is not given.
pub const DEFAULT_CONTROLLER_FRAMES: usize = 60;

/// The one line `host-sim target --controller` refuses a model with when it
/// is not PFNN-shaped (the controller's own
/// [`phasegate_controller::Error::NotPfnn`]).
pub fn check_pfnn(model: &Model<'_>) -> Result<()> {
    let (inputs, outputs) = (model.input_dim(), model.output_dim());
    if inputs != INPUTS || outputs != OUTPUTS {
        bail!(
            "{}",
            phasegate_controller::Error::NotPfnn {
                inputs: inputs as u32,
                outputs: outputs as u32,
            }
        );
    }
    Ok(())
}

/// The commands of `script` for frames `0..frames`, exactly as `host-sim
/// rollout` feeds them.
pub fn script_commands(script: &Script, frames: usize) -> Vec<Command> {
    (0..frames).map(|f| script.command(f)).collect()
}

/// The controller-mode input image: one record (mix field, command) per
/// frame. `mix_fields` are the raw mix fields (one per command). No
/// deadline.
pub fn controller_image(commands: &[Command], mix_fields: &[[u8; wire::MIX_LEN]]) -> Vec<u8> {
    deadline_image(commands, mix_fields, DeadlineConfig::NONE)
}

/// [`controller_image`] followed by the deadline block of `deadline` (none
/// when it has no budget).
pub fn deadline_image(
    commands: &[Command],
    mix_fields: &[[u8; wire::MIX_LEN]],
    deadline: DeadlineConfig,
) -> Vec<u8> {
    assert_eq!(
        commands.len(),
        mix_fields.len(),
        "one mix field per command"
    );
    let mut records = Vec::with_capacity(commands.len() * wire::COMMAND_RECORD_LEN);
    for (c, m) in commands.iter().zip(mix_fields) {
        wire::encode_command_record(m, c, &mut records);
    }
    let header = wire::InputHeader {
        frames: commands.len() as u32,
        input_dim: INPUTS as u32,
        output_dim: OUTPUTS as u32,
        crc: wire::crc32(&records),
        mode: wire::Mode::Controller,
    };
    let mut image = header.encode().to_vec();
    image.extend_from_slice(&records);
    if let Some(budget) = deadline.budget {
        image.extend_from_slice(&wire::encode_deadline(budget, deadline.policy));
    }
    image
}

/// The host reference: `Locomotion<f32>` over the runtime with
/// `styles` added in order, each frame's mix set before its step (what the
/// firmware does). Returns every pose.
pub fn host_poses(
    model: Model<'_>,
    styles: &[StyleFile],
    commands: &[Command],
    mixes: &[Mix],
) -> Result<Vec<Pose<f32>>> {
    replay_poses(model, styles, commands, mixes, &[])
}

/// [`host_poses`] replaying the firmware's deadline decisions: frame `i`
/// is held ([`FrameAction::Hold`] through `Locomotion::frame`, as on the
/// device) when `held[i]` (missing entries: inferred). The host cannot
/// know the device's tick counts, so it takes the decisions from the
/// firmware's records; [`replay_policy`] checks that they are the policy's.
pub fn replay_poses(
    model: Model<'_>,
    styles: &[StyleFile],
    commands: &[Command],
    mixes: &[Mix],
    held: &[bool],
) -> Result<Vec<Pose<f32>>> {
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
    let mut state = Box::new(Locomotion::<f32>::new(&*rt).context("Locomotion::new")?);
    let mut poses = Vec::with_capacity(commands.len());
    for (i, c) in commands.iter().enumerate() {
        let mix = mixes.get(i).copied().unwrap_or(Mix::Base);
        rt.set_mix(mix)
            .with_context(|| format!("frame {i}: mix {}", styles::mix_spec_item(mix)))?;
        let action = if held.get(i).copied().unwrap_or(false) {
            FrameAction::Hold
        } else {
            FrameAction::Infer
        };
        let pose = state
            .frame(&mut *rt, action, c)
            .with_context(|| format!("frame {i}: host controller step"))?;
        poses.push(pose.clone());
    }
    Ok(poses)
}

/// Ticks replayed from the firmware's records: each frame reads the clock
/// twice (start, end), and the end is the start plus that frame's ticks.
struct ReplayTicks<'a> {
    ticks: std::slice::Iter<'a, u64>,
    now: u64,
    at_start: bool,
}

impl TickSource for ReplayTicks<'_> {
    fn now_ticks(&mut self) -> u64 {
        if !self.at_start {
            self.now += self.ticks.next().copied().unwrap_or(0);
        }
        self.at_start = !self.at_start;
        self.now
    }
}

/// A pin that records its level after each frame.
#[derive(Default)]
struct LevelPin(bool);

impl embedded_hal::digital::ErrorType for LevelPin {
    type Error = std::convert::Infallible;
}

impl embedded_hal::digital::OutputPin for LevelPin {
    fn set_low(&mut self) -> Result<(), Self::Error> {
        self.0 = false;
        Ok(())
    }
    fn set_high(&mut self) -> Result<(), Self::Error> {
        self.0 = true;
        Ok(())
    }
}

/// The deadline policy run on the host over the firmware's frame ticks:
/// what each frame's status must be (overrun, held, pin level after it).
pub fn replay_policy(config: DeadlineConfig, frame_ticks: &[u64]) -> Vec<wire::FrameStatus> {
    let clock = ReplayTicks {
        ticks: frame_ticks.iter(),
        now: 0,
        at_start: true,
    };
    let Ok(mut d) = Deadline::new(config, LevelPin::default(), clock);
    frame_ticks
        .iter()
        .map(|_| {
            let f = d.frame(|_| ());
            wire::FrameStatus {
                overrun: f.outcome.overrun,
                held: f.outcome.held,
                pin_high: d.pin().0,
            }
        })
        .collect()
}

/// Name of the `k`-th f32 of a pose in wire order (`wire::pose_values`).
pub fn pose_field_name(k: usize) -> String {
    const XYZ: [&str; 3] = ["x", "y", "z"];
    const XYZW: [&str; 4] = ["x", "y", "z", "w"];
    const CONTACTS: [&str; 4] = ["left heel", "left toe", "right heel", "right toe"];
    const GAITS: [&str; 4] = ["stand", "walk", "jog", "crouch"];
    let mut k = k;
    if k < 3 {
        return format!("root_position.{}", XYZ[k]);
    }
    k -= 3;
    if k < 2 {
        return format!("facing.{}", ["x", "z"][k]);
    }
    k -= 2;
    if k < 3 * JOINTS {
        return format!("joint_positions[{}].{}", k / 3, XYZ[k % 3]);
    }
    k -= 3 * JOINTS;
    if k < 4 * JOINTS {
        return format!("joint_rotations[{}].{}", k / 4, XYZW[k % 4]);
    }
    k -= 4 * JOINTS;
    if k < 4 {
        return format!("contacts[{}] ({})", k, CONTACTS[k]);
    }
    k -= 4;
    if k == 0 {
        return "phase".into();
    }
    k -= 1;
    match GAITS.get(k) {
        Some(g) => format!("gaits[{k}] ({g})"),
        None => format!("value {k} past the pose"),
    }
}

/// One pose value that differs between the firmware and the host.
#[derive(Clone, Debug, PartialEq)]
pub struct PoseMismatch {
    /// Frame index.
    pub frame: usize,
    /// Field name (`joint_rotations[3].w`, `frame` for the frame counter).
    pub field: String,
    /// Host value.
    pub host: f32,
    /// Firmware value.
    pub target: f32,
}

/// Compares the poses value by value, bits included: the count of values
/// that differ and the first few of them.
pub fn compare_poses(host: &[Pose<f32>], target: &[Pose<f32>]) -> (usize, Vec<PoseMismatch>) {
    let mut count = host.len().abs_diff(target.len()) * (wire::POSE_VALUES + 1);
    let mut first = Vec::new();
    for (frame, (h, t)) in host.iter().zip(target).enumerate() {
        let mut push = |field: String, a: f32, b: f32| {
            count += 1;
            if first.len() < 10 {
                first.push(PoseMismatch {
                    frame,
                    field,
                    host: a,
                    target: b,
                });
            }
        };
        if h.frame != t.frame {
            push("frame".into(), h.frame as f32, t.frame as f32);
        }
        for (k, (a, b)) in wire::pose_values(h).zip(wire::pose_values(t)).enumerate() {
            if a.to_bits() != b.to_bits() {
                push(pose_field_name(k), *a, *b);
            }
        }
    }
    (count, first)
}

/// Everything `host-sim target --controller` measured.
#[derive(Clone, Debug)]
pub struct ControllerReport {
    /// The blob that ran.
    pub model: PathBuf,
    /// Blob size, bytes.
    pub blob_len: usize,
    /// The script's name.
    pub script: String,
    /// Frames (controller steps) run.
    pub frames: usize,
    /// The style blobs that were flashed.
    pub styles: Vec<StyleFile>,
    /// The mix schedule.
    pub mix: MixSpec,
    /// The frame deadline the firmware ran with.
    pub deadline: DeadlineConfig,
    /// Each frame's deadline status, as the firmware recorded it.
    pub status: Vec<wire::FrameStatus>,
    /// Frames whose recorded status differs from the host's replay of the
    /// policy on the firmware's frame ticks ([`replay_policy`]).
    pub policy_mismatches: Vec<usize>,
    /// Pose values (f32 and frame counters) that differ from the host.
    pub mismatches: usize,
    /// The first few of them.
    pub first_mismatches: Vec<PoseMismatch>,
    /// Instructions per whole `Locomotion::step` (inferred frames only).
    pub step_instructions: Stats,
    /// Instructions per network call inside the step (`Runtime::run`:
    /// input quantisation, inference, de-quantisation).
    pub network_instructions: Stats,
    /// The loop's own cost per step: step minus network, frame by frame.
    pub loop_instructions: Stats,
    /// Network instructions per kind of mix.
    pub mix_groups: Vec<MixGroup>,
    /// Multiply-accumulates per frame of the base model.
    pub macs_per_frame: u32,
    /// SysTick ticks of the calibration loop, and its instructions.
    pub calibration: (u32, u32),
    /// The controller firmware's flash use.
    pub flash: FlashUse,
    /// The controller firmware's RAM use (stack measured in this run).
    pub ram: RamUse,
    /// The inference firmware's flash use (from its ELF, for comparison).
    pub inference_flash: FlashUse,
    /// The inference firmware's `.bss`.
    pub inference_bss: u64,
    /// The firmware's decoded defmt log.
    pub log: Vec<String>,
    /// QEMU's wall time.
    pub wall: Duration,
}

impl ControllerReport {
    /// Whether every pose value of every frame matched the host bit for bit.
    pub fn bit_exact(&self) -> bool {
        self.mismatches == 0
    }

    /// Frames that overran their budget.
    pub fn overruns(&self) -> usize {
        self.status.iter().filter(|s| s.overrun).count()
    }

    /// Frames held (inference skipped).
    pub fn held(&self) -> usize {
        self.status.iter().filter(|s| s.held).count()
    }

    /// Frames after which the status pin read high.
    pub fn pin_high_frames(&self) -> usize {
        self.status.iter().filter(|s| s.pin_high).count()
    }

    /// The deadline lines of the report (none without a budget).
    fn deadline_lines(&self, s: &mut String) {
        let Some(b) = self.deadline.budget else {
            return;
        };
        let list = |pick: fn(&wire::FrameStatus) -> bool| {
            let v: Vec<String> = (self.status.iter().enumerate())
                .filter(|(_, st)| pick(st))
                .map(|(i, _)| i.to_string())
                .take(12)
                .collect();
            v.join(" ")
        };
        let _ = writeln!(
            s,
            "deadline: {} ticks ({} instructions) per frame, policy {:?}: {} of {} frames overran (first: {}), {} held (first: {}), status pin high after {} frames",
            b.ticks(),
            u64::from(b.ticks()) * INSTRUCTIONS_PER_TICK,
            self.deadline.policy,
            self.overruns(),
            self.frames,
            list(|st| st.overrun),
            self.held(),
            list(|st| st.held),
            self.pin_high_frames()
        );
        if self.policy_mismatches.is_empty() {
            let _ = writeln!(
                s,
                "deadline: the host's replay of the policy on the firmware's frame ticks gives the same overruns, held frames and pin levels"
            );
        } else {
            let _ = writeln!(
                s,
                "deadline: POLICY MISMATCH at {} frames (first {}): the firmware's statuses are not the policy's",
                self.policy_mismatches.len(),
                self.policy_mismatches[0]
            );
        }
    }

    /// Issue 4's budgets applied to the controller firmware: the verdict
    /// (printed, not enforced: the controller is an opt-in build).
    pub fn budget_verdict(&self) -> String {
        super::report::budget_verdict(&self.ram, &self.flash, CONTROLLER_TEXT_BUDGET)
    }

    /// The human-readable report.
    pub fn render(&self) -> String {
        let mut s =
            super::report::render_head(&self.log, &self.model, self.blob_len, self.macs_per_frame);
        for (i, st) in self.styles.iter().enumerate() {
            let _ = writeln!(
                s,
                "style {i}: {} ({:?}, {} B, {} MACs per frame)",
                st.path.display(),
                st.name,
                st.bytes.len(),
                st.macs
            );
        }
        let _ = writeln!(
            s,
            "controller: script {}, {} steps, mix schedule {}",
            self.script, self.frames, self.mix
        );
        if self.bit_exact() {
            let _ = writeln!(
                s,
                "result: bit-exact: all {} poses x {} f32 values (and frame counters) equal the host's Locomotion<f32>",
                self.frames,
                wire::POSE_VALUES
            );
        } else {
            let _ = writeln!(
                s,
                "result: MISMATCH: {} pose values differ from the host's Locomotion<f32>",
                self.mismatches
            );
            for m in &self.first_mismatches {
                let _ = writeln!(
                    s,
                    "  frame {} {}: host {:e} ({:#010x}), target {:e} ({:#010x})",
                    m.frame,
                    m.field,
                    m.host,
                    m.host.to_bits(),
                    m.target,
                    m.target.to_bits()
                );
            }
        }
        let line = |s: &mut String, what: &str, st: Stats| {
            let _ = writeln!(
                s,
                "instructions per step, {what}: min {} median {} max {}",
                st.min, st.median, st.max
            );
        };
        self.deadline_lines(&mut s);
        line(&mut s, "whole Locomotion::step", self.step_instructions);
        line(
            &mut s,
            "network (Runtime::run: quantise, infer, de-quantise)",
            self.network_instructions,
        );
        line(
            &mut s,
            "the loop's own cost (step - network)",
            self.loop_instructions,
        );
        if self.mix_groups.iter().any(|g| g.label != "base") {
            let _ = writeln!(
                s,
                "network instructions per mix (frames, min / median / max, MACs):"
            );
            for g in &self.mix_groups {
                let _ = writeln!(
                    s,
                    "  {:<14} {:>4} frames  {} / {} / {}  {} MACs",
                    g.label, g.frames, g.infer.min, g.infer.median, g.infer.max, g.macs
                );
            }
        }
        s += &super::memory_lines(
            "controller firmware ",
            self.calibration,
            &self.flash,
            &self.ram,
        );
        let (fl, r) = (self.flash, self.ram);
        let _ = writeln!(
            s,
            "inference firmware (no controller feature): .text {} B, .bss {} B; the controller adds {} B of .text and {} B of .bss",
            self.inference_flash.text,
            self.inference_bss,
            fl.text as i64 - self.inference_flash.text as i64,
            r.bss as i64 - self.inference_bss as i64
        );
        let _ = writeln!(
            s,
            "budgets (controller firmware): static RAM + stack {} B <= {RAM_BUDGET} B, .text {} B <= {CONTROLLER_TEXT_BUDGET} B: {}",
            r.total(),
            fl.text,
            self.budget_verdict(),
        );
        let _ = writeln!(s, "QEMU wall time: {:.2} s", self.wall.as_secs_f64());
        s
    }
}

/// What `host-sim target --controller` runs.
#[derive(Clone, Debug)]
pub struct ControllerArgs<'a> {
    /// The model blob.
    pub model: &'a Path,
    /// A built-in script name or a JSON script file.
    pub script: &'a str,
    /// Steps (default [`DEFAULT_CONTROLLER_FRAMES`]).
    pub frames: Option<usize>,
    /// Style blobs.
    pub styles: &'a [PathBuf],
    /// Mix schedule (default [`MixSpec::default_for`] the styles).
    pub mix: Option<MixSpec>,
    /// The frame deadline ([`DeadlineConfig::NONE`]: frames are timed,
    /// none overruns).
    pub deadline: DeadlineConfig,
}

/// Runs the controller on the firmware and on the host; does not print or
/// judge bit-exactness (see [`ControllerReport::bit_exact`]).
pub fn execute(args: &ControllerArgs<'_>) -> Result<ControllerReport> {
    let blob = exporter::atomic::read_input(args.model)
        .with_context(|| format!("cannot read the model blob {}", args.model.display()))?;
    let model = Model::from_bytes(&blob)
        .with_context(|| format!("{} is not a valid model blob", args.model.display()))?;
    check_pfnn(&model)
        .with_context(|| format!("--controller: {} is refused", args.model.display()))?;
    let script = Script::load(args.script)?;
    let frames = args.frames.unwrap_or(DEFAULT_CONTROLLER_FRAMES);
    ensure!(frames > 0, "no frames to run");
    let style_files = args
        .styles
        .iter()
        .map(|p| StyleFile::read(p))
        .collect::<Result<Vec<_>>>()?;
    let mix = args
        .mix
        .clone()
        .unwrap_or_else(|| MixSpec::default_for(style_files.len()));
    let mixes = mix.schedule(frames);
    styles::check_schedule(&mixes, style_files.len())?;
    let commands = script_commands(&script, frames);
    let macs = model.macs_per_frame();

    eprintln!(
        "building the firmware with the controller feature (cargo build --release --features controller in {}) ...",
        super::firmware_dir().display()
    );
    let elf_path = build_controller_firmware()?;
    let elf = ElfInfo::read(&elf_path)?;
    let inference_elf = ElfInfo::read(&build_firmware()?)?;
    let mix_fields: Vec<[u8; wire::MIX_LEN]> = mixes.iter().map(|&m| wire::encode_mix(m)).collect();
    let image = deadline_image(&commands, &mix_fields, args.deadline);
    let input_crc = wire::InputHeader::parse(&image)
        .map(|(h, _)| h.crc)
        .unwrap_or(0);
    let styles_image = styles::pack_styles(
        &style_files
            .iter()
            .map(|s| s.bytes.clone())
            .collect::<Vec<_>>(),
    );
    let max_macs = mixes
        .iter()
        .map(|&m| styles::frame_macs(u64::from(macs), &style_files, m))
        .max()
        .unwrap_or(u64::from(macs));
    eprintln!("running {frames} controller steps under QEMU ...");
    let booted = boot(
        &elf,
        &elf_path,
        Some(args.model),
        (!style_files.is_empty()).then_some(&styles_image[..]),
        Some(&image),
        time_limit(frames, u32::try_from(max_macs).unwrap_or(u32::MAX)),
    )?;
    let file = booted.output_file()?;
    let out = parse_pose_file(file, frames, input_crc)?;
    let t = out.trailer;
    super::check_calibration(&t)?;
    let held: Vec<bool> = out.status.iter().map(|s| s.held).collect();
    let host = replay_poses(model, &style_files, &commands, &mixes, &held)?;
    let (mismatches, first_mismatches) = compare_poses(&host, &out.poses);
    let replayed = replay_policy(args.deadline, &out.step_ticks);
    let policy_mismatches = (replayed.iter().zip(&out.status).enumerate())
        .filter(|(_, (a, b))| a != b)
        .map(|(i, _)| i)
        .collect();
    // Held frames run no step: the step and network figures are over the
    // inferred frames.
    let inferred = |v: &[u64]| -> Vec<u64> {
        v.iter()
            .zip(&held)
            .filter(|(_, h)| !**h)
            .map(|(t, _)| t * INSTRUCTIONS_PER_TICK)
            .collect()
    };
    let step = inferred(&out.step_ticks);
    let network = inferred(&out.network_ticks);
    let own: Vec<u64> = step
        .iter()
        .zip(&network)
        .map(|(s, n)| s.saturating_sub(*n))
        .collect();
    let (flash, ram) = memory_use(&elf, &t);
    let (inference_flash, inference_ram) = memory_use(&inference_elf, &t);
    Ok(ControllerReport {
        model: args.model.to_path_buf(),
        blob_len: blob.len(),
        script: script.name.clone(),
        frames,
        mix_groups: styles::mix_groups(
            &(mixes.iter().zip(&held))
                .filter(|(_, h)| !**h)
                .map(|(m, _)| *m)
                .collect::<Vec<_>>(),
            &network,
            u64::from(macs),
            &style_files,
        ),
        deadline: args.deadline,
        status: out.status.clone(),
        policy_mismatches,
        styles: style_files,
        mix,
        mismatches,
        first_mismatches,
        step_instructions: Stats::of(&step),
        network_instructions: Stats::of(&network),
        loop_instructions: Stats::of(&own),
        macs_per_frame: macs,
        calibration: (t.calib_ticks, t.calib_instructions),
        flash,
        ram,
        inference_flash,
        inference_bss: inference_ram.bss,
        log: booted.log,
        wall: booted.run.wall,
    })
}

/// `host-sim target --controller`: runs, prints the report, fails on any
/// mismatch.
pub fn run(args: &ControllerArgs<'_>) -> Result<ControllerReport> {
    let report = execute(args)?;
    print!("{}", report.render());
    if let Some(&first) = report.policy_mismatches.first() {
        bail!(
            "the firmware's deadline statuses differ from the policy replayed on its frame ticks ({} frames, first {first})",
            report.policy_mismatches.len()
        );
    }
    if !report.bit_exact() {
        let m = report.first_mismatches.first();
        bail!(
            "the firmware's poses differ from the host's Locomotion<f32> ({} values{})",
            report.mismatches,
            m.map(|m| format!(", first at frame {} {}", m.frame, m.field))
                .unwrap_or_default()
        );
    }
    Ok(report)
}

/// The firmware's controller-mode output file, parsed.
pub struct PoseFile {
    /// Every pose.
    pub poses: Vec<Pose<f32>>,
    /// Ticks in the network per step.
    pub network_ticks: Vec<u64>,
    /// Ticks per whole frame (as the deadline timed it).
    pub step_ticks: Vec<u64>,
    /// Each frame's deadline status.
    pub status: Vec<wire::FrameStatus>,
    /// The trailer.
    pub trailer: wire::Trailer,
}

/// Parses a controller-mode output file of `frames` records.
pub fn parse_pose_file(file: &[u8], frames: usize, input_crc: u32) -> Result<PoseFile> {
    let h = wire::OutputHeader::parse(file)
        .map_err(|e| anyhow::anyhow!("firmware output file: {e}"))?;
    ensure!(
        h.mode == wire::Mode::Controller
            && h.frames as usize == frames
            && h.input_crc == input_crc,
        "firmware output file is {:?} mode, {} frames, input CRC {:#x}; expected controller mode, {frames} frames, {input_crc:#x}",
        h.mode,
        h.frames,
        h.input_crc
    );
    let rl = h.record_len();
    let (records, trailer) = records_and_trailer(file, rl, frames, ("poses", "steps"))?;
    let mut out = PoseFile {
        poses: Vec::with_capacity(frames),
        network_ticks: Vec::with_capacity(frames),
        step_ticks: Vec::with_capacity(frames),
        status: Vec::with_capacity(frames),
        trailer,
    };
    for r in records.chunks_exact(rl) {
        let (head, status, pose) = wire::decode_pose_record(r)
            .context("firmware pose record has the wrong length or an unknown status bit")?;
        out.network_ticks.push(u64::from(head.infer_ticks));
        out.step_ticks.push(u64::from(head.frame_ticks));
        out.status.push(status);
        out.poses.push(pose);
    }
    Ok(out)
}
