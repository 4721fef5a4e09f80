//! `host-sim target --reach SCRIPT --omg DIR --model BLOB`: the OMG
//! reaching loop (`Reach<f32, W>` over the runtime) on the Cortex-M4
//! firmware under QEMU, every frame compared bit for bit with the same
//! loop on the host (same blob, layout, first frame and hand targets).
//!
//! The targets are `host-sim rollout --omg`'s (a built-in or JSON target
//! script, `ref:N` or `clip:N`, [`crate::omg_rollout`]); a hand's target is
//! sent on the frames where it changes. A joint-velocity model's plan also
//! carries its skeleton and start state ([`DofPlan`]; from rest for a
//! script). The firmware is the `reach`
//! feature build ([`build_reach_firmware`]): both loops together do not fit
//! the controller firmware's 64 KiB `.text` budget.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, ensure, Context, Result};
use phasegate::{Model, Runtime};
use phasegate_controller::reach::{PoseForm, Skeleton};
use phasegate_controller::{CostMode, Reach, ReachLayout, Target};

use super::build::build_reach_firmware;
use super::run::records_and_trailer;
use super::{
    boot, memory_use, time_limit, wire, ElfInfo, FlashUse, RamUse, Stats, HOST_N, HOST_S, HOST_W,
    INSTRUCTIONS_PER_TICK, RAM_BUDGET,
};
use crate::footprint::TEXT_BUDGETS;
use crate::omg::{load_dir, reach_layout, Start};
use crate::omg_rollout::{targets, OmgRolloutArgs};
use exporter::net::omg::OmgNet;
use wire::reach::{self as wr, FrameHead, TargetOutcome, HANDS};

/// Values per frame the firmware's loop holds (its staging width).
pub const DEVICE_WIDTH: usize = 512;

/// The reach firmware's `.text` budget.
const REACH_TEXT_BUDGET: u64 = TEXT_BUDGETS.reach_firmware;

/// Steps run when `--frames` is not given.
pub const DEFAULT_REACH_FRAMES: usize = 60;

/// What the device and the host run: the layout, the cost mode, the first
/// frame and each step's hand targets (`None`: kept).
#[derive(Clone, Debug)]
pub struct ReachPlan {
    /// The frame layout (from the model's `config.json`).
    pub layout: ReachLayout,
    /// Grounded or faithful.
    pub mode: CostMode,
    /// The first frame `X`.
    pub first: Vec<f32>,
    /// A joint-velocity model's skeleton and start state.
    pub dofs: Option<DofPlan>,
    /// Per step, each hand's new target.
    pub targets: Vec<[Option<Target<f32>>; HANDS]>,
}

/// The skeleton and start joint angles and velocities of a joint-velocity
/// model's plan, as the device holds them (f32).
#[derive(Clone, Debug)]
pub struct DofPlan {
    /// The rig.
    pub skeleton: Skeleton<f32>,
    /// Start joint angles, radians.
    pub q0: Vec<f32>,
    /// Start joint velocities, rad/s.
    pub v0: Vec<f32>,
}

impl DofPlan {
    fn wire(&self) -> wr::DofStart<'_> {
        wr::DofStart {
            skeleton: &self.skeleton,
            q0: &self.q0,
            v0: &self.v0,
        }
    }
}

/// Hand `h`'s target in a target block (K positions, then K forward + up
/// pairs), as f32.
fn hand_target(block: &[f64], k: usize, h: usize) -> Target<f32> {
    let v = |i: usize| block[i] as f32;
    let (p, r) = (3 * h, 3 * k + 6 * h);
    Target {
        position: [v(p), v(p + 1), v(p + 2)],
        forward: [v(r), v(r + 1), v(r + 2)],
        up: [v(r + 3), v(r + 4), v(r + 5)],
    }
}

/// The plan of `steps` steps of the target script `script` for the model
/// of `dir` (`host-sim rollout --omg`'s start frame and targets): step `t`
/// sets a hand's target when block `t + 1` changes it.
pub fn plan_from_script(
    dir: &Path,
    script: &str,
    data: Option<PathBuf>,
    steps: usize,
    mode: CostMode,
) -> Result<ReachPlan> {
    let d = load_dir(dir)?;
    let args = OmgRolloutArgs {
        dir: dir.to_path_buf(),
        model: None,
        rig: None,
        script: script.to_string(),
        data,
        frames: Some(steps + 1),
        mode,
    };
    let (start, blocks) = targets(&args, &d)?;
    plan_from_start(&d.omg, &start, &blocks, mode).with_context(|| dir.display().to_string())
}

/// The plan of `omg`'s rollout from `start` through the target blocks
/// `blocks` (block 0 is the start frame's; one step per later block, which
/// sets a hand's target where it changes it).
pub fn plan_from_start(
    omg: &OmgNet,
    start: &Start,
    blocks: &[Vec<f64>],
    mode: CostMode,
) -> Result<ReachPlan> {
    let layout = reach_layout(omg)?;
    let f32s = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
    let dofs = match &omg.dof {
        None => None,
        Some(form) => Some(DofPlan {
            skeleton: crate::omg::skeleton(&form.skeleton)?,
            q0: f32s(&start.q0),
            v0: f32s(&start.v0),
        }),
    };
    let k = layout.key();
    ensure!(k >= HANDS, "{k} key joints, reach mode sends two hands");
    let targets = blocks
        .windows(2)
        .map(|w| {
            std::array::from_fn(|h| {
                let (a, b) = (hand_target(&w[0], k, h), hand_target(&w[1], k, h));
                (a != b).then_some(b)
            })
        })
        .collect();
    Ok(ReachPlan {
        layout,
        mode,
        first: f32s(&start.first),
        dofs,
        targets,
    })
}

/// The reach-mode input image of `plan` for a network of `outputs` values.
pub fn reach_image(plan: &ReachPlan, outputs: usize) -> Result<Vec<u8>> {
    let width = plan.first.len();
    let mut records = vec![0u8; wr::setup_len(width)];
    let dofs = plan.dofs.as_ref().map(DofPlan::wire);
    wr::encode_setup(
        &plan.layout,
        plan.mode,
        &plan.first,
        dofs.as_ref(),
        &mut records,
    )
    .context(
        "the layout has more key joints than the wire carries, or its pose form and the plan's \
         skeleton disagree",
    )?;
    for t in &plan.targets {
        wr::encode_target_record(t, &mut records);
    }
    let header = wire::InputHeader {
        frames: plan.targets.len() as u32,
        input_dim: width as u32,
        output_dim: outputs as u32,
        crc: wire::crc32(&records),
        mode: wire::Mode::Reach,
    };
    let mut image = header.encode().to_vec();
    image.extend_from_slice(&records);
    Ok(image)
}

/// Each step's target outcomes, one per hand.
pub type Outcomes = Vec<[TargetOutcome; HANDS]>;

/// The host reference: `Reach<f32, DEVICE_WIDTH>` over the runtime, the
/// firmware's loop step for step. Returns every frame after its step and
/// each step's target outcomes.
pub fn host_frames(model: Model<'_>, plan: &ReachPlan) -> Result<(Vec<Vec<f32>>, Outcomes)> {
    let mut rt = Box::new(
        Runtime::<'_, HOST_W, HOST_S, HOST_N>::new(model)
            .context("the host runtime refuses the model")?,
    );
    let layout = plan.layout.clone();
    let mut state = Box::new(
        match &plan.dofs {
            None => Reach::<f32, DEVICE_WIDTH>::new(&*rt, layout, plan.mode, &plan.first),
            Some(d) => Reach::with_dofs(
                &*rt,
                layout,
                plan.mode,
                &plan.first,
                d.skeleton.clone(),
                &d.q0,
                &d.v0,
            ),
        }
        .context("Reach::new")?,
    );
    let mut frames = Vec::with_capacity(plan.targets.len());
    let mut outcomes = Vec::with_capacity(plan.targets.len());
    for (i, hands) in plan.targets.iter().enumerate() {
        let mut o = [TargetOutcome::Kept; HANDS];
        for (h, t) in hands.iter().enumerate() {
            if let Some(t) = t {
                o[h] = match state.set_target(h, t) {
                    Ok(()) => TargetOutcome::Set,
                    Err(phasegate_controller::Error::BadTarget { field }) => {
                        TargetOutcome::Refused { field }
                    }
                    Err(e) => bail!("step {i}: hand {h}: {e}"),
                };
            }
        }
        state
            .step(&mut *rt)
            .with_context(|| format!("step {i}: host reaching step"))?;
        frames.push(state.frame().to_vec());
        outcomes.push(o);
    }
    Ok((frames, outcomes))
}

/// Name of value `k` of a frame of `layout`.
pub fn frame_field_name(layout: &ReachLayout, k: usize) -> String {
    let vel = match &layout.pose {
        PoseForm::DofVelocity { vel, .. } => vel.clone(),
        PoseForm::Absolute => 0..0,
    };
    for (name, r) in [
        ("pos", &layout.pos),
        ("rot", &layout.rot),
        ("vel", &vel),
        ("cost", &layout.cost),
        ("target", &layout.target),
    ] {
        if r.contains(&k) {
            return format!("{name}[{}] (value {k})", k - r.start);
        }
    }
    format!("value {k}")
}

/// One frame value that differs between the firmware and the host.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameMismatch {
    /// Step index.
    pub frame: usize,
    /// Field name.
    pub field: String,
    /// Host value.
    pub host: f32,
    /// Firmware value.
    pub target: f32,
}

/// Compares the frames bit for bit: the count of values that differ and
/// the first few.
pub fn compare_frames(
    layout: &ReachLayout,
    host: &[Vec<f32>],
    target: &[Vec<f32>],
) -> (usize, Vec<FrameMismatch>) {
    let width = host.first().map_or(0, Vec::len);
    let mut count = host.len().abs_diff(target.len()) * width;
    let mut first = Vec::new();
    for (frame, (h, t)) in host.iter().zip(target).enumerate() {
        for (k, (a, b)) in h.iter().zip(t).enumerate() {
            if a.to_bits() != b.to_bits() {
                count += 1;
                if first.len() < 10 {
                    first.push(FrameMismatch {
                        frame,
                        field: frame_field_name(layout, k),
                        host: *a,
                        target: *b,
                    });
                }
            }
        }
    }
    (count, first)
}

/// The firmware's reach-mode output file, parsed.
pub struct FrameFile {
    /// Every frame after its step.
    pub frames: Vec<Vec<f32>>,
    /// Each step's record head (ticks, index, target outcomes).
    pub heads: Vec<FrameHead>,
    /// The trailer.
    pub trailer: wire::Trailer,
}

/// Parses a reach-mode output file of `frames` records of `width` values.
pub fn parse_frame_file(
    file: &[u8],
    frames: usize,
    width: usize,
    input_crc: u32,
) -> Result<FrameFile> {
    let h = wire::OutputHeader::parse(file)
        .map_err(|e| anyhow::anyhow!("firmware output file: {e}"))?;
    ensure!(
        h.mode == wire::Mode::Reach
            && h.frames as usize == frames
            && h.output_dim as usize == width
            && h.input_crc == input_crc,
        "firmware output file is {:?} mode, {} frames of {}, input CRC {:#x}; expected reach mode, {frames} frames of {width}, {input_crc:#x}",
        h.mode,
        h.frames,
        h.output_dim,
        h.input_crc
    );
    let rl = h.record_len();
    let (records, trailer) = records_and_trailer(file, rl, frames, ("frames", "steps"))?;
    let mut out = FrameFile {
        frames: Vec::with_capacity(frames),
        heads: Vec::with_capacity(frames),
        trailer,
    };
    for r in records.chunks_exact(rl) {
        let mut f = vec![0f32; width];
        let head = wr::decode_frame_record(r, &mut f)
            .context("firmware frame record has the wrong length or an unknown target outcome")?;
        out.frames.push(f);
        out.heads.push(head);
    }
    Ok(out)
}

/// What `host-sim target --reach` runs.
#[derive(Clone, Debug)]
pub struct ReachArgs<'a> {
    /// The OMG model blob.
    pub model: &'a Path,
    /// The model's directory (`config.json`, references): the layout, the
    /// start frame, the script's joint names.
    pub dir: &'a Path,
    /// A target script (`host-sim rollout --omg --script`'s forms).
    pub script: &'a str,
    /// The generated data, for `clip:N`.
    pub data: Option<PathBuf>,
    /// Steps (default [`DEFAULT_REACH_FRAMES`]).
    pub frames: Option<usize>,
    /// Grounded or faithful.
    pub mode: CostMode,
}

/// Everything `host-sim target --reach` measured.
#[derive(Clone, Debug)]
pub struct ReachReport {
    /// The blob that ran.
    pub model: PathBuf,
    /// Blob size, bytes.
    pub blob_len: usize,
    /// The script.
    pub script: String,
    /// The cost mode.
    pub mode: CostMode,
    /// Steps run.
    pub frames: usize,
    /// Frame width.
    pub width: usize,
    /// Values that differ from the host (frames and target outcomes).
    pub mismatches: usize,
    /// The first few.
    pub first_mismatches: Vec<FrameMismatch>,
    /// Steps whose target outcomes differ from the host's.
    pub outcome_mismatches: Vec<usize>,
    /// Hand targets set, and refused (step, hand, field).
    pub targets_set: usize,
    /// Refused targets.
    pub refused: Vec<(usize, usize, u8)>,
    /// Instructions per whole frame (targets set and `Reach::step`).
    pub frame_instructions: Stats,
    /// Instructions per network call (`Runtime::run`).
    pub network_instructions: Stats,
    /// The loop's own cost: frame minus network.
    pub glue_instructions: Stats,
    /// Multiply-accumulates per frame.
    pub macs_per_frame: u32,
    /// Activation and adapter buffers the model needs, bytes.
    pub activation_bytes: usize,
    /// Bytes of the loop's state on the device (from its log).
    pub state_bytes: usize,
    /// SysTick ticks of the calibration loop, and its instructions.
    pub calibration: (u32, u32),
    /// The reach firmware's flash use.
    pub flash: FlashUse,
    /// The reach firmware's RAM use (stack measured in this run).
    pub ram: RamUse,
    /// The firmware's decoded defmt log.
    pub log: Vec<String>,
    /// QEMU's wall time.
    pub wall: Duration,
}

impl ReachReport {
    /// Whether every frame value and target outcome matched the host.
    pub fn bit_exact(&self) -> bool {
        self.mismatches == 0 && self.outcome_mismatches.is_empty()
    }

    /// `.text` and RAM against their budgets.
    pub fn budget_verdict(&self) -> String {
        super::report::budget_verdict(&self.ram, &self.flash, REACH_TEXT_BUDGET)
    }

    /// The human-readable report.
    pub fn render(&self) -> String {
        let mut s =
            super::report::render_head(&self.log, &self.model, self.blob_len, self.macs_per_frame);
        let _ = writeln!(
            s,
            "reach: script {}, {:?} costs, {} steps of {} values; {} hand targets set, {} refused{}",
            self.script,
            self.mode,
            self.frames,
            self.width,
            self.targets_set,
            self.refused.len(),
            self.refused
                .iter()
                .map(|(f, h, field)| format!(" (step {f} hand {h} field {field})"))
                .collect::<String>()
        );
        if self.bit_exact() {
            let _ = writeln!(
                s,
                "result: bit-exact: all {} frames x {} f32 values and the target outcomes equal the host's Reach<f32, {DEVICE_WIDTH}>",
                self.frames, self.width
            );
        } else {
            let _ = writeln!(
                s,
                "result: MISMATCH: {} frame values and {} steps' target outcomes differ from the host's Reach<f32, {DEVICE_WIDTH}>",
                self.mismatches,
                self.outcome_mismatches.len()
            );
            for m in &self.first_mismatches {
                let _ = writeln!(
                    s,
                    "  step {} {}: host {:e} ({:#010x}), target {:e} ({:#010x})",
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
                "instructions per frame, {what}: min {} median {} max {}",
                st.min, st.median, st.max
            );
        };
        line(
            &mut s,
            "whole frame (set targets + Reach::step)",
            self.frame_instructions,
        );
        line(
            &mut s,
            "network (Runtime::run: quantise, infer, de-quantise)",
            self.network_instructions,
        );
        line(
            &mut s,
            "controller glue (frame - network)",
            self.glue_instructions,
        );
        s += &super::memory_lines("reach firmware ", self.calibration, &self.flash, &self.ram);
        let _ = writeln!(
            s,
            "flash for this model: blob {} B + .text {} B + .rodata {} B = {} B",
            self.blob_len,
            self.flash.text,
            self.flash.rodata,
            self.blob_len as u64 + self.flash.text + self.flash.rodata
        );
        let _ = writeln!(
            s,
            "RAM for this model: activations {} B (the model's need; the firmware reserves its fixed arena in .bss), controller state {} B (Reach<f32, {DEVICE_WIDTH}>), stack high-water {} B",
            self.activation_bytes, self.state_bytes, self.ram.stack_high_water
        );
        let _ = writeln!(
            s,
            "budgets (reach firmware): static RAM + stack {} B <= {RAM_BUDGET} B, .text {} B <= {REACH_TEXT_BUDGET} B: {}",
            self.ram.total(),
            self.flash.text,
            self.budget_verdict()
        );
        let _ = writeln!(s, "QEMU wall time: {:.2} s", self.wall.as_secs_f64());
        s
    }
}

/// The loop state's size on the device, as the firmware logs it (the
/// host's is larger: its `usize` ranges are 8 bytes).
fn device_state_bytes(log: &[String]) -> Option<usize> {
    log.iter().find_map(|l| {
        let rest = l.split("loop state ").nth(1)?;
        rest.split(' ').next()?.parse().ok()
    })
}

/// Runs `plan` on the reach firmware and on the host; does not print or
/// judge bit-exactness.
pub fn execute_plan(model_path: &Path, script: &str, plan: &ReachPlan) -> Result<ReachReport> {
    let blob = exporter::atomic::read_input(model_path)
        .with_context(|| format!("cannot read the model blob {}", model_path.display()))?;
    let model = Model::from_bytes(&blob)
        .with_context(|| format!("{} is not a valid model blob", model_path.display()))?;
    let frames = plan.targets.len();
    ensure!(frames > 0, "no frames to run");
    let width = plan.first.len();
    ensure!(
        model.input_dim() == width,
        "{} has {} inputs, the model directory's frames are {width} wide: a blob of another model?",
        model_path.display(),
        model.input_dim()
    );
    let image = reach_image(plan, model.output_dim())?;
    let input_crc = wire::InputHeader::parse(&image)
        .map(|(h, _)| h.crc)
        .unwrap_or(0);
    eprintln!(
        "building the firmware with the reach feature (cargo build --release --features reach in {}) ...",
        super::firmware_dir().display()
    );
    let elf_path = build_reach_firmware()?;
    let elf = ElfInfo::read(&elf_path)?;
    let macs = model.macs_per_frame();
    eprintln!("running {frames} reaching steps under QEMU ...");
    let booted = boot(
        &elf,
        &elf_path,
        Some(model_path),
        None,
        Some(&image),
        time_limit(frames, macs),
    )?;
    let out = parse_frame_file(booted.output_file()?, frames, width, input_crc)?;
    let t = out.trailer;
    super::check_calibration(&t)?;
    let activation_bytes = model.ram_bytes();
    let (host, outcomes) = host_frames(model, plan)?;
    let (mismatches, first_mismatches) = compare_frames(&plan.layout, &host, &out.frames);
    let outcome_mismatches = (out.heads.iter().zip(&outcomes).enumerate())
        .filter(|(i, (h, o))| h.targets != **o || h.frame as usize != *i)
        .map(|(i, _)| i)
        .collect();
    let refused = (outcomes.iter().enumerate())
        .flat_map(|(i, o)| {
            o.iter().enumerate().filter_map(move |(h, t)| match t {
                TargetOutcome::Refused { field } => Some((i, h, *field)),
                _ => None,
            })
        })
        .collect();
    let targets_set = outcomes
        .iter()
        .flatten()
        .filter(|t| **t == TargetOutcome::Set)
        .count();
    let ins = |f: fn(&FrameHead) -> u32| -> Vec<u64> {
        out.heads
            .iter()
            .map(|h| u64::from(f(h)) * INSTRUCTIONS_PER_TICK)
            .collect()
    };
    let frame = ins(|h| h.frame_ticks);
    let network = ins(|h| h.network_ticks);
    let glue: Vec<u64> = frame
        .iter()
        .zip(&network)
        .map(|(f, n)| f.saturating_sub(*n))
        .collect();
    let (flash, ram) = memory_use(&elf, &t);
    Ok(ReachReport {
        model: model_path.to_path_buf(),
        blob_len: blob.len(),
        script: script.to_string(),
        mode: plan.mode,
        frames,
        width,
        mismatches,
        first_mismatches,
        outcome_mismatches,
        targets_set,
        refused,
        frame_instructions: Stats::of(&frame),
        network_instructions: Stats::of(&network),
        glue_instructions: Stats::of(&glue),
        macs_per_frame: macs,
        activation_bytes,
        state_bytes: device_state_bytes(&booted.log)
            .unwrap_or(Reach::<f32, DEVICE_WIDTH>::STATE_RAM_BYTES),
        calibration: (t.calib_ticks, t.calib_instructions),
        flash,
        ram,
        log: booted.log,
        wall: booted.run.wall,
    })
}

/// Runs the script's plan on the firmware and the host.
pub fn execute(args: &ReachArgs<'_>) -> Result<ReachReport> {
    let steps = args.frames.unwrap_or(DEFAULT_REACH_FRAMES);
    ensure!(steps > 0, "no frames to run");
    let plan = plan_from_script(args.dir, args.script, args.data.clone(), steps, args.mode)?;
    execute_plan(args.model, args.script, &plan)
}

/// `host-sim target --reach`: runs, prints the report, fails on any
/// mismatch.
pub fn run(args: &ReachArgs<'_>) -> Result<ReachReport> {
    let report = execute(args)?;
    print!("{}", report.render());
    if !report.bit_exact() {
        let m = report.first_mismatches.first();
        bail!(
            "the firmware's frames differ from the host's Reach<f32, {DEVICE_WIDTH}> ({} values, {} target outcomes{})",
            report.mismatches,
            report.outcome_mismatches.len(),
            m.map(|m| format!(", first at step {} {}", m.frame, m.field))
                .unwrap_or_default()
        );
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::target::{qemu_available, repo_root};

    /// 30 steps of `tiny_fe_r1` int8 (the golden blob) on the reach
    /// firmware under QEMU, with the left hand's target moved at step 10
    /// and a NaN target for the right hand at step 20 (refused, recorded,
    /// the run goes on): every frame and target outcome equals the host's,
    /// and the firmware stays within its `.text` and RAM budgets.
    #[test]
    fn reach_on_qemu_is_bit_exact_with_a_moved_and_a_refused_target() {
        if !qemu_available() {
            eprintln!(
                "SKIPPED reach_on_qemu_is_bit_exact_with_a_moved_and_a_refused_target: qemu-system-arm not found (apt-get install qemu-system-arm)"
            );
            return;
        }
        let root = repo_root();
        let dir = root.join("models/omg/tiny_fe_r1");
        let blob = root.join("tests/golden/omg-tiny-fe-r1/model.blob");
        let mut plan = plan_from_script(&dir, "reach-front", None, 30, CostMode::Grounded).unwrap();
        assert!(plan.targets.iter().flatten().all(Option::is_none));
        plan.targets[10][0] = Some(Target {
            position: [0.35, 1.1, 0.25],
            forward: [0.0, 0.0, 1.0],
            up: [0.0, 1.0, 0.0],
        });
        plan.targets[20][1] = Some(Target {
            position: [-0.3, f32::NAN, 0.2],
            forward: [0.0, 0.0, 1.0],
            up: [0.0, 1.0, 0.0],
        });
        let r = execute_plan(&blob, "reach-front + edits", &plan).unwrap();
        assert!(r.bit_exact(), "{}", r.render());
        assert_eq!(r.targets_set, 1);
        assert_eq!(r.refused, vec![(20, 1, 1)]);
        assert_eq!(r.budget_verdict(), "within budget", "{}", r.render());
        // The moved target reaches the frame's target block the next step.
        let t = plan.layout.target.start;
        let out = host_frames(
            Model::from_bytes(&std::fs::read(&blob).unwrap()).unwrap(),
            &plan,
        )
        .unwrap();
        assert_eq!(out.0[10][t..t + 3], [0.35, 1.1, 0.25]);
        assert_eq!(out.0[9][t..t + 3], out.0[0][t..t + 3]);
    }

    /// A joint-velocity model (int8) from rest on the reach firmware under
    /// QEMU: its skeleton and start state travel in the setup, and every
    /// frame (FK pose included) and target outcome equals the host's
    /// `Reach<f32>`, a refused target included; within budget. Skipped
    /// without QEMU. The model is `omg::tests::dof_model`.
    #[test]
    fn a_dof_model_on_qemu_is_bit_exact_with_the_host_loop() {
        if !qemu_available() {
            eprintln!(
                "SKIPPED a_dof_model_on_qemu_is_bit_exact_with_the_host_loop: no qemu-system-arm"
            );
            return;
        }
        let dir = crate::omg::tests::dof_model();
        let d = load_dir(&dir).unwrap();
        let i8 = phasegate::blob::WeightFormat::I8;
        let blob = crate::omg::export(&d, i8, &crate::omg::exporter_options(i8)).unwrap();
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("dof.blob");
        std::fs::write(&path, &blob).unwrap();
        let mut plan = plan_from_script(&dir, "reach-front", None, 20, CostMode::Grounded).unwrap();
        let dofs = plan.dofs.as_ref().expect("a joint-velocity plan");
        assert!(
            dofs.q0.iter().chain(&dofs.v0).all(|&v| v == 0.0),
            "from rest"
        );
        plan.targets[5][1] = Some(Target {
            position: [0.0, 1.0, f32::INFINITY],
            forward: [0.0, 0.0, 1.0],
            up: [0.0, 1.0, 0.0],
        });
        let r = execute_plan(&path, "reach-front + a refused target", &plan).unwrap();
        assert!(r.bit_exact(), "{}", r.render());
        assert_eq!(r.refused, vec![(5, 1, 2)]);
        assert_eq!(r.budget_verdict(), "within budget", "{}", r.render());
        assert!(r
            .log
            .iter()
            .any(|l| l.contains("joint-velocity model: 31 joints, 30 DOFs")));
    }
}
