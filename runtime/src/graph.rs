//! The graph a header describes, from the header alone: where every slice
//! lives in the activation arena, which buffers are live when, and the
//! checks of the exporter's arena plan. The exporter plans with the same
//! lifetimes ([`buffers`]) the loader checks.
//!
//! Time runs in steps: step 0 writes the quantised input, node `i` runs at
//! step `i + 1`, and the output stage reads the output at step `n + 1`
//! (`n` nodes). A buffer is live from the step that writes it to the last
//! step that reads it, both included; two buffers whose lifetimes meet must
//! not share an element.

use crate::blob::{GateSource, Header, Node, NodeOp, Nodes, Slice, Source, Span, MAX_NODES};
use crate::error::{Error, Result};
use crate::ops::{GatedOp, Layer};

/// Node index used in errors about the model's input and output.
pub const IO: u8 = 255;

/// Most buffers a plan has: the input, and per node a concatenated input,
/// a scratch vector and an output.
pub const MAX_BUFFERS: usize = 1 + 3 * MAX_NODES;

/// What a buffer of the plan holds.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
pub enum Role {
    /// The quantised model input (`Header::input`).
    Input,
    /// Node `i`'s concatenated input (`Node::input` of a node with more than
    /// one input slice; a node with one slice reads it in place).
    Concat(u8),
    /// Node `i`'s intermediate vector (`Node::scratch`).
    Scratch(u8),
    /// Node `i`'s output (`Node::output`).
    Output(u8),
}

impl Role {
    /// The node the buffer belongs to ([`IO`] for the input).
    pub fn node(&self) -> u8 {
        match *self {
            Role::Input => IO,
            Role::Concat(i) | Role::Scratch(i) | Role::Output(i) => i,
        }
    }
}

/// One buffer of the plan and its lifetime in steps.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
pub struct Buffer {
    /// What it holds.
    pub role: Role,
    /// Where it is.
    pub span: Span,
    /// Step that writes it.
    pub first: usize,
    /// Last step that reads it (`first` for a buffer nobody reads).
    pub last: usize,
}

impl Buffer {
    /// Whether the two buffers are live at a common step.
    pub fn meets(&self, other: &Buffer) -> bool {
        self.first <= other.last && other.first <= self.last
    }
}

/// Whether node `node` reads its input in place (one slice) rather than
/// from a concatenation.
pub fn in_place(node: &Node) -> bool {
    node.inputs.len() == 1
}

/// The arena range of `slice`, or `None` when its source does not exist,
/// has no vector (a softmax gate) or is shorter than the slice.
pub fn locate<N: Nodes>(h: &Header<N>, slice: &Slice) -> Option<Span> {
    let (base, width) = match slice.source {
        Source::Input => (h.input, h.input_dim),
        Source::Node(j) => {
            let n = h.nodes.node(usize::from(j))?;
            (n.output, n.out_dim())
        }
    };
    if base.len != width {
        return None;
    }
    within(base, slice)
}

/// The arena range of `slice` of the vector that fills `base`, or `None`
/// when the slice does not lie inside it.
pub(crate) fn within(base: Span, slice: &Slice) -> Option<Span> {
    let end = u32::from(slice.start) + u32::from(slice.len);
    if end > u32::from(base.len) || base.len == 0 {
        return None;
    }
    Some(Span {
        offset: base.offset.checked_add(slice.start)?,
        len: slice.len,
    })
}

/// Last step that reads `source`, or `written` when nothing does.
fn last_read<N: Nodes>(h: &Header<N>, source: Source, written: usize) -> usize {
    let mut last = written;
    for (i, n) in h.nodes.each().enumerate() {
        if n.inputs.iter().any(|s| s.source == source) {
            last = last.max(i + 1);
        }
    }
    if h.output.source == source {
        last = h.nodes.count() + 1;
    }
    last
}

/// Every buffer of the plan with its lifetime, in the order they are
/// written. Header only: the spans are whatever the header says.
pub fn buffers<N: Nodes>(h: &Header<N>) -> heapless::Vec<Buffer, MAX_BUFFERS> {
    let mut out = heapless::Vec::new();
    let mut push = |role, span: Span, first, last| {
        // Cannot fail: at most one input and three buffers per node.
        let _ = out.push(Buffer {
            role,
            span,
            first,
            last,
        });
    };
    push(Role::Input, h.input, 0, last_read(h, Source::Input, 0));
    for (i, n) in h.nodes.each().enumerate() {
        let (step, id) = (i + 1, i as u8);
        if !in_place(&n) {
            push(Role::Concat(id), n.input, step, step);
        }
        if n.scratch.len > 0 {
            push(Role::Scratch(id), n.scratch, step, step);
        }
        if n.output.len > 0 {
            push(
                Role::Output(id),
                n.output,
                step,
                last_read(h, Source::Node(id), step),
            );
        }
    }
    out
}

/// Elements the plan uses: the largest end of any span.
pub fn arena_elements<N: Nodes>(h: &Header<N>) -> usize {
    end_of(&buffers(h))
}

fn end_of(buffers: &[Buffer]) -> usize {
    buffers
        .iter()
        .map(|b| b.span.end() as usize)
        .max()
        .unwrap_or(0)
}

/// The graph's structure: every slice reads the input or an earlier layer
/// node and lies inside it; every node's input, scratch and output spans
/// have the lengths its op needs; gate sources are earlier softmax gates with the layer's expert
/// count; the output is a slice of the right width.
pub fn check_structure<N: Nodes>(h: &Header<N>) -> Result<()> {
    if h.nodes.count() == 0 || h.input_dim == 0 || h.output_dim == 0 {
        return Err(Error::UnsupportedParameter { layer: IO });
    }
    if h.input.len != h.input_dim {
        return Err(Error::DimensionMismatch { layer: IO });
    }
    for i in 0..h.nodes.count() {
        let id = i as u8;
        let bad = Error::GraphInvalid { node: id };
        let n = h.nodes.node(i).ok_or(bad)?;
        let mut width = 0u32;
        for s in &n.inputs {
            let earlier = match s.source {
                Source::Input => true,
                Source::Node(j) => usize::from(j) < i,
            };
            if !earlier || s.len == 0 || locate(h, s).is_none() {
                return Err(bad);
            }
            width += u32::from(s.len);
        }
        if n.inputs.is_empty() {
            return Err(bad);
        }
        let dims = Error::DimensionMismatch { layer: id };
        if width != u32::from(n.in_dim()) || n.input.len != n.in_dim() {
            return Err(dims);
        }
        let scratch = n.layer().map_or(0, <Layer<'_> as GatedOp<'_>>::scratch);
        if n.output.len != n.out_dim() || usize::from(n.scratch.len) != scratch {
            return Err(dims);
        }
        if let [one] = n.inputs.as_slice() {
            if locate(h, one) != Some(n.input) {
                return Err(Error::ArenaOverlap { node: id });
            }
        }
        match (&n.op, n.gate) {
            (NodeOp::Softmax(_), GateSource::None) => {}
            (NodeOp::Softmax(_), _) => return Err(bad),
            (NodeOp::Layer(d), GateSource::Node(j)) => {
                let gate = h.nodes.node(usize::from(j)).filter(|_| usize::from(j) < i);
                match gate.map(|g| g.op) {
                    Some(NodeOp::Softmax(s)) if s.experts == d.experts => {}
                    Some(NodeOp::Softmax(_)) => return Err(Error::GatingMismatch { layer: id }),
                    _ => return Err(bad),
                }
            }
            (NodeOp::Layer(_), _) => {}
        }
    }
    let out = locate(h, &h.output).ok_or(Error::GraphInvalid { node: IO })?;
    if out.len != h.output_dim {
        return Err(Error::DimensionMismatch { layer: IO });
    }
    Ok(())
}

/// The arena plan: no two buffers live at a common step share an element,
/// and `ram_bytes` is exactly twice the elements the plan uses (so the
/// figure is both sufficient and tight). Call after [`check_structure`].
pub fn check_plan<N: Nodes>(h: &Header<N>) -> Result<()> {
    let all = buffers(h);
    for (k, a) in all.iter().enumerate() {
        for b in all.iter().skip(k + 1) {
            if a.meets(b) && a.span.overlaps(&b.span) {
                return Err(Error::ArenaOverlap {
                    node: b.role.node(),
                });
            }
        }
    }
    if u64::from(h.ram_bytes) != 2 * end_of(&all) as u64 {
        return Err(Error::HeaderInconsistent);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::blob::{
        AccWidth, Activation, Gating, LayerDesc, LayerOp, ModelKind, Section, WeightFormat,
    };

    fn layer(in_dim: u16, out_dim: u16) -> NodeOp {
        NodeOp::Layer(LayerDesc {
            op: LayerOp::Dense,
            in_dim,
            out_dim,
            experts: 1,
            weights: WeightFormat::I8,
            acc: AccWidth::I32,
            activation: Activation::Elu,
            weight_section: Section::default(),
            bias_section: Section::default(),
            requant_section: Section::default(),
        })
    }

    fn node(op: NodeOp, inputs: &[Slice], input: Span, output: Span) -> Node {
        Node {
            op,
            inputs: inputs.iter().copied().collect(),
            gate: GateSource::None,
            input,
            scratch: Span::default(),
            output,
        }
    }

    fn span(offset: u16, len: u16) -> Span {
        Span { offset, len }
    }

    fn all(source: Source, len: u16) -> Slice {
        Slice {
            source,
            start: 0,
            len,
        }
    }

    /// input(4) -> a(3), b(2) from input; c = [a, b] -> 2; output c.
    fn branching() -> Header {
        let mut h = Header {
            kind: ModelKind::Mlp,
            gating: Gating::Single,
            input_dim: 4,
            output_dim: 2,
            nodes: heapless::Vec::new(),
            input: span(0, 4),
            output: all(Source::Node(2), 2),
            input_stage: Section::default(),
            output_stage: Section::default(),
            ram_bytes: 0,
            macs_per_frame: 0,
            payload_len: 0,
            payload_crc: 0,
        };
        let x = all(Source::Input, 4);
        let _ = h
            .nodes
            .push(node(layer(4, 3), &[x], span(0, 4), span(4, 3)));
        let _ = h
            .nodes
            .push(node(layer(4, 2), &[x], span(0, 4), span(7, 2)));
        let cat = [all(Source::Node(0), 3), all(Source::Node(1), 2)];
        let _ = h
            .nodes
            .push(node(layer(5, 2), &cat, span(9, 5), span(0, 2)));
        h.ram_bytes = 2 * 14;
        h
    }

    #[test]
    fn lifetimes_follow_the_readers() {
        let h = branching();
        let b = buffers(&h);
        let roles: Vec<_> = b.iter().map(|b| (b.role, b.first, b.last)).collect();
        assert_eq!(
            roles,
            vec![
                (Role::Input, 0, 2),
                (Role::Output(0), 1, 3),
                (Role::Output(1), 2, 3),
                (Role::Concat(2), 3, 3),
                (Role::Output(2), 3, 4),
            ]
        );
        assert_eq!(arena_elements(&h), 14);
        check_structure(&h).unwrap();
        check_plan(&h).unwrap();
    }

    #[test]
    fn the_plan_may_reuse_dead_buffers_but_not_live_ones() {
        let mut h = branching();
        // The output may take the input's place: the input is dead by then.
        h.nodes[2].output = span(2, 2);
        check_plan(&h).unwrap();
        // Not the concatenation's, which node 2 reads while writing it.
        h.nodes[2].output = span(10, 2);
        assert_eq!(check_plan(&h), Err(Error::ArenaOverlap { node: 2 }));
        // Node 1 may not write over node 0's output, which node 2 reads.
        let mut h = branching();
        h.nodes[1].output = span(5, 2);
        assert_eq!(check_plan(&h), Err(Error::ArenaOverlap { node: 1 }));
        // Nor over the input it reads.
        let mut h = branching();
        h.nodes[1].output = span(3, 2);
        assert_eq!(check_plan(&h), Err(Error::ArenaOverlap { node: 1 }));
    }

    #[test]
    fn the_ram_figure_is_exact() {
        let mut h = branching();
        h.ram_bytes += 2;
        assert_eq!(check_plan(&h), Err(Error::HeaderInconsistent));
        h.ram_bytes -= 4;
        assert_eq!(check_plan(&h), Err(Error::HeaderInconsistent));
    }

    #[test]
    fn inputs_must_be_defined_before_use() {
        let mut h = branching();
        h.nodes[0].inputs[0] = all(Source::Node(1), 4);
        assert_eq!(check_structure(&h), Err(Error::GraphInvalid { node: 0 }));
        let mut h = branching();
        h.nodes[2].inputs[1].start = 1;
        assert_eq!(check_structure(&h), Err(Error::GraphInvalid { node: 2 }));
        let mut h = branching();
        h.output = all(Source::Node(7), 2);
        assert_eq!(check_structure(&h), Err(Error::GraphInvalid { node: IO }));
        let mut h = branching();
        h.nodes[1].input = span(1, 4);
        assert_eq!(check_structure(&h), Err(Error::ArenaOverlap { node: 1 }));
        let mut h = branching();
        h.nodes[2].gate = GateSource::Node(0);
        assert_eq!(check_structure(&h), Err(Error::GraphInvalid { node: 2 }));
    }
}
