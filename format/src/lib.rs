//! The phasegate blob format: framing, header and payload records
//! (`docs/blob-format.md`, `docs/graph-format.md`), and the one error type
//! of loading and running a blob. `phasegate` re-exports both as
//! `phasegate::blob` and `phasegate::Error`; this crate exists so that a
//! firmware can optimise this load-time code for size while the runtime's
//! kernels are optimised for speed.
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

pub mod blob;
pub mod error;

pub use error::{Error, Result};
