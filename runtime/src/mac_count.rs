//! Multiply-accumulates the kernels actually perform, counted when the
//! `mac-count` feature is on (host builds; it needs 64-bit atomics), so a
//! test can hold the header's `macs_per_frame` to what the runtime does
//! (issue 12's op-count honesty check, `tests/tests/mac_count.rs`). Without
//! the feature [`add`] is empty and the counting loops compile away.

#[cfg(all(feature = "mac-count", target_has_atomic = "64"))]
static MACS: core::sync::atomic::AtomicU64 = core::sync::atomic::AtomicU64::new(0);

/// Adds `n` multiply-accumulates.
#[inline(always)]
pub fn add(n: usize) {
    #[cfg(all(feature = "mac-count", target_has_atomic = "64"))]
    MACS.fetch_add(n as u64, core::sync::atomic::Ordering::Relaxed);
    #[cfg(not(all(feature = "mac-count", target_has_atomic = "64")))]
    let _ = n;
}

/// The count since the last call (0 without the feature).
pub fn take() -> u64 {
    #[cfg(all(feature = "mac-count", target_has_atomic = "64"))]
    return MACS.swap(0, core::sync::atomic::Ordering::Relaxed);
    #[cfg(not(all(feature = "mac-count", target_has_atomic = "64")))]
    0
}

/// Whether this build counts.
pub const COUNTING: bool = cfg!(all(feature = "mac-count", target_has_atomic = "64"));
