//! OMG reaching control: targets for the key joints in, a pose out every
//! frame (`../shared/docs/omg-spec.md` §1.4-1.5, `docs/omg.md`,
//! `docs/omg-joint-velocity.md`).
//!
//! The state is one OMG frame `X` (phase, pose, costs, targets, in the
//! model's raw units). Each [`Reach::step`] runs the network on `X`, places
//! its output blocks (phase after the network's own 0.9/0.1 phase update,
//! costs) into the next frame, builds the pose block as the layout's
//! [`PoseForm`] says, writes the current targets into its target block
//! and, in [`CostMode::Grounded`], recomputes the costs from the new pose
//! and those targets, so that they always agree with the targets however
//! these move. [`CostMode::Faithful`] feeds the predicted costs back, as
//! the thesis's loop does.
//!
//! Two pose forms: [`PoseForm::Absolute`] (the network decodes the pose
//! block, which is copied; [`Reach::new`]) and [`PoseForm::DofVelocity`]
//! (the network decodes a desired joint velocity `u`; the loop also holds
//! the rig's joint angles `q` and velocities `v`, limits `u` by the joint
//! limits and the acceleration limit, integrates `q` and rebuilds the pose
//! by forward kinematics on the [`Skeleton`]; [`Reach::with_dofs`]).
//!
//! Generic over the scalar like the locomotion loop: the device runs it in
//! `f32` over the fixed-point runtime, the host's reference in `f64` over
//! the float network (`host_sim::omg`), the same code.

use core::ops::Range;

use crate::error::{Error, Result};
use crate::locomotion::Network;
use crate::real::Real;
pub use crate::skeleton::{Dof, Joint, Skeleton, MAX_DOFS, MAX_JOINTS};

/// Most key joints a layout may name (the thesis uses 4: hands and feet).
pub const MAX_KEY: usize = 8;

/// Largest target coordinate accepted, metres from the character's root:
/// anything further is a caller's bug, not a reach.
pub const MAX_TARGET_M: f64 = 100.0;

/// How far the squared length of an axis in a whole target block
/// ([`Reach::set_target_block`]) may be from 1: the data's axes are unit to
/// f32 rounding, and an axis of another length would be fed to the network
/// as it is.
pub const UNIT_AXIS_TOLERANCE: f64 = 1e-3;

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
    /// blocks the network computes (in [`PoseForm::DofVelocity`] the pose
    /// entry is empty: the pose is built by FK).
    pub blocks: [(Range<usize>, Range<usize>); 3],
    /// How the frame's pose block is made.
    pub pose: PoseForm,
}

/// How a reaching loop makes the frame's pose block (pos, rot, vel).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PoseForm {
    /// The network decodes the pose block; the layout's `blocks[1]` says
    /// where it is in the output and in the frame (the models before
    /// joint velocities; a config without `pose_form`).
    Absolute,
    /// The network decodes `u`, the desired velocity of each of the
    /// skeleton's DOFs times the frame time (radians per frame); the loop
    /// limits it, integrates the joint angles and builds pos, rot and vel
    /// by forward kinematics (`docs/omg-joint-velocity.md`).
    DofVelocity {
        /// Where `u` is in the network output (D values).
        out: Range<usize>,
        /// The frame's joint velocity block (3 per joint, m/s).
        vel: Range<usize>,
    },
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

    /// Joints of a frame (its position block's length / 3).
    pub fn joints(&self) -> usize {
        self.pos.len() / 3
    }

    /// Checks the layout against itself and a network of `inputs` ->
    /// `outputs` values: every block inside its vector with the widths the
    /// key joints imply, and for the joint-velocity form its `u` and
    /// velocity blocks and an empty pose entry in `blocks`
    /// ([`Error::BadLayout`] names which check failed; the skeleton is
    /// checked by [`Reach::with_dofs`]).
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
            match &self.pose {
                PoseForm::Absolute => true,
                PoseForm::DofVelocity { out, .. } => within(out, outputs),
            },
            match &self.pose {
                PoseForm::Absolute => true,
                PoseForm::DofVelocity { vel, .. } => {
                    within(vel, self.width) && vel.len() == 3 * joints
                }
            },
            match &self.pose {
                PoseForm::Absolute => true,
                PoseForm::DofVelocity { .. } => {
                    self.blocks[1].0.is_empty() && self.blocks[1].1.is_empty()
                }
            },
        ];
        match checks.iter().position(|ok| !ok) {
            None => Ok(()),
            Some(i) => Err(bad_layout(i as u8)),
        }
    }
}

/// The reaching loop's state for frames of up to `W` values (and, in the
/// joint-velocity form, the skeleton and its joint angles and velocities).
pub struct Reach<R, const W: usize> {
    layout: ReachLayout,
    mode: CostMode,
    x: [R; W],
    out: [R; W],
    targets: [R; W],
    dofs: Option<DofState<R>>,
}

/// The joint-velocity form's own state.
struct DofState<R> {
    skeleton: Skeleton<R>,
    /// Joint angles, radians (the first D).
    q: [R; MAX_DOFS],
    /// Joint velocities, rad/s (the first D).
    v: [R; MAX_DOFS],
}

/// `v` normalised; `None` when it has no direction (all zero, or not
/// finite). Scaled by its largest component first, so that neither huge
/// components (whose squares overflow) nor tiny ones (whose squares
/// vanish) lose the direction.
pub fn unit<R: Real>(v: [R; 3]) -> Option<[R; 3]> {
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
    /// Bytes of the loop's state (without the network): three frames of
    /// `W` values, the layout and, for either form (the type is one), room
    /// for a skeleton of [`MAX_JOINTS`] joints and [`MAX_DOFS`] DOFs with
    /// their angles and velocities (8,792 B for `Reach<f32, 512>` on the
    /// Cortex-M4).
    pub const STATE_RAM_BYTES: usize = core::mem::size_of::<Self>();

    /// A loop of no model yet: every buffer zero, a layout of nothing.
    /// [`Reach::restart`] or [`Reach::restart_dofs`] make it a loop. A
    /// constant, so that a `static` holding it starts in `.bss` and a
    /// device builds its loop in place, without the state passing through
    /// the stack ([`Reach::new`] and [`Reach::with_dofs`] return it by
    /// value, for the host).
    pub const IDLE: Self = Reach {
        layout: ReachLayout {
            width: 0,
            pos: 0..0,
            rot: 0..0,
            cost: 0..0,
            target: 0..0,
            key_joints: heapless::Vec::new(),
            blocks: [(0..0, 0..0), (0..0, 0..0), (0..0, 0..0)],
            pose: PoseForm::Absolute,
        },
        mode: CostMode::Grounded,
        x: [R::ZERO; W],
        out: [R::ZERO; W],
        targets: [R::ZERO; W],
        dofs: None,
    };

    /// The checks both forms make: `layout` against `net`
    /// ([`Error::BadLayout`]), frames within `W` values
    /// ([`Error::TooWide`]), `first` a whole finite frame.
    fn check_start<N: Network<R>>(net: &N, layout: &ReachLayout, first: &[R]) -> Result<()> {
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
        Ok(())
    }

    /// The frames of a checked start: `first`, its targets, all else zero.
    fn fill(&mut self, layout: ReachLayout, mode: CostMode, first: &[R]) {
        self.x.fill(R::ZERO);
        if let Some(x) = self.x.get_mut(..first.len()) {
            x.copy_from_slice(first);
        }
        self.out.fill(R::ZERO);
        self.targets = self.x;
        self.layout = layout;
        self.mode = mode;
    }

    /// Starts from `first` (a whole frame: typically the rest pose with its
    /// targets, frame 0 of a clip), after checking `layout` against `net`
    /// ([`Error::BadLayout`]) and that frames fit `W` values
    /// ([`Error::TooWide`]). The targets start as `first`'s. For
    /// [`PoseForm::Absolute`] layouts ([`Reach::with_dofs`] takes the
    /// others; [`Error::BadLayout`] 12 here).
    pub fn new<N: Network<R>>(
        net: &N,
        layout: ReachLayout,
        mode: CostMode,
        first: &[R],
    ) -> Result<Self> {
        let mut r = Self::IDLE;
        r.restart(net, layout, mode, first)?;
        Ok(r)
    }

    /// [`Reach::new`] in place: this loop starts again as `new` would make
    /// it; refused with no state change.
    pub fn restart<N: Network<R>>(
        &mut self,
        net: &N,
        layout: ReachLayout,
        mode: CostMode,
        first: &[R],
    ) -> Result<()> {
        if layout.pose != PoseForm::Absolute {
            return Err(Error::BadLayout { reason: 12 });
        }
        Self::check_start(net, &layout, first)?;
        self.fill(layout, mode, first);
        self.dofs = None;
        Ok(())
    }

    /// The joint-velocity form ([`PoseForm::DofVelocity`]): starts from
    /// `first` with joint angles `q0` (radians) and velocities `v0`
    /// (rad/s), one per DOF of `skeleton`, checked as [`Reach::new`]
    /// checks and also: the layout's `u` block one value per DOF
    /// ([`Error::BadLayout`] 8) and the frame's joints the skeleton's (11);
    /// an absolute layout is refused (12); `q0` and `v0` of the wrong
    /// length ([`Error::Runtime`]) or not finite ([`Error::BadStart`]).
    /// `q0` is taken as given (a start beyond a limit is clamped to it by
    /// the first step). A clip starts from its frame 0 with its joint
    /// angles and `v0 = q0 / dt` (its frame 0 is one step from rest); a
    /// user from rest: [`rest_frame`] with `q0 = v0 = 0`.
    pub fn with_dofs<N: Network<R>>(
        net: &N,
        layout: ReachLayout,
        mode: CostMode,
        first: &[R],
        skeleton: Skeleton<R>,
        q0: &[R],
        v0: &[R],
    ) -> Result<Self> {
        let mut r = Self::IDLE;
        r.restart_dofs(net, layout, mode, first, skeleton, q0, v0)?;
        Ok(r)
    }

    /// [`Reach::with_dofs`] in place (what the device does, on its static
    /// [`Reach::IDLE`]); refused with no state change.
    #[allow(clippy::too_many_arguments)]
    pub fn restart_dofs<N: Network<R>>(
        &mut self,
        net: &N,
        layout: ReachLayout,
        mode: CostMode,
        first: &[R],
        skeleton: Skeleton<R>,
        q0: &[R],
        v0: &[R],
    ) -> Result<()> {
        let PoseForm::DofVelocity { out, .. } = &layout.pose else {
            return Err(Error::BadLayout { reason: 12 });
        };
        let d = skeleton.dofs().len();
        if out.len() != d {
            return Err(Error::BadLayout { reason: 8 });
        }
        if layout.joints() != skeleton.joints().len() {
            return Err(Error::BadLayout { reason: 11 });
        }
        for s in [q0, v0] {
            if s.len() != d {
                return Err(Error::Runtime(phasegate::Error::LengthMismatch {
                    expected: d as u32,
                    found: s.len() as u32,
                }));
            }
        }
        if let Some(i) = q0.iter().chain(v0).position(|v| !v.is_finite()) {
            return Err(Error::BadStart { index: i as u16 });
        }
        Self::check_start(net, &layout, first)?;
        self.fill(layout, mode, first);
        let state = self.dofs.get_or_insert_with(|| DofState {
            skeleton: Skeleton::EMPTY,
            q: [R::ZERO; MAX_DOFS],
            v: [R::ZERO; MAX_DOFS],
        });
        state.skeleton = skeleton;
        state.q.fill(R::ZERO);
        state.v.fill(R::ZERO);
        if let (Some(q), Some(v)) = (state.q.get_mut(..d), state.v.get_mut(..d)) {
            q.copy_from_slice(q0);
            v.copy_from_slice(v0);
        }
        Ok(())
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

    /// The joint angles of the current frame, radians, one per DOF
    /// (joint-velocity form; empty for an absolute model).
    pub fn dof(&self) -> &[R] {
        match &self.dofs {
            Some(s) => s.q.get(..s.skeleton.dofs().len()).unwrap_or(&[]),
            None => &[],
        }
    }

    /// The joint velocities, rad/s, one per DOF (joint-velocity form;
    /// empty for an absolute model).
    pub fn dof_velocity(&self) -> &[R] {
        match &self.dofs {
            Some(s) => s.v.get(..s.skeleton.dofs().len()).unwrap_or(&[]),
            None => &[],
        }
    }

    /// The skeleton (joint-velocity form).
    pub fn skeleton(&self) -> Option<&Skeleton<R>> {
        self.dofs.as_ref().map(|s| &s.skeleton)
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

    /// Sets the whole target block (9K values, the data's layout: K
    /// positions, then K forward + up pairs) at once, e.g. from a recorded
    /// clip, under [`Reach::set_target`]'s rule: refused with no state
    /// change ([`Error::BadTarget`] with the value's index) when a value is
    /// not finite, a position coordinate is beyond [`MAX_TARGET_M`], or an
    /// axis is not of unit length (within [`UNIT_AXIS_TOLERANCE`] on its
    /// square; for the first of its values). Unlike `set_target` it does
    /// not normalise: the block goes in as given, so a clip's targets reach
    /// the network bit for bit.
    pub fn set_target_block(&mut self, block: &[R]) -> Result<()> {
        let range = self.layout.target.clone();
        if block.len() != range.len() {
            return Err(Error::Runtime(phasegate::Error::LengthMismatch {
                expected: range.len() as u32,
                found: block.len() as u32,
            }));
        }
        let bad = |i: usize| Error::BadTarget {
            field: u8::try_from(i).unwrap_or(u8::MAX),
        };
        if let Some(i) = block.iter().position(|v| !v.is_finite()) {
            return Err(bad(i));
        }
        let positions = 3 * self.layout.key();
        let (pos, axes) = block.split_at(positions.min(block.len()));
        let far = R::lit(MAX_TARGET_M);
        if let Some(i) = pos.iter().position(|v| v.abs() > far) {
            return Err(bad(i));
        }
        let tol = R::lit(UNIT_AXIS_TOLERANCE);
        for (a, axis) in axes.chunks_exact(3).enumerate() {
            // Finite and checked below 2 first, so the squares cannot
            // overflow.
            let unit_length = axis.iter().all(|v| v.abs() <= R::lit(2.0)) && {
                let n2 = axis.iter().fold(R::ZERO, |s, &v| s + v * v);
                (n2 - R::ONE).abs() <= tol
            };
            if !unit_length {
                return Err(bad(positions + 3 * a));
            }
        }
        self.targets
            .get_mut(range)
            .ok_or(Error::BadTarget { field: 255 })?
            .copy_from_slice(block);
        Ok(())
    }

    /// One frame: the network on the current frame, the next frame built
    /// from its output and the current targets, costs as the mode says.
    /// In the joint-velocity form (`docs/omg-joint-velocity.md`, steps
    /// 1-5): the phase and cost blocks from the output, `u` limited
    /// ([`Skeleton::limit`]) into the next joint angles and velocities, the
    /// pose block by FK of those angles (velocities against the frame's
    /// positions before the step), then the targets and costs. On an error
    /// (the network's, or a non-finite output) the state is unchanged.
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
        if let (PoseForm::DofVelocity { out: u, vel }, Some(s)) =
            (&self.layout.pose, &mut self.dofs)
        {
            let d = s.skeleton.dofs().len();
            if let (Some(q), Some(v), Some(u)) =
                (s.q.get_mut(..d), s.v.get_mut(..d), self.out.get(u.clone()))
            {
                s.skeleton.limit(q, v, u);
                write_pose(&self.layout, vel, &s.skeleton, q, &mut self.x, true);
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

/// Writes the pose block of `frame` (laid out by `layout`, velocities in
/// `vel`) from FK of `q` on `sk`: `pos` the joint positions, `rot` per
/// joint the rotation's third column (forward) then its second (up), `vel`
/// `(P - P_before) * fps` against the positions `frame` holds before (with
/// `moving`; zero without).
fn write_pose<R: Real>(
    layout: &ReachLayout,
    vel: &Range<usize>,
    sk: &Skeleton<R>,
    q: &[R],
    frame: &mut [R],
    moving: bool,
) {
    let j = sk.joints().len();
    let (mut p, mut g) = ([R::ZERO; 3 * MAX_JOINTS], [R::ZERO; 9 * MAX_JOINTS]);
    let (Some(p), Some(g)) = (p.get_mut(..3 * j), g.get_mut(..9 * j)) else {
        return;
    };
    if sk.forward_kinematics(q, p, g).is_err() {
        return;
    }
    let fps = sk.fps();
    for (i, (pi, gi)) in p.chunks_exact(3).zip(g.chunks_exact(9)).enumerate() {
        let (at_p, at_r, at_v) = (
            layout.pos.start + 3 * i,
            layout.rot.start + 6 * i,
            vel.start + 3 * i,
        );
        // The third column (forward) and the second (up), row by row.
        let cols = gi.chunks_exact(3).map(|row| match *row {
            [_, up, fwd] => (fwd, up),
            _ => (R::ZERO, R::ZERO),
        });
        for (k, (&pk, (fwd, up))) in pi.iter().zip(cols).enumerate() {
            let before = frame.get(at_p + k).copied().unwrap_or(R::ZERO);
            if let Some(d) = frame.get_mut(at_v + k) {
                *d = if moving { (pk - before) * fps } else { R::ZERO };
            }
            for (at, v) in [(at_p + k, pk), (at_r + k, fwd), (at_r + 3 + k, up)] {
                if let Some(d) = frame.get_mut(at) {
                    *d = v;
                }
            }
        }
    }
}

/// The rest frame of a joint-velocity model (`layout`, `sk`) for the
/// targets `targets` (the frame's 9K-value target block): the pose by FK
/// of `q = 0` with zero velocities, phases 0, the targets, and the costs
/// grounded on them. Where a user starts [`Reach::with_dofs`] from (with
/// `q0 = v0 = 0`). Refused with [`Error::BadLayout`] when the layout is
/// absolute (12), its checks fail (against a network of its own width
/// and `u` block end) or its joints are not the skeleton's (11), and when
/// `targets` or `frame` have the wrong length or a target is not finite.
pub fn rest_frame<R: Real>(
    layout: &ReachLayout,
    sk: &Skeleton<R>,
    targets: &[R],
    frame: &mut [R],
) -> Result<()> {
    let PoseForm::DofVelocity { out, vel } = &layout.pose else {
        return Err(Error::BadLayout { reason: 12 });
    };
    let outputs = out
        .end
        .max(layout.blocks.iter().map(|b| b.0.end).max().unwrap_or(0));
    layout.check(layout.width, outputs)?;
    if layout.joints() != sk.joints().len() {
        return Err(Error::BadLayout { reason: 11 });
    }
    for (n, want) in [
        (targets.len(), layout.target.len()),
        (frame.len(), layout.width),
    ] {
        if n != want {
            return Err(Error::Runtime(phasegate::Error::LengthMismatch {
                expected: want as u32,
                found: n as u32,
            }));
        }
    }
    if let Some(i) = targets.iter().position(|v| !v.is_finite()) {
        return Err(Error::BadTarget {
            field: u8::try_from(i).unwrap_or(u8::MAX),
        });
    }
    frame.fill(R::ZERO);
    let q = [R::ZERO; MAX_DOFS];
    write_pose(
        layout,
        vel,
        sk,
        q.get(..sk.dofs().len()).unwrap_or(&[]),
        frame,
        false,
    );
    if let Some(d) = frame.get_mut(layout.target.clone()) {
        d.copy_from_slice(targets);
    }
    let mut costs = [R::ZERO; 6 * MAX_KEY];
    let k6 = 6 * layout.key();
    let c = costs.get_mut(..k6).unwrap_or(&mut []);
    grounded_costs(layout, frame, c);
    if let Some(d) = frame.get_mut(layout.cost.clone()) {
        d.copy_from_slice(costs.get(..k6).unwrap_or(&[]));
    }
    Ok(())
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
            pose: PoseForm::Absolute,
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
        // The block path keeps set_target's rule: positions within reach,
        // axes of unit length (not normalised: refused).
        let block = |p: [f64; 3], f: [f64; 3], u: [f64; 3]| [p, f, u].concat();
        let (p, f, u) = ([0.3, 1.2, 0.2], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]);
        for (b, field) in [
            (block([0.0, 0.0, 1e9], f, u), 2),
            (block(p, [0.0; 3], u), 3),
            (block(p, [0.0, 0.0, 2.0], u), 3),
            (block(p, f, [1e30, 1e30, 0.0]), 6),
            (block(p, f, [0.0, 0.7, 0.7]), 6),
        ] {
            assert_eq!(r.set_target_block(&b), Err(Error::BadTarget { field }));
        }
        assert_eq!(r.frame(), &before[..]);
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

    // The joint-velocity form.

    /// The 3-joint chain of the skeleton tests: a root at (0, 1, 0), a
    /// child 1 m up, a grandchild 0.5 m forward; DOFs root.x, child.y,
    /// child.z, grandchild.z, limits +-1 (grandchild.z +-0.2).
    fn chain<R: Real>() -> Skeleton<R> {
        let j = |parent, o: [f64; 3]| Joint {
            parent,
            offset: o.map(R::lit),
        };
        let d = |joint, axis, lim: f64| Dof {
            joint,
            axis,
            lower: R::lit(-lim),
            upper: R::lit(lim),
        };
        Skeleton::new(
            [
                j(None, [0.0, 1.0, 0.0]),
                j(Some(0), [0.0, 1.0, 0.0]),
                j(Some(1), [0.0, 0.0, 0.5]),
            ],
            [d(0, 0, 1.0), d(1, 1, 1.0), d(1, 2, 1.0), d(2, 2, 0.2)],
            R::lit(60.0),
            R::lit(5.0),
        )
        .unwrap()
    }

    /// J = 3, K = 1 (the grandchild), D = 4: frame = phase 2, pos 9,
    /// rot 18, vel 9, cost 6, target 9 = 53 values; the network's output
    /// `[phase 2, u 4, cost 6]` = 12.
    fn dof_layout() -> ReachLayout {
        ReachLayout {
            width: 53,
            pos: 2..11,
            rot: 11..29,
            cost: 38..44,
            target: 44..53,
            key_joints: heapless::Vec::from_slice(&[2]).unwrap(),
            blocks: [(0..2, 0..2), (2..2, 2..2), (6..12, 38..44)],
            pose: PoseForm::DofVelocity {
                out: 2..6,
                vel: 29..38,
            },
        }
    }

    /// Phase and costs from its input; `u` a function of the frame (the
    /// grandchild's position) plus `bias`, so the loop closes on its own
    /// pose.
    struct Toward {
        bias: [f64; 4],
        fail: bool,
    }

    impl<R: Real> Network<R> for Toward {
        fn input_dim(&self) -> usize {
            53
        }
        fn output_dim(&self) -> usize {
            12
        }
        fn predict(&mut self, _: R, x: &[R], y: &mut [R]) -> Result<()> {
            if self.fail {
                return Err(Error::NonFinite { index: 0 });
            }
            y[..2].copy_from_slice(&x[..2]);
            // Towards the target (44..47) from the grandchild (8..11).
            let e = |k: usize| x[44 + k] - x[8 + k];
            let gain = R::lit(0.02);
            // root.x lifts the hand forward, child.y swings it to +x.
            let u = [e(2), e(0), e(1), e(0)];
            for (d, (e, b)) in y[2..6].iter_mut().zip(u.iter().zip(self.bias)) {
                *d = gain * *e + R::lit(b);
            }
            y[6..12].copy_from_slice(&x[38..44]);
            Ok(())
        }
        fn mean_output(&self, y: &mut [R]) -> Result<()> {
            y.fill(R::ZERO);
            Ok(())
        }
    }

    fn dof_first<R: Real>(target: [f64; 3]) -> Vec<R> {
        let mut t = [R::ZERO; 9];
        for k in 0..3 {
            t[k] = R::lit(target[k]);
        }
        t[3 + 2] = R::ONE;
        t[3 + 4] = R::ONE;
        let mut f = vec![R::ZERO; 53];
        rest_frame(&dof_layout(), &chain(), &t, &mut f).unwrap();
        f
    }

    #[test]
    fn the_rest_frame_is_fk_at_zero_with_its_targets_and_grounded_costs() {
        let f: Vec<f64> = dof_first([0.3, 2.0, 0.5]);
        assert_eq!(f[2..11], [0.0, 1.0, 0.0, 0.0, 2.0, 0.0, 0.0, 2.0, 0.5]);
        for j in 0..3 {
            assert_eq!(f[11 + 6 * j..17 + 6 * j], [0.0, 0.0, 1.0, 0.0, 1.0, 0.0]);
        }
        assert_eq!(f[29..38], [0.0; 9], "velocities");
        assert_eq!(f[..2], [0.0; 2], "phases");
        assert_eq!(f[44..47], [0.3, 2.0, 0.5]);
        let c = &f[38..44];
        assert!((c[0] - 0.3).abs() < 1e-12 && c[1].abs() < 1e-12 && c[2].abs() < 1e-12);
        assert_eq!(c[3..], [0.0; 3]);
        // Not a joint-velocity layout, or not its skeleton.
        let mut out = vec![0.0; 35];
        assert_eq!(
            rest_frame(&layout(), &chain::<f64>(), &[0.0; 9], &mut out),
            Err(Error::BadLayout { reason: 12 })
        );
        let mut l = dof_layout();
        l.pos = 2..8;
        assert!(rest_frame(&l, &chain::<f64>(), &[0.0; 9], &mut vec![0.0; 53]).is_err());
    }

    #[test]
    fn a_dof_step_limits_u_integrates_and_rebuilds_the_pose_by_fk() {
        let first: Vec<f64> = dof_first([0.3, 2.0, 0.5]);
        let mut net = Toward {
            bias: [0.0, 0.0, 0.0, 0.01],
            fail: false,
        };
        let q0 = [0.01, -0.02, 0.0, 0.0];
        let v0 = [0.6, -1.2, 0.0, 0.0];
        let mut r: Reach<f64, 64> = Reach::with_dofs(
            &net,
            dof_layout(),
            CostMode::Grounded,
            &first,
            chain(),
            &q0,
            &v0,
        )
        .unwrap();
        assert_eq!(r.dof(), &q0);
        assert_eq!(r.dof_velocity(), &v0);
        let mut expect_q = q0;
        let mut expect_v = v0;
        let sk = chain::<f64>();
        for _ in 0..120 {
            let before = r.frame().to_vec();
            let mut out = [0.0; 12];
            Network::<f64>::predict(&mut net, 0.0, &before, &mut out).unwrap();
            sk.limit(&mut expect_q, &mut expect_v, &out[2..6]);
            r.step(&mut net).unwrap();
            assert_eq!(r.dof(), &expect_q);
            assert_eq!(r.dof_velocity(), &expect_v);
            let f = r.frame();
            let (mut p, mut g) = ([0.0; 9], [0.0; 27]);
            sk.forward_kinematics(&expect_q, &mut p, &mut g).unwrap();
            assert_eq!(f[2..11], p);
            for j in 0..3 {
                let m = &g[9 * j..9 * j + 9];
                assert_eq!(
                    f[11 + 6 * j..17 + 6 * j],
                    [m[2], m[5], m[8], m[1], m[4], m[7]]
                );
                for k in 0..3 {
                    assert_eq!(
                        f[29 + 3 * j + k],
                        (p[3 * j + k] - before[2 + 3 * j + k]) * 60.0
                    );
                }
            }
            assert_eq!(f[..2], before[..2], "phase from the output");
            let mut c = [0.0; 6];
            grounded_costs(&dof_layout(), f, &mut c);
            assert_eq!(f[38..44], c);
        }
        // Within the limits all along (grandchild.z is driven by its bias
        // into its +0.2 limit).
        assert!((r.dof()[3] - 0.2).abs() < 1e-12, "{:?}", r.dof());
        // The hand came closer to its target.
        let d = |f: &[f64]| (0..3).map(|k| (f[44 + k] - f[8 + k]).powi(2)).sum::<f64>();
        assert!(
            d(r.frame()) < d(&first),
            "{} vs {}",
            d(r.frame()),
            d(&first)
        );
        // A failed frame changes nothing, joint angles included.
        let (frame, q, v) = (
            r.frame().to_vec(),
            r.dof().to_vec(),
            r.dof_velocity().to_vec(),
        );
        net.fail = true;
        assert!(r.step(&mut net).is_err());
        assert_eq!(
            (r.frame(), r.dof(), r.dof_velocity()),
            (&frame[..], &q[..], &v[..])
        );
    }

    #[test]
    fn dof_layouts_and_start_states_are_refused_naming_the_check() {
        let net = Toward {
            bias: [0.0; 4],
            fail: false,
        };
        let first: Vec<f64> = dof_first([0.3, 2.0, 0.5]);
        let z = [0.0; 4];
        let make = |l: ReachLayout, sk: Skeleton<f64>, q: &[f64], v: &[f64]| {
            Reach::<f64, 64>::with_dofs(&net, l, CostMode::Grounded, &first, sk, q, v).err()
        };
        let reason = |r| Some(Error::BadLayout { reason: r });
        assert_eq!(make(dof_layout(), chain(), &z, &z), None);
        assert_eq!(
            Reach::<f64, 64>::new(&net, dof_layout(), CostMode::Grounded, &first).err(),
            reason(12)
        );
        let mut l = dof_layout();
        l.pose = PoseForm::Absolute;
        assert_eq!(make(l, chain(), &z, &z), reason(12));
        let with = |out: Range<usize>, vel: Range<usize>| ReachLayout {
            pose: PoseForm::DofVelocity { out, vel },
            ..dof_layout()
        };
        assert_eq!(make(with(2..13, 29..38), chain(), &z, &z), reason(8));
        assert_eq!(make(with(2..5, 29..38), chain(), &z, &z), reason(8));
        assert_eq!(make(with(2..6, 29..37), chain(), &z, &z), reason(9));
        let mut l = dof_layout();
        l.blocks[1] = (2..6, 2..6);
        assert_eq!(make(l, chain(), &z, &z), reason(10));
        let two = Skeleton::new(
            chain::<f64>().joints()[..2].iter().copied(),
            chain::<f64>().dofs().iter().copied().take(3).chain([Dof {
                joint: 0,
                axis: 1,
                lower: 0.0,
                upper: 0.0,
            }]),
            60.0,
            5.0,
        )
        .unwrap();
        assert_eq!(make(dof_layout(), two, &z, &z), reason(11));
        assert!(matches!(
            make(dof_layout(), chain(), &z[..3], &z),
            Some(Error::Runtime(_))
        ));
        assert_eq!(
            make(dof_layout(), chain(), &z, &[0.0, 0.0, f64::NAN, 0.0]),
            Some(Error::BadStart { index: 6 })
        );
        assert_eq!(
            make(dof_layout(), chain(), &[f64::INFINITY, 0.0, 0.0, 0.0], &z),
            Some(Error::BadStart { index: 0 })
        );
    }

    /// The device's f32 loop and the host's f64 loop over the same
    /// network and start differ by rounding only: within 1e-5 m over 200
    /// steps of a closed loop that drives joints into their limits.
    #[test]
    fn the_f32_and_f64_dof_loops_agree_closely() {
        let bias = [0.004, -0.003, 0.002, 0.006];
        let (mut n32, mut n64) = (Toward { bias, fail: false }, Toward { bias, fail: false });
        let (q0, v0) = ([0.01, -0.02, 0.03, 0.0], [0.6, -1.2, 1.8, 0.0]);
        let f64_first: Vec<f64> = dof_first([0.4, 1.6, 0.6]);
        let f32_first: Vec<f32> = dof_first([0.4, 1.6, 0.6]);
        let mut a: Reach<f64, 64> = Reach::with_dofs(
            &n64,
            dof_layout(),
            CostMode::Grounded,
            &f64_first,
            chain(),
            &q0,
            &v0,
        )
        .unwrap();
        let mut b: Reach<f32, 64> = Reach::with_dofs(
            &n32,
            dof_layout(),
            CostMode::Grounded,
            &f32_first,
            chain(),
            &q0.map(|v| v as f32),
            &v0.map(|v| v as f32),
        )
        .unwrap();
        let mut worst = 0f64;
        let mut at_limit = false;
        for _ in 0..200 {
            a.step(&mut n64).unwrap();
            b.step(&mut n32).unwrap();
            for (x, y) in a.pose().positions.iter().zip(b.pose().positions) {
                worst = worst.max((x - f64::from(*y)).abs());
            }
            at_limit |= a
                .dof()
                .iter()
                .zip(chain::<f64>().dofs())
                .any(|(q, d)| *q == d.upper || *q == d.lower);
        }
        assert!(at_limit, "the loop reaches a limit");
        assert!(worst < 1e-5, "{worst}");
        assert!(worst > 0.0, "different precisions");
    }
}
