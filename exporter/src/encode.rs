//! The one encoder: lays out every blob (models whose layers may be dense,
//! CP or diagonal, and style blobs), fills in the header and frames it.
//! The inverse of `phasegate::Model::from_bytes`; see `docs/blob-format.md`.

use phasegate::blob::{
    crc32, AccWidth, Header, LayerDesc, LayerOp, ModelKind, Node, NodeOp, Section, Span,
    WeightFormat, FORMAT_VERSION, MAGIC, MAX_NODES, MAX_STYLE_NAME, PAYLOAD_ALIGN, PREAMBLE_LEN,
};
use phasegate::ops::cp::MidRecord;
use phasegate::ops::{GatedOp, Layer};

use crate::plan::plan_arena;

pub use crate::lower::qmodel::{EncodeError, QCp, QKind, QLayer, QModel, QNode, QNodeOp, Wiring};

struct Payload(Vec<u8>);

impl Payload {
    fn push(&mut self, bytes: &[u8]) -> Result<Section, EncodeError> {
        while !self.0.len().is_multiple_of(4) {
            self.0.push(0);
        }
        let offset = u32::try_from(self.0.len()).map_err(|_| EncodeError::TooLarge("payload"))?;
        let len = u32::try_from(bytes.len()).map_err(|_| EncodeError::TooLarge("section"))?;
        self.0.extend_from_slice(bytes);
        Ok(Section { offset, len })
    }
}

/// `n` weights as rows of `width` in `format`'s storage order (each row
/// padded to `format.row_bytes(width)`).
fn weight_bytes(
    w: &[i32],
    format: WeightFormat,
    (n, width): (usize, usize),
    layer: usize,
    what: &'static str,
) -> Result<Vec<u8>, EncodeError> {
    if w.len() != n || width == 0 || !n.is_multiple_of(width) {
        return Err(EncodeError::Length { layer, what });
    }
    let bad = || EncodeError::OutOfRange { layer, what };
    let mut out = Vec::with_capacity(n / width * format.row_bytes(width));
    for row in w.chunks(width) {
        let mut stored = vec![0u8; format.row_bytes(width)];
        for (j, &v) in row.iter().enumerate() {
            let s = format.position(j) * format.bytes();
            match format {
                WeightFormat::I8 | WeightFormat::I8Interleaved => {
                    stored[s] = i8::try_from(v).map_err(|_| bad())? as u8
                }
                WeightFormat::I16 => stored[s..s + 2]
                    .copy_from_slice(&i16::try_from(v).map_err(|_| bad())?.to_le_bytes()),
            }
        }
        out.extend(stored);
    }
    Ok(out)
}

fn bias_bytes(l: &QLayer, i: usize) -> Result<Vec<u8>, EncodeError> {
    let d = &l.desc;
    if l.bias.len() != usize::from(d.experts) * usize::from(d.out_dim) {
        return Err(EncodeError::Length {
            layer: i,
            what: "bias",
        });
    }
    let mut out = Vec::new();
    for &b in &l.bias {
        match d.acc {
            AccWidth::I32 => out.extend(
                i32::try_from(b)
                    .map_err(|_| EncodeError::OutOfRange {
                        layer: i,
                        what: "bias",
                    })?
                    .to_le_bytes(),
            ),
            AccWidth::I64 => out.extend(b.to_le_bytes()),
        }
    }
    Ok(out)
}

fn stage_bytes(records: &[(f32, f32)]) -> Vec<u8> {
    records
        .iter()
        .flat_map(|(a, b)| a.to_le_bytes().into_iter().chain(b.to_le_bytes()))
        .collect()
}

fn layer_sections(payload: &mut Payload, l: &QLayer, i: usize) -> Result<LayerDesc, EncodeError> {
    let d = l.desc;
    let (experts, out, inp) = (
        usize::from(d.experts),
        usize::from(d.out_dim),
        usize::from(d.in_dim),
    );
    if l.requant.len() != out {
        return Err(EncodeError::Length {
            layer: i,
            what: "requant",
        });
    }
    let mut desc = d;
    match d.op {
        LayerOp::Dense => {
            // int8 dense rows go in the order the DSP kernel reads
            // (`docs/blob-format.md`, "Weights"); every build reads it. Rows
            // narrower than its block of 16 inputs never reach its loop and
            // stay plain (no padding).
            if d.weights == WeightFormat::I8 && inp >= 16 {
                desc.weights = WeightFormat::I8Interleaved;
            }
            desc.weight_section = payload.push(&weight_bytes(
                &l.weights,
                desc.weights,
                (experts * out * inp, inp),
                i,
                "weights",
            )?)?;
        }
        LayerOp::Diagonal => {
            desc.weight_section = payload.push(&weight_bytes(
                &l.weights,
                d.weights,
                (experts * out, out),
                i,
                "weights",
            )?)?;
        }
        LayerOp::Cp { rank, .. } => {
            let r = usize::from(rank);
            let cp = l.cp.as_ref().ok_or(EncodeError::Length {
                layer: i,
                what: "cp factors",
            })?;
            if cp.cores.len() != experts * r || cp.mid.len() != r {
                return Err(EncodeError::Length {
                    layer: i,
                    what: "cores",
                });
            }
            // Both factors are one matrix each for the dense kernels: int8
            // ones go in the DSP kernel's order when the rows of either
            // (`in` wide for `B^T`, `rank` wide for `A`) reach its block
            // of 16 inputs.
            if d.weights == WeightFormat::I8 && inp.max(r) >= 16 {
                desc.weights = WeightFormat::I8Interleaved;
            }
            let bt = payload.push(&weight_bytes(
                &l.weights,
                desc.weights,
                (r * inp, inp),
                i,
                "B",
            )?)?;
            let a = payload.push(&weight_bytes(&cp.a, desc.weights, (out * r, r), i, "A")?)?;
            let cores: Vec<u8> = cp.cores.iter().flat_map(|c| c.to_le_bytes()).collect();
            let cores = payload.push(&cores)?;
            let mid: Vec<u8> = cp.mid.iter().flat_map(MidRecord::to_bytes).collect();
            let mid = payload.push(&mid)?;
            desc.weight_section = bt;
            desc.op = LayerOp::Cp {
                rank,
                a,
                cores,
                mid,
            };
        }
        LayerOp::Rbf { .. } | LayerOp::Dec { .. } => {
            let rbf = l.rbf.as_ref().ok_or(EncodeError::Length {
                layer: i,
                what: "rbf arrays",
            })?;
            if rbf.scales.len() != experts * out || rbf.align.len() != inp {
                return Err(EncodeError::Length {
                    layer: i,
                    what: "rbf scales",
                });
            }
            desc.weight_section = payload.push(&weight_bytes(
                &l.weights,
                d.weights,
                (experts * out * inp, inp),
                i,
                "centres",
            )?)?;
            let scales: Vec<u8> = rbf.scales.iter().flat_map(|r| r.to_bytes()).collect();
            let scales = payload.push(&scales)?;
            let align = payload.push(&rbf.align)?;
            desc.op = match d.op {
                LayerOp::Dec { .. } => LayerOp::Dec { scales, align },
                _ => LayerOp::Rbf { scales, align },
            };
        }
    }
    desc.bias_section = payload.push(&bias_bytes(l, i)?)?;
    let rq: Vec<u8> = l.requant.iter().flat_map(|r| r.to_bytes()).collect();
    desc.requant_section = payload.push(&rq)?;
    Ok(desc)
}

/// Lays out the payload, plans the arena, fills in the header and returns
/// the blob bytes. The header is checked with the runtime's own graph and
/// plan checks before it is framed.
pub fn encode(m: &QModel) -> Result<Vec<u8>, EncodeError> {
    let (graph, output) = m.graph();
    if graph.len() > MAX_NODES {
        return Err(EncodeError::TooManyNodes(graph.len()));
    }
    let mut payload = Payload(Vec::new());
    let dim = |n: usize, what| u16::try_from(n).map_err(|_| EncodeError::TooLarge(what));
    let (kind, input_stage, output_stage, input_dim, output_dim) = match &m.kind {
        QKind::Model(kind) => (
            *kind,
            payload.push(&stage_bytes(&m.input_stage))?,
            payload.push(&stage_bytes(&m.output_stage))?,
            dim(m.input_stage.len(), "input width")?,
            dim(m.output_stage.len(), "output width")?,
        ),
        QKind::Style {
            base_crc,
            layer,
            name,
        } => {
            if name.len() > MAX_STYLE_NAME {
                return Err(EncodeError::TooLarge("style name"));
            }
            let first = m.layers.first().ok_or(EncodeError::Length {
                layer: 0,
                what: "adapter",
            })?;
            let name = payload.push(name.as_bytes())?;
            (
                ModelKind::Style {
                    base_crc: *base_crc,
                    layer: *layer,
                    name,
                },
                Section::default(),
                Section::default(),
                first.desc.in_dim,
                first.desc.out_dim,
            )
        }
    };
    let mut descs = Vec::new();
    for (i, l) in m.layers.iter().enumerate() {
        descs.push(layer_sections(&mut payload, l, i)?);
    }
    let mut nodes = heapless::Vec::new();
    for (i, n) in graph.iter().enumerate() {
        let op = match &n.op {
            QNodeOp::Layer(l) => NodeOp::Layer(*descs.get(*l).ok_or(EncodeError::Length {
                layer: i,
                what: "layer index",
            })?),
            QNodeOp::Softmax(s) => NodeOp::Softmax(*s),
        };
        let span = |len: usize| -> Result<Span, EncodeError> {
            Ok(Span {
                offset: 0,
                len: u16::try_from(len).map_err(|_| EncodeError::TooLarge("node width"))?,
            })
        };
        let (in_dim, scratch, out_dim) = match &op {
            NodeOp::Layer(d) => (
                d.in_dim,
                <Layer<'_> as GatedOp<'_>>::scratch(d),
                usize::from(d.out_dim),
            ),
            NodeOp::Softmax(s) => (s.experts, 0, 0),
        };
        let node = Node {
            op,
            inputs: heapless::Vec::from_slice(&n.inputs)
                .map_err(|_| EncodeError::TooLarge("number of input slices of a node"))?,
            gate: n.gate,
            input: span(usize::from(in_dim))?,
            scratch: span(scratch)?,
            output: span(out_dim)?,
        };
        nodes
            .push(node)
            .map_err(|_| EncodeError::TooManyNodes(graph.len()))?;
    }
    let mut header = Header {
        kind,
        gating: m.gating,
        input_dim,
        output_dim,
        nodes,
        input: Span {
            offset: 0,
            len: input_dim,
        },
        output,
        input_stage,
        output_stage,
        ram_bytes: 0,
        macs_per_frame: 0,
        payload_len: u32::try_from(payload.0.len())
            .map_err(|_| EncodeError::TooLarge("payload"))?,
        payload_crc: crc32(&payload.0),
    };
    plan_arena(&mut header)?;
    phasegate::graph::check_structure(&header).map_err(EncodeError::Graph)?;
    phasegate::graph::check_plan(&header).map_err(EncodeError::Graph)?;
    header.macs_per_frame = u32::try_from(phasegate::macs(&header))
        .map_err(|_| EncodeError::TooLarge("MACs per frame"))?;
    Ok(frame(&header, &payload.0))
}

/// Preamble + header + padding + payload. Public so tests can build blobs
/// with deliberately inconsistent headers.
pub fn frame(header: &Header, payload: &[u8]) -> Vec<u8> {
    let header_bytes = postcard::to_allocvec(header).unwrap_or_default();
    let header_len = u16::try_from(header_bytes.len()).unwrap_or(u16::MAX);
    let mut out =
        Vec::with_capacity(PREAMBLE_LEN + header_bytes.len() + PAYLOAD_ALIGN + payload.len());
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&header_len.to_le_bytes());
    let mut crc_input = out.clone();
    crc_input.extend_from_slice(&header_bytes);
    out.extend_from_slice(&crc32(&crc_input).to_le_bytes());
    out.extend_from_slice(&header_bytes);
    out.resize(out.len().next_multiple_of(PAYLOAD_ALIGN), 0);
    out.extend_from_slice(payload);
    out
}
