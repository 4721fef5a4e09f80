//! What the fuzz targets (`fuzz/`, cargo-fuzz, nightly) and their stable
//! proptest equivalents (`tests/tests/fuzz_equivalents.rs`) share: the code
//! each target runs on one input, the structure-aware mutation that keeps a
//! blob's framing valid (both CRCs and the payload length recomputed after
//! every mutation, styles re-bound to their base), and the seed files of
//! every kind.
//!
//! Every `exercise_*` function must return normally whatever its input:
//! a panic is a finding. Inputs that are refused are fine; what matters is
//! that refusing them, or running what was accepted, never panics.

use std::collections::BTreeMap;
use std::io::Cursor;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use exporter::npz::NpArray;
use phasegate::blob::{crc32, Header, ModelKind};
use phasegate::style::BlendWeight;
use phasegate::{blob_len_from_prefix, Mix, Model, Phase, Runtime, Style, StyleId};
use phasegate_controller::{Command, GaitWeights, Locomotion, PfnnController};

/// Arena of the runtimes the targets run (elements): every committed
/// golden blob fits.
pub const ARENA: usize = 4096;
/// Adapter scratch of the styled runtime (elements).
pub const SCRATCH: usize = 1024;
/// Styles a styled runtime holds.
pub const BANK: usize = 4;

const PREAMBLE: usize = 12;

fn payload_start(header_len: usize) -> usize {
    (PREAMBLE + header_len).next_multiple_of(16)
}

// ---------------------------------------------------------------------------
// Framing: splitting a chain of blobs, resealing a damaged one.

/// Splits a concatenation of blobs (a base model followed by style blobs,
/// as they would lie in flash) at the lengths their prefixes state; what
/// does not frame is the last piece.
pub fn split_chain(bytes: &[u8]) -> Vec<&[u8]> {
    let mut out = Vec::new();
    let mut rest = bytes;
    while !rest.is_empty() {
        match blob_len_from_prefix(rest) {
            Ok(n) if n > 0 && n <= rest.len() => {
                out.push(&rest[..n]);
                rest = &rest[n..];
            }
            _ => {
                out.push(rest);
                break;
            }
        }
    }
    out
}

/// The header of a blob if its header bytes decode (whatever the CRCs say).
pub fn raw_header(blob: &[u8]) -> Option<Header> {
    let h = usize::from(u16::from_le_bytes([*blob.get(6)?, *blob.get(7)?]));
    let bytes = blob.get(PREAMBLE..PREAMBLE + h)?;
    postcard::take_from_bytes::<Header>(bytes)
        .ok()
        .map(|(h, _)| h)
}

/// Makes a (possibly mutated) blob's framing consistent again, so that the
/// loader's structural checks, not its CRCs, decide: if the header bytes
/// decode, the payload length and CRC are set to the bytes after the
/// padding and the header is re-encoded (leftover header bytes dropped);
/// the header CRC is always recomputed when the header is all there. The
/// magic and version bytes are kept as they are. `base_crc`, when given,
/// re-binds a style or rig header to that base.
pub fn reseal(blob: &[u8], base_crc: Option<u32>) -> Vec<u8> {
    if blob.len() < PREAMBLE {
        return blob.to_vec();
    }
    let h = usize::from(u16::from_le_bytes([blob[6], blob[7]]));
    let mut out = match raw_header(blob) {
        Some(mut header) => {
            let p = payload_start(h).min(blob.len());
            let payload = &blob[p..];
            header.payload_len = payload.len() as u32;
            header.payload_crc = crc32(payload);
            match (base_crc, &mut header.kind) {
                (Some(crc), ModelKind::Style { base_crc, .. })
                | (Some(crc), ModelKind::Rig { base_crc, .. }) => *base_crc = crc,
                _ => {}
            }
            let mut out = exporter::encode::frame(&header, payload);
            out[..6].copy_from_slice(&blob[..6]);
            out
        }
        None => blob.to_vec(),
    };
    let h = usize::from(u16::from_le_bytes([out[6], out[7]]));
    if PREAMBLE + h <= out.len() {
        let mut covered = out[..8].to_vec();
        covered.extend_from_slice(&out[PREAMBLE..PREAMBLE + h]);
        let crc = crc32(&covered);
        out[8..12].copy_from_slice(&crc.to_le_bytes());
    }
    out
}

/// The payload CRC a style must name to be bound to `base`.
pub fn binding_crc(base: &[u8]) -> Option<u32> {
    raw_header(base).map(|h| h.payload_crc)
}

/// One structure-aware mutation of a chain of blobs: picks a blob, then its
/// header bytes, its payload or the whole blob, lets `mutate` change those
/// bytes (libFuzzer's own mutator in the fuzz targets, random edits in the
/// proptests), then reseals every blob and, unless `choice` says otherwise,
/// re-binds the styles to the base. `choice` is a random number that picks
/// the blob, the region and the variants.
pub fn mutate_chain(data: &[u8], choice: u64, mutate: &mut dyn FnMut(&mut Vec<u8>)) -> Vec<u8> {
    let mut blobs: Vec<Vec<u8>> = split_chain(data).into_iter().map(<[u8]>::to_vec).collect();
    if blobs.is_empty() {
        blobs.push(Vec::new());
    }
    let i = (choice as usize) % blobs.len();
    let blob = &mut blobs[i];
    let h = if blob.len() >= PREAMBLE {
        usize::from(u16::from_le_bytes([blob[6], blob[7]]))
    } else {
        0
    };
    let (lo, hi) = match (choice >> 8) % 4 {
        // The postcard header: every field, lengths and indices included.
        0 | 1 => (PREAMBLE.min(blob.len()), (PREAMBLE + h).min(blob.len())),
        // The payload: weights, biases, records, stages.
        2 => (payload_start(h).min(blob.len()), blob.len()),
        _ => (0, blob.len()),
    };
    let mut region = blob[lo..hi].to_vec();
    mutate(&mut region);
    let h_changed = blob.len() >= PREAMBLE && (choice >> 8) % 4 < 2 && region.len() != hi - lo;
    let mut edited = blob[..lo].to_vec();
    edited.extend_from_slice(&region);
    if h_changed {
        // Keep the header length honest and the payload where it belongs.
        let new_h = region.len().min(usize::from(u16::MAX));
        edited[6..8].copy_from_slice(&(new_h as u16).to_le_bytes());
        edited.resize(payload_start(new_h).max(edited.len()), 0);
        edited.extend_from_slice(blob.get(payload_start(h)..).unwrap_or(&[]));
    } else {
        edited.extend_from_slice(&blob[hi..]);
    }
    *blob = edited;
    // One mutation in eight is left unsealed: the CRC checks get their share.
    if (choice >> 16) & 7 == 0 {
        return blobs.concat();
    }
    let base = reseal(&blobs[0], None);
    let bind = (choice >> 24) & 7 != 0;
    let crc = if bind { binding_crc(&base) } else { None };
    let mut out = base;
    for b in &blobs[1..] {
        out.extend(reseal(b, crc));
    }
    out
}

// ---------------------------------------------------------------------------
// Running what loads.

/// Phases at the edges of the cycle.
pub const PHASES: [u32; 5] = [0, 1, 1 << 30, 1 << 31, u32::MAX];

/// Float inputs at their extremes (finite ones must run; NaN and
/// infinities must be refused).
pub fn extreme_inputs(n: usize) -> Vec<Vec<f32>> {
    let alt = |a: f32, b: f32| (0..n).map(|i| if i % 2 == 0 { a } else { b }).collect();
    let mut v: Vec<Vec<f32>> = vec![
        vec![f32::MAX; n],
        vec![-f32::MAX; n],
        alt(f32::MAX, -f32::MAX),
        vec![0.0; n],
        vec![-0.0; n],
        vec![f32::MIN_POSITIVE / 8.0; n],
        vec![1e30; n],
    ];
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let mut x = vec![1.0; n];
        if let Some(last) = x.last_mut() {
            *last = bad;
        }
        v.push(x);
    }
    v
}

/// Quantised inputs at the i16 rails.
pub fn extreme_quantised(n: usize) -> Vec<Vec<i16>> {
    vec![
        vec![i16::MAX; n],
        vec![i16::MIN; n],
        (0..n)
            .map(|i| if i % 2 == 0 { i16::MAX } else { i16::MIN })
            .collect(),
        vec![0; n],
    ]
}

/// Every extreme input at every phase through `rt`, by the float and the
/// quantised paths; returns the number of frames that ran.
pub fn run_frames<const A: usize, const S: usize, const N: usize>(
    rt: &mut Runtime<'_, A, S, N>,
    phases: &[u32],
) -> usize {
    let (n, m) = (rt.model().input_dim(), rt.model().output_dim());
    let mut frames = 0;
    let mut y = vec![0f32; m];
    for x in extreme_inputs(n) {
        for &ph in phases {
            let r = rt.run(Phase::from_bits(ph), &x, &mut y);
            assert_eq!(
                r.is_ok(),
                x.iter().all(|v| v.is_finite()),
                "finite inputs run, others are refused: {r:?}"
            );
            frames += usize::from(r.is_ok());
        }
    }
    for q in extreme_quantised(n) {
        for &ph in phases {
            if let Ok(out) = rt.run_quantised(Phase::from_bits(ph), &q) {
                let out = out.to_vec();
                rt.dequantise_output(&out, &mut y)
                    .expect("a frame's output dequantises");
                frames += 1;
            }
        }
    }
    // Arguments of the wrong length are refused, never read out of bounds.
    let _ = rt.run(Phase::from_bits(0), &vec![0.0; n + 1], &mut y);
    let _ = rt.run_quantised(Phase::from_bits(0), &vec![0; n.saturating_sub(1)]);
    frames
}

/// The `model` target: a blob loaded exactly and as a region, its prefix
/// length, every extreme input at every edge phase through what loads,
/// and its self-test, if it has one.
pub fn exercise_model(bytes: &[u8]) -> usize {
    let _ = blob_len_from_prefix(bytes);
    let _ = Style::from_bytes(bytes);
    let mut frames = 0;
    for model in [Model::from_bytes(bytes), Model::from_region(bytes)]
        .into_iter()
        .flatten()
    {
        let _ = model.header().decoded();
        let _ = model.macs_per_frame();
        if let Ok(mut rt) = Runtime::<ARENA>::new(model) {
            frames += run_frames(&mut rt, &PHASES);
            // A mutated blob may end with a self-test section: whatever it
            // holds, the self-test passes or names a vector, never more.
            match rt.run_self_test() {
                Ok(_) | Err(phasegate::Error::SelfTestFailed { .. }) => {}
                Err(e) => panic!("a loaded self-test passes or fails a vector: {e:?}"),
            }
        }
    }
    frames
}

/// Every mix of `styles` attached styles, and some that name styles that
/// are not there: none, each one, each ordered pair at weights 0, 1/2, 1
/// and the largest blend weight.
pub fn every_mix(styles: usize) -> Vec<Mix> {
    let mut v = vec![
        Mix::Base,
        Mix::One(StyleId(styles as u8)),
        Mix::One(StyleId(255)),
    ];
    for a in 0..styles as u8 {
        v.push(Mix::One(StyleId(a)));
        for b in 0..=styles as u8 {
            for w in [
                BlendWeight::ZERO,
                BlendWeight::from_num(0.5),
                BlendWeight::ONE,
                BlendWeight::MAX,
            ] {
                v.push(Mix::Blend {
                    from: StyleId(a),
                    to: StyleId(b),
                    weight: w,
                });
            }
        }
    }
    v
}

/// The `styled` target: a base blob followed by style blobs (a flash
/// layout); the base loads as a region, every style that loads is added,
/// and every mix runs every extreme input at the edge phases.
pub fn exercise_styled(bytes: &[u8]) -> usize {
    let chain = split_chain(bytes);
    let Some((base, styles)) = chain.split_first() else {
        return 0;
    };
    let Ok(model) = Model::from_region(base) else {
        return 0;
    };
    let Ok(mut rt) = Runtime::<ARENA, SCRATCH, BANK>::new(model) else {
        return 0;
    };
    let mut attached = 0;
    for s in styles {
        let _ = Style::from_bytes(s);
        if let Ok(style) = Style::from_region(s) {
            let _ = (
                style.name(),
                style.macs_per_frame(),
                style.scratch_elements(),
            );
            attached += usize::from(rt.add_style(style).is_ok());
        }
    }
    let mut frames = 0;
    for mix in every_mix(attached) {
        let set = rt.set_mix(mix);
        let valid = match mix {
            Mix::Base => true,
            Mix::One(a) => usize::from(a.0) < attached,
            Mix::Blend { from, to, .. } => {
                usize::from(from.0) < attached && usize::from(to.0) < attached
            }
        };
        assert_eq!(
            set.is_ok(),
            valid,
            "{mix:?} with {attached} styles: {set:?}"
        );
        if set.is_ok() {
            frames += run_frames(&mut rt, &[0, 1 << 31, u32::MAX]);
        }
    }
    frames
}

/// The `rig` target: a motion blob followed by a rig blob (each in its own
/// flash region on a device); the pair loads exactly and as regions, and
/// what loads runs every extreme input at the edge phases.
pub fn exercise_rig(bytes: &[u8]) -> usize {
    let chain = split_chain(bytes);
    let (Some(motion), Some(rig)) = (chain.first(), chain.get(1)) else {
        return 0;
    };
    let _ = phasegate::RigInfo::from_bytes(rig);
    let mut frames = 0;
    for model in [
        Model::with_rig(motion, rig),
        Model::with_rig_regions(motion, rig),
    ]
    .into_iter()
    .flatten()
    {
        let _ = (
            model.header().decoded(),
            model.rig_nodes(),
            model.arena_elements(),
        );
        if let Ok(mut rt) = Runtime::<ARENA>::new(model) {
            frames += run_frames(&mut rt, &PHASES);
        }
    }
    frames
}

/// A small motion blob (the branching graph of
/// `host_sim::target::synthetic::branching_net`, OMG-shaped) and a rig
/// blob of its encoder and decoder (`pose1`, `pose2`, `dec1`, `dec2`).
pub fn small_rig_pair() -> (Vec<u8>, Vec<u8>) {
    use exporter::quantise::QuantOptions;
    let net = host_sim::target::synthetic::branching_net(7);
    let opts = QuantOptions {
        calibration_samples: 64,
        ..QuantOptions::default()
    };
    let motion = exporter::export::export(&net, None, &opts).unwrap().0;
    let mask = exporter::rig::rig_mask(&net, &["pose1", "pose2", "dec1", "dec2"]).unwrap();
    let rig = exporter::rig::export_rig(&net, &motion, mask, "small", &opts)
        .unwrap()
        .0;
    (motion, rig)
}

/// A float from a tag byte and the bytes after it: most tags pick a hostile
/// value (NaN, infinities, huge, tiny, signed zeros), the rest take the
/// next four bytes as raw bits.
fn hostile_f32(data: &mut &[u8]) -> f32 {
    const SPECIAL: [f32; 14] = [
        f32::NAN,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::MAX,
        -f32::MAX,
        f32::MIN_POSITIVE,
        1e-45,
        0.0,
        -0.0,
        1e30,
        -1e30,
        2.5,
        1.0,
        -1.0,
    ];
    let Some((&tag, rest)) = data.split_first() else {
        return 0.0;
    };
    *data = rest;
    if let Some(v) = SPECIAL.get(usize::from(tag)) {
        return *v;
    }
    let mut b = [0u8; 4];
    for (i, slot) in b.iter_mut().enumerate() {
        *slot = data.get(i).copied().unwrap_or(0);
    }
    *data = data.get(4..).unwrap_or(&[]);
    f32::from_bits(u32::from_le_bytes(b))
}

/// Commands decoded from fuzz bytes: 10 floats each (velocity, facing,
/// four gait weights), plus an action byte (0 step, 1 reset, 2 a frame of
/// the styled mix switch) ahead of each.
pub fn commands(mut data: &[u8]) -> Vec<(u8, Command)> {
    let mut out = Vec::new();
    while !data.is_empty() && out.len() < 64 {
        let action = data[0] % 8;
        data = &data[1..];
        let mut f = || hostile_f32(&mut data);
        let c = Command {
            velocity: [f(), f()],
            facing: [f(), f()],
            gait: GaitWeights {
                stand: f(),
                walk: f(),
                jog: f(),
                crouch: f(),
            },
        };
        out.push((action, c));
    }
    out
}

/// The committed OMG model `tiny_fe_r1` as an int8 blob, and its first
/// reference frame (f32), built once.
/// The committed tiny_fe_r1 as an int8 blob, with what a joint-velocity
/// loop starts from (the first reference frame, the skeleton, the first
/// reference clip's joint angles and velocities).
struct OmgFixture {
    blob: Vec<u8>,
    layout: phasegate_controller::ReachLayout,
    skeleton: phasegate_controller::Skeleton<f32>,
    first: Vec<f32>,
    q0: Vec<f32>,
    v0: Vec<f32>,
}

fn omg_blob() -> &'static OmgFixture {
    static B: OnceLock<OmgFixture> = OnceLock::new();
    B.get_or_init(|| {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/omg/tiny_fe_r1");
        let d = host_sim::omg::load_dir(&dir).expect("committed OMG model");
        let opts = exporter::quantise::QuantOptions {
            headroom: exporter::net::omg::HEADROOM,
            ..Default::default()
        };
        let blob = host_sim::omg::export(&d, phasegate::blob::WeightFormat::I8, &opts)
            .expect("OMG export");
        let f32s = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        let start = host_sim::omg::reference_start(&d, 0);
        let form = d.omg.dof.as_ref().expect("a joint-velocity model");
        OmgFixture {
            blob,
            layout: host_sim::omg::reach_layout(&d.omg).expect("layout"),
            skeleton: host_sim::omg::skeleton::<f32>(&form.skeleton).expect("skeleton"),
            first: f32s(&start.first),
            q0: f32s(&start.q0),
            v0: f32s(&start.v0),
        }
    })
}

/// The `reach` target: the OMG reaching loop (`Reach<f32>` over the
/// runtime, the committed tiny_fe_r1 at int8, grounded and faithful) fed
/// arbitrary target edits and steps. Each action byte picks: set a hand's
/// target (9 hostile floats: position, forward, up), set the target of a
/// key joint that may not exist, set the whole target block (36 floats),
/// switch nothing and step. A refused target must leave the frame and the
/// targets untouched (the next step equals a step without it); an
/// accepted one must have been finite, within range and with axes; every
/// step over the fixed-point runtime gives a finite frame.
pub fn exercise_reach(mut data: &[u8]) -> usize {
    use phasegate_controller::{reach::MAX_TARGET_M, CostMode, Reach, Target};
    let f = omg_blob();
    let layout = &f.layout;
    let mode = match data.first() {
        Some(b) if b % 2 == 1 => CostMode::Faithful,
        _ => CostMode::Grounded,
    };
    data = data.get(1..).unwrap_or(&[]);
    let model = Model::from_bytes(&f.blob).expect("OMG blob");
    let mut rt = Box::new(Runtime::<ARENA>::new(model).expect("fits"));
    let mut r: Box<Reach<f32, 512>> = Box::new(
        Reach::with_dofs(
            &*rt,
            layout.clone(),
            mode,
            &f.first,
            f.skeleton.clone(),
            &f.q0,
            &f.v0,
        )
        .expect("reach"),
    );
    let mut steps = 0;
    let mut actions = 0;
    while !data.is_empty() && actions < 48 {
        actions += 1;
        let action = data[0] % 6;
        data = &data[1..];
        let before = r.frame().to_vec();
        match action {
            0..=2 => {
                let key = if action == 2 {
                    usize::from(data.first().copied().unwrap_or(0) % 8)
                } else {
                    usize::from(action)
                };
                let mut v = [0f32; 9];
                for x in &mut v {
                    *x = hostile_f32(&mut data);
                }
                let t = Target {
                    position: [v[0], v[1], v[2]],
                    forward: [v[3], v[4], v[5]],
                    up: [v[6], v[7], v[8]],
                };
                let finite = v.iter().all(|x| x.is_finite());
                let in_range = v[..3].iter().all(|x| f64::from(x.abs()) <= MAX_TARGET_M);
                let targets = r.targets().to_vec();
                match r.set_target(key, &t) {
                    Ok(()) => assert!(
                        key < layout.key() && finite && in_range,
                        "accepted key {key} {t:?}"
                    ),
                    Err(_) => {
                        assert_eq!(r.frame(), &before[..], "a refused target changed the frame");
                        assert_eq!(r.targets(), &targets[..], "a refused target was kept");
                        // Any axis with a non-zero component has a direction.
                        let clear =
                            v[3..6].iter().any(|x| *x != 0.0) && v[6..9].iter().any(|x| *x != 0.0);
                        assert!(
                            !(key < layout.key() && finite && in_range && clear),
                            "refused a valid target for key {key}: {t:?}"
                        );
                    }
                }
            }
            3 => {
                let mut block = [0f32; 36];
                for x in &mut block {
                    *x = hostile_f32(&mut data);
                }
                let finite = block.iter().all(|x| x.is_finite());
                let keys = layout.key();
                let in_range = block[..3 * keys]
                    .iter()
                    .all(|x| f64::from(x.abs()) <= MAX_TARGET_M);
                // In f32, as Reach<f32> computes it (so the edge agrees).
                let tol = phasegate_controller::reach::UNIT_AXIS_TOLERANCE as f32;
                let unit = block[3 * keys..].chunks_exact(3).all(|a| {
                    a.iter().all(|x| x.abs() <= 2.0)
                        && (a.iter().fold(0f32, |s, &x| s + x * x) - 1.0).abs() <= tol
                });
                let targets = r.targets().to_vec();
                match r.set_target_block(&block) {
                    Ok(()) => assert!(finite && in_range && unit, "accepted {block:?}"),
                    Err(_) => {
                        assert_eq!(r.targets(), &targets[..], "a refused block was kept");
                        assert!(!(finite && in_range && unit), "refused {block:?}");
                    }
                }
                assert_eq!(r.frame(), &before[..]);
            }
            _ => {
                let pose = r.step(&mut *rt).expect("a fixed-point step cannot fail");
                assert!(pose
                    .positions
                    .iter()
                    .chain(pose.rotations)
                    .all(|v| v.is_finite()));
                assert!(r.frame().iter().all(|v| v.is_finite()), "non-finite frame");
                steps += 1;
            }
        }
    }
    steps
}

/// The default model's styles, built once.
fn default_styles() -> &'static [Vec<u8>] {
    static S: OnceLock<Vec<Vec<u8>>> = OnceLock::new();
    S.get_or_init(|| host_sim::target::synthetic::default_model_styles().expect("styles build"))
}

/// The `controller` target: the locomotion loop on the embedded default
/// model (plain, and with its two styles switched by the commands), fed
/// arbitrary commands. NaN and infinities must be refused with the state
/// untouched; every accepted frame gives a finite pose.
pub fn exercise_controller(data: &[u8]) -> usize {
    let cmds = commands(data);
    let mut frames = 0;
    let model = Model::from_bytes(host_sim::default_model::BLOB).expect("default model");
    let rt = Runtime::<1024>::new(model).expect("default model fits");
    let mut ctl = PfnnController::new(rt).expect("controller");
    for (action, c) in &cmds {
        if *action == 1 {
            ctl.reset().expect("reset");
            continue;
        }
        let finite = [c.velocity, c.facing]
            .iter()
            .flatten()
            .chain([c.gait.stand, c.gait.walk, c.gait.jog, c.gait.crouch].iter())
            .all(|v| v.is_finite());
        match ctl.step(c) {
            Ok(pose) => {
                assert!(finite, "a non-finite command was accepted: {c:?}");
                assert!(
                    pose.joint_positions
                        .iter()
                        .flatten()
                        .chain(pose.root_position.iter())
                        .chain(pose.facing.iter())
                        .all(|v| v.is_finite()),
                    "non-finite pose for {c:?}"
                );
                frames += 1;
            }
            Err(e) => assert!(!finite, "a finite command was refused: {c:?}: {e}"),
        }
    }
    // The styled loop: the same commands, the mix switched by the actions.
    let styles = default_styles();
    let model = Model::from_bytes(host_sim::default_model::BLOB).expect("default model");
    let mut rt = Runtime::<1024, 256, 2>::new(model).expect("fits");
    for s in styles {
        rt.add_style(Style::from_bytes(s).expect("style"))
            .expect("bound");
    }
    let Ok(mut state) = Locomotion::<f32>::new(&rt) else {
        panic!("locomotion state");
    };
    for (action, c) in &cmds {
        let mix = match action {
            2 => Mix::One(StyleId(0)),
            3 => Mix::One(StyleId(1)),
            4 => Mix::Blend {
                from: StyleId(0),
                to: StyleId(1),
                weight: BlendWeight::from_bits(u16::from(*action) * 4099),
            },
            5 => Mix::Base,
            _ => rt.mix(),
        };
        rt.set_mix(mix).expect("attached styles");
        if state.step(&mut rt, c).is_ok() {
            frames += 1;
        }
    }
    frames
}

// ---------------------------------------------------------------------------
// The host tools' file parsers.

/// A scratch directory for parsers that only read paths: one per thread
/// (the proptest equivalents run in parallel), removed when the thread ends.
fn scratch_dir() -> PathBuf {
    thread_local! {
        static DIR: tempfile::TempDir = {
            let shm = Path::new("/dev/shm");
            let b = tempfile::Builder::new().prefix("phasegate-fuzz-").tempdir_in(shm);
            b.or_else(|_| tempfile::tempdir()).expect("scratch dir")
        };
    }
    DIR.with(|d| d.path().to_path_buf())
}

fn write(name: &str, bytes: &[u8]) -> PathBuf {
    let p = scratch_dir().join(name);
    std::fs::write(&p, bytes).expect("scratch file");
    p
}

/// The `weights` target: one file given to every weight-file parser of the
/// exporter and host-sim (`.npz` in memory and from a path, the PFNN
/// `.npz` layout in every gating mode, `.safetensors` from bytes and from a
/// path, `.npy` matrices and vectors of host-sim).
pub fn exercise_weights(bytes: &[u8]) -> usize {
    use exporter::net::GatingMode;
    let mut ok = 0;
    let name = Path::new("fuzz.npz");
    ok += usize::from(exporter::npz::read_npz_from(Cursor::new(bytes), name).is_ok());
    for mode in [GatingMode::Cubic, GatingMode::Linear, GatingMode::Constant] {
        ok += usize::from(exporter::npz::pfnn_from_npz_bytes(bytes, name, mode).is_ok());
    }
    ok += usize::from(exporter::cp::import::parse_safetensors(bytes).is_ok());
    for ext in ["npz", "safetensors"] {
        let p = write(&format!("w.{ext}"), bytes);
        ok += usize::from(exporter::cp::import::read_arrays(&p).is_ok());
    }
    let p = write("a.npy", bytes);
    ok += usize::from(host_sim::npy::read_matrix_f32_any(&p).is_ok());
    ok += usize::from(host_sim::npy::read_matrix_f32(&p, 3).is_ok());
    ok += usize::from(host_sim::npy::read_matrix_i16(&p).is_ok());
    ok += usize::from(host_sim::npy::read_vector_f32(&p).is_ok());
    ok
}

/// The arrays the `configs` target's graph descriptions are read with (the
/// softmax-graph golden's weights).
pub fn graph_arrays() -> &'static BTreeMap<String, NpArray> {
    static A: OnceLock<BTreeMap<String, NpArray>> = OnceLock::new();
    A.get_or_init(|| {
        let bytes = golden("softmax-graph/model.npz");
        exporter::npz::read_npz_from(Cursor::new(bytes), Path::new("model.npz")).expect("golden")
    })
}

/// The `configs` target: text given to the JSON graph reader (with the
/// golden graph's weights, then exported if it builds) and to host-sim's
/// command-script reader (whose commands are then evaluated over frames).
pub fn exercise_configs(bytes: &[u8]) -> usize {
    let mut ok = 0;
    let Ok(text) = std::str::from_utf8(bytes) else {
        return 0;
    };
    if let Ok(file) = serde_json::from_str::<exporter::net::json::GraphFile>(text) {
        if let Ok(net) = exporter::net::json::net_from_file(&file, graph_arrays()) {
            ok += 1;
            let x = vec![0.5; net.input_dim()];
            let _ = net.forward(&x, 1.0);
        }
    }
    let p = write("g.json", bytes);
    let w = scratch_dir().join("g.npz");
    if !w.exists() {
        std::fs::write(&w, golden("softmax-graph/model.npz")).expect("weights");
    }
    ok += usize::from(exporter::net::json::read_graph(&p, &w).is_ok());
    if let Ok(script) = host_sim::rollout::Script::from_json(text) {
        ok += 1;
        for frame in [0, 1, 59, 60, 600, 60 * 3600, usize::MAX / 2] {
            let _ = script.command(frame);
        }
    }
    // An OMG target script, laid out for the tiny FE-OMG (its own length,
    // capped so that a valid long script does not make the run slow).
    if let Ok(script) = serde_json::from_str::<host_sim::omg_rollout::script::TargetScript>(text) {
        let cfg = omg_config();
        let frames = script.frames.unwrap_or(10).min(64);
        ok += usize::from(script.blocks(cfg, &vec![0.0; 9 * cfg.key], frames).is_ok());
        let _ = script.blocks(cfg, &vec![0.0; 9 * cfg.key], usize::MAX);
    }
    ok
}

/// The tiny FE-OMG's configuration (target scripts name its key joints).
fn omg_config() -> &'static exporter::net::omg::OmgConfig {
    static C: OnceLock<exporter::net::omg::OmgConfig> = OnceLock::new();
    C.get_or_init(|| {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/omg/tiny_fe_r1");
        exporter::net::omg::read_omg(&dir.join("model.safetensors"), &dir.join("config.json"))
            .expect("the committed OMG model")
            .config
    })
}

/// Files of a PFNN directory, in the order the `pfnn_dir` target's input
/// lists them: the statistics, then per table the weights and biases of
/// the three layers.
pub fn pfnn_file_names(tables: usize) -> Vec<String> {
    use exporter::pfnn_dir::{bias_file_name, weight_file_name};
    let mut v: Vec<String> = ["Xmean.bin", "Xstd.bin", "Ymean.bin", "Ystd.bin"]
        .map(String::from)
        .to_vec();
    for t in 0..tables {
        v.extend((0..3).map(|l| weight_file_name(l, t)));
        v.extend((0..3).map(|l| bias_file_name(l, t)));
    }
    v
}

/// Packs files for the `pfnn_dir` target: a count byte, a u16 LE length per
/// file, then the contents.
pub fn pack_files(files: &[Vec<u8>]) -> Vec<u8> {
    let mut out = vec![files.len() as u8];
    for f in files {
        out.extend((f.len().min(usize::from(u16::MAX)) as u16).to_le_bytes());
    }
    for f in files {
        out.extend(&f[..f.len().min(usize::from(u16::MAX))]);
    }
    out
}

/// The `pfnn_dir` target: a directory of the demo's `.bin` files (at most
/// three tables; missing files stay missing) read by the exporter with its
/// dimensions inferred from the files, and with fixed small dimensions.
pub fn exercise_pfnn_dir(bytes: &[u8]) -> usize {
    use exporter::pfnn_dir::{load_pfnn_dir_auto, load_pfnn_dir_dims, PfnnDims};
    let names = pfnn_file_names(3);
    let Some((&count, rest)) = bytes.split_first() else {
        return 0;
    };
    let count = usize::from(count).min(names.len());
    let (lens, mut data) = rest.split_at((2 * count).min(rest.len()));
    let dir = scratch_dir().join("pfnn");
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("dir");
    for (name, len) in names.iter().zip(lens.chunks_exact(2)) {
        let len = usize::from(u16::from_le_bytes([len[0], len[1]])).min(data.len());
        std::fs::write(dir.join(name), &data[..len]).expect("file");
        data = &data[len..];
    }
    let mut ok = 0;
    if let Ok(t) = load_pfnn_dir_auto(&dir, None) {
        ok += 1;
        let (net, _) = exporter::net::Net::from_pfnn_tables(&t, exporter::net::GatingMode::Cubic);
        let _ = net.forward(&vec![0.25; net.input_dim()], 2.0);
    }
    let dims = PfnnDims {
        input: 3,
        hidden: 4,
        output: 2,
        tables: 2,
    };
    ok += usize::from(load_pfnn_dir_dims(&dir, dims, None).is_ok());
    ok
}

// ---------------------------------------------------------------------------
// OMG model directories.

/// The committed tiny FE-OMG's files: `(model.safetensors, config.json)`.
pub fn omg_files() -> &'static (Vec<u8>, String) {
    static F: OnceLock<(Vec<u8>, String)> = OnceLock::new();
    F.get_or_init(|| {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/omg/tiny_fe_r1");
        let w = std::fs::read(dir.join("model.safetensors")).expect("the committed OMG weights");
        let c = std::fs::read_to_string(dir.join("config.json")).expect("the committed OMG config");
        (w, c)
    })
}

/// Packs an OMG model directory for the `omg_model` target: mode byte 1,
/// the config's length (u32 LE), the config, the weights.
pub fn pack_omg(config: &str, weights: &[u8]) -> Vec<u8> {
    let mut out = vec![1u8];
    out.extend((config.len() as u32).to_le_bytes());
    out.extend(config.as_bytes());
    out.extend(weights);
    out
}

/// Weight files the `omg_model` target exports and runs as blobs (bytes;
/// larger ones only run the f64 forward, so that one input stays fast).
const OMG_EXPORT_MAX_BYTES: usize = 1 << 20;

/// The `omg_model` target: an OMG model directory (`config.json` and
/// `model.safetensors`) read by the exporter (`omg_from_bytes`, and
/// `read_omg` from the files, which must agree). Mode byte bit 0 clear:
/// the rest is the config, with the committed tiny FE-OMG's weights; set:
/// [`pack_omg`]'s layout, both files from the input. What builds runs one
/// f64 frame; with bit 1 set, a small one is also exported as an int8 and
/// an int16 blob, which must load and run every extreme input.
pub fn exercise_omg_model(bytes: &[u8]) -> usize {
    let Some((&mode, rest)) = bytes.split_first() else {
        return 0;
    };
    let (config, weights): (&[u8], &[u8]) = if mode % 2 == 0 {
        (rest, &omg_files().0)
    } else {
        let Some((len, rest)) = rest.split_first_chunk::<4>() else {
            return 0;
        };
        rest.split_at((u32::from_le_bytes(*len) as usize).min(rest.len()))
    };
    let mut ok = 0;
    let from_files = exporter::net::omg::read_omg(
        &write("m.safetensors", weights),
        &write("config.json", config),
    );
    let Ok(text) = std::str::from_utf8(config) else {
        assert!(from_files.is_err(), "a config that is not UTF-8 is refused");
        return 0;
    };
    let from_bytes = exporter::net::omg::omg_from_bytes(weights, text);
    assert_eq!(
        from_files.is_ok(),
        from_bytes.is_ok(),
        "the files and the bytes are read alike: {:?} / {:?}",
        from_files.err(),
        from_bytes.as_ref().err()
    );
    let Ok(omg) = from_bytes else {
        return 0;
    };
    ok += 1;
    let export = mode & 2 != 0 && weights.len() <= OMG_EXPORT_MAX_BYTES;
    let x = vec![0.25; omg.config.model_width];
    let y = match omg.dof {
        None => omg.step(&x),
        Some(_) => omg.output(&x),
    };
    assert!(!y.is_empty());
    if export {
        for format in [
            phasegate::blob::WeightFormat::I8,
            phasegate::blob::WeightFormat::I16,
        ] {
            let opts = exporter::quantise::QuantOptions {
                weights: format,
                calibration_samples: 16,
                ..exporter::quantise::QuantOptions::default()
            };
            if let Ok((blob, _)) = exporter::export::export(&omg.net, None, &opts) {
                let model = Model::from_bytes(&blob).expect("an exported blob loads");
                let mut rt =
                    Runtime::<OMG_ARENA>::new(model).expect("an exported blob fits its arena");
                ok += usize::from(run_frames(&mut rt, &[0]) > 0);
            }
        }
    }
    ok
}

/// Arena of the `omg_model` target's runtimes (elements).
const OMG_ARENA: usize = 1 << 16;

// ---------------------------------------------------------------------------
// The self-test section.

/// The models the `self_test` target appends sections to: the format's
/// byte-level example (2 -> 1) and a small phase-gated dense network.
fn self_test_bases() -> &'static [Vec<u8>; 2] {
    static B: OnceLock<[Vec<u8>; 2]> = OnceLock::new();
    B.get_or_init(|| {
        let opts = exporter::quantise::QuantOptions {
            calibration_samples: 64,
            ..exporter::quantise::QuantOptions::default()
        };
        let pfnn = host_sim::target::synthetic::pfnn_base(4, 6, 8, 5);
        let dense = exporter::export::export(&pfnn, None, &opts)
            .expect("export")
            .0;
        [fixture("example-v2.blob"), dense]
    })
}

/// The quantised outputs of `rt` for every extreme quantised input at
/// every edge phase (`None` for a refused frame).
fn quantised_outputs<const A: usize>(rt: &mut Runtime<'_, A>) -> Vec<Option<Vec<i16>>> {
    let n = rt.model().input_dim();
    let mut v = Vec::new();
    for q in extreme_quantised(n) {
        for &ph in &PHASES {
            v.push(
                rt.run_quantised(Phase::from_bits(ph), &q)
                    .ok()
                    .map(<[i16]>::to_vec),
            );
        }
    }
    v
}

/// The `self_test` target: a self-test section made from the input and
/// appended to a model's payload, both CRCs resealed, so that the
/// section's own checks decide. Byte 0: bit 0 picks the base model; bit 1
/// set, the footer's fields (start, count, dimensions, version: 12 bytes)
/// come from the input, as they are; clear, the footer is consistent with
/// the records that follow (count from their length, at most 1,024), and
/// such a blob must load; bit 2 (with a consistent footer) replaces every
/// expected output by what the runtime computes, and the self-test must
/// then pass with its count. Whatever loads must compute what the base
/// computes, before and after its self-test; a failed self-test names a
/// vector and an output inside the section.
pub fn exercise_self_test(bytes: &[u8]) -> usize {
    use phasegate::blob::{Framed, MAX_SELF_TEST_VECTORS, SELF_TEST_MAGIC, SELF_TEST_VERSION};
    let Some((&mode, rest)) = bytes.split_first() else {
        return 0;
    };
    let base = &self_test_bases()[usize::from(mode & 1)];
    let mut base_rt = Runtime::<ARENA>::new(Model::from_bytes(base).expect("base")).expect("base");
    let (ins, outs) = (base_rt.model().input_dim(), base_rt.model().output_dim());
    let record = 4 + 2 * ins + 2 * outs;
    let mut payload = Framed::parse(base, true).expect("base").payload.to_vec();
    payload.resize(payload.len().next_multiple_of(4), 0);
    let start = payload.len();
    let consistent = mode & 2 == 0;
    let (footer, mut records) = if consistent {
        let count = (rest.len() / record).clamp(1, usize::from(MAX_SELF_TEST_VECTORS));
        let mut r = rest.to_vec();
        r.resize(count * record, 0);
        let mut f = (start as u32).to_le_bytes().to_vec();
        for v in [count as u16, ins as u16, outs as u16, SELF_TEST_VERSION] {
            f.extend(v.to_le_bytes());
        }
        (f, r)
    } else {
        let (f, r) = rest.split_at(rest.len().min(12));
        let mut f = f.to_vec();
        f.resize(12, 0);
        (f, r.to_vec())
    };
    let count = records.len() / record;
    if consistent && mode & 4 != 0 {
        for r in records.chunks_exact_mut(record) {
            let phase = u32::from_le_bytes([r[0], r[1], r[2], r[3]]);
            let x: Vec<i16> = r[4..4 + 2 * ins]
                .chunks_exact(2)
                .map(|b| i16::from_le_bytes([b[0], b[1]]))
                .collect();
            let y = base_rt
                .run_quantised(Phase::from_bits(phase), &x)
                .expect("a frame runs")
                .to_vec();
            for (slot, v) in r[4 + 2 * ins..].chunks_exact_mut(2).zip(y) {
                slot.copy_from_slice(&v.to_le_bytes());
            }
        }
    }
    payload.extend(&records);
    payload.resize(payload.len().next_multiple_of(4), 0);
    payload.extend(&footer);
    payload.extend(SELF_TEST_MAGIC);
    let blob = exporter::self_test::reseal(base, &payload).expect("the base loads");
    let model = Model::from_bytes(&blob);
    if consistent {
        assert!(
            model.is_ok(),
            "a consistent section loads: {:?}",
            model.err()
        );
    }
    let Ok(model) = model else {
        return 0;
    };
    let mut rt = Runtime::<ARENA>::new(model).expect("the base's arena fits");
    let expected = quantised_outputs(&mut base_rt);
    assert_eq!(
        quantised_outputs(&mut rt),
        expected,
        "the section changes nothing the model computes"
    );
    // The vectors the loader found (none when the footer's magic is all
    // that is left of a section).
    let stored = rt.model().self_test().map_or(0, |t| usize::from(t.count()));
    if consistent {
        assert_eq!(stored, count, "a consistent section holds its records");
    }
    let r = rt.run_self_test();
    match r {
        Ok(n) => {
            assert_eq!(
                usize::from(n),
                stored,
                "a passing self-test runs every vector"
            );
            assert!(n <= MAX_SELF_TEST_VECTORS);
        }
        Err(phasegate::Error::SelfTestFailed { vector, output, .. }) => {
            assert!(
                mode & 4 == 0 || !consistent,
                "the runtime's own outputs pass: {r:?}"
            );
            assert!(usize::from(vector) < stored, "{r:?}");
            assert!(usize::from(output) < outs, "{r:?}");
        }
        Err(e) => panic!("a loaded self-test either passes or fails a vector: {e:?}"),
    }
    assert_eq!(
        quantised_outputs(&mut rt),
        expected,
        "the self-test leaves the model as it was"
    );
    1
}

// ---------------------------------------------------------------------------
// Seeds.

/// A committed golden file, by its path under `tests/golden/`.
pub fn golden(rel: &str) -> Vec<u8> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("golden")
        .join(rel);
    std::fs::read(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// A committed blob fixture, by its name under `tests/fixtures/`.
pub fn fixture(name: &str) -> Vec<u8> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures")
        .join(name);
    std::fs::read(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// Valid files of every kind, per target: `(target, name, bytes)`. Small
/// ones are generated here (through the real exporter); the large goldens
/// are read from `tests/golden/` (`include_large`).
pub fn seeds(include_large: bool) -> Vec<(&'static str, String, Vec<u8>)> {
    use exporter::quantise::QuantOptions;
    use host_sim::target::synthetic;
    let mut v: Vec<(&'static str, String, Vec<u8>)> = Vec::new();
    let opts = QuantOptions {
        calibration_samples: 64,
        ..QuantOptions::default()
    };
    let export = |net: &exporter::net::Net| exporter::export::export(net, None, &opts).unwrap().0;
    // Models: the format example (dense, one neuron), a small dense PFNN,
    // a small CP + diagonal network, the golden CP/diagonal and softmax
    // graph blobs, a small RBF network; large: the golden dense and OMG
    // blobs.
    v.push((
        "model",
        "example-v2.blob".into(),
        fixture("example-v2.blob"),
    ));
    let pfnn = synthetic::pfnn_base(4, 6, 8, 5);
    let base = export(&pfnn);
    v.push(("model", "dense-small.blob".into(), base.clone()));
    v.push((
        "model",
        "cp-diagonal-small.blob".into(),
        export(&synthetic::cp_net(3, 6, 8, 5, 3)),
    ));
    v.push((
        "model",
        "cp-diagonal.blob".into(),
        golden("cp-diagonal/model.blob"),
    ));
    v.push((
        "model",
        "softmax-graph.blob".into(),
        golden("softmax-graph/model.blob"),
    ));
    v.push((
        "model",
        "rbf-small.blob".into(),
        export(&synthetic::rbf_net(5)),
    ));
    v.push((
        "model",
        "dec-small.blob".into(),
        export(&synthetic::dec_net(5)),
    ));
    if include_large {
        v.push(("model", "default.blob".into(), golden("default/model.blob")));
        v.push((
            "model",
            "dense-int16.blob".into(),
            golden("dense-int16/model.blob"),
        ));
        v.push((
            "model",
            "omg-tiny-fe-r1.blob".into(),
            golden("omg-tiny-fe-r1/model.blob"),
        ));
        v.push((
            "model",
            "dec-graph.blob".into(),
            golden("dec-graph/model.blob"),
        ));
    }
    // Styles: the small base followed by a CP, a diagonal and a full
    // adapter; and each alone after it.
    let styles: Vec<Vec<u8>> = ["cp", "diagonal", "full"]
        .iter()
        .enumerate()
        .map(|(i, form)| {
            let ad = synthetic::adapter(form, 8, 2, 30 + i as u64);
            synthetic::style_blob(&base, &pfnn, &ad, form, None).unwrap()
        })
        .collect();
    v.push((
        "styled",
        "base+3.bin".into(),
        [base.clone(), styles.concat()].concat(),
    ));
    for (s, form) in styles.iter().zip(["cp", "diagonal", "full"]) {
        v.push((
            "styled",
            format!("base+{form}.bin"),
            [base.clone(), s.clone()].concat(),
        ));
        v.push(("model", format!("style-{form}.blob"), s.clone()));
    }
    if include_large {
        let mut chain = golden("default/model.blob");
        for s in default_styles() {
            chain.extend(s);
        }
        v.push(("styled", "default+2.bin".into(), chain));
    }
    // Rigs: a small motion blob followed by a rig blob for it.
    let (motion, rig) = small_rig_pair();
    v.push(("rig", "motion+rig.bin".into(), [motion, rig].concat()));
    // Controller commands: walk, jog, stand, crouch, a reset, hostile values.
    let enc = |vals: &[f32]| -> Vec<u8> {
        let mut out = vec![0u8];
        for x in vals {
            out.push(0xff);
            out.extend(x.to_le_bytes());
        }
        out
    };
    let mut walk = Vec::new();
    for _ in 0..8 {
        walk.extend(enc(&[0.0, 2.5, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0]));
    }
    walk.extend(enc(&[4.5, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0]));
    walk.extend(enc(&[0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]));
    walk.extend(enc(&[1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]));
    v.push(("controller", "walk-jog-stand-crouch.bin".into(), walk));
    v.push(("controller", "hostile.bin".into(), (0u8..=40).collect()));
    // Reaching: hand targets set then steps, a whole block, hostile values.
    let mut reach = vec![0u8];
    for (hand, p) in [(0u8, [0.3f32, 1.1, 0.4]), (1, [-0.3, 1.0, 0.35])] {
        reach.push(hand);
        reach.extend(&enc(&[p[0], p[1], p[2], 0.0, 0.0, 1.0, 0.0, 1.0, 0.0])[1..]);
        reach.extend([5u8, 5, 5, 5]);
    }
    reach.push(3);
    reach.extend(&enc(&[0.2; 36])[1..]);
    reach.extend([5u8; 4]);
    v.push(("reach", "two-hands-then-block.bin".into(), reach));
    v.push(("reach", "hostile.bin".into(), (0u8..=60).collect()));
    // Weight files: float32 and float64 .npz, .safetensors, .npy.
    let dir = tempfile::tempdir().unwrap();
    let arrays = vec![
        ("a", vec![2u64, 3], vec![1.0f32, -2.0, 3.5, 0.0, 1e-3, 7.0]),
        ("b", vec![3u64], vec![0.5f32, 0.25, -1.0]),
    ];
    let npz = dir.path().join("x.npz");
    exporter::npz::write_npz(&npz, &arrays).unwrap();
    v.push(("weights", "small.npz".into(), std::fs::read(&npz).unwrap()));
    let st = dir.path().join("x.safetensors");
    exporter::cp::import::write_safetensors(&st, &arrays).unwrap();
    v.push((
        "weights",
        "small.safetensors".into(),
        std::fs::read(&st).unwrap(),
    ));
    let npy = dir.path().join("x.npy");
    let m = host_sim::npy::Matrix {
        rows: 2,
        cols: 3,
        data: vec![1.0f32, -2.0, 3.5, 0.0, 1e-3, 7.0],
    };
    host_sim::npy::write_matrix(&npy, &m).unwrap();
    v.push(("weights", "matrix.npy".into(), std::fs::read(&npy).unwrap()));
    let q = host_sim::npy::Matrix {
        rows: 1,
        cols: 3,
        data: vec![1i16, -2, 3],
    };
    host_sim::npy::write_matrix(&npy, &q).unwrap();
    v.push((
        "weights",
        "matrix-i16.npy".into(),
        std::fs::read(&npy).unwrap(),
    ));
    host_sim::npy::write_vector(&npy, &[0.5f32, -0.25]).unwrap();
    v.push(("weights", "vector.npy".into(), std::fs::read(&npy).unwrap()));
    let pfnn_npz = dir.path().join("pfnn.npz");
    exporter::npz::pfnn_to_npz(&synthetic::pfnn_base(4, 3, 4, 2), &pfnn_npz).unwrap();
    v.push((
        "weights",
        "pfnn-tiny.npz".into(),
        std::fs::read(&pfnn_npz).unwrap(),
    ));
    // The hostile classes the parsers must refuse: shapes whose element
    // count overflows, safetensors whose tensors overlap or whose shape
    // claims far more than the data holds.
    let npy_with_shape = |shape: &str| -> Vec<u8> {
        let mut h = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}");
        while (10 + h.len() + 1) % 64 != 0 {
            h.push(' ');
        }
        h.push('\n');
        let mut out = b"\x93NUMPY\x01\x00".to_vec();
        out.extend((h.len() as u16).to_le_bytes());
        out.extend(h.as_bytes());
        out.extend([0u8; 16]);
        out
    };
    v.push((
        "weights",
        "hostile-shape-overflow.npy".into(),
        npy_with_shape("(4294967296, 4294967296, 16)"),
    ));
    v.push((
        "weights",
        "hostile-shape-huge.npy".into(),
        npy_with_shape("(1099511627776, 1)"),
    ));
    let safetensors = |header: &str, data: usize| -> Vec<u8> {
        let mut out = (header.len() as u64).to_le_bytes().to_vec();
        out.extend(header.as_bytes());
        out.extend(vec![0u8; data]);
        out
    };
    v.push((
        "weights",
        "hostile-overlap.safetensors".into(),
        safetensors(
            r#"{"a":{"dtype":"F32","shape":[2],"data_offsets":[0,8]},"b":{"dtype":"F32","shape":[2],"data_offsets":[0,8]}}"#,
            8,
        ),
    ));
    v.push((
        "weights",
        "hostile-shape.safetensors".into(),
        safetensors(
            r#"{"a":{"dtype":"F32","shape":[4611686018427387904,4],"data_offsets":[0,8]}}"#,
            8,
        ),
    ));
    if include_large {
        v.push((
            "weights",
            "cp-diagonal.npz".into(),
            golden("cp-diagonal/model.npz"),
        ));
        v.push((
            "weights",
            "phases.npy".into(),
            golden("cp-diagonal/phases.npy"),
        ));
    }
    // Configs: the golden graph description and the golden script.
    v.push((
        "configs",
        "graph.json".into(),
        golden("softmax-graph/model.json"),
    ));
    v.push((
        "configs",
        "script.json".into(),
        golden("controller/script.json"),
    ));
    v.push((
        "configs",
        "target-script.json".into(),
        host_sim::omg_rollout::script::BUILT_IN[0]
            .2
            .as_bytes()
            .to_vec(),
    ));
    // OMG model directories: the committed tiny FE-OMG's config with its
    // weights (run only, and exported), both files packed (large).
    let (omg_w, omg_c) = omg_files();
    for (mode, name) in [(0u8, "config.bin"), (2, "config-export.bin")] {
        let mut b = vec![mode];
        b.extend(omg_c.as_bytes());
        v.push(("omg_model", name.into(), b));
    }
    if include_large {
        v.push(("omg_model", "tiny-fe-r1.bin".into(), pack_omg(omg_c, omg_w)));
    }
    // Self-test sections: three vectors on each base, with a consistent
    // footer (expected outputs as stored, then as computed), and a footer
    // given field by field.
    for base in 0..2u8 {
        let records: Vec<u8> = (0..3 * 20u8).map(|i| i.wrapping_mul(37)).collect();
        for flags in [0u8, 4] {
            let mut b = vec![base | flags];
            b.extend(&records);
            v.push(("self_test", format!("base{base}-flags{flags}.bin"), b));
        }
    }
    let mut b = vec![2u8];
    for f in [
        40u32.to_le_bytes().to_vec(),
        1u16.to_le_bytes().to_vec(),
        2u16.to_le_bytes().to_vec(),
        1u16.to_le_bytes().to_vec(),
        1u16.to_le_bytes().to_vec(),
    ] {
        b.extend(f);
    }
    b.extend([0, 0, 0, 0, 0x80, 0x01, 0x60, 0xff, 0x77, 0x0e, 0, 0]);
    v.push(("self_test", "example-footer.bin".into(), b));
    // A PFNN directory: 3 inputs, 4 hidden, 2 outputs, 2 tables.
    let f = |n: usize, s: f32| -> Vec<u8> {
        (0..n)
            .flat_map(|i| (s + i as f32 * 0.125).to_le_bytes())
            .collect()
    };
    let (i, h, o) = (3, 4, 2);
    let mut files = vec![f(i, 0.0), f(i, 1.0), f(o, 0.0), f(o, 1.0)];
    for t in 0..2 {
        let s = t as f32 * 0.5;
        files.extend([
            f(h * i, s),
            f(h * h, s),
            f(o * h, s),
            f(h, s),
            f(h, s),
            f(o, s),
        ]);
    }
    v.push(("pfnn_dir", "tiny-2-tables.bin".into(), pack_files(&files)));
    v
}
