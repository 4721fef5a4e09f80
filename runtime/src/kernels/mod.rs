//! Integer kernels. Everything here is integer-only, so the same blob and
//! input give the same bits on every target.

pub mod cp;
pub mod dense;
pub mod diag;
pub mod layer;
