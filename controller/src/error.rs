//! The one error type of the controller crate.

use core::fmt;

/// Everything that can go wrong when making a controller or stepping it.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum Error {
    /// The runtime refused something (a model too wide for the buffers, a
    /// NaN network input, a slice of the wrong length, ...).
    Runtime(phasegate::Error),
    /// A command holds NaN or an infinity; the frame is refused and the
    /// controller's state is unchanged. (Finite out-of-range values are
    /// clamped instead.)
    BadCommand {
        /// The field, numbered as in [`crate::field`]: 0-1 velocity,
        /// 2-3 facing, 4-7 gait stand, walk, jog, crouch.
        field: u8,
    },
    /// The network is not PFNN-shaped (342 inputs, 311 outputs), so the
    /// locomotion loop cannot drive it.
    NotPfnn {
        /// Inputs of the network.
        inputs: u32,
        /// Outputs of the network.
        outputs: u32,
    },
    /// The network gave a NaN or infinite output (only a float network
    /// can: fixed-point outputs are bounded), or a reaching controller's
    /// starting frame holds one; the pose is left untouched.
    NonFinite {
        /// Index of the first offending output.
        index: u32,
    },
    /// A reaching target holds NaN, an infinity, a coordinate beyond
    /// [`crate::reach::MAX_TARGET_M`] or an axis of no length; refused, the
    /// controller's targets are unchanged.
    BadTarget {
        /// 0-2 position, 3-5 forward, 6-8 up (or the value's index in a
        /// whole target block); 255: no such key joint.
        field: u8,
    },
    /// A reaching layout does not fit itself, the network or the
    /// skeleton ([`crate::reach::ReachLayout::check`],
    /// [`crate::reach::Reach::with_dofs`]).
    BadLayout {
        /// The failed check: 0 frame width vs network inputs, 1 no key
        /// joints, 2 positions, 3 rotations, 4 costs, 5 targets, 6 key
        /// joint indices, 7 network output blocks; the joint-velocity form:
        /// 8 its `u` block (within the outputs, one value per DOF), 9 its
        /// velocity block (3 per joint), 10 the pose entry of the output
        /// blocks (empty in this form), 11 the skeleton's joints vs the
        /// frame's; 12 the constructor does not build the layout's pose form
        /// (`Reach::new`: absolute, `Reach::with_dofs`: joint velocity).
        reason: u8,
    },
    /// A skeleton refused by [`crate::reach::Skeleton::new`].
    BadSkeleton {
        /// The check that failed.
        check: SkeletonCheck,
        /// The joint (or DOF, for the DOF checks) it failed on; the
        /// capacity for the two capacity checks; 0 for the rates.
        index: u16,
    },
    /// A joint-velocity reaching controller's start state (joint angles
    /// `q0`, velocities `v0`) holds NaN or an infinity.
    BadStart {
        /// Index of the first offending value: `0..D` in `q0`, `D..2D` in
        /// `v0`.
        index: u16,
    },
    /// Frames wider than the controller's buffers.
    TooWide {
        /// Values needed.
        width: u32,
        /// Values the buffers hold.
        capacity: u32,
    },
    /// A frame budget of 0 ticks (or more than `u32::MAX`, given in
    /// instructions): no frame could meet it; configure no budget instead.
    BadBudget {
        /// The budget asked for, in ticks.
        ticks: u32,
    },
    /// An overrun policy number that names no policy (0 report, 1 hold
    /// next).
    BadPolicy {
        /// The number.
        value: u32,
    },
}

/// Which check refused a skeleton ([`Error::BadSkeleton`]).
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum SkeletonCheck {
    /// More joints than [`crate::reach::MAX_JOINTS`].
    TooManyJoints,
    /// More DOFs than [`crate::reach::MAX_DOFS`].
    TooManyDofs,
    /// A joint's parent does not come before it.
    Parent,
    /// A rest offset coordinate is not finite or beyond
    /// [`crate::skeleton::MAX_OFFSET_M`].
    Offset,
    /// A DOF names no joint of the skeleton.
    DofJoint,
    /// A DOF's axis is not 0 (x), 1 (y) or 2 (z).
    DofAxis,
    /// A DOF's limits are not finite, or `lower > upper`.
    DofLimits,
    /// A second DOF on the same joint and axis.
    DuplicateDof,
    /// The frame rate is not finite and positive.
    Fps,
    /// The acceleration limit is not finite and positive.
    AMax,
}

impl SkeletonCheck {
    /// What the check requires, in words.
    pub fn describe(self) -> &'static str {
        match self {
            SkeletonCheck::TooManyJoints => "at most 64 joints",
            SkeletonCheck::TooManyDofs => "at most 64 DOFs",
            SkeletonCheck::Parent => "a joint's parent comes before it",
            SkeletonCheck::Offset => "offsets finite and within 100 m",
            SkeletonCheck::DofJoint => "a DOF names a joint of the skeleton",
            SkeletonCheck::DofAxis => "a DOF's axis is 0, 1 or 2",
            SkeletonCheck::DofLimits => "a DOF's limits finite, lower <= upper",
            SkeletonCheck::DuplicateDof => "one DOF per joint and axis",
            SkeletonCheck::Fps => "fps finite and positive",
            SkeletonCheck::AMax => "a_max finite and positive",
        }
    }
}

/// Result with the controller's [`Error`].
pub type Result<T> = core::result::Result<T, Error>;

impl From<phasegate::Error> for Error {
    fn from(e: phasegate::Error) -> Self {
        Error::Runtime(e)
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Error::Runtime(e) => e.fmt(f),
            Error::BadCommand { field } => {
                write!(f, "controller command field {field} is NaN or infinite")
            }
            Error::NotPfnn { inputs, outputs } => write!(
                f,
                "model has {inputs} inputs and {outputs} outputs; a PFNN controller needs 342 and 311"
            ),
            Error::NonFinite { index } => {
                write!(f, "network output {index} is NaN or infinite")
            }
            Error::BadTarget { field } => {
                write!(f, "reaching target field {field} is not finite, too far or has no direction")
            }
            Error::BadLayout { reason } => {
                write!(f, "reaching layout does not fit the network (check {reason})")
            }
            Error::BadSkeleton { check, index } => write!(
                f,
                "skeleton refused at joint or DOF {index}: {} ({check:?})",
                check.describe()
            ),
            Error::BadStart { index } => {
                write!(f, "reaching start state value {index} is NaN or infinite")
            }
            Error::TooWide { width, capacity } => write!(
                f,
                "frames of {width} values do not fit the controller's {capacity}-value buffers"
            ),
            Error::BadBudget { ticks } => write!(
                f,
                "frame budget of {ticks} ticks refused: it must be at least 1 tick and fit in 32 bits"
            ),
            Error::BadPolicy { value } => write!(
                f,
                "overrun policy {value} is unknown (0 report, 1 hold next)"
            ),
        }
    }
}

impl core::error::Error for Error {
    fn source(&self) -> Option<&(dyn core::error::Error + 'static)> {
        match self {
            Error::Runtime(e) => Some(e),
            _ => None,
        }
    }
}
