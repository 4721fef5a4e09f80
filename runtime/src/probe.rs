//! A hook at the executor's stage boundaries, for measuring where a frame's
//! time goes (the firmware reads SysTick in it; see `docs/performance.md`).
//!
//! [`Runtime::run_quantised`](crate::Runtime::run_quantised) runs with
//! [`NoProbe`], whose empty, inlined [`Probe::mark`] compiles away: the
//! executor's code is the same as without the hook.

/// A boundary between two stages of a frame, in the order they are passed.
#[derive(Clone, Copy, Debug, Eq, PartialEq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Mark {
    /// The executor starts: the quantised input is in the arena.
    Start,
    /// The phase gate is computed.
    Gate,
    /// Node `i`'s input slices are gathered into its input span (nothing
    /// to copy when it reads in place).
    Gathered(u8),
    /// Node `i` has run (a softmax gate its coefficients; a layer its op,
    /// requantisation, activation and any style adapters).
    Done(u8),
}

/// Called by the executor at every [`Mark`] of a frame.
pub trait Probe {
    /// The frame has reached `at`.
    #[inline(always)]
    fn mark(&mut self, at: Mark) {
        let _ = at;
    }
}

/// The probe that does nothing: normal inference.
#[derive(Clone, Copy, Debug, Default)]
pub struct NoProbe;

impl Probe for NoProbe {}
