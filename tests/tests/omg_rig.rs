//! Rig blobs (docs/omg.md, "Rig blobs"): one motion blob exported from
//! `models/omg/tiny_fe_r1`, rig blobs for R1 (the same model) and R4
//! (`tiny_fe_r4_frozen`, whose cost encoder, gate and experts are R1's,
//! frozen) quantised against it, run as pairs on the host runtime.

use std::path::{Path, PathBuf};

use exporter::rig::{export_rig, rig_mask, OMG_RIG_NODES};
use host_sim::omg::{export, exporter_options, load_dir, rig_agreement, OmgDir};
use phasegate::blob::{Framed, Header, ModelKind, NodeOp, Source, WeightFormat};
use phasegate::{Error, Model, Phase, RigInfo, Runtime};

fn model_dir(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../models/omg")
        .join(name)
}

/// The motion blob (tiny_fe_r1 as `exporter omg` writes it) and the rig
/// blob of `dir`'s model for it, as `exporter omg-rig` writes them.
fn pair(d: &OmgDir, motion: &OmgDir, w: WeightFormat, name: &str) -> (Vec<u8>, Vec<u8>) {
    let opts = exporter_options(w);
    let m = export(motion, w, &opts).unwrap();
    let mask = rig_mask(&d.omg.net, &OMG_RIG_NODES).unwrap();
    let (rig, report) = export_rig(&d.omg.net, &m, mask, name, &opts).unwrap();
    assert_eq!(report.blob_bytes, rig.len());
    (m, rig)
}

#[test]
fn motion_r1_with_the_r4_rig_follows_the_r4_model() {
    let r1 = load_dir(&model_dir("tiny_fe_r1")).unwrap();
    let r4 = load_dir(&model_dir("tiny_fe_r4_frozen")).unwrap();
    let (m16, rig16) = pair(&r4, &r1, WeightFormat::I16, "R4");
    let (m8, rig8) = pair(&r4, &r1, WeightFormat::I8, "R4");
    let a16 = rig_agreement(&r4, &m16, &rig16, "int16").unwrap();
    let a8 = rig_agreement(&r4, &m8, &rig8, "int8").unwrap();
    eprintln!("{a16:?}\n{a8:?}");
    // The pair needs what the R4 model alone needs (its graph, its plan).
    let single_blob = export(&r4, WeightFormat::I8, &exporter_options(WeightFormat::I8)).unwrap();
    let single = Model::from_bytes(&single_blob).unwrap();
    assert_eq!(a8.ram_bytes, single.ram_bytes());
    assert_eq!(a8.macs_per_frame, single.macs_per_frame());
    // Measured (docs/omg.md): int16 one step max 0.018 cm, rollout p99
    // 0.025 cm; int8 one step p99 0.30 cm, rollout p99 0.54 cm. The bars
    // are the single R4 blob's (tests/omg_models.rs).
    assert!(a16.one_step.max_joint_m <= 0.001, "{a16:?}");
    assert!(a16.rollout.p99_joint_m <= 0.01, "{a16:?}");
    assert!(a8.one_step.p99_joint_m <= 0.01, "{a8:?}");
    assert!(a8.rollout.p99_joint_m <= 0.02, "{a8:?}");
}

/// The raw i16 outputs of `model` on every reference input of `d`.
fn raw_outputs(model: Model<'_>, d: &OmgDir) -> Vec<i16> {
    let mut rt: Box<Runtime<'_, 4096>> = Box::new(Runtime::new(model).unwrap());
    let [clips, frames, _] = d.refs.inputs.dims;
    let mut q = vec![0i16; rt.model().input_dim()];
    let mut out = Vec::new();
    for c in 0..clips {
        for t in 0..frames {
            let x: Vec<f32> = d.refs.inputs.row(c, t).iter().map(|&v| v as f32).collect();
            rt.quantise_input(&x, &mut q).unwrap();
            out.extend_from_slice(rt.run_quantised(Phase::from_bits(0), &q).unwrap());
        }
    }
    out
}

#[test]
fn motion_r1_with_the_r1_rig_is_the_r1_blob_bit_for_bit() {
    let r1 = load_dir(&model_dir("tiny_fe_r1")).unwrap();
    for w in [WeightFormat::I8, WeightFormat::I16] {
        let (m, rig) = pair(&r1, &r1, w, "R1");
        let both = Model::with_rig(&m, &rig).unwrap();
        let single = Model::from_bytes(&m).unwrap();
        // The R1 rig's nodes are the motion blob's own, byte for byte: the
        // same calibration, and formats forced to what they already were.
        let (hb, hs) = (both.header().decoded(), single.header().decoded());
        assert_eq!(hb.nodes.len(), hs.nodes.len());
        for (i, (a, b)) in hb.nodes.iter().zip(&hs.nodes).enumerate() {
            let (Some(ka), Some(kb)) = (both.kernel(i), single.kernel(i)) else {
                continue;
            };
            assert_eq!(ka.requant(), kb.requant(), "{w:?} node {i}");
            assert_eq!(a.inputs, b.inputs, "{w:?} node {i}");
        }
        assert_eq!(both.ram_bytes(), single.ram_bytes());
        assert_eq!(raw_outputs(both, &r1), raw_outputs(single, &r1), "{w:?}");
    }
}

#[test]
fn a_rig_for_another_motion_blob_is_refused_naming_both_crcs() {
    let r1 = load_dir(&model_dir("tiny_fe_r1")).unwrap();
    let r4 = load_dir(&model_dir("tiny_fe_r4_frozen")).unwrap();
    let (m8, rig8) = pair(&r4, &r1, WeightFormat::I8, "R4");
    let m16 = export(&r1, WeightFormat::I16, &exporter_options(WeightFormat::I16)).unwrap();
    let crc = |b: &[u8]| Model::from_bytes(b).unwrap().header().payload_crc;
    let e = Model::with_rig(&m16, &rig8).unwrap_err();
    assert_eq!(
        e,
        Error::RigMismatch {
            motion_crc: crc(&m16),
            rig_crc: crc(&m8)
        }
    );
    let text = e.to_string();
    assert!(text.contains(&format!("{:#010x}", crc(&m16))), "{text}");
    assert!(text.contains(&format!("{:#010x}", crc(&m8))), "{text}");
    let info = RigInfo::from_bytes(&rig8).unwrap();
    assert_eq!((info.name, info.base_crc), ("R4", crc(&m8)));
    // Each blob where the other belongs.
    assert_eq!(Model::from_bytes(&rig8).unwrap_err(), Error::NotAModel);
    assert_eq!(Model::with_rig(&m8, &m8).unwrap_err(), Error::NotARig);
    assert_eq!(RigInfo::from_bytes(&m8).unwrap_err(), Error::NotARig);
    assert!(Model::with_rig(&rig8, &rig8).is_err());
}

#[test]
fn damaged_and_truncated_rig_blobs_are_refused() {
    let r1 = load_dir(&model_dir("tiny_fe_r1")).unwrap();
    let r4 = load_dir(&model_dir("tiny_fe_r4_frozen")).unwrap();
    let (m, rig) = pair(&r4, &r1, WeightFormat::I8, "R4");
    Model::with_rig(&m, &rig).unwrap();
    // Every byte of the preamble, header and padding, then every 97th of
    // the payload (each flip is caught by a CRC; the whole blob's every
    // byte is tests/byte_flips.rs's job on a small rig).
    let header_end = 64 + usize::from(u16::from_le_bytes([rig[6], rig[7]]));
    let flips = (0..header_end.min(rig.len())).chain((header_end..rig.len()).step_by(97));
    for at in flips {
        let mut bad = rig.clone();
        bad[at] ^= 0x5a;
        assert!(Model::with_rig(&m, &bad).is_err(), "flip at {at}");
    }
    for cut in [0, 4, 11, 12, 100, header_end, rig.len() / 2, rig.len() - 1] {
        assert!(
            matches!(
                Model::with_rig(&m, &rig[..cut]).unwrap_err(),
                Error::Truncated { .. } | Error::BadMagic | Error::HeaderCorrupt
            ),
            "cut at {cut}"
        );
    }
    let mut long = rig.clone();
    long.push(0);
    assert!(matches!(
        Model::with_rig(&m, &long).unwrap_err(),
        Error::TrailingBytes { .. }
    ));
    // From flash regions, bytes after each blob are ignored.
    let mut mr = m.clone();
    mr.extend([0xff; 64]);
    Model::with_rig_regions(&mr, &long).unwrap();
}

/// The rig's header re-framed after `edit` (payload unchanged).
fn reframed(rig: &[u8], edit: impl FnOnce(&mut Header)) -> Vec<u8> {
    let f = Framed::parse(rig, true).unwrap();
    let mut h = f.header.decoded();
    edit(&mut h);
    exporter::encode::frame(&h, f.payload)
}

#[test]
fn a_rig_that_does_not_fit_its_motion_blob_is_refused() {
    let r1 = load_dir(&model_dir("tiny_fe_r1")).unwrap();
    let r4 = load_dir(&model_dir("tiny_fe_r4_frozen")).unwrap();
    let (m, rig) = pair(&r4, &r1, WeightFormat::I8, "R4");
    let exporter::net::Wiring::Graph(graph) = &r4.omg.net.wiring else {
        panic!("an OMG net is a graph");
    };
    let g = |name: &str| graph.node(name).unwrap();
    // cost0 (a motion node) reading its input slice one element later:
    // the input-stage records there are not the motion blob's.
    let cost0 = g("cost0");
    let moved = reframed(&rig, |h| {
        let s = &mut h.nodes[cost0].inputs[0];
        assert_eq!(s.source, Source::Input);
        s.start -= 1;
    });
    assert!(matches!(
        Model::with_rig(&m, &moved).unwrap_err(),
        Error::RigIncompatible { .. } | Error::ArenaOverlap { .. } | Error::GraphInvalid { .. }
    ));
    // A motion node claimed by the rig but whose sections are not in the
    // rig's payload.
    let gate0 = g("gate0");
    let claimed = reframed(&rig, |h| {
        if let ModelKind::Rig { nodes, .. } = &mut h.kind {
            *nodes |= 1 << gate0;
        }
    });
    assert!(Model::with_rig(&m, &claimed).is_err());
    // A motion node whose op differs from the motion blob's.
    let moe1 = g("moe1");
    let changed = reframed(&rig, |h| {
        if let NodeOp::Layer(d) = &mut h.nodes[moe1].op {
            d.bias_section = d.requant_section;
        }
    });
    assert!(Model::with_rig(&m, &changed).is_err());
    // A rig bit past the graph.
    let past = reframed(&rig, |h| {
        if let ModelKind::Rig { nodes, .. } = &mut h.kind {
            *nodes |= 1 << 20;
        }
    });
    assert_eq!(
        Model::with_rig(&m, &past).unwrap_err(),
        Error::RigIncompatible { node: 255 }
    );
}
