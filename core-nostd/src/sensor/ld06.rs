//! The LDRobot LD06 / LD19 serial LiDAR protocol, the first device of the live path (issue 18):
//! the byte stream decoded packet by packet without a heap, and the points gathered into whole
//! revolutions of fixed angular bins, the beam layout of the mapper's scans.
//!
//! # Packet (47 bytes, little endian; from the vendor's development manual)
//! | bytes | field |
//! |---|---|
//! | 0 | start, `0x54` |
//! | 1 | `0x2C`: three reserved bits (`001`) and the point count, 12 |
//! | 2..4 | rotation speed, degrees per second |
//! | 4..6 | angle of the first point, 0.01 degree |
//! | 6..42 | 12 points: distance in mm (`u16`, 0: no return), intensity (`u8`) |
//! | 42..44 | angle of the last point, 0.01 degree |
//! | 44..46 | time stamp, ms, wrapping at 30,000 |
//! | 46 | CRC-8 of bytes 0..46 (polynomial `0x4D`, initial value 0, most significant bit first) |
//!
//! The points lie evenly from the first angle to the last (which wraps past 360 degrees at the
//! packet that crosses zero). The head turns clockwise seen from above, so its angles grow
//! clockwise; [`Revolution`] turns them into counter-clockwise angles (the ROS convention).
//!
//! [`PacketReader`] takes one byte at a time (a serial port's reads cut packets anywhere):
//! bytes before a start are counted as skipped, a packet whose CRC fails is counted and the
//! search for the next start resumes inside it, so a good packet right after a damaged one is
//! not lost.

use core::f32::consts::PI;

/// Bytes of one packet.
pub const PACKET_LEN: usize = 47;
/// Points of one packet.
pub const POINTS: usize = 12;
/// First byte of a packet.
pub const START: u8 = 0x54;
/// Second byte of a packet (reserved bits and [`POINTS`]).
pub const VER_LEN: u8 = 0x2C;
/// Angles are in hundredths of a degree below this.
const FULL_TURN: u16 = 36_000;

/// One measured point.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Ld06Point {
    /// Distance, mm (0: no return).
    pub distance_mm: u16,
    /// Return strength.
    pub intensity: u8,
}

/// One decoded packet.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Ld06Packet {
    /// Rotation speed, degrees per second.
    pub speed_dps: u16,
    /// Angle of the first point, 0.01 degree (clockwise), below 36,000.
    pub start_cdeg: u16,
    /// Angle of the last point, 0.01 degree, below 36,000.
    pub end_cdeg: u16,
    /// The device's time stamp, ms (wraps at 30,000).
    pub stamp_ms: u16,
    /// The points, first to last.
    pub points: [Ld06Point; POINTS],
}

impl Ld06Packet {
    /// Clockwise angle of point `i`, 0.01 degree, in `[0, 36000)`.
    pub fn angle_cdeg(&self, i: usize) -> u32 {
        let span = (u32::from(self.end_cdeg) + u32::from(FULL_TURN) - u32::from(self.start_cdeg))
            % u32::from(FULL_TURN);
        let step = span as f32 / (POINTS - 1) as f32;
        let a = f32::from(self.start_cdeg) + step * i as f32;
        (libm::roundf(a) as u32) % u32::from(FULL_TURN)
    }

    /// The packet's 47 bytes (the simulator's device emulator and the tests write packets).
    pub fn encode(&self) -> [u8; PACKET_LEN] {
        let mut b = [0u8; PACKET_LEN];
        b[0] = START;
        b[1] = VER_LEN;
        b[2..4].copy_from_slice(&self.speed_dps.to_le_bytes());
        b[4..6].copy_from_slice(&self.start_cdeg.to_le_bytes());
        for (i, p) in self.points.iter().enumerate() {
            let at = 6 + 3 * i;
            b[at..at + 2].copy_from_slice(&p.distance_mm.to_le_bytes());
            b[at + 2] = p.intensity;
        }
        b[42..44].copy_from_slice(&self.end_cdeg.to_le_bytes());
        b[44..46].copy_from_slice(&self.stamp_ms.to_le_bytes());
        b[46] = crc8(&b[..46]);
        b
    }

    /// Decodes a packet whose framing and CRC were checked.
    fn decode(b: &[u8; PACKET_LEN]) -> Result<Self, Ld06Reject> {
        let u16_at = |at: usize| u16::from_le_bytes([b[at], b[at + 1]]);
        let mut p = Ld06Packet {
            speed_dps: u16_at(2),
            start_cdeg: u16_at(4),
            end_cdeg: u16_at(42),
            stamp_ms: u16_at(44),
            points: [Ld06Point::default(); POINTS],
        };
        if p.start_cdeg >= FULL_TURN || p.end_cdeg >= FULL_TURN {
            return Err(Ld06Reject::Angle);
        }
        for (i, pt) in p.points.iter_mut().enumerate() {
            let at = 6 + 3 * i;
            *pt = Ld06Point {
                distance_mm: u16_at(at),
                intensity: b[at + 2],
            };
        }
        Ok(p)
    }
}

/// Why a packet was dropped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Ld06Reject {
    Crc,
    Angle,
}

/// CRC-8 of the protocol: polynomial `0x4D`, initial value 0, most significant bit first.
pub fn crc8(bytes: &[u8]) -> u8 {
    let mut crc = 0u8;
    for &b in bytes {
        crc ^= b;
        for _ in 0..8 {
            crc = if crc & 0x80 != 0 {
                (crc << 1) ^ 0x4D
            } else {
                crc << 1
            };
        }
    }
    crc
}

/// What the reader met.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Ld06Counters {
    /// Packets decoded.
    pub packets: u64,
    /// Bytes dropped while looking for a packet start.
    pub skipped_bytes: u64,
    /// Packets whose CRC did not match.
    pub crc_errors: u64,
    /// Packets with an angle of 360 degrees or more.
    pub bad_angles: u64,
}

/// Decodes the byte stream of one device.
#[derive(Clone, Debug)]
pub struct PacketReader {
    buf: [u8; PACKET_LEN],
    len: usize,
    counters: Ld06Counters,
}

impl Default for PacketReader {
    fn default() -> Self {
        Self::new()
    }
}

impl PacketReader {
    /// A reader waiting for a packet start.
    pub const fn new() -> Self {
        PacketReader {
            buf: [0; PACKET_LEN],
            len: 0,
            counters: Ld06Counters {
                packets: 0,
                skipped_bytes: 0,
                crc_errors: 0,
                bad_angles: 0,
            },
        }
    }

    /// What the reader met so far.
    pub fn counters(&self) -> Ld06Counters {
        self.counters
    }

    /// Takes the next byte; a packet when this byte completed a valid one.
    pub fn push(&mut self, byte: u8) -> Option<Ld06Packet> {
        if !self.frame(byte) {
            return None;
        }
        self.len = 0;
        let rejected = if crc8(&self.buf[..PACKET_LEN - 1]) != self.buf[PACKET_LEN - 1] {
            Ld06Reject::Crc
        } else {
            match Ld06Packet::decode(&self.buf) {
                Ok(p) => {
                    self.counters.packets += 1;
                    return Some(p);
                }
                Err(r) => r,
            }
        };
        match rejected {
            Ld06Reject::Crc => self.counters.crc_errors += 1,
            Ld06Reject::Angle => self.counters.bad_angles += 1,
        }
        // A start may hide inside the rejected bytes: frame them again (46 bytes cannot
        // complete a packet, so this does not recurse).
        let rest = self.buf;
        for &b in &rest[1..] {
            self.frame(b);
        }
        None
    }

    /// Appends `byte` to the packet being framed; true when the buffer holds a whole packet.
    fn frame(&mut self, byte: u8) -> bool {
        match self.len {
            0 if byte != START => {
                self.counters.skipped_bytes += 1;
                return false;
            }
            1 if byte != VER_LEN => {
                // The start was not one; this byte may be the next.
                self.counters.skipped_bytes += 1;
                self.len = 0;
                return self.frame(byte);
            }
            _ => {}
        }
        self.buf[self.len] = byte;
        self.len += 1;
        self.len == PACKET_LEN
    }
}

/// Points gathered into a whole revolution of `N` beams, counter-clockwise from angle 0, one
/// beam every `2 pi / N`: the scan a [`BeamGeometry`](crate::frontend::scan::BeamGeometry)
/// with `angle_min = 0` and `angle_increment = 2 pi / N` describes. A point goes to its nearest
/// beam; two in one beam keep the nearer return; a beam without one is NaN.
#[derive(Clone, Debug)]
pub struct Revolution<const N: usize> {
    ranges: [f32; N],
    last_cdeg: Option<u32>,
    points: u32,
}

impl<const N: usize> Default for Revolution<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> Revolution<N> {
    /// Angle between beams, radians.
    pub const INCREMENT: f32 = 2.0 * PI / N as f32;

    /// An empty revolution.
    pub const fn new() -> Self {
        Revolution {
            ranges: [f32::NAN; N],
            last_cdeg: None,
            points: 0,
        }
    }

    /// Adds the points of `packet`. When the head passes angle zero inside it, the revolution
    /// so far is copied to `out` (ranges in metres) and the number of its points returned; the
    /// packet's points after zero start the next one.
    pub fn add(&mut self, packet: &Ld06Packet, out: &mut [f32; N]) -> Option<u32> {
        let mut done = None;
        for (i, p) in packet.points.iter().enumerate() {
            let a = packet.angle_cdeg(i);
            let wrapped = self.last_cdeg.is_some_and(|last| a + 18_000 < last);
            if let Some(n) = self.point(a, p.distance_mm, wrapped, out) {
                done = Some(n);
            }
        }
        done
    }

    /// Adds one point at the clockwise device angle `cw_cdeg` (0.01 degree) and distance
    /// `distance_mm` (0: no return). `new_turn` says the point begins the next revolution (the
    /// device's flag, or the angle passing zero): the revolution so far is then copied to `out`
    /// and its number of points returned.
    pub fn point(
        &mut self,
        cw_cdeg: u32,
        distance_mm: u16,
        new_turn: bool,
        out: &mut [f32; N],
    ) -> Option<u32> {
        let mut done = None;
        if new_turn && self.points > 0 {
            out.copy_from_slice(&self.ranges);
            done = Some(self.points);
            self.ranges = [f32::NAN; N];
            self.points = 0;
        }
        let a = cw_cdeg % u32::from(FULL_TURN);
        self.last_cdeg = Some(a);
        if distance_mm == 0 || N == 0 {
            return done;
        }
        // Clockwise device angle to counter-clockwise beam.
        let ccw = (u32::from(FULL_TURN) - a) % u32::from(FULL_TURN);
        let beam = libm::roundf(ccw as f32 * N as f32 / f32::from(FULL_TURN)) as usize % N;
        let r = f32::from(distance_mm) / 1000.0;
        let slot = &mut self.ranges[beam];
        if slot.is_nan() || r < *slot {
            *slot = r;
        }
        self.points += 1;
        done
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use std::vec::Vec;

    use super::*;

    /// A packet of a head at `start_cdeg`, 0.8 degree between points, seeing a wall at
    /// `distance_mm` everywhere.
    fn packet(start_cdeg: u16, distance_mm: u16) -> Ld06Packet {
        let end = (u32::from(start_cdeg) + 11 * 80) % 36_000;
        Ld06Packet {
            speed_dps: 3600,
            start_cdeg,
            end_cdeg: end as u16,
            stamp_ms: 1234,
            points: [Ld06Point {
                distance_mm,
                intensity: 200,
            }; POINTS],
        }
    }

    #[test]
    fn the_crc_is_the_vendors_polynomial() {
        // The first entries of the table of CRC-8 with polynomial 0x4D (one byte each).
        let table: Vec<u8> = (0..8u8).map(|b| crc8(&[b])).collect();
        assert_eq!(table, [0x00, 0x4d, 0x9a, 0xd7, 0x79, 0x34, 0xe3, 0xae]);
    }

    #[test]
    fn a_packet_reads_back_and_its_angles_wrap() {
        let p = packet(35_800, 1500);
        let mut r = PacketReader::new();
        let got: Vec<_> = p.encode().iter().filter_map(|&b| r.push(b)).collect();
        assert_eq!(got, [p]);
        assert_eq!(p.angle_cdeg(0), 35_800);
        assert_eq!(p.angle_cdeg(2), 35_960);
        assert_eq!(p.angle_cdeg(3), 40);
        assert_eq!(p.angle_cdeg(11), 680);
    }

    #[test]
    fn noise_and_a_damaged_packet_are_counted_and_the_next_packet_is_kept() {
        let (a, b) = (packet(1000, 800), packet(1880, 900));
        let mut bad = a.encode();
        bad[20] ^= 0x40;
        let mut stream: Vec<u8> = [0x00, 0x54, 0x54, 0x13].to_vec();
        stream.extend_from_slice(&bad[..40]);
        // A good packet starts inside the damaged one's bytes.
        stream.extend_from_slice(&b.encode());
        stream.extend_from_slice(&a.encode());
        stream.extend_from_slice(&b.encode()[..30]);
        let mut r = PacketReader::new();
        let got: Vec<_> = stream.iter().filter_map(|&x| r.push(x)).collect();
        assert_eq!(got, [b, a]);
        let c = r.counters();
        assert_eq!((c.packets, c.crc_errors), (2, 1));
        assert!(c.skipped_bytes >= 4, "{c:?}");
        // A bad angle under a good CRC.
        let mut odd = packet(100, 700);
        odd.start_cdeg = 36_000;
        let got: Vec<_> = odd.encode().iter().filter_map(|&x| r.push(x)).collect();
        assert!(got.is_empty());
        assert_eq!(r.counters().bad_angles, 1);
    }

    #[test]
    fn a_revolution_of_a_round_room_fills_its_beams_counter_clockwise() {
        const N: usize = 450;
        let mut rev = Revolution::<N>::new();
        let mut out = [0.0f32; N];
        let mut done = Vec::new();
        // Two and a half turns of 0.8-degree points; a wall 2 m away except one point at 1 m
        // at clockwise 90 degrees.
        let mut start = 0u32;
        for _ in 0..(36_000 * 5 / 2 / (12 * 80)) {
            let mut p = packet(start as u16, 2000);
            for i in 0..POINTS {
                if p.angle_cdeg(i) == 9_040 {
                    p.points[i].distance_mm = 1000;
                }
            }
            if let Some(n) = rev.add(&p, &mut out) {
                done.push((n, out));
            }
            start = (start + 12 * 80) % 36_000;
        }
        assert_eq!(done.len(), 2);
        for (n, ranges) in &done {
            assert_eq!(*n, 450, "points in a turn");
            assert!(
                ranges.iter().all(|r| r.is_finite()),
                "every beam has a point"
            );
            // Clockwise 90.4 degrees is counter-clockwise 269.6 = 337 x 0.8: beam 337 of 450.
            let near: Vec<usize> = (0..N).filter(|&i| ranges[i] < 1.5).collect();
            assert_eq!(near, [337]);
        }
    }
}
