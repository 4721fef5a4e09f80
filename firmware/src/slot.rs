//! [`Slot`]: the firmware binaries' one way to own static buffers.

use core::cell::UnsafeCell;
use core::mem::MaybeUninit;
use core::sync::atomic::{AtomicBool, Ordering};

/// A `static` handed out once as `&'static mut` (no heap, no `static mut`).
/// Holds either a value written at run time or a constant initial value
/// (which then lives in .bss/.data and is never copied through the stack).
pub struct Slot<T> {
    taken: AtomicBool,
    value: UnsafeCell<MaybeUninit<T>>,
}

// SAFETY: `take`/`init` hand out the only reference, once (guarded by `taken`).
unsafe impl<T> Sync for Slot<T> {}

impl<T> Slot<T> {
    /// An empty slot, filled by [`Slot::init`].
    pub const fn empty() -> Self {
        Slot {
            taken: AtomicBool::new(false),
            value: UnsafeCell::new(MaybeUninit::uninit()),
        }
    }

    /// A slot holding `value` from the start, handed out by [`Slot::take`].
    pub const fn with(value: T) -> Self {
        Slot {
            taken: AtomicBool::new(false),
            value: UnsafeCell::new(MaybeUninit::new(value)),
        }
    }

    /// Moves `value` into an empty slot and returns the only `&mut` to it;
    /// `None` if the slot was handed out before.
    // A `&mut` from `&self` is the point (as in static_cell): `taken` makes it unique.
    #[allow(clippy::mut_from_ref)]
    pub fn init(&'static self, value: T) -> Option<&'static mut T> {
        if self.taken.swap(true, Ordering::AcqRel) {
            return None;
        }
        // SAFETY: first and only hand-out (checked above): no other reference.
        Some(unsafe { (*self.value.get()).write(value) })
    }

    /// The only `&mut` to a slot made with [`Slot::with`]; `None` if handed
    /// out before.
    ///
    /// # Safety
    /// The slot must have been made with [`Slot::with`] (initialised).
    #[allow(clippy::mut_from_ref)]
    pub unsafe fn take(&'static self) -> Option<&'static mut T> {
        if self.taken.swap(true, Ordering::AcqRel) {
            return None;
        }
        // SAFETY: initialised (caller's contract), first and only hand-out.
        Some(unsafe { (*self.value.get()).assume_init_mut() })
    }
}
