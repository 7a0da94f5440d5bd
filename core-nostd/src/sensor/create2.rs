//! The iRobot Create 2 (a Roomba 600 with its serial port open) as a wheel-odometry source: the
//! requests that start its sensor stream, the stream's frames decoded byte by byte without a
//! heap, and its wheel encoder counts turned into the robot's pose by differential-drive dead
//! reckoning (the wheel odometry of the paper's front-end, section III-B.1).
//!
//! # Frames (from iRobot's public Open Interface specification)
//! * Requests are an opcode and its data: [`START`] opens the interface in its passive mode
//!   (sensors are read, the robot is not driven: mapping must not take the robot over);
//!   [`STREAM`] `n id1 .. idn` asks for the packets `id1 .. idn` every 15 ms;
//!   [`PAUSE_RESUME`] `0` stops the stream.
//! * A stream frame is [`HEADER`], a byte count `n`, then `n` bytes of packets (each its id and
//!   its data), then a checksum chosen so that all bytes of the frame, header and checksum
//!   included, add up to 0 modulo 256.
//! * Packets [`LEFT_ENCODER`] and [`RIGHT_ENCODER`]: each wheel's encoder count, 16 bits big
//!   endian, counting up forwards and down backwards, wrapping at 65,535.
//!
//! A frame whose checksum fails is not a frame: the reader drops its first byte and looks for
//! the next header (counted), so it finds the frame boundaries again after noise. A frame with
//! a packet this reader does not know is counted and skipped (its length is unknown).
//!
//! # Geometry
//! 508.8 counts per wheel turn, wheels of 72 mm, 235 mm apart ([`WheelGeometry::CREATE2`]).
//! Between two frames the robot is taken to move on a circular arc (constant wheel speeds), the
//! exact solution for the 15 ms between frames.

use crate::geom::Se2;

/// Opcode: start the Open Interface (passive mode).
pub const START: u8 = 128;
/// Opcode: stream packets, followed by their count and ids.
pub const STREAM: u8 = 148;
/// Opcode: pause (0) or resume (1) the stream.
pub const PAUSE_RESUME: u8 = 150;
/// First byte of a stream frame.
pub const HEADER: u8 = 19;
/// Packet id of the left wheel's encoder count.
pub const LEFT_ENCODER: u8 = 43;
/// Packet id of the right wheel's encoder count.
pub const RIGHT_ENCODER: u8 = 44;
/// The requests that start the stream of both encoder counts.
pub const START_ENCODER_STREAM: [u8; 5] = [START, STREAM, 2, LEFT_ENCODER, RIGHT_ENCODER];
/// The request that pauses the stream.
pub const PAUSE_STREAM: [u8; 2] = [PAUSE_RESUME, 0];
/// Bytes of a frame carrying both encoder counts.
pub const ENCODER_FRAME_LEN: usize = 9;
/// Longest frame: header, count, 255 bytes of packets, checksum.
const MAX_FRAME: usize = 258;

/// Data bytes of the packets this reader knows; `None` for the others.
const fn packet_len(id: u8) -> Option<usize> {
    match id {
        // Bumps and wheel drops, wall, cliffs, virtual wall, dirt detect, OI mode, stasis.
        7..=13 | 15 | 35 | 58 => Some(1),
        // Distance, angle, encoder counts, wheel velocities.
        19 | 20 | LEFT_ENCODER | RIGHT_ENCODER | 41 | 42 => Some(2),
        _ => None,
    }
}

/// Both wheels' encoder counts from one frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EncoderCounts {
    /// Left wheel.
    pub left: u16,
    /// Right wheel.
    pub right: u16,
}

impl EncoderCounts {
    /// The stream frame carrying these counts (as the robot sends it).
    pub fn encode(&self) -> [u8; ENCODER_FRAME_LEN] {
        let (l, r) = (self.left.to_be_bytes(), self.right.to_be_bytes());
        let mut f = [
            HEADER,
            6,
            LEFT_ENCODER,
            l[0],
            l[1],
            RIGHT_ENCODER,
            r[0],
            r[1],
            0,
        ];
        f[8] = checksum(&f[..8]);
        f
    }
}

/// The byte that makes `bytes` and itself add up to 0 modulo 256.
pub fn checksum(bytes: &[u8]) -> u8 {
    bytes
        .iter()
        .fold(0u8, |s, &b| s.wrapping_add(b))
        .wrapping_neg()
}

/// What the reader met.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StreamCounters {
    /// Frames whose checksum held.
    pub frames: u64,
    /// Frames whose checksum failed.
    pub checksum_errors: u64,
    /// Bytes skipped while looking for a header.
    pub skipped_bytes: u64,
    /// Good frames with a packet this reader does not know, or without both encoders.
    pub frames_ignored: u64,
}

/// Stream frames decoded byte by byte.
#[derive(Clone, Debug)]
pub struct StreamReader {
    buf: [u8; MAX_FRAME],
    len: usize,
    counters: StreamCounters,
}

impl Default for StreamReader {
    fn default() -> Self {
        Self::new()
    }
}

impl StreamReader {
    /// A reader waiting for a header.
    pub const fn new() -> Self {
        StreamReader {
            buf: [0; MAX_FRAME],
            len: 0,
            counters: StreamCounters {
                frames: 0,
                checksum_errors: 0,
                skipped_bytes: 0,
                frames_ignored: 0,
            },
        }
    }

    /// What it met so far.
    pub fn counters(&self) -> StreamCounters {
        self.counters
    }

    /// The next byte; the encoder counts when it completed a good frame carrying both.
    pub fn push(&mut self, byte: u8) -> Option<EncoderCounts> {
        if self.len == MAX_FRAME {
            self.drop_front(1);
            self.counters.skipped_bytes += 1;
        }
        self.buf[self.len] = byte;
        self.len += 1;
        self.next_frame()
    }

    /// The first good frame at the front of the buffer, consumed; the bytes before it are
    /// dropped (counted).
    fn next_frame(&mut self) -> Option<EncoderCounts> {
        loop {
            if self.len == 0 {
                return None;
            }
            if self.buf[0] != HEADER {
                self.drop_front(1);
                self.counters.skipped_bytes += 1;
                continue;
            }
            if self.len < 2 {
                return None;
            }
            let total = usize::from(self.buf[1]) + 3;
            if self.len < total {
                return None;
            }
            if checksum(&self.buf[..total]) != 0 {
                // Not a frame, or a damaged one: its header may have been a data byte.
                self.counters.checksum_errors += 1;
                self.drop_front(1);
                continue;
            }
            self.counters.frames += 1;
            let counts = encoders(&self.buf[2..total - 1]);
            self.drop_front(total);
            match counts {
                Some(c) => return Some(c),
                None => self.counters.frames_ignored += 1,
            }
        }
    }

    fn drop_front(&mut self, n: usize) {
        self.buf.copy_within(n..self.len, 0);
        self.len -= n;
    }
}

/// Both encoder counts from a frame's packets; `None` when one is missing or a packet is
/// unknown.
fn encoders(mut packets: &[u8]) -> Option<EncoderCounts> {
    let (mut left, mut right) = (None, None);
    while let [id, rest @ ..] = packets {
        let n = packet_len(*id)?;
        let data = rest.get(..n)?;
        match *id {
            LEFT_ENCODER => left = Some(u16::from_be_bytes([data[0], data[1]])),
            RIGHT_ENCODER => right = Some(u16::from_be_bytes([data[0], data[1]])),
            _ => {}
        }
        packets = &rest[n..];
    }
    Some(EncoderCounts {
        left: left?,
        right: right?,
    })
}

/// A differential drive's wheels as its encoders see them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WheelGeometry {
    /// Travel of a wheel per encoder count, metres.
    pub metres_per_count: f64,
    /// Distance between the wheels' contact points, metres.
    pub track: f64,
}

impl WheelGeometry {
    /// The Create 2's: 508.8 counts per turn of a 72 mm wheel, wheels 235 mm apart.
    pub const CREATE2: WheelGeometry = WheelGeometry {
        metres_per_count: core::f64::consts::PI * 0.072 / 508.8,
        track: 0.235,
    };
}

/// A step of either wheel larger than this many counts between two frames is not motion (a
/// wheel at the Create's top speed, 0.5 m/s, turns about 17 counts in the 15 ms between
/// frames and 1,000 in 0.9 s): the counters were reset, e.g. by the robot restarting.
pub const MAX_STEP_COUNTS: i32 = 1000;

/// Encoder counts integrated into the pose of the robot in its odometry frame.
#[derive(Clone, Copy, Debug)]
pub struct EncoderOdometry {
    geometry: WheelGeometry,
    last: Option<EncoderCounts>,
    pose: Se2,
    jumps: u64,
}

impl EncoderOdometry {
    /// Dead reckoning from the identity with `geometry`.
    pub const fn new(geometry: WheelGeometry) -> Self {
        EncoderOdometry {
            geometry,
            last: None,
            pose: Se2::IDENTITY,
            jumps: 0,
        }
    }

    /// The pose after the frames so far.
    pub fn pose(&self) -> Se2 {
        self.pose
    }

    /// Steps taken for a counter reset rather than motion.
    pub fn jumps(&self) -> u64 {
        self.jumps
    }

    /// Forgets the last counts (the device was reopened): the next frame moves nothing.
    pub fn restart(&mut self) {
        self.last = None;
    }

    /// The pose after a frame with `counts`: moved along the arc both wheels rolled since the
    /// previous frame (counters wrap); the first frame after a start and a step beyond
    /// [`MAX_STEP_COUNTS`] (counted) only set the reference.
    pub fn update(&mut self, counts: EncoderCounts) -> Se2 {
        let Some(last) = self.last.replace(counts) else {
            return self.pose;
        };
        // Differences modulo 2^16, read as signed: a wheel turning back over zero counts down.
        let dl = i32::from(counts.left.wrapping_sub(last.left) as i16);
        let dr = i32::from(counts.right.wrapping_sub(last.right) as i16);
        if dl.abs() > MAX_STEP_COUNTS || dr.abs() > MAX_STEP_COUNTS {
            self.jumps += 1;
            return self.pose;
        }
        let g = self.geometry;
        let (l, r) = (
            f64::from(dl) * g.metres_per_count,
            f64::from(dr) * g.metres_per_count,
        );
        let arc = Se2::exp(&nalgebra::Vector3::new(
            0.5 * (l + r),
            0.0,
            (r - l) / g.track,
        ));
        self.pose = self.pose.compose(&arc);
        self.pose
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;

    fn feed(reader: &mut StreamReader, bytes: &[u8]) -> std::vec::Vec<EncoderCounts> {
        bytes.iter().filter_map(|&b| reader.push(b)).collect()
    }

    #[test]
    fn a_frame_round_trips_and_its_checksum_is_the_specifications() {
        // The specification's example frame (a cliff signal and a virtual wall) sums to zero.
        assert_eq!(checksum(&[19, 5, 29, 2, 25, 13, 0]), 163);
        let c = EncoderCounts {
            left: 0x1234,
            right: 65_535,
        };
        let f = c.encode();
        assert_eq!(f.iter().fold(0u8, |s, &b| s.wrapping_add(b)), 0);
        assert_eq!(feed(&mut StreamReader::new(), &f), [c]);
    }

    #[test]
    fn damage_and_noise_are_counted_and_the_next_frames_are_found() {
        let frames: std::vec::Vec<EncoderCounts> = (0..6u16)
            .map(|k| EncoderCounts {
                left: 100 * k,
                right: 65_500u16.wrapping_add(19 * k),
            })
            .collect();
        let mut bytes = std::vec![0x13, 0x02, 0xFF, 0x00];
        for (k, f) in frames.iter().enumerate() {
            let mut b = f.encode();
            if k == 2 {
                b[4] ^= 0x40;
            }
            bytes.extend_from_slice(&b);
        }
        let mut r = StreamReader::new();
        let got = feed(&mut r, &bytes);
        let want: std::vec::Vec<EncoderCounts> = frames
            .iter()
            .enumerate()
            .filter(|&(k, _)| k != 2)
            .map(|(_, f)| *f)
            .collect();
        assert_eq!(got, want);
        let c = r.counters();
        assert_eq!(c.frames, 5);
        assert!(c.checksum_errors >= 1 && c.skipped_bytes > 0, "{c:?}");
    }

    #[test]
    fn frames_without_both_encoders_are_ignored_and_others_are_read_through() {
        // Bumps (7), distance (19) and both encoders in one frame; then only the angle (20).
        let mut f = std::vec![
            HEADER,
            11,
            7,
            0,
            19,
            0,
            5,
            LEFT_ENCODER,
            0,
            9,
            RIGHT_ENCODER,
            1,
            2
        ];
        f.push(checksum(&f));
        let mut g = std::vec![HEADER, 3, 20, 0, 1];
        g.push(checksum(&g));
        let mut r = StreamReader::new();
        let mut bytes = f.clone();
        bytes.extend_from_slice(&g);
        assert_eq!(
            feed(&mut r, &bytes),
            [EncoderCounts {
                left: 9,
                right: 258
            }]
        );
        assert_eq!(r.counters().frames, 2);
        assert_eq!(r.counters().frames_ignored, 1);
    }

    #[test]
    fn counts_integrate_to_straight_lines_and_turns_across_the_wrap() {
        let g = WheelGeometry::CREATE2;
        let mut o = EncoderOdometry::new(g);
        let start = EncoderCounts {
            left: 65_000,
            right: 65_000,
        };
        o.update(start);
        // One metre straight ahead, over the counters' wrap, in steps of 10 counts.
        let n = libm::round(1.0 / g.metres_per_count) as i32;
        let mut c = start;
        for _ in 0..n / 10 {
            c.left = c.left.wrapping_add(10);
            c.right = c.right.wrapping_add(10);
            o.update(c);
        }
        let p = o.pose();
        assert!((p.x - 1.0).abs() < 0.01 && p.y.abs() < 1e-9 && p.theta.abs() < 1e-12);
        // A quarter turn on the spot to the left: the wheels roll pi/4 * track in opposite ways.
        let quarter = libm::round(core::f64::consts::FRAC_PI_4 * g.track / g.metres_per_count);
        for _ in 0..(quarter as i32) {
            c.left = c.left.wrapping_sub(1);
            c.right = c.right.wrapping_add(1);
            o.update(c);
        }
        let q = o.pose();
        assert!(
            (q.theta - core::f64::consts::FRAC_PI_2).abs() < 0.01,
            "{q:?}"
        );
        assert!((q.x - p.x).abs() < 1e-9 && (q.y - p.y).abs() < 1e-9);
        // Backwards 10 cm: along -y of the start now.
        for _ in 0..23 {
            c.left = c.left.wrapping_sub(10);
            c.right = c.right.wrapping_sub(10);
            o.update(c);
        }
        assert!((o.pose().y - q.y + 0.1).abs() < 0.01, "{:?}", o.pose());
    }

    #[test]
    fn a_counter_reset_is_no_motion() {
        let mut o = EncoderOdometry::new(WheelGeometry::CREATE2);
        o.update(EncoderCounts {
            left: 30_000,
            right: 30_000,
        });
        let p = o.update(EncoderCounts { left: 0, right: 0 });
        assert_eq!((p, o.jumps()), (Se2::IDENTITY, 1));
        // From the new counts on it moves again; a restart forgets the reference.
        assert!(o.update(EncoderCounts { left: 5, right: 5 }).x > 0.0);
        o.restart();
        let before = o.pose();
        assert_eq!(
            o.update(EncoderCounts {
                left: 900,
                right: 0
            }),
            before
        );
    }
}
