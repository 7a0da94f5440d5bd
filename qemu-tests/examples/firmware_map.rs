//! Benchmark: the mapper firmware (`home` profile, static resources) on whole CARMEN logs
//! under `qemu-system-arm -icount shift=0`, one Cortex-A9 instruction per virtual nanosecond.
//! Prints one markdown table of instruction percentiles per section and log, one of counts,
//! stack and accuracy (the real-time trajectory emitted on the A9, scored against the GMapping
//! reference relations like `cloi eval ref`), and keeps each run's console output and pose
//! file under `target/bench-firmware/LOG/`.
//!
//! `cargo run --release -p cloi-qemu-tests --example firmware_map -- [LOG ...]`
//! (`bench/firmware.sh` runs it on intel, fr079 and mit-csail; LOG is a name under
//! `../shared/data/carmen/` without `.clf`, or a path to a `.clf`).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use cloi_core::Se2;
use cloi_host::eval::relations::{relations_from_reference, score, PlanarTrajectory};
use cloi_host::io::carmen::{CarmenReader, CarmenRecord};
use cloi_qemu_tests::mapper::{run_mapper_timeout, MapperRun};
use cloi_qemu_tests::{build_firmware, firmware_elf, workspace_root};

/// Sections printed, with the scans each covers.
const SECTIONS: [(&str, &str); 8] = [
    ("frontend", "accepted scans"),
    ("gpe", "accepted scans"),
    ("frontend_gpe", "scans that are not keyframes"),
    ("keyframe_update", "keyframes"),
    ("loop_search", "loop searches"),
    ("push_scan", "accepted scans"),
    (
        "backend_working",
        "back-end steps that worked (optimizer or far loop search)",
    ),
    (
        "backend_optimizer",
        "back-end steps that advanced the optimizer",
    ),
];

/// The front laser's mounting from the log's `robot_frontlaser_offset` parameter (forward
/// offset only, as CARMEN records it), read up to the first laser line.
fn laser_offset(clf: &std::path::Path) -> Result<Se2> {
    let mut x = 0.0;
    for rec in CarmenReader::open(clf, false)? {
        match rec? {
            CarmenRecord::Param { name, value } if name == "robot_frontlaser_offset" => {
                x = value.parse().unwrap_or(0.0);
            }
            CarmenRecord::Laser(_) => break,
            _ => {}
        }
    }
    Ok(Se2::new(x, 0.0, 0.0))
}

fn main() -> Result<()> {
    let mut logs: Vec<String> = std::env::args().skip(1).collect();
    if logs.is_empty() {
        logs = ["intel", "fr079", "mit-csail"].map(String::from).to_vec();
    }
    build_firmware()?;
    let elf = firmware_elf("cloi-mapper");
    let root = workspace_root().join("target").join("bench-firmware");
    let mut runs: Vec<(String, MapperRun, f64, Option<f64>)> = Vec::new();
    for log in &logs {
        let clf = if log.ends_with(".clf") {
            PathBuf::from(log)
        } else {
            workspace_root().join(format!("../shared/data/carmen/{log}.clf"))
        };
        let name = clf
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| log.clone());
        let dir = root.join(&name);
        std::fs::create_dir_all(&dir)?;
        let dir = dir.canonicalize()?;
        let cloilog = dir.join(format!("{name}.cloilog"));
        cloi_host::io::cloilog::carmen_to_cloilog(&clf, &cloilog, false, None, None)
            .with_context(|| format!("converting {}", clf.display()))?;
        eprintln!("{name}: running the mapper firmware under QEMU ...");
        let t0 = Instant::now();
        let run = run_mapper_timeout(&elf, &cloilog, &dir.join("poses.txt"), 7200)?;
        let wall = t0.elapsed().as_secs_f64();
        std::fs::write(dir.join("firmware.log"), &run.log)?;
        // The real-time trajectory as emitted on the A9, against the reference relations, in
        // the laser's frame (the reference holds laser poses; fr079's laser is off-centre).
        let reference = clf.with_file_name(format!("{name}.gfs_reference_poses.txt"));
        let error = if reference.is_file() {
            let reference = PlanarTrajectory::load_reference(&reference)?;
            let rels = relations_from_reference(&reference, 1.0);
            let mut poses: Vec<(i64, Se2)> = run
                .poses
                .iter()
                .map(|p| (p.t_ns, Se2::new(p.pose[0], p.pose[1], p.pose[2])))
                .collect();
            // Sorted by time, as the scoring expects (intel's stamps step back in the file).
            poses.sort_by_key(|p| p.0);
            let laser = laser_offset(&clf)?;
            let trajectory = PlanarTrajectory { poses }.in_sensor_frame(&laser);
            Some(score(&trajectory, &rels, 0.0)?.trans_mean_m)
        } else {
            None
        };
        runs.push((name, run, wall, error));
    }

    println!("Instructions per call (min / median / p99 / max; 1 instruction ~ 1 ns at 1 GHz):\n");
    print!("| section | calls |");
    for (name, ..) in &runs {
        print!(" {name} median | {name} p99 | {name} max |");
    }
    println!();
    print!("|---|---|");
    for _ in &runs {
        print!("---:|---:|---:|");
    }
    println!();
    for (section, over) in SECTIONS {
        print!("| {section} | {over} |");
        for (_, run, ..) in &runs {
            match run.sections.get(section) {
                Some(p) => print!(" {} | {} | {} |", p.median, p.p99, p.max),
                None => print!(" - | - | - |"),
            }
        }
        println!();
    }
    println!(
        "\n| log | scans | keyframes kept / made | loop closures | prunes | dropped keyframes | \
         stack bytes | real-time error m | QEMU wall s |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|");
    for (name, run, wall, error) in &runs {
        let c = |k: &str| run.counters.get(k).copied().unwrap_or(0);
        println!(
            "| {name} | {} | {} / {} | {} | {} | {} | {} | {} | {wall:.0} |",
            run.scans,
            run.keyframes.len(),
            c("keyframes"),
            c("loop_closures"),
            c("prunes"),
            c("keyframes_dropped"),
            run.stack_used_bytes,
            error.map_or("-".into(), |e| format!("{e:.4}")),
        );
    }
    Ok(())
}
