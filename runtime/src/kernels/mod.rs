//! Integer kernels. Everything here is integer-only, so the same blob and
//! input give the same bits on every target.

pub mod dense;
