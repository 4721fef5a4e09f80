//! The trajectory window: one second of past and one of future root
//! positions, facings and gait weights around the current frame.
//!
//! The demo keeps 120 frames (60 past, the current one at index 60, 59
//! future) but only ever reads frames 0..=110: the network sees every 10th
//! frame (0, 10, ..., 110) and the blending of frame `i` reads frames `i-1`
//! and `i`. Frames 111..119 are written and never read, so this window
//! stops at 110 and saves their RAM. Heights are not stored: the ground is
//! flat at `y = 0`.

use crate::geom::{forward, mix_directions, normalise2, turn2, unyaw2, yaw2, Vec2};
use crate::layout::{Inputs, Outputs, FUTURE_SAMPLES, SAMPLES, SAMPLE_STEP};
use crate::real::Real;

/// Index of the current frame.
pub const CURRENT: usize = 60;
/// Frames kept: the past second, the current frame and 50 future ones.
pub const WINDOW: usize = (SAMPLES - 1) * SAMPLE_STEP + 1;

/// A gait weight closer than this to its target is set to it.
pub const SETTLE: f64 = 1e-6;

/// Gait weights in the order the network takes them.
pub type Gaits<R> = [R; 4];

/// Index of each gait in [`Gaits`].
pub mod gait {
    /// Stand.
    pub const STAND: usize = 0;
    /// Walk.
    pub const WALK: usize = 1;
    /// Jog.
    pub const JOG: usize = 2;
    /// Crouch.
    pub const CROUCH: usize = 3;
}

/// Past, current and predicted future of the root.
#[derive(Clone, Debug)]
pub struct Trajectory<R> {
    /// Ground-plane positions, world.
    pub positions: [Vec2<R>; WINDOW],
    /// Facings, world. Not necessarily unit: the demo feeds them as they are.
    pub directions: [Vec2<R>; WINDOW],
    /// Gait weights.
    pub gaits: [Gaits<R>; WINDOW],
}

impl<R: Real> Trajectory<R> {
    /// Standing at the origin facing `+z`, every gait weight 0 (the demo's
    /// reset).
    pub fn new() -> Self {
        Trajectory {
            positions: [[R::ZERO; 2]; WINDOW],
            directions: [forward(); WINDOW],
            gaits: [[R::ZERO; 4]; WINDOW],
        }
    }

    /// Position of frame `i` (origin if out of the window, which no caller
    /// asks for).
    fn position(&self, i: usize) -> Vec2<R> {
        self.positions.get(i).copied().unwrap_or([R::ZERO; 2])
    }

    /// The root of frame `i`: position and unit facing.
    pub fn root(&self, i: usize) -> (Vec2<R>, Vec2<R>) {
        let dir = self.directions.get(i).copied().unwrap_or(forward());
        (self.position(i), normalise2(dir))
    }

    /// The current gait weights.
    pub fn current_gaits(&self) -> Gaits<R> {
        self.gaits.get(CURRENT).copied().unwrap_or([R::ZERO; 4])
    }

    /// Blends the current gait weights toward `target` by `rate`; a weight
    /// within [`SETTLE`] of its target lands on it.
    ///
    /// Why the snap: the loop scales root motion and phase speed by
    /// `(1 - stand)^0.25`, and a geometric blend leaves `1 - stand = 0.9^n`
    /// forever. The fourth root turns that vanishing tail into a visible
    /// factor (`0.9^150 = 1.4e-7`, but its fourth root is 0.02), and where
    /// the tail ends depends on the precision: f32 rounds `stand` to 1 after
    /// about 157 frames, f64 after about 350. Measured on the real PFNN,
    /// that alone moved an idle character's phase by 0.9 rad between the
    /// f32 and f64 controllers. Snapping at 1e-6, far above f32's
    /// resolution near 1, ends the tail at the same frame (131) in every
    /// precision; the demo's own f32 loop ends it at 157.
    pub fn blend_current_gaits(&mut self, target: Gaits<R>, rate: R) {
        if let Some(g) = self.gaits.get_mut(CURRENT) {
            for (w, t) in g.iter_mut().zip(target) {
                let blended = w.mix(t, rate);
                *w = if (blended - t).abs() < R::lit(SETTLE) {
                    t
                } else {
                    blended
                };
            }
        }
    }

    /// Bends the future toward the command: each future step is blended
    /// between the predicted step and `velocity`, each future facing turned
    /// toward `facing`, both more strongly further ahead (the blend is
    /// `1 - (1 - t)^bias`, `t` the fraction of the future second), and the
    /// future gaits set to the current ones.
    pub fn bend_future(&mut self, velocity: Vec2<R>, facing: Vec2<R>, strafe: R) {
        let bias_pos = R::lit(0.5).mix(R::ONE, strafe);
        let bias_dir = R::lit(2.0).mix(R::lit(0.5), strafe);
        let gaits = self.current_gaits();
        let mut prev_old = self.position(CURRENT);
        let mut prev_new = prev_old;
        let future = self
            .positions
            .iter_mut()
            .zip(self.directions.iter_mut())
            .zip(self.gaits.iter_mut())
            .enumerate()
            .skip(CURRENT + 1);
        for (i, ((p, d), g)) in future {
            let t = R::from_u32((i - CURRENT) as u32) / R::from_u32(CURRENT as u32);
            let scale_pos = R::ONE - (R::ONE - t).powf(bias_pos);
            let scale_dir = R::ONE - (R::ONE - t).powf(bias_dir);
            let old = *p;
            *p = [
                prev_new[0] + (old[0] - prev_old[0]).mix(velocity[0], scale_pos),
                prev_new[1] + (old[1] - prev_old[1]).mix(velocity[1], scale_pos),
            ];
            prev_old = old;
            prev_new = *p;
            *d = mix_directions(*d, facing, scale_dir);
            *g = gaits;
        }
    }

    /// Writes the trajectory samples (positions and facings relative to the
    /// root `(root, facing)`) and gait samples into the input vector.
    pub fn write_inputs(&self, root: Vec2<R>, facing: Vec2<R>, x: &mut Inputs<'_, R>) {
        let (px, rest) = x.trajectory.split_at_mut(SAMPLES);
        let (pz, rest) = rest.split_at_mut(SAMPLES);
        let (dx, dz) = rest.split_at_mut(SAMPLES);
        let samples = self
            .positions
            .iter()
            .zip(&self.directions)
            .step_by(SAMPLE_STEP);
        for ((((p, d), px), pz), (dx, dz)) in samples
            .zip(px.iter_mut())
            .zip(pz.iter_mut())
            .zip(dx.iter_mut().zip(dz.iter_mut()))
        {
            let rel = unyaw2(facing, [p[0] - root[0], p[1] - root[1]]);
            let dir = unyaw2(facing, *d);
            (*px, *pz, *dx, *dz) = (rel[0], rel[1], dir[0], dir[1]);
        }
        // Stand, walk, jog, crouch from the window; jump and the unused
        // column stay zero (no jump areas on flat ground).
        x.gaits.fill(R::ZERO);
        for (k, gaits) in self.gaits.iter().step_by(SAMPLE_STEP).enumerate() {
            for (column, &w) in x.gaits.chunks_exact_mut(SAMPLES).zip(gaits) {
                if let Some(slot) = column.get_mut(k) {
                    *slot = w;
                }
            }
        }
    }

    /// After inference: shifts the past by one frame, moves and turns the
    /// current root by the predicted root motion scaled by `moving` (the
    /// demo's `(1 - stand)^0.25`), and replaces the future by the predicted
    /// samples, linearly interpolated between them.
    pub fn advance(&mut self, y: &Outputs<'_, R>, moving: R) {
        self.positions.copy_within(1..=CURRENT, 0);
        self.directions.copy_within(1..=CURRENT, 0);
        self.gaits.copy_within(1..=CURRENT, 0);

        let (pos, facing) = self.root(CURRENT);
        let step = yaw2(facing, *y.root_velocity);
        let pos = [pos[0] + moving * step[0], pos[1] + moving * step[1]];
        let dir = self.directions.get(CURRENT).copied().unwrap_or(forward());
        let dir = turn2(dir, -(moving * y.root_turn));
        if let Some(p) = self.positions.get_mut(CURRENT) {
            *p = pos;
        }
        if let Some(d) = self.directions.get_mut(CURRENT) {
            *d = dir;
        }
        let facing = normalise2(dir);

        let (px, rest) = y.trajectory.split_at(FUTURE_SAMPLES);
        let (pz, rest) = rest.split_at(FUTURE_SAMPLES);
        let (dx, dz) = rest.split_at(FUTURE_SAMPLES);
        let at = |s: &[R], k: usize| s.get(k).copied().unwrap_or(R::ZERO);
        let future = self
            .positions
            .iter_mut()
            .zip(self.directions.iter_mut())
            .enumerate()
            .skip(CURRENT + 1);
        for (i, (p, d)) in future {
            // Frame CURRENT + 10 k holds predicted sample k.
            let k = (i - CURRENT) / SAMPLE_STEP;
            let m =
                R::from_u32(((i - CURRENT) % SAMPLE_STEP) as u32) / R::from_u32(SAMPLE_STEP as u32);
            let lerp = |s: &[R]| at(s, k).mix(at(s, k + 1), m);
            let local = yaw2(facing, [lerp(px), lerp(pz)]);
            *p = [local[0] + pos[0], local[1] + pos[1]];
            *d = normalise2(yaw2(facing, [lerp(dx), lerp(dz)]));
        }
    }
}

impl<R: Real> Default for Trajectory<R> {
    fn default() -> Self {
        Self::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::{INPUTS, OUTPUTS};

    #[test]
    fn window_covers_every_sample_the_network_reads() {
        assert_eq!(WINDOW, 111);
        assert_eq!((WINDOW - 1) / SAMPLE_STEP + 1, SAMPLES);
    }

    #[test]
    fn bending_a_still_future_walks_it_toward_the_command() {
        let mut t = Trajectory::<f64>::new();
        t.bend_future([0.0, 2.0], [0.0, 1.0], 0.0);
        // Each step blends toward 2 units per frame, more strongly ahead.
        let last = t.positions[WINDOW - 1];
        assert!(last[0] == 0.0 && last[1] > 0.0 && last[1] < 100.0);
        let steps: Vec<f64> = t.positions[CURRENT..]
            .windows(2)
            .map(|w| w[1][1] - w[0][1])
            .collect();
        assert!(steps.windows(2).all(|s| s[1] >= s[0]));
        // The past is untouched.
        assert!(t.positions[..=CURRENT].iter().all(|p| *p == [0.0, 0.0]));
    }

    #[test]
    fn inputs_are_root_relative() {
        let mut t = Trajectory::<f64>::new();
        for (i, p) in t.positions.iter_mut().enumerate() {
            *p = [10.0, i as f64];
        }
        t.gaits[CURRENT] = [0.25, 0.5, 0.0, 1.0];
        let mut x = [0.0; INPUTS];
        let mut inputs = Inputs::split(&mut x).unwrap();
        let (root, facing) = ([10.0, 60.0], [1.0, 0.0]);
        t.write_inputs(root, facing, &mut inputs);
        // Facing +x: the path along +z lies to the character's right (-x
        // in root space) and the current sample is at the root.
        assert_eq!(x[6], 0.0);
        assert_eq!(x[12 + 6], 0.0);
        assert_eq!(x[7], -10.0);
        assert_eq!(x[48 + 6], 0.25);
        assert_eq!(x[84 + 6], 1.0);
    }

    #[test]
    fn advance_moves_the_root_and_lays_the_predicted_future() {
        let mut t = Trajectory::<f64>::new();
        let mut y = [0.0; OUTPUTS];
        y[1] = 3.0; // forward 3 units
        for k in 0..FUTURE_SAMPLES {
            y[14 + k] = 10.0 * k as f64; // future z
            y[26 + k] = 1.0; // future direction z
        }
        let out = Outputs::split(&y).unwrap();
        t.advance(&out, 1.0);
        assert_eq!(t.positions[CURRENT], [0.0, 3.0]);
        assert_eq!(t.positions[CURRENT + 5], [0.0, 8.0]);
        assert_eq!(t.positions[WINDOW - 1], [0.0, 53.0]);
        // Half the motion when the character is half standing.
        let mut t = Trajectory::<f64>::new();
        t.advance(&out, 0.5);
        assert_eq!(t.positions[CURRENT], [0.0, 1.5]);
    }
}
