//! The host <-> firmware wire format under QEMU: one `no_std` crate
//! (`phasegate-wire`) that the firmware and host-sim both depend on, so both
//! ends read and write one definition.
//!
//! Only `core` and `phasegate`'s [`Mix`] type, no `unsafe`, no allocation.
//! All integers and floats are little-endian. Specified in
//! `docs/firmware.md`, which also says why these are fixed-length records
//! rather than postcard: frame `i` is read in place at a fixed offset, and
//! a run cut short shows in the output file's length.
//!
//! Host -> firmware: the **input image** (version 3), loaded raw at the start
//! of the HOSTIO region (memory.x) with `-device loader,file=...,force-raw=on`:
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 4 | magic `PGIN` |
//! | 4 | 2 | version (3) |
//! | 6 | 2 | header length (32): the first record starts here |
//! | 8 | 4 | frames N |
//! | 12 | 4 | input dim I |
//! | 16 | 4 | output dim O (what the host expects the model to produce) |
//! | 20 | 4 | record length: 12 + 4 I (network mode), 40 (controller mode) |
//! | 24 | 4 | CRC-32 (ISO-HDLC) of the N records |
//! | 28 | 4 | mode: 0 = network, 1 = controller, 2 = reach (any other value: [`WireError::UnknownMode`]) |
//!
//! **Network mode** (0): N records of the frame's mix (8 bytes, below),
//! phase (f32, radians), I inputs (f32, model units).
//!
//! **Controller mode** (1): the firmware runs the locomotion loop
//! (`Locomotion<f32>` over the styled runtime, reset from the model) and
//! the records carry commands instead of network inputs. I and O must be
//! the PFNN's 342 and 311 (a model of another shape is refused by the
//! firmware with `Error::NotPfnn`, exit code [`exit::NOT_PFNN`]). Each of
//! the N records is 40 bytes: the frame's mix (8 bytes, below), then the
//! `Command` as 8 f32 ([`encode_command`]):
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 8 | mix field |
//! | 8 | 8 | `velocity[0]`, `velocity[1]` (f32) |
//! | 16 | 8 | `facing[0]`, `facing[1]` (f32) |
//! | 24 | 16 | `gait.stand`, `gait.walk`, `gait.jog`, `gait.crouch` (f32) |
//!
//! The f32 are raw bits: the firmware rebuilds the exact `Command` (NaN
//! and infinities included, which `Locomotion::step` refuses with
//! `BadCommand`: exit code [`exit::FRAME_ERROR`]).
//!
//! **Reach mode** (2): the firmware runs the OMG reaching loop
//! (`Reach<f32, W>` over the runtime). I is the frame width n (the
//! network's inputs), O the network's outputs. The records start with a
//! setup (layout, cost mode, the pose form with a joint-velocity model's
//! skeleton and start joint angles and velocities, first frame;
//! [`reach::encode_setup`], [`reach::setup_len`]`(I)` bytes, counted in
//! the CRC), then N target
//! records of [`reach::TARGET_RECORD_LEN`] bytes (a flags word, both
//! hands' position, forward, up as f32). The output records are
//! [`reach::frame_record_len`]`(I)` bytes: network ticks, frame ticks,
//! frame index, the hands' target outcomes, then the whole frame `X`
//! after the step. See the [`reach`] module.
//!
//! A controller-mode image may be followed by a 16-byte deadline block
//! (frame budget and overrun policy, [`encode_deadline`]; the table is in
//! `src/deadline.rs` and `docs/deadline.md`).
//!
//! The **mix field** says which style adapters the frame uses
//! ([`Mix`]; the firmware calls `Runtime::set_mix` with it before the
//! frame). Style ids are the order of the style blobs in the STYLES region
//! (0 = first):
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 1 | kind: 0 = `Base` (no adapter), 1 = `One(a)`, 2 = `Blend { from: a, to: b, weight }` |
//! | 1 | 1 | a: style id (`One`, `Blend`), else 0 |
//! | 2 | 1 | b: style id (`Blend`), else 0 |
//! | 3 | 1 | reserved, 0 |
//! | 4 | 2 | weight (`Blend`): U1F15 bits, 0 ..= 0x8000 (0.0 ..= 1.0), else 0 |
//! | 6 | 2 | reserved, 0 |
//!
//! Any other kind, a non-zero byte in a field the kind does not use, or a
//! weight above 0x8000 is malformed ([`WireError::UnknownMixKind`],
//! [`WireError::BadMixField`]); a well-formed id of a style that was not
//! loaded is refused by the runtime (`Error::UnknownStyle`). Either way the
//! firmware stops at that frame with [`exit::FRAME_ERROR`].
//!
//! Firmware -> host: the **output file** `phasegate-out.bin` (version 1),
//! written through semihosting in QEMU's working directory: a 32-byte header
//! (`PGOT`, version, header length, N, O, record length, the input image's
//! CRC, the mode u32 (echoed from the input image), 4 reserved bytes), N
//! records, and a 32-byte trailer (`PGND`, frames done, stack high-water
//! bytes, stack size bytes, calibration ticks, calibration instructions,
//! 8 reserved bytes).
//!
//! Network-mode records (8 + 6 O bytes): u32 inference ticks, u32
//! whole-frame ticks, O i16 quantised outputs, O f32 de-quantised outputs.
//!
//! Network mode also writes the **profile file** `phasegate-profile.bin`
//! (version 1): where each frame's time went, stage by stage. A 32-byte
//! header (`PGPF`, version, header length, N, stages per frame S, record
//! length 8 S, the input image's CRC, 8 reserved bytes), then N records of
//! S stages in frame order, 8 bytes each ([`StageTicks`]): kind u8
//! ([`StageKind`]), node u8, 2 reserved bytes, u32 SysTick ticks. A model
//! of `n` nodes has S = 2 n + 3: input, gate, then gather and op of each
//! node, then output. Hosts that do not read it lose nothing: the output
//! file is unchanged.
//!
//! Controller-mode records (16 + 4 x [`POSE_VALUES`] = 940 bytes): u32
//! network ticks (the loop's `Network::predict`: `Runtime::run`,
//! i.e. input quantisation, inference, de-quantisation), u32 frame ticks
//! (the whole `Locomotion::frame`, as the deadline timed it), u32
//! `Pose::frame`, u32 deadline [`FrameStatus`] (bit 0 overran, bit 1 held,
//! bit 2 status pin high), then the pose's 231
//! f32 as raw bits ([`encode_pose_record`]): `root_position` (3),
//! `facing` (2), `joint_positions` (31 x 3), `joint_rotations` (31 x 4,
//! `[x, y, z, w]`), `contacts` (4), `phase` (1), `gaits` (4).

#![cfg_attr(not(test), no_std)]
#![deny(missing_docs)]

use phasegate::style::BlendWeight;
use phasegate::{Mix, StyleId};
use phasegate_controller::layout::JOINTS;
use phasegate_controller::{Command, GaitWeights, Pose};

mod deadline;
pub mod reach;
pub use deadline::{
    encode_deadline, parse_deadline, FrameStatus, DEADLINE_BLOCK_LEN, DEADLINE_MAGIC,
};

/// Magic of the input image.
pub const INPUT_MAGIC: [u8; 4] = *b"PGIN";
/// Magic of the output file.
pub const OUTPUT_MAGIC: [u8; 4] = *b"PGOT";
/// Magic of the output file's trailer.
pub const TRAILER_MAGIC: [u8; 4] = *b"PGND";
/// Version of the input image (2: a mix field starts every record; 3: the
/// reach setup carries the pose form and a joint-velocity model's
/// skeleton and start state).
pub const INPUT_VERSION: u16 = 3;
/// Version of the output file.
pub const OUTPUT_VERSION: u16 = 1;
/// Bytes of a record's mix field.
pub const MIX_LEN: usize = 8;
/// Bytes of a record before its inputs: the mix field and the phase.
pub const RECORD_HEAD_LEN: usize = MIX_LEN + 4;
/// Largest blend weight on the wire: U1F15 bits of 1.0.
pub const MAX_BLEND_BITS: u16 = 0x8000;
/// Length of every header and of the trailer.
pub const HEADER_LEN: usize = 32;
/// File name of the output file, relative to QEMU's working directory.
pub const OUTPUT_FILE: &str = "phasegate-out.bin";
/// f32 values of a [`Command`] on the wire.
pub const COMMAND_VALUES: usize = 8;
/// Bytes of a controller-mode input record: the mix field and the command.
pub const COMMAND_RECORD_LEN: usize = MIX_LEN + 4 * COMMAND_VALUES;
/// f32 values of a [`Pose`] on the wire (everything but `frame`).
pub const POSE_VALUES: usize = 3 + 2 + 3 * JOINTS + 4 * JOINTS + 4 + 1 + 4;
/// Bytes of a controller-mode output record: two tick counts, the frame
/// number, the deadline's [`FrameStatus`] and the pose's f32.
pub const POSE_RECORD_LEN: usize = 16 + 4 * POSE_VALUES;

/// What the records of an input image hold.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Mode {
    /// Raw network frames: mix, phase, inputs (mode 0).
    Network,
    /// Controller commands: mix, command (mode 1).
    Controller,
    /// The reaching loop: setup, then hand targets (mode 2).
    Reach,
}

impl Mode {
    /// The mode's number on the wire.
    pub fn to_u32(self) -> u32 {
        match self {
            Mode::Network => 0,
            Mode::Controller => 1,
            Mode::Reach => 2,
        }
    }

    /// The mode with number `v`.
    pub fn from_u32(v: u32) -> Result<Mode, WireError> {
        match v {
            0 => Ok(Mode::Network),
            1 => Ok(Mode::Controller),
            2 => Ok(Mode::Reach),
            m => Err(WireError::UnknownMode(m)),
        }
    }
}

/// Why an input image or output file is refused.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum WireError {
    /// The magic is wrong: nothing (or something else) was loaded there.
    BadMagic,
    /// A version this code does not read.
    UnsupportedVersion(u16),
    /// A record's mix field has a kind other than 0 (base), 1 (one style)
    /// or 2 (blend).
    UnknownMixKind(u8),
    /// A record's mix field has a non-zero byte in a field its kind does
    /// not use, or a blend weight above 1.0 (0x8000).
    BadMixField {
        /// Offset of the offending byte within the 8-byte mix field.
        offset: u8,
    },
    /// The header length, record length or dimensions are inconsistent.
    BadHeader,
    /// The records end past the available bytes.
    Truncated {
        /// Bytes needed.
        needed: u64,
        /// Bytes available.
        available: u64,
    },
    /// The records do not match their CRC-32.
    CrcMismatch,
    /// The header's mode is not 0 (network), 1 (controller) or 2 (reach).
    UnknownMode(u32),
    /// The deadline block after the records is damaged (CRC) or names a
    /// zero budget or an unknown policy.
    BadDeadline,
}

impl core::fmt::Display for WireError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match *self {
            WireError::BadMagic => f.write_str("bad magic (nothing loaded there?)"),
            WireError::UnsupportedVersion(v) => write!(f, "unsupported version {v}"),
            WireError::UnknownMixKind(k) => write!(
                f,
                "unknown mix kind {k} (0 = base, 1 = one style, 2 = blend)"
            ),
            WireError::BadMixField { offset } => write!(
                f,
                "malformed mix field: byte {offset} must be 0 for this kind, or the blend weight exceeds 1.0"
            ),
            WireError::BadHeader => f.write_str("inconsistent header"),
            WireError::Truncated { needed, available } => {
                write!(f, "truncated: needs {needed} bytes, has {available}")
            }
            WireError::CrcMismatch => f.write_str("records do not match their CRC-32"),
            WireError::UnknownMode(m) => {
                write!(
                    f,
                    "unknown mode {m} (0 = network, 1 = controller, 2 = reach)"
                )
            }
            WireError::BadDeadline => f.write_str(
                "damaged deadline block (CRC), or a zero budget or an unknown policy",
            ),
        }
    }
}

pub(crate) fn u16_at(b: &[u8], at: usize) -> u16 {
    match b.get(at..at + 2) {
        Some(&[x, y]) => u16::from_le_bytes([x, y]),
        _ => 0,
    }
}

pub(crate) fn u32_at(b: &[u8], at: usize) -> u32 {
    match b.get(at..at + 4) {
        Some(&[x, y, z, w]) => u32::from_le_bytes([x, y, z, w]),
        _ => 0,
    }
}

pub(crate) fn put_u32(b: &mut [u8], at: usize, v: u32) {
    if let Some(d) = b.get_mut(at..at + 4) {
        d.copy_from_slice(&v.to_le_bytes());
    }
}

pub(crate) fn put_u16(b: &mut [u8], at: usize, v: u16) {
    if let Some(d) = b.get_mut(at..at + 2) {
        d.copy_from_slice(&v.to_le_bytes());
    }
}

fn check_preamble(b: &[u8], magic: [u8; 4], version: u16) -> Result<(), WireError> {
    if b.len() < HEADER_LEN {
        return Err(WireError::Truncated {
            needed: HEADER_LEN as u64,
            available: b.len() as u64,
        });
    }
    if b.get(..4) != Some(&magic[..]) {
        return Err(WireError::BadMagic);
    }
    let found = u16_at(b, 4);
    if found != version {
        return Err(WireError::UnsupportedVersion(found));
    }
    if usize::from(u16_at(b, 6)) != HEADER_LEN {
        return Err(WireError::BadHeader);
    }
    Ok(())
}

/// CRC-32/ISO-HDLC (zlib's), bitwise: small code, no table; fast enough for
/// a few MB under QEMU.
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &byte in bytes {
        crc ^= u32::from(byte);
        for _ in 0..8 {
            let mask = (crc & 1).wrapping_neg();
            crc = (crc >> 1) ^ (0xEDB8_8320 & mask);
        }
    }
    !crc
}

/// Header of the input image.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
pub struct InputHeader {
    /// Frames N.
    pub frames: u32,
    /// Inputs per frame.
    pub input_dim: u32,
    /// Outputs per frame the host expects.
    pub output_dim: u32,
    /// CRC-32 of the records.
    pub crc: u32,
    /// What the records hold.
    pub mode: Mode,
}

impl InputHeader {
    /// Bytes of one record: the mix field, the phase and the inputs
    /// (network mode), or the mix field and the command (controller mode).
    pub fn record_len(&self) -> usize {
        match self.mode {
            Mode::Network => RECORD_HEAD_LEN + 4 * self.input_dim as usize,
            Mode::Controller => COMMAND_RECORD_LEN,
            Mode::Reach => reach::TARGET_RECORD_LEN,
        }
    }

    /// Bytes before the first record (after the header): reach mode's
    /// setup, else none.
    pub fn setup_len(&self) -> u64 {
        match self.mode {
            Mode::Reach => reach::setup_len(self.input_dim as usize) as u64,
            _ => 0,
        }
    }

    /// Bytes of the whole image.
    pub fn image_len(&self) -> u64 {
        HEADER_LEN as u64 + self.setup_len() + self.frames as u64 * self.record_len() as u64
    }

    /// The 32 header bytes.
    pub fn encode(&self) -> [u8; HEADER_LEN] {
        let mut b = [0u8; HEADER_LEN];
        b[..4].copy_from_slice(&INPUT_MAGIC);
        put_u16(&mut b, 4, INPUT_VERSION);
        put_u16(&mut b, 6, HEADER_LEN as u16);
        put_u32(&mut b, 8, self.frames);
        put_u32(&mut b, 12, self.input_dim);
        put_u32(&mut b, 16, self.output_dim);
        put_u32(&mut b, 20, self.record_len() as u32);
        put_u32(&mut b, 24, self.crc);
        put_u32(&mut b, 28, self.mode.to_u32());
        b
    }

    /// Parses and checks the header at the start of `region` (which may be
    /// longer than the image); returns it and the records' bytes (in reach
    /// mode, the setup and the records), CRC checked.
    pub fn parse(region: &[u8]) -> Result<(InputHeader, &[u8]), WireError> {
        check_preamble(region, INPUT_MAGIC, INPUT_VERSION)?;
        let h = InputHeader {
            frames: u32_at(region, 8),
            input_dim: u32_at(region, 12),
            output_dim: u32_at(region, 16),
            crc: u32_at(region, 24),
            mode: Mode::from_u32(u32_at(region, 28))?,
        };
        if h.input_dim == 0
            || h.input_dim > 0x0100_0000
            || u32_at(region, 20) as usize != h.record_len()
        {
            return Err(WireError::BadHeader);
        }
        let end = h.image_len();
        if end > region.len() as u64 {
            return Err(WireError::Truncated {
                needed: end,
                available: region.len() as u64,
            });
        }
        let records = region
            .get(HEADER_LEN..end as usize)
            .ok_or(WireError::BadHeader)?;
        if crc32(records) != h.crc {
            return Err(WireError::CrcMismatch);
        }
        Ok((h, records))
    }
}

/// One input record, read: the raw mix field, and the phase in radians.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InputRecord {
    /// The mix field's bytes (decode with [`decode_mix`]).
    pub mix: [u8; MIX_LEN],
    /// Phase, radians.
    pub phase: f32,
}

/// Reads one input record: returns its mix field and phase and writes the
/// inputs to `inputs` (whose length must be the input dim); `None` on a
/// length mismatch.
pub fn read_record(record: &[u8], inputs: &mut [f32]) -> Option<InputRecord> {
    if record.len() != RECORD_HEAD_LEN + 4 * inputs.len() {
        return None;
    }
    let mix = record.get(..MIX_LEN)?.try_into().ok()?;
    let phase = f32::from_bits(u32_at(record, MIX_LEN));
    for (i, x) in inputs.iter_mut().enumerate() {
        *x = f32::from_bits(u32_at(record, RECORD_HEAD_LEN + 4 * i));
    }
    Some(InputRecord { mix, phase })
}

/// Writes one input record (mix field, phase, inputs) to the end of `out`.
pub fn encode_input_record(
    mix: &[u8; MIX_LEN],
    phase: f32,
    inputs: &[f32],
    out: &mut impl Extend<u8>,
) {
    out.extend(mix.iter().copied());
    out.extend(phase.to_bits().to_le_bytes());
    for x in inputs {
        out.extend(x.to_bits().to_le_bytes());
    }
}

/// The mix field of `mix`. Encodes what it is given: a blend weight above
/// 1.0 is written as is (and refused by [`decode_mix`]).
pub fn encode_mix(mix: Mix) -> [u8; MIX_LEN] {
    let mut b = [0u8; MIX_LEN];
    match mix {
        Mix::Base => {}
        Mix::One(StyleId(a)) => {
            b[0] = 1;
            b[1] = a;
        }
        Mix::Blend {
            from: StyleId(a),
            to: StyleId(c),
            weight,
        } => {
            b[0] = 2;
            b[1] = a;
            b[2] = c;
            put_u16(&mut b, 4, weight.to_bits());
        }
    }
    b
}

/// Decodes and checks a mix field (see the table in the module docs).
pub fn decode_mix(b: &[u8; MIX_LEN]) -> Result<Mix, WireError> {
    let [kind, a, c, ..] = *b;
    let weight = u16_at(b, 4);
    // Bytes the kind uses; every other byte must be 0.
    let used: [bool; MIX_LEN] = match kind {
        0 => [true, false, false, false, false, false, false, false],
        1 => [true, true, false, false, false, false, false, false],
        2 => [true, true, true, false, true, true, false, false],
        k => return Err(WireError::UnknownMixKind(k)),
    };
    for (offset, (&byte, &is_used)) in b.iter().zip(&used).enumerate() {
        if byte != 0 && !is_used {
            return Err(WireError::BadMixField {
                offset: offset as u8,
            });
        }
    }
    Ok(match kind {
        0 => Mix::Base,
        1 => Mix::One(StyleId(a)),
        _ => {
            if weight > MAX_BLEND_BITS {
                return Err(WireError::BadMixField { offset: 4 });
            }
            Mix::Blend {
                from: StyleId(a),
                to: StyleId(c),
                weight: BlendWeight::from_bits(weight),
            }
        }
    })
}

/// The command's 8 f32, in wire order (see the module docs): velocity,
/// facing, then the gait weights stand, walk, jog, crouch.
pub fn command_values(c: &Command) -> [f32; COMMAND_VALUES] {
    let g = &c.gait;
    [
        c.velocity[0],
        c.velocity[1],
        c.facing[0],
        c.facing[1],
        g.stand,
        g.walk,
        g.jog,
        g.crouch,
    ]
}

/// The 32 bytes of `command` (8 f32, raw bits, little-endian).
pub fn encode_command(command: &Command) -> [u8; 4 * COMMAND_VALUES] {
    let mut b = [0u8; 4 * COMMAND_VALUES];
    for (d, v) in b.chunks_exact_mut(4).zip(command_values(command)) {
        d.copy_from_slice(&v.to_bits().to_le_bytes());
    }
    b
}

/// The command in `b` (at least 32 bytes; missing bytes read as 0).
pub fn decode_command(b: &[u8]) -> Command {
    let v = |i: usize| f32::from_bits(u32_at(b, 4 * i));
    Command {
        velocity: [v(0), v(1)],
        facing: [v(2), v(3)],
        gait: GaitWeights {
            stand: v(4),
            walk: v(5),
            jog: v(6),
            crouch: v(7),
        },
    }
}

/// Writes one controller-mode input record (mix field, command) to the end
/// of `out`.
pub fn encode_command_record(mix: &[u8; MIX_LEN], command: &Command, out: &mut impl Extend<u8>) {
    out.extend(mix.iter().copied());
    out.extend(encode_command(command));
}

/// Reads one controller-mode input record: its raw mix field and command;
/// `None` unless it is [`COMMAND_RECORD_LEN`] bytes.
pub fn read_command_record(record: &[u8]) -> Option<([u8; MIX_LEN], Command)> {
    if record.len() != COMMAND_RECORD_LEN {
        return None;
    }
    let mix = record.get(..MIX_LEN)?.try_into().ok()?;
    Some((mix, decode_command(record.get(MIX_LEN..)?)))
}

/// The pose's f32 in wire order: root position, facing, joint positions,
/// joint rotations, contacts, phase, gaits ([`POSE_VALUES`] of them).
pub fn pose_values(p: &Pose<f32>) -> impl Iterator<Item = &f32> {
    p.root_position
        .iter()
        .chain(&p.facing)
        .chain(p.joint_positions.iter().flatten())
        .chain(p.joint_rotations.iter().flatten())
        .chain(&p.contacts)
        .chain(core::iter::once(&p.phase))
        .chain(&p.gaits)
}

/// The pose's f32, mutably, in wire order.
fn pose_values_mut(p: &mut Pose<f32>) -> impl Iterator<Item = &mut f32> {
    p.root_position
        .iter_mut()
        .chain(&mut p.facing)
        .chain(p.joint_positions.iter_mut().flatten())
        .chain(p.joint_rotations.iter_mut().flatten())
        .chain(&mut p.contacts)
        .chain(core::iter::once(&mut p.phase))
        .chain(&mut p.gaits)
}

/// Encodes one controller-mode output record into `buf` (length
/// [`POSE_RECORD_LEN`]): network ticks, frame ticks, the frame number, the
/// deadline status and the pose; `None` on a length mismatch.
pub fn encode_pose_record(
    head: RecordHead,
    status: FrameStatus,
    pose: &Pose<f32>,
    buf: &mut [u8],
) -> Option<()> {
    if buf.len() != POSE_RECORD_LEN {
        return None;
    }
    put_u32(buf, 0, head.infer_ticks);
    put_u32(buf, 4, head.frame_ticks);
    put_u32(buf, 8, pose.frame);
    put_u32(buf, 12, status.to_u32());
    for (d, v) in buf
        .get_mut(16..)?
        .chunks_exact_mut(4)
        .zip(pose_values(pose))
    {
        d.copy_from_slice(&v.to_bits().to_le_bytes());
    }
    Some(())
}

/// Decodes one controller-mode output record: its head (network ticks,
/// frame ticks), the deadline status and the pose; `None` on a length
/// mismatch or a status word with unknown bits.
pub fn decode_pose_record(buf: &[u8]) -> Option<(RecordHead, FrameStatus, Pose<f32>)> {
    if buf.len() != POSE_RECORD_LEN {
        return None;
    }
    let head = RecordHead {
        infer_ticks: u32_at(buf, 0),
        frame_ticks: u32_at(buf, 4),
    };
    let status = FrameStatus::from_u32(u32_at(buf, 12))?;
    let mut pose = Pose::zero();
    pose.frame = u32_at(buf, 8);
    for (i, v) in pose_values_mut(&mut pose).enumerate() {
        *v = f32::from_bits(u32_at(buf, 16 + 4 * i));
    }
    Some((head, status, pose))
}

/// File name of the profile file, relative to QEMU's working directory.
pub const PROFILE_FILE: &str = "phasegate-profile.bin";
/// Magic of the profile file.
pub const PROFILE_MAGIC: [u8; 4] = *b"PGPF";
/// Version of the profile file.
pub const PROFILE_VERSION: u16 = 1;
/// Bytes of one stage in a profile record.
pub const STAGE_LEN: usize = 8;

/// A stage of a frame in the profile file.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Hash, PartialOrd, Ord)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum StageKind {
    /// Input stage: phase conversion, input quantisation, and the copy
    /// into the arena (0).
    Input,
    /// The phase gate's coefficients (1).
    Gate,
    /// Preparing a node: decoding its record from the blob header and
    /// copying its input slices into its input span (2).
    Gather,
    /// A node's op: a layer with its requantisation, activation and style
    /// adapters, or a softmax gate (3).
    Node,
    /// Output stage: locating and copying the output, de-quantisation (4).
    Output,
}

impl StageKind {
    /// The kind's number on the wire.
    pub fn to_u8(self) -> u8 {
        match self {
            StageKind::Input => 0,
            StageKind::Gate => 1,
            StageKind::Gather => 2,
            StageKind::Node => 3,
            StageKind::Output => 4,
        }
    }

    /// The kind with number `v`, if any.
    pub fn from_u8(v: u8) -> Option<StageKind> {
        Some(match v {
            0 => StageKind::Input,
            1 => StageKind::Gate,
            2 => StageKind::Gather,
            3 => StageKind::Node,
            4 => StageKind::Output,
            _ => return None,
        })
    }
}

/// One stage of one frame: what ran and how many SysTick ticks it took.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
pub struct StageTicks {
    /// What ran.
    pub kind: StageKind,
    /// The node (0 for the input, gate and output stages).
    pub node: u8,
    /// SysTick ticks.
    pub ticks: u32,
}

impl StageTicks {
    /// A placeholder (input stage, 0 ticks), for filling arrays.
    pub const ZERO: StageTicks = StageTicks {
        kind: StageKind::Input,
        node: 0,
        ticks: 0,
    };

    /// The stage's 8 bytes.
    pub fn encode(&self) -> [u8; STAGE_LEN] {
        let mut b = [0u8; STAGE_LEN];
        b[0] = self.kind.to_u8();
        b[1] = self.node;
        put_u32(&mut b, 4, self.ticks);
        b
    }

    /// Decodes a stage; `None` for a wrong length or an unknown kind.
    pub fn decode(b: &[u8]) -> Option<StageTicks> {
        if b.len() != STAGE_LEN {
            return None;
        }
        Some(StageTicks {
            kind: StageKind::from_u8(*b.first()?)?,
            node: *b.get(1)?,
            ticks: u32_at(b, 4),
        })
    }
}

/// Header of the profile file.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
pub struct ProfileHeader {
    /// Frames the firmware will write.
    pub frames: u32,
    /// Stages per frame: 2 x nodes + 3.
    pub stages: u32,
    /// The input image's CRC, echoed.
    pub input_crc: u32,
}

impl ProfileHeader {
    /// Stages per frame of a model of `nodes` nodes.
    pub fn stages_for(nodes: usize) -> u32 {
        2 * nodes as u32 + 3
    }

    /// Bytes of one record.
    pub fn record_len(&self) -> usize {
        STAGE_LEN * self.stages as usize
    }

    /// The 32 header bytes.
    pub fn encode(&self) -> [u8; HEADER_LEN] {
        let mut b = [0u8; HEADER_LEN];
        b[..4].copy_from_slice(&PROFILE_MAGIC);
        put_u16(&mut b, 4, PROFILE_VERSION);
        put_u16(&mut b, 6, HEADER_LEN as u16);
        put_u32(&mut b, 8, self.frames);
        put_u32(&mut b, 12, self.stages);
        put_u32(&mut b, 16, self.record_len() as u32);
        put_u32(&mut b, 20, self.input_crc);
        b
    }

    /// Parses the header at the start of `file`.
    pub fn parse(file: &[u8]) -> Result<ProfileHeader, WireError> {
        check_preamble(file, PROFILE_MAGIC, PROFILE_VERSION)?;
        let h = ProfileHeader {
            frames: u32_at(file, 8),
            stages: u32_at(file, 12),
            input_crc: u32_at(file, 20),
        };
        // Bounded first, so `record_len` cannot wrap on a 32-bit host.
        if h.stages > 0x0100_0000 || u32_at(file, 16) as usize != h.record_len() {
            return Err(WireError::BadHeader);
        }
        Ok(h)
    }
}

/// Header of the output file.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
pub struct OutputHeader {
    /// Frames the firmware will write.
    pub frames: u32,
    /// Outputs per frame (reach mode: the frame width, the f32 each
    /// record carries).
    pub output_dim: u32,
    /// The input image's CRC, echoed: binds these outputs to those inputs.
    pub input_crc: u32,
    /// The input image's mode, echoed: what the records hold.
    pub mode: Mode,
}

impl OutputHeader {
    /// Bytes of one record.
    pub fn record_len(&self) -> usize {
        match self.mode {
            Mode::Network => 8 + 6 * self.output_dim as usize,
            Mode::Controller => POSE_RECORD_LEN,
            Mode::Reach => reach::frame_record_len(self.output_dim as usize),
        }
    }

    /// The 32 header bytes.
    pub fn encode(&self) -> [u8; HEADER_LEN] {
        let mut b = [0u8; HEADER_LEN];
        b[..4].copy_from_slice(&OUTPUT_MAGIC);
        put_u16(&mut b, 4, OUTPUT_VERSION);
        put_u16(&mut b, 6, HEADER_LEN as u16);
        put_u32(&mut b, 8, self.frames);
        put_u32(&mut b, 12, self.output_dim);
        put_u32(&mut b, 16, self.record_len() as u32);
        put_u32(&mut b, 20, self.input_crc);
        put_u32(&mut b, 24, self.mode.to_u32());
        b
    }

    /// Parses the header at the start of `file`.
    pub fn parse(file: &[u8]) -> Result<OutputHeader, WireError> {
        check_preamble(file, OUTPUT_MAGIC, OUTPUT_VERSION)?;
        let h = OutputHeader {
            frames: u32_at(file, 8),
            output_dim: u32_at(file, 12),
            input_crc: u32_at(file, 20),
            mode: Mode::from_u32(u32_at(file, 24))?,
        };
        // The width is bounded first (as the input header's is), so
        // `record_len` cannot wrap on a 32-bit host.
        if h.output_dim > 0x0100_0000 || u32_at(file, 16) as usize != h.record_len() {
            return Err(WireError::BadHeader);
        }
        Ok(h)
    }
}

/// One output record.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
pub struct RecordHead {
    /// SysTick ticks spent in `Runtime::run_quantised` (integer inference);
    /// in controller mode, in the loop's `Network::predict` (`run`: input
    /// quantisation, inference, de-quantisation).
    pub infer_ticks: u32,
    /// SysTick ticks for the whole frame: phase and input conversion,
    /// inference and de-quantisation; in controller mode, the whole
    /// `Locomotion::step`.
    pub frame_ticks: u32,
}

/// Encodes one output record into `buf` (length `8 + 6 * q.len()`);
/// returns `None` on a length mismatch.
pub fn encode_record(head: RecordHead, q: &[i16], f: &[f32], buf: &mut [u8]) -> Option<()> {
    if q.len() != f.len() || buf.len() != 8 + 6 * q.len() {
        return None;
    }
    put_u32(buf, 0, head.infer_ticks);
    put_u32(buf, 4, head.frame_ticks);
    let (qb, fb) = buf.get_mut(8..)?.split_at_mut(2 * q.len());
    for (d, v) in qb.chunks_exact_mut(2).zip(q) {
        d.copy_from_slice(&v.to_le_bytes());
    }
    for (d, v) in fb.chunks_exact_mut(4).zip(f) {
        d.copy_from_slice(&v.to_bits().to_le_bytes());
    }
    Some(())
}

/// Decodes one output record: its head, and the outputs into `q` and `f`.
pub fn decode_record(buf: &[u8], q: &mut [i16], f: &mut [f32]) -> Option<RecordHead> {
    if q.len() != f.len() || buf.len() != 8 + 6 * q.len() {
        return None;
    }
    let head = RecordHead {
        infer_ticks: u32_at(buf, 0),
        frame_ticks: u32_at(buf, 4),
    };
    for (i, v) in q.iter_mut().enumerate() {
        *v = u16_at(buf, 8 + 2 * i) as i16;
    }
    let base = 8 + 2 * q.len();
    for (i, v) in f.iter_mut().enumerate() {
        *v = f32::from_bits(u32_at(buf, base + 4 * i));
    }
    Some(head)
}

/// The output file's trailer: written last, so its presence says the run
/// finished.
#[derive(Clone, Copy, Debug, Default, Eq, PartialEq)]
pub struct Trailer {
    /// Frames written.
    pub frames_done: u32,
    /// Deepest stack use seen, in bytes (painted-stack high-water mark).
    pub stack_high_water: u32,
    /// Bytes between the end of static RAM and the initial stack pointer.
    pub stack_size: u32,
    /// SysTick ticks the calibration loop took.
    pub calib_ticks: u32,
    /// Instructions the calibration loop executes.
    pub calib_instructions: u32,
}

impl Trailer {
    /// The 32 trailer bytes.
    pub fn encode(&self) -> [u8; HEADER_LEN] {
        let mut b = [0u8; HEADER_LEN];
        b[..4].copy_from_slice(&TRAILER_MAGIC);
        put_u32(&mut b, 4, self.frames_done);
        put_u32(&mut b, 8, self.stack_high_water);
        put_u32(&mut b, 12, self.stack_size);
        put_u32(&mut b, 16, self.calib_ticks);
        put_u32(&mut b, 20, self.calib_instructions);
        b
    }

    /// Parses a trailer.
    pub fn parse(b: &[u8]) -> Result<Trailer, WireError> {
        if b.len() != HEADER_LEN {
            return Err(WireError::Truncated {
                needed: HEADER_LEN as u64,
                available: b.len() as u64,
            });
        }
        if b.get(..4) != Some(&TRAILER_MAGIC[..]) {
            return Err(WireError::BadMagic);
        }
        Ok(Trailer {
            frames_done: u32_at(b, 4),
            stack_high_water: u32_at(b, 8),
            stack_size: u32_at(b, 12),
            calib_ticks: u32_at(b, 16),
            calib_instructions: u32_at(b, 20),
        })
    }
}

/// The firmware's semihosting exit codes (QEMU exits with the same code).
pub mod exit {
    /// Every frame ran and the outputs were written (or, without an input
    /// image, the model was validated).
    pub const OK: i32 = 0;
    /// The panic handler ran (a bug: nothing in the firmware should panic).
    pub const PANIC: i32 = 1;
    /// The model blob in the MODEL region was refused.
    pub const BAD_MODEL: i32 = 2;
    /// The input image in the HOSTIO region was refused.
    pub const BAD_INPUT: i32 = 3;
    /// The runtime refused a frame (NaN/inf input or phase, wrong length),
    /// or its mix (malformed mix field, or an id of a style not loaded).
    pub const FRAME_ERROR: i32 = 4;
    /// Writing the output file through semihosting failed.
    pub const OUTPUT_ERROR: i32 = 5;
    /// A hard fault (bad memory access, ...) or an unexpected interrupt.
    pub const HARD_FAULT: i32 = 6;
    /// A style blob in the STYLES region was refused (damaged, built for
    /// another base model, incompatible with it, or too big for the
    /// firmware's scratch buffer or bank).
    pub const BAD_STYLE: i32 = 7;
    /// Controller mode on a model that is not PFNN-shaped (342 inputs,
    /// 311 outputs): `Error::NotPfnn`.
    pub const NOT_PFNN: i32 = 8;
    /// Controller mode on a firmware built without the `controller`
    /// feature.
    pub const NO_CONTROLLER: i32 = 9;
    /// Reach mode: the image's layout does not fit the model or the
    /// firmware's frame buffers (`Error::BadLayout`, `TooWide`), or its
    /// first frame is not finite.
    pub const BAD_LAYOUT: i32 = 10;
    /// The rig blob at the start of the STYLES region was refused: built
    /// for another motion blob (`Error::RigMismatch`, both payload CRCs),
    /// not fitting it (`RigIncompatible`), damaged, or too big for the
    /// firmware's buffers.
    pub const BAD_RIG: i32 = 11;
    /// The model blob's self-test failed: a stored vector did not give its
    /// stored output on this device (`Error::SelfTestFailed`, logged with
    /// the vector and output index, expected and computed value), or could
    /// not run. The model is never run.
    pub const SELF_TEST_FAILED: i32 = 12;

    /// One line saying what an exit code means.
    pub fn describe(code: i32) -> &'static str {
        match code {
            OK => "success",
            PANIC => "firmware panicked",
            BAD_MODEL => "model blob refused",
            BAD_INPUT => "input image refused",
            FRAME_ERROR => "runtime refused a frame or its mix",
            OUTPUT_ERROR => "could not write the output file",
            HARD_FAULT => "hard fault or unexpected interrupt",
            BAD_STYLE => "style blob refused",
            NOT_PFNN => "model is not PFNN-shaped: the controller needs 342 inputs and 311 outputs",
            NO_CONTROLLER => "controller mode needs the firmware's `controller` feature",
            BAD_LAYOUT => "reaching layout or first frame refused",
            BAD_RIG => "rig blob refused",
            SELF_TEST_FAILED => "the model blob's self-test failed on the device",
            _ => "unknown exit code",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Profile headers and stages read back what was written; an unknown
    /// stage kind or a wrapping stage count is refused.
    #[test]
    fn profile_round_trips() {
        let h = ProfileHeader {
            frames: 3,
            stages: ProfileHeader::stages_for(4),
            input_crc: 0xDEAD_BEEF,
        };
        assert_eq!(h.stages, 11);
        assert_eq!(ProfileHeader::parse(&h.encode()), Ok(h));
        let mut wide = h.encode();
        wide[12..16].copy_from_slice(&0x2000_0001u32.to_le_bytes());
        assert_eq!(ProfileHeader::parse(&wide), Err(WireError::BadHeader));
        for kind in (0..5).filter_map(StageKind::from_u8) {
            let st = StageTicks {
                kind,
                node: 7,
                ticks: 123_456,
            };
            assert_eq!(StageTicks::decode(&st.encode()), Some(st));
        }
        let mut bad = StageTicks::ZERO.encode();
        bad[0] = 5;
        assert_eq!(StageTicks::decode(&bad), None);
    }

    /// An output header whose width would make its record length wrap on a
    /// 32-bit host is refused, not read with a wrapped length.
    #[test]
    fn output_header_width_is_bounded() {
        let h = |output_dim| OutputHeader {
            frames: 1,
            output_dim,
            input_crc: 0,
            mode: Mode::Network,
        };
        let ok = h(311);
        assert_eq!(OutputHeader::parse(&ok.encode()), Ok(ok));
        let wide = h(0x2AAA_AAAB); // 8 + 6 * w wraps to 10 in 32 bits
        assert_eq!(
            OutputHeader::parse(&wide.encode()),
            Err(WireError::BadHeader)
        );
    }
}
