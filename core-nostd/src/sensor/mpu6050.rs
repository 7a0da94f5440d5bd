//! The InvenSense MPU-6050 family's gyro over I2C (`embedded-hal` 1.0): the yaw rate the
//! odometry fusion takes (paper III-B.2: wheels and a slow gyro).
//!
//! # Registers (from the vendor's public register map)
//! | register | use here |
//! |---|---|
//! | `0x75` WHO_AM_I | `0x68` (MPU-6050), `0x70` (MPU-6500), `0x71` (MPU-9250), `0x73` (MPU-9255) |
//! | `0x6B` PWR_MGMT_1 | `0x80` resets; `0x01` wakes with the X gyro's PLL as the clock |
//! | `0x1A` CONFIG | low-pass filter `3`: 44 Hz bandwidth, 1 kHz gyro output |
//! | `0x19` SMPLRT_DIV | sample rate = 1 kHz / (1 + divider) |
//! | `0x1B` GYRO_CONFIG | full scale in bits 4:3: +-250, 500, 1000, 2000 deg/s |
//! | `0x47`, `0x48` GYRO_ZOUT | yaw rate, big-endian `i16`, 131 / 65.5 / 32.8 / 16.4 LSB per deg/s |
//!
//! The driver owns the bus handle and never blocks beyond the bus calls; the reset's settling
//! time is the caller's (it has the clock): [`Mpu6050::reset`], wait 100 ms, then
//! [`Mpu6050::configure`].
//!
//! The bias at standstill is module [`gyro`](super::gyro)'s.

use embedded_hal::i2c::I2c;

use super::gyro::{GyroError, GyroRange, Registers, YawGyro};

/// The chip's I2C address with its AD0 pin low (`0x69` with AD0 high).
pub const DEFAULT_ADDRESS: u8 = 0x68;

const WHO_AM_I: u8 = 0x75;
const PWR_MGMT_1: u8 = 0x6B;
const CONFIG: u8 = 0x1A;
const SMPLRT_DIV: u8 = 0x19;
const GYRO_CONFIG: u8 = 0x1B;
const GYRO_ZOUT_H: u8 = 0x47;

/// WHO_AM_I answers of the parts whose gyro registers are the MPU-6050's.
pub const KNOWN_PARTS: [u8; 4] = [0x68, 0x70, 0x71, 0x73];

/// Bits 4:3 of GYRO_CONFIG for `range`.
fn range_bits(range: GyroRange) -> u8 {
    (match range {
        GyroRange::Dps250 => 0,
        GyroRange::Dps500 => 1,
        GyroRange::Dps1000 => 2,
        GyroRange::Dps2000 => 3,
    }) << 3
}

/// Radians per second of one count at `range`.
fn rad_per_lsb(range: GyroRange) -> f32 {
    let lsb_per_dps = match range {
        GyroRange::Dps250 => 131.0,
        GyroRange::Dps500 => 65.5,
        GyroRange::Dps1000 => 32.8,
        GyroRange::Dps2000 => 16.4,
    };
    core::f32::consts::PI / 180.0 / lsb_per_dps
}

/// An MPU-6050 (or MPU-6500 / 9250 / 9255) on an I2C bus.
#[derive(Debug)]
pub struct Mpu6050<I2C> {
    regs: Registers<I2C>,
    range: GyroRange,
}

impl<I2C: I2c> Mpu6050<I2C> {
    /// Checks that a part of the family answers at `address`.
    ///
    /// # Errors
    /// A bus error, or [`GyroError::NotFound`] with what answered.
    pub fn probe(i2c: I2C, address: u8) -> Result<Self, GyroError<I2C::Error>> {
        Ok(Mpu6050 {
            regs: Registers::probe(i2c, address, WHO_AM_I, &KNOWN_PARTS)?,
            range: GyroRange::Dps250,
        })
    }

    /// Resets every register; wait 100 ms before [`Mpu6050::configure`].
    ///
    /// # Errors
    /// A bus error.
    pub fn reset(&mut self) -> Result<(), GyroError<I2C::Error>> {
        self.regs.write(PWR_MGMT_1, 0x80)
    }

    /// Wakes the chip and sets the gyro: `range`, a 44 Hz low-pass filter and `rate_hz`
    /// samples per second (4 to 1,000; the divider rounds it).
    ///
    /// # Errors
    /// A bus error.
    pub fn configure(
        &mut self,
        range: GyroRange,
        rate_hz: u16,
    ) -> Result<(), GyroError<I2C::Error>> {
        let divider = (1000 / u32::from(rate_hz.clamp(4, 1000))).saturating_sub(1) as u8;
        self.regs.write(PWR_MGMT_1, 0x01)?;
        self.regs.write(CONFIG, 0x03)?;
        self.regs.write(SMPLRT_DIV, divider)?;
        self.regs.write(GYRO_CONFIG, range_bits(range))?;
        self.range = range;
        Ok(())
    }

    /// The rate about the chip's z axis, rad/s (counter-clockwise seen from above when the
    /// chip lies face up), uncorrected for bias.
    ///
    /// # Errors
    /// A bus error.
    pub fn yaw_rate(&mut self) -> Result<f32, GyroError<I2C::Error>> {
        let b = self.regs.read2(GYRO_ZOUT_H)?;
        Ok(f32::from(i16::from_be_bytes(b)) * rad_per_lsb(self.range))
    }

    /// Gives the bus back.
    pub fn release(self) -> I2C {
        self.regs.release()
    }
}

impl<I2C: I2c> YawGyro for Mpu6050<I2C> {
    type Error = I2C::Error;

    fn yaw_rate(&mut self) -> Result<f32, GyroError<I2C::Error>> {
        Mpu6050::yaw_rate(self)
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use std::vec;
    use std::vec::Vec;

    use embedded_hal_mock::eh1::i2c::{Mock, Transaction};

    use super::*;

    fn configured() -> Vec<Transaction> {
        vec![
            Transaction::write_read(0x68, vec![WHO_AM_I], vec![0x68]),
            Transaction::write(0x68, vec![PWR_MGMT_1, 0x80]),
            Transaction::write(0x68, vec![PWR_MGMT_1, 0x01]),
            Transaction::write(0x68, vec![CONFIG, 0x03]),
            // 100 Hz: 1 kHz / (1 + 9).
            Transaction::write(0x68, vec![SMPLRT_DIV, 9]),
            Transaction::write(0x68, vec![GYRO_CONFIG, 0x08]),
        ]
    }

    #[test]
    fn the_chip_is_set_up_and_its_yaw_rate_read_in_radians() {
        let mut t = configured();
        // 65.5 LSB per deg/s at +-500: 6550 counts are 100 deg/s, -655 are -10 deg/s.
        t.push(Transaction::write_read(
            0x68,
            vec![GYRO_ZOUT_H],
            vec![0x19, 0x96],
        ));
        t.push(Transaction::write_read(
            0x68,
            vec![GYRO_ZOUT_H],
            vec![0xFD, 0x71],
        ));
        let mut i2c = Mock::new(&t);
        let mut g = Mpu6050::probe(i2c.clone(), DEFAULT_ADDRESS).expect("found");
        g.reset().expect("reset");
        g.configure(GyroRange::Dps500, 100).expect("configured");
        let a = g.yaw_rate().expect("read");
        let b = g.yaw_rate().expect("read");
        assert!((a - 100f32.to_radians()).abs() < 1e-5, "{a}");
        assert!((b + 10f32.to_radians()).abs() < 1e-5, "{b}");
        i2c.done();
    }

    #[test]
    fn another_part_at_the_address_is_refused_with_what_it_is() {
        let t = [Transaction::write_read(0x68, vec![WHO_AM_I], vec![0x12])];
        let mut i2c = Mock::new(&t);
        let e = Mpu6050::probe(i2c.clone(), DEFAULT_ADDRESS).expect_err("not a gyro");
        assert_eq!(e, GyroError::NotFound { who_am_i: 0x12 });
        i2c.done();
    }

    #[test]
    fn a_bus_error_is_an_error_not_a_rate() {
        use embedded_hal::i2c::ErrorKind;
        let mut t = configured();
        t.push(
            Transaction::write_read(0x68, vec![GYRO_ZOUT_H], vec![0, 0])
                .with_error(ErrorKind::Other),
        );
        let mut i2c = Mock::new(&t);
        let mut g = Mpu6050::probe(i2c.clone(), DEFAULT_ADDRESS).expect("found");
        g.reset().expect("reset");
        g.configure(GyroRange::Dps500, 100).expect("configured");
        assert_eq!(g.yaw_rate(), Err(GyroError::Bus(ErrorKind::Other)));
        i2c.done();
    }
}
