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
