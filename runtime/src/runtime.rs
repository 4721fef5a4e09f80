//! `Runtime`: the one executor. A model, its two static activation
//! buffers, and optionally a bank of styles (residual adapters beside a
//! base layer) with the per-frame [`Mix`].

use crate::blob::{Activation, Requant, REQUANT_RECORD_LEN};
use crate::error::{Error, Result};
use crate::fixed::elu::elu_q;
use crate::fixed::gate::Gate;
use crate::fixed::phase::Phase;
use crate::fixed::{round_shift, sat_i16};
use crate::model::Model;
use crate::ops::GatedOp;
use crate::style::{Mix, Style, StyleId};

/// Runs a [`Model`] frame by frame, plain or with styles.
///
/// - `W`: capacity, in i16 elements, of each of the two ping-pong
///   activation buffers ([`Model::buffer_elements`] is what a model needs;
///   checked by [`Runtime::new`], so no frame can run out of room);
/// - `S`: capacity of the adapter scratch buffer ([`Style::scratch_elements`]
///   is what a style needs; checked by [`Runtime::add_style`]); 0 for a
///   runtime without styles;
/// - `N`: how many styles the bank holds; 0 for a runtime without styles.
///
/// Its size is `(2 * W + S) * 2` bytes plus the model's header and the bank:
/// put it in a `static` (or on the stack) and the whole inference needs no
/// other RAM. Use [`Runtime::required_elements`] to size `W` from a blob.
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
/// // Size the buffers from the blob, like CMSIS-NN's buffer-size queries.
/// let need = Runtime::<0>::required_elements(&model);
/// assert_eq!(need, 342);
/// assert!(Runtime::<341>::new(Model::from_bytes(BLOB)?).is_err());
///
/// let mut rt: Runtime<'_, 342> = Runtime::new(model)?;
/// let (inputs, mut pose) = ([0.5f32; 342], [0f32; 311]);
/// rt.run(Phase::from_radians(1.25)?, &inputs, &mut pose)?;
/// assert!(pose.iter().all(|y| y.is_finite()));
/// assert_eq!(rt.clipped_inputs(), 0);
/// # Ok::<(), phasegate::Error>(())
/// ```
pub struct Runtime<'a, const W: usize, const S: usize = 0, const N: usize = 0> {
    model: Model<'a>,
    styles: heapless::Vec<Style<'a>, N>,
    mix: Mix,
    a: [i16; W],
    b: [i16; W],
    scratch: [i16; S],
    clipped: u32,
}

impl<'a, const W: usize, const S: usize, const N: usize> Runtime<'a, W, S, N> {
    /// Bytes of RAM the buffers (activations and adapter scratch) take.
    pub const CAPACITY_BYTES: usize = (2 * W + S) * core::mem::size_of::<i16>();

    /// The activation capacity `W` a model needs (each of the two buffers),
    /// the way CMSIS-NN's `*_get_buffer_size` functions size a scratch
    /// buffer: `Runtime::<W>::new` accepts the model iff this is `<= W`.
    pub fn required_elements(model: &Model<'_>) -> usize {
        model.buffer_elements()
    }

    /// Wraps a validated model; refuses it when its widest layer does not fit.
    pub fn new(model: Model<'a>) -> Result<Self> {
        let needed = Self::required_elements(&model);
        if needed > W {
            return Err(buffer_error(needed, W));
        }
        Ok(Runtime {
            model,
            styles: heapless::Vec::new(),
            mix: Mix::Base,
            a: [0; W],
            b: [0; W],
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
    /// existing layer with the adapter's dimensions, gating and output
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
        let (bd, ad) = (base.desc(), style.kernel().desc());
        if bd.in_dim != ad.in_dim
            || bd.out_dim != ad.out_dim
            || style.gating() != self.model.header().gating
            || (ad.gated && !bd.gated)
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
        let id = StyleId(self.styles.len() as u8);
        self.styles.push(style).map_err(|_| Error::TooManyStyles {
            capacity: N.min(256) as u32,
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
    /// quantised input (layer 0's Q format, see [`Runtime::quantise_input`]);
    /// returns the i16 outputs of the last layer, before the output stage.
    pub fn run_quantised(&mut self, phase: Phase, input_q: &[i16]) -> Result<&[i16]> {
        let n = self.model.input_dim();
        check_len(n, input_q.len())?;
        let dst = self.a.get_mut(..n).ok_or(buffer_error(n, W))?;
        dst.copy_from_slice(input_q);
        let in_a = self.forward(phase)?;
        self.output(in_a)
    }

    /// Float in, float out, with the current mix: quantises `input` (model
    /// units; counts the clipped values, see [`Runtime::clipped_inputs`]),
    /// runs the network, writes de-quantised outputs (model units) to `output`.
    pub fn run(&mut self, phase: Phase, input: &[f32], output: &mut [f32]) -> Result<()> {
        check_len(self.model.output_dim(), output.len())?;
        self.clipped = quantise_into(&self.model, input, &mut self.a)?;
        let in_a = self.forward(phase)?;
        dequantise_into(&self.model, self.output(in_a)?, output)
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

    /// The output rows, in buffer `a` when `in_a`, else in `b`.
    fn output(&self, in_a: bool) -> Result<&[i16]> {
        let n = self.model.output_dim();
        let buf = if in_a { &self.a } else { &self.b };
        buf.get(..n).ok_or(buffer_error(n, W))
    }

    /// Runs every layer from the quantised input in `a`, ping-ponging with
    /// `b`, adding the mix's adapters beside their base layers; returns
    /// whether the output ended in `a` (read it with [`Self::output`], so
    /// `run` can de-quantise without copying the model).
    fn forward(&mut self, phase: Phase) -> Result<bool> {
        let gate = self.model.gate(phase);
        let weights = self.mix.weights();
        let mut src = &mut self.a;
        let mut dst = &mut self.b;
        let mut in_a = true;
        for i in 0..self.model.layer_count() {
            let layer = self
                .model
                .kernel(i)
                .ok_or(Error::SectionOutOfBounds { layer: i as u8 })?;
            let g = if layer.desc().gated {
                gate
            } else {
                Gate::SINGLE
            };
            let styled = adapters(
                &self.styles,
                &weights,
                i,
                &gate,
                &src[..],
                &mut self.scratch,
            )?;
            if !styled {
                if layer.run_pingpong(&g, &mut src[..], &mut dst[..])? {
                    core::mem::swap(&mut src, &mut dst);
                    in_a = !in_a;
                }
                continue;
            }
            // A residual node: the base layer without its activation, plus
            // the mixed adapter output, then the base layer's activation.
            let activation = layer.desc().activation;
            let plain = layer.with_activation(Activation::Identity);
            if plain.run_pingpong(&g, &mut src[..], &mut dst[..])? {
                core::mem::swap(&mut src, &mut dst);
                in_a = !in_a;
            }
            let out = usize::from(layer.desc().out_dim);
            let y = src.get_mut(..out).ok_or(buffer_error(out, W))?;
            let recs = layer.requant().as_chunks::<REQUANT_RECORD_LEN>().0;
            for ((yj, &rj), rec) in y.iter_mut().zip(&self.scratch[..]).zip(recs) {
                let v = sat_i16(i64::from(*yj) + i64::from(rj));
                *yj = match activation {
                    Activation::Identity => v,
                    Activation::Elu => {
                        let frac = Requant::from_bytes(rec).map_or(0, |r| r.frac);
                        elu_q(v, frac)
                    }
                };
            }
        }
        Ok(in_a)
    }
}

/// Writes the mixed adapter output of layer `layer` into `scratch[..out]`:
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
            let g = if k.desc().gated { *gate } else { Gate::SINGLE };
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
    // `as i64` truncates toward zero and saturates, identically on every target.
    sat_i16(r as i64)
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
