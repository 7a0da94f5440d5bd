//! A gyro on the robot's I2C bus as a yaw-rate source (`cloi run --imu KIND:/dev/i2c-N[@ADDR]`):
//! the core's `embedded-hal` drivers ([`cloi_core::sensor::mpu6050`],
//! [`cloi_core::sensor::lsm6ds`]) on Linux's I2C device through `linux-embedded-hal`.
//!
//! A thread sets the chip up (+-250 deg/s, [`RATE_HZ`] samples a second), reads the yaw rate at
//! that rate and stamps each reading with the host's clock. The robot is taken to stand still
//! for the first [`BIAS_SECONDS`]: those readings are not sent on but measure the gyro's bias
//! ([`StillBias`]), which every later reading has taken off (the scan matcher refines what is
//! left while driving). If they spread as if the robot moved, the bias is left at zero with a
//! warning. A reading that fails is counted and skipped; the chip is not reopened (a bus that
//! stops answering shows as read errors in the report, and the mapper goes on with the wheels).
//!
//! The chip is read as mounted face up, its z axis pointing up. `--record` writes the rates sent
//! on as `/imu`.

use std::str::FromStr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::SyncSender;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context, Result};
use cloi_core::sensor::gyro::{GyroRange, StillBias, YawGyro};
use cloi_core::sensor::{lsm6ds, mpu6050};
use serde::Serialize;

use super::port::{self, now_ns};
use super::record::{self, SharedRecorder};
use crate::map::input::SensorEvent;

/// Readings a second.
pub const RATE_HZ: u16 = 200;
/// Seconds of readings at the start that measure the bias (the robot stands still).
pub const BIAS_SECONDS: f64 = 1.0;
/// Largest spread of the still readings, rad/s (about 1 deg/s): more, and something moved.
pub const STILL_SPREAD: f32 = 0.02;

/// Gyro parts `cloi run` reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GyroKind {
    /// InvenSense MPU-6050, 6500, 9250, 9255 (address 0x68, 0x69 with AD0 high).
    Mpu6050,
    /// STMicroelectronics LSM6DS3, DS3TR-C, DSL, DSR, DSO, DSOX (address 0x6a, 0x6b with SA0
    /// high).
    Lsm6ds,
}

/// A gyro given as `KIND:PATH[@ADDRESS]`.
#[derive(Clone, Debug, PartialEq)]
pub struct ImuSpec {
    /// The part.
    pub kind: GyroKind,
    /// The I2C device, e.g. `/dev/i2c-1`.
    pub path: String,
    /// Its 7-bit address on the bus.
    pub address: u8,
}

impl FromStr for ImuSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let (kind, rest) = s.split_once(':').ok_or_else(|| {
            format!("`{s}`: expected KIND:PATH[@ADDRESS], e.g. mpu6050:/dev/i2c-1")
        })?;
        let (kind, default) = match kind {
            "mpu6050" => (GyroKind::Mpu6050, mpu6050::DEFAULT_ADDRESS),
            "lsm6ds" => (GyroKind::Lsm6ds, lsm6ds::DEFAULT_ADDRESS),
            other => return Err(format!("unknown gyro `{other}` (known: mpu6050, lsm6ds)")),
        };
        let (path, address) = match rest.rsplit_once('@') {
            Some((path, a)) => {
                let digits = a.strip_prefix("0x").unwrap_or(a);
                let address = u8::from_str_radix(digits, 16)
                    .ok()
                    .filter(|&v| v < 0x80)
                    .ok_or_else(|| format!("`{a}` is not a 7-bit I2C address in hex"))?;
                (path, address)
            }
            None => (rest, default),
        };
        if path.is_empty() {
            return Err(format!("`{s}`: the I2C device path is missing"));
        }
        Ok(ImuSpec {
            kind,
            path: path.to_owned(),
            address,
        })
    }
}

/// What the gyro's thread met, for the run's report.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct GyroCounters {
    /// Readings sent on.
    pub rates: u64,
    /// Readings that failed.
    pub read_errors: u64,
    /// Readings taken while standing still at the start.
    pub still_readings: u64,
    /// The bias taken off every reading, rad/s (`None` when the still readings spread).
    pub bias: Option<f32>,
    /// Readings written to the recording.
    pub recorded: u64,
}

/// Opens the I2C device, sets the chip up (a clear error if it is not there or not the part
/// named) and starts the thread that sends its rates on `tx` until `stop` is set.
///
/// # Errors
/// The device cannot be opened, the chip does not answer or is another part, or the thread
/// cannot be started.
pub fn start(
    spec: &ImuSpec,
    recorder: Arc<SharedRecorder>,
    tx: SyncSender<Result<SensorEvent>>,
    stop: Arc<AtomicBool>,
    counters: Arc<Mutex<GyroCounters>>,
) -> Result<std::thread::JoinHandle<Result<()>>> {
    let bus = linux_embedded_hal::I2cdev::new(&spec.path)
        .with_context(|| format!("opening the I2C device {}", spec.path))?;
    let what = format!("the gyro at 0x{:02x} on {}", spec.address, spec.path);
    let spawn = |name: &str| std::thread::Builder::new().name(name.into());
    match spec.kind {
        GyroKind::Mpu6050 => {
            let mut g =
                mpu6050::Mpu6050::probe(bus, spec.address).map_err(|e| anyhow!("{what}: {e:?}"))?;
            g.reset().map_err(|e| anyhow!("{what}: {e:?}"))?;
            std::thread::sleep(Duration::from_millis(100));
            g.configure(GyroRange::Dps250, RATE_HZ)
                .map_err(|e| anyhow!("{what}: {e:?}"))?;
            spawn("cloi-gyro").spawn(move || read_rates(g, &recorder, &tx, &stop, &counters))
        }
        GyroKind::Lsm6ds => {
            let mut g =
                lsm6ds::Lsm6ds::probe(bus, spec.address).map_err(|e| anyhow!("{what}: {e:?}"))?;
            g.reset().map_err(|e| anyhow!("{what}: {e:?}"))?;
            std::thread::sleep(Duration::from_millis(50));
            g.configure(GyroRange::Dps250, RATE_HZ)
                .map_err(|e| anyhow!("{what}: {e:?}"))?;
            spawn("cloi-gyro").spawn(move || read_rates(g, &recorder, &tx, &stop, &counters))
        }
    }
    .context("starting the gyro's thread")
}

/// Reads `gyro` at [`RATE_HZ`] until `stop` is set or the receiver is gone: the first
/// [`BIAS_SECONDS`] measure the bias, the rest are sent on with it taken off.
///
/// # Errors
/// None today; the result leaves room for a bus that must end the run.
pub fn read_rates<G: YawGyro>(
    mut gyro: G,
    recorder: &SharedRecorder,
    tx: &SyncSender<Result<SensorEvent>>,
    stop: &AtomicBool,
    counters: &Mutex<GyroCounters>,
) -> Result<()>
where
    G::Error: std::fmt::Debug,
{
    let count = |f: &mut dyn FnMut(&mut GyroCounters)| port::update(counters, f);
    let period = Duration::from_secs_f64(1.0 / f64::from(RATE_HZ));
    let still_readings = (BIAS_SECONDS * f64::from(RATE_HZ)) as u32;
    let mut still = StillBias::new(still_readings * 4 / 5, STILL_SPREAD);
    let mut bias = None;
    let (mut taken, mut last_stamp) = (0u32, i64::MIN);
    let mut next = Instant::now();
    while !stop.load(Ordering::Acquire) {
        next += period;
        std::thread::sleep(next.saturating_duration_since(Instant::now()));
        let rate = match gyro.yaw_rate() {
            Ok(r) => r,
            Err(e) => {
                count(&mut |c| c.read_errors += 1);
                log::debug!("gyro read failed: {e:?}");
                continue;
            }
        };
        let t_ns = now_ns().max(last_stamp.saturating_add(1));
        last_stamp = t_ns;
        if taken < still_readings {
            still.push(rate);
            taken += 1;
            if taken == still_readings {
                bias = still.bias();
                if bias.is_none() {
                    log::warn!(
                        "the gyro's first {BIAS_SECONDS} s spread as if the robot moved: \
                         its bias is left to the scan matcher"
                    );
                }
                count(&mut |c| {
                    c.still_readings = u64::from(taken);
                    c.bias = bias;
                });
            }
            continue;
        }
        let yaw_rate = f64::from(rate - bias.unwrap_or(0.0));
        count(&mut |c| c.rates += 1);
        if record::record(recorder, |r| r.gyro(t_ns, yaw_rate)) {
            count(&mut |c| c.recorded += 1);
        }
        if tx.send(Ok(SensorEvent::Gyro { t_ns, yaw_rate })).is_err() {
            break;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use cloi_core::sensor::gyro::GyroError;

    #[test]
    fn imu_specs_parse_with_and_without_an_address() {
        let s: ImuSpec = "mpu6050:/dev/i2c-1".parse().expect("parses");
        assert_eq!(
            (s.kind, s.path.as_str(), s.address),
            (GyroKind::Mpu6050, "/dev/i2c-1", 0x68)
        );
        let s: ImuSpec = "lsm6ds:/dev/i2c-0@0x6b".parse().expect("parses");
        assert_eq!((s.kind, s.address), (GyroKind::Lsm6ds, 0x6B));
        let s: ImuSpec = "mpu6050:/dev/i2c-2@69".parse().expect("parses");
        assert_eq!(s.address, 0x69);
        for bad in [
            "mpu6050",
            "bmi088:/dev/i2c-1",
            "lsm6ds:",
            "mpu6050:/dev/i2c-1@0x80",
            "mpu6050:/x@zz",
        ] {
            assert!(bad.parse::<ImuSpec>().is_err(), "{bad}");
        }
    }

    /// A gyro standing still for a second (bias 0.01 rad/s, +-0.003 of noise), then turning at
    /// 0.5 rad/s; every 50th reading fails.
    struct Simulated {
        reads: u32,
    }

    impl YawGyro for Simulated {
        type Error = ();

        fn yaw_rate(&mut self) -> Result<f32, GyroError<()>> {
            self.reads += 1;
            if self.reads.is_multiple_of(50) {
                return Err(GyroError::Bus(()));
            }
            let noise = if self.reads.is_multiple_of(2) {
                0.003
            } else {
                -0.003
            };
            let turning = if self.reads > 220 { 0.5 } else { 0.0 };
            Ok(0.01 + noise + turning)
        }
    }

    #[test]
    fn the_still_start_measures_the_bias_and_later_rates_lose_it() {
        let (tx, rx) = std::sync::mpsc::sync_channel(1024);
        let stop = AtomicBool::new(false);
        let counters = Mutex::new(GyroCounters::default());
        let recorder = Mutex::new(None);
        std::thread::scope(|s| {
            let reader =
                s.spawn(|| read_rates(Simulated { reads: 0 }, &recorder, &tx, &stop, &counters));
            let mut rates = Vec::new();
            while rates.len() < 100 {
                match rx.recv().expect("a rate") {
                    Ok(SensorEvent::Gyro { t_ns, yaw_rate }) => rates.push((t_ns, yaw_rate)),
                    other => panic!("{other:?}"),
                }
            }
            stop.store(true, Ordering::Release);
            reader.join().expect("no panic").expect("ends");
            let c = *counters.lock().expect("counters");
            assert_eq!(c.still_readings, u64::from(RATE_HZ));
            let bias = c.bias.expect("a bias");
            assert!((bias - 0.01).abs() < 1e-3, "{bias}");
            assert!(c.read_errors >= 4, "{c:?}");
            // The first still readings measured the bias; the next ones (still or turning)
            // come with it taken off.
            assert!(rates.windows(2).all(|w| w[1].0 > w[0].0));
            let turning: Vec<f64> = rates.iter().map(|r| r.1).filter(|&r| r > 0.25).collect();
            assert!(turning.len() > 50, "{}", turning.len());
            assert!(
                turning.iter().all(|&r| (r - 0.5).abs() < 0.005),
                "{turning:?}"
            );
            let still: Vec<f64> = rates.iter().map(|r| r.1).filter(|&r| r <= 0.25).collect();
            assert!(still.iter().all(|&r| r.abs() < 0.005), "{still:?}");
        });
    }
}
