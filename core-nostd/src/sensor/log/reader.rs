//! Streaming decoding of a `.cloilog`: records pulled from a [`ByteSource`] through a buffer
//! the caller lends, so a bare-metal target can read a log of any length in fixed chunks.

use core::fmt;

use super::frame::{decode_frame, decode_header, frame_len};
use super::{LogError, LogHeader, LogRecord, HEADER_LEN, MIN_READER_BUFFER};

/// Where a [`LogReader`] gets its bytes: a file read in chunks, a serial link, a slice.
pub trait ByteSource {
    /// The source's own error.
    type Error;

    /// Fills the front of `buf` with the next bytes and returns how many; 0 means the end.
    ///
    /// # Errors
    /// The source's failure; the reader passes it on as [`ReadError::Source`].
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error>;
}

impl ByteSource for &[u8] {
    type Error = core::convert::Infallible;

    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let n = buf.len().min(self.len());
        let (head, tail) = self.split_at(n);
        if let Some(dst) = buf.get_mut(..n) {
            dst.copy_from_slice(head);
        }
        *self = tail;
        Ok(n)
    }
}

/// A failure of [`LogReader::next_record`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ReadError<E> {
    /// The log is damaged; `offset` is the stream position of the header or record at fault.
    Log {
        /// What is wrong.
        error: LogError,
        /// Byte offset in the stream.
        offset: u64,
    },
    /// The byte source failed.
    Source(E),
}

impl<E: fmt::Display> fmt::Display for ReadError<E> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Log { error, offset } => write!(f, "at byte {offset}: {error}"),
            Self::Source(e) => write!(f, "reading the log: {e}"),
        }
    }
}

impl<E: fmt::Debug + fmt::Display> core::error::Error for ReadError<E> {}

/// Streams records from a [`ByteSource`] through a buffer lent by the caller.
///
/// The reader asks the source for as many bytes as fit after the unread ones (a source may
/// return fewer: the firmware reads fixed chunks), moves the unread tail to the front when a
/// record would not fit, and yields each record borrowed from the buffer until the next call.
/// After an error it yields nothing more.
#[derive(Debug)]
pub struct LogReader<'b, S> {
    source: S,
    buf: &'b mut [u8],
    start: usize,
    end: usize,
    /// Stream offset of `buf[start]`.
    offset: u64,
    header: Option<LogHeader>,
    records: u32,
    source_done: bool,
    failed: bool,
}

/// What the buffer holds at its front.
enum Front {
    Ready(usize),
    Need(usize),
}

impl<'b, S: ByteSource> LogReader<'b, S> {
    /// A reader over `source` using `buf` (at least [`MIN_READER_BUFFER`] bytes).
    ///
    /// # Errors
    /// [`LogError::BufferTooSmall`].
    pub fn new(source: S, buf: &'b mut [u8]) -> Result<Self, LogError> {
        if buf.len() < MIN_READER_BUFFER {
            return Err(LogError::BufferTooSmall {
                need: MIN_READER_BUFFER,
                have: buf.len(),
            });
        }
        Ok(Self {
            source,
            buf,
            start: 0,
            end: 0,
            offset: 0,
            header: None,
            records: 0,
            source_done: false,
            failed: false,
        })
    }

    /// The file header, once the first record (or the end) has been read.
    pub fn header(&self) -> Option<LogHeader> {
        self.header
    }

    /// Records yielded so far.
    pub fn records(&self) -> u32 {
        self.records
    }

    /// Stream offset of the next unread byte.
    pub fn offset(&self) -> u64 {
        self.offset
    }

    /// The source (e.g. to close a file).
    pub fn into_source(self) -> S {
        self.source
    }

    fn fail<T>(&mut self, error: LogError) -> Result<T, ReadError<S::Error>> {
        self.failed = true;
        Err(ReadError::Log {
            error,
            offset: self.offset,
        })
    }

    /// Makes room for `need` bytes at the front and reads once from the source; returns
    /// false at the end of the source.
    fn refill(&mut self, need: usize) -> Result<bool, ReadError<S::Error>> {
        if self.source_done {
            return Ok(false);
        }
        if self.start + need > self.buf.len() || self.end == self.buf.len() {
            self.buf.copy_within(self.start..self.end, 0);
            self.end -= self.start;
            self.start = 0;
        }
        let Some(space) = self.buf.get_mut(self.end..) else {
            return Ok(false);
        };
        let n = match self.source.read(space) {
            Ok(n) => n.min(space.len()),
            Err(e) => {
                self.failed = true;
                return Err(ReadError::Source(e));
            }
        };
        if n == 0 {
            self.source_done = true;
            return Ok(false);
        }
        self.end += n;
        Ok(true)
    }

    fn front(&self) -> Result<Front, LogError> {
        let avail = self.buf.get(self.start..self.end).unwrap_or(&[]);
        if self.header.is_none() {
            return Ok(match decode_header(avail)? {
                Some((_, len)) => Front::Ready(len),
                None => Front::Need(HEADER_LEN.max(avail.len() + 1)),
            });
        }
        Ok(match frame_len(avail)? {
            Some(total) if total <= avail.len() => Front::Ready(total),
            Some(total) => Front::Need(total),
            None => Front::Need(8),
        })
    }

    /// Next record, `Ok(None)` at the clean end of the log.
    ///
    /// # Errors
    /// [`ReadError::Log`] for damaged or truncated data (including a record count that
    /// disagrees with the header), [`ReadError::Source`] when the source fails.
    pub fn next_record(&mut self) -> Result<Option<LogRecord<'_>>, ReadError<S::Error>> {
        if self.failed {
            return Ok(None);
        }
        let len = loop {
            let need = match self.front() {
                Ok(Front::Ready(len)) if self.header.is_some() => break len,
                Ok(Front::Ready(len)) => {
                    // The header: remember it, skip it and look again.
                    let avail = self.buf.get(self.start..self.end).unwrap_or(&[]);
                    match decode_header(avail) {
                        Ok(Some((h, _))) => self.header = Some(h),
                        Ok(None) => return self.fail(LogError::BadMagic),
                        Err(e) => return self.fail(e),
                    }
                    self.start += len;
                    self.offset += len as u64;
                    continue;
                }
                Ok(Front::Need(need)) => need,
                Err(e) => return self.fail(e),
            };
            if !self.refill(need)? {
                let have = self.end - self.start;
                if self.header.is_none() {
                    return self.fail(LogError::Truncated {
                        have,
                        need: HEADER_LEN,
                    });
                }
                if have > 0 {
                    return self.fail(LogError::Truncated { have, need });
                }
                if let Some(expected) = self.header.and_then(|h| h.record_count) {
                    if expected != self.records {
                        return self.fail(LogError::CountMismatch {
                            expected,
                            found: self.records,
                        });
                    }
                }
                return Ok(None);
            }
        };
        let at = self.start;
        let offset = self.offset;
        self.start += len;
        self.offset += len as u64;
        // Disjoint fields: the record borrows `buf` while `failed` and `records` change.
        let Self {
            buf,
            failed,
            records,
            ..
        } = self;
        let frame = buf.get(at..at + len).unwrap_or(&[]);
        match decode_frame(frame) {
            Ok((record, _)) => {
                *records = records.saturating_add(1);
                Ok(Some(record))
            }
            Err(error) => {
                *failed = true;
                Err(ReadError::Log { error, offset })
            }
        }
    }
}
