//! CLOi-Mapper firmware for a bare-metal Cortex-A9 (QEMU `vexpress-a9`).
//!
//! Runs the core's fixed workload, printing for every section its instruction count (from the
//! A9 global timer under `-icount shift=0`) and its checksum as raw f64 bits, then the stack
//! high-water mark, and exits through semihosting (status 0 on success). The QEMU tests parse
//! this output; each line is `key=value` pairs separated by spaces.
#![no_std]
#![no_main]

mod timer;

use aarch32_rt::entry;
use cloi_core::workload::Section;
use semihosting::{println, process};

#[entry]
fn main() -> ! {
    timer::enable();
    println!("firmware=cloi-firmware version={}", env!("CARGO_PKG_VERSION"));
    for section in Section::ALL {
        let start = timer::ticks();
        let result = core::hint::black_box(section.run());
        let end = timer::ticks();
        let ticks = end - start;
        println!(
            "section={} ticks={} instructions={} result={:016x}",
            section.name(),
            ticks,
            ticks * timer::INSTRUCTIONS_PER_TICK,
            result.to_bits()
        );
    }
    report_stack();
    println!("status=ok");
    process::exit(0)
}

/// Prints the SYS-mode stack high-water mark. aarch32-rt zeroes the stacks at boot, so the
/// untouched words at the bottom are still zero.
fn report_stack() {
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

#[panic_handler]
fn panic(info: &core::panic::PanicInfo<'_>) -> ! {
    println!("status=panic message={}", info);
    process::exit(101)
}
