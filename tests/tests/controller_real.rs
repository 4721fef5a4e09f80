//! Issue 3, point 6: the device controller on the real PFNN
//! (../shared/pfnn/network, or $PHASEGATE_PFNN_DIR), 600 frames of every
//! built-in script, int16 and int8 cubic blobs and an f32 float controller
//! against the f64 float controller. Skipped, with a message, where the
//! weights are absent.

use host_sim::rollout::fidelity::{export_blobs, load_cubic, measure, VARIANTS};
use phasegate_tests::real_pfnn_dir as pfnn_dir;

#[test]
fn long_rollouts_stay_with_the_float_controller() {
    let Some(dir) = pfnn_dir() else { return };
    let net = load_cubic(&dir).unwrap();
    let blobs = export_blobs(&net, &Default::default()).unwrap();
    let f = measure(&net, &blobs, &[], 600, None).unwrap();
    println!("{}", f.table());
    assert_eq!(f.scripts.len(), 6);

    // The bars: int16 joint p99 and phase error at every frame
    // against max(floor, 3 x the f32 controller's worst frame); every
    // sanity metric of both blobs within max(10%, 0.5) of the f64 rollout.
    let v = f.violations();
    assert!(v.is_empty(), "fidelity bars missed:\n{}", v.join("\n"));

    for s in &f.scripts {
        let [f32r, i16r, i8r] = [0, 1, 2].map(|i| &s.variants[i]);
        assert_eq!([f32r.name, i16r.name, i8r.name], VARIANTS, "variant order");
        // Rounding alone stays far below a unit on every script (the
        // controller is not chaotic on flat ground; see docs/controller.md).
        assert!(
            f32r.errors.worst_frame_p99 < 0.05,
            "{}: f32 vs f64 {}",
            s.script,
            f32r.errors.worst_frame_p99
        );
        // int16 stays within a few millimetres and never loses the phase.
        assert!(i16r.errors.worst_frame_p99 < 1.0, "{}", s.script);
        assert!(i16r.errors.phase_error_max < 0.02, "{}", s.script);
        // Nothing walks into the floor.
        assert!(s.reference.penetration_max < 0.5, "{}", s.script);
    }
}

/// Issue 13's closed-loop figures with the int8 blob calibrated on 24
/// random tours (`--calibration-tours 24`, docs/fixed-point.md, "Rounding
/// for the closed loop"; the tours share no script with the scored ones).
///
/// The bars (worst-frame joint p99 <= 3, final root drift <= 5)
/// are printed, not asserted: this blob meets them (measured 2026-12-01:
/// p99 at most 2.28, drift at most 2.47), but of 32 tour seeds 23 did,
/// and the misses are single events (the hands after jog-stop-jog's stop,
/// p99 up to 5.71), so any change of the blob draws the verdict again
/// (docs/fixed-point.md, "Thirty-two tour seeds"). What is asserted is the
/// bound every all-int8 blob calibrated on tours has stayed within (p99
/// 5.71, drift 5.77), which the uncalibrated default misses (crouch-walk
/// p99 10.75, drift 8.29).
#[test]
fn tour_calibrated_int8_rollouts_stay_close() {
    let Some(dir) = pfnn_dir() else { return };
    let net = load_cubic(&dir).unwrap();
    let knobs = host_sim::quant_knobs::Int8Knobs {
        calibration_tours: Some(24),
        tour_seed: 1,
        ..Default::default()
    };
    let blobs = export_blobs(&net, &knobs).unwrap();
    let f = measure(&net, &blobs, &[], 600, None).unwrap();
    println!("{}", f.table());
    let misses = f.int8_misses();
    println!(
        "issue 13's int8 bars: {}",
        if misses.is_empty() {
            "met".into()
        } else {
            misses.join("; ")
        }
    );
    assert_eq!(f.scripts.len(), 6);
    for s in &f.scripts {
        let e = &s.variants[2].errors;
        assert_eq!(s.variants[2].name, VARIANTS[2]);
        assert!(
            e.worst_frame_p99 <= 6.0,
            "{}: p99 {}",
            s.script,
            e.worst_frame_p99
        );
        assert!(
            e.root_drift_final <= 6.0,
            "{}: drift {}",
            s.script,
            e.root_drift_final
        );
    }
    // The issue-3 bars hold for this blob too.
    let v = f.violations();
    assert!(v.is_empty(), "fidelity bars missed:\n{}", v.join("\n"));
}
