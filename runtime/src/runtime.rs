//! `Runtime`: the one executor. A model, its static activation arena laid
//! out by the blob's plan, and optionally a bank of styles (residual
//! adapters beside a base layer) with the per-frame [`Mix`].

use crate::blob::{
    Activation, GateSource, NodeOp, Nodes, Requant, Source, Span, MAX_NODES, REQUANT_RECORD_LEN,
};
use crate::error::{Error, Result};
use crate::fixed::elu::elu_q;
use crate::fixed::gate::Gate;
use crate::fixed::phase::Phase;
use crate::fixed::{round_shift, sat_i16};
use crate::graph::{in_place, locate, within};
use crate::model::{Model, MAX_GATES};
use crate::ops::{GatedOp, Layer};
use crate::probe::{Mark, NoProbe, Probe};
use crate::style::{Mix, Style, StyleId};

/// Runs a [`Model`] frame by frame, plain or with styles.
///
/// - `A`: capacity, in i16 elements, of the activation arena
///   ([`Model::arena_elements`] is what a model needs: the exporter's plan,
///   checked at load; checked again by [`Runtime::new`], so no frame can run
///   out of room);
/// - `S`: capacity of the adapter scratch buffer ([`Style::scratch_elements`]
///   is what a style needs; checked by [`Runtime::add_style`]); 0 for a
///   runtime without styles;
/// - `N`: how many styles the bank holds; 0 for a runtime without styles;
///   at most 256, the number of [`StyleId`]s (a `u8`): a larger bank does
///   not compile, so an id can never wrap and select another style.
///
/// ```compile_fail
/// # static BLOB: &[u8] = include_bytes!("../../tests/golden/default/model.blob");
/// let model = phasegate::Model::from_bytes(BLOB).unwrap();
/// let rt = phasegate::Runtime::<'_, 374, 0, 257>::new(model); // error: N > 256
/// ```
///
/// Its size is `(A + S) * 2` bytes plus the model's header and the bank:
/// put it in a `static` (or on the stack) and the whole inference needs no
/// other RAM. Use [`Runtime::required_elements`] to size `A` from a blob.
///
/// Each frame runs the nodes in order: a node's input slices are
/// concatenated into its input span (read in place when there is one), a
/// softmax gate turns its logits into the coefficients of the layers it
/// drives, and a layer runs its op from its input span to its output span,
/// adding the mix's adapters when it is a style's base layer.
///
/// Styles are stateless: switching or blending between frames changes only
/// which adapters the next frame adds, never the phase or any other state,
/// so a switch is exactly as if the new mix had been used all along.
///
/// # Example
///
/// ```
/// use phasegate::{Model, Phase, Runtime};
///
/// // A blob as it sits in flash: here the repository's golden default model
/// // (342 inputs, two hidden layers of 32, 311 outputs).
/// static BLOB: &[u8] = include_bytes!("../../tests/golden/default/model.blob");
/// let model = Model::from_bytes(BLOB)?; // validates everything, once
///
/// // Size the arena from the blob, like CMSIS-NN's buffer-size queries:
/// // the input and the first hidden layer are live together.
/// let need = Runtime::<0>::required_elements(&model);
/// assert_eq!(need, 374);
/// assert!(Runtime::<373>::new(Model::from_bytes(BLOB)?).is_err());
///
/// let mut rt: Runtime<'_, 374> = Runtime::new(model)?;
/// let (inputs, mut pose) = ([0.5f32; 342], [0f32; 311]);
/// rt.run(Phase::from_radians(1.25)?, &inputs, &mut pose)?;
/// assert!(pose.iter().all(|y| y.is_finite()));
/// assert_eq!(rt.clipped_inputs(), 0);
/// # Ok::<(), phasegate::Error>(())
/// ```
pub struct Runtime<'a, const A: usize, const S: usize = 0, const N: usize = 0> {
    model: Model<'a>,
    styles: heapless::Vec<Style<'a>, N>,
    mix: Mix,
    arena: Arena<A>,
    scratch: [i16; S],
    clipped: u32,
}

impl<'a, const A: usize, const S: usize, const N: usize> Runtime<'a, A, S, N> {
    /// Bytes of RAM the buffers (activation arena and adapter scratch) take.
    pub const CAPACITY_BYTES: usize = (A + S) * core::mem::size_of::<i16>();

    /// The arena capacity `A` a model needs, the way CMSIS-NN's
    /// `*_get_buffer_size` functions size a scratch buffer:
    /// `Runtime::<A>::new` accepts the model iff this is `<= A`.
    pub fn required_elements(model: &Model<'_>) -> usize {
        model.arena_elements()
    }

    /// Wraps a validated model; refuses it when its arena does not fit.
    pub fn new(model: Model<'a>) -> Result<Self> {
        const {
            assert!(
                N <= 256,
                "a style bank holds at most 256 styles (StyleId is a u8)"
            )
        };
        let needed = Self::required_elements(&model);
        if needed > A {
            return Err(buffer_error(needed, A));
        }
        Ok(Runtime {
            model,
            styles: heapless::Vec::new(),
            mix: Mix::Base,
            arena: Arena([0; A]),
            scratch: [0; S],
            clipped: 0,
        })
    }

    /// The (base) model.
    pub fn model(&self) -> &Model<'a> {
        &self.model
    }

    /// Adds a style to the bank after checking it belongs to this base:
    /// same base payload CRC ([`Error::StyleMismatch`] otherwise), an
    /// existing layer node with the adapter's dimensions, gating and output
    /// formats ([`Error::StyleIncompatible`]), room in the scratch buffer
    /// ([`Error::BufferTooSmall`]) and in the bank ([`Error::TooManyStyles`]).
    pub fn add_style(&mut self, style: Style<'a>) -> Result<StyleId> {
        let base_crc = self.model.header().payload_crc;
        if style.base_crc() != base_crc {
            return Err(Error::StyleMismatch {
                base_crc,
                style_crc: style.base_crc(),
            });
        }
        let li = style.layer();
        let incompatible = Error::StyleIncompatible { layer: li };
        let base = self.model.kernel(usize::from(li)).ok_or(incompatible)?;
        let base_gate = self
            .model
            .nodes()
            .node(usize::from(li))
            .map_or(GateSource::None, |n| n.gate);
        let (bd, ad) = (base.desc(), style.kernel().desc());
        if bd.in_dim != ad.in_dim
            || bd.out_dim != ad.out_dim
            || style.gating() != self.model.header().gating
            || (style.gate() == GateSource::Phase && base_gate != GateSource::Phase)
        {
            return Err(incompatible);
        }
        let base_recs = base.requant().as_chunks::<REQUANT_RECORD_LEN>().0;
        let style_recs = style.kernel().requant().as_chunks::<REQUANT_RECORD_LEN>().0;
        let same_formats = base_recs.len() == style_recs.len()
            && base_recs.iter().zip(style_recs).all(|(b, s)| {
                Requant::from_bytes(b).map(|r| r.frac) == Requant::from_bytes(s).map(|r| r.frac)
            });
        if !same_formats {
            return Err(incompatible);
        }
        let needed = style.scratch_elements();
        if needed > S {
            return Err(buffer_error(needed, S));
        }
        // Fits: the push below succeeds only while len < N <= 256.
        let id = StyleId(self.styles.len() as u8);
        self.styles.push(style).map_err(|_| Error::TooManyStyles {
            capacity: N as u32, // <= 256, checked at compile time in `new`
        })?;
        Ok(id)
    }

    /// The styles added so far, in [`StyleId`] order.
    pub fn styles(&self) -> &[Style<'a>] {
        &self.styles
    }

    /// The style of `id`.
    pub fn style(&self, id: StyleId) -> Option<&Style<'a>> {
        self.styles.get(usize::from(id.0))
    }

    /// Sets the mix of the following frames (call it between frames, as
    /// often as every frame); refuses unknown styles.
    pub fn set_mix(&mut self, mix: Mix) -> Result<()> {
        for (id, _) in mix.weights() {
            if let Some(id) = id {
                if self.style(id).is_none() {
                    return Err(Error::UnknownStyle {
                        index: u32::from(id.0),
                    });
                }
            }
        }
        self.mix = mix;
        Ok(())
    }

    /// The current mix ([`Mix::Base`] until [`Runtime::set_mix`]).
    pub fn mix(&self) -> Mix {
        self.mix
    }

    /// Integer-only inference with the current mix: `input_q` holds the
    /// quantised input (the input's Q formats, see
    /// [`Runtime::quantise_input`]); returns the i16 outputs, before the
    /// output stage.
    pub fn run_quantised(&mut self, phase: Phase, input_q: &[i16]) -> Result<&[i16]> {
        self.run_quantised_probed(phase, input_q, &mut NoProbe)
    }

    /// [`Runtime::run_quantised`], calling `probe` at every stage boundary
    /// of the frame ([`Mark`]): how the firmware times each node.
    pub fn run_quantised_probed<P: Probe>(
        &mut self,
        phase: Phase,
        input_q: &[i16],
        probe: &mut P,
    ) -> Result<&[i16]> {
        check_len(self.model.input_dim(), input_q.len())?;
        let dst = span_mut(&mut self.arena.0, self.model.header().input)?;
        dst.copy_from_slice(input_q);
        self.forward(phase, probe)?;
        self.output()
    }

    /// Runs the model's stored self-test ([`Model::self_test`]): every
    /// vector's quantised input at its phase through the base model (no
    /// style, whatever the current mix, which is kept), each output
    /// compared with the stored one. Returns how many vectors passed (0
    /// when the blob has no self-test), or
    /// [`Error::SelfTestFailed`] naming the first vector and output that
    /// differ, with the stored and the computed value. Overwrites the
    /// arena (as a frame does).
    #[cfg(any(test, feature = "self-test"))]
    pub fn run_self_test(&mut self) -> Result<u16> {
        let Some(test) = self.model.self_test() else {
            return Ok(0);
        };
        let base = Mix::Base.weights();
        let mut passed = 0u16;
        for (vector, v) in (0u16..).zip(test.vectors()) {
            let dst = span_mut(&mut self.arena.0, self.model.header().input)?;
            for (d, x) in dst.iter_mut().zip(v.inputs()) {
                *d = x;
            }
            forward_graph(
                &self.model,
                &mut self.arena.0,
                &self.styles,
                &base,
                &mut self.scratch,
                Phase::from_bits(v.phase),
                &mut NoProbe,
            )?;
            let got = self.output()?;
            for ((output, &g), e) in (0u16..).zip(got).zip(v.expected()) {
                if g != e {
                    return Err(Error::SelfTestFailed {
                        vector,
                        output,
                        expected: e,
                        got: g,
                    });
                }
            }
            passed = vector.saturating_add(1);
        }
        Ok(passed)
    }

    /// Float in, float out, with the current mix: quantises `input` (model
    /// units; counts the clipped values, see [`Runtime::clipped_inputs`]),
    /// runs the network, writes de-quantised outputs (model units) to `output`.
    pub fn run(&mut self, phase: Phase, input: &[f32], output: &mut [f32]) -> Result<()> {
        check_len(self.model.output_dim(), output.len())?;
        let dst = span_mut(&mut self.arena.0, self.model.header().input)?;
        self.clipped = quantise_into(&self.model, input, dst)?;
        self.forward(phase, &mut NoProbe)?;
        dequantise_into(&self.model, self.output()?, output)
    }

    /// How many inputs of the last `run` fell outside the range the blob
    /// declares and were clipped (0 in normal operation; see the export
    /// report's `input_range_sigma`).
    pub fn clipped_inputs(&self) -> u32 {
        self.clipped
    }

    /// The quantised input for `input` (model units), as `run` computes it:
    /// `q = round((x - offset) * scale)` in IEEE f32, ties away from zero,
    /// saturated to i16.
    pub fn quantise_input(&self, input: &[f32], out: &mut [i16]) -> Result<()> {
        quantise_into(&self.model, input, out).map(|_| ())
    }

    /// De-quantises the i16 outputs of [`Runtime::run_quantised`]:
    /// `y = q * scale + offset` in IEEE f32, as `run` computes it.
    pub fn dequantise_output(&self, q: &[i16], out: &mut [f32]) -> Result<()> {
        dequantise_into(&self.model, q, out)
    }

    /// The model's output slice of the arena.
    fn output(&self) -> Result<&[i16]> {
        let h = self.model.header();
        let s = locate(h, &h.output).ok_or(Error::GraphInvalid { node: STAGE_NODE })?;
        let cap = self.arena.0.len();
        self.arena
            .0
            .get(usize::from(s.offset)..s.end() as usize)
            .ok_or(buffer_error(s.end() as usize, cap))
    }

    /// Runs every node from the quantised input already in the arena:
    /// [`forward_graph`] over this runtime's buffers.
    fn forward<P: Probe>(&mut self, phase: Phase, probe: &mut P) -> Result<()> {
        let weights = self.mix.weights();
        forward_graph(
            &self.model,
            &mut self.arena.0,
            &self.styles,
            &weights,
            &mut self.scratch,
            phase,
            probe,
        )
    }
}

/// The graph of `model` over `arena` (the quantised input already in
/// place), with the styles of `weights` from `styles` adding their adapter
/// outputs through `adapter_out`. Not generic (the probe is a trait object, a
/// call per stage mark): compiled once, in this crate and at its
/// optimisation level, whatever buffer sizes the runtime has and whichever
/// crate instantiates it (the firmware builds the rest for size).
#[inline(never)]
fn forward_graph(
    model: &Model<'_>,
    arena: &mut [i16],
    styles: &[Style<'_>],
    weights: &[(Option<StyleId>, i64); 2],
    adapter_out: &mut [i16],
    phase: Phase,
    probe: &mut dyn Probe,
) -> Result<()> {
    probe.mark(Mark::Start);
    let phase_gate = model.gate(phase);
    probe.mark(Mark::Gate);
    let mut gates = [Gate::SINGLE; MAX_GATES];
    // Each node's output span and gate slot, noted as it runs: later
    // nodes find their slices and gates here instead of decoding the
    // node they read from again.
    let mut outputs = [Span::default(); MAX_NODES];
    let mut slots = [0u8; MAX_NODES];
    let mut softmaxes = 0u8;
    let h = model.header();
    for i in 0..h.nodes.count() {
        let id = i as u8;
        let invalid = Error::GraphInvalid { node: id };
        // The loader decoded every node already; should one not decode
        // now, the frame fails rather than skipping the rest.
        let node = h.nodes.node(i).ok_or(invalid)?;
        if let Some(o) = outputs.get_mut(i) {
            *o = node.output;
        }
        if !in_place(&node) {
            let mut at = usize::from(node.input.offset);
            for s in &node.inputs {
                let base = match s.source {
                    Source::Input => h.input,
                    Source::Node(j) => *outputs.get(usize::from(j)).ok_or(invalid)?,
                };
                let src = within(base, s).ok_or(invalid)?;
                // Past u16 a span cannot name the place: refused, never wrapped.
                let offset = u16::try_from(at).map_err(|_| Error::ArenaOverlap { node: id })?;
                let dst = Span {
                    offset,
                    len: src.len,
                };
                let (from, to, _) = split(arena, src, dst, Span::default())?;
                to.copy_from_slice(from);
                at += usize::from(src.len);
            }
        }
        probe.mark(Mark::Gathered(id));
        let layer = match &node.op {
            NodeOp::Softmax(s) => {
                let logits = span_mut(arena, node.input)?;
                if let Some(g) = gates.get_mut(usize::from(softmaxes)) {
                    *g = Gate::softmax(logits, s.frac)?;
                }
                if let Some(slot) = slots.get_mut(i) {
                    *slot = softmaxes;
                }
                softmaxes = softmaxes.saturating_add(1);
                probe.mark(Mark::Done(id));
                continue;
            }
            NodeOp::Layer(d) => Layer::new(model.node_payload(i), *d, id)
                .ok_or(Error::SectionOutOfBounds { layer: id })?,
        };
        let gate = match node.gate {
            GateSource::None => Gate::SINGLE,
            GateSource::Phase => phase_gate,
            GateSource::Node(j) => slots
                .get(usize::from(j))
                .and_then(|&k| gates.get(usize::from(k)))
                .copied()
                .unwrap_or(Gate::SINGLE),
        };
        let (x, scratch, y) = split(arena, node.input, node.scratch, node.output)?;
        let styled = adapters(styles, weights, i, &phase_gate, x, adapter_out)?;
        if !styled {
            layer.run(&gate, x, scratch, y)?;
            probe.mark(Mark::Done(id));
            continue;
        }
        // A residual node: the base layer without its activation, plus
        // the mixed adapter output, then the base layer's activation.
        let activation = layer.desc().activation;
        let plain = layer.with_activation(Activation::Identity);
        plain.run(&gate, x, scratch, y)?;
        let recs = layer.requant().as_chunks::<REQUANT_RECORD_LEN>().0;
        for ((yj, &rj), rec) in y.iter_mut().zip(&adapter_out[..]).zip(recs) {
            let v = sat_i16(i64::from(*yj) + i64::from(rj));
            *yj = match activation {
                Activation::Identity => v,
                Activation::Elu => {
                    let frac = Requant::from_bytes(rec).map_or(0, |r| r.frac);
                    elu_q(v, frac)
                }
            };
        }
        probe.mark(Mark::Done(id));
    }
    Ok(())
}

/// The activation arena: word-aligned for kernels that load two i16 at a
/// time, and 8-aligned so that a runtime's size grows with `A` by exactly
/// `2 A` rounded up to 8 bytes.
#[repr(C, align(8))]
struct Arena<const A: usize>([i16; A]);

/// Node index of the model's output in errors.
const STAGE_NODE: u8 = crate::graph::IO;

/// The arena elements of `s`, mutably.
fn span_mut(arena: &mut [i16], s: Span) -> Result<&mut [i16]> {
    let cap = arena.len();
    arena
        .get_mut(usize::from(s.offset)..s.end() as usize)
        .ok_or(buffer_error(s.end() as usize, cap))
}

/// Borrows `read` shared and `w1`, `w2` mutably from one arena. The loader
/// proved the three disjoint (empty spans are always disjoint); an overlap
/// or a span past the end is an error, never a panic.
fn split(
    arena: &mut [i16],
    read: Span,
    w1: Span,
    w2: Span,
) -> Result<(&[i16], &mut [i16], &mut [i16])> {
    let cap = arena.len();
    let mut order = [(read, 0usize), (w1, 1), (w2, 2)];
    order.sort_unstable_by_key(|(s, _)| (s.len > 0, s.offset));
    let mut parts: [&mut [i16]; 3] = [&mut [], &mut [], &mut []];
    let mut rest = arena;
    let mut cut = 0usize;
    for (s, slot) in order {
        if s.len == 0 {
            continue;
        }
        let start = usize::from(s.offset);
        let skip = start
            .checked_sub(cut)
            .ok_or(Error::ArenaOverlap { node: STAGE_NODE })?;
        let tail = core::mem::take(&mut rest)
            .split_at_mut_checked(skip)
            .ok_or(buffer_error(s.end() as usize, cap))?
            .1;
        let (piece, after) = tail
            .split_at_mut_checked(usize::from(s.len))
            .ok_or(buffer_error(s.end() as usize, cap))?;
        if let Some(p) = parts.get_mut(slot) {
            *p = piece;
        }
        rest = after;
        cut = s.end() as usize;
    }
    let [r, a, b] = parts;
    Ok((r, a, b))
}

/// Writes the mixed adapter output of node `layer` into `scratch[..out]`:
/// each active style's i16 output (computed from `x`, the layer's input),
/// weighted in Q16 and rounded once. Returns `false` when no style of the
/// mix sits beside this layer.
fn adapters(
    styles: &[Style<'_>],
    weights: &[(Option<StyleId>, i64); 2],
    layer: usize,
    gate: &Gate,
    x: &[i16],
    scratch: &mut [i16],
) -> Result<bool> {
    let mut used = [None::<(&Style<'_>, i64)>; 2];
    for (slot, &(id, w)) in used.iter_mut().zip(weights) {
        if let Some(style) = id.and_then(|id| styles.get(usize::from(id.0))) {
            if usize::from(style.layer()) == layer {
                *slot = Some((style, w));
            }
        }
    }
    let Some(out) = used
        .iter()
        .flatten()
        .map(|(s, _)| usize::from(s.kernel().desc().out_dim))
        .next()
    else {
        return Ok(false);
    };
    let capacity = scratch.len();
    let (first, rest) = scratch
        .split_at_mut_checked(out)
        .ok_or(buffer_error(out, capacity))?;
    let (second, middle) = rest
        .split_at_mut_checked(out)
        .ok_or(buffer_error(2 * out, capacity))?;
    first.fill(0);
    second.fill(0);
    let mut ws = [0i64; 2];
    for ((slot, buf), w) in used.iter().zip([&mut *first, &mut *second]).zip(&mut ws) {
        if let Some((style, weight)) = slot {
            let k = style.kernel();
            let g = match style.gate() {
                GateSource::Phase => *gate,
                _ => Gate::SINGLE,
            };
            k.run(&g, x, middle, buf)?;
            *w = *weight;
        }
    }
    for (r1, &r2) in first.iter_mut().zip(second.iter()) {
        let mixed = ws[0] * i64::from(*r1) + ws[1] * i64::from(r2);
        *r1 = sat_i16(round_shift(mixed, 16));
    }
    Ok(true)
}

pub(crate) fn check_len(expected: usize, found: usize) -> Result<()> {
    if expected == found {
        Ok(())
    } else {
        Err(Error::LengthMismatch {
            expected: expected as u32,
            found: found as u32,
        })
    }
}

fn buffer_error(needed: usize, capacity: usize) -> Error {
    Error::BufferTooSmall {
        needed: needed as u32,
        capacity: capacity as u32,
    }
}

/// Round half away from zero in IEEE f32 arithmetic; saturates; NaN is
/// refused earlier.
fn round_to_i16(v: f32) -> i16 {
    let r = if v >= 0.0 { v + 0.5 } else { v - 0.5 };
    // `as i32` truncates toward zero and saturates, identically on every
    // target (a saturated i32 saturates the i16 the same way an i64 would),
    // and on the Cortex-M4 it is one `VCVT` rather than a software routine.
    sat_i16(i64::from(r as i32))
}

/// Quantises `input` into `out`; returns how many values were clipped.
/// The output stage: `y = q * scale + offset` in IEEE f32, one formula for
/// every runtime's `run` and `dequantise_output`.
pub(crate) fn dequantise_into(model: &Model<'_>, q: &[i16], out: &mut [f32]) -> Result<()> {
    check_len(model.output_dim(), q.len())?;
    check_len(model.output_dim(), out.len())?;
    for ((o, &v), (scale, offset)) in out.iter_mut().zip(q).zip(model.output_stage()) {
        *o = f32::from(v) * scale + offset;
    }
    Ok(())
}

pub(crate) fn quantise_into(model: &Model<'_>, input: &[f32], out: &mut [i16]) -> Result<u32> {
    check_len(model.input_dim(), input.len())?;
    let capacity = out.len();
    let out = out
        .get_mut(..input.len())
        .ok_or(buffer_error(input.len(), capacity))?;
    let mut clipped = 0;
    for (i, ((o, &x), (offset, scale))) in out
        .iter_mut()
        .zip(input)
        .zip(model.input_stage())
        .enumerate()
    {
        if !x.is_finite() {
            return Err(Error::NonFinite { index: i as u32 });
        }
        let q = round_to_i16((x - offset) * scale);
        clipped += u32::from(q == i16::MAX || q == i16::MIN);
        *o = q;
    }
    Ok(clipped)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Same bits as through an i64 (the conversion it had before): every
    /// 61st f32 bit pattern, NaN included.
    #[test]
    fn rounding_through_i32_matches_the_i64_conversion() {
        for bits in (0..=u32::MAX).step_by(61) {
            let v = f32::from_bits(bits);
            let r = if v >= 0.0 { v + 0.5 } else { v - 0.5 };
            assert_eq!(round_to_i16(v), sat_i16(r as i64), "{v:e}");
        }
    }

    #[test]
    fn rounding_is_half_away_and_saturating() {
        assert_eq!(round_to_i16(0.5), 1);
        assert_eq!(round_to_i16(-0.5), -1);
        assert_eq!(round_to_i16(0.49), 0);
        assert_eq!(round_to_i16(1e9), i16::MAX);
        assert_eq!(round_to_i16(-1e9), i16::MIN);
        assert_eq!(round_to_i16(f32::INFINITY), i16::MAX);
    }
}
