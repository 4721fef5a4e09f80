//! The rig of a joint-velocity OMG model (`docs/omg-joint-velocity.md`):
//! its joints (parent, rest offset), its degrees of freedom (joint, axis,
//! limits), the frame rate and the acceleration limit; forward kinematics
//! (FK) of joint angles, and the limit stage that turns a desired joint
//! velocity into the next joint angles (`tools/omg/ik.py`,
//! `HandIK.limit`).
//!
//! Bounded without a heap: at most [`MAX_JOINTS`] joints and [`MAX_DOFS`]
//! DOFs. Everything is checked once, in [`Skeleton::new`], so FK and the
//! limit stage cannot fail afterwards.
//!
//! The arithmetic is [`Real`]'s (`f32` on the device, `f64` for the host's
//! reference), each operation in a fixed order and none fused, so the
//! device and the host's `f32` loop give the same bits.

use crate::error::{Error, Result, SkeletonCheck};
use crate::real::Real;

/// Most joints a skeleton may have.
pub const MAX_JOINTS: usize = 64;
/// Most degrees of freedom a skeleton may have.
pub const MAX_DOFS: usize = 64;
/// Largest rest offset coordinate accepted, metres.
pub const MAX_OFFSET_M: f64 = 100.0;

/// Marks an axis of a joint that no DOF turns.
const NO_DOF: u8 = u8::MAX;

/// One joint: its parent (`None`: a root, placed at its offset from the
/// pivot) and its rest offset from the parent, in the parent's frame.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Joint<R> {
    /// Index of the parent joint, which must come before this one.
    pub parent: Option<u16>,
    /// Rest offset from the parent (a root: from the pivot), metres.
    pub offset: [R; 3],
}

/// One degree of freedom: a rotation of one joint about one of its local
/// axes, between two limits.
#[derive(Clone, Copy, Debug, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Dof<R> {
    /// The joint it turns.
    pub joint: u16,
    /// 0 = x, 1 = y, 2 = z.
    pub axis: u8,
    /// Lowest angle, radians.
    pub lower: R,
    /// Highest angle, radians (at least `lower`).
    pub upper: R,
}

/// A checked rig: joints (parents before children), DOFs in the model's
/// order (the order of its `u` output and of the data's `dof` block), the
/// frame rate and the joints' acceleration limit.
#[derive(Clone, Debug, PartialEq)]
pub struct Skeleton<R> {
    joints: heapless::Vec<Joint<R>, MAX_JOINTS>,
    dofs: heapless::Vec<Dof<R>, MAX_DOFS>,
    /// Per joint, the index of the DOF on each axis ([`NO_DOF`]: none).
    by_axis: [[u8; 3]; MAX_JOINTS],
    fps: R,
    dt: R,
    a_max: R,
}

fn refuse(check: SkeletonCheck, index: usize) -> Error {
    Error::BadSkeleton {
        check,
        index: u16::try_from(index).unwrap_or(u16::MAX),
    }
}

impl<R: Real> Skeleton<R> {
    /// No joints, no DOFs, rates 1 (a placeholder for state built in
    /// place; [`Skeleton::new`] makes real ones).
    pub const EMPTY: Self = Skeleton {
        joints: heapless::Vec::new(),
        dofs: heapless::Vec::new(),
        by_axis: [[NO_DOF; 3]; MAX_JOINTS],
        fps: R::ONE,
        dt: R::ONE,
        a_max: R::ONE,
    };

    /// Checks and builds a skeleton. Refused with
    /// [`Error::BadSkeleton`] naming the check and the joint or DOF:
    /// more than [`MAX_JOINTS`] joints or [`MAX_DOFS`] DOFs (index: the
    /// capacity), a parent not before its joint, an offset coordinate not
    /// finite or beyond [`MAX_OFFSET_M`], a DOF of no such joint, an axis
    /// other than 0, 1, 2, a second DOF on one joint's axis, limits not
    /// finite or `lower > upper`, a frame rate or acceleration limit that
    /// is not finite and positive.
    pub fn new(
        joints: impl IntoIterator<Item = Joint<R>>,
        dofs: impl IntoIterator<Item = Dof<R>>,
        fps: R,
        a_max: R,
    ) -> Result<Self> {
        let positive = |v: R| v.is_finite() && v > R::ZERO;
        if !positive(fps) {
            return Err(refuse(SkeletonCheck::Fps, 0));
        }
        if !positive(a_max) {
            return Err(refuse(SkeletonCheck::AMax, 0));
        }
        let mut sk = Skeleton {
            joints: heapless::Vec::new(),
            dofs: heapless::Vec::new(),
            by_axis: [[NO_DOF; 3]; MAX_JOINTS],
            fps,
            dt: R::ONE / fps,
            a_max,
        };
        let far = R::lit(MAX_OFFSET_M);
        for (j, joint) in joints.into_iter().enumerate() {
            if joint.parent.is_some_and(|p| usize::from(p) >= j) {
                return Err(refuse(SkeletonCheck::Parent, j));
            }
            if joint.offset.iter().any(|v| !v.is_finite() || v.abs() > far) {
                return Err(refuse(SkeletonCheck::Offset, j));
            }
            sk.joints
                .push(joint)
                .map_err(|_| refuse(SkeletonCheck::TooManyJoints, MAX_JOINTS))?;
        }
        for (d, dof) in dofs.into_iter().enumerate() {
            let joint = usize::from(dof.joint);
            if joint >= sk.joints.len() {
                return Err(refuse(SkeletonCheck::DofJoint, d));
            }
            if dof.axis > 2 {
                return Err(refuse(SkeletonCheck::DofAxis, d));
            }
            if !(dof.lower.is_finite() && dof.upper.is_finite() && dof.lower <= dof.upper) {
                return Err(refuse(SkeletonCheck::DofLimits, d));
            }
            let slot = sk
                .by_axis
                .get_mut(joint)
                .and_then(|a| a.get_mut(usize::from(dof.axis)))
                .ok_or_else(|| refuse(SkeletonCheck::DofJoint, d))?;
            if *slot != NO_DOF {
                return Err(refuse(SkeletonCheck::DuplicateDof, d));
            }
            sk.dofs
                .push(dof)
                .map_err(|_| refuse(SkeletonCheck::TooManyDofs, MAX_DOFS))?;
            // Below MAX_DOFS = 64: fits a u8 and is never NO_DOF.
            *slot = d as u8;
        }
        Ok(sk)
    }

    /// The joints, parents first.
    pub fn joints(&self) -> &[Joint<R>] {
        &self.joints
    }

    /// The DOFs, in the model's order.
    pub fn dofs(&self) -> &[Dof<R>] {
        &self.dofs
    }

    /// Frames per second.
    pub fn fps(&self) -> R {
        self.fps
    }

    /// The frame time `1 / fps`, seconds.
    pub fn dt(&self) -> R {
        self.dt
    }

    /// The joints' acceleration limit, rad/s^2.
    pub fn a_max(&self) -> R {
        self.a_max
    }

    /// Forward kinematics of joint angles `q` (one per DOF): each joint's
    /// position (`positions`, 3 per joint, metres in the root space) and
    /// rotation (`rotations`, 9 per joint, row-major). Per joint in order,
    /// `R_j = Rx(e_x) Ry(e_y) Rz(e_z)` of its DOF angles (an axis without
    /// a DOF is not turned), `G_j = G_parent R_j` (a root: `R_j`),
    /// `P_j = P_parent + G_parent offset_j` (a root: `offset_j`), as
    /// `tools/omg/rigs.py: forward_kinematics`. Refused when a slice has
    /// the wrong length.
    pub fn forward_kinematics(
        &self,
        q: &[R],
        positions: &mut [R],
        rotations: &mut [R],
    ) -> Result<()> {
        let j = self.joints.len();
        for (n, want) in [
            (q.len(), self.dofs.len()),
            (positions.len(), 3 * j),
            (rotations.len(), 9 * j),
        ] {
            if n != want {
                return Err(Error::Runtime(phasegate::Error::LengthMismatch {
                    expected: want as u32,
                    found: n as u32,
                }));
            }
        }
        for (i, (joint, axes)) in self.joints.iter().zip(&self.by_axis).enumerate() {
            let (mut g, mut p) = ([R::ZERO; 9], joint.offset);
            match joint.parent.map(usize::from) {
                None => {
                    g[0] = R::ONE;
                    g[4] = R::ONE;
                    g[8] = R::ONE;
                }
                Some(parent) => {
                    let (gp, pp) = match (
                        rotations.get(9 * parent..9 * parent + 9),
                        positions.get(3 * parent..3 * parent + 3),
                    ) {
                        (Some(gp), Some(pp)) => (gp, pp),
                        _ => continue,
                    };
                    g.copy_from_slice(gp);
                    let o = joint.offset;
                    for ((pr, row), &base) in p.iter_mut().zip(g.chunks_exact(3)).zip(pp) {
                        if let [a, b, c] = *row {
                            *pr = base + (a * o[0] + b * o[1] + c * o[2]);
                        }
                    }
                }
            }
            for (axis, &d) in axes.iter().enumerate() {
                if let Some(&angle) = q.get(usize::from(d)) {
                    turn(&mut g, axis, angle);
                }
            }
            if let (Some(gd), Some(pd)) = (
                rotations.get_mut(9 * i..9 * i + 9),
                positions.get_mut(3 * i..3 * i + 3),
            ) {
                gd.copy_from_slice(&g);
                pd.copy_from_slice(&p);
            }
        }
        Ok(())
    }

    /// The limit stage of one frame (`HandIK.limit`; step 2 of
    /// `docs/omg-joint-velocity.md`): from angles `q` and velocities `v`
    /// (rad/s) towards the desired motion `u` (radians per frame), per
    /// DOF: `w = u / dt`, no faster towards a limit than the speed it can
    /// stop from at `a_max` (`stop(room) = sqrt(h^2 + 2 a room) - h`,
    /// `h = a dt / 2`), the velocity changed by at most `a dt`, the angle
    /// clamped to the limits and the velocity made the step actually
    /// taken. `q` and `v` are updated in place; extra values of any slice
    /// beyond the DOFs are ignored.
    pub fn limit(&self, q: &mut [R], v: &mut [R], u: &[R]) {
        let (a, dt) = (self.a_max, self.dt);
        let h = R::lit(0.5) * a * dt;
        let two_a = R::lit(2.0) * a;
        let stop = |room: R| {
            let room = if room > R::ZERO { room } else { R::ZERO };
            (h * h + two_a * room).sqrt() - h
        };
        let step = a * dt;
        for (((dof, q), v), &u) in self.dofs.iter().zip(q).zip(v).zip(u) {
            let mut w = u / dt;
            let up = stop(dof.upper - *q);
            if up < w {
                w = up;
            }
            let down = -stop(*q - dof.lower);
            if down > w {
                w = down;
            }
            let v1 = *v + (w - *v).clamp_to(-step, step);
            let q1 = (*q + v1 * dt).clamp_to(dof.lower, dof.upper);
            *v = (q1 - *q) / dt;
            *q = q1;
        }
    }
}

/// `g = g R_axis(t)` for a row-major rotation `g`: with `(i, j)` the axes
/// after `axis` (x: y, z; y: z, x; z: x, y), columns `i` and `j` become
/// `c g_i + s g_j` and `c g_j - s g_i` (the other products of the full
/// matrix product are exact zeros).
fn turn<R: Real>(g: &mut [R; 9], axis: usize, t: R) {
    let (s, c) = t.sin_cos();
    for row in g.chunks_exact_mut(3) {
        let [r0, r1, r2] = row else { continue };
        let (gi, gj) = match axis {
            0 => (r1, r2),
            1 => (r2, r0),
            _ => (r0, r1),
        };
        let (a, b) = (*gi, *gj);
        *gi = a * c + b * s;
        *gj = b * c - a * s;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn joint(parent: Option<u16>, offset: [f64; 3]) -> Joint<f64> {
        Joint { parent, offset }
    }

    fn dof(joint: u16, axis: u8) -> Dof<f64> {
        Dof {
            joint,
            axis,
            lower: -1.0,
            upper: 1.0,
        }
    }

    /// A 3-joint chain: a root at (0, 1, 0), a child 1 m up, a grandchild
    /// 0.5 m forward; DOFs root.x, child.y, child.z, grandchild.z.
    fn chain() -> Skeleton<f64> {
        Skeleton::new(
            [
                joint(None, [0.0, 1.0, 0.0]),
                joint(Some(0), [0.0, 1.0, 0.0]),
                joint(Some(1), [0.0, 0.0, 0.5]),
            ],
            [dof(0, 0), dof(1, 1), dof(1, 2), dof(2, 2)],
            60.0,
            5.0,
        )
        .unwrap()
    }

    fn fk(s: &Skeleton<f64>, q: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let j = s.joints().len();
        let (mut p, mut g) = (vec![0.0; 3 * j], vec![0.0; 9 * j]);
        s.forward_kinematics(q, &mut p, &mut g).unwrap();
        (p, g)
    }

    fn close(a: &[f64], b: &[f64]) {
        assert_eq!(a.len(), b.len());
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!((x - y).abs() < 1e-12, "{i}: {x} vs {y} ({a:?} vs {b:?})");
        }
    }

    #[test]
    fn fk_of_a_chain_matches_hand_computed_poses() {
        let s = chain();
        // Rest: offsets added up, rotations the identity.
        let (p, g) = fk(&s, &[0.0; 4]);
        close(&p, &[0.0, 1.0, 0.0, 0.0, 2.0, 0.0, 0.0, 2.0, 0.5]);
        let eye = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        close(&g, &[eye, eye, eye].concat());

        // Root turned 90 degrees about x: its up (y) becomes +z, so the
        // child sits 1 m forward of the root and the grandchild's forward
        // offset points down.
        let h = core::f64::consts::FRAC_PI_2;
        let (p, g) = fk(&s, &[h, 0.0, 0.0, 0.0]);
        close(&p, &[0.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.5, 1.0]);
        // Rx(90) = [[1,0,0],[0,0,-1],[0,1,0]].
        close(&g[..9], &[1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0]);

        // The child turned 90 degrees about y: the grandchild's forward
        // (z) offset becomes +x. Then also 90 about z (Ry Rz): the child's
        // rotation is Ry(90) Rz(90) = [[0,0,1],[1,0,0],[0,1,0]].
        let (p, _) = fk(&s, &[0.0, h, 0.0, 0.0]);
        close(&p[6..], &[0.5, 2.0, 0.0]);
        let (p, g) = fk(&s, &[0.0, h, h, 0.0]);
        close(&g[9..18], &[0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
        close(&p[6..], &[0.5, 2.0, 0.0]);
        // The grandchild's own z turn moves nothing of its position.
        let (p2, g2) = fk(&s, &[0.0, h, h, 0.7]);
        close(&p2, &p);
        // ... but turns its rotation: G = G_child Rz(0.7).
        let (c, sn) = (0.7f64.cos(), 0.7f64.sin());
        let gc = [0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0];
        let rz = [c, -sn, 0.0, sn, c, 0.0, 0.0, 0.0, 1.0];
        let mut want = [0.0; 9];
        for r in 0..3 {
            for k in 0..3 {
                want[3 * r + k] = (0..3).map(|m| gc[3 * r + m] * rz[3 * m + k]).sum();
            }
        }
        close(&g2[18..], &want);

        // A general angle about x on the root: the child at
        // (0, 1 + cos t, sin t).
        let t: f64 = 0.3;
        let (p, _) = fk(&s, &[t, 0.0, 0.0, 0.0]);
        close(&p[3..6], &[0.0, 1.0 + t.cos(), t.sin()]);
    }

    /// A random skeleton of `n` joints with a DOF on every axis of every
    /// joint.
    fn random_skeleton(seed: u64, n: usize) -> Skeleton<f64> {
        let mut r = seed;
        let mut next = || {
            r = r.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
            (r >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        let joints: Vec<Joint<f64>> = (0..n)
            .map(|j| Joint {
                parent: (j > 0).then(|| ((next() + 1.0) * 0.5 * j as f64) as u16),
                offset: [next(), next(), next()],
            })
            .collect();
        let dofs: Vec<Dof<f64>> = (0..3 * n)
            .map(|d| Dof {
                joint: (d / 3) as u16,
                axis: (d % 3) as u8,
                lower: -3.0,
                upper: 3.0,
            })
            .collect();
        Skeleton::new(joints, dofs, 60.0, 5.0).unwrap()
    }

    #[test]
    fn bone_lengths_and_rotations_hold_over_random_angles() {
        for seed in 0..20 {
            let s = random_skeleton(seed, 21);
            let mut r = seed + 99;
            let q: Vec<f64> = (0..s.dofs().len())
                .map(|_| {
                    r = r.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(7);
                    ((r >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0) * 3.0
                })
                .collect();
            let (p, g) = fk(&s, &q);
            for (j, joint) in s.joints().iter().enumerate() {
                let Some(par) = joint.parent.map(usize::from) else {
                    close(&p[3 * j..3 * j + 3], &joint.offset);
                    continue;
                };
                let bone: f64 = (0..3)
                    .map(|k| (p[3 * j + k] - p[3 * par + k]).powi(2))
                    .sum::<f64>()
                    .sqrt();
                let rest: f64 = joint.offset.iter().map(|v| v * v).sum::<f64>().sqrt();
                assert!((bone - rest).abs() < 1e-12, "joint {j}: {bone} vs {rest}");
                // G orthonormal.
                let m = &g[9 * j..9 * j + 9];
                for a in 0..3 {
                    for b in 0..3 {
                        let dot: f64 = (0..3).map(|k| m[3 * k + a] * m[3 * k + b]).sum();
                        let want = if a == b { 1.0 } else { 0.0 };
                        assert!((dot - want).abs() < 1e-12);
                    }
                }
            }
        }
    }

    #[test]
    fn the_limit_stage_matches_hand_computed_values() {
        // a = 5, fps = 60: dt = 1/60, a dt = 1/12 rad/s per frame,
        // h = 1/24.
        let s = Skeleton::new(
            [joint(None, [0.0; 3])],
            [Dof {
                joint: 0,
                axis: 0,
                lower: -0.5,
                upper: 0.5,
            }],
            60.0,
            5.0,
        )
        .unwrap();
        let (dt, step, h) = (1.0 / 60.0, 5.0 / 60.0, 0.5 * 5.0 / 60.0);
        let stop = |room: f64| (h * h + 10.0 * f64::max(room, 0.0)).sqrt() - h;

        // Far from the limits, from rest: the acceleration clamp.
        let (mut q, mut v) = ([0.0], [0.0]);
        s.limit(&mut q, &mut v, &[0.1]);
        assert!((v[0] - step).abs() < 1e-12, "{v:?}");
        assert!((q[0] - step * dt).abs() < 1e-15);

        // Within the clamp: the desired velocity is taken as it is.
        let (mut q, mut v) = ([0.0], [1.0]);
        s.limit(&mut q, &mut v, &[1.05 * dt]);
        assert!((v[0] - 1.05).abs() < 1e-12 && (q[0] - 1.05 * dt).abs() < 1e-15);

        // Near the upper limit: no faster than the stop speed of the room
        // left (0.01 rad: stop = sqrt(h^2 + 0.1) - h = 0.27729...).
        let (mut q, mut v) = ([0.49], [0.3]);
        s.limit(&mut q, &mut v, &[10.0 * dt]);
        let w = stop(0.01);
        assert!((w - 0.277_294).abs() < 1e-5, "{w}");
        assert!((v[0] - w).abs() < 1e-12, "{v:?} vs {w}");
        assert!((q[0] - (0.49 + w * dt)).abs() < 1e-15);

        // At the lower limit, asked to go further: stop speed 0, the
        // velocity falls by a dt and the angle is clamped at the limit,
        // the velocity being the step taken (0).
        let (mut q, mut v) = ([-0.5], [0.0]);
        s.limit(&mut q, &mut v, &[-1.0]);
        assert_eq!((q[0], v[0]), (-0.5, 0.0));

        // Moving fast at the limit: the clamp of q, and v the step taken.
        let (mut q, mut v) = ([0.499], [3.0]);
        s.limit(&mut q, &mut v, &[3.0 * dt]);
        // w = min(3, stop(0.001)) = 0.0667; v' = 3 - 1/12; q' clamps.
        assert_eq!(q[0], 0.5);
        assert!((v[0] - 0.001 / dt).abs() < 1e-9, "{v:?}");

        // Beyond a limit (a start outside them): clamped back.
        let (mut q, mut v) = ([0.7], [0.0]);
        s.limit(&mut q, &mut v, &[0.0]);
        assert_eq!(q[0], 0.5);
        assert!((v[0] - (0.5 - 0.7) / dt).abs() < 1e-9);
    }

    #[test]
    fn skeletons_are_refused_naming_the_check() {
        let ok = [joint(None, [0.0; 3]), joint(Some(0), [0.0, 1.0, 0.0])];
        let bad = |js: &[Joint<f64>], ds: &[Dof<f64>], fps: f64, a: f64| match Skeleton::new(
            js.iter().copied(),
            ds.iter().copied(),
            fps,
            a,
        ) {
            Err(Error::BadSkeleton { check, index }) => (check, index),
            other => panic!("{other:?}"),
        };
        use SkeletonCheck as C;
        assert_eq!(bad(&ok, &[], 0.0, 5.0), (C::Fps, 0));
        assert_eq!(bad(&ok, &[], f64::INFINITY, 5.0), (C::Fps, 0));
        assert_eq!(bad(&ok, &[], 60.0, -1.0), (C::AMax, 0));
        assert_eq!(bad(&ok, &[], 60.0, f64::NAN), (C::AMax, 0));
        let cyc = [joint(None, [0.0; 3]), joint(Some(1), [0.0; 3])];
        assert_eq!(bad(&cyc, &[], 60.0, 5.0), (C::Parent, 1));
        let far = [joint(None, [0.0, f64::NAN, 0.0])];
        assert_eq!(bad(&far, &[], 60.0, 5.0), (C::Offset, 0));
        let far = [joint(None, [0.0; 3]), joint(Some(0), [1e3, 0.0, 0.0])];
        assert_eq!(bad(&far, &[], 60.0, 5.0), (C::Offset, 1));
        assert_eq!(
            bad(&ok, &[dof(0, 0), dof(2, 0)], 60.0, 5.0),
            (C::DofJoint, 1)
        );
        assert_eq!(bad(&ok, &[dof(1, 3)], 60.0, 5.0), (C::DofAxis, 0));
        assert_eq!(
            bad(&ok, &[dof(1, 2), dof(0, 2), dof(1, 2)], 60.0, 5.0),
            (C::DuplicateDof, 2)
        );
        let flipped = Dof {
            lower: 0.5,
            upper: 0.4,
            ..dof(1, 0)
        };
        assert_eq!(bad(&ok, &[flipped], 60.0, 5.0), (C::DofLimits, 0));
        let nan = Dof {
            upper: f64::NAN,
            ..dof(1, 0)
        };
        assert_eq!(bad(&ok, &[nan], 60.0, 5.0), (C::DofLimits, 0));
        let many: Vec<Joint<f64>> = (0..65u16)
            .map(|j| joint(j.checked_sub(1), [0.0; 3]))
            .collect();
        assert_eq!(bad(&many, &[], 60.0, 5.0), (C::TooManyJoints, 64));
        let wide: Vec<Joint<f64>> = (0..22u16)
            .map(|j| joint(j.checked_sub(1), [0.0; 3]))
            .collect();
        let dofs: Vec<Dof<f64>> = (0..65u16).map(|d| dof(d / 3, (d % 3) as u8)).collect();
        assert_eq!(bad(&wide, &dofs, 60.0, 5.0), (C::TooManyDofs, 64));
        // Equal limits are a fixed joint, not an error.
        let fixed = Dof {
            lower: 0.2,
            upper: 0.2,
            ..dof(1, 0)
        };
        assert!(Skeleton::new(ok, [fixed], 60.0, 5.0).is_ok());
        // FK refuses slices of the wrong length.
        let s = chain();
        let (mut p, mut g) = ([0.0; 9], [0.0; 27]);
        assert!(s.forward_kinematics(&[0.0; 3], &mut p, &mut g).is_err());
        assert!(s
            .forward_kinematics(&[0.0; 4], &mut p[..6], &mut g)
            .is_err());
    }
}
