//! The bare-metal firmware on the emulated Cortex-A9: exact, repeatable instruction counts under
//! budget, results bit-identical to x86-64, and a bounded stack.

use cloi_core::workload::{Section, WorkloadStorage};
use cloi_qemu_tests::{build_firmware, run_firmware, workspace_root};

/// Instruction budget of each section (a new section must be given one here) (measured counts are in the README;
/// these ceilings leave ~25 % of headroom for compiler changes, not for regressions to hide).
fn budget(section: Section) -> u64 {
    match section {
        // 20,000 compositions including their sin/cos: <= 600 instructions each.
        Section::Se2Chain => 20_000 * 600,
        // 5,000 head-to-tail compoundings: <= 900 instructions each.
        Section::CovarianceCompound => 5_000 * 900,
        // 5,000 exp/log round trips with three trig calls: <= 1,000 each.
        Section::ExpLog => 5_000 * 1_000,
        // 5,000 Cholesky factorizations and solves of a 3x3 system plus trig: <= 900 each
        // (measured 698 with the covariance opaque to the optimizer, so the factorization is
        // not hoisted out of the loop).
        Section::Mahalanobis => 5_000 * 900,
        // One Gauss-Newton solve of a 24-node graph with four loops (ordering, linear
        // initialisation, three iterations): measured 513,190.
        Section::PoseGraphSolve => 650_000,
        // Preprocess two 180-beam scans, ray-trace one into an 82 x 82 submap, voxel point
        // map, ICP of the second (measured 1,768,680 instructions with floor without libm):
        // ~25 % headroom.
        Section::ScanMatch => 2_210_000,
        // Two 320 x 240 frames filled with 36 panels (a fill per row, then the pixel sum):
        // measured 1,338,950.
        Section::CameraRender => 1_680_000,
        // The visual front-end on those two frames (4-level pyramid, FAST with the grid,
        // orientation, smoothing, BRIEF of 111 and 115 corners, brute-force matching of the
        // second frame to the first, 89 matches): measured 36,312,610, 18.2 M per frame.
        Section::CameraTrack => 45_500_000,
    }
}

/// SYS-mode stack budget of the workload (the mapper's is set by its own issue).
const STACK_BUDGET_BYTES: u64 = 32 * 1024;

#[test]
fn firmware_counts_are_exact_within_budget_and_match_x86() {
    let elf = build_firmware().expect("firmware builds");
    let first = run_firmware(&elf).expect("first run");
    let second = run_firmware(&elf).expect("second run");

    // Keep the log for `cloi-budget --run-log` and for people.
    let log_path = workspace_root().join("target").join("qemu-firmware.log");
    std::fs::create_dir_all(log_path.parent().unwrap()).unwrap();
    std::fs::write(&log_path, &first.log).unwrap();

    assert_eq!(
        first.sections.len(),
        Section::ALL.len(),
        "every section ran:\n{}",
        first.log
    );
    let mut storage = Box::new(WorkloadStorage::new());
    for (section, (a, b)) in Section::ALL
        .iter()
        .zip(first.sections.iter().zip(&second.sections))
    {
        assert_eq!(a.name, section.name());
        assert_eq!(
            a.instructions, b.instructions,
            "{}: instruction counts differ between two runs",
            a.name
        );
        assert!(
            a.instructions <= budget(*section),
            "{}: {} instructions over the budget of {}",
            a.name,
            a.instructions,
            budget(*section)
        );
        // Same code on x86-64: IEEE-754 doubles with libm on both sides, no FMA contraction,
        // so the checksums agree to the bit.
        let host = section.run(&mut storage);
        assert_eq!(
            a.result_bits,
            host.to_bits(),
            "{}: Cortex-A9 gives {} but x86-64 gives {}",
            a.name,
            f64::from_bits(a.result_bits),
            host
        );
        println!(
            "{:<14} {:>12} instructions  result {:e}",
            a.name, a.instructions, host
        );
    }
    assert!(
        first.stack_used_bytes > 0 && first.stack_used_bytes <= STACK_BUDGET_BYTES,
        "stack high-water {} B (budget {} B)",
        first.stack_used_bytes,
        STACK_BUDGET_BYTES
    );
}
