//! Running the firmware: booting QEMU with the blob, the styles and the
//! input image, reading back its outputs and timings, and the host
//! runtime's outputs for the same frames.

use std::path::Path;
use std::time::Duration;

use anyhow::{bail, ensure, Context, Result};
use phasegate::{Mix, Model, Phase, Runtime, Style};

use super::report::*;
use super::*;

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

impl Booted {
    /// The output file of a run that exited cleanly; otherwise an error
    /// with the exit code, the firmware's log and QEMU's stderr.
    pub fn output_file(&self) -> Result<&[u8]> {
        if self.run.exit_code != wire::exit::OK {
            let mut msg = format!(
                "the firmware exited with code {} ({})",
                self.run.exit_code,
                wire::exit::describe(self.run.exit_code)
            );
            for line in &self.log {
                msg.push_str("\n  firmware: ");
                msg.push_str(line);
            }
            if !self.run.stderr.trim().is_empty() {
                msg.push_str("\n  qemu: ");
                msg.push_str(self.run.stderr.trim());
            }
            bail!(msg);
        }
        self.run
            .output_file
            .as_deref()
            .context("the firmware wrote no output file")
    }
}

/// Boots the firmware `elf` with `blob` (if any) at MODEL (at BIGMODEL when
/// it does not fit MODEL), the STYLES image
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
    boot_with(elf, elf_path, blob, styles, image, timeout, &[])
}

/// [`boot`] with `extra` QEMU options.
pub fn boot_with(
    elf: &ElfInfo,
    elf_path: &Path,
    blob: Option<&Path>,
    styles: Option<&[u8]>,
    image: Option<&[u8]>,
    timeout: Duration,
    extra: &[std::ffi::OsString],
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
        // MODEL, or BIGMODEL for a blob too large for it (the firmware
        // looks there when MODEL holds no blob).
        let addr = match elf.bigmodel {
            _ if len <= room => elf.model.0,
            Some((start, end)) if len <= end - start => start,
            big => bail!(
                "{} is {len} bytes, the MODEL region (memory.x) holds {room} bytes{}",
                b.display(),
                big.map(|(s, e)| format!(", BIGMODEL {}", e - s))
                    .unwrap_or_default()
            ),
        };
        loads.push(qemu::Load {
            file: b.to_path_buf(),
            addr,
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
    let run = qemu::run_with(elf_path, &loads, timeout, extra)?;
    let log = log::decode(&elf.bytes, &run.stdout)?;
    Ok(Booted { run, log })
}

/// The region `boot` loads a blob of `len` bytes at: its name and size.
fn model_region(elf: &ElfInfo, len: u64) -> (&'static str, u64) {
    let model = elf.model.1 - elf.model.0;
    match elf.bigmodel {
        Some((start, end)) if len > model => ("BIGMODEL", end - start),
        _ => ("MODEL", model),
    }
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
pub(crate) struct TargetOutputs {
    pub(crate) q: Vec<i16>,
    pub(crate) f: Vec<f32>,
    infer_ticks: Vec<u64>,
    frame_ticks: Vec<u64>,
    pub(crate) trailer: wire::Trailer,
}

pub(crate) fn parse_outputs(
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
    let (records, trailer) = records_and_trailer(file, rl, frames, ("records", "frames"))?;
    let mut out = TargetOutputs {
        q: vec![0; frames * output_dim],
        f: vec![0.0; frames * output_dim],
        infer_ticks: Vec::with_capacity(frames),
        frame_ticks: Vec::with_capacity(frames),
        trailer,
    };
    for (i, r) in records.chunks_exact(rl).enumerate() {
        let span = i * output_dim..(i + 1) * output_dim;
        let head = wire::decode_record(r, &mut out.q[span.clone()], &mut out.f[span])
            .context("firmware output record has the wrong length")?;
        out.infer_ticks.push(u64::from(head.infer_ticks));
        out.frame_ticks.push(u64::from(head.frame_ticks));
    }
    Ok(out)
}

/// The `frames` records (`record_len` bytes each) of a firmware output
/// file whose header was checked, and its trailer, once the file's length
/// and the trailer's frame count say the run finished. `nouns`: what a
/// record and a frame are called in the errors.
pub(super) fn records_and_trailer<'f>(
    file: &'f [u8],
    record_len: usize,
    frames: usize,
    nouns: (&str, &str),
) -> Result<(&'f [u8], wire::Trailer)> {
    let (record, frame) = nouns;
    let body = &file[wire::HEADER_LEN..];
    let expected = frames * record_len + wire::HEADER_LEN;
    ensure!(
        body.len() == expected,
        "firmware output file holds {} bytes after its header, expected {expected} ({frames} {record} and the trailer): the run stopped early",
        body.len()
    );
    let (records, tail) = body.split_at(frames * record_len);
    let trailer =
        wire::Trailer::parse(tail).map_err(|e| anyhow::anyhow!("firmware output trailer: {e}"))?;
    ensure!(
        trailer.frames_done as usize == frames,
        "the firmware reports {} {frame} done, expected {frames}",
        trailer.frames_done
    );
    Ok((records, trailer))
}

/// Does the work of [`run_target`] without printing or judging the result.
pub fn execute(args: &TargetArgs) -> Result<TargetReport> {
    let blob = exporter::atomic::read_input(&args.model)
        .with_context(|| format!("cannot read the model blob {}", args.model.display()))?;
    let rig = match &args.rig {
        Some(path) => Some(RigFile::read(path)?),
        None => None,
    };
    ensure!(
        rig.is_none() || args.styles.is_empty(),
        "a rig blob and style blobs both go to the STYLES region: give one or the other"
    );
    let load = || {
        let alone = Model::from_bytes(&blob)
            .with_context(|| format!("{} is not a valid model blob", args.model.display()))?;
        match &rig {
            Some(r) => Model::with_rig(&blob, &r.bytes).with_context(|| {
                format!(
                    "{} is not a rig blob for the motion blob {}",
                    r.path.display(),
                    args.model.display()
                )
            }),
            None => Ok(alone),
        }
    };
    let model = load()?;
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
        // A pair is not the blob alone: never the blob's golden vectors.
        if rig.is_some() { &[] } else { &blob },
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

    // A rig pair, or a model with a DEC node, runs on the reach build (the
    // OMG firmware, with the `rig` and `dec` features).
    let reach_build = rig.is_some() || has_dec_node(&blob);
    let elf_path = if reach_build {
        eprintln!(
            "building the reach firmware (cargo build --release --bin reach-firmware --features reach in {}) ...",
            firmware_dir().display()
        );
        super::build::build_reach_firmware()?
    } else {
        eprintln!(
            "building the firmware (cargo build --release in {}) ...",
            firmware_dir().display()
        );
        build_firmware()?
    };
    let elf = ElfInfo::read(&elf_path)?;
    let image = frames.image(output_dim);
    let input_crc = wire::InputHeader::parse(&image)
        .map(|(h, _)| h.crc)
        .unwrap_or(0);
    // The STYLES region holds the rig blob, or the styles.
    let styles_image = match &rig {
        Some(r) => r.bytes.clone(),
        None => styles::pack_styles(
            &style_files
                .iter()
                .map(|s| s.bytes.clone())
                .collect::<Vec<_>>(),
        ),
    };
    let frame_macs: Vec<u64> = frames
        .mixes
        .iter()
        .map(|&m| styles::frame_macs(u64::from(macs), &style_files, m))
        .collect();
    let max_macs = frame_macs.iter().copied().max().unwrap_or(u64::from(macs));
    eprintln!("running {} frames under QEMU ...", frames.len());
    let trace_dir = tempfile::Builder::new()
        .prefix("phasegate-trace-")
        .tempdir()
        .context("cannot create a temporary directory")?;
    let trace = trace_dir.path().join("trace.log");
    let booted = boot_with(
        &elf,
        &elf_path,
        Some(&args.model),
        (!styles_image.is_empty()).then_some(&styles_image[..]),
        Some(&image),
        time_limit(frames.len(), u32::try_from(max_macs).unwrap_or(u32::MAX)),
        &if args.cycles {
            cycles::qemu_trace_args(&trace)
        } else {
            Vec::new()
        },
    )?;
    let file = booted.output_file()?;
    let out = parse_outputs(file, frames.len(), output_dim, input_crc)?;
    let t = out.trailer;
    check_calibration(&t)?;
    // A blob with a self-test section (and no rig: the section is the
    // motion blob's alone) must have passed it at boot.
    if let (Some(n), None) = (
        Model::from_bytes(&blob).ok().and_then(|m| m.self_test()),
        &rig,
    ) {
        let line = format!("self-test: {} vectors passed", n.count());
        ensure!(
            booted.log.iter().any(|l| l.contains(&line)),
            "the blob has a self-test of {} vectors, but the firmware did not log {line:?}",
            n.count()
        );
    }
    let self_test = match args.self_test {
        None => None,
        Some(n) => {
            ensure!(
                rig.is_none(),
                "--self-test checks a model blob alone, not a rig pair"
            );
            eprintln!("checking the boot self-test under QEMU, passing and corrupted ...");
            Some(super::self_test::check(
                &elf,
                &elf_path,
                &blob,
                n,
                &image,
                (&out.q, &out.f),
                |file| parse_outputs(file, frames.len(), output_dim, input_crc).map(|o| (o.q, o.f)),
                time_limit(frames.len(), u32::try_from(max_macs).unwrap_or(u32::MAX)),
            )?)
        }
    };
    // A firmware that writes no profile (an older build) just gives no
    // per-stage table.
    let stages = match booted.run.profile_file.as_deref() {
        Some(file) => layers::profile(&load()?, file, frames.len(), input_crc)?,
        None => Vec::new(),
    };

    let cycles = if args.cycles {
        let file = std::fs::File::open(&trace)
            .with_context(|| format!("QEMU wrote no trace at {}", trace.display()))?;
        let priced = cycles::price_trace(std::io::BufReader::new(file))?;
        ensure!(
            priced.len() == frames.len(),
            "the trace brackets {} frames, the run had {}",
            priced.len(),
            frames.len()
        );
        cycles::CycleReport::of(priced)
    } else {
        None
    };

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
        model_region: model_region(&elf, blob.len() as u64),
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
        stages,
        styles_image: (styles_image.len(), elf.styles.1 - elf.styles.0),
        styles: style_files,
        rig,
        reach_build,
        mix,
        mix_groups,
        model_ram_bytes,
        calibration: (t.calib_ticks, t.calib_instructions),
        flash,
        ram,
        log: booted.log,
        wall: booted.run.wall,
        cycles,
        self_test,
    })
}

/// Whether `blob` (a motion or graph blob) has a DEC layer node, which
/// the reach build of the firmware runs (and the inference core), not the
/// QEMU firmware.
pub(crate) fn has_dec_node(blob: &[u8]) -> bool {
    phasegate::Model::from_bytes(blob).is_ok_and(|m| {
        m.header().nodes.iter().any(|n| {
            n.layer()
                .is_some_and(|l| matches!(l.op, phasegate::blob::LayerOp::Dec { .. }))
        })
    })
}
