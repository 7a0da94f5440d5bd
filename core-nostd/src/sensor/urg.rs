//! Hokuyo's SCIP 2.0 protocol (URG-04LX, UTM-30LX and their kin on a serial or USB port): the
//! requests the host sends, the parameter lines of `PP`, and the scans of `MD` / `GD` decoded
//! line by line without a heap.
//!
//! # Frames (from the vendor's public protocol description)
//! * Requests and responses are lines of printable characters ending in LF. A request is a
//!   two-letter command and its parameters ([`md_request`], [`PP`], [`BM`], [`QT`]); the
//!   response repeats the request line, then a status line (two characters and a check
//!   character), then lines of data each ending in its check character, then an empty line.
//! * A check character is the sum of the line's other characters, its low six bits, plus
//!   `0x30`.
//! * Numbers are written six bits to a character, each plus `0x30`, most significant first:
//!   distances in three characters (mm; values below 20 are the device's error codes), time
//!   stamps in four (ms, wrapping at 2^24). The distances run on from one data line to the
//!   next: a value may start at the end of one line and end on the next.
//! * `MD` (continuous scans) answers first with status `00` and no data, then each scan with
//!   status `99`, its time stamp line and its distances; `GD` (one scan) answers `00` and its
//!   data.
//! * `PP` answers `NAME:VALUE;` lines (the check character after the `;` covers the text
//!   before it): `DMIN`, `DMAX` (mm), `ARES` (steps in a full turn), `AMIN`, `AMAX` (the first
//!   and last step measured), `AFRT` (the step straight ahead) and `SCAN` (turns a minute).
//!
//! A line whose check character does not match is counted; the scan it belongs to is dropped
//! (a distance lost would shift every later one to another bearing).

/// The longest line the reader keeps (a data line is 64 characters and its check).
pub const MAX_LINE: usize = 80;
/// Most steps of one scan (a UTM-30LX measures 1,081).
pub const MAX_STEPS: usize = 1440;

/// Request: the device's parameters.
pub const PP: &[u8] = b"PP\n";
/// Request: switch the laser on.
pub const BM: &[u8] = b"BM\n";
/// Request: stop measuring, laser off.
pub const QT: &[u8] = b"QT\n";
/// Request: switch a device that also speaks SCIP 1.1 to SCIP 2.0.
pub const SCIP2: &[u8] = b"SCIP2.0\n";
/// Bytes of an `MD` request.
pub const MD_LEN: usize = 16;

/// The check character of `text`.
pub fn check(text: &[u8]) -> u8 {
    (text.iter().fold(0u32, |s, &b| s + u32::from(b)) & 0x3F) as u8 + 0x30
}

/// A number written in `chars` (six bits a character, plus `0x30`).
pub fn decode(chars: &[u8]) -> u32 {
    chars
        .iter()
        .fold(0, |v, &c| (v << 6) | u32::from(c.wrapping_sub(0x30) & 0x3F))
}

/// `value` written in `N` characters (its low `6 * N` bits).
pub fn encode<const N: usize>(value: u32) -> [u8; N] {
    let mut out = [0u8; N];
    for (i, c) in out.iter_mut().enumerate() {
        *c = ((value >> (6 * (N - 1 - i))) & 0x3F) as u8 + 0x30;
    }
    out
}

/// `n` as `D` decimal digits (its last `D` when longer).
fn digits<const D: usize>(mut n: u32) -> [u8; D] {
    let mut out = [b'0'; D];
    for c in out.iter_mut().rev() {
        *c = b'0' + (n % 10) as u8;
        n /= 10;
    }
    out
}

/// The request of continuous scans of steps `first..=last`, every step (no grouping), every
/// turn, until stopped: `MD` `first` `last` (four digits each) `00` `0` `00`.
pub fn md_request(first: u16, last: u16) -> [u8; MD_LEN] {
    let mut r = [0u8; MD_LEN];
    r[..2].copy_from_slice(b"MD");
    r[2..6].copy_from_slice(&digits::<4>(u32::from(first)));
    r[6..10].copy_from_slice(&digits::<4>(u32::from(last)));
    r[10..15].copy_from_slice(b"00000");
    r[15] = b'\n';
    r
}

/// What `PP` told of the device.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct UrgParams {
    /// Shortest range, mm.
    pub dmin: u32,
    /// Longest range, mm.
    pub dmax: u32,
    /// Steps in a full turn.
    pub ares: u32,
    /// First step measured.
    pub amin: u32,
    /// Last step measured.
    pub amax: u32,
    /// The step straight ahead.
    pub afrt: u32,
    /// Turns a minute.
    pub scan_rpm: u32,
}

impl UrgParams {
    /// Takes one line of a `PP` answer (`NAME:VALUE;` and its check character); whether it
    /// was a good line of a known name.
    pub fn take_line(&mut self, line: &[u8]) -> bool {
        let Some((&sum, body)) = line.split_last() else {
            return false;
        };
        let Some(text) = body.strip_suffix(b";") else {
            return false;
        };
        if check(text) != sum {
            return false;
        }
        let Some(colon) = text.iter().position(|&b| b == b':') else {
            return false;
        };
        let (name, value) = (&text[..colon], &text[colon + 1..]);
        let Some(v) = parse_decimal(value) else {
            return false;
        };
        let slot = match name {
            b"DMIN" => &mut self.dmin,
            b"DMAX" => &mut self.dmax,
            b"ARES" => &mut self.ares,
            b"AMIN" => &mut self.amin,
            b"AMAX" => &mut self.amax,
            b"AFRT" => &mut self.afrt,
            b"SCAN" => &mut self.scan_rpm,
            _ => return false,
        };
        *slot = v;
        true
    }

    /// Whether the parameters describe a device this reader can take: a turn of steps, a
    /// measured span within it and within [`MAX_STEPS`], ranges and a turning speed.
    pub fn usable(&self) -> bool {
        self.ares > 0
            && self.amin <= self.amax
            && self.amax < self.ares
            && (self.amax - self.amin + 1) as usize <= MAX_STEPS
            && self.dmin < self.dmax
            && self.scan_rpm > 0
    }

    /// The `PP` line of `name` with `value` (what a device sends; for emulators and tests).
    pub fn line(name: &str, value: u32, out: &mut [u8; 24]) -> usize {
        let mut n = 0;
        for &b in name.as_bytes().iter().chain(b":") {
            out[n] = b;
            n += 1;
        }
        let d = digits::<10>(value);
        let first = d.iter().position(|&c| c != b'0').unwrap_or(9);
        for &b in &d[first..] {
            out[n] = b;
            n += 1;
        }
        let sum = check(&out[..n]);
        out[n] = b';';
        out[n + 1] = sum;
        out[n + 2] = b'\n';
        n + 3
    }
}

/// A decimal number of at most nine digits.
fn parse_decimal(s: &[u8]) -> Option<u32> {
    if s.is_empty() || s.len() > 9 {
        return None;
    }
    s.iter().try_fold(0u32, |v, &c| {
        c.is_ascii_digit().then(|| v * 10 + u32::from(c - b'0'))
    })
}

/// What the reader met.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct UrgCounters {
    /// Lines read.
    pub lines: u64,
    /// Lines whose check character did not match.
    pub check_errors: u64,
    /// Lines longer than [`MAX_LINE`], dropped.
    pub long_lines: u64,
    /// Whole scans decoded.
    pub scans: u64,
    /// Scans dropped: a bad line, a status other than `99`/`00`, more steps than
    /// [`MAX_STEPS`], or distances not a whole number of values.
    pub scans_dropped: u64,
}

/// Where the reader is in a response.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Part {
    /// Waiting for the echo of a request.
    Echo,
    /// The echo was of `MD` or `GD`: the status line comes.
    Status,
    /// A scan's time stamp line comes.
    Stamp,
    /// Distance lines come, until the empty line.
    Data,
    /// Not a scan, or a damaged one: skip to the empty line.
    Skip,
}

/// One scan decoded: its time stamp and the number of distances (in [`ScanReader::ranges_mm`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct UrgScan {
    /// The device's clock at the scan, ms (wraps at 2^24).
    pub stamp_ms: u32,
    /// Distances decoded.
    pub steps: usize,
}

/// Responses decoded byte by byte into scans.
#[derive(Clone, Debug)]
pub struct ScanReader {
    line: [u8; MAX_LINE],
    len: usize,
    long: bool,
    part: Part,
    stamp_ms: u32,
    ranges: [u32; MAX_STEPS],
    steps: usize,
    /// Characters of a distance begun at the end of the last line.
    pending: [u8; 3],
    pending_len: usize,
    counters: UrgCounters,
}

impl Default for ScanReader {
    fn default() -> Self {
        Self::new()
    }
}

impl ScanReader {
    /// A reader waiting for a response.
    pub const fn new() -> Self {
        ScanReader {
            line: [0; MAX_LINE],
            len: 0,
            long: false,
            part: Part::Echo,
            stamp_ms: 0,
            ranges: [0; MAX_STEPS],
            steps: 0,
            pending: [0; 3],
            pending_len: 0,
            counters: UrgCounters {
                lines: 0,
                check_errors: 0,
                long_lines: 0,
                scans: 0,
                scans_dropped: 0,
            },
        }
    }

    /// What it met so far.
    pub fn counters(&self) -> UrgCounters {
        self.counters
    }

    /// The distances of the last scan, mm (values below 20 are the device's error codes).
    pub fn ranges_mm(&self) -> &[u32] {
        &self.ranges[..self.steps]
    }

    /// The next byte; a scan when it ended one.
    pub fn push(&mut self, byte: u8) -> Option<UrgScan> {
        if byte != b'\n' {
            if self.len < MAX_LINE {
                self.line[self.len] = byte;
                self.len += 1;
            } else {
                self.long = true;
            }
            return None;
        }
        let len = core::mem::take(&mut self.len);
        self.counters.lines += 1;
        if core::mem::take(&mut self.long) {
            self.counters.long_lines += 1;
            self.drop_scan();
            return None;
        }
        self.line_ended(len)
    }

    fn line_ended(&mut self, len: usize) -> Option<UrgScan> {
        if len == 0 {
            // The end of a response.
            let part = core::mem::replace(&mut self.part, Part::Echo);
            if part == Part::Data {
                if self.pending_len == 0 {
                    self.counters.scans += 1;
                    return Some(UrgScan {
                        stamp_ms: self.stamp_ms,
                        steps: self.steps,
                    });
                }
                self.counters.scans_dropped += 1;
            }
            return None;
        }
        let mut line = [0u8; MAX_LINE];
        line[..len].copy_from_slice(&self.line[..len]);
        let line = &line[..len];
        match self.part {
            Part::Echo => {
                self.part = if line.starts_with(b"MD") || line.starts_with(b"GD") {
                    Part::Status
                } else {
                    Part::Skip
                };
            }
            Part::Status => {
                self.part = match line {
                    [a, b, sum] if check(&[*a, *b]) == *sum => match [*a, *b] {
                        // `MD`'s first answer (`00`) has no data; `GD`'s has.
                        [b'9', b'9'] | [b'0', b'0'] => Part::Stamp,
                        _ => Part::Skip,
                    },
                    _ => {
                        self.counters.check_errors += 1;
                        Part::Skip
                    }
                };
            }
            Part::Stamp => match self.data_line(line) {
                Some(text) if text.len() == 4 => {
                    self.stamp_ms = decode(text);
                    self.steps = 0;
                    self.pending_len = 0;
                    self.part = Part::Data;
                }
                _ => self.drop_scan(),
            },
            Part::Data => {
                let mut chars = [0u8; MAX_LINE];
                let Some(text) = self.data_line(line) else {
                    self.drop_scan();
                    return None;
                };
                let n = text.len();
                chars[..n].copy_from_slice(text);
                for &c in &chars[..n] {
                    self.pending[self.pending_len] = c;
                    self.pending_len += 1;
                    if self.pending_len == 3 {
                        self.pending_len = 0;
                        if self.steps == MAX_STEPS {
                            self.drop_scan();
                            return None;
                        }
                        self.ranges[self.steps] = decode(&self.pending);
                        self.steps += 1;
                    }
                }
            }
            Part::Skip => {}
        }
        None
    }

    /// The text of a data line whose check character matches (counted when not).
    fn data_line<'l>(&mut self, line: &'l [u8]) -> Option<&'l [u8]> {
        let (&sum, text) = line.split_last()?;
        if check(text) == sum {
            Some(text)
        } else {
            self.counters.check_errors += 1;
            None
        }
    }

    /// Drops the scan under way (counted) and skips to the end of its response.
    fn drop_scan(&mut self) {
        if matches!(self.part, Part::Stamp | Part::Data) {
            self.counters.scans_dropped += 1;
        }
        self.part = Part::Skip;
    }
}

/// Writes one scan as an `MD` response block (echo, status `99`, time stamp, distances in
/// lines of 64 characters, each with its check, and the empty line) into `out`; the bytes
/// written (for emulators and tests). `out` must hold `echo.len() + 12 + 66 * lines` bytes.
pub fn write_scan(echo: &[u8], stamp_ms: u32, ranges_mm: &[u32], out: &mut [u8]) -> usize {
    let mut n = 0;
    let mut put = |bytes: &[u8], out: &mut [u8]| {
        out[n..n + bytes.len()].copy_from_slice(bytes);
        n += bytes.len();
    };
    put(echo, out);
    put(b"99b\n", out);
    let stamp = encode::<4>(stamp_ms);
    put(&stamp, out);
    put(&[check(&stamp), b'\n'], out);
    let mut line = [0u8; 64];
    let mut len = 0;
    for &r in ranges_mm {
        for c in encode::<3>(r) {
            line[len] = c;
            len += 1;
            if len == 64 {
                put(&line, out);
                put(&[check(&line), b'\n'], out);
                len = 0;
            }
        }
    }
    if len > 0 {
        put(&line[..len], out);
        put(&[check(&line[..len]), b'\n'], out);
    }
    put(b"\n", out);
    n
}

#[cfg(test)]
mod tests {
    extern crate std;
    use std::vec;
    use std::vec::Vec;

    use super::*;

    fn scan_bytes(stamp: u32, ranges: &[u32]) -> Vec<u8> {
        let echo = md_request(44, 725);
        let mut out = vec![0u8; echo.len() + 12 + 66 * (ranges.len() * 3 / 64 + 1)];
        let n = write_scan(&echo, stamp, ranges, &mut out);
        out.truncate(n);
        out
    }

    #[test]
    fn numbers_and_checks_are_the_specifications() {
        // The status of a continuous scan, "99", checks as 'b'; "00" as 'P'.
        assert_eq!(check(b"99"), b'b');
        assert_eq!(check(b"00"), b'P');
        // 5432 mm in three characters, a time stamp in four.
        assert_eq!(decode(&encode::<3>(5432)), 5432);
        assert_eq!(decode(&encode::<4>(16_000_000)), 16_000_000);
        assert_eq!(&md_request(44, 725), b"MD0044072500000\n");
    }

    #[test]
    fn scans_are_decoded_across_line_breaks_and_damage_drops_one_scan() {
        let a: Vec<u32> = (0..682).map(|k| 20 + 7 * k).collect();
        let b: Vec<u32> = (0..682).map(|k| 5000 - 3 * k).collect();
        let mut bytes = b"MD0044072500000\n00P\n\n".to_vec();
        bytes.extend(scan_bytes(1000, &a));
        let mut damaged = scan_bytes(1100, &b);
        damaged[60] ^= 0x01;
        bytes.extend(damaged);
        bytes.extend(scan_bytes(1200, &b));
        let mut r = ScanReader::new();
        let mut got = Vec::new();
        for byte in bytes {
            if let Some(s) = r.push(byte) {
                got.push((s.stamp_ms, r.ranges_mm().to_vec()));
            }
        }
        assert_eq!(got, [(1000, a), (1200, b)]);
        let c = r.counters();
        assert_eq!((c.scans, c.scans_dropped, c.check_errors), (2, 1, 1));
    }

    #[test]
    fn parameters_are_read_from_their_lines() {
        let mut p = UrgParams::default();
        let mut line = [0u8; 24];
        for (name, v) in [
            ("DMIN", 20),
            ("DMAX", 5600),
            ("ARES", 1024),
            ("AMIN", 44),
            ("AMAX", 725),
            ("AFRT", 384),
            ("SCAN", 600),
        ] {
            let n = UrgParams::line(name, v, &mut line);
            // Without its LF, as the reader hands lines over.
            assert!(p.take_line(&line[..n - 1]), "{name}");
        }
        assert!(p.usable());
        assert_eq!((p.ares, p.afrt, p.scan_rpm), (1024, 384, 600));
        assert!(!p.take_line(b"MODL:URG;X"), "a bad check");
        assert!(!p.take_line(b"DMIN:2x;"), "not a number");
    }
}
