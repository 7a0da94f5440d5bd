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

use core::panic::PanicInfo;

use semihosting::io::Write as _;
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

/// Prints `status=panic` with the panic's location and, when it is a literal, its message, then
/// exits with status 101.
///
/// It writes raw bytes and formats nothing with `core::fmt`: formatting can panic again, and a
/// handler that formats makes the call graph recursive (panic, format, panic), which the static
/// stack bound (`cloi-budget --stack-ir`) refuses.
pub fn panic_exit(info: &PanicInfo<'_>) -> ! {
    if let Ok(mut out) = semihosting::io::stdout() {
        let mut line = [0u8; 10];
        let (file, line_no) = info
            .location()
            .map_or(("unknown", 0), |l| (l.file(), l.line()));
        let parts: [&[u8]; 7] = [
            b"status=panic file=",
            file.as_bytes(),
            b" line=",
            decimal(line_no, &mut line),
            b" message=",
            info.message().as_str().unwrap_or("(formatted)").as_bytes(),
            b"\n",
        ];
        for part in parts {
            if out.write_all(part).is_err() {
                break;
            }
        }
    }
    semihosting::process::exit(101)
}

/// `n` in decimal, written at the end of `buf`.
fn decimal(mut n: u32, buf: &mut [u8; 10]) -> &[u8] {
    let mut at = buf.len();
    loop {
        at -= 1;
        // `n % 10` is below 10: the cast keeps it whole.
        buf[at] = b'0' + (n % 10) as u8;
        n /= 10;
        if n == 0 || at == 0 {
            return &buf[at..];
        }
    }
}
