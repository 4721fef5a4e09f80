//! Host-side tools for phasegate: import a trained PFNN, recover the exact
//! phase-spline control points, and run the float reference network that the
//! fixed-point runtime is measured against.

pub mod budget;
pub mod calibrate;
pub mod cli_args;
pub mod cli_contract;
pub mod control_points;
pub mod cost;
pub mod cp;
pub mod encode;
pub mod error;
pub mod export;
pub mod inspect;
pub mod io;
pub mod lower;
pub mod net;
pub mod npz;
pub mod ops;
pub mod pfnn_dir;
pub mod plan;
pub mod progress;
pub mod quantise;
pub mod rig;
pub mod self_test;
pub mod style;

// The modules' old paths, until their users move (docs/architecture.md).
pub use io::{atomic, sizes};
