//! Rigs: one motion blob in flash serving several skeletons.
//!
//! An OMG-shaped graph splits into the nodes that depend on the skeleton
//! (the per-rig autoencoder, and the output node that reads its decoder
//! and the rig's input layout) and the rest (cost encoder, gate, experts:
//! the motion). A rig blob ([`ModelKind::Rig`]) has the model blob's
//! framing and a header holding the *whole* graph of the combination for
//! its rig: its input and output widths and stages, and every node with
//! its arena plan. The nodes it names (`nodes`, a bit set) have their
//! sections in the rig's payload; every other node must be the motion
//! blob's node of the same index, op for op (the same sections, in the
//! motion blob's payload), reading the same slices except that a slice of
//! the input may sit elsewhere in the rig's frame layout.
//!
//! [`Model::with_rig`] checks the rig against the motion blob (its base CRC
//! against the motion blob's payload CRC, [`Error::RigMismatch`]; the
//! interface formats, [`Error::RigIncompatible`]) and then validates the
//! combination exactly like a single blob (structure, sections, overflow
//! proof, arena plan, RAM and MAC figures). The result is an ordinary
//! [`Model`]: the one executor runs it, each node reading its weights from
//! whichever flash region holds them.
//!
//! The motion blob is any graph model blob, unchanged: alone it still runs
//! as the full model of the rig it was exported from.

use crate::blob::{Framed, ModelKind, Nodes, Requant, Source, REQUANT_RECORD_LEN};
use crate::error::{Error, Result};
use crate::graph::IO;
use crate::model::Model;
use crate::style::name_str;

/// What a rig blob says about itself, from its framing and header alone
/// (payload CRC verified; nothing checked against a motion blob).
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
pub struct RigInfo<'a> {
    /// The rig's name.
    pub name: &'a str,
    /// Payload CRC-32 of the motion blob it was built for.
    pub base_crc: u32,
    /// Its own payload CRC-32.
    pub payload_crc: u32,
    /// Bit `i` set: node `i` is the rig's.
    pub nodes: u32,
    /// Bytes of the whole rig blob.
    pub blob_len: usize,
}

impl<'a> RigInfo<'a> {
    /// Reads a rig blob's framing and header (the slice must be exactly
    /// one blob); [`Error::NotARig`] for any other kind of blob.
    pub fn from_bytes(blob: &'a [u8]) -> Result<Self> {
        let f = Framed::parse(blob, true)?;
        let ModelKind::Rig {
            base_crc,
            nodes,
            name,
        } = f.header.kind
        else {
            return Err(Error::NotARig);
        };
        Ok(RigInfo {
            name: name_str(f.payload, name)?,
            base_crc,
            payload_crc: f.header.payload_crc,
            nodes,
            blob_len: f.blob_len,
        })
    }
}

impl<'a> Model<'a> {
    /// A motion blob and a rig blob for it, each exactly one blob, as one
    /// model: see the module documentation. [`Model::arena_elements`] of
    /// the result is the RAM the combination needs.
    pub fn with_rig(motion: &'a [u8], rig: &'a [u8]) -> Result<Self> {
        Self::load_rig(Model::from_bytes(motion)?, rig, true)
    }

    /// Like [`Model::with_rig`], each blob at the start of its own flash
    /// region (bytes after each blob are ignored).
    pub fn with_rig_regions(motion: &'a [u8], rig: &'a [u8]) -> Result<Self> {
        Model::from_region(motion)?.with_rig_region(rig)
    }

    /// This model (a motion blob already loaded) with the rig blob at the
    /// start of `rig`'s region, as [`Model::with_rig_regions`] gives it,
    /// without validating the motion blob a second time.
    pub fn with_rig_region(self, rig: &'a [u8]) -> Result<Self> {
        Self::load_rig(self, rig, false)
    }

    fn load_rig(motion: Model<'a>, rig: &'a [u8], exact: bool) -> Result<Self> {
        let framed = Framed::parse(rig, exact)?;
        let ModelKind::Rig {
            base_crc,
            nodes,
            name,
        } = framed.header.kind
        else {
            return Err(Error::NotARig);
        };
        let motion_crc = motion.header().payload_crc;
        if base_crc != motion_crc {
            return Err(Error::RigMismatch {
                motion_crc,
                rig_crc: base_crc,
            });
        }
        name_str(framed.payload, name)?;
        let (m, r) = (motion.header(), &framed.header);
        let count = r.nodes.count();
        if r.gating != m.gating || count != m.nodes.count() || nodes >> count != 0 {
            return Err(Error::RigIncompatible { node: IO });
        }
        let combined = Model::combined(&motion, framed, nodes)?;
        check_fit(&motion, &combined)?;
        Ok(combined)
    }

    /// Bit `i` set: node `i`'s weights are the rig blob's (0 for a single
    /// blob).
    pub fn rig_nodes(&self) -> u32 {
        self.own_nodes()
    }
}

/// Every node outside the rig's is the motion blob's, reading the same
/// slices in the same formats: an input slice's input-stage records are
/// the motion blob's (bit for bit), a rig node's rows it reads have the
/// formats of the motion blob's node of that index.
fn check_fit(motion: &Model<'_>, combined: &Model<'_>) -> Result<()> {
    let own = |i: usize| (combined.own_nodes() >> (i & 31)) & 1 != 0;
    let (m, r) = (motion.header(), combined.header());
    for i in 0..r.nodes.count() {
        let bad = Error::RigIncompatible { node: i as u8 };
        let (rn, mn) = (r.nodes.node(i).ok_or(bad)?, m.nodes.node(i).ok_or(bad)?);
        if own(i) {
            if rn.layer().is_none() {
                return Err(bad);
            }
            continue;
        }
        if rn.op != mn.op || rn.gate != mn.gate || rn.inputs.len() != mn.inputs.len() {
            return Err(bad);
        }
        for (a, b) in rn.inputs.iter().zip(&mn.inputs) {
            if a.len != b.len || a.source != b.source {
                return Err(bad);
            }
            let len = usize::from(a.len);
            match a.source {
                Source::Input => {
                    let ra = combined.input_stage().skip(usize::from(a.start)).take(len);
                    let mb = motion.input_stage().skip(usize::from(b.start)).take(len);
                    let mut n = 0;
                    for (x, y) in ra.zip(mb) {
                        if x.0.to_bits() != y.0.to_bits() || x.1.to_bits() != y.1.to_bits() {
                            return Err(bad);
                        }
                        n += 1;
                    }
                    if n != len {
                        return Err(bad);
                    }
                }
                Source::Node(j) => {
                    let j = usize::from(j);
                    if a.start != b.start {
                        return Err(bad);
                    }
                    if own(j)
                        && !same_formats(
                            rows(combined, j, a.start, len),
                            rows(motion, j, b.start, len),
                        )
                    {
                        return Err(bad);
                    }
                }
            }
        }
    }
    Ok(())
}

/// The requantisation records of rows `start..start + len` of node `j`.
fn rows<'a>(
    model: &Model<'a>,
    j: usize,
    start: u16,
    len: usize,
) -> Option<&'a [[u8; REQUANT_RECORD_LEN]]> {
    let k = model.kernel(j)?;
    let from = usize::from(start);
    k.requant()
        .as_chunks::<REQUANT_RECORD_LEN>()
        .0
        .get(from..from.checked_add(len)?)
}

/// Whether the two row ranges exist and have the same formats, row by row.
fn same_formats(
    a: Option<&[[u8; REQUANT_RECORD_LEN]]>,
    b: Option<&[[u8; REQUANT_RECORD_LEN]]>,
) -> bool {
    let frac = |r| Requant::from_bytes(r).map(|q| q.frac);
    match (a, b) {
        (Some(a), Some(b)) => {
            a.len() == b.len()
                && a.iter()
                    .zip(b)
                    .all(|(x, y)| frac(x).is_some() && frac(x) == frac(y))
        }
        _ => false,
    }
}
