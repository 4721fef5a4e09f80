//! Tests of `host-sim target`: the wire format, the STYLES image and the mix
//! schedules (always), and under QEMU (skipped with a message when
//! `qemu-system-arm` or the golden vectors are missing): bit-exactness on
//! the golden vectors, on a whole-network CP model and on a base with two
//! styles switched and blended between frames; issue 4's memory budgets;
//! the must-fail cases (a model too wide for the firmware's buffers is
//! refused at load; buffers too big for RAM fail to link; bad blobs; a style
//! for another base or a damaged style is refused at boot; an unknown style
//! or a malformed mix stops the run at that frame); and the defmt log
//! snapshots.

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

use phasegate::style::BlendWeight;
use phasegate::{Mix, Model, Phase, Runtime, Style, StyleId};

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
    let blob = frames::golden_root().join("default").join("model.blob");
    if blob.exists() {
        Some(blob)
    } else {
        println!(
            "SKIPPED {test}: no golden vectors at {}",
            frames::golden_root().join("default").display()
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
    let mut f = frames::generated(3, &[(0.0, 1.0), (1.0, 2.0)], 7);
    f.mixes = vec![
        Mix::Base,
        Mix::One(StyleId(2)),
        Mix::Blend {
            from: StyleId(1),
            to: StyleId(0),
            weight: BlendWeight::from_bits(0x2000),
        },
    ];
    let image = f.image(5);
    let (h, records) = wire::InputHeader::parse(&image).unwrap();
    assert_eq!((h.frames, h.input_dim, h.output_dim), (3, 2, 5));
    assert_eq!(h.record_len(), 8 + 4 + 4 * 2);
    assert_eq!(records.len(), 3 * h.record_len());
    // The version and the record length are where the doc table says.
    assert_eq!(&image[4..6], &3u16.to_le_bytes());
    assert_eq!(&image[20..24], &20u32.to_le_bytes());
    let mut x = [0f32; 2];
    for (i, r) in records.chunks_exact(h.record_len()).enumerate() {
        let rec = wire::read_record(r, &mut x).unwrap();
        assert_eq!(rec.phase.to_bits(), f.phases[i].to_bits());
        assert_eq!(wire::decode_mix(&rec.mix), Ok(f.mixes[i]));
        assert_eq!(x, f.input(i));
    }
    // The mix field starts the record, byte for byte as documented.
    assert_eq!(&records[20..28], &[1, 2, 0, 0, 0, 0, 0, 0]);
    assert_eq!(&records[40..48], &[2, 1, 0, 0, 0x00, 0x20, 0, 0]);
    assert!(wire::read_record(&records[..19], &mut x).is_none());
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
    // A version-1 image (records without a mix field) and a version-2
    // one (a reach setup without the pose-form section) are refused.
    for v in [1, 2] {
        let mut bad = image.clone();
        bad[4] = v;
        assert_eq!(
            wire::InputHeader::parse(&bad),
            Err(wire::WireError::UnsupportedVersion(u16::from(v)))
        );
    }
    let mut bad = image;
    bad[20] ^= 4;
    assert_eq!(
        wire::InputHeader::parse(&bad),
        Err(wire::WireError::BadHeader)
    );
}

#[test]
fn mix_fields_round_trip_and_malformed_ones_are_refused() {
    let w = |bits| BlendWeight::from_bits(bits);
    for mix in [
        Mix::Base,
        Mix::One(StyleId(0)),
        Mix::One(StyleId(255)),
        Mix::Blend {
            from: StyleId(0),
            to: StyleId(1),
            weight: w(0),
        },
        Mix::Blend {
            from: StyleId(3),
            to: StyleId(3),
            weight: w(0x8000),
        },
    ] {
        assert_eq!(wire::decode_mix(&wire::encode_mix(mix)), Ok(mix), "{mix:?}");
    }
    assert_eq!(
        wire::decode_mix(&[3, 0, 0, 0, 0, 0, 0, 0]),
        Err(wire::WireError::UnknownMixKind(3))
    );
    // Bytes the kind does not use must be 0.
    for (field, offset) in [
        ([0u8, 1, 0, 0, 0, 0, 0, 0], 1),
        ([1, 0, 1, 0, 0, 0, 0, 0], 2),
        ([1, 0, 0, 0, 1, 0, 0, 0], 4),
        ([2, 0, 1, 1, 0, 0, 0, 0], 3),
        ([2, 0, 1, 0, 0, 0, 0, 9], 7),
    ] {
        assert_eq!(
            wire::decode_mix(&field),
            Err(wire::WireError::BadMixField { offset }),
            "{field:?}"
        );
    }
    // Weights above 1.0 are refused, 1.0 itself is fine.
    assert!(wire::decode_mix(&[2, 0, 1, 0, 0x00, 0x80, 0, 0]).is_ok());
    assert_eq!(
        wire::decode_mix(&[2, 0, 1, 0, 0x01, 0x80, 0, 0]),
        Err(wire::WireError::BadMixField { offset: 4 })
    );
    assert_eq!(
        wire::decode_mix(&wire::encode_mix(Mix::Blend {
            from: StyleId(0),
            to: StyleId(1),
            weight: w(0xFFFF),
        })),
        Err(wire::WireError::BadMixField { offset: 4 })
    );
}

#[test]
fn styles_are_packed_at_16_byte_offsets() {
    let blobs = vec![vec![1u8; 5], vec![2u8; 16], vec![3u8; 1]];
    let image = styles::pack_styles(&blobs);
    assert_eq!(image.len(), 32 + 1);
    assert_eq!(&image[..5], &[1; 5]);
    assert_eq!(&image[5..16], &[0; 11]);
    assert_eq!(&image[16..32], &[2; 16]);
    assert_eq!(image[32], 3);
    assert!(styles::pack_styles(&[]).is_empty());
}

#[test]
fn mix_specs_parse_and_schedule() {
    let sched = |spec: &str, n| spec.parse::<MixSpec>().unwrap().schedule(n);
    let blend = |a, b, bits| Mix::Blend {
        from: StyleId(a),
        to: StyleId(b),
        weight: BlendWeight::from_bits(bits),
    };
    assert_eq!(sched("base", 3), vec![Mix::Base; 3]);
    assert_eq!(sched("1", 2), vec![Mix::One(StyleId(1)); 2]);
    assert_eq!(sched("blend:0:1:0.3", 1), vec![blend(0, 1, 9830)]);
    assert_eq!(
        sched("base*2,0,blend:1:0:1", 6),
        vec![
            Mix::Base,
            Mix::Base,
            Mix::One(StyleId(0)),
            blend(1, 0, 0x8000),
            Mix::Base,
            Mix::Base
        ]
    );
    let c = sched("cycle", 18);
    assert_eq!(&c[..2], &[Mix::Base; 2]);
    assert_eq!(&c[2..4], &[Mix::One(StyleId(0)); 2]);
    assert_eq!(&c[4..6], &[Mix::One(StyleId(1)); 2]);
    let weights: Vec<u16> = c[6..16]
        .iter()
        .step_by(2)
        .map(|m| match m {
            Mix::Blend { from, to, weight } => {
                assert_eq!((from.0, to.0), (0, 1));
                weight.to_bits()
            }
            other => panic!("{other:?}"),
        })
        .collect();
    assert_eq!(weights, [0, 0x2000, 0x4000, 0x6000, 0x8000]);
    assert_eq!(&c[16..18], &[Mix::Base; 2]);
    assert_eq!(sched("cycle:1", 8)[7], blend(0, 1, 0x8000));
    for bad in [
        "",
        "blend:0:1",
        "blend:0:1:1.5",
        "blend:0:1:-0.1",
        "256",
        "x",
        "base*0",
        "cycle:0",
        "cycles",
    ] {
        assert!(bad.parse::<MixSpec>().is_err(), "{bad:?} parsed");
    }
    for spec in ["base", "cycle:3", "base*2,0,blend:0:1:0.5"] {
        assert_eq!(spec.parse::<MixSpec>().unwrap().to_string(), spec);
    }
    assert!(styles::check_schedule(&sched("cycle", 16), 2).is_ok());
    let e = styles::check_schedule(&sched("cycle", 16), 1).unwrap_err();
    assert!(e.to_string().contains("uses style 1"), "{e}");
    assert_eq!(MixSpec::default_for(0).schedule(2), vec![Mix::Base; 2]);
    assert!(matches!(
        MixSpec::default_for(2),
        MixSpec::Cycle { step: 2 }
    ));
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
        mode: wire::Mode::Network,
    };
    assert_eq!(wire::OutputHeader::parse(&h.encode()), Ok(h));
    assert_eq!(h.record_len(), 8 + 6 * 4);
    let c = wire::OutputHeader {
        mode: wire::Mode::Controller,
        ..h
    };
    assert_eq!(wire::OutputHeader::parse(&c.encode()), Ok(c));
    assert_eq!(c.record_len(), 16 + 4 * 231);
    assert_eq!(&c.encode()[24..28], &1u32.to_le_bytes());
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
        self_test: None,
        model: PathBuf::new(),
        blob_len: 0,
        model_region: ("MODEL", 0),
        source: String::new(),
        frames: 1,
        output_dim: 1,
        mismatches: 0,
        first_mismatches: vec![],
        golden_mismatches: None,
        infer_instructions: Stats::default(),
        frame_instructions: Stats::default(),
        macs_per_frame: 1,
        per_frame: vec![],
        stages: vec![],
        styles: vec![],
        rig: None,
        reach_build: false,
        styles_image: (0, 0),
        mix: MixSpec::default(),
        mix_groups: vec![],
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
        cycles: None,
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
    use exporter::encode::{encode, QKind, QLayer, QModel};
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
    let mut layer = |i: usize, o: usize| QLayer {
        desc: LayerDesc {
            op: LayerOp::Dense,
            in_dim: i as u16,
            out_dim: o as u16,
            experts: 1,
            weights: WeightFormat::I8,
            acc: AccWidth::I32,
            activation: Activation::Identity,
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
        cp: None,
        rbf: None,
        gated: false,
    };
    let layers = vec![layer(input_dim, width), layer(width, output_dim)];
    let m = QModel {
        kind: QKind::Model(ModelKind::Mlp),
        gating: Gating::Single,
        input_stage: vec![(0.0, 256.0); input_dim],
        output_stage: vec![(1.0 / 256.0, 0.0); output_dim],
        layers,
        wiring: exporter::encode::Wiring::Chain,
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

/// The boot self-test under QEMU (issue 38, point 6), both ways: the
/// golden softmax graph with 6 vectors passes at boot and runs its frames
/// as without the section; a copy with one stored output changed and the
/// CRC re-sealed loads but is refused with `SELF_TEST_FAILED` and a log
/// line naming the vector and output; a blob exported with a self-test
/// passes it in the main run, and a malformed section is a load refusal
/// (`BAD_MODEL`, `SelfTestMalformed`), not a self-test failure.
#[test]
fn the_boot_self_test_passes_and_a_corrupted_one_is_refused() {
    let name = "the_boot_self_test_passes_and_a_corrupted_one_is_refused";
    if !qemu_or_skip(name) {
        return;
    }
    let golden = repo_root().join("tests/golden/softmax-graph/model.blob");
    let report = execute(&TargetArgs {
        model: golden.clone(),
        frames: Some(4),
        self_test: Some(6),
        ..TargetArgs::default()
    })
    .unwrap();
    println!("{}", report.render());
    assert!(report.bit_exact());
    let t = report.self_test.clone().unwrap();
    assert_eq!(t.vectors, 6);
    assert!(t.instructions > 0);
    assert_eq!(t.corrupted_exit, wire::exit::SELF_TEST_FAILED);
    assert!(
        t.failed_line.contains("self-test failed: vector 3 output"),
        "{}",
        t.failed_line
    );
    // The main run of a blob that carries a self-test runs it.
    let blob = std::fs::read(&golden).unwrap();
    let (with, _) = exporter::self_test::with_self_test(&blob, 3).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("with.blob");
    std::fs::write(&path, &with).unwrap();
    let report = execute(&TargetArgs {
        model: path.clone(),
        frames: Some(2),
        ..TargetArgs::default()
    })
    .unwrap();
    assert!(
        report
            .log
            .iter()
            .any(|l| l.contains("self-test: 3 vectors passed")),
        "{:?}",
        report.log
    );
    // A malformed section (the footer's input width changed, re-sealed).
    let m = phasegate::Model::from_bytes(&with).unwrap();
    let mut p = m.payload().to_vec();
    let n = p.len();
    p[n - 10] ^= 1;
    let bad = exporter::self_test::reseal(&with, &p).unwrap();
    let path = dir.path().join("malformed.blob");
    std::fs::write(&path, &bad).unwrap();
    let elf_path = build_firmware().unwrap();
    let elf = ElfInfo::read(&elf_path).unwrap();
    let booted = boot(
        &elf,
        &elf_path,
        Some(&path),
        None,
        None,
        std::time::Duration::from_secs(60),
    )
    .unwrap();
    assert_eq!(
        booted.run.exit_code,
        wire::exit::BAD_MODEL,
        "{:?}",
        booted.log
    );
    assert!(
        booted.log.iter().any(|l| l.contains("SelfTestMalformed")),
        "{:?}",
        booted.log
    );
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
    // 16 inputs and a 1,600-wide hidden layer: the arena needs 1,616.
    std::fs::write(&path, synthetic_blob(16, 1600, 4, 5)).unwrap();
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
        msg.contains("BufferTooSmall { needed: 1616, capacity: 1536 }"),
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
        let booted = boot(
            &elf,
            &elf_path,
            Some(&path),
            None,
            None,
            Duration::from_secs(60),
        )
        .unwrap();
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
/// (`Xmean + Xstd * N(0, 1)`). Needs the weights: `$PHASEGATE_PFNN_DIR`,
/// as the other real-PFNN tests read it, or `../shared/pfnn/network`.
#[test]
fn real_pfnn_int8_cubic_is_bit_exact_on_the_target() {
    use exporter::net::{GatingMode, Net};
    use npyz::WriterBuilder;
    let name = "real_pfnn_int8_cubic_is_bit_exact_on_the_target";
    let dir = std::env::var_os("PHASEGATE_PFNN_DIR")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| repo_root().join("../shared/pfnn/network"));
    if !dir.join("Xmean.bin").is_file() {
        eprintln_direct!("SKIPPED {name}: no real PFNN at {}", dir.display());
        return;
    }
    if !qemu_or_skip(name) {
        return;
    }
    let tables = exporter::pfnn_dir::load_pfnn_dir(&dir).unwrap();
    let (net, residual) = Net::from_pfnn_tables(&tables, GatingMode::Cubic);
    let opts = exporter::quantise::QuantOptions {
        weights: phasegate::blob::WeightFormat::I8,
        ..exporter::quantise::QuantOptions::default()
    };
    let (blob, _) = exporter::export::export(&net, residual, &opts).unwrap();
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
        ..TargetArgs::default()
    })
    .unwrap();
    assert!(report.bit_exact());
    assert_eq!(report.frames, n);
    assert!(report.blob_len > 2_000_000, "{} bytes", report.blob_len);
    report.check_budgets().unwrap();
}

// ---- CP layers and styles ----

/// A small base (24 -> 20 -> 20 -> 10, cubic) with its blob and float twin.
fn styled_base(seed: u64) -> (Vec<u8>, exporter::net::Net) {
    let pfnn = synthetic::pfnn_base(seed, 24, 20, 10);
    let (blob, _) =
        exporter::export::export(&pfnn, None, &exporter::quantise::QuantOptions::default())
            .unwrap();
    (blob, pfnn)
}

/// The base of [`styled_base`] with a CP (rank 6) and a diagonal style.
fn base_and_two_styles(dir: &std::path::Path) -> (PathBuf, Vec<PathBuf>) {
    let (blob, net) = styled_base(41);
    let base = dir.join("base.blob");
    std::fs::write(&base, &blob).unwrap();
    let mut paths = Vec::new();
    for (form, name, seed) in [("cp", "cp-style", 42), ("diagonal", "diag-style", 43)] {
        let s = synthetic::style_blob(
            &blob,
            &net,
            &synthetic::adapter(form, 20, 6, seed),
            name,
            None,
        )
        .unwrap();
        let p = dir.join(format!("{name}.style"));
        std::fs::write(&p, s).unwrap();
        paths.push(p);
    }
    (base, paths)
}

/// The styled runtime's `dequantise_output` (what the firmware and the host
/// reference use) equals its own `run` bit for bit, with a style active.
#[test]
fn styled_dequantise_output_equals_run() {
    let dir = tempfile::tempdir().unwrap();
    let (base, styles) = base_and_two_styles(dir.path());
    let blob = std::fs::read(&base).unwrap();
    let style = std::fs::read(&styles[0]).unwrap();
    let model = Model::from_bytes(&blob).unwrap();
    let stage: Vec<(f32, f32)> = model.input_stage().collect();
    let f = frames::generated(4, &stage, 9);
    let mut rt: Box<Runtime<'_, 64, 256, 2>> = Box::new(Runtime::new(model).unwrap());
    rt.add_style(Style::from_bytes(&style).unwrap()).unwrap();
    rt.set_mix(Mix::One(StyleId(0))).unwrap();
    let mut q_in = vec![0i16; f.input_dim];
    for i in 0..f.len() {
        let phase = Phase::from_radians(f.phases[i]).unwrap();
        let (mut a, mut b) = (vec![0f32; 10], vec![0f32; 10]);
        rt.run(phase, f.input(i), &mut a).unwrap();
        rt.quantise_input(f.input(i), &mut q_in).unwrap();
        let q = rt.run_quantised(phase, &q_in).unwrap().to_vec();
        rt.dequantise_output(&q, &mut b).unwrap();
        assert_eq!(
            a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            b.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
        );
    }
    assert!(rt.dequantise_output(&[0; 9], &mut [0.0; 10]).is_err());
}

/// Issue 5: a model whose every layer is CP or diagonal runs bit-exact on
/// the target.
#[test]
fn whole_cp_model_is_bit_exact_on_the_target() {
    let name = "whole_cp_model_is_bit_exact_on_the_target";
    if !qemu_or_skip(name) {
        return;
    }
    let net = synthetic::cp_net(51, 40, 48, 12, 16);
    let (blob, _) =
        exporter::export::export(&net, None, &exporter::quantise::QuantOptions::default()).unwrap();
    let model = Model::from_bytes(&blob).unwrap();
    let ops: Vec<_> = model
        .header()
        .nodes
        .iter()
        .filter_map(|n| n.layer().map(|l| l.op))
        .collect();
    assert!(
        matches!(
            ops[..],
            [
                phasegate::blob::LayerOp::Cp { rank: 16, .. },
                phasegate::blob::LayerOp::Diagonal,
                phasegate::blob::LayerOp::Cp { rank: 8, .. }
            ]
        ),
        "{ops:?}"
    );
    let report = run_bit_exact(&blob, 8);
    assert_eq!(
        u64::from(report.macs_per_frame),
        16 * (40 + 48 + 4) + 4 * 48 + 8 * (48 + 12 + 4)
    );
    assert!(report.infer_instructions.min > 0);
    report.check_budgets().unwrap();
}

/// Runs `blob` for `frames` generated frames under QEMU (from a temporary
/// file, as `host-sim target --model` does) and checks that every frame is
/// bit-exact with the host runtime.
fn run_bit_exact(blob: &[u8], frames: usize) -> TargetReport {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("model.blob");
    std::fs::write(&path, blob).unwrap();
    let report = execute(&TargetArgs {
        model: path,
        frames: Some(frames),
        ..TargetArgs::default()
    })
    .unwrap();
    println!("{}", report.render());
    assert!(report.bit_exact(), "{}", report.render());
    assert_eq!(report.frames, frames);
    report
}

/// OMG's DEC op on the Cortex-M4: graphs with a DEC node (3 centres over a
/// 4-wide latent, and 16 over a 32-wide one, as the tiny RBF-CAT's) run on
/// the reach build (the one with the `dec` feature), bit-exact with the
/// host, within its budgets. The same graphs with an RBF node (the
/// inference firmware) give the cost of the soft assignment's divisions,
/// which `exporter::cost::PER_ROW_DEC` prices.
#[test]
fn dec_graphs_are_bit_exact_on_the_reach_firmware() {
    let name = "dec_graphs_are_bit_exact_on_the_reach_firmware";
    if !qemu_or_skip(name) {
        return;
    }
    for (latent, clusters) in [(4usize, 3usize), (32, 16)] {
        let mut medians = Vec::new();
        for dec in [true, false] {
            let net = synthetic::clustering_net(61, latent, clusters, dec);
            let (blob, _) =
                exporter::export::export(&net, None, &exporter::quantise::QuantOptions::default())
                    .unwrap();
            let report = run_bit_exact(&blob, 8);
            assert_eq!(report.reach_build, dec, "{}", report.render());
            assert_eq!(
                u64::from(report.macs_per_frame),
                (6 * latent + clusters * latent + (clusters + latent) * 5) as u64
            );
            report.check_budgets().unwrap();
            let model = Model::from_bytes(&blob).unwrap();
            medians.push((
                report.infer_instructions.median,
                exporter::cost::estimate_instructions(&model),
            ));
        }
        let ((dec, dec_est), (rbf, rbf_est)) = (medians[0], medians[1]);
        println!(
            "{clusters} centres over {latent}: DEC {dec}, RBF {rbf} instructions per frame \
             (median): {:.0} per DEC row more; estimated {dec_est} and {rbf_est}",
            (dec as f64 - rbf as f64) / clusters as f64
        );
    }
}

/// Issue 5: a base and two styles (CP and diagonal adapters beside layer 1)
/// run bit-exact on the target while the mix switches every frame between
/// base, each style, and blends at weights 0, 0.25, 0.5, 0.75 and 1; the
/// styled frames really differ from the base.
#[test]
fn styles_switched_and_blended_are_bit_exact_on_the_target() {
    let name = "styles_switched_and_blended_are_bit_exact_on_the_target";
    if !qemu_or_skip(name) {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (base, styles) = base_and_two_styles(dir.path());
    let args = TargetArgs {
        model: base.clone(),
        frames: Some(16),
        styles: styles.clone(),
        mix: Some("cycle:1".parse().unwrap()),
        ..TargetArgs::default()
    };
    let report = execute(&args).unwrap();
    println!("{}", report.render());
    assert!(report.bit_exact(), "{}", report.render());
    assert_eq!(report.frames, 16);
    let log = report.log.join("\n");
    assert!(
        log.contains("\"cp-style\"") && log.contains("CP adapter 20 -> 20, rank 6"),
        "{log}"
    );
    assert!(
        log.contains("\"diag-style\"") && log.contains("diagonal adapter 20 -> 20"),
        "{log}"
    );
    assert!(log.contains("2 styles in the STYLES region"), "{log}");
    let labels: Vec<&str> = report.mix_groups.iter().map(|g| g.label.as_str()).collect();
    assert_eq!(labels, ["base", "style 0", "style 1", "blend 0 -> 1"]);
    let blend = &report.mix_groups[3];
    assert_eq!(blend.weights, [0.0, 0.25, 0.5, 0.75, 1.0]);
    assert_eq!(blend.frames, 10);
    // MACs: the base's plus each adapter the mix runs (both for a blend).
    let (s0, s1) = (report.styles[0].macs, report.styles[1].macs);
    let base_macs = u64::from(report.macs_per_frame);
    assert_eq!(report.mix_groups[0].macs, base_macs);
    assert_eq!(report.mix_groups[1].macs, base_macs + s0);
    assert_eq!(report.mix_groups[2].macs, base_macs + s1);
    assert_eq!(blend.macs, base_macs + s0 + s1);
    // Adapters cost instructions: a blend runs both.
    assert!(blend.infer.min > report.mix_groups[0].infer.max);
    report.check_budgets().unwrap();

    // The mixes changed the outputs (so bit-exactness covers the adapters):
    // the same frames with the base alone differ in every styled frame.
    let blob = std::fs::read(&base).unwrap();
    let model = Model::from_bytes(&blob).unwrap();
    let style_files: Vec<StyleFile> = styles.iter().map(|p| StyleFile::read(p).unwrap()).collect();
    let mut f = frames::select(None, None, Some(16), &blob, &model).unwrap();
    f.mixes = "cycle:1".parse::<MixSpec>().unwrap().schedule(16);
    let (styled, _) = host_outputs(model.clone(), &style_files, &f).unwrap();
    let mixes = std::mem::replace(&mut f.mixes, vec![Mix::Base; 16]);
    let (plain, _) = host_outputs(model, &style_files, &f).unwrap();
    let out = 10;
    for (i, mix) in mixes.iter().enumerate() {
        let differs = styled[i * out..(i + 1) * out] != plain[i * out..(i + 1) * out];
        assert_eq!(differs, *mix != Mix::Base, "frame {i} ({mix:?})");
    }
}

/// Issue 5: a style built for another base is refused at boot with
/// BAD_STYLE and a log naming both CRCs; so are a damaged style and a model
/// blob in the STYLES region. Never a panic.
#[test]
fn styles_for_another_base_or_damaged_are_refused_at_boot() {
    let name = "styles_for_another_base_or_damaged_are_refused_at_boot";
    if !qemu_or_skip(name) {
        return;
    }
    let elf_path = build_firmware().unwrap();
    let elf = ElfInfo::read(&elf_path).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (base_blob, base_net) = styled_base(41);
    let (other_blob, other_net) = styled_base(99);
    let base_crc = Model::from_bytes(&base_blob).unwrap().header().payload_crc;
    let other_crc = Model::from_bytes(&other_blob).unwrap().header().payload_crc;
    assert_ne!(base_crc, other_crc);
    let good = synthetic::style_blob(
        &base_blob,
        &base_net,
        &synthetic::adapter("cp", 20, 6, 42),
        "good",
        None,
    )
    .unwrap();
    let foreign = synthetic::style_blob(
        &other_blob,
        &other_net,
        &synthetic::adapter("cp", 20, 6, 42),
        "foreign",
        None,
    )
    .unwrap();
    let mut damaged = good.clone();
    *damaged.last_mut().unwrap() ^= 0x40;
    let base = dir.path().join("base.blob");
    std::fs::write(&base, &base_blob).unwrap();
    // (case, style blobs in the region, what the refusal line must name)
    type Case = (&'static str, Vec<Vec<u8>>, Vec<String>);
    let cases: Vec<Case> = vec![
        (
            "style for another base, second in the region",
            vec![good.clone(), foreign],
            vec![
                "style 1 at 0x".into(),
                "StyleMismatch".into(),
                format!("{base_crc:#010x}"),
                format!("{other_crc:#010x}"),
            ],
        ),
        (
            "damaged style",
            vec![damaged],
            vec!["style 0 at 0x".into(), "PayloadCorrupt".into()],
        ),
        (
            "a model in the STYLES region",
            vec![other_blob.clone()],
            vec!["NotAStyle".into()],
        ),
    ];
    for (case, blobs, expected) in cases {
        let image = styles::pack_styles(&blobs);
        let booted = boot(
            &elf,
            &elf_path,
            Some(&base),
            Some(&image),
            None,
            Duration::from_secs(60),
        )
        .unwrap();
        assert_eq!(
            booted.run.exit_code,
            wire::exit::BAD_STYLE,
            "{case}: {:?}",
            booted.log
        );
        let last = booted.log.last().cloned().unwrap_or_default();
        assert!(last.starts_with("ERROR"), "{case}: {last}");
        for e in &expected {
            assert!(last.contains(e.as_str()), "{case}: {e:?} not in {last}");
        }
    }
    // The host refuses the foreign style too, before running anything.
    let foreign_path = dir.path().join("foreign.style");
    std::fs::write(
        &foreign_path,
        synthetic::style_blob(
            &other_blob,
            &other_net,
            &synthetic::adapter("cp", 20, 6, 42),
            "foreign",
            None,
        )
        .unwrap(),
    )
    .unwrap();
    let err = execute(&TargetArgs {
        model: base,
        frames: Some(2),
        styles: vec![foreign_path],
        ..TargetArgs::default()
    })
    .unwrap_err();
    assert!(
        format!("{err:#}").contains("refused by the host runtime"),
        "{err:#}"
    );
}

/// Issue 5: a frame whose mix names a style that was not loaded, or whose
/// mix field is malformed, stops the run at that frame with FRAME_ERROR
/// (the frames before it are written).
#[test]
fn unknown_style_or_malformed_mix_is_a_frame_error() {
    let name = "unknown_style_or_malformed_mix_is_a_frame_error";
    if !qemu_or_skip(name) {
        return;
    }
    let elf_path = build_firmware().unwrap();
    let elf = ElfInfo::read(&elf_path).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let (base, styles) = base_and_two_styles(dir.path());
    let blob = std::fs::read(&base).unwrap();
    let model = Model::from_bytes(&blob).unwrap();
    let image = styles::pack_styles(&[std::fs::read(&styles[0]).unwrap()]);
    let f = frames::select(None, None, Some(3), &blob, &model).unwrap();
    let ok0 = wire::encode_mix(Mix::Base);
    let ok1 = wire::encode_mix(Mix::One(StyleId(0)));
    let cases: [(&str, [u8; wire::MIX_LEN], &str); 4] = [
        (
            "style 1 not loaded",
            wire::encode_mix(Mix::One(StyleId(1))),
            "UnknownStyle { index: 1 }",
        ),
        (
            "blend to an unknown style",
            wire::encode_mix(Mix::Blend {
                from: StyleId(0),
                to: StyleId(7),
                weight: BlendWeight::from_bits(0x4000),
            }),
            "UnknownStyle { index: 7 }",
        ),
        (
            "unknown kind",
            [9, 0, 0, 0, 0, 0, 0, 0],
            "UnknownMixKind(9)",
        ),
        (
            "weight above 1",
            [2, 0, 0, 0, 0x01, 0x80, 0, 0],
            "BadMixField { offset: 4 }",
        ),
    ];
    for (case, bad, expected) in cases {
        let input = f.image_with_mix_fields(model.output_dim(), &[ok0, ok1, bad]);
        let booted = boot(
            &elf,
            &elf_path,
            Some(&base),
            Some(&image),
            Some(&input),
            Duration::from_secs(60),
        )
        .unwrap();
        assert_eq!(
            booted.run.exit_code,
            wire::exit::FRAME_ERROR,
            "{case}: {:?}",
            booted.log
        );
        let last = booted.log.last().cloned().unwrap_or_default();
        assert!(
            last.starts_with("ERROR frame 2: mix") && last.contains(expected),
            "{case}: {last}"
        );
        // Frames 0 and 1 ran and were written before the refusal.
        let file = booted.run.output_file.unwrap_or_default();
        assert_eq!(
            file.len(),
            wire::HEADER_LEN + 2 * (8 + 6 * model.output_dim()),
            "{case}"
        );
    }
}

// ---- the controller loop on the target ----

#[test]
fn command_images_and_pose_records_round_trip() {
    use phasegate_controller::{Command, GaitWeights, Pose};
    let commands = [
        Command::stand(),
        Command {
            velocity: [1.5, -2.25],
            facing: [0.0, 1.0],
            gait: GaitWeights {
                stand: 0.125,
                walk: 0.5,
                jog: 0.25,
                crouch: 1.0,
            },
        },
        // Hostile values travel as raw bits (the firmware's step refuses them).
        Command {
            velocity: [f32::NAN, f32::INFINITY],
            facing: [-0.0, f32::MIN_POSITIVE],
            gait: GaitWeights::default(),
        },
    ];
    let mixes = [
        wire::encode_mix(Mix::Base),
        wire::encode_mix(Mix::One(StyleId(1))),
        wire::encode_mix(Mix::Base),
    ];
    let image = controller::controller_image(&commands, &mixes);
    let (h, records) = wire::InputHeader::parse(&image).unwrap();
    assert_eq!(h.mode, wire::Mode::Controller);
    assert_eq!((h.frames, h.input_dim, h.output_dim), (3, 342, 311));
    assert_eq!(h.record_len(), 40);
    assert_eq!(&image[20..24], &40u32.to_le_bytes());
    assert_eq!(&image[28..32], &1u32.to_le_bytes());
    // Documented layout of record 1: mix, then velocity, facing, gaits.
    let r1 = &records[40..80];
    assert_eq!(&r1[..8], &[1, 1, 0, 0, 0, 0, 0, 0]);
    assert_eq!(&r1[8..12], &1.5f32.to_le_bytes());
    assert_eq!(&r1[20..24], &1.0f32.to_le_bytes());
    assert_eq!(&r1[24..28], &0.125f32.to_le_bytes());
    assert_eq!(&r1[36..40], &1.0f32.to_le_bytes());
    let bits = |c: &Command| wire::encode_command(c);
    for (i, r) in records.chunks_exact(h.record_len()).enumerate() {
        let (mix, c) = wire::read_command_record(r).unwrap();
        assert_eq!(mix, mixes[i]);
        assert_eq!(bits(&c), bits(&commands[i]), "record {i}");
    }
    assert!(wire::read_command_record(&records[..39]).is_none());
    // An unknown mode is refused.
    let mut bad = image.clone();
    bad[28] = 3;
    assert_eq!(
        wire::InputHeader::parse(&bad),
        Err(wire::WireError::UnknownMode(3))
    );

    // Pose records: every value in its documented place.
    let mut pose = Pose::<f32>::zero();
    pose.frame = 77;
    let mut k = 0u32;
    let mut next = || {
        k += 1;
        k as f32 * 0.5 - 3.0
    };
    for v in pose
        .root_position
        .iter_mut()
        .chain(&mut pose.facing)
        .chain(pose.joint_positions.iter_mut().flatten())
        .chain(pose.joint_rotations.iter_mut().flatten())
        .chain(&mut pose.contacts)
        .chain(std::iter::once(&mut pose.phase))
        .chain(&mut pose.gaits)
    {
        *v = next();
    }
    let head = wire::RecordHead {
        infer_ticks: 11,
        frame_ticks: 22,
    };
    let status = wire::FrameStatus {
        overrun: true,
        held: false,
        pin_high: true,
    };
    let mut buf = vec![0u8; wire::POSE_RECORD_LEN];
    wire::encode_pose_record(head, status, &pose, &mut buf).unwrap();
    assert_eq!(&buf[8..12], &77u32.to_le_bytes());
    assert_eq!(&buf[12..16], &5u32.to_le_bytes());
    assert_eq!(&buf[16..20], &pose.root_position[0].to_le_bytes());
    let rot = 16 + 4 * (3 + 2 + 3 * 31);
    assert_eq!(
        &buf[rot..rot + 4],
        &pose.joint_rotations[0][0].to_le_bytes()
    );
    assert_eq!(&buf[buf.len() - 4..], &pose.gaits[3].to_le_bytes());
    let (h2, s2, p2) = wire::decode_pose_record(&buf).unwrap();
    assert_eq!((h2, s2, &p2), (head, status, &pose));
    assert!(wire::decode_pose_record(&buf[1..]).is_none());
    assert!(wire::encode_pose_record(head, status, &pose, &mut buf[1..]).is_none());
    // A status word with an unknown bit is refused.
    buf[12] = 8;
    assert!(wire::decode_pose_record(&buf).is_none());

    // Field names follow the same order, and a changed value is found.
    assert_eq!(controller::pose_field_name(0), "root_position.x");
    assert_eq!(controller::pose_field_name(5), "joint_positions[0].x");
    assert_eq!(controller::pose_field_name(5 + 93), "joint_rotations[0].x");
    assert_eq!(controller::pose_field_name(230), "gaits[3] (crouch)");
    let mut other = pose.clone();
    other.joint_rotations[2][3] = f32::from_bits(other.joint_rotations[2][3].to_bits() ^ 1);
    let (n, first) =
        controller::compare_poses(std::slice::from_ref(&pose), std::slice::from_ref(&other));
    assert_eq!(n, 1);
    assert_eq!(first[0].field, "joint_rotations[2].w");
    assert_eq!(
        controller::compare_poses(std::slice::from_ref(&pose), std::slice::from_ref(&pose)).0,
        0
    );
}

#[test]
fn controller_is_bit_exact_on_the_default_model() {
    let name = "controller_is_bit_exact_on_the_default_model";
    if !qemu_or_skip(name) {
        return;
    }
    let Some(blob) = golden_or_skip(name) else {
        return;
    };
    let report = controller::run(&controller::ControllerArgs {
        model: &blob,
        script: "walk",
        frames: Some(60),
        styles: &[],
        mix: None,
        deadline: phasegate_controller::DeadlineConfig::NONE,
    })
    .unwrap();
    assert!(report.bit_exact());
    assert_eq!(report.frames, 60);
    assert!(report.network_instructions.min > 0);
    assert!(report.step_instructions.min > report.network_instructions.max);
    assert!(report.loop_instructions.min > 0);
    // The poses moved: the walk is not the reset pose repeated.
    let bytes = std::fs::read(&blob).unwrap();
    let model = Model::from_bytes(&bytes).unwrap();
    let cmds = controller::script_commands(&phasegate_script("walk"), 60);
    let poses = controller::host_poses(model, &[], &cmds, &[]).unwrap();
    assert_ne!(poses[0].root_position, poses[59].root_position);
    // Issue 4's RAM budget holds for the controller firmware too.
    assert!(report.ram.total() <= RAM_BUDGET, "{}", report.render());
    println!("{}", report.render());
}

fn phasegate_script(name: &str) -> crate::rollout::Script {
    crate::rollout::Script::builtin(name).unwrap()
}

#[test]
fn controller_with_styles_switched_and_blended_is_bit_exact() {
    let name = "controller_with_styles_switched_and_blended_is_bit_exact";
    if !qemu_or_skip(name) {
        return;
    }
    let Some(blob) = golden_or_skip(name) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let paths: Vec<PathBuf> = synthetic::default_model_styles()
        .unwrap()
        .into_iter()
        .enumerate()
        .map(|(i, b)| {
            let p = dir.path().join(format!("s{i}.style"));
            std::fs::write(&p, b).unwrap();
            p
        })
        .collect();
    // Every step of `cycle` (base, 0, 1, blends at 0 .. 1) twice, one frame each.
    let mix: MixSpec = "cycle:1".parse().unwrap();
    let frames = 16;
    let report = controller::run(&controller::ControllerArgs {
        model: &blob,
        script: "zigzag",
        frames: Some(frames),
        styles: &paths,
        mix: Some(mix.clone()),
        deadline: phasegate_controller::DeadlineConfig::NONE,
    })
    .unwrap();
    assert!(report.bit_exact());
    let labels: Vec<&str> = report.mix_groups.iter().map(|g| g.label.as_str()).collect();
    assert_eq!(labels, ["base", "style 0", "style 1", "blend 0 -> 1"]);
    // The styles change the poses (else the comparison would prove little).
    let bytes = std::fs::read(&blob).unwrap();
    let files: Vec<StyleFile> = paths.iter().map(|p| StyleFile::read(p).unwrap()).collect();
    let cmds = controller::script_commands(&phasegate_script("zigzag"), frames);
    let styled = controller::host_poses(
        Model::from_bytes(&bytes).unwrap(),
        &files,
        &cmds,
        &mix.schedule(frames),
    )
    .unwrap();
    let plain =
        controller::host_poses(Model::from_bytes(&bytes).unwrap(), &files, &cmds, &[]).unwrap();
    assert_eq!(styled[0], plain[0], "frame 0 uses the base in both");
    assert_ne!(styled[frames - 1], plain[frames - 1]);
}

#[test]
fn controller_refuses_non_pfnn_models_and_bad_commands() {
    use phasegate_controller::Command;
    let name = "controller_refuses_non_pfnn_models_and_bad_commands";
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("small.blob");
    std::fs::write(&path, synthetic_blob(24, 64, 9, 3)).unwrap();
    // On the host, before QEMU: one line naming the shape.
    let err = controller::execute(&controller::ControllerArgs {
        model: &path,
        script: "walk",
        frames: Some(4),
        styles: &[],
        mix: None,
        deadline: phasegate_controller::DeadlineConfig::NONE,
    })
    .unwrap_err();
    let msg = format!("{err:#}");
    assert!(
        msg.contains("24 inputs and 9 outputs") && msg.contains("342 and 311"),
        "{msg}"
    );
    assert!(!msg.contains('\n'), "{msg}");
    if !qemu_or_skip(name) {
        return;
    }
    let Some(golden) = golden_or_skip(name) else {
        return;
    };
    let cmds = controller::script_commands(&phasegate_script("walk"), 3);
    let base = [wire::encode_mix(Mix::Base); 3];
    let image = controller::controller_image(&cmds, &base);
    // On the firmware: the runtime's NotPfnn, its own exit code.
    let elf_path = build_controller_firmware().unwrap();
    let elf = ElfInfo::read(&elf_path).unwrap();
    let t = Duration::from_secs(60);
    let booted = boot(&elf, &elf_path, Some(&path), None, Some(&image), t).unwrap();
    assert_eq!(
        booted.run.exit_code,
        wire::exit::NOT_PFNN,
        "{:?}",
        booted.log
    );
    let last = booted.log.last().cloned().unwrap_or_default();
    assert!(
        last.contains("NotPfnn { inputs: 24, outputs: 9 }") && last.contains("342 and 311"),
        "{last}"
    );
    // A NaN command stops the run at its frame with BadCommand.
    let mut bad = cmds.clone();
    bad[2] = Command {
        velocity: [0.0, f32::NAN],
        ..cmds[2]
    };
    let image_bad = controller::controller_image(&bad, &base);
    let booted = boot(&elf, &elf_path, Some(&golden), None, Some(&image_bad), t).unwrap();
    assert_eq!(
        booted.run.exit_code,
        wire::exit::FRAME_ERROR,
        "{:?}",
        booted.log
    );
    let last = booted.log.last().cloned().unwrap_or_default();
    assert!(last.contains("frame 2: BadCommand { field: 1 }"), "{last}");
    let file = booted.run.output_file.unwrap_or_default();
    assert_eq!(file.len(), wire::HEADER_LEN + 2 * wire::POSE_RECORD_LEN);
    // The inference firmware has no controller: refused, not misread.
    let inf_path = build_firmware().unwrap();
    let inf = ElfInfo::read(&inf_path).unwrap();
    let booted = boot(&inf, &inf_path, Some(&golden), None, Some(&image), t).unwrap();
    assert_eq!(
        booted.run.exit_code,
        wire::exit::NO_CONTROLLER,
        "{:?}",
        booted.log
    );
}

/// The controller under a frame deadline on the firmware (docs/deadline.md).
fn deadline_run(
    blob: &std::path::Path,
    instructions: u64,
    policy: phasegate_controller::OverrunPolicy,
) -> controller::ControllerReport {
    let deadline = phasegate_controller::DeadlineConfig {
        budget: Some(
            phasegate_controller::FrameBudget::from_instructions(
                instructions,
                INSTRUCTIONS_PER_TICK as u32,
            )
            .unwrap(),
        ),
        policy,
    };
    let report = controller::run(&controller::ControllerArgs {
        model: blob,
        script: "walk",
        frames: Some(40),
        styles: &[],
        mix: None,
        deadline,
    })
    .unwrap();
    println!("{}", report.render());
    assert!(report.policy_mismatches.is_empty());
    assert!(report.bit_exact());
    report
}

/// A budget far below a step's cost (4,000 instructions: a step of the
/// default model costs a few hundred thousand) overruns every inferred
/// frame; under hold-next every other frame is held (the same pose
/// again), the status pin reads high after each overrun and low after
/// each held frame, the defmt log has one line per overrun, and the
/// host's loop replaying the held frames stays bit-exact. Report-only:
/// every frame overruns, none is held, the poses are the plain loop's.
/// A generous budget: nothing overruns.
#[test]
fn controller_deadline_overruns_hold_and_drive_the_pin_under_qemu() {
    use phasegate_controller::OverrunPolicy;
    let name = "controller_deadline_overruns_hold_and_drive_the_pin_under_qemu";
    if !qemu_or_skip(name) {
        return;
    }
    let Some(blob) = golden_or_skip(name) else {
        return;
    };
    let tight = deadline_run(&blob, 4_000, OverrunPolicy::HoldNext);
    assert_eq!(tight.frames, 40);
    for (i, s) in tight.status.iter().enumerate() {
        let inferred = i % 2 == 0;
        assert_eq!(
            (s.overrun, s.held, s.pin_high),
            (inferred, !inferred, inferred),
            "frame {i}"
        );
    }
    let warns = tight
        .log
        .iter()
        .filter(|l| l.contains("overran its budget"))
        .count();
    assert_eq!(warns, 20, "{:?}", tight.log);
    assert!(tight
        .log
        .iter()
        .any(|l| l.contains("deadline: 20 of 40 frames overran, 20 held")));
    // Held frames repeat the pose; the character still walked 20 frames.
    let bytes = std::fs::read(&blob).unwrap();
    let cmds = controller::script_commands(&phasegate_script("walk"), 40);
    let held: Vec<bool> = tight.status.iter().map(|s| s.held).collect();
    let poses =
        controller::replay_poses(Model::from_bytes(&bytes).unwrap(), &[], &cmds, &[], &held)
            .unwrap();
    assert_eq!(poses[1], poses[0]);
    assert_eq!(poses[39].frame, 20);

    let report_only = deadline_run(&blob, 4_000, OverrunPolicy::Report);
    assert_eq!((report_only.overruns(), report_only.held()), (40, 0));
    assert_eq!(report_only.pin_high_frames(), 40);

    let generous = deadline_run(&blob, 100_000_000, OverrunPolicy::HoldNext);
    assert_eq!(
        (
            generous.overruns(),
            generous.held(),
            generous.pin_high_frames()
        ),
        (0, 0, 0)
    );
    assert!(!generous
        .log
        .iter()
        .any(|l| l.contains("overran its budget")));
}

/// The policy replayed on the host from recorded frame ticks.
#[test]
fn policy_replay_follows_the_recorded_ticks() {
    use phasegate_controller::{DeadlineConfig, OverrunPolicy};
    let c = DeadlineConfig::new(100, OverrunPolicy::HoldNext).unwrap();
    let s = controller::replay_policy(c, &[50, 150, 2, 101, 1, 100]);
    let bits: Vec<u32> = s.iter().map(|s| s.to_u32()).collect();
    // overrun | held << 1 | pin << 2
    assert_eq!(bits, vec![0, 5, 2, 5, 2, 0]);
    assert!(controller::replay_policy(DeadlineConfig::NONE, &[u64::MAX])
        .iter()
        .all(|s| s.to_u32() == 0));
}

/// A damaged deadline block is refused by the firmware with one error
/// line and the bad-input exit code, before any frame runs.
#[test]
fn controller_refuses_a_damaged_deadline_block() {
    let name = "controller_refuses_a_damaged_deadline_block";
    if !qemu_or_skip(name) {
        return;
    }
    let Some(blob) = golden_or_skip(name) else {
        return;
    };
    let cmds = controller::script_commands(&phasegate_script("walk"), 2);
    let base = vec![wire::encode_mix(Mix::Base); 2];
    let budget = phasegate_controller::FrameBudget::from_ticks(50).unwrap();
    let mut image = controller::deadline_image(
        &cmds,
        &base,
        phasegate_controller::DeadlineConfig {
            budget: Some(budget),
            policy: phasegate_controller::OverrunPolicy::HoldNext,
        },
    );
    let n = image.len();
    image[n - 8] = 7; // policy 7, CRC now wrong
    let elf_path = build_controller_firmware().unwrap();
    let elf = ElfInfo::read(&elf_path).unwrap();
    let t = Duration::from_secs(60);
    let booted = boot(&elf, &elf_path, Some(&blob), None, Some(&image), t).unwrap();
    assert_eq!(
        booted.run.exit_code,
        wire::exit::BAD_INPUT,
        "{:?}",
        booted.log
    );
    let last = booted.log.last().cloned().unwrap_or_default();
    assert!(last.contains("deadline block refused"), "{last}");
}

/// The exporter's cost model (`exporter::cost`) against the firmware: on
/// every golden blob the estimate is within the model's stated tolerance
/// of the measured whole frame (`Runtime::run`'s three stages).
#[test]
fn cost_estimate_tracks_qemu() {
    let name = "cost_estimate_tracks_qemu";
    if !qemu_or_skip(name) {
        return;
    }
    if golden_or_skip(name).is_none() {
        return;
    }
    for case in ["default", "dense-int16", "softmax-graph", "cp-diagonal"] {
        let blob = frames::golden_root().join(case).join("model.blob");
        let report = execute(&TargetArgs {
            model: blob.clone(),
            frames: Some(8),
            inputs: None,
            phases: None,
            styles: vec![],
            rig: None,
            mix: None,
            cycles: false,
            self_test: None,
        })
        .unwrap();
        let bytes = std::fs::read(&blob).unwrap();
        let estimate = exporter::cost::estimate_instructions(&Model::from_bytes(&bytes).unwrap());
        let measured = report.frame_instructions.median;
        println!(
            "{case}: estimated {estimate}, measured {measured} instructions per frame ({:+.1} %)",
            (estimate as f64 / measured as f64 - 1.0) * 100.0
        );
        assert!(
            estimate.abs_diff(measured) * 100 <= exporter::cost::TOLERANCE_PERCENT * measured,
            "{case}: estimated {estimate}, measured {measured}"
        );
    }
}

/// `--cycles` traces the run and prices each frame's inference: the
/// trace's instruction count is the firmware's own measurement (SysTick,
/// 40-instruction ticks) plus the marker calls and the two `now()` readings
/// inside the brackets, and the cycle range is ordered.
#[test]
fn cycle_trace_counts_what_the_firmware_measures() {
    let name = "cycle_trace_counts_what_the_firmware_measures";
    if !qemu_or_skip(name) {
        return;
    }
    if golden_or_skip(name).is_none() {
        return;
    }
    for case in ["default", "cp-diagonal"] {
        let report = execute(&TargetArgs {
            model: frames::golden_root().join(case).join("model.blob"),
            frames: Some(3),
            cycles: true,
            ..TargetArgs::default()
        })
        .unwrap();
        assert!(report.bit_exact(), "{case}: a traced run stays bit-exact");
        let c = report.cycles.expect("--cycles gives a cycle report");
        assert_eq!(c.frames, 3);
        let traced = c.median.instructions;
        let measured = report.infer_instructions.median;
        assert!(
            traced.abs_diff(measured) <= 2 * INSTRUCTIONS_PER_TICK + 64,
            "{case}: trace {traced} vs firmware {measured} instructions"
        );
        let [lo, typ, hi] = c.median.cycles;
        assert!(
            lo <= typ && typ <= hi && lo >= traced,
            "{case}: {lo} {typ} {hi}"
        );
        assert_eq!(
            c.median.mix.values().map(|m| m.instructions).sum::<u64>(),
            traced
        );
        assert!(
            !c.median.mix.contains_key(&super::cycles::Class::Unknown),
            "{case}: every executed instruction is in the cycle table: {:?}",
            c.median.mix.keys()
        );
        println!("{case}:\n{}", c.render(u64::from(report.macs_per_frame)));
    }
}

/// Issue 11 item 6: one motion blob (tiny_fe_r1 at int8) in MODEL and a
/// rig blob in STYLES run as one model on the firmware, bit for bit with
/// the host runtime's pair, switching rigs between runs (R4, then R1); a
/// rig built for another motion blob is refused at boot with BAD_RIG and
/// both CRCs in the log.
#[test]
fn motion_blob_with_two_rig_blobs_is_bit_exact_on_the_target() {
    let name = "motion_blob_with_two_rig_blobs_is_bit_exact_on_the_target";
    if !qemu_or_skip(name) {
        return;
    }
    use exporter::rig::{export_rig, rig_mask, OMG_RIG_NODES};
    use phasegate::blob::WeightFormat;
    let models = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/omg");
    let load = |m: &str| crate::omg::load_dir(&models.join(m)).unwrap();
    let (r1, r4) = (load("tiny_fe_r1"), load("tiny_fe_r4_frozen"));
    let opts = crate::omg::exporter_options(WeightFormat::I8);
    let motion = crate::omg::export(&r1, WeightFormat::I8, &opts).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let motion_path = dir.path().join("motion.blob");
    std::fs::write(&motion_path, &motion).unwrap();
    let rig_of = |d: &crate::omg::OmgDir, base: &[u8], rig: &str| {
        let mask = rig_mask(&d.omg.net, &OMG_RIG_NODES).unwrap();
        let (bytes, _) = export_rig(&d.omg.net, base, mask, rig, &opts).unwrap();
        let path = dir.path().join(format!("{rig}.rig"));
        std::fs::write(&path, bytes).unwrap();
        path
    };
    for (d, rig, dims) in [
        (&r4, "R4", (356, 8 + 24 + 24)),
        (&r1, "R1", (440, 8 + 30 + 24)),
    ] {
        let path = rig_of(d, &motion, rig);
        let report = execute(&TargetArgs {
            model: motion_path.clone(),
            rig: Some(path),
            frames: Some(4),
            ..TargetArgs::default()
        })
        .unwrap();
        println!("{}", report.render());
        assert!(report.bit_exact(), "{rig}: {}", report.render());
        assert_eq!(report.frames, 4);
        assert_eq!(report.output_dim, dims.1, "{rig}");
        assert!(
            report
                .log
                .iter()
                .any(|l| l.contains("rig blob at") && l.contains(rig)),
            "{rig}: {:?}",
            report.log
        );
        report.check_budgets().unwrap();
    }
    // A rig bound to another motion blob (the int16 one).
    let other = crate::omg::export(
        &r1,
        WeightFormat::I16,
        &crate::omg::exporter_options(WeightFormat::I16),
    )
    .unwrap();
    let stray = rig_of(&r4, &other, "stray");
    // The reach firmware (the build with rig pairs) refuses it at boot,
    // naming both CRCs.
    let elf_path = build_reach_firmware().unwrap();
    let elf = ElfInfo::read(&elf_path).unwrap();
    let booted = boot(
        &elf,
        &elf_path,
        Some(&motion_path),
        Some(&std::fs::read(&stray).unwrap()),
        None,
        Duration::from_secs(60),
    )
    .unwrap();
    assert_eq!(
        booted.run.exit_code,
        wire::exit::BAD_RIG,
        "{:?}",
        booted.log
    );
    let last = booted.log.last().cloned().unwrap_or_default();
    let crc = |b: &[u8]| Model::from_bytes(b).unwrap().header().payload_crc;
    for e in [
        "rig blob at 0x".to_string(),
        "RigMismatch".into(),
        format!("{:#010x}", crc(&motion)),
        format!("{:#010x}", crc(&other)),
    ] {
        assert!(last.contains(e.as_str()), "{e:?} not in {last}");
    }
    // And the host before running anything.
    let err = execute(&TargetArgs {
        model: motion_path,
        rig: Some(stray),
        frames: Some(1),
        ..TargetArgs::default()
    })
    .unwrap_err();
    let msg = format!("{err:#}");
    assert!(
        msg.contains("is not a rig blob for the motion blob"),
        "{msg}"
    );
}
