//! File input and output through ARM semihosting: a `.cloilog` read from the host in fixed
//! chunks, text lines buffered before each write, a saved map (`.cloimap`) read and written as
//! an `embedded-io` stream, and the NUL-terminated paths the semihosting calls take.

use core::ffi::CStr;

use cloi_core::sensor::log::ByteSource;
use semihosting::fs::File;
use semihosting::io::{Read as _, Write as _};

/// Bytes per `SYS_READ`.
pub const CHUNK: usize = 4096;
/// Output buffered before each `SYS_WRITE`.
const OUT_BUFFER: usize = 8192;

/// A semihosting file read in fixed chunks.
pub(crate) struct ChunkedFile(pub(crate) File);

impl ByteSource for ChunkedFile {
    type Error = semihosting::io::Error;

    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let n = buf.len().min(CHUNK);
        self.0.read(&mut buf[..n])
    }
}

/// Text lines collected for the output file.
pub(crate) struct OutBuffer {
    pub(crate) bytes: [u8; OUT_BUFFER],
    pub(crate) len: usize,
}

impl core::fmt::Write for OutBuffer {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        let end = self.len + s.len();
        let dst = self.bytes.get_mut(self.len..end).ok_or(core::fmt::Error)?;
        dst.copy_from_slice(s.as_bytes());
        self.len = end;
        Ok(())
    }
}

impl OutBuffer {
    pub(crate) const fn new() -> Self {
        Self {
            bytes: [0; OUT_BUFFER],
            len: 0,
        }
    }

    pub(crate) fn flush_to(&mut self, file: &mut File) -> Result<(), semihosting::io::Error> {
        file.write_all(&self.bytes[..self.len])?;
        self.len = 0;
        Ok(())
    }
}

/// Copies `text` into `buf` with a terminating NUL, for the semihosting calls.
pub(crate) fn c_path<'a>(text: &str, buf: &'a mut [u8; 512]) -> Option<&'a CStr> {
    let bytes = text.as_bytes();
    buf.get_mut(..bytes.len())?.copy_from_slice(bytes);
    *buf.get_mut(bytes.len())? = 0;
    CStr::from_bytes_until_nul(&buf[..=bytes.len()]).ok()
}

/// A semihosting file as an `embedded-io` stream: reads in [`CHUNK`]s, writes gathered in a
/// buffer of the same size (the map writer's fields are a few bytes each, and every
/// semihosting call traps to the host).
pub(crate) struct MapFile {
    file: File,
    buffer: [u8; CHUNK],
    len: usize,
}

impl MapFile {
    pub(crate) fn new(file: File) -> Self {
        Self {
            file,
            buffer: [0; CHUNK],
            len: 0,
        }
    }
}

impl embedded_io::ErrorType for MapFile {
    type Error = embedded_io::ErrorKind;
}

impl embedded_io::Read for MapFile {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let n = buf.len().min(CHUNK);
        self.file
            .read(&mut buf[..n])
            .map_err(|_| embedded_io::ErrorKind::Other)
    }
}

impl embedded_io::Write for MapFile {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        if self.len == CHUNK {
            self.flush()?;
        }
        let n = buf.len().min(CHUNK - self.len);
        self.buffer[self.len..self.len + n].copy_from_slice(&buf[..n]);
        self.len += n;
        Ok(n)
    }

    fn flush(&mut self) -> Result<(), Self::Error> {
        self.file
            .write_all(&self.buffer[..self.len])
            .map_err(|_| embedded_io::ErrorKind::Other)?;
        self.len = 0;
        Ok(())
    }
}
