//! The firmware's replay mode on a real log: the first scans of intel.clf, converted to a
//! `.cloilog`, streamed through semihosting into the bare-metal Cortex-A9 firmware under
//! `qemu-system-arm -icount shift=0`. The per-scan poses must equal, bit for bit, the same core
//! calls on x86-64; the instruction percentiles per scan and the stack must stay under their
//! budgets, and two runs must count the same instructions.
//!
//! Equality: both sides run the same Rust code on IEEE-754 doubles and floats with `libm`
//! (no std float functions, no fused multiply-add on either target), so the results are
//! expected to agree to the bit; the test asserts bit identity, not a tolerance.

use cloi_qemu_tests::replay::{host_replay, run_replay, Percentiles};
use cloi_qemu_tests::{build_firmware, firmware_elf, workspace_root};

/// Scans of intel.clf replayed (about 0.36 MB of log, ~4 s under QEMU).
const SCANS: u64 = 400;

/// Instruction budgets per scan of the replay step (preprocess + ICP against the keyframe
/// points + keyframe insertion). Measured on 400 scans: median 735,250, p99 3,888,250, max
/// 4,247,350 (floor without libm since 2026-12-01; 1,011,730 / 4,738,980 / 5,474,100 before);
/// the ceilings leave ~25 % for compiler changes.
const MEDIAN_BUDGET: u64 = 920_000;
const P99_BUDGET: u64 = 4_860_000;
const MAX_BUDGET: u64 = 5_310_000;

/// Stack high-water budget of the replay (issue 8: at most 64 KiB).
const STACK_BUDGET_BYTES: u64 = 64 * 1024;

#[test]
fn intel_replay_on_the_a9_matches_x86_within_budget() {
    let Some(clf) = cloi_host::dataset::shared_file("carmen/intel.clf") else {
        return;
    };
    let dir = workspace_root().join("target").join("qemu-replay");
    std::fs::create_dir_all(&dir).unwrap();
    let dir = dir.canonicalize().unwrap();
    let log = dir.join(format!("intel-{SCANS}.cloilog"));
    let report =
        cloi_host::io::cloilog::carmen_to_cloilog(&clf, &log, false, None, Some(SCANS)).unwrap();
    assert_eq!(report.scans, SCANS);
    assert_eq!(report.input.damaged, 0);

    build_firmware().expect("firmware builds");
    let elf = firmware_elf("cloi-replay");
    let first = run_replay(&elf, &log, &dir.join("poses-1.txt")).expect("first replay");
    let second = run_replay(&elf, &log, &dir.join("poses-2.txt")).expect("second replay");
    std::fs::write(dir.join("firmware.log"), &first.log).unwrap();
    println!("{}", first.log);

    // Every scan ran and matched.
    assert_eq!(first.scans, SCANS);
    assert_eq!(first.poses.len() as u64, SCANS);
    assert_eq!(first.unmatched, 0, "{}", first.log);

    // Exact, repeatable instruction counts; the printed percentiles are those of the file.
    let counts: Vec<u64> = first.poses.iter().map(|p| p.instructions).collect();
    let again: Vec<u64> = second.poses.iter().map(|p| p.instructions).collect();
    assert_eq!(counts, again, "instruction counts differ between two runs");
    assert_eq!(first.instructions, Percentiles::of(&counts));
    let p = first.instructions;
    println!(
        "replay of {} scans: instructions per scan min {} median {} p99 {} max {}; stack {} B",
        p.n, p.min, p.median, p.p99, p.max, first.stack_used_bytes
    );
    assert!(
        p.median <= MEDIAN_BUDGET,
        "median {} > {MEDIAN_BUDGET}",
        p.median
    );
    assert!(p.p99 <= P99_BUDGET, "p99 {} > {P99_BUDGET}", p.p99);
    assert!(p.max <= MAX_BUDGET, "max {} > {MAX_BUDGET}", p.max);
    assert!(
        first.stack_used_bytes > 0 && first.stack_used_bytes <= STACK_BUDGET_BYTES,
        "stack high-water {} B (budget {STACK_BUDGET_BYTES} B)",
        first.stack_used_bytes
    );

    // The same calls on x86-64, on the same bytes: bit-identical poses.
    let host = host_replay(&std::fs::read(&log).unwrap()).unwrap();
    assert_eq!(host.len(), first.poses.len());
    for (i, (h, a)) in host.iter().zip(&first.poses).enumerate() {
        assert_eq!(h.stamp.as_nanos(), a.t_ns, "scan {i}: time");
        assert_eq!(h.matched, a.matched, "scan {i}: matched");
        let hp = [h.pose.x, h.pose.y, h.pose.theta];
        for (k, (hv, av)) in hp.iter().zip(&a.pose).enumerate() {
            assert_eq!(
                hv.to_bits(),
                av.to_bits(),
                "scan {i}: component {k}: x86-64 {hv} vs Cortex-A9 {av}"
            );
        }
    }
    let last = host.last().unwrap().pose;
    println!(
        "final pose after {SCANS} scans: {:.6} {:.6} {:.6} (identical on both)",
        last.x, last.y, last.theta
    );
}
