//! CRC-32 (IEEE 802.3, as in zlib and PNG): the checksum that ends every `.cloilog` record,
//! computed by `crc32fast` (table-driven without `std`; the same bytes on every target).

/// CRC-32 (IEEE) of `bytes`.
pub fn crc32(bytes: &[u8]) -> u32 {
    crc32fast::hash(bytes)
}
