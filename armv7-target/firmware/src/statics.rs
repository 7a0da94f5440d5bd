//! Static storage handed out once as `&'static mut`: how the large buffers of the mapper
//! (its resources, the read buffer, per-scan counts) live in `.bss` instead of on the stack.

use core::cell::UnsafeCell;
use core::sync::atomic::{AtomicBool, Ordering};

/// A value in a `static` that one caller may borrow mutably, once.
pub struct TakeOnce<T> {
    value: UnsafeCell<T>,
    taken: AtomicBool,
}

// SAFETY: the value is reachable only through `take`, which hands out at most one reference
// for the whole program (the flag is swapped atomically).
unsafe impl<T: Send> Sync for TakeOnce<T> {}

impl<T> TakeOnce<T> {
    /// Wraps a value built at compile time.
    pub const fn new(value: T) -> Self {
        Self {
            value: UnsafeCell::new(value),
            taken: AtomicBool::new(false),
        }
    }

    /// The value, the first time; `None` after that.
    // A unique `&mut` from `&self` is the point: the atomic flag makes it the only one.
    #[allow(clippy::mut_from_ref)]
    pub fn take(&'static self) -> Option<&'static mut T> {
        if self.taken.swap(true, Ordering::AcqRel) {
            return None;
        }
        // SAFETY: the flag guarantees this is the only reference ever created.
        Some(unsafe { &mut *self.value.get() })
    }
}
