//! Time stamps.

use core::fmt;

/// A point in time: signed nanoseconds since an epoch chosen by the caller (Unix time for
/// recorded logs, boot time on a robot). `i64` nanoseconds span about +-292 years.
///
/// The core never reads a clock; every stamp comes from the caller.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Timestamp(pub i64);

impl Timestamp {
    /// The time `ns` nanoseconds after the epoch.
    pub const fn from_nanos(ns: i64) -> Self {
        Self(ns)
    }

    /// Nanoseconds since the epoch.
    pub const fn as_nanos(self) -> i64 {
        self.0
    }

    /// Seconds since the epoch (`f64` keeps about 0.1 us near 1e9 s).
    pub fn as_secs_f64(self) -> f64 {
        self.0 as f64 * 1e-9
    }

    /// Seconds from `earlier` to `self` (negative if `earlier` is later), or `None` on overflow.
    pub fn seconds_since(self, earlier: Timestamp) -> Option<f64> {
        self.0.checked_sub(earlier.0).map(|d| d as f64 * 1e-9)
    }
}

impl fmt::Display for Timestamp {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let secs = self.0.div_euclid(1_000_000_000);
        let nanos = self.0.rem_euclid(1_000_000_000);
        write!(f, "{secs}.{nanos:09}")
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use std::string::ToString;

    use super::*;

    #[test]
    fn displays_as_decimal_seconds() {
        assert_eq!(Timestamp(1_500_000_001).to_string(), "1.500000001");
        assert_eq!(Timestamp(-1).to_string(), "-1.999999999");
        assert_eq!(Timestamp(0).to_string(), "0.000000000");
    }

    #[test]
    fn differences() {
        let a = Timestamp::from_nanos(1_000);
        let b = Timestamp::from_nanos(501_000);
        assert_eq!(b.seconds_since(a), Some(0.0005));
        assert_eq!(Timestamp(i64::MIN).seconds_since(Timestamp(1)), None);
        assert!(a < b);
    }
}
