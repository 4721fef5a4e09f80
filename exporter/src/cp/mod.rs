//! CP-decomposed layers on the exporter side, beyond the op itself
//! ([`crate::ops::cp`]): decomposition of dense expert weights by CP-ALS
//! ([`als`]), import of trained CP factors from `.npz` / `.safetensors`
//! ([`import`]), the per-rank report on a real network ([`report`]) and
//! distillation ([`distill`]).
//!
//! See `docs/cp-and-styles.md` for the formats and the measurements.

pub mod als;
pub mod cli;
pub mod distill;
pub mod import;
pub mod report;
