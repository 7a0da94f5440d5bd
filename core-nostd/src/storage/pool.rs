//! A fixed-capacity pool of values addressed by typed ids.
//!
//! The pool does not own its memory: it borrows a slice of [`Slot`]s that the caller provides
//! (a `static`, a field of a resources struct, or a local array in a test), in the manner of
//! smoltcp's socket sets. Insertion and removal are O(1) through a free list threaded through
//! the vacant slots; a full pool returns [`CapacityError`] and never panics.

use core::fmt;
use core::marker::PhantomData;

use crate::error::CapacityError;

/// A typed index into a pool.
pub trait PoolId: Copy + Eq + Ord + fmt::Debug {
    /// The id of slot `index`.
    fn from_index(index: u32) -> Self;
    /// The slot index of this id.
    fn index(self) -> usize;
}

/// Declares a `Copy` newtype id over `u32` that implements [`PoolId`].
#[macro_export]
macro_rules! typed_id {
    ($(#[$meta:meta])* $name:ident) => {
        $(#[$meta])*
        #[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
        #[cfg_attr(feature = "defmt", derive(defmt::Format))]
        pub struct $name(pub u32);

        impl $crate::storage::PoolId for $name {
            #[inline]
            fn from_index(index: u32) -> Self {
                $name(index)
            }
            #[inline]
            fn index(self) -> usize {
                self.0 as usize
            }
        }
    };
}

/// One cell of pool storage.
#[derive(Clone, Copy, Debug, Default)]
pub enum Slot<T> {
    /// Never used since the storage was created.
    #[default]
    Unused,
    /// Used once, now free; `next` is the next free slot (`u32::MAX` ends the list).
    Free {
        /// Next free slot index.
        next: u32,
    },
    /// Holds a value.
    Occupied(T),
}

impl<T> Slot<T> {
    /// Storage of `N` unused slots, usable in a `const` or `static` initialiser.
    pub const fn array<const N: usize>() -> [Slot<T>; N] {
        [const { Slot::Unused }; N]
    }
}

const END: u32 = u32::MAX;

/// A pool of `T` over borrowed slots, addressed by ids of type `I`.
#[derive(Debug)]
pub struct Pool<'a, T, I: PoolId> {
    slots: &'a mut [Slot<T>],
    /// Slots at or above this index have never been used.
    high_water: usize,
    free_head: u32,
    len: usize,
    what: &'static str,
    _id: PhantomData<I>,
}

impl<'a, T, I: PoolId> Pool<'a, T, I> {
    /// A pool over `slots`, which are reset to unused. `what` names the pool in errors.
    /// At most `u32::MAX - 1` slots are used.
    pub fn new(slots: &'a mut [Slot<T>], what: &'static str) -> Self {
        for s in slots.iter_mut() {
            *s = Slot::Unused;
        }
        Pool {
            slots,
            high_water: 0,
            free_head: END,
            len: 0,
            what,
            _id: PhantomData,
        }
    }

    /// Number of values held.
    #[inline]
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when no value is held.
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Number of slots.
    #[inline]
    pub fn capacity(&self) -> usize {
        self.slots.len().min(END as usize)
    }

    /// True when an insertion would fail.
    #[inline]
    pub fn is_full(&self) -> bool {
        self.len >= self.capacity()
    }

    /// Stores `value` and returns its id.
    ///
    /// # Errors
    /// [`CapacityError`] when every slot is taken; the value is dropped.
    pub fn insert(&mut self, value: T) -> Result<I, CapacityError> {
        self.try_insert(value).map_err(|(e, _)| e)
    }

    /// Stores `value` and returns its id, or gives the value back when the pool is full.
    ///
    /// # Errors
    /// [`CapacityError`] with the value when every slot is taken.
    pub fn try_insert(&mut self, value: T) -> Result<I, (CapacityError, T)> {
        let index = if self.free_head != END {
            let index = self.free_head as usize;
            match self.slots.get(index) {
                Some(Slot::Free { next }) => self.free_head = *next,
                // The free list only ever links free slots; treat anything else as full.
                _ => return Err((self.full_error(), value)),
            }
            index
        } else if self.high_water < self.capacity() {
            self.high_water += 1;
            self.high_water - 1
        } else {
            return Err((self.full_error(), value));
        };
        match self.slots.get_mut(index) {
            Some(slot) => {
                *slot = Slot::Occupied(value);
                self.len += 1;
                Ok(I::from_index(index as u32))
            }
            None => Err((self.full_error(), value)),
        }
    }

    fn full_error(&self) -> CapacityError {
        CapacityError {
            what: self.what,
            capacity: self.capacity(),
        }
    }

    /// The value with id `id`, if it is held.
    #[inline]
    pub fn get(&self, id: I) -> Option<&T> {
        match self.slots.get(id.index()) {
            Some(Slot::Occupied(v)) => Some(v),
            _ => None,
        }
    }

    /// The value with id `id`, mutably, if it is held.
    #[inline]
    pub fn get_mut(&mut self, id: I) -> Option<&mut T> {
        match self.slots.get_mut(id.index()) {
            Some(Slot::Occupied(v)) => Some(v),
            _ => None,
        }
    }

    /// True when `id` refers to a held value.
    #[inline]
    pub fn contains(&self, id: I) -> bool {
        self.get(id).is_some()
    }

    /// Removes and returns the value with id `id`; `None` when it is not held.
    pub fn remove(&mut self, id: I) -> Option<T> {
        let index = id.index();
        let slot = self.slots.get_mut(index)?;
        if !matches!(slot, Slot::Occupied(_)) {
            return None;
        }
        let old = core::mem::replace(
            slot,
            Slot::Free {
                next: self.free_head,
            },
        );
        self.free_head = index as u32;
        self.len -= 1;
        match old {
            Slot::Occupied(v) => Some(v),
            _ => None,
        }
    }

    /// Iterates over `(id, &value)` in slot order.
    pub fn iter(&self) -> impl Iterator<Item = (I, &T)> + '_ {
        self.slots
            .iter()
            .take(self.high_water)
            .enumerate()
            .filter_map(|(i, s)| match s {
                Slot::Occupied(v) => Some((I::from_index(i as u32), v)),
                _ => None,
            })
    }

    /// Iterates over `(id, &mut value)` in slot order.
    pub fn iter_mut(&mut self) -> impl Iterator<Item = (I, &mut T)> + '_ {
        self.slots
            .iter_mut()
            .take(self.high_water)
            .enumerate()
            .filter_map(|(i, s)| match s {
                Slot::Occupied(v) => Some((I::from_index(i as u32), v)),
                _ => None,
            })
    }

    /// Removes every value.
    pub fn clear(&mut self) {
        for s in self.slots.iter_mut() {
            *s = Slot::Unused;
        }
        self.high_water = 0;
        self.free_head = END;
        self.len = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    crate::typed_id!(
        /// Test id.
        TestId
    );

    #[test]
    fn fills_then_reports_full_and_reuses_freed_slots() {
        let mut storage = Slot::<u64>::array::<3>();
        let mut pool: Pool<'_, u64, TestId> = Pool::new(&mut storage, "test");
        let a = pool.insert(10).unwrap();
        let b = pool.insert(20).unwrap();
        let c = pool.insert(30).unwrap();
        let err = pool.try_insert(40).unwrap_err();
        assert_eq!(
            err.0,
            CapacityError {
                what: "test",
                capacity: 3
            }
        );
        assert_eq!(err.1, 40, "the rejected value is handed back");
        assert_eq!(pool.remove(b), Some(20));
        assert_eq!(pool.remove(b), None);
        assert_eq!(pool.get(b), None);
        let d = pool.insert(50).unwrap();
        assert_eq!(d, b, "a freed slot is reused");
        let all: heapless::Vec<(TestId, u64), 3> = pool.iter().map(|(i, v)| (i, *v)).collect();
        assert_eq!(&all[..], &[(a, 10), (b, 50), (c, 30)]);
        assert_eq!(pool.len(), 3);
        pool.clear();
        assert!(pool.is_empty());
    }

    #[test]
    fn out_of_range_ids_are_absent() {
        let mut storage = Slot::<u8>::array::<2>();
        let mut pool: Pool<'_, u8, TestId> = Pool::new(&mut storage, "test");
        assert!(pool.get(TestId(7)).is_none());
        assert!(pool.remove(TestId(7)).is_none());
        assert!(pool.get_mut(TestId(1)).is_none());
    }
}
