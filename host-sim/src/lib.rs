//! host-sim: runs the phasegate runtime on the host, runs the float
//! references, compares them, and drives the demos and golden vectors.

pub mod accuracy;
pub mod compare;
pub mod controller;
pub mod default_model;
pub mod demo;
pub mod demo_omg;
pub mod eval;
pub mod footprint;
pub mod golden;
pub mod npy;
pub mod omg;
pub mod omg_reach;
pub mod omg_rollout;
pub mod quant_knobs;
pub mod reach_metrics;
pub mod render;
pub mod rollout;
pub mod saturation;
pub mod style;
pub mod target;
