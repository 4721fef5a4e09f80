//! `StyledRuntime`: a base model, a bank of styles and the per-frame mix.

use fixed::types::U1F15;

use crate::blob::{Activation, Requant, REQUANT_RECORD_LEN};
use crate::error::{Error, Result};
use crate::fixed::elu::elu_q;
use crate::fixed::gate::{Gate, ONE};
use crate::fixed::phase::Phase;
use crate::fixed::{round_shift, sat_i16};
use crate::model::Model;
use crate::ops::GatedOp;
use crate::runtime::{check_len, dequantise_into, quantise_into};
use crate::style::Style;

/// Handle of a style in a [`StyledRuntime`]'s bank.
#[derive(Clone, Copy, Debug, Eq, PartialEq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct StyleId(pub u8);

/// Which adapters a frame uses.
#[derive(Clone, Copy, Debug, Default, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Mix {
    /// No adapter: the base model alone.
    #[default]
    Base,
    /// One style.
    One(StyleId),
    /// Two styles, their adapter outputs interpolated:
    /// `r = (1 - weight) r_from + weight r_to`, `weight` clamped to `[0, 1]`.
    Blend {
        /// Style at weight 0.
        from: StyleId,
        /// Style at weight 1.
        to: StyleId,
        /// Interpolation weight.
        #[cfg_attr(feature = "defmt", defmt(Debug2Format))]
        weight: U1F15,
    },
}

impl Mix {
    /// The active styles with their Q16 weights.
    fn weights(&self) -> [(Option<StyleId>, i64); 2] {
        let one = i64::from(ONE);
        match *self {
            Mix::Base => [(None, 0), (None, 0)],
            Mix::One(s) => [(Some(s), one), (None, 0)],
            Mix::Blend { from, to, weight } => {
                let w = (i64::from(weight.to_bits()) << 1).min(one);
                [(Some(from), one - w), (Some(to), w)]
            }
        }
    }
}

/// Runs a base [`Model`] with up to `N` styles. `W` is the capacity of each
/// of its two activation buffers (as [`crate::Runtime`]'s), `S` of the
/// adapter scratch buffer (see [`Style::scratch_elements`]). Everything is
/// checked when a style is added, so a frame can only fail on its arguments.
///
/// Styles are stateless: switching or blending between frames changes only
/// which adapters the next frame adds, never the phase or any other state,
/// so a switch is exactly as if the new mix had been used all along.
pub struct StyledRuntime<'a, const W: usize, const S: usize, const N: usize> {
    model: Model<'a>,
    styles: heapless::Vec<Style<'a>, N>,
    mix: Mix,
    a: [i16; W],
    b: [i16; W],
    scratch: [i16; S],
}

impl<'a, const W: usize, const S: usize, const N: usize> StyledRuntime<'a, W, S, N> {
    /// Bytes of RAM the buffers take.
    pub const CAPACITY_BYTES: usize = (2 * W + S) * core::mem::size_of::<i16>();

    /// Wraps a validated base model; refuses it when its widest layer does
    /// not fit the activation buffers.
    pub fn new(model: Model<'a>) -> Result<Self> {
        let needed = model.buffer_elements();
        if needed > W {
            return Err(Error::BufferTooSmall {
                needed: needed as u32,
                capacity: W as u32,
            });
        }
        Ok(StyledRuntime {
            model,
            styles: heapless::Vec::new(),
            mix: Mix::Base,
            a: [0; W],
            b: [0; W],
            scratch: [0; S],
        })
    }

    /// The base model.
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
            return Err(Error::BufferTooSmall {
                needed: needed as u32,
                capacity: S as u32,
            });
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

    /// The current mix.
    pub fn mix(&self) -> Mix {
        self.mix
    }

    /// Float in, float out, with the current mix (see [`crate::Runtime::run`]).
    pub fn run(&mut self, phase: Phase, input: &[f32], output: &mut [f32]) -> Result<()> {
        check_len(self.model.output_dim(), output.len())?;
        quantise_into(&self.model, input, &mut self.a)?;
        let in_a = self.forward(phase)?;
        dequantise_into(&self.model, self.output(in_a)?, output)
    }

    /// Integer-only inference with the current mix (see
    /// [`crate::Runtime::run_quantised`]).
    pub fn run_quantised(&mut self, phase: Phase, input_q: &[i16]) -> Result<&[i16]> {
        let n = self.model.input_dim();
        check_len(n, input_q.len())?;
        let dst = self.a.get_mut(..n).ok_or(Error::BufferTooSmall {
            needed: n as u32,
            capacity: W as u32,
        })?;
        dst.copy_from_slice(input_q);
        let in_a = self.forward(phase)?;
        self.output(in_a)
    }

    /// The quantised input for `input` (model units).
    pub fn quantise_input(&self, input: &[f32], out: &mut [i16]) -> Result<()> {
        quantise_into(&self.model, input, out).map(|_| ())
    }

    /// De-quantises the i16 outputs of [`StyledRuntime::run_quantised`]:
    /// `y = q * scale + offset` in IEEE f32, as `run` and
    /// `Runtime::dequantise_output` compute it.
    pub fn dequantise_output(&self, q: &[i16], out: &mut [f32]) -> Result<()> {
        dequantise_into(&self.model, q, out)
    }

    /// The output rows, in buffer `a` when `in_a`, else in `b`.
    fn output(&self, in_a: bool) -> Result<&[i16]> {
        let n = self.model.output_dim();
        let buf = if in_a { &self.a } else { &self.b };
        buf.get(..n).ok_or(Error::BufferTooSmall {
            needed: n as u32,
            capacity: W as u32,
        })
    }

    /// Runs every layer from the quantised input in `a`, ping-ponging with
    /// `b`; returns whether the output ended in `a` (read it with
    /// [`Self::output`], so `run` can de-quantise without copying the model).
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
            let activation = layer.desc().activation;
            let plain = layer.with_activation(Activation::Identity);
            if plain.run_pingpong(&g, &mut src[..], &mut dst[..])? {
                core::mem::swap(&mut src, &mut dst);
                in_a = !in_a;
            }
            let out = usize::from(layer.desc().out_dim);
            let y = src.get_mut(..out).ok_or(Error::BufferTooSmall {
                needed: out as u32,
                capacity: W as u32,
            })?;
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
    let too_small = |needed: usize| Error::BufferTooSmall {
        needed: needed as u32,
        capacity: capacity as u32,
    };
    let (first, rest) = scratch.split_at_mut_checked(out).ok_or(too_small(out))?;
    let (second, middle) = rest.split_at_mut_checked(out).ok_or(too_small(2 * out))?;
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
