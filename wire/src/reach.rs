//! Reach mode (mode 2): the OMG reaching loop (`Reach<f32, W>` over the
//! runtime) on the device. The image's records start with a **setup**
//! (the frame layout, the cost mode and the first frame `X`), then one
//! **target record** per frame; the output file holds one **frame record**
//! per frame. Specified in `docs/firmware.md` ("Reach mode").
//!
//! The layout travels in the image because the blob does not carry it
//! (it comes from the model's `config.json`, which the host reads); so do
//! a joint-velocity model's pose form, skeleton and start state (joint
//! angles and velocities), in a section of fixed size
//! ([`SKELETON_SECTION_LEN`]: room for [`MAX_JOINTS`] joints and
//! [`MAX_DOFS`] DOFs) so that every field sits at a fixed offset.

use core::ops::Range;

use phasegate_controller::reach::{Dof, Joint, PoseForm, Skeleton, MAX_DOFS, MAX_JOINTS, MAX_KEY};
use phasegate_controller::{CostMode, ReachLayout, Target};

use crate::{put_u32, u32_at};

/// Hands whose targets a target record carries (key joints 0 and 1).
pub const HANDS: usize = 2;
/// f32 of one hand's target: position, forward, up.
pub const TARGET_VALUES: usize = 9;
/// Bytes of a reach-mode input record: a flags word (bit `h`: set hand
/// `h`'s target this frame), then both hands' targets.
pub const TARGET_RECORD_LEN: usize = 4 + 4 * HANDS * TARGET_VALUES;
/// Bytes of the layout part of the setup (mode, key joints, ranges,
/// output blocks).
pub const LAYOUT_LEN: usize = 104;
/// Bytes of one joint in the skeleton section: parent i32 (-1: a root),
/// offset 3 f32.
pub const JOINT_LEN: usize = 16;
/// Bytes of one DOF in the skeleton section: joint u16, axis u8, a zero
/// byte, lower and upper f32.
pub const DOF_LEN: usize = 12;
/// Bytes of the pose-form section: form u32 (0 absolute, 1 joint
/// velocity), the `u` and velocity ranges, J, D, fps and a_max (f32),
/// then [`MAX_JOINTS`] joints, [`MAX_DOFS`] DOFs, [`MAX_DOFS`] f32 of
/// `q0` and of `v0` (zero past J and D, all zero for an absolute model).
pub const SKELETON_SECTION_LEN: usize = 36 + MAX_JOINTS * JOINT_LEN + MAX_DOFS * (DOF_LEN + 8);
/// Bytes of the setup before the first frame's `width` f32.
pub const SETUP_HEAD_LEN: usize = LAYOUT_LEN + SKELETON_SECTION_LEN;
/// Offsets within the setup of the skeleton section's parts.
const JOINTS_AT: usize = LAYOUT_LEN + 36;
const DOFS_AT: usize = JOINTS_AT + MAX_JOINTS * JOINT_LEN;
const Q0_AT: usize = DOFS_AT + MAX_DOFS * DOF_LEN;
const V0_AT: usize = Q0_AT + 4 * MAX_DOFS;
/// Bytes of a reach-mode output record before the frame's f32: network
/// ticks, frame ticks, frame index, target outcomes.
pub const FRAME_RECORD_HEAD_LEN: usize = 16;

/// Bytes of the setup of a frame of `width` values.
pub fn setup_len(width: usize) -> usize {
    SETUP_HEAD_LEN + 4 * width
}

/// Bytes of a reach-mode output record of a frame of `width` values.
pub fn frame_record_len(width: usize) -> usize {
    FRAME_RECORD_HEAD_LEN + 4 * width
}

fn mode_u32(mode: CostMode) -> u32 {
    match mode {
        CostMode::Grounded => 0,
        CostMode::Faithful => 1,
    }
}

fn put_range(b: &mut [u8], at: usize, r: &Range<usize>) {
    put_u32(b, at, r.start as u32);
    put_u32(b, at + 4, r.end as u32);
}

fn range_at(b: &[u8], at: usize) -> Range<usize> {
    u32_at(b, at) as usize..u32_at(b, at + 4) as usize
}

/// A joint-velocity model's skeleton and start state, as the host sends
/// them.
#[derive(Clone, Copy, Debug)]
pub struct DofStart<'a> {
    /// The rig.
    pub skeleton: &'a Skeleton<f32>,
    /// Start joint angles, one per DOF, radians.
    pub q0: &'a [f32],
    /// Start joint velocities, one per DOF, rad/s.
    pub v0: &'a [f32],
}

fn put_f32(b: &mut [u8], at: usize, v: f32) {
    put_u32(b, at, v.to_bits());
}

fn f32_at(b: &[u8], at: usize) -> f32 {
    f32::from_bits(u32_at(b, at))
}

/// The setup's bytes (`setup_len(first.len())` of them): cost mode u32
/// (0 grounded, 1 faithful), key joints K u32, 8 u16 key joint indices
/// (unused ones 0), the pos, rot, cost and target ranges (start, end u32
/// each), the three `(output range, frame range)` blocks, the pose-form
/// section ([`SKELETON_SECTION_LEN`] bytes; `dofs` for a joint-velocity
/// layout), then `first` (`docs/firmware.md`, "Reach mode", has the
/// table). `None` when `buf` has the wrong length, the layout more than
/// [`MAX_KEY`] key joints, `dofs` is given for an absolute layout or
/// missing for a joint-velocity one, or `q0` / `v0` are not one value per
/// DOF.
pub fn encode_setup(
    layout: &ReachLayout,
    mode: CostMode,
    first: &[f32],
    dofs: Option<&DofStart<'_>>,
    buf: &mut [u8],
) -> Option<()> {
    if buf.len() != setup_len(first.len()) || layout.key_joints.len() > MAX_KEY {
        return None;
    }
    buf.fill(0);
    match (&layout.pose, dofs) {
        (PoseForm::Absolute, None) => {}
        (PoseForm::DofVelocity { out, vel }, Some(d)) => {
            let (joints, dof) = (d.skeleton.joints(), d.skeleton.dofs());
            if d.q0.len() != dof.len() || d.v0.len() != dof.len() {
                return None;
            }
            put_u32(buf, LAYOUT_LEN, 1);
            put_range(buf, LAYOUT_LEN + 4, out);
            put_range(buf, LAYOUT_LEN + 12, vel);
            put_u32(buf, LAYOUT_LEN + 20, joints.len() as u32);
            put_u32(buf, LAYOUT_LEN + 24, dof.len() as u32);
            put_f32(buf, LAYOUT_LEN + 28, d.skeleton.fps());
            put_f32(buf, LAYOUT_LEN + 32, d.skeleton.a_max());
            for (i, j) in joints.iter().enumerate() {
                let at = JOINTS_AT + JOINT_LEN * i;
                put_u32(buf, at, j.parent.map_or(-1, i32::from) as u32);
                for (k, &o) in j.offset.iter().enumerate() {
                    put_f32(buf, at + 4 + 4 * k, o);
                }
            }
            for (i, f) in dof.iter().enumerate() {
                let at = DOFS_AT + DOF_LEN * i;
                crate::put_u16(buf, at, f.joint);
                *buf.get_mut(at + 2)? = f.axis;
                put_f32(buf, at + 4, f.lower);
                put_f32(buf, at + 8, f.upper);
            }
            for (i, (&q, &v)) in d.q0.iter().zip(d.v0).enumerate() {
                put_f32(buf, Q0_AT + 4 * i, q);
                put_f32(buf, V0_AT + 4 * i, v);
            }
        }
        _ => return None,
    }
    put_u32(buf, 0, mode_u32(mode));
    put_u32(buf, 4, layout.key_joints.len() as u32);
    for (i, &j) in layout.key_joints.iter().enumerate() {
        crate::put_u16(buf, 8 + 2 * i, j);
    }
    for (i, r) in [&layout.pos, &layout.rot, &layout.cost, &layout.target]
        .into_iter()
        .enumerate()
    {
        put_range(buf, 24 + 8 * i, r);
    }
    for (i, (o, f)) in layout.blocks.iter().enumerate() {
        put_range(buf, 56 + 16 * i, o);
        put_range(buf, 64 + 16 * i, f);
    }
    for (d, v) in buf
        .get_mut(SETUP_HEAD_LEN..)?
        .chunks_exact_mut(4)
        .zip(first)
    {
        d.copy_from_slice(&v.to_bits().to_le_bytes());
    }
    Some(())
}

/// A setup, read: the layout (of frames `width` wide), the cost mode,
/// a joint-velocity model's skeleton section and the first frame's bytes
/// (decode with [`read_f32`]).
pub struct Setup<'a> {
    /// The frame layout (not yet checked against the network:
    /// `Reach::new` does that).
    pub layout: ReachLayout,
    /// Grounded or faithful.
    pub mode: CostMode,
    /// The skeleton and start state of a joint-velocity layout.
    pub dofs: Option<DofSetup<'a>>,
    /// `width` f32, raw bits.
    pub first: &'a [u8],
}

/// A setup's skeleton section, read in place: the counts and rates, and
/// the joints, DOFs and start state on demand (the skeleton is checked by
/// `Skeleton::new`, which the device calls with [`DofSetup::joints`] and
/// [`DofSetup::dofs`]).
#[derive(Clone, Copy, Debug)]
pub struct DofSetup<'a> {
    head: &'a [u8],
    /// Joints J (at most [`MAX_JOINTS`]).
    pub joints: usize,
    /// DOFs D (at most [`MAX_DOFS`]).
    pub dof_count: usize,
    /// Frames per second.
    pub fps: f32,
    /// The joints' acceleration limit, rad/s^2.
    pub a_max: f32,
}

impl DofSetup<'_> {
    /// The J joints.
    pub fn joints(&self) -> impl Iterator<Item = Joint<f32>> + '_ {
        (0..self.joints).map(|i| {
            let at = JOINTS_AT + JOINT_LEN * i;
            Joint {
                parent: u16::try_from(u32_at(self.head, at) as i32).ok(),
                offset: [1, 2, 3].map(|k| f32_at(self.head, at + 4 * k)),
            }
        })
    }

    /// The D DOFs.
    pub fn dofs(&self) -> impl Iterator<Item = Dof<f32>> + '_ {
        (0..self.dof_count).map(|i| {
            let at = DOFS_AT + DOF_LEN * i;
            Dof {
                joint: crate::u16_at(self.head, at),
                axis: self.head.get(at + 2).copied().unwrap_or(u8::MAX),
                lower: f32_at(self.head, at + 4),
                upper: f32_at(self.head, at + 8),
            }
        })
    }

    /// Writes `q0` into `q` and `v0` into `v`; `None` unless both hold
    /// exactly D values.
    pub fn start(&self, q: &mut [f32], v: &mut [f32]) -> Option<()> {
        if q.len() != self.dof_count || v.len() != self.dof_count {
            return None;
        }
        for (i, (q, v)) in q.iter_mut().zip(v).enumerate() {
            *q = f32_at(self.head, Q0_AT + 4 * i);
            *v = f32_at(self.head, V0_AT + 4 * i);
        }
        Some(())
    }
}

/// Reads the setup at the start of `records` for frames of `width` values;
/// returns it and the target records after it. `None` when it is cut
/// short, names an unknown cost mode or pose form, more than [`MAX_KEY`]
/// key joints, more than [`MAX_JOINTS`] joints or [`MAX_DOFS`] DOFs, a
/// parent other than -1 or a joint index, or a non-zero byte in the
/// skeleton section of an absolute layout's setup.
pub fn parse_setup(records: &[u8], width: usize) -> Option<(Setup<'_>, &[u8])> {
    let (head, rest) = records.split_at_checked(SETUP_HEAD_LEN)?;
    let (first, targets) = rest.split_at_checked(width.checked_mul(4)?)?;
    let mode = match u32_at(head, 0) {
        0 => CostMode::Grounded,
        1 => CostMode::Faithful,
        _ => return None,
    };
    let k = u32_at(head, 4) as usize;
    if k > MAX_KEY {
        return None;
    }
    let mut key_joints = heapless::Vec::new();
    for i in 0..k {
        key_joints.push(crate::u16_at(head, 8 + 2 * i)).ok()?;
    }
    let block = |i: usize| (range_at(head, 56 + 16 * i), range_at(head, 64 + 16 * i));
    let section = head.get(LAYOUT_LEN..)?;
    let (pose, dofs) = match u32_at(head, LAYOUT_LEN) {
        0 if section.iter().all(|&b| b == 0) => (PoseForm::Absolute, None),
        1 => {
            let d = DofSetup {
                head,
                joints: u32_at(head, LAYOUT_LEN + 20) as usize,
                dof_count: u32_at(head, LAYOUT_LEN + 24) as usize,
                fps: f32_at(head, LAYOUT_LEN + 28),
                a_max: f32_at(head, LAYOUT_LEN + 32),
            };
            if d.joints > MAX_JOINTS || d.dof_count > MAX_DOFS {
                return None;
            }
            let parent_ok = |i: usize| {
                let p = u32_at(head, JOINTS_AT + JOINT_LEN * i) as i32;
                p == -1 || u16::try_from(p).is_ok()
            };
            if !(0..d.joints).all(parent_ok) {
                return None;
            }
            let pose = PoseForm::DofVelocity {
                out: range_at(head, LAYOUT_LEN + 4),
                vel: range_at(head, LAYOUT_LEN + 12),
            };
            (pose, Some(d))
        }
        _ => return None,
    };
    let layout = ReachLayout {
        width,
        pos: range_at(head, 24),
        rot: range_at(head, 32),
        cost: range_at(head, 40),
        target: range_at(head, 48),
        key_joints,
        blocks: [block(0), block(1), block(2)],
        pose,
    };
    Some((
        Setup {
            layout,
            mode,
            dofs,
            first,
        },
        targets,
    ))
}

/// Decodes the f32 of `bytes` (raw bits, little-endian) into `out`; `None`
/// unless `bytes` holds exactly `out.len()` of them.
pub fn read_f32(bytes: &[u8], out: &mut [f32]) -> Option<()> {
    if bytes.len() != 4 * out.len() {
        return None;
    }
    for (i, v) in out.iter_mut().enumerate() {
        *v = f32::from_bits(u32_at(bytes, 4 * i));
    }
    Some(())
}

/// Writes one target record: hand `h`'s target is set this frame when
/// `targets[h]` is `Some` (`None`: written as zeros, not set).
pub fn encode_target_record(targets: &[Option<Target<f32>>; HANDS], out: &mut impl Extend<u8>) {
    let flags = (targets.iter().enumerate())
        .filter(|(_, t)| t.is_some())
        .fold(0u32, |f, (h, _)| f | 1 << h);
    out.extend(flags.to_le_bytes());
    for t in targets {
        let zero = Target {
            position: [0.0; 3],
            forward: [0.0; 3],
            up: [0.0; 3],
        };
        let t = t.unwrap_or(zero);
        for v in t.position.iter().chain(&t.forward).chain(&t.up) {
            out.extend(v.to_bits().to_le_bytes());
        }
    }
}

/// Reads one target record; `None` unless it is [`TARGET_RECORD_LEN`]
/// bytes with no flag bits past the hands.
pub fn read_target_record(record: &[u8]) -> Option<[Option<Target<f32>>; HANDS]> {
    if record.len() != TARGET_RECORD_LEN {
        return None;
    }
    let flags = u32_at(record, 0);
    if flags >> HANDS != 0 {
        return None;
    }
    let v = |h: usize, i: usize| f32::from_bits(u32_at(record, 4 + 4 * (TARGET_VALUES * h + i)));
    let target = |h: usize| {
        (flags & 1 << h != 0).then(|| Target {
            position: [v(h, 0), v(h, 1), v(h, 2)],
            forward: [v(h, 3), v(h, 4), v(h, 5)],
            up: [v(h, 6), v(h, 7), v(h, 8)],
        })
    };
    Some([target(0), target(1)])
}

/// What became of one hand's target in a frame.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum TargetOutcome {
    /// The record did not set it (0).
    Kept,
    /// Set (1).
    Set,
    /// Refused by `Reach::set_target` with `Error::BadTarget { field }`
    /// (2; the field in the high byte); the previous target holds.
    Refused {
        /// 0-2 position, 3-5 forward, 6-8 up; 255 no such key joint.
        field: u8,
    },
}

impl TargetOutcome {
    fn to_u16(self) -> u16 {
        match self {
            TargetOutcome::Kept => 0,
            TargetOutcome::Set => 1,
            TargetOutcome::Refused { field } => 2 | u16::from(field) << 8,
        }
    }

    fn from_u16(v: u16) -> Option<TargetOutcome> {
        let field = (v >> 8) as u8;
        match (v & 0xFF, field) {
            (0, 0) => Some(TargetOutcome::Kept),
            (1, 0) => Some(TargetOutcome::Set),
            (2, field) => Some(TargetOutcome::Refused { field }),
            _ => None,
        }
    }
}

/// One reach-mode output record's head.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
pub struct FrameHead {
    /// SysTick ticks in the network (`Runtime::run`: quantise, infer,
    /// de-quantise).
    pub network_ticks: u32,
    /// SysTick ticks of the whole frame: setting the targets and
    /// `Reach::step`.
    pub frame_ticks: u32,
    /// Frame index (0: the first step after the setup's frame).
    pub frame: u32,
    /// Each hand's target outcome.
    pub targets: [TargetOutcome; HANDS],
}

/// Encodes one reach-mode output record into `buf` (length
/// [`frame_record_len`]`(frame.len())`): the head, then the frame `X`
/// after the step as raw f32 bits; `None` on a length mismatch.
pub fn encode_frame_record(head: &FrameHead, frame: &[f32], buf: &mut [u8]) -> Option<()> {
    if buf.len() != frame_record_len(frame.len()) {
        return None;
    }
    put_u32(buf, 0, head.network_ticks);
    put_u32(buf, 4, head.frame_ticks);
    put_u32(buf, 8, head.frame);
    let [a, b] = head.targets;
    put_u32(buf, 12, u32::from(a.to_u16()) | u32::from(b.to_u16()) << 16);
    for (d, v) in buf
        .get_mut(FRAME_RECORD_HEAD_LEN..)?
        .chunks_exact_mut(4)
        .zip(frame)
    {
        d.copy_from_slice(&v.to_bits().to_le_bytes());
    }
    Some(())
}

/// Decodes one reach-mode output record into its head and `frame`; `None`
/// on a length mismatch or an unknown outcome.
pub fn decode_frame_record(buf: &[u8], frame: &mut [f32]) -> Option<FrameHead> {
    if buf.len() != frame_record_len(frame.len()) {
        return None;
    }
    let t = u32_at(buf, 12);
    let head = FrameHead {
        network_ticks: u32_at(buf, 0),
        frame_ticks: u32_at(buf, 4),
        frame: u32_at(buf, 8),
        targets: [
            TargetOutcome::from_u16(t as u16)?,
            TargetOutcome::from_u16((t >> 16) as u16)?,
        ],
    };
    read_f32(buf.get(FRAME_RECORD_HEAD_LEN..)?, frame)?;
    Some(head)
}

#[cfg(test)]
mod tests {
    use super::*;

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

    /// Setups, target records and frame records read back what was
    /// written; damaged ones are refused.
    #[test]
    fn reach_records_round_trip() {
        let first: Vec<f32> = (0..35).map(|i| i as f32 * 0.5).collect();
        let mut setup = vec![0u8; setup_len(35)];
        encode_setup(&layout(), CostMode::Faithful, &first, None, &mut setup).unwrap();
        let t = Target {
            position: [0.1, f32::NAN, 0.3],
            forward: [0.0, 0.0, 1.0],
            up: [0.0, 1.0, 0.0],
        };
        let mut records = setup.clone();
        encode_target_record(&[None, Some(t)], &mut records);
        let (s, rest) = parse_setup(&records, 35).unwrap();
        assert_eq!(s.layout, layout());
        assert!(s.dofs.is_none());
        assert_eq!(s.mode, CostMode::Faithful);
        let mut back = [0f32; 35];
        read_f32(s.first, &mut back).unwrap();
        assert_eq!(&back[..], &first[..]);
        let [a, b] = read_target_record(rest).unwrap();
        assert_eq!(a, None);
        let b = b.unwrap();
        assert!(b.position[1].is_nan() && b.forward == t.forward);
        let mut bad = rest.to_vec();
        bad[0] = 4;
        assert!(read_target_record(&bad).is_none());
        assert!(parse_setup(&setup[..50], 35).is_none());
        let mut bad_mode = setup.clone();
        bad_mode[0] = 2;
        assert!(parse_setup(&bad_mode, 35).is_none());

        let head = FrameHead {
            network_ticks: 7,
            frame_ticks: 9,
            frame: 3,
            targets: [TargetOutcome::Set, TargetOutcome::Refused { field: 255 }],
        };
        let mut rec = vec![0u8; frame_record_len(35)];
        encode_frame_record(&head, &first, &mut rec).unwrap();
        let mut got = [0f32; 35];
        assert_eq!(decode_frame_record(&rec, &mut got), Some(head));
        assert_eq!(&got[..], &first[..]);
        rec[13] = 0x7;
        assert_eq!(decode_frame_record(&rec, &mut got), None);
    }

    /// A joint-velocity setup carries the pose form, the skeleton and the
    /// start state bit for bit; the form and the section must agree.
    #[test]
    fn a_dof_setup_round_trips_its_skeleton_and_start() {
        // J = 2 (pos 2..8, rot 8..20, vel 20..26), K = 1; output [phase 2,
        // u 3, cost 6].
        let l = ReachLayout {
            width: 41,
            pos: 2..8,
            rot: 8..20,
            cost: 26..32,
            target: 32..41,
            key_joints: heapless::Vec::from_slice(&[1]).unwrap(),
            blocks: [(0..2, 0..2), (2..2, 2..2), (5..11, 26..32)],
            pose: PoseForm::DofVelocity {
                out: 2..5,
                vel: 20..26,
            },
        };
        let sk = Skeleton::new(
            [
                Joint {
                    parent: None,
                    offset: [0.0, 1.04, 0.0],
                },
                Joint {
                    parent: Some(0),
                    offset: [0.1, 0.2, -0.3],
                },
            ],
            [(0, 1), (1, 0), (1, 2)].map(|(joint, axis)| Dof {
                joint,
                axis,
                lower: -0.0875,
                upper: 0.3125,
            }),
            60.0,
            5.0,
        )
        .unwrap();
        let (q0, v0) = ([0.001f32, -0.002, 0.0], [0.06f32, -0.12, f32::MIN_POSITIVE]);
        let start = DofStart {
            skeleton: &sk,
            q0: &q0,
            v0: &v0,
        };
        let first: Vec<f32> = (0..41).map(|i| i as f32 * 0.25).collect();
        let mut setup = vec![0u8; setup_len(41)];
        encode_setup(&l, CostMode::Grounded, &first, Some(&start), &mut setup).unwrap();
        let (s, rest) = parse_setup(&setup, 41).unwrap();
        assert!(rest.is_empty());
        assert_eq!(s.layout, l);
        let d = s.dofs.unwrap();
        let back = Skeleton::new(d.joints(), d.dofs(), d.fps, d.a_max).unwrap();
        assert_eq!(back, sk);
        let (mut q, mut v) = ([0f32; 3], [0f32; 3]);
        d.start(&mut q, &mut v).unwrap();
        assert_eq!((q, v), (q0, v0));
        assert!(d.start(&mut q[..2], &mut v).is_none());
        let mut f = [0f32; 41];
        read_f32(s.first, &mut f).unwrap();
        assert_eq!(&f[..], &first[..]);
        // The form and the section must agree.
        assert!(encode_setup(&l, CostMode::Grounded, &first, None, &mut setup).is_none());
        assert!(encode_setup(
            &layout(),
            CostMode::Grounded,
            &first[..35],
            Some(&start),
            &mut vec![0; setup_len(35)]
        )
        .is_none());
        let short = DofStart {
            q0: &q0[..2],
            ..start
        };
        assert!(encode_setup(&l, CostMode::Grounded, &first, Some(&short), &mut setup).is_none());
        // Damaged: an unknown form, too many joints, a parent below -1, and
        // a skeleton byte in an absolute setup.
        encode_setup(&l, CostMode::Grounded, &first, Some(&start), &mut setup).unwrap();
        for (at, v) in [
            (LAYOUT_LEN, 2u32),
            (LAYOUT_LEN + 20, 65),
            (JOINTS_AT, (-2i32) as u32),
        ] {
            let mut bad = setup.clone();
            put_u32(&mut bad, at, v);
            assert!(parse_setup(&bad, 41).is_none(), "offset {at}");
        }
        let mut abs = vec![0u8; setup_len(35)];
        encode_setup(&layout(), CostMode::Grounded, &first[..35], None, &mut abs).unwrap();
        abs[Q0_AT] = 1;
        assert!(parse_setup(&abs, 35).is_none());
        // A refused skeleton comes out as the controller's typed error.
        let mut bad = setup.clone();
        bad[DOFS_AT + DOF_LEN + 2] = 5;
        let (s, _) = parse_setup(&bad, 41).unwrap();
        let d = s.dofs.unwrap();
        assert!(matches!(
            Skeleton::new(d.joints(), d.dofs(), d.fps, d.a_max),
            Err(phasegate_controller::Error::BadSkeleton { index: 1, .. })
        ));
    }
}
