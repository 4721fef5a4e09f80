//! PFNN locomotion control: stick in, pose out, every frame; and OMG
//! reaching control ([`Reach`]: targets in, pose out, every frame).
//!
//! [`PfnnController`] runs the public PFNN demo's character loop on flat
//! ground (trajectory blending toward the command, gait blending, the 342
//! inputs in root space, inference at the current phase, joint blending,
//! trajectory and root update, phase update) over any [`Network`], in `f32`
//! with no heap; on the device that is the fixed-point
//! [`phasegate::Runtime`] (plain or with styles). Foot IK is not done:
//! the pose is the network's, which is what the fidelity checks compare.
//!
//! The loop itself ([`Locomotion`]) is generic over the scalar ([`Real`]:
//! `f32` or `f64`) and the network ([`Network`]), so the host's float
//! reference runs the very same code in `f64` over the float network; the
//! two differ in arithmetic only. `docs/controller.md` describes the loop,
//! its departures from the demo and the fidelity measured on the real PFNN.
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

mod command;
pub mod deadline;
mod error;
mod f32_math;
pub mod geom;
pub mod layout;
mod locomotion;
mod pfnn;
mod pose;
pub mod reach;
mod real;
pub mod skeleton;
pub mod trajectory;

pub use command::{field, Command, Gait, GaitWeights, MAX_SPEED, MIN_FACING};
pub use deadline::{
    Deadline, DeadlineConfig, FrameAction, FrameBudget, FrameOutcome, OverrunPolicy, TickSource,
    TimedFrame,
};
pub use error::{Error, Result, SkeletonCheck};
pub use locomotion::{rates, Locomotion, Network};
pub use pfnn::{phase_from_cycles, PfnnController};
pub use pose::Pose;
pub use reach::{CostMode, PoseForm, Reach, ReachLayout, ReachPose, Skeleton, Target};
pub use real::Real;
