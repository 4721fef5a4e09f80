//! Tests of `host-sim target`: the wire format (always), and under QEMU
//! (skipped with a message when `qemu-system-arm` or the golden vectors are
//! missing): bit-exactness on the golden vectors, issue 4's memory budgets,
//! the two must-fail cases (a model too wide for the firmware's buffers is
//! refused at load; buffers too big for RAM fail to link), bad blobs, and
//! the defmt log snapshots.

/// Straight to stderr: the harness swallows println! of passing tests, and a
/// skip must be visible.
macro_rules! eprintln_direct {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stderr(), $($t)*);
    }};
}

use std::path::PathBuf;
use std::time::Duration;

use super::*;

fn qemu_or_skip(test: &str) -> bool {
    if qemu_available() {
        true
    } else {
        eprintln_direct!(
            "SKIPPED {test}: qemu-system-arm not found (apt-get install qemu-system-arm)"
        );
        false
    }
}

fn golden_or_skip(test: &str) -> Option<PathBuf> {
    let blob = frames::golden_dir().join("model.blob");
    if blob.exists() {
        Some(blob)
    } else {
        println!(
            "SKIPPED {test}: no golden vectors at {}",
            frames::golden_dir().display()
        );
        None
    }
}

// ---- wire format (no QEMU) ----

#[test]
fn crc32_is_the_zlib_one() {
    assert_eq!(wire::crc32(b"123456789"), 0xCBF4_3926);
    assert_eq!(wire::crc32(b""), 0);
}

#[test]
fn input_image_round_trips_and_rejects_damage() {
    let f = frames::generated(3, &[(0.0, 1.0), (1.0, 2.0)], 7);
    let image = f.image(5);
    let (h, records) = wire::InputHeader::parse(&image).unwrap();
    assert_eq!((h.frames, h.input_dim, h.output_dim), (3, 2, 5));
    assert_eq!(records.len(), 3 * h.record_len());
    let mut x = [0f32; 2];
    for (i, r) in records.chunks_exact(h.record_len()).enumerate() {
        let p = wire::read_record(r, &mut x).unwrap();
        assert_eq!(p.to_bits(), f.phases[i].to_bits());
        assert_eq!(x, f.input(i));
    }
    // Longer region (the rest of PSRAM) is fine.
    let mut region = image.clone();
    region.resize(image.len() + 100, 0);
    assert!(wire::InputHeader::parse(&region).is_ok());
    // Damage.
    assert_eq!(
        wire::InputHeader::parse(&[0u8; 64]),
        Err(wire::WireError::BadMagic)
    );
    assert!(matches!(
        wire::InputHeader::parse(&image[..image.len() - 1]),
        Err(wire::WireError::Truncated { .. })
    ));
    let mut bad = image.clone();
    *bad.last_mut().unwrap() ^= 1;
    assert_eq!(
        wire::InputHeader::parse(&bad),
        Err(wire::WireError::CrcMismatch)
    );
    let mut bad = image.clone();
    bad[4] = 9;
    assert_eq!(
        wire::InputHeader::parse(&bad),
        Err(wire::WireError::UnsupportedVersion(9))
    );
    let mut bad = image;
    bad[20] ^= 4;
    assert_eq!(
        wire::InputHeader::parse(&bad),
        Err(wire::WireError::BadHeader)
    );
}

#[test]
fn output_records_round_trip() {
    let q = [1i16, -2, i16::MIN, i16::MAX];
    let f = [0.5f32, -0.0, f32::MIN_POSITIVE, 1e30];
    let mut buf = vec![0u8; 8 + 6 * q.len()];
    let head = wire::RecordHead {
        infer_ticks: 12345,
        frame_ticks: 23456,
    };
    wire::encode_record(head, &q, &f, &mut buf).unwrap();
    let (mut q2, mut f2) = ([0i16; 4], [0f32; 4]);
    assert_eq!(wire::decode_record(&buf, &mut q2, &mut f2), Some(head));
    assert_eq!(q2, q);
    assert_eq!(f2.map(f32::to_bits), f.map(f32::to_bits));
    assert!(wire::encode_record(head, &q, &f, &mut buf[1..]).is_none());
    let t = wire::Trailer {
        frames_done: 3,
        stack_high_water: 1000,
        stack_size: 2000,
        calib_ticks: 1000,
        calib_instructions: 40000,
    };
    assert_eq!(wire::Trailer::parse(&t.encode()), Ok(t));
    let h = wire::OutputHeader {
        frames: 3,
        output_dim: 4,
        input_crc: 0xDEAD_BEEF,
    };
    assert_eq!(wire::OutputHeader::parse(&h.encode()), Ok(h));
}

#[test]
fn stats_are_min_median_max() {
    assert_eq!(
        Stats::of(&[5, 1, 3]),
        Stats {
            min: 1,
            median: 3,
            max: 5
        }
    );
    assert_eq!(
        Stats::of(&[4, 1, 3, 2]),
        Stats {
            min: 1,
            median: 2,
            max: 4
        }
    );
    assert_eq!(Stats::of(&[]), Stats::default());
}

#[test]
fn budgets_bite() {
    let mut r = TargetReport {
        model: PathBuf::new(),
        blob_len: 0,
        model_region: 0,
        source: String::new(),
        frames: 1,
        output_dim: 1,
        mismatches: 0,
        first_mismatches: vec![],
        golden_mismatches: None,
        infer_instructions: Stats::default(),
        frame_instructions: Stats::default(),
        macs_per_frame: 1,
        model_ram_bytes: 0,
        calibration: (1000, 40000),
        flash: FlashUse {
            text: TEXT_BUDGET,
            ..FlashUse::default()
        },
        ram: RamUse {
            bss: RAM_BUDGET - 100,
            stack_high_water: 100,
            ..RamUse::default()
        },
        log: vec![],
        wall: Duration::ZERO,
    };
    assert!(r.check_budgets().is_ok());
    r.ram.stack_high_water += 4;
    assert!(r
        .check_budgets()
        .unwrap_err()
        .to_string()
        .contains("static RAM + stack"));
    r.ram.stack_high_water -= 4;
    r.flash.text += 1;
    assert!(r.check_budgets().unwrap_err().to_string().contains(".text"));
}

// ---- synthetic blobs (exporter's blob writer) ----

/// A small valid blob: one ungated identity layer `in -> width` then
/// `width -> out`, tiny weights so the 32-bit accumulator proof holds.
fn synthetic_blob(input_dim: usize, width: usize, output_dim: usize, seed: u64) -> Vec<u8> {
    use exporter::blob_writer::{encode, BlobLayer, BlobModel};
    use phasegate::blob::{
        AccWidth, Activation, Gating, LayerDesc, LayerOp, ModelKind, Requant, Section, WeightFormat,
    };
    let mut s = seed;
    let mut next = move || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((s >> 33) % 7) as i32 - 3
    };
    let mut layer = |i: usize, o: usize| BlobLayer {
        desc: LayerDesc {
            op: LayerOp::Dense,
            in_dim: i as u16,
            out_dim: o as u16,
            experts: 1,
            weights: WeightFormat::I8,
            acc: AccWidth::I32,
            activation: Activation::Identity,
            gated: false,
            weight_section: Section::default(),
            bias_section: Section::default(),
            requant_section: Section::default(),
        },
        weights: (0..i * o).map(|_| next()).collect(),
        bias: (0..o).map(|_| i64::from(next()) * 100).collect(),
        requant: vec![
            Requant {
                multiplier: 1 << 14,
                pre_shift: 0,
                post_shift: 20,
                frac: 8
            };
            o
        ],
    };
    let layers = vec![layer(input_dim, width), layer(width, output_dim)];
    let m = BlobModel {
        kind: ModelKind::Mlp,
        gating: Gating::Single,
        input_stage: vec![(0.0, 256.0); input_dim],
        output_stage: vec![(1.0 / 256.0, 0.0); output_dim],
        layers,
    };
    encode(&m).expect("synthetic model encodes")
}

#[test]
fn synthetic_blobs_load_on_the_host() {
    let blob = synthetic_blob(12, 40, 7, 1);
    let m = phasegate::Model::from_bytes(&blob).unwrap();
    assert_eq!((m.input_dim(), m.output_dim()), (12, 7));
}

// ---- under QEMU ----

#[test]
fn firmware_is_bit_exact_on_a_synthetic_model_and_within_budgets() {
    if !qemu_or_skip("firmware_is_bit_exact_on_a_synthetic_model_and_within_budgets") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("synthetic.blob");
    std::fs::write(&path, synthetic_blob(24, 64, 9, 3)).unwrap();
    let report = execute(&TargetArgs {
        model: path,
        frames: Some(5),
        ..TargetArgs::default()
    })
    .unwrap();
    println!("{}", report.render());
    assert!(report.bit_exact(), "{}", report.render());
    assert_eq!(report.frames, 5);
    assert!(report.infer_instructions.min > 0);
    report.check_budgets().unwrap();
}

#[test]
fn firmware_matches_the_golden_vectors_and_budgets() {
    let name = "firmware_matches_the_golden_vectors_and_budgets";
    if !qemu_or_skip(name) {
        return;
    }
    let Some(blob) = golden_or_skip(name) else {
        return;
    };
    let report = run_target(&TargetArgs {
        model: blob,
        ..TargetArgs::default()
    })
    .unwrap();
    assert!(report.bit_exact());
    assert_eq!(report.golden_mismatches, Some(0));
    report.check_budgets().unwrap();
}

/// Must-fail case 1: a model whose widest layer (600) exceeds the
/// firmware's activation buffers (512 elements) is refused at load with a
/// typed error and a failing exit code, not run and not a panic.
#[test]
fn model_too_wide_for_the_buffers_is_refused_at_load() {
    if !qemu_or_skip("model_too_wide_for_the_buffers_is_refused_at_load") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("wide.blob");
    std::fs::write(&path, synthetic_blob(16, 600, 4, 5)).unwrap();
    let err = execute(&TargetArgs {
        model: path.clone(),
        frames: Some(1),
        ..TargetArgs::default()
    })
    .unwrap_err();
    let msg = format!("{err:#}");
    assert!(
        msg.contains("exited with code 2 (model blob refused)"),
        "{msg}"
    );
    assert!(
        msg.contains("BufferTooSmall { needed: 600, capacity: 512 }"),
        "{msg}"
    );
    assert!(msg.contains("activation buffers too small"), "{msg}");
}

/// Must-fail case 2: buffers far larger than the board's RAM region fail to
/// link with the linker's region-overflow message.
#[test]
fn oversize_buffers_fail_to_link() {
    let target_dir = firmware_dir().join("target").join("must-fail");
    let out = cargo_build(&["oversize-buffers"], Some(&target_dir)).unwrap();
    assert!(
        !out.success,
        "the oversize-buffers firmware linked; it must not"
    );
    assert!(
        out.stderr.contains("will not fit in region 'RAM'")
            || out.stderr.contains("will not fit in region `RAM`"),
        "unexpected failure:\n{}",
        out.stderr
    );
}

#[test]
fn bad_blobs_are_refused_with_their_error() {
    if !qemu_or_skip("bad_blobs_are_refused_with_their_error") {
        return;
    }
    let elf_path = build_firmware().unwrap();
    let elf = ElfInfo::read(&elf_path).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let good = synthetic_blob(8, 16, 4, 9);
    let mut cases: Vec<(&str, Vec<u8>, &str)> = vec![
        // In a flash region, bytes past a truncated blob are whatever the
        // region holds (zeros here): the payload CRC catches it.
        (
            "truncated",
            good[..good.len() - 8].to_vec(),
            "PayloadCorrupt",
        ),
        (
            "bad magic",
            b"NOPE but long enough to hold a preamble".to_vec(),
            "BadMagic",
        ),
    ];
    let mut payload_flip = good.clone();
    *payload_flip.last_mut().unwrap() ^= 0x80;
    cases.push(("payload bit flip", payload_flip, "PayloadCorrupt"));
    let mut version = good.clone();
    version[4] = 99;
    cases.push(("future version", version, "UnsupportedVersion { found: 99"));
    let mut header = good;
    header[14] ^= 0x10;
    cases.push(("header bit flip", header, "HeaderCorrupt"));
    for (name, bytes, expected) in cases {
        let path = dir.path().join("bad.blob");
        std::fs::write(&path, &bytes).unwrap();
        let booted = boot(&elf, &elf_path, Some(&path), None, Duration::from_secs(60)).unwrap();
        assert_eq!(
            booted.run.exit_code,
            wire::exit::BAD_MODEL,
            "{name}: {:?}",
            booted.log
        );
        let last = booted.log.last().cloned().unwrap_or_default();
        assert!(
            last.starts_with("ERROR") && last.contains(expected),
            "{name}: {last}"
        );
    }
}

#[test]
fn firmware_log_snapshots() {
    let name = "firmware_log_snapshots";
    if !qemu_or_skip(name) || golden_or_skip(name).is_none() {
        return;
    }
    let overwrite = std::env::var("PHASEGATE_OVERWRITE_SNAPSHOTS").is_ok_and(|v| v == "1");
    let results = snapshot::run_snapshots(overwrite).unwrap();
    for (name, outcome) in results {
        println!("snapshot {name}: {outcome:?}");
    }
}

/// Issue 4 point 3: the real PFNN, int8 weights, cubic gating (about
/// 2.4 MB), bit-exact under QEMU for 10 frames of realistic inputs
/// (`Xmean + Xstd * N(0, 1)`). Needs `../shared/pfnn/network`.
#[test]
fn real_pfnn_int8_cubic_is_bit_exact_on_the_target() {
    use exporter::float_pfnn::{FloatPfnn, GatingMode};
    use npyz::WriterBuilder;
    let name = "real_pfnn_int8_cubic_is_bit_exact_on_the_target";
    let dir = repo_root()
        .join("..")
        .join("shared")
        .join("pfnn")
        .join("network");
    if !dir.exists() {
        eprintln_direct!("SKIPPED {name}: no real PFNN at {}", dir.display());
        return;
    }
    if !qemu_or_skip(name) {
        return;
    }
    let tables = exporter::pfnn_dir::load_pfnn_dir(&dir).unwrap();
    let (net, residual) = FloatPfnn::from_tables(&tables, GatingMode::Cubic);
    let opts = exporter::quantise::QuantOptions {
        weights: phasegate::blob::WeightFormat::I8,
        ..exporter::quantise::QuantOptions::default()
    };
    let (blob, _) = exporter::export::export_pfnn(&net, residual, &opts).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let blob_path = tmp.path().join("pfnn-int8-cubic.blob");
    std::fs::write(&blob_path, &blob).unwrap();
    let n = 10;
    let s = exporter::calibrate::normal_inputs(&net.xmean.to_vec(), &net.xstd.to_vec(), n, 1.0, 4);
    let x: Vec<f32> = s.inputs.iter().flatten().map(|&v| v as f32).collect();
    let p: Vec<f32> = s.phases.iter().map(|&v| v as f32).collect();
    let write = |path: &std::path::Path, shape: &[u64], data: &[f32]| {
        let mut w = npyz::WriteOptions::new()
            .default_dtype()
            .shape(shape)
            .writer(std::fs::File::create(path).unwrap())
            .begin_nd()
            .unwrap();
        w.extend(data.iter().copied()).unwrap();
        w.finish().unwrap();
    };
    let (xp, pp) = (tmp.path().join("x.npy"), tmp.path().join("p.npy"));
    write(&xp, &[n as u64, net.xmean.len() as u64], &x);
    write(&pp, &[n as u64], &p);
    let report = run_target(&TargetArgs {
        model: blob_path,
        frames: None,
        inputs: Some(xp),
        phases: Some(pp),
    })
    .unwrap();
    assert!(report.bit_exact());
    assert_eq!(report.frames, n);
    assert!(report.blob_len > 2_000_000, "{} bytes", report.blob_len);
    report.check_budgets().unwrap();
}
