//! Layer 1 of the exporter: files and arrays, knowing nothing of networks.
//! Atomic output and input guards, checked sizes, tensors by name (`.npz`,
//! `.safetensors`), and input rows (drawn or recorded).

pub mod atomic;
pub mod samples;
pub mod sizes;
pub mod tensors;
