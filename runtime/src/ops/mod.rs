//! The ops: every way a gated layer `y = act(requant(sum_k g_k (W_k x + b_k)))`
//! can compute its products, each in one module behind one trait,
//! [`GatedOp`]:
//!
//! | module | `LayerOp` | `W_k x` |
//! |---|---|---|
//! | [`dense`] | `Dense` | one `out x in` matrix per expert |
//! | [`cp`] | `Cp` | `A diag(d_k) B^T x`, the matrix never formed |
//! | [`diagonal`] | `Diagonal` | `w_k . x` (`in == out`) |
//! | [`rbf`] | `Rbf` | `2^31 exp(-sigma_k^2 |x - c_k|^2)` per row (not linear) |
//! | `dec` (feature `dec`) | `Dec` | `2^31 q_k`, the Student-t soft assignment to the centres `c_k` (not linear) |
//!
//! An op's module holds all of it: binding its payload sections (structural
//! checks), its value checks and overflow proof (re-derived at load from
//! the blob's own numbers), its MAC and scratch figures, and its kernel. The
//! output-row tail (requantisation, activation) and the record checks all
//! ops share are in `common`. [`Layer`] is the closed set of ops the format
//! knows, generated from one list (`closed_set!`); the loader
//! ([`crate::Model`], [`crate::Style`]) and the executors
//! ([`crate::Runtime`]) only go through it.
//!
//! Every op passes one test contract (`ops::contract`, run by
//! `cargo test -p phasegate`): bit-exact against a plain i128 reference, the
//! overflow proof refusing what could overflow and accepting the worst case
//! that cannot, and a bounded fixed-vs-float error. `docs/adding-an-op.md`
//! lists the steps to add one.

#[cfg(all(feature = "kernel-check", phasegate_dsp))]
mod check_rng;
pub(crate) mod common;
pub mod cp;
#[cfg(any(test, feature = "dec"))]
pub mod dec;
pub mod dense;
pub mod diagonal;
pub mod rbf;

#[cfg(test)]
mod contract;

use crate::blob::{Activation, Gating, LayerDesc, LayerOp};
use crate::error::Result;
use crate::fixed::gate::Gate;

pub use common::requantise;

/// One op of a gated layer: load-time validation, overflow proof, cost
/// figures and kernel. `'a` is the blob's lifetime (the op borrows its
/// tables from the payload, which stays in flash).
///
/// The loader calls, for each layer, [`GatedOp::bind`] (sections), then,
/// once the whole header is consistent, [`GatedOp::check`] (values); the
/// executor calls [`GatedOp::run`] every frame, on spans of its arena.
pub trait GatedOp<'a>: Sized {
    /// Header only: multiply-accumulates per frame of the layer `desc`
    /// with `active` experts in use (1 when ungated). Counted by the
    /// header's `macs_per_frame`, which the loader recomputes.
    fn macs(desc: &LayerDesc, active: u64) -> u64;

    /// Header only: i16 elements of the intermediate vector the op keeps
    /// between its stages (0 for a single-stage op): the length of the
    /// node's `scratch` span in the arena plan.
    fn scratch(desc: &LayerDesc) -> usize {
        let _ = desc;
        0
    }

    /// Load, structure: binds the op's sections of `payload`, in the order
    /// of its table in `docs/`, each in bounds, 4-aligned and of its exact
    /// length, plus the op's shape constraints. Layer `index` is for errors.
    fn bind(payload: &'a [u8], desc: LayerDesc, index: u8) -> Result<Self>;

    /// Load, values: every record in range and the overflow proof, for any
    /// i16 input and any gate `gating` can produce. After it succeeds a
    /// frame can only fail on its buffers.
    fn check(&self, gating: &Gating) -> Result<()>;

    /// The layer's descriptor.
    fn desc(&self) -> &LayerDesc;

    /// The descriptor, mutably (the styled runtime swaps the activation).
    fn desc_mut(&mut self) -> &mut LayerDesc;

    /// The `out_dim` requantisation records (one per output row).
    fn requant(&self) -> &'a [u8];

    /// The kernel: `x` has `in_dim` elements, `scratch` at least
    /// [`GatedOp::scratch`], `y` at least `out_dim`; the three never overlap.
    fn run(&self, gate: &Gate, x: &[i16], scratch: &mut [i16], y: &mut [i16]) -> Result<()>;
}

/// Generates [`Layer`], the closed set of ops, from one list of
/// `Variant(Type) = pattern of LayerOp`: the enum, and its [`GatedOp`]
/// implementation, which dispatches on the header's `LayerOp` for the
/// header-only figures and `bind`, and on the variant for the rest. This
/// list is the only place that maps a `LayerOp` to its module.
macro_rules! closed_set {
    ($( $(#[doc = $doc:literal])* $(#[cfg($cfg:meta)])? $variant:ident($ty:ident) = $pat:pat, )*) => {
        /// A validated layer of any op, bound to its payload sections.
        #[derive(Clone, Copy, Debug)]
        pub enum Layer<'a> {
            $( $(#[doc = $doc])* $(#[cfg($cfg)])? $variant($ty<'a>), )*
        }

        impl<'a> GatedOp<'a> for Layer<'a> {
            fn macs(desc: &LayerDesc, active: u64) -> u64 {
                match desc.op { $( $(#[cfg($cfg)])? $pat => $ty::macs(desc, active), )* #[allow(unreachable_patterns)] _ => 0 }
            }
            fn scratch(desc: &LayerDesc) -> usize {
                match desc.op { $( $(#[cfg($cfg)])? $pat => $ty::scratch(desc), )* #[allow(unreachable_patterns)] _ => 0 }
            }
            fn bind(payload: &'a [u8], desc: LayerDesc, index: u8) -> Result<Self> {
                match desc.op {
                    $( $(#[cfg($cfg)])? $pat => $ty::bind(payload, desc, index).map(Layer::$variant), )*
                    // An op the format decodes but this build leaves out.
                    #[allow(unreachable_patterns)]
                    _ => Err(crate::error::Error::UnsupportedParameter { layer: index }),
                }
            }
            fn check(&self, gating: &Gating) -> Result<()> {
                match self { $( $(#[cfg($cfg)])? Layer::$variant(l) => l.check(gating), )* }
            }
            fn desc(&self) -> &LayerDesc {
                match self { $( $(#[cfg($cfg)])? Layer::$variant(l) => l.desc(), )* }
            }
            fn desc_mut(&mut self) -> &mut LayerDesc {
                match self { $( $(#[cfg($cfg)])? Layer::$variant(l) => l.desc_mut(), )* }
            }
            fn requant(&self) -> &'a [u8] {
                match self { $( $(#[cfg($cfg)])? Layer::$variant(l) => l.requant(), )* }
            }
            fn run(&self, gate: &Gate, x: &[i16], scratch: &mut [i16], y: &mut [i16]) -> Result<()> {
                match self { $( $(#[cfg($cfg)])? Layer::$variant(l) => l.run(gate, x, scratch, y), )* }
            }
        }
    };
}

use cp::CpLayer;
#[cfg(any(test, feature = "dec"))]
use dec::DecLayer;
use dense::DenseLayer;
use diagonal::DiagLayer;
use rbf::RbfLayer;

closed_set! {
    /// `LayerOp::Dense`: [`dense`].
    Dense(DenseLayer) = LayerOp::Dense,
    /// `LayerOp::Cp`: [`cp`].
    Cp(CpLayer) = LayerOp::Cp { .. },
    /// `LayerOp::Diagonal`: [`diagonal`].
    Diagonal(DiagLayer) = LayerOp::Diagonal,
    /// `LayerOp::Rbf`: [`rbf`].
    Rbf(RbfLayer) = LayerOp::Rbf { .. },
    /// `LayerOp::Dec`: `dec` (feature `dec`).
    #[cfg(any(test, feature = "dec"))]
    Dec(DecLayer) = LayerOp::Dec { .. },
}

impl<'a> Layer<'a> {
    /// The layer `desc` over `payload`, bound and structurally checked
    /// ([`GatedOp::bind`]); `None` when that fails.
    pub fn new(payload: &'a [u8], desc: LayerDesc, index: u8) -> Option<Layer<'a>> {
        <Layer<'a> as GatedOp<'a>>::bind(payload, desc, index).ok()
    }

    /// The layer's descriptor.
    pub fn desc(&self) -> &LayerDesc {
        GatedOp::desc(self)
    }

    /// The requantisation records (one per output row).
    pub fn requant(&self) -> &'a [u8] {
        GatedOp::requant(self)
    }

    /// The same layer with another activation (the styled runtime runs the
    /// base layer without its ELU, adds the adapter, then applies it).
    pub fn with_activation(mut self, activation: Activation) -> Layer<'a> {
        self.desc_mut().activation = activation;
        self
    }

    /// Elements of scratch [`GatedOp::run`] needs.
    pub fn scratch_elements(&self) -> usize {
        <Layer<'a> as GatedOp<'a>>::scratch(self.desc())
    }
}
