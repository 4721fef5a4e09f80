//! The locomotion loop on a styled runtime: what a device with a base blob
//! and style blobs in flash runs every frame. On the embedded default model
//! (PFNN-shaped, random weights) with a CP style beside its middle layer:
//! no style gives the plain controller bit for bit; a style changes the
//! motion; a switch or blend between frames depends only on the loop's state
//! and the new mix. (The default model's weights are random, so its phase
//! says nothing about smoothness: `host-sim style-demo` measures that on the
//! real PFNN.)

use exporter::net::{Adapter, CpLayer, NetLayer};
use exporter::quantise::QuantOptions;
use exporter::style::build_style;
use host_sim::default_model::{self, HIDDEN};
use ndarray::{Array1, Array2};
use phasegate::style::BlendWeight;
use phasegate::{Mix, Model, Runtime, Style, StyleId};
use phasegate_controller::{Command, Gait, Locomotion, PfnnController, Pose};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

type Styled<'a> = Runtime<'a, 512, 256, 4>;

const FRAMES: usize = 240;

/// A rank-6 CP adapter beside layer 1, strong enough to change the motion.
fn adapter(seed: u64) -> Adapter {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut n = |s: f64| s * ((0..12).map(|_| rng.gen_range(0.0..1.0)).sum::<f64>() - 6.0);
    let a = Array2::from_shape_fn((HIDDEN, 6), |_| n(0.4));
    let b = Array2::from_shape_fn((HIDDEN, 6), |_| n(0.4));
    let d = Array2::from_shape_fn((4, 6), |_| 0.5 + n(0.1));
    let bias = (0..4)
        .map(|_| Array1::from_shape_fn(HIDDEN, |_| n(0.1)))
        .collect();
    Adapter {
        layer: 1,
        op: NetLayer::Cp(CpLayer { a, b, d, bias }),
    }
}

fn style_blobs() -> Vec<Vec<u8>> {
    let net = default_model::float_model().unwrap();
    (0..2)
        .map(|i| {
            build_style(
                default_model::BLOB,
                &net,
                &adapter(40 + i),
                &format!("style{i}"),
                &QuantOptions::default(),
                64,
            )
            .unwrap()
            .0
        })
        .collect()
}

fn command(frame: usize) -> Command {
    let gait = [Gait::Walk, Gait::Jog, Gait::Walk, Gait::Crouch][frame * 4 / FRAMES];
    let turn = (frame as f32 * 0.02).sin();
    Command::moving([turn, 2.0], gait)
}

/// Runs the loop, choosing each frame's mix with `mix_at`.
fn run_styled(blobs: &[Vec<u8>], mix_at: impl Fn(usize) -> Mix) -> Vec<Pose<f32>> {
    let mut rt = Box::new(Styled::new(Model::from_bytes(default_model::BLOB).unwrap()).unwrap());
    for b in blobs {
        rt.add_style(Style::from_bytes(b).unwrap()).unwrap();
    }
    let mut state = Locomotion::new(rt.as_ref()).unwrap();
    (0..FRAMES)
        .map(|f| {
            rt.set_mix(mix_at(f)).unwrap();
            state.step(rt.as_mut(), &command(f)).unwrap().clone()
        })
        .collect()
}

fn joint_gap(a: &Pose<f32>, b: &Pose<f32>) -> f32 {
    a.joint_positions
        .iter()
        .zip(&b.joint_positions)
        .map(|(p, q)| {
            p.iter()
                .zip(q)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f32::max)
        })
        .fold(0.0, f32::max)
}

#[test]
fn no_style_is_the_plain_controller_bit_for_bit() {
    let blobs = style_blobs();
    let styled = run_styled(&blobs, |_| Mix::Base);
    let mut plain: Box<PfnnController<Runtime<'_, 512>>> = Box::new(
        PfnnController::from_model(Model::from_bytes(default_model::BLOB).unwrap()).unwrap(),
    );
    for (f, s) in styled.iter().enumerate() {
        let p = plain.step(&command(f)).unwrap();
        assert_eq!(p, s, "frame {f}");
    }
}

#[test]
fn a_style_changes_the_motion_and_a_switch_depends_only_on_the_loop_state() {
    let blobs = style_blobs();
    let (a, b) = (StyleId(0), StyleId(1));
    let blend = |w: f32| Mix::Blend {
        from: a,
        to: b,
        weight: BlendWeight::from_num(w),
    };
    // Switch every 12 frames through base, a, b and blends at 0, 0.5 and 1.
    let schedule = [
        Mix::Base,
        Mix::One(a),
        Mix::One(b),
        blend(0.0),
        blend(0.5),
        blend(1.0),
        Mix::Base,
    ];
    let mix_at = |f: usize| schedule[(f / 12) % schedule.len()];
    let base = run_styled(&blobs, |_| Mix::Base);
    let one = run_styled(&blobs, |_| Mix::One(a));

    // The style really changes the motion (not a no-op adapter).
    let effect = base
        .iter()
        .zip(&one)
        .map(|(p, q)| joint_gap(p, q))
        .fold(0.0, f32::max);
    println!("largest joint difference, style 0 vs base: {effect:.3}");
    assert!(effect > 1.0, "the style barely changes the pose: {effect}");

    // The switching run, and beside it, at every frame, the same loop state
    // stepped by a runtime that has had the frame's mix all along: the poses
    // agree bit for bit, so a switch carries nothing over from the previous
    // mix (the phase is the loop's, untouched by the runtime).
    let model = || Model::from_bytes(default_model::BLOB).unwrap();
    let mut rt = Box::new(Styled::new(model()).unwrap());
    let mut fresh: Vec<Box<Styled<'_>>> = schedule
        .iter()
        .map(|&m| {
            let mut r = Box::new(Styled::new(model()).unwrap());
            for bl in &blobs {
                r.add_style(Style::from_bytes(bl).unwrap()).unwrap();
            }
            r.set_mix(m).unwrap();
            r
        })
        .collect();
    for bl in &blobs {
        rt.add_style(Style::from_bytes(bl).unwrap()).unwrap();
    }
    let mut state = Locomotion::new(rt.as_ref()).unwrap();
    let mut switched = Vec::with_capacity(FRAMES);
    for f in 0..FRAMES {
        let mut alone = state.clone();
        let slot = (f / 12) % schedule.len();
        let want = alone
            .step(fresh[slot].as_mut(), &command(f))
            .unwrap()
            .clone();
        rt.set_mix(mix_at(f)).unwrap();
        let got = state.step(rt.as_mut(), &command(f)).unwrap().clone();
        assert_eq!(got, want, "frame {f} ({:?})", mix_at(f));
        assert_eq!(got.phase, state.pose().phase);
        switched.push(got);
    }
    assert!(switched.iter().all(Pose::is_finite));
    // Up to the first switch the switched run is the base run, bit for bit.
    assert_eq!(&switched[..12], &base[..12]);
}
