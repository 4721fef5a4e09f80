//! `Runtime`: a model plus its two static activation buffers.

use crate::error::{Error, Result};
use crate::fixed::phase::Phase;
use crate::fixed::sat_i16;
use crate::model::Model;
use crate::ops::GatedOp;

/// Runs a [`Model`] frame by frame. `W` is the capacity, in i16 elements, of
/// each of its two ping-pong activation buffers; the model's need is checked
/// against it when the runtime is made, so no frame can run out of room.
///
/// Its size is `2 * W * 2` bytes plus the model's header: put it in a
/// `static` (or on the stack) and the whole inference needs no other RAM.
pub struct Runtime<'a, const W: usize> {
    model: Model<'a>,
    a: [i16; W],
    b: [i16; W],
    clipped: u32,
}

impl<'a, const W: usize> Runtime<'a, W> {
    /// Bytes of activation RAM this runtime holds.
    pub const CAPACITY_BYTES: usize = 2 * W * core::mem::size_of::<i16>();

    /// Wraps a validated model; refuses it when its widest layer does not fit.
    pub fn new(model: Model<'a>) -> Result<Self> {
        let needed = model.buffer_elements();
        if needed > W {
            return Err(Error::BufferTooSmall {
                needed: needed as u32,
                capacity: W as u32,
            });
        }
        Ok(Runtime {
            model,
            a: [0; W],
            b: [0; W],
            clipped: 0,
        })
    }

    /// The model.
    pub fn model(&self) -> &Model<'a> {
        &self.model
    }

    /// Integer-only inference: `input_q` holds the quantised input (layer
    /// 0's Q format, see [`Runtime::quantise_input`]); returns the i16
    /// outputs of the last layer, before the output stage.
    pub fn run_quantised(&mut self, phase: Phase, input_q: &[i16]) -> Result<&[i16]> {
        let n = self.model.input_dim();
        check_len(n, input_q.len())?;
        let dst = self.a.get_mut(..n).ok_or(buffer_error(n, W))?;
        dst.copy_from_slice(input_q);
        self.forward(phase)
    }

    /// Float in, float out: quantises `input` (model units), runs the
    /// network, writes de-quantised outputs (model units) to `output`.
    pub fn run(&mut self, phase: Phase, input: &[f32], output: &mut [f32]) -> Result<()> {
        check_len(self.model.output_dim(), output.len())?;
        let Runtime {
            model,
            a,
            b,
            clipped,
        } = self;
        *clipped = quantise_into(model, input, a)?;
        let q = forward(model, a, b, phase)?;
        dequantise_into(model, q, output)
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

    /// De-quantises the i16 outputs of [`Runtime::run_quantised`].
    pub fn dequantise_output(&self, q: &[i16], out: &mut [f32]) -> Result<()> {
        dequantise_into(&self.model, q, out)
    }

    fn forward(&mut self, phase: Phase) -> Result<&[i16]> {
        forward(&self.model, &mut self.a, &mut self.b, phase)
    }
}

/// Runs every layer, ping-ponging between `a` (which holds the quantised
/// input) and `b`; returns the output slice. A free function over the
/// fields so `run` can read the model's output stage while it holds the
/// result, without copying the model.
fn forward<'s, const W: usize>(
    model: &Model<'_>,
    a: &'s mut [i16; W],
    b: &'s mut [i16; W],
    phase: Phase,
) -> Result<&'s [i16]> {
    let gate = model.gate(phase);
    let mut src = a;
    let mut dst = b;
    for i in 0..model.layer_count() {
        let layer = model
            .kernel(i)
            .ok_or(Error::SectionOutOfBounds { layer: i as u8 })?;
        let g = if layer.desc().gated {
            gate
        } else {
            crate::fixed::gate::Gate::SINGLE
        };
        if layer.run_pingpong(&g, &mut src[..], &mut dst[..])? {
            core::mem::swap(&mut src, &mut dst);
        }
    }
    let n = model.output_dim();
    src.get(..n).ok_or(buffer_error(n, W))
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
