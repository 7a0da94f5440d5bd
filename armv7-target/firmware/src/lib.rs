//! Shared pieces of the CLOi-Mapper firmware binaries for the bare-metal Cortex-A9 (QEMU
//! `vexpress-a9`):
//! * `cloi-firmware` (`src/main.rs`): the core's fixed workload, section by section;
//! * `cloi-mapper` (`src/bin/cloi-mapper.rs`): the real mapper (`home` profile) over a
//!   `.cloilog`, fed as `cloi map --deterministic` feeds it ([`mapper`]).
//!
//! They are two binaries so that the mapper's code cannot change how the compiler inlines the
//! workload's sections, whose instruction budgets are fixed. The mapper reads its log and
//! writes its results through [`semihost_io`] and summarizes its instruction counts with
//! [`stats`].
#![no_std]

pub mod mapper;
pub mod semihost_io;
pub mod statics;
pub mod stats;
pub mod timer;

use semihosting::println;

/// Prints the SYS-mode stack high-water mark. aarch32-rt zeroes the stacks at boot, so the
/// untouched words at the bottom are still zero.
pub fn report_stack() {
    let Some(range) = aarch32_rt::stacks::Stack::Sys.range(0) else {
        println!("stack_used_bytes=unknown");
        return;
    };
    // SAFETY: the range is the SYS stack that the linker script reserved; it is mapped, word
    // aligned and readable.
    let (total, used) = unsafe { aarch32_cpu::stacks::stack_used_bytes(range) };
    println!("stack_total_bytes={total}");
    println!("stack_used_bytes={used}");
}
