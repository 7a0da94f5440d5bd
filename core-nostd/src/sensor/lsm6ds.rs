//! The STMicroelectronics LSM6DS family's gyro over I2C (`embedded-hal` 1.0): LSM6DS3,
//! LSM6DS3TR-C, LSM6DSL, LSM6DSR, LSM6DSO and LSM6DSOX, current parts on robot boards, read
//! for the yaw rate the odometry fusion takes (paper III-B.2).
//!
//! # Registers (from the vendor's public datasheets; the gyro's are the same across the family)
//! | register | use here |
//! |---|---|
//! | `0x0F` WHO_AM_I | `0x69` (DS3), `0x6A` (DS3TR-C, DSL), `0x6B` (DSR), `0x6C` (DSO, DSOX) |
//! | `0x12` CTRL3_C | `0x01` resets; `0x44` keeps both bytes of a sample together (BDU) and steps the register address in multi-byte reads (IF_INC) |
//! | `0x11` CTRL2_G | output rate in bits 7:4 (12.5, 26, 52, 104, 208, 416, 833, 1660 Hz), full scale in bits 3:2: +-250, 500, 1000, 2000 deg/s |
//! | `0x26`, `0x27` OUTZ_G | yaw rate, little-endian `i16`, 8.75 / 17.5 / 35 / 70 mdeg/s per LSB |
//!
//! As with the MPU-6050, the reset's settling time is the caller's: [`Lsm6ds::reset`], wait
//! 50 ms, then [`Lsm6ds::configure`].

use embedded_hal::i2c::I2c;

use super::gyro::{GyroError, GyroRange, Registers, YawGyro};

/// The chip's I2C address with its SA0 pin low (`0x6B` with SA0 high).
pub const DEFAULT_ADDRESS: u8 = 0x6A;

const WHO_AM_I: u8 = 0x0F;
const CTRL2_G: u8 = 0x11;
const CTRL3_C: u8 = 0x12;
const OUTZ_L_G: u8 = 0x26;

/// WHO_AM_I answers of the family's parts.
pub const KNOWN_PARTS: [u8; 4] = [0x69, 0x6A, 0x6B, 0x6C];

/// Bits 3:2 of CTRL2_G for `range`.
fn range_bits(range: GyroRange) -> u8 {
    (match range {
        GyroRange::Dps250 => 0,
        GyroRange::Dps500 => 1,
        GyroRange::Dps1000 => 2,
        GyroRange::Dps2000 => 3,
    }) << 2
}

/// Radians per second of one count at `range`.
fn rad_per_lsb(range: GyroRange) -> f32 {
    let mdps_per_lsb = match range {
        GyroRange::Dps250 => 8.75,
        GyroRange::Dps500 => 17.5,
        GyroRange::Dps1000 => 35.0,
        GyroRange::Dps2000 => 70.0,
    };
    mdps_per_lsb * 1e-3 * core::f32::consts::PI / 180.0
}

/// Output rates of CTRL2_G's codes 1 to 8, Hz.
const RATES_HZ: [f32; 8] = [12.5, 26.0, 52.0, 104.0, 208.0, 416.0, 833.0, 1660.0];

/// Bits 7:4 of CTRL2_G: the slowest output rate of at least `rate_hz` (12.5 Hz to 1.66 kHz).
fn rate_bits(rate_hz: u16) -> u8 {
    let at_least = RATES_HZ.iter().position(|&r| r >= f32::from(rate_hz));
    (at_least.unwrap_or(RATES_HZ.len() - 1) as u8 + 1) << 4
}

/// An LSM6DS family part on an I2C bus.
#[derive(Debug)]
pub struct Lsm6ds<I2C> {
    regs: Registers<I2C>,
    range: GyroRange,
}

impl<I2C: I2c> Lsm6ds<I2C> {
    /// Checks that a part of the family answers at `address`.
    ///
    /// # Errors
    /// A bus error, or [`GyroError::NotFound`] with what answered.
    pub fn probe(i2c: I2C, address: u8) -> Result<Self, GyroError<I2C::Error>> {
        Ok(Lsm6ds {
            regs: Registers::probe(i2c, address, WHO_AM_I, &KNOWN_PARTS)?,
            range: GyroRange::Dps250,
        })
    }

    /// Resets every register; wait 50 ms before [`Lsm6ds::configure`].
    ///
    /// # Errors
    /// A bus error.
    pub fn reset(&mut self) -> Result<(), GyroError<I2C::Error>> {
        self.regs.write(CTRL3_C, 0x01)
    }

    /// Sets the gyro: `range` and the slowest output rate of at least `rate_hz` (12.5 Hz to
    /// 1.66 kHz), samples read whole.
    ///
    /// # Errors
    /// A bus error.
    pub fn configure(
        &mut self,
        range: GyroRange,
        rate_hz: u16,
    ) -> Result<(), GyroError<I2C::Error>> {
        self.regs.write(CTRL3_C, 0x44)?;
        self.regs
            .write(CTRL2_G, rate_bits(rate_hz) | range_bits(range))?;
        self.range = range;
        Ok(())
    }

    /// The rate about the chip's z axis, rad/s (counter-clockwise seen from above when the
    /// chip lies face up), uncorrected for bias.
    ///
    /// # Errors
    /// A bus error.
    pub fn yaw_rate(&mut self) -> Result<f32, GyroError<I2C::Error>> {
        let b = self.regs.read2(OUTZ_L_G)?;
        Ok(f32::from(i16::from_le_bytes(b)) * rad_per_lsb(self.range))
    }

    /// Gives the bus back.
    pub fn release(self) -> I2C {
        self.regs.release()
    }
}

impl<I2C: I2c> YawGyro for Lsm6ds<I2C> {
    type Error = I2C::Error;

    fn yaw_rate(&mut self) -> Result<f32, GyroError<I2C::Error>> {
        Lsm6ds::yaw_rate(self)
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use std::vec;

    use embedded_hal_mock::eh1::i2c::{Mock, Transaction};

    use super::*;

    #[test]
    fn the_chip_is_set_up_and_its_yaw_rate_read_in_radians() {
        let t = [
            Transaction::write_read(0x6A, vec![WHO_AM_I], vec![0x6C]),
            Transaction::write(0x6A, vec![CTRL3_C, 0x01]),
            Transaction::write(0x6A, vec![CTRL3_C, 0x44]),
            // 208 Hz (code 5) for 200 Hz asked, +-500 deg/s (01 in bits 3:2).
            Transaction::write(0x6A, vec![CTRL2_G, 0x54]),
            // 17.5 mdeg/s per LSB: 5714 counts are 100 deg/s, -572 are -10 (to a count).
            Transaction::write_read(0x6A, vec![OUTZ_L_G], 5714i16.to_le_bytes().to_vec()),
            Transaction::write_read(0x6A, vec![OUTZ_L_G], (-572i16).to_le_bytes().to_vec()),
        ];
        let mut i2c = Mock::new(&t);
        let mut g = Lsm6ds::probe(i2c.clone(), DEFAULT_ADDRESS).expect("found");
        g.reset().expect("reset");
        g.configure(GyroRange::Dps500, 200).expect("configured");
        let a = g.yaw_rate().expect("read");
        let b = YawGyro::yaw_rate(&mut g).expect("read");
        assert!((a.to_degrees() - 100.0).abs() < 0.02, "{}", a.to_degrees());
        assert!((b.to_degrees() + 10.0).abs() < 0.02, "{}", b.to_degrees());
        i2c.done();
    }

    #[test]
    fn output_rates_round_up_to_the_chips() {
        assert_eq!(rate_bits(1), 0x10);
        assert_eq!(rate_bits(13), 0x20);
        assert_eq!(rate_bits(104), 0x40);
        assert_eq!(rate_bits(200), 0x50);
        assert_eq!(rate_bits(u16::MAX), 0x80);
    }

    #[test]
    fn another_part_at_the_address_is_refused_with_what_it_is() {
        let t = [Transaction::write_read(0x6A, vec![WHO_AM_I], vec![0x68])];
        let mut i2c = Mock::new(&t);
        let e = Lsm6ds::probe(i2c.clone(), DEFAULT_ADDRESS).expect_err("an MPU-6050");
        assert_eq!(e, GyroError::NotFound { who_am_i: 0x68 });
        i2c.done();
    }
}
