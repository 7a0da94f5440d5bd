//! The Slamtec RPLIDAR serial protocol (A1, A2, C1), standard scan mode: the requests the host
//! sends, the response descriptor, and the 5-byte measurement nodes decoded byte by byte
//! without a heap. Nodes go into the same [`Revolution`](super::ld06::Revolution) as the
//! LD06's points (the RPLIDAR's angles also grow clockwise).
//!
//! # Frames (from the vendor's public protocol description)
//! * A request is `0xA5`, a command byte (and for some commands a payload): [`STOP`],
//!   [`RESET`], [`SCAN`], [`GET_HEALTH`].
//! * A response starts with a 7-byte descriptor: `0xA5 0x5A`, a 32-bit little-endian word
//!   holding the data length (30 bits) and the send mode (2 bits: 1 = a stream of responses),
//!   and the data type. A scan answers [`SCAN_DESCRIPTOR`]: 5-byte nodes, streamed.
//! * A node: byte 0 = quality (6 bits) << 2 | !S << 1 | S, S set on the first node of a new
//!   turn; byte 1 = angle bits 6..0 << 1 | 1 (the check bit); byte 2 = angle bits 14..7, the
//!   angle in 1/64 degree; bytes 3-4 = distance in 1/4 mm, little endian (0: no return).
//!
//! A node whose S and !S agree, or whose check bit is clear, is not a node boundary: the reader
//! drops one byte and tries again (counted), so it finds the node grid again after noise.

/// First byte of every request and response descriptor.
pub const SYNC: u8 = 0xA5;
/// Second byte of a response descriptor.
pub const SYNC2: u8 = 0x5A;
/// Request: stop scanning.
pub const STOP: u8 = 0x25;
/// Request: reset the core.
pub const RESET: u8 = 0x40;
/// Request: start a standard scan.
pub const SCAN: u8 = 0x20;
/// Request: the device's health.
pub const GET_HEALTH: u8 = 0x52;
/// The descriptor a standard scan answers with (5-byte nodes, streamed, type 0x81).
pub const SCAN_DESCRIPTOR: [u8; 7] = [SYNC, SYNC2, 0x05, 0x00, 0x00, 0x40, 0x81];
/// Bytes of one node.
pub const NODE_LEN: usize = 5;

/// A request of `command` without payload.
pub const fn request(command: u8) -> [u8; 2] {
    [SYNC, command]
}

/// One measurement.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Node {
    /// First node of a new turn.
    pub start: bool,
    /// Return strength (0..63).
    pub quality: u8,
    /// Clockwise angle, 1/64 degree.
    pub angle_q6: u16,
    /// Distance, 1/4 mm (0: no return).
    pub distance_q2: u16,
}

impl Node {
    /// The node's 5 bytes.
    pub fn encode(&self) -> [u8; NODE_LEN] {
        let s = u8::from(self.start);
        let a = self.angle_q6 & 0x7FFF;
        let d = self.distance_q2.to_le_bytes();
        [
            (self.quality & 0x3F) << 2 | (s ^ 1) << 1 | s,
            ((a & 0x7F) as u8) << 1 | 1,
            (a >> 7) as u8,
            d[0],
            d[1],
        ]
    }

    fn decode(b: &[u8; NODE_LEN]) -> Option<Self> {
        let s = b[0] & 1;
        if s == (b[0] >> 1) & 1 || b[1] & 1 == 0 {
            return None;
        }
        Some(Node {
            start: s == 1,
            quality: b[0] >> 2,
            angle_q6: u16::from(b[1] >> 1) | u16::from(b[2]) << 7,
            distance_q2: u16::from_le_bytes([b[3], b[4]]),
        })
    }

    /// Clockwise angle, 0.01 degree.
    pub fn angle_cdeg(&self) -> u32 {
        (u32::from(self.angle_q6) * 100 + 32) / 64
    }

    /// Distance, mm (rounded).
    pub fn distance_mm(&self) -> u16 {
        ((u32::from(self.distance_q2) + 2) / 4) as u16
    }
}

/// What the node reader met.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct NodeCounters {
    /// Nodes decoded.
    pub nodes: u64,
    /// Bytes dropped to find the node grid again.
    pub skipped_bytes: u64,
}

/// Decodes a standard scan's node stream (after its descriptor).
#[derive(Clone, Debug, Default)]
pub struct NodeReader {
    buf: [u8; NODE_LEN],
    len: usize,
    counters: NodeCounters,
}

impl NodeReader {
    /// A reader at a node boundary.
    pub const fn new() -> Self {
        NodeReader {
            buf: [0; NODE_LEN],
            len: 0,
            counters: NodeCounters {
                nodes: 0,
                skipped_bytes: 0,
            },
        }
    }

    /// What the reader met so far.
    pub fn counters(&self) -> NodeCounters {
        self.counters
    }

    /// Takes the next byte; a node when this byte completed a valid one.
    pub fn push(&mut self, byte: u8) -> Option<Node> {
        self.buf[self.len] = byte;
        self.len += 1;
        if self.len < NODE_LEN {
            return None;
        }
        if let Some(node) = Node::decode(&self.buf) {
            self.len = 0;
            self.counters.nodes += 1;
            return Some(node);
        }
        // Not a boundary: drop the first byte and wait for one more.
        self.buf.copy_within(1.., 0);
        self.len = NODE_LEN - 1;
        self.counters.skipped_bytes += 1;
        None
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use std::vec::Vec;

    use super::super::ld06::Revolution;
    use super::*;

    /// `turns` turns of 360 nodes, one a degree, at `mm` everywhere.
    fn stream(turns: usize, mm: u16) -> Vec<u8> {
        let mut out = Vec::new();
        for _ in 0..turns {
            for k in 0..360u16 {
                let n = Node {
                    start: k == 0,
                    quality: 47,
                    angle_q6: k * 64,
                    distance_q2: mm * 4,
                };
                out.extend_from_slice(&n.encode());
            }
        }
        out
    }

    #[test]
    fn nodes_round_trip_and_their_units_convert() {
        let n = Node {
            start: true,
            quality: 63,
            angle_q6: 359 * 64 + 32,
            distance_q2: 12_001,
        };
        let mut r = NodeReader::new();
        let got: Vec<Node> = n.encode().iter().filter_map(|&b| r.push(b)).collect();
        assert_eq!(got, [n]);
        assert_eq!(n.angle_cdeg(), 35_950);
        assert_eq!(n.distance_mm(), 3000);
        assert_eq!(request(SCAN), [0xA5, 0x20]);
    }

    #[test]
    fn noise_before_the_stream_is_skipped_and_turns_are_cut_at_the_start_flag() {
        let mut bytes = std::vec![0x00, 0xFF, 0x13];
        bytes.extend(stream(3, 1500));
        let mut r = NodeReader::new();
        let mut rev = Revolution::<360>::new();
        let mut out = [0f32; 360];
        let mut turns = Vec::new();
        for b in bytes {
            if let Some(n) = r.push(b) {
                if let Some(points) = rev.point(n.angle_cdeg(), n.distance_mm(), n.start, &mut out)
                {
                    turns.push((points, out));
                }
            }
        }
        assert!(r.counters().skipped_bytes >= 3, "{:?}", r.counters());
        // Three turns, each cut when the next starts: two whole ones come out.
        assert_eq!(turns.len(), 2);
        for (points, ranges) in &turns {
            assert_eq!(*points, 360);
            assert!(ranges.iter().all(|&m| (m - 1.5).abs() < 1e-6));
        }
    }
}
