//! Where things are in PFNN's input (342) and output (311) vectors.
//! See `shared/pfnn/README.md` for the tables these constants encode.

/// Joints of the PFNN skeleton.
pub const JOINTS: usize = 31;
/// Trajectory samples in the input: every [`SAMPLE_STEP`]-th frame of the window.
pub const SAMPLES: usize = 12;
/// Frames between two trajectory samples.
pub const SAMPLE_STEP: usize = 10;
/// Future samples the network predicts (the current frame's included).
pub const FUTURE_SAMPLES: usize = 6;
/// Width of the input vector.
pub const INPUTS: usize = 342;
/// Width of the output vector.
pub const OUTPUTS: usize = 311;

/// Parent of each joint (`-1` for the root), from the demo's
/// `character_parents.bin`: hips 0; left leg 1-5 (hip joint, upper leg,
/// knee, heel, toe); right leg 6-10; spine 11-13; neck and head 14-16;
/// left arm 17-23; right arm 24-30.
pub const PARENTS: [i8; JOINTS] = [
    -1, 0, 1, 2, 3, 4, 0, 6, 7, 8, 9, 0, 11, 12, 13, 14, 15, 13, 17, 18, 19, 20, 21, 20, 13, 24,
    25, 26, 27, 28, 27,
];

/// The joints whose contact labels the network predicts, in output order:
/// left heel, left toe, right heel, right toe.
pub const CONTACT_JOINTS: [usize; 4] = [4, 5, 9, 10];

/// The output vector, split into named parts (borrowed, no copies).
pub struct Outputs<'y, R> {
    /// Root velocity `(x, z)` in root space, units per frame.
    pub root_velocity: &'y [R; 2],
    /// Root angular velocity about `y`, radians per frame (the demo turns by
    /// its negative).
    pub root_turn: R,
    /// Phase change, cycles per frame.
    pub phase_change: R,
    /// Foot contact labels, [`CONTACT_JOINTS`] order.
    pub contacts: &'y [R; 4],
    /// Future trajectory: positions x, positions z, directions x,
    /// directions z, [`FUTURE_SAMPLES`] each, in the current root space.
    pub trajectory: &'y [R; 4 * FUTURE_SAMPLES],
    /// Joint positions, root space.
    pub positions: &'y [R; 3 * JOINTS],
    /// Joint velocities, root space, units per frame.
    pub velocities: &'y [R; 3 * JOINTS],
    /// Joint rotations, exponential map, root space.
    pub rotations: &'y [R; 3 * JOINTS],
}

impl<'y, R: Copy> Outputs<'y, R> {
    /// Splits an output vector; `None` only if it is not [`OUTPUTS`] long.
    pub fn split(y: &'y [R]) -> Option<Self> {
        let (root_velocity, y) = y.split_first_chunk::<2>()?;
        let (&[root_turn, phase_change], y) = y.split_first_chunk::<2>()?;
        let (contacts, y) = y.split_first_chunk::<4>()?;
        let (trajectory, y) = y.split_first_chunk::<{ 4 * FUTURE_SAMPLES }>()?;
        let (positions, y) = y.split_first_chunk::<{ 3 * JOINTS }>()?;
        let (velocities, y) = y.split_first_chunk::<{ 3 * JOINTS }>()?;
        let (rotations, y) = y.split_first_chunk::<{ 3 * JOINTS }>()?;
        y.is_empty().then_some(Outputs {
            root_velocity,
            root_turn,
            phase_change,
            contacts,
            trajectory,
            positions,
            velocities,
            rotations,
        })
    }
}

/// The input vector, split into named parts to be written.
pub struct Inputs<'x, R> {
    /// Trajectory positions x, positions z, directions x, directions z
    /// ([`SAMPLES`] each), in the current root space.
    pub trajectory: &'x mut [R; 4 * SAMPLES],
    /// Gait weights: stand, walk, jog, crouch, jump, unused ([`SAMPLES`] each).
    pub gaits: &'x mut [R; 6 * SAMPLES],
    /// Previous joint positions, previous root space.
    pub positions: &'x mut [R; 3 * JOINTS],
    /// Previous joint velocities, previous root space.
    pub velocities: &'x mut [R; 3 * JOINTS],
    /// Terrain right, trajectory height, terrain left, relative to the root
    /// height ([`SAMPLES`] each): all zero on flat ground.
    pub heights: &'x mut [R; 3 * SAMPLES],
}

impl<'x, R> Inputs<'x, R> {
    /// Splits an input vector; `None` only if it is not [`INPUTS`] long.
    pub fn split(x: &'x mut [R]) -> Option<Self> {
        let (trajectory, x) = x.split_first_chunk_mut::<{ 4 * SAMPLES }>()?;
        let (gaits, x) = x.split_first_chunk_mut::<{ 6 * SAMPLES }>()?;
        let (positions, x) = x.split_first_chunk_mut::<{ 3 * JOINTS }>()?;
        let (velocities, x) = x.split_first_chunk_mut::<{ 3 * JOINTS }>()?;
        let (heights, x) = x.split_first_chunk_mut::<{ 3 * SAMPLES }>()?;
        x.is_empty().then_some(Inputs {
            trajectory,
            gaits,
            positions,
            velocities,
            heights,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splits_cover_the_vectors_exactly() {
        let y: [u16; OUTPUTS] = core::array::from_fn(|i| i as u16);
        let o = Outputs::split(&y).unwrap();
        assert_eq!(o.root_velocity, &[0, 1]);
        assert_eq!((o.root_turn, o.phase_change), (2, 3));
        assert_eq!(o.contacts, &[4, 5, 6, 7]);
        assert_eq!(o.trajectory[0], 8);
        assert_eq!(o.positions[0], 32);
        assert_eq!(o.velocities[0], 125);
        assert_eq!(o.rotations[0], 218);
        assert!(Outputs::split(&y[1..]).is_none());

        let mut x = [0u16; INPUTS];
        let i = Inputs::split(&mut x).unwrap();
        i.gaits[0] = 1;
        i.positions[0] = 2;
        i.velocities[0] = 3;
        i.heights[0] = 4;
        assert_eq!((x[48], x[120], x[213], x[306]), (1, 2, 3, 4));
        assert!(Inputs::split(&mut [0u16; INPUTS + 1]).is_none());
        // The parent table is a tree rooted at 0 with parents before children.
        for (j, &p) in PARENTS.iter().enumerate().skip(1) {
            assert!(p >= 0 && (p as usize) < j);
        }
    }
}
