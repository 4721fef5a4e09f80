//! OMG reaching control: targets for the key joints in, a pose out every
//! frame (`../shared/docs/omg-spec.md` §1.4-1.5, `docs/omg.md`).
//!
//! The state is one OMG frame `X` (phase, pose, costs, targets, in the
//! model's raw units). Each [`Reach::step`] runs the network on `X`, places
//! its output blocks (phase after the network's own 0.9/0.1 phase update,
//! pose, costs) into the next frame, writes the current targets into its
//! target block and, in [`CostMode::Grounded`], recomputes the costs from
//! the decoded pose and those targets, so that they always agree with the
//! targets however these move. [`CostMode::Faithful`] feeds the predicted
//! costs back, as the thesis's loop does.
//!
//! Generic over the scalar like the locomotion loop: the device runs it in
//! `f32` over the fixed-point runtime, the host's reference in `f64` over
//! the float network (`host_sim::omg`), the same code.

use core::ops::Range;

use crate::error::{Error, Result};
use crate::locomotion::Network;
use crate::real::Real;

/// Most key joints a layout may name (the thesis uses 4: hands and feet).
pub const MAX_KEY: usize = 8;

/// Largest target coordinate accepted, metres from the character's root:
/// anything further is a caller's bug, not a reach.
pub const MAX_TARGET_M: f64 = 100.0;

/// Where the blocks of an OMG frame are (`X` and `Y` share one layout), and
/// where the network's output blocks go. Built once from the model's
/// `config.json` (the host does it; on the device it is a constant the
/// exporter's config gives) and checked by [`ReachLayout::check`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ReachLayout {
    /// Width n of a frame.
    pub width: usize,
    /// Joint positions, 3 per joint.
    pub pos: Range<usize>,
    /// Joint rotations, forward then up (6 per joint).
    pub rot: Range<usize>,
    /// Costs: position (3 per key joint) then rotation (3 per key joint).
    pub cost: Range<usize>,
    /// Targets: positions (3 per key joint) then rotations, forward then
    /// up (6 per key joint).
    pub target: Range<usize>,
    /// Indices of the key joints among the joints, hands first.
    pub key_joints: heapless::Vec<u16, MAX_KEY>,
    /// `(network output range, frame range)` of the phase, pose and cost
    /// blocks the network computes.
    pub blocks: [(Range<usize>, Range<usize>); 3],
}

/// What is fed back besides the network's output.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum CostMode {
    /// Costs recomputed from the decoded pose and the current targets
    /// (recommended when targets move, spec §1.5).
    Grounded,
    /// The network's predicted costs fed back (the thesis's loop).
    Faithful,
}

/// One key joint's target, in the character's root space.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Target<R> {
    /// Position, metres.
    pub position: [R; 3],
    /// Forward axis of the target's orientation (normalised on input).
    pub forward: [R; 3],
    /// Up axis of the target's orientation (normalised on input).
    pub up: [R; 3],
}

/// The pose of the current frame: views into the state.
#[derive(Clone, Copy, Debug)]
pub struct ReachPose<'a, R> {
    /// Joint positions, 3 per joint, root space, metres.
    pub positions: &'a [R],
    /// Joint rotations as forward then up vectors, 6 per joint.
    pub rotations: &'a [R],
}

fn bad_layout(reason: u8) -> Error {
    Error::BadLayout { reason }
}

impl ReachLayout {
    /// Key joints.
    pub fn key(&self) -> usize {
        self.key_joints.len()
    }

    /// Checks the layout against itself and a network of `inputs` ->
    /// `outputs` values: every block inside its vector with the widths the
    /// key joints imply ([`Error::BadLayout`] names which check failed).
    pub fn check(&self, inputs: usize, outputs: usize) -> Result<()> {
        let k = self.key();
        let within = |r: &Range<usize>, n: usize| r.start <= r.end && r.end <= n;
        let joints = self.pos.len() / 3;
        let checks = [
            inputs == self.width,
            k > 0,
            within(&self.pos, self.width) && self.pos.len().is_multiple_of(3),
            within(&self.rot, self.width) && self.rot.len() == 6 * joints,
            within(&self.cost, self.width) && self.cost.len() == 6 * k,
            within(&self.target, self.width) && self.target.len() == 9 * k,
            self.key_joints.iter().all(|&j| usize::from(j) < joints),
            self.blocks
                .iter()
                .all(|(o, f)| within(o, outputs) && within(f, self.width) && o.len() == f.len()),
        ];
        match checks.iter().position(|ok| !ok) {
            None => Ok(()),
            Some(i) => Err(bad_layout(i as u8)),
        }
    }
}

/// The reaching loop's state for frames of up to `W` values.
pub struct Reach<R, const W: usize> {
    layout: ReachLayout,
    mode: CostMode,
    x: [R; W],
    out: [R; W],
    targets: [R; W],
}

/// `v` normalised; `None` when it has no direction (all zero, or not
/// finite). Scaled by its largest component first, so that neither huge
/// components (whose squares overflow) nor tiny ones (whose squares
/// vanish) lose the direction.
fn unit<R: Real>(v: [R; 3]) -> Option<[R; 3]> {
    let m = v
        .iter()
        .fold(R::ZERO, |m, x| if x.abs() > m { x.abs() } else { m });
    if !(m.is_finite() && m > R::ZERO) || v.iter().any(|x| !x.is_finite()) {
        return None;
    }
    let w = [v[0] / m, v[1] / m, v[2] / m];
    let n = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
    Some([w[0] / n, w[1] / n, w[2] / n])
}

/// `v / max(|v|, 1e-8)`, as the model's cost definition divides.
fn normalised<R: Real>(v: [R; 3]) -> [R; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    let n = if n > R::lit(1e-8) { n } else { R::lit(1e-8) };
    [v[0] / n, v[1] / n, v[2] / n]
}

fn cross<R: Real>(a: [R; 3], b: [R; 3]) -> [R; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// (side, up, forward) unit axes of a forward/up rotation, side =
/// normalise(up x forward).
fn axes<R: Real>(r: &[R]) -> [[R; 3]; 3] {
    let at = |i: usize| r.get(i).copied().unwrap_or(R::ZERO);
    let f = normalised([at(0), at(1), at(2)]);
    let u = normalised([at(3), at(4), at(5)]);
    [normalised(cross(u, f)), u, f]
}

/// The cost block (6K values) of frame `y` against its own target block
/// (spec eq 3.4-3.5 in the code's form): target position minus key-joint
/// position, then per key joint the angles / pi between the target's and
/// the joint's side, up and forward axes.
pub fn grounded_costs<R: Real>(layout: &ReachLayout, y: &[R], costs: &mut [R]) {
    let k = layout.key();
    let get = |i: usize| y.get(i).copied().unwrap_or(R::ZERO);
    let (pos, rot, tgt) = (layout.pos.start, layout.rot.start, layout.target.start);
    let trot = tgt + 3 * k;
    let pi = R::lit(core::f64::consts::PI);
    for (i, &j) in layout.key_joints.iter().enumerate() {
        let j = usize::from(j);
        for d in 0..3 {
            if let Some(c) = costs.get_mut(3 * i + d) {
                *c = get(tgt + 3 * i + d) - get(pos + 3 * j + d);
            }
        }
        let (ts, js) = (trot + 6 * i, rot + 6 * j);
        let (at, aj) = match (y.get(ts..ts + 6), y.get(js..js + 6)) {
            (Some(t), Some(a)) => (axes(t), axes(a)),
            _ => continue,
        };
        for (a, (ta, ja)) in at.iter().zip(&aj).enumerate() {
            let dot = ta[0] * ja[0] + ta[1] * ja[1] + ta[2] * ja[2];
            if let Some(c) = costs.get_mut(3 * k + 3 * i + a) {
                *c = dot.clamp_to(-R::ONE, R::ONE).acos() / pi;
            }
        }
    }
}

impl<R: Real, const W: usize> Reach<R, W> {
    /// Bytes of the loop's state (without the network).
    pub const STATE_RAM_BYTES: usize = core::mem::size_of::<Self>();

    /// Starts from `first` (a whole frame: typically the rest pose with its
    /// targets, frame 0 of a clip), after checking `layout` against `net`
    /// ([`Error::BadLayout`]) and that frames fit `W` values
    /// ([`Error::TooWide`]). The targets start as `first`'s.
    pub fn new<N: Network<R>>(
        net: &N,
        layout: ReachLayout,
        mode: CostMode,
        first: &[R],
    ) -> Result<Self> {
        layout.check(net.input_dim(), net.output_dim())?;
        if layout.width > W || net.output_dim() > W {
            return Err(Error::TooWide {
                width: layout.width.max(net.output_dim()) as u32,
                capacity: W as u32,
            });
        }
        if first.len() != layout.width {
            return Err(Error::Runtime(phasegate::Error::LengthMismatch {
                expected: layout.width as u32,
                found: first.len() as u32,
            }));
        }
        if let Some(i) = first.iter().position(|v| !v.is_finite()) {
            return Err(Error::NonFinite { index: i as u32 });
        }
        let mut x = [R::ZERO; W];
        x.get_mut(..first.len())
            .ok_or(Error::BadLayout { reason: 0 })?
            .copy_from_slice(first);
        Ok(Reach {
            layout,
            mode,
            x,
            out: [R::ZERO; W],
            targets: x,
        })
    }

    /// The layout.
    pub fn layout(&self) -> &ReachLayout {
        &self.layout
    }

    /// The current frame `X` (the network's next input).
    pub fn frame(&self) -> &[R] {
        self.x.get(..self.layout.width).unwrap_or(&[])
    }

    /// The targets the next [`Reach::step`] writes (the frame's target
    /// block layout: 3K positions, then 6K forward/up axes).
    pub fn targets(&self) -> &[R] {
        self.targets.get(self.layout.target.clone()).unwrap_or(&[])
    }

    /// The current pose.
    pub fn pose(&self) -> ReachPose<'_, R> {
        ReachPose {
            positions: self.x.get(self.layout.pos.clone()).unwrap_or(&[]),
            rotations: self.x.get(self.layout.rot.clone()).unwrap_or(&[]),
        }
    }

    /// Sets key joint `key`'s target (0 and 1 are the hands), used from the
    /// next [`Reach::step`] on; any frame. Refused with no state change:
    /// an unknown key joint ([`Error::BadTarget`] field 255), a NaN or
    /// infinite value or a coordinate beyond [`MAX_TARGET_M`] (field 0-2
    /// position, 3-5 forward, 6-8 up), an axis of no length. The axes are
    /// normalised.
    pub fn set_target(&mut self, key: usize, t: &Target<R>) -> Result<()> {
        let k = self.layout.key();
        if key >= k {
            return Err(Error::BadTarget { field: 255 });
        }
        let values = t.position.iter().chain(&t.forward).chain(&t.up);
        let far = R::lit(MAX_TARGET_M);
        if let Some(i) = values
            .enumerate()
            .position(|(i, v)| !v.is_finite() || (i < 3 && v.abs() > far))
        {
            return Err(Error::BadTarget { field: i as u8 });
        }
        let f = unit(t.forward).ok_or(Error::BadTarget { field: 3 })?;
        let u = unit(t.up).ok_or(Error::BadTarget { field: 6 })?;
        let base = self.layout.target.start;
        let (p, r) = (base + 3 * key, base + 3 * k + 6 * key);
        let dst = self
            .targets
            .get_mut(p..p + 3)
            .ok_or(Error::BadTarget { field: 255 })?;
        dst.copy_from_slice(&t.position);
        let dst = self
            .targets
            .get_mut(r..r + 6)
            .ok_or(Error::BadTarget { field: 255 })?;
        let (df, du) = dst.split_at_mut(3);
        df.copy_from_slice(&f);
        du.copy_from_slice(&u);
        Ok(())
    }

    /// Sets the whole target block (9K values, the data's layout) at once,
    /// e.g. from a recorded clip; refused with no state change when a
    /// value is not finite ([`Error::BadTarget`] with the value's index).
    pub fn set_target_block(&mut self, block: &[R]) -> Result<()> {
        let range = self.layout.target.clone();
        if block.len() != range.len() {
            return Err(Error::Runtime(phasegate::Error::LengthMismatch {
                expected: range.len() as u32,
                found: block.len() as u32,
            }));
        }
        if let Some(i) = block.iter().position(|v| !v.is_finite()) {
            return Err(Error::BadTarget {
                field: u8::try_from(i).unwrap_or(u8::MAX),
            });
        }
        self.targets
            .get_mut(range)
            .ok_or(Error::BadTarget { field: 255 })?
            .copy_from_slice(block);
        Ok(())
    }

    /// One frame: the network on the current frame, the next frame built
    /// from its output and the current targets, costs as the mode says.
    /// On an error (the network's, or a non-finite output) the state is
    /// unchanged.
    pub fn step<N: Network<R>>(&mut self, net: &mut N) -> Result<ReachPose<'_, R>> {
        let (n, o) = (self.layout.width, net.output_dim());
        let (x, out) = match (self.x.get(..n), self.out.get_mut(..o)) {
            (Some(x), Some(out)) => (x, out),
            _ => return Err(Error::BadLayout { reason: 0 }),
        };
        net.predict(R::ZERO, x, out)?;
        if let Some(i) = out.iter().position(|v| !v.is_finite()) {
            return Err(Error::NonFinite { index: i as u32 });
        }
        // The network has read `x`: the next frame is built in place (the
        // blocks it does not compute carry over).
        for (from, to) in &self.layout.blocks {
            if let (Some(src), Some(dst)) = (self.out.get(from.clone()), self.x.get_mut(to.clone()))
            {
                dst.copy_from_slice(src);
            }
        }
        let t = self.layout.target.clone();
        if let (Some(src), Some(dst)) = (self.targets.get(t.clone()), self.x.get_mut(t)) {
            dst.copy_from_slice(src);
        }
        if self.mode == CostMode::Grounded {
            let mut costs = [R::ZERO; 6 * MAX_KEY];
            let k6 = 6 * self.layout.key();
            let c = costs.get_mut(..k6).unwrap_or(&mut []);
            grounded_costs(&self.layout, &self.x, c);
            if let Some(dst) = self.x.get_mut(self.layout.cost.clone()) {
                dst.copy_from_slice(costs.get(..k6).unwrap_or(&[]));
            }
        }
        Ok(self.pose())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// J = 2 joints, K = 1 key joint (joint 1): frame = phase 2, pos 6,
    /// rot 12, cost 6, target 9 = 35 values.
    fn layout() -> ReachLayout {
        ReachLayout {
            width: 35,
            pos: 2..8,
            rot: 8..20,
            cost: 20..26,
            target: 26..35,
            key_joints: heapless::Vec::from_slice(&[1]).unwrap(),
            blocks: [(0..2, 0..2), (2..20, 2..20), (20..26, 20..26)],
        }
    }

    /// Outputs its input's first 26 values plus `shift` on the pose.
    struct Shift {
        shift: f64,
        calls: usize,
        fail: bool,
    }

    impl Network<f64> for Shift {
        fn input_dim(&self) -> usize {
            35
        }
        fn output_dim(&self) -> usize {
            26
        }
        fn predict(&mut self, _: f64, x: &[f64], y: &mut [f64]) -> Result<()> {
            self.calls += 1;
            if self.fail {
                return Err(Error::NonFinite { index: 3 });
            }
            y.copy_from_slice(&x[..26]);
            for v in &mut y[2..8] {
                *v += self.shift;
            }
            Ok(())
        }
        fn mean_output(&self, y: &mut [f64]) -> Result<()> {
            y.fill(0.0);
            Ok(())
        }
    }

    fn first() -> [f64; 35] {
        let mut f = [0.0; 35];
        // Both joints' rotations: forward z, up y.
        for j in 0..2 {
            f[8 + 6 * j + 2] = 1.0;
            f[8 + 6 * j + 4] = 1.0;
        }
        f[29 + 2] = 1.0;
        f[29 + 4] = 1.0;
        f
    }

    #[test]
    fn grounded_costs_vanish_at_the_target_and_measure_angles() {
        let l = layout();
        let mut y = first();
        y[5..8].copy_from_slice(&[0.3, 1.0, 0.2]);
        y[26..29].copy_from_slice(&[0.3, 1.0, 0.2]);
        let mut c = [9.0; 6];
        grounded_costs(&l, &y, &mut c);
        assert_eq!(c, [0.0; 6]);
        // Target forward along x instead of z: the side and forward axes
        // are 90 degrees apart (0.5 in units of pi), up agrees.
        y[29..32].copy_from_slice(&[1.0, 0.0, 0.0]);
        grounded_costs(&l, &y, &mut c);
        assert!((c[3] - 0.5).abs() < 1e-12 && c[4].abs() < 1e-12 && (c[5] - 0.5).abs() < 1e-12);
    }

    fn shift_and_reach(mode: CostMode) -> (Shift, Reach<f64, 40>) {
        let net = Shift {
            shift: 0.1,
            calls: 0,
            fail: false,
        };
        let r = Reach::new(&net, layout(), mode, &first()).unwrap();
        (net, r)
    }

    #[test]
    fn a_step_places_the_blocks_and_grounds_the_costs_on_the_new_target() {
        let (mut net, mut r) = shift_and_reach(CostMode::Grounded);
        let t = Target {
            position: [1.0, 2.0, 3.0],
            forward: [0.0, 0.0, 2.0],
            up: [0.0, 3.0, 0.0],
        };
        r.set_target(0, &t).unwrap();
        let p = r.step(&mut net).unwrap();
        assert_eq!(p.positions[3..6], [0.1, 0.1, 0.1]);
        let f = r.frame();
        assert_eq!(f[26..29], [1.0, 2.0, 3.0]);
        assert_eq!(f[29..35], [0.0, 0.0, 1.0, 0.0, 1.0, 0.0], "axes normalised");
        assert_eq!(f[20..23], [0.9, 1.9, 2.9], "target minus key joint");
        assert_eq!(f[23..26], [0.0, 0.0, 0.0]);
        // Faithful: the network's costs (its input's, here) stay.
        let mut r: Reach<f64, 40> =
            Reach::new(&net, layout(), CostMode::Faithful, &first()).unwrap();
        r.set_target(0, &t).unwrap();
        r.step(&mut net).unwrap();
        assert_eq!(r.frame()[20..26], [0.0; 6]);
    }

    #[test]
    fn bad_targets_and_failed_frames_change_nothing() {
        let (mut net, mut r) = shift_and_reach(CostMode::Grounded);
        let ok = Target {
            position: [0.1, 0.2, 0.3],
            forward: [0.0, 0.0, 1.0],
            up: [0.0, 1.0, 0.0],
        };
        let before = r.frame().to_vec();
        for (t, field) in [
            (
                Target {
                    position: [f64::NAN, 0.0, 0.0],
                    ..ok
                },
                0,
            ),
            (
                Target {
                    position: [0.0, 0.0, 1e9],
                    ..ok
                },
                2,
            ),
            (
                Target {
                    forward: [0.0, f64::INFINITY, 0.0],
                    ..ok
                },
                4,
            ),
            (
                Target {
                    forward: [0.0; 3],
                    ..ok
                },
                3,
            ),
            (
                Target {
                    up: [0.0, 0.0, -0.0],
                    ..ok
                },
                6,
            ),
        ] {
            assert_eq!(r.set_target(0, &t), Err(Error::BadTarget { field }));
        }
        assert_eq!(r.set_target(1, &ok), Err(Error::BadTarget { field: 255 }));
        assert_eq!(
            r.set_target_block(&[f64::NAN; 9]),
            Err(Error::BadTarget { field: 0 })
        );
        net.fail = true;
        assert!(r.step(&mut net).is_err());
        assert_eq!(r.frame(), &before[..]);
        // And the refused targets were never used.
        net.fail = false;
        r.step(&mut net).unwrap();
        assert_eq!(r.frame()[26..35], first()[26..35]);
    }

    #[test]
    fn axes_of_any_finite_size_keep_their_direction() {
        for v in [
            [0.0, 4.6e27f32, 0.0],
            [0.0, 1e-45, 0.0],
            [0.0, f32::MAX, f32::MAX],
        ] {
            let u = unit(v).unwrap();
            assert!(
                u[0] == 0.0 && (u[1] - if v[2] == 0.0 { 1.0 } else { 0.70710677 }).abs() < 1e-6,
                "{u:?}"
            );
        }
        assert_eq!(unit([0.0f32, -0.0, 0.0]), None);
        assert_eq!(unit([f32::NAN, 1.0, 0.0]), None);
    }

    #[test]
    fn layouts_that_do_not_fit_the_network_or_the_buffers_are_refused() {
        let net = Shift {
            shift: 0.0,
            calls: 0,
            fail: false,
        };
        let mut l = layout();
        l.cost = 20..25;
        assert_eq!(
            Reach::<f64, 40>::new(&net, l, CostMode::Grounded, &first()).err(),
            Some(Error::BadLayout { reason: 4 })
        );
        let mut l = layout();
        l.blocks[1] = (2..30, 2..30);
        assert_eq!(
            Reach::<f64, 40>::new(&net, l, CostMode::Grounded, &first()).err(),
            Some(Error::BadLayout { reason: 7 })
        );
        assert_eq!(
            Reach::<f64, 30>::new(&net, layout(), CostMode::Grounded, &first()).err(),
            Some(Error::TooWide {
                width: 35,
                capacity: 30
            })
        );
        assert!(matches!(
            Reach::<f64, 40>::new(&net, layout(), CostMode::Grounded, &first()[..34]),
            Err(Error::Runtime(_))
        ));
    }
}
