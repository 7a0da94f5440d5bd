//! CLOi-Mapper firmware for a bare-metal Cortex-A9 (QEMU `vexpress-a9`): the mapper binary.
//!
//! Reads `log=PATH out=PATH [save=MAP]` from the semihosting command line
//! (`SYS_GET_CMDLINE`, i.e. QEMU's `-append`), runs the `home` mapper over the `.cloilog` at
//! `log` (see `cloi_firmware::mapper`), writes the real-time and keyframe poses to `out` (and
//! with `save`, the final map as a `.cloimap`), prints the
//! instruction percentiles per section and the stack high-water mark, and exits through semihosting (status 0 on success). Paths are opened by
//! QEMU on the host (relative to its working folder) and must not contain spaces.
//! `load=MAP` instead reads a saved map into the profile's static pools and prints what it
//! holds (`cloi_firmware::mapper::load`); `localize=MAP [initial=X,Y,THETA]` with `log` and
//! `out` localizes in a saved map instead of mapping (`cloi localize`; without `initial`, by
//! global localization).
#![no_std]
#![no_main]

use aarch32_rt::entry;
use cloi_firmware::{mapper, report_stack, timer};
use semihosting::{println, process};

/// Bytes of command line the firmware reads.
const CMDLINE_BYTES: usize = 1024;

#[entry]
fn main() -> ! {
    timer::enable();
    println!("firmware=cloi-mapper version={}", env!("CARGO_PKG_VERSION"));
    let Ok(args) = semihosting::experimental::env::args::<CMDLINE_BYTES>() else {
        println!("status=error message=\"no semihosting command line\"");
        process::exit(2);
    };
    let (mut log, mut out, mut save, mut load) = (None, None, None, None);
    let (mut localize, mut initial) = (None, None);
    // The first word is the kernel's file name.
    for arg in (&args).skip(1).flatten() {
        if let Some(v) = arg.strip_prefix("log=") {
            log = Some(v);
        } else if let Some(v) = arg.strip_prefix("out=") {
            out = Some(v);
        } else if let Some(v) = arg.strip_prefix("save=") {
            save = Some(v);
        } else if let Some(v) = arg.strip_prefix("load=") {
            load = Some(v);
        } else if let Some(v) = arg.strip_prefix("localize=") {
            localize = Some(v);
        } else if let Some(v) = arg.strip_prefix("initial=") {
            let Some(pose) = parse_pose(v) else {
                println!("status=error message=\"initial= wants X,Y,THETA\"");
                process::exit(2);
            };
            initial = Some(pose);
        } else {
            println!("status=error message=\"unknown argument {arg}\"");
            process::exit(2);
        }
    }
    let localize = localize.map(|map| mapper::LocalizeIn { map, initial });
    let result = match (log, out, load) {
        (Some(log), Some(out), None) if localize.is_none() || save.is_none() => {
            mapper::run(log, out, save, localize)
        }
        (None, None, Some(map)) if save.is_none() && localize.is_none() => mapper::load(map),
        _ => {
            println!(
                "status=error message=\"usage: -append 'log=PATH out=PATH [save=MAP]', \
                 'log=PATH out=PATH localize=MAP [initial=X,Y,THETA]' or 'load=MAP'\""
            );
            process::exit(2);
        }
    };
    if let Err(message) = result {
        println!("status=error message=\"{message}\"");
        process::exit(1);
    }
    report_stack();
    println!("status=ok");
    process::exit(0)
}

/// `X,Y,THETA` as a pose.
fn parse_pose(s: &str) -> Option<cloi_core::Se2> {
    let mut v = s.split(',').map(|f| f.parse::<f64>().ok());
    let pose = cloi_core::Se2::new(v.next()??, v.next()??, v.next()??);
    (v.next().is_none() && pose.is_finite()).then_some(pose)
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo<'_>) -> ! {
    cloi_firmware::panic_exit(info)
}
