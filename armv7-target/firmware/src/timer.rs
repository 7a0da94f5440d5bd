//! The Cortex-A9 MPCore global timer, our instruction counter.
//!
//! Under `qemu-system-arm -icount shift=0,sleep=off` virtual time advances one nanosecond per
//! guest instruction and this 64-bit timer counts at 100 MHz of virtual time, so one tick is
//! exactly ten instructions, identical from run to run.

use core::ptr::{read_volatile, write_volatile};

const BASE: usize = 0x1E00_0200;
const COUNTER_LO: *mut u32 = BASE as *mut u32;
const COUNTER_HI: *mut u32 = (BASE + 0x04) as *mut u32;
const CONTROL: *mut u32 = (BASE + 0x08) as *mut u32;

/// Guest instructions per timer tick under `-icount shift=0`.
pub const INSTRUCTIONS_PER_TICK: u64 = 10;

/// Starts the timer.
pub fn enable() {
    // SAFETY: the vexpress-a9 private peripheral region maps the global timer at BASE; this is
    // the only code that touches it.
    unsafe { write_volatile(CONTROL, 1) };
}

/// The current 64-bit count (the high word is re-read to catch a carry between the reads).
pub fn ticks() -> u64 {
    loop {
        // SAFETY: as in `enable`: plain reads of the timer's counter registers.
        let (hi, lo, hi2) = unsafe {
            (
                read_volatile(COUNTER_HI),
                read_volatile(COUNTER_LO),
                read_volatile(COUNTER_HI),
            )
        };
        if hi == hi2 {
            return (u64::from(hi) << 32) | u64::from(lo);
        }
    }
}
