//! What the gyro drivers share (modules [`mpu6050`](super::mpu6050) and
//! [`lsm6ds`](super::lsm6ds)): the full scales, the errors, the yaw rate as a trait, and the
//! gyro's bias measured while the robot stands still.
//!
//! # Bias at standstill
//! A MEMS gyro's zero-rate output drifts with temperature and differs per part; integrated for
//! minutes, a bias of 0.5 deg/s turns the map by degrees. While the robot is known to stand
//! (the wheels report no motion, or the robot has just been switched on), [`StillBias`]
//! averages the rate; the mean becomes the bias only when the samples' spread says nothing
//! moved (a robot pushed by hand while its wheels are still is not averaged in). The scan
//! matcher keeps refining it while driving (`frontend::gyro_bias`).

/// Full scale of a gyro.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GyroRange {
    /// +-250 deg/s (+-245 on some parts): a cleaning robot turns at most about 120 deg/s.
    Dps250,
    /// +-500 deg/s.
    Dps500,
    /// +-1000 deg/s.
    Dps1000,
    /// +-2000 deg/s.
    Dps2000,
}

/// What went wrong talking to a gyro.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GyroError<E> {
    /// The bus failed (no answer, arbitration lost, ...).
    Bus(E),
    /// Something answered at the address, but not a part the driver knows.
    NotFound {
        /// Its WHO_AM_I register.
        who_am_i: u8,
    },
}

/// A chip's registers at `address` on an I2C bus: what both gyro drivers read and write.
#[derive(Debug)]
pub(crate) struct Registers<I2C> {
    i2c: I2C,
    address: u8,
}

impl<I2C: embedded_hal::i2c::I2c> Registers<I2C> {
    /// The chip at `address` if its `who_am_i` register reads one of `known`.
    pub(crate) fn probe(
        mut i2c: I2C,
        address: u8,
        who_am_i: u8,
        known: &[u8],
    ) -> Result<Self, GyroError<I2C::Error>> {
        let mut who = [0u8];
        i2c.write_read(address, &[who_am_i], &mut who)
            .map_err(GyroError::Bus)?;
        if !known.contains(&who[0]) {
            return Err(GyroError::NotFound { who_am_i: who[0] });
        }
        Ok(Registers { i2c, address })
    }

    /// Writes `value` into `register`.
    pub(crate) fn write(&mut self, register: u8, value: u8) -> Result<(), GyroError<I2C::Error>> {
        self.i2c
            .write(self.address, &[register, value])
            .map_err(GyroError::Bus)
    }

    /// Two registers from `first` on.
    pub(crate) fn read2(&mut self, first: u8) -> Result<[u8; 2], GyroError<I2C::Error>> {
        let mut b = [0u8; 2];
        self.i2c
            .write_read(self.address, &[first], &mut b)
            .map_err(GyroError::Bus)?;
        Ok(b)
    }

    /// Gives the bus back.
    pub(crate) fn release(self) -> I2C {
        self.i2c
    }
}

/// A gyro that reads the rate about the robot's vertical axis.
pub trait YawGyro {
    /// The bus's error.
    type Error;

    /// The rate about the chip's z axis, rad/s (counter-clockwise seen from above when the
    /// chip lies face up), uncorrected for bias.
    ///
    /// # Errors
    /// A bus error.
    fn yaw_rate(&mut self) -> Result<f32, GyroError<Self::Error>>;
}

/// The gyro's bias from the rates measured while the robot stands still (module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StillBias {
    /// Samples needed before the mean is believed.
    pub min_samples: u32,
    /// Largest standard deviation of still samples, rad/s: more means something moved.
    pub max_spread: f32,
    n: u32,
    mean: f64,
    m2: f64,
}

impl StillBias {
    /// An estimator that believes `min_samples` still samples whose spread stays below
    /// `max_spread` rad/s.
    pub const fn new(min_samples: u32, max_spread: f32) -> Self {
        StillBias {
            min_samples,
            max_spread,
            n: 0,
            mean: 0.0,
            m2: 0.0,
        }
    }

    /// Adds a rate measured while standing still (Welford's running mean and variance).
    pub fn push(&mut self, rate: f32) {
        if !rate.is_finite() {
            return;
        }
        self.n = self.n.saturating_add(1);
        let x = f64::from(rate);
        let d = x - self.mean;
        self.mean += d / f64::from(self.n);
        self.m2 += d * (x - self.mean);
    }

    /// Forgets the samples (the robot moved, or their spread showed it was not still).
    pub fn clear(&mut self) {
        *self = StillBias::new(self.min_samples, self.max_spread);
    }

    /// The bias, once enough samples agree.
    pub fn bias(&self) -> Option<f32> {
        if self.n < self.min_samples.max(2) {
            return None;
        }
        let spread = libm::sqrt(self.m2 / f64::from(self.n - 1));
        (spread <= f64::from(self.max_spread)).then_some(self.mean as f32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bias_is_the_still_mean_only_when_nothing_moved() {
        let mut b = StillBias::new(100, 0.01);
        // A bias of 0.02 rad/s with +-0.005 of noise.
        for k in 0..99 {
            b.push(0.02 + if k % 2 == 0 { 0.005 } else { -0.005 });
        }
        assert_eq!(b.bias(), None, "too few samples");
        b.push(f32::NAN);
        assert_eq!(b.bias(), None, "NaN is not a sample");
        b.push(0.02);
        let bias = b.bias().expect("enough still samples");
        assert!((bias - 0.02).abs() < 1e-4, "{bias}");
        // Pushed by hand: a turn in the samples spreads them beyond the bound.
        for _ in 0..20 {
            b.push(0.5);
        }
        assert_eq!(b.bias(), None);
        b.clear();
        assert_eq!(b.bias(), None);
    }
}
