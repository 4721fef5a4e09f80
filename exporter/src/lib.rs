//! Host-side tools for phasegate: import a trained PFNN, recover the exact
//! phase-spline control points, and run the float reference network that the
//! fixed-point runtime is measured against.

pub mod control_points;
pub mod error;
pub mod float_pfnn;
pub mod pfnn_dir;
pub mod blob_writer;
pub mod calibrate;
pub mod quantise;
pub mod atomic;
pub mod export;
pub mod npz;
pub mod inspect;
