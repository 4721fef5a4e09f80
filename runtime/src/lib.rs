//! phasegate: a `no_std`, heap-free, fixed-point runtime for phase-gated
//! motion networks (PFNN, and the gated layers OMG is built from).
//!
//! ```text
//! let model = Model::from_bytes(BLOB)?;            // validates everything once
//! let mut rt: Runtime<'_, 1024> = Runtime::new(model)?; // arena, i16 elements
//! rt.run(Phase::from_radians(p)?, &inputs, &mut outputs)?;
//! ```
//!
//! The blob format is specified in `docs/blob-format.md`; the fixed-point
//! scheme in `docs/fixed-point.md`.
#![cfg_attr(not(test), no_std)]
#![deny(missing_docs)]
#![cfg_attr(
    not(test),
    deny(
        clippy::unwrap_used,
        clippy::expect_used,
        clippy::panic,
        clippy::indexing_slicing
    )
)]

pub use phasegate_format::blob;
use phasegate_format::error;
pub(crate) mod fixed;
pub mod graph;
pub mod mac_count;
mod model;
pub mod ops;
pub mod probe;
#[cfg(feature = "rig")]
pub mod rig;
mod runtime;
pub mod style;

pub use blob::{blob_len_from_prefix, Header};
pub use error::{Error, Result};
pub use fixed::elu::elu_q;
pub use fixed::gate::Gate;
pub use fixed::phase::Phase;
pub use fixed::softmax::MAX_LOGITS;
pub use model::{macs, node_gating, Model, MAX_GATES, STAGE};
pub use probe::{Mark, NoProbe, Probe};
#[cfg(feature = "rig")]
pub use rig::RigInfo;
pub use runtime::Runtime;
pub use style::{Mix, Style, StyleId};
#[cfg(test)]
mod self_test_tests;
