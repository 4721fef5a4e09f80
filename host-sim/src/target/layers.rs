//! Per-layer figures of a target run: the firmware's profile file (each
//! frame's SysTick ticks per stage, `wire::ProfileHeader`) averaged over
//! the frames and joined with what the blob says of each node (op, shape,
//! experts active, MACs).

use std::fmt::Write as _;

use anyhow::{ensure, Context, Result};
use phasegate::blob::{LayerOp, NodeOp, Nodes as _, WeightFormat};
use phasegate::ops::{GatedOp, Layer};
use phasegate::{node_gating, Model};
use serde::Serialize;

use super::wire::{self, StageKind};
use super::INSTRUCTIONS_PER_TICK;

/// One stage of the frame, averaged over the frames.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StageRow {
    /// `input`, `gate`, `prepare` (decoding the node's record and
    /// gathering its inputs), `node` or `output`.
    pub stage: &'static str,
    /// The node, for `prepare` and `node`.
    pub node: Option<u8>,
    /// What the node computes: `dense`, `cp`, `diagonal`, `softmax`;
    /// empty for the other stages.
    pub op: String,
    /// `in -> out` (with the CP rank), empty for the other stages.
    pub shape: String,
    /// Weight and accumulator widths (`i8/i32`), empty for the others.
    pub formats: String,
    /// Experts active per frame (the gate's non-zero coefficients).
    pub experts: u32,
    /// Multiply-accumulates per frame of the base layer (no adapters).
    pub macs: u64,
    /// Mean instructions per frame (ticks x 40; resolution one tick).
    pub instructions: f64,
    /// Fewest and most instructions in one frame.
    pub min: u64,
    /// Most instructions in one frame.
    pub max: u64,
}

impl StageRow {
    /// Instructions per MAC, when the stage does MACs.
    pub fn per_mac(&self) -> Option<f64> {
        (self.macs > 0).then(|| self.instructions / self.macs as f64)
    }
}

fn stage_name(k: StageKind) -> &'static str {
    match k {
        StageKind::Input => "input",
        StageKind::Gate => "gate",
        StageKind::Gather => "prepare",
        StageKind::Node => "node",
        StageKind::Output => "output",
    }
}

/// What the blob says of node `i`: op, shape, formats, experts, MACs.
fn describe(model: &Model<'_>, i: u8) -> (String, String, String, u32, u64) {
    let h = model.header();
    let Some(node) = h.nodes.node(usize::from(i)) else {
        return Default::default();
    };
    let active = node_gating(&h.gating, &h.nodes, &node).active();
    match node.op {
        NodeOp::Softmax(s) => (
            "softmax".into(),
            format!("{} logits", s.experts),
            String::new(),
            u32::from(s.experts),
            0,
        ),
        NodeOp::Layer(d) => {
            let (op, rank) = match d.op {
                LayerOp::Dense => ("dense", String::new()),
                LayerOp::Cp { rank, .. } => ("cp", format!(" rank {rank}")),
                LayerOp::Diagonal => ("diagonal", String::new()),
                LayerOp::Rbf { .. } => ("rbf", String::new()),
                LayerOp::Dec { .. } => ("dec", String::new()),
            };
            let w = match d.weights {
                WeightFormat::I8 => "i8",
                WeightFormat::I16 => "i16",
                WeightFormat::I8Interleaved => "i8x",
            };
            let acc = if d.acc.bytes() == 4 { "i32" } else { "i64" };
            (
                op.into(),
                format!("{} -> {}{rank}", d.in_dim, d.out_dim),
                format!("{w}/{acc}"),
                active as u32,
                Layer::macs(&d, active as u64),
            )
        }
    }
}

/// Parses the profile file of a run of `frames` frames on `model` and
/// averages each stage over the frames.
pub fn profile(
    model: &Model<'_>,
    file: &[u8],
    frames: usize,
    input_crc: u32,
) -> Result<Vec<StageRow>> {
    let h = wire::ProfileHeader::parse(file)
        .map_err(|e| anyhow::anyhow!("firmware profile file: {e}"))?;
    let nodes = model.header().nodes.count();
    ensure!(
        h.frames as usize == frames
            && h.input_crc == input_crc
            && h.stages == wire::ProfileHeader::stages_for(nodes),
        "firmware profile file is for {} frames of {} stages (input CRC {:#x}), expected {frames} of {} ({input_crc:#x})",
        h.frames,
        h.stages,
        h.input_crc,
        wire::ProfileHeader::stages_for(nodes)
    );
    let rl = h.record_len();
    let body = &file[wire::HEADER_LEN..];
    ensure!(
        body.len() == frames * rl,
        "firmware profile file holds {} bytes of records, expected {}: the run stopped early",
        body.len(),
        frames * rl
    );
    let mut ticks: Vec<Vec<u64>> = vec![Vec::with_capacity(frames); h.stages as usize];
    let mut order = Vec::new();
    for (f, rec) in body.chunks_exact(rl).enumerate() {
        for (s, b) in rec.chunks_exact(wire::STAGE_LEN).enumerate() {
            let st = wire::StageTicks::decode(b)
                .with_context(|| format!("firmware profile file: frame {f} stage {s}"))?;
            if f == 0 {
                order.push((st.kind, st.node));
            }
            ensure!(
                order.get(s) == Some(&(st.kind, st.node)),
                "firmware profile file: frame {f} stage {s} is not the first frame's"
            );
            ticks[s].push(u64::from(st.ticks));
        }
    }
    Ok(order
        .iter()
        .zip(&ticks)
        .map(|(&(kind, node), t)| {
            let on_node = matches!(kind, StageKind::Gather | StageKind::Node);
            let (op, shape, formats, experts, macs) = if kind == StageKind::Node {
                describe(model, node)
            } else {
                Default::default()
            };
            let instr: Vec<u64> = t.iter().map(|v| v * INSTRUCTIONS_PER_TICK).collect();
            StageRow {
                stage: stage_name(kind),
                node: on_node.then_some(node),
                op,
                shape,
                formats,
                experts,
                macs,
                instructions: instr.iter().sum::<u64>() as f64 / instr.len().max(1) as f64,
                min: instr.iter().copied().min().unwrap_or(0),
                max: instr.iter().copied().max().unwrap_or(0),
            }
        })
        .collect())
}

/// The per-stage table, one line per stage.
pub fn render(rows: &[StageRow], frames: usize) -> String {
    let mut s = String::new();
    let total: f64 = rows.iter().map(|r| r.instructions).sum();
    let _ = writeln!(
        s,
        "per stage (mean of {frames} frames; each stage read to 1 SysTick tick = {INSTRUCTIONS_PER_TICK} instructions, and includes about 40 instructions of its probe mark; prepare = decode the node's record and gather its inputs):"
    );
    let _ = writeln!(
        s,
        "  {:<12} {:<9} {:<22} {:<8} {:>7} {:>10} {:>12} {:>8} {:>6}",
        "stage", "op", "shape", "formats", "experts", "MACs", "instructions", "instr/MAC", "share"
    );
    for r in rows {
        let name = match r.node {
            Some(n) => format!("{} {n}", r.stage),
            None => r.stage.to_string(),
        };
        let per_mac = r.per_mac().map(|v| format!("{v:.3}")).unwrap_or_default();
        let experts = if r.experts > 0 {
            r.experts.to_string()
        } else {
            String::new()
        };
        let macs = if r.macs > 0 {
            r.macs.to_string()
        } else {
            String::new()
        };
        let _ = writeln!(
            s,
            "  {:<12} {:<9} {:<22} {:<8} {:>7} {:>10} {:>12.0} {:>8} {:>5.1}%",
            name,
            r.op,
            r.shape,
            r.formats,
            experts,
            macs,
            r.instructions,
            per_mac,
            100.0 * r.instructions / total.max(1.0)
        );
    }
    let _ = writeln!(
        s,
        "  {:<12} {:<9} {:<22} {:<8} {:>7} {:>10} {:>12.0}",
        "sum", "", "", "", "", "", total
    );
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use wire::{ProfileHeader, StageTicks};

    /// A profile file of `frames` frames of the default model's 9 stages,
    /// stage `s` of frame `f` taking `s + f` ticks.
    fn file(frames: u32, stages: u32) -> Vec<u8> {
        let h = ProfileHeader {
            frames,
            stages,
            input_crc: 7,
        };
        let mut v = h.encode().to_vec();
        let mut kinds = vec![(StageKind::Input, 0), (StageKind::Gate, 0)];
        for n in 0..3 {
            kinds.push((StageKind::Gather, n));
            kinds.push((StageKind::Node, n));
        }
        kinds.push((StageKind::Output, 0));
        for f in 0..frames {
            for (s, &(kind, node)) in kinds.iter().enumerate() {
                let ticks = s as u32 + f;
                v.extend(StageTicks { kind, node, ticks }.encode());
            }
        }
        v
    }

    #[test]
    fn stages_are_averaged_and_described() {
        let model = Model::from_bytes(crate::default_model::BLOB).unwrap();
        let rows = profile(&model, &file(2, 9), 2, 7).unwrap();
        assert_eq!(rows.len(), 9);
        let node0 = &rows[3];
        assert_eq!((node0.stage, node0.node), ("node", Some(0)));
        assert_eq!((node0.op.as_str(), node0.experts), ("dense", 4));
        assert_eq!(node0.shape, "342 -> 32");
        assert_eq!(node0.macs, 342 * 32 * 4);
        // 3 and 4 ticks: 140 instructions on average.
        assert_eq!(
            (node0.instructions, node0.min, node0.max),
            (140.0, 120, 160)
        );
        assert!(render(&rows, 2).contains("node 0"));
        // A file for other frames, inputs or stage counts is refused.
        assert!(profile(&model, &file(2, 9), 3, 7).is_err());
        assert!(profile(&model, &file(2, 9), 2, 8).is_err());
        assert!(profile(&model, &file(2, 11), 2, 7).is_err());
        let cut = file(2, 9);
        assert!(profile(&model, &cut[..cut.len() - 1], 2, 7).is_err());
    }
}
