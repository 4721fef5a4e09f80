//! One gated layer of any op, ready to run: the dispatch between the dense,
//! CP and diagonal kernels.

use crate::blob::{Activation, LayerDesc, LayerOp, Section};
use crate::error::Result;
use crate::fixed::gate::Gate;
use crate::kernels::cp::CpLayer;
use crate::kernels::dense::DenseLayer;
use crate::kernels::diag::DiagLayer;

/// A validated layer of any op, with its payload sections.
#[derive(Clone, Copy, Debug)]
pub enum Kernel<'a> {
    /// `LayerOp::Dense`.
    Dense(DenseLayer<'a>),
    /// `LayerOp::Cp`.
    Cp(CpLayer<'a>),
    /// `LayerOp::Diagonal`.
    Diagonal(DiagLayer<'a>),
}

fn section(payload: &[u8], s: Section) -> Option<&[u8]> {
    payload.get(s.offset as usize..s.end()? as usize)
}

impl<'a> Kernel<'a> {
    /// The kernel of `desc` over `payload`; `None` when a section lies
    /// outside the payload (the loader has refused such blobs already).
    pub fn new(payload: &'a [u8], desc: LayerDesc, index: u8) -> Option<Kernel<'a>> {
        let weights = section(payload, desc.weight_section)?;
        let bias = section(payload, desc.bias_section)?;
        let requant = section(payload, desc.requant_section)?;
        Some(match desc.op {
            LayerOp::Dense => Kernel::Dense(DenseLayer {
                desc,
                weights,
                bias,
                requant,
                index,
            }),
            LayerOp::Cp {
                rank,
                a,
                cores,
                mid,
            } => Kernel::Cp(CpLayer {
                desc,
                rank,
                bt: weights,
                a: section(payload, a)?,
                cores: section(payload, cores)?,
                mid: section(payload, mid)?,
                bias,
                requant,
                index,
            }),
            LayerOp::Diagonal => Kernel::Diagonal(DiagLayer {
                desc,
                weights,
                bias,
                requant,
                index,
            }),
        })
    }

    /// The layer's descriptor.
    pub fn desc(&self) -> &LayerDesc {
        match self {
            Kernel::Dense(l) => &l.desc,
            Kernel::Cp(l) => &l.desc,
            Kernel::Diagonal(l) => &l.desc,
        }
    }

    /// The requantisation records (one per output row).
    pub fn requant(&self) -> &'a [u8] {
        match self {
            Kernel::Dense(l) => l.requant,
            Kernel::Cp(l) => l.requant,
            Kernel::Diagonal(l) => l.requant,
        }
    }

    /// The same layer with another activation (the styled runtime runs the
    /// base layer without its ELU, adds the adapter, then applies it).
    pub fn with_activation(mut self, activation: Activation) -> Kernel<'a> {
        match &mut self {
            Kernel::Dense(l) => l.desc.activation = activation,
            Kernel::Cp(l) => l.desc.activation = activation,
            Kernel::Diagonal(l) => l.desc.activation = activation,
        }
        self
    }

    /// Runs the layer with two ping-pong buffers: reads `src`; returns
    /// `true` when the output is in `dst` (swap the buffers), `false` when
    /// it is back in `src` (a CP layer keeps its middle vector in `dst`).
    pub fn run_pingpong(&self, gate: &Gate, src: &mut [i16], dst: &mut [i16]) -> Result<bool> {
        match self {
            Kernel::Dense(l) => l.run(gate, src, dst).map(|()| true),
            Kernel::Diagonal(l) => l.run(gate, src, dst).map(|()| true),
            Kernel::Cp(l) => {
                l.middle(gate, src, dst)?;
                l.output(gate, dst, src)?;
                Ok(false)
            }
        }
    }

    /// Runs the layer from `x` into `y`, using `scratch` (at least the rank
    /// of a CP layer) for the middle vector.
    pub fn run_into(
        &self,
        gate: &Gate,
        x: &[i16],
        scratch: &mut [i16],
        y: &mut [i16],
    ) -> Result<()> {
        match self {
            Kernel::Dense(l) => l.run(gate, x, y),
            Kernel::Diagonal(l) => l.run(gate, x, y),
            Kernel::Cp(l) => {
                l.middle(gate, x, scratch)?;
                l.output(gate, scratch, y)
            }
        }
    }

    /// Elements of scratch [`Kernel::run_into`] needs.
    pub fn scratch_elements(&self) -> usize {
        match self {
            Kernel::Cp(l) => usize::from(l.rank),
            _ => 0,
        }
    }

    /// Index of the layer, for errors.
    pub fn index(&self) -> u8 {
        match self {
            Kernel::Dense(l) => l.index,
            Kernel::Cp(l) => l.index,
            Kernel::Diagonal(l) => l.index,
        }
    }
}
