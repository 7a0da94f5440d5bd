//! Error types shared across layers.

use core::fmt;

/// A fixed-capacity container is full.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct CapacityError {
    /// Which container (for messages), e.g. `"nodes"`.
    pub what: &'static str,
    /// Its capacity.
    pub capacity: usize,
}

impl fmt::Display for CapacityError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "the {} pool is full (capacity {})",
            self.what, self.capacity
        )
    }
}

impl core::error::Error for CapacityError {}
