//! Rig blobs (`docs/graph-format.md`, "Rig blobs"): the rig-specific nodes
//! of a graph, quantised against a motion blob's interface formats and
//! written beside it.
//!
//! The rig's net is quantised as a whole with the row formats of every
//! node outside the rig, and of every rig node a motion node reads, taken
//! from the motion blob (so the rig's encoder writes what the motion
//! blob's experts read, and its decoder and output node read the experts'
//! rows in their formats); the input stage of a graph puts every input
//! column at one format, so the slices the motion nodes read match when
//! their normalisation does (checked at load). Only the rig nodes' sections
//! and the rig's stages go into its payload; the header's other nodes are
//! the motion blob's, their sections in its payload.

use anyhow::{anyhow, bail, ensure, Context, Result};
use phasegate::blob::{
    crc32, Header, LayerOp, ModelKind, NodeOp, Nodes, Section, Source, MAX_STYLE_NAME,
};
use phasegate::Model;
use serde::Serialize;

use crate::encode::{encode, frame};
use crate::inspect::row_formats;
use crate::net::{Net, Wiring};
use crate::quantise::{quantise_net, QuantOptions};

/// The nodes of an OMG graph (`exporter omg`, docs/omg.md) that belong to
/// the rig: the autoencoder and the output node, which reads the decoder
/// and the rig's input layout.
pub const OMG_RIG_NODES: [&str; 6] = ["enc0", "enc1", "enc2", "dec0", "dec1", "out"];

/// What `exporter omg-rig` reports.
#[derive(Clone, Debug, Serialize)]
pub struct RigReport {
    /// The rig's name.
    pub name: String,
    /// Bytes of the rig blob.
    pub blob_bytes: usize,
    /// Payload CRC-32 of the motion blob it is bound to.
    pub base_crc: u32,
    /// Bytes of the motion blob.
    pub motion_bytes: usize,
    /// Indices of the rig's nodes.
    pub nodes: Vec<usize>,
    /// Activation RAM of the combination, bytes.
    pub ram_bytes: usize,
    /// Multiply-accumulates per frame of the combination.
    pub macs_per_frame: u32,
}

/// The bit set of the nodes of `net`'s graph named in `names`.
pub fn rig_mask(net: &Net, names: &[&str]) -> Result<u32> {
    let Wiring::Graph(g) = &net.wiring else {
        bail!("a rig is part of a graph network, not of a chain");
    };
    let mut mask = 0u32;
    for name in names {
        let i = g
            .node(name)
            .ok_or_else(|| anyhow!("the graph has no node {name:?}"))?;
        mask |= 1 << i;
    }
    Ok(mask)
}

/// `opts` with the row formats the rig of the nodes in `mask` must share
/// with `motion` (a model blob): those of every motion node, and of the
/// rig's nodes that motion nodes read.
pub fn rig_options(motion: &[u8], mask: u32, opts: &QuantOptions) -> Result<QuantOptions> {
    let m = Model::from_bytes(motion).map_err(|e| anyhow!("motion blob: {e}"))?;
    let own = |i: usize| (mask >> i) & 1 != 0;
    let mut opts = opts.clone();
    for i in 0..m.nodes().count() {
        let n = m.nodes().node(i).context("motion blob node")?;
        let read_by_motion =
            m.nodes().each().enumerate().any(|(k, r)| {
                !own(k) && r.inputs.iter().any(|s| s.source == Source::Node(i as u8))
            });
        if n.layer().is_some() && (!own(i) || read_by_motion) {
            opts.row_formats
                .insert(i, row_formats(&m, i).context("motion blob")?);
        }
    }
    Ok(opts)
}

/// Quantises `net` against `motion` (a model blob) and writes the rig blob
/// of the nodes in `mask`, named `name`; checks the pair loads.
pub fn export_rig(
    net: &Net,
    motion: &[u8],
    mask: u32,
    name: &str,
    opts: &QuantOptions,
) -> Result<(Vec<u8>, RigReport)> {
    ensure!(
        name.len() <= MAX_STYLE_NAME,
        "the rig name is {} bytes, at most {MAX_STYLE_NAME}",
        name.len()
    );
    let m = Model::from_bytes(motion).map_err(|e| anyhow!("motion blob: {e}"))?;
    let own = |i: usize| (mask >> i) & 1 != 0;
    let count = m.nodes().count();
    let opts = rig_options(motion, mask, opts)?;
    let q = quantise_net(net, &opts)?;
    let full = encode(&q.model)?;
    let fm = Model::from_bytes(&full).map_err(|e| anyhow!("the rig's whole graph: {e}"))?;
    let mut h: Header = fm.header().decoded();
    ensure!(
        h.nodes.len() == count,
        "the rig's graph has {} nodes, the motion blob's {count}",
        h.nodes.len()
    );
    let mut payload = Vec::new();
    let mut push = |bytes: &[u8]| -> Result<Section> {
        payload.resize(payload.len().next_multiple_of(4), 0);
        let s = Section {
            offset: u32::try_from(payload.len())?,
            len: u32::try_from(bytes.len())?,
        };
        payload.extend_from_slice(bytes);
        Ok(s)
    };
    let src = fm.payload();
    let copy = |s: Section| -> Result<&[u8]> {
        src.get(s.offset as usize..(s.offset + s.len) as usize)
            .context("section of the rig's graph")
    };
    h.input_stage = push(copy(h.input_stage)?)?;
    h.output_stage = push(copy(h.output_stage)?)?;
    let name_section = push(name.as_bytes())?;
    for (i, node) in h.nodes.iter_mut().enumerate() {
        if !own(i) {
            node.op = m.nodes().node(i).context("motion blob node")?.op;
            continue;
        }
        let NodeOp::Layer(d) = &mut node.op else {
            bail!("rig node {i} is not a layer");
        };
        d.weight_section = push(copy(d.weight_section)?)?;
        d.bias_section = push(copy(d.bias_section)?)?;
        d.requant_section = push(copy(d.requant_section)?)?;
        if let LayerOp::Cp { a, cores, mid, .. } = &mut d.op {
            *a = push(copy(*a)?)?;
            *cores = push(copy(*cores)?)?;
            *mid = push(copy(*mid)?)?;
        }
    }
    let base_crc = m.header().payload_crc;
    h.kind = ModelKind::Rig {
        base_crc,
        nodes: mask,
        name: name_section,
    };
    h.payload_len = u32::try_from(payload.len())?;
    h.payload_crc = crc32(&payload);
    let blob = frame(&h, &payload);
    let both = Model::with_rig(motion, &blob)
        .map_err(|e| anyhow!("the rig does not load beside its motion blob: {e}"))?;
    let report = RigReport {
        name: name.to_string(),
        blob_bytes: blob.len(),
        base_crc,
        motion_bytes: motion.len(),
        nodes: (0..count).filter(|&i| own(i)).collect(),
        ram_bytes: both.ram_bytes(),
        macs_per_frame: both.macs_per_frame(),
    };
    Ok((blob, report))
}
