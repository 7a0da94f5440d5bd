//! CLOi-Mapper firmware for a bare-metal Cortex-A9 (QEMU `vexpress-a9`): the workload binary.
//!
//! Runs the core's fixed workload, printing for every section its instruction count (from the
//! A9 global timer under `-icount shift=0`) and its checksum as raw f64 bits, then the stack
//! high-water mark, and exits through semihosting (status 0 on success). The QEMU tests parse
//! this output; each line is `key=value` pairs separated by spaces.
#![no_std]
#![no_main]

use aarch32_rt::entry;
use cloi_core::workload::{Section, WorkloadStorage};
use cloi_firmware::statics::TakeOnce;
use cloi_firmware::{report_stack, timer};
use semihosting::{println, process};

/// The storage of the sections too large for the stack (the camera frames).
static STORAGE: TakeOnce<WorkloadStorage> = TakeOnce::new(WorkloadStorage::new());

#[entry]
fn main() -> ! {
    timer::enable();
    let Some(storage) = STORAGE.take() else {
        println!("status=error message=workload storage taken twice");
        process::exit(1)
    };
    println!(
        "firmware=cloi-firmware version={}",
        env!("CARGO_PKG_VERSION")
    );
    for section in Section::ALL {
        let start = timer::ticks();
        let result = core::hint::black_box(section.run(storage));
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

#[panic_handler]
fn panic(info: &core::panic::PanicInfo<'_>) -> ! {
    cloi_firmware::panic_exit(info)
}
