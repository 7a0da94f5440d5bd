//! Checks of a linked firmware image.

use std::path::Path;

use anyhow::{Context, Result};
use object::{Object, ObjectSection, ObjectSymbol};

/// Symbols whose presence means a heap allocator was linked.
pub const ALLOCATOR_SYMBOLS: [&str; 6] = [
    "__rust_alloc",
    "__rust_alloc_zeroed",
    "__rust_realloc",
    "__rust_dealloc",
    "__rdl_alloc",
    "__rg_alloc",
];

/// What the ELF check found.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ElfReport {
    /// Bytes of code (`.text` and friends).
    pub text: u64,
    /// Bytes of read-only data.
    pub rodata: u64,
    /// Bytes of initialised data.
    pub data: u64,
    /// Bytes of zero-initialised data.
    pub bss: u64,
    /// Bytes reserved for stacks (the `.stacks` section of aarch32-rt), if present.
    pub stacks: u64,
    /// Allocator symbols found (should be empty).
    pub allocator_symbols: Vec<String>,
}

impl ElfReport {
    /// Static RAM: `.data + .bss` (stacks are reported apart).
    pub fn static_ram(&self) -> u64 {
        self.data + self.bss
    }
}

/// Reads section sizes and allocator symbols from the ELF file at `path`.
///
/// # Errors
/// The file cannot be read or is not an ELF object.
pub fn inspect(path: &Path) -> Result<ElfReport> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    inspect_bytes(&bytes).with_context(|| format!("parsing ELF file {}", path.display()))
}

/// Like [`inspect`], on bytes in memory.
///
/// # Errors
/// The bytes are not an ELF object.
pub fn inspect_bytes(bytes: &[u8]) -> Result<ElfReport> {
    let file = object::File::parse(bytes)?;
    let mut report = ElfReport::default();
    for section in file.sections() {
        let name = section.name().unwrap_or("");
        let size = section.size();
        if name.starts_with(".text") || name == ".vector_table" || name == ".init" {
            report.text += size;
        } else if name.starts_with(".rodata") || name == ".ARM.exidx" {
            report.rodata += size;
        } else if name.starts_with(".data") {
            report.data += size;
        } else if name.starts_with(".bss") || name.starts_with(".uninit") {
            report.bss += size;
        } else if name.starts_with(".stack") {
            report.stacks += size;
        }
    }
    for sym in file.symbols() {
        if let Ok(name) = sym.name() {
            if ALLOCATOR_SYMBOLS.contains(&name) {
                report.allocator_symbols.push(name.to_owned());
            }
        }
    }
    Ok(report)
}

/// Reads the stack high-water mark from a firmware run log (`stack_used_bytes=N` line).
pub fn stack_high_water(log: &str) -> Option<u64> {
    log.lines().find_map(|l| {
        l.trim()
            .strip_prefix("stack_used_bytes=")?
            .trim()
            .parse()
            .ok()
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn non_elf_input_is_an_error() {
        assert!(inspect_bytes(b"not an elf file").is_err());
    }

    #[test]
    fn reads_stack_line() {
        assert_eq!(
            stack_high_water("a=1\nstack_used_bytes= 4096\n"),
            Some(4096)
        );
        assert_eq!(stack_high_water("nothing"), None);
    }
}
