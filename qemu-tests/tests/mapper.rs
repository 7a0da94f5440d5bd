//! The real mapper on the Cortex-A9: the first scans of intel.clf, converted to a `.cloilog`,
//! streamed through semihosting into the bare-metal `cloi-mapper` firmware (the `home`
//! profile's `MapperResources` as one static) under `qemu-system-arm -icount shift=0`, fed
//! as `cloi map --deterministic` feeds the mapper. The same log goes through `cloi map
//! --deterministic --profile home` on x86-64 (in-process: `cloi_host::map::run::run`).
//!
//! Checks: the two configurations are identical; every scan's real-time pose (`gpe.tum`) and
//! every keyframe's final pose (`graph.g2o` VERTEX lines) are bit-identical on both machines;
//! the saved maps (`.cloimap`) are the same bytes, and the firmware reads the host's map into
//! its static pools with the same contents and localizes in it as `cloi localize` does; the
//! instruction percentiles per section and the stack are under the budgets below.
//!
//! Equality: both sides run the same Rust code on IEEE-754 doubles and floats with `libm`
//! (no std float functions in the core, no fused multiply-add on either target), so the
//! results are expected to agree to the bit; the test asserts bit identity, not a tolerance.

use cloi_core::mapper::MapperConfig;
use cloi_host::map::config::{MapConfig, Profile};
use cloi_host::map::run::{run, LocalizeIn, MapSettings, StampPolicy};
use cloi_host::map::{open_input, InputOptions};
use cloi_qemu_tests::mapper::{load_map_firmware, run_localizer, run_mapper, run_mapper_saving};
use cloi_qemu_tests::stats::Percentiles;
use cloi_qemu_tests::{build_firmware, firmware_elf, workspace_root};

/// Scans of intel.clf mapped (about 0.9 MB of log; enough keyframes for the back-end to run
/// during the log, about 20 s under QEMU).
const SCANS: u64 = 1000;

/// Back-end iterations per scan: the default of `cloi map --backend-iterations` and the
/// firmware's `BACKEND_ITERATIONS_PER_SCAN`.
const BACKEND_ITERATIONS: u32 = 5;

/// Instruction budgets per section: (name, median, p99, max). Measured on these 1000 scans
/// (all accepted: the 130 whose stamps step back are fed in file order; 163 keyframes, 82 loop
/// searches that found no candidate yet, 3 back-end optimizations during the log), with the
/// home profile's front-end (rotated turn seeds only above 5 cm RMS, stalled odometry
/// compensated) and floor without libm:
/// * `push_scan` (front-end + GPE + keyframe + loop search, every accepted scan): median
///   881,670, p99 4,453,340, max 5,312,850;
/// * `frontend_gpe` (scans that did not become keyframes): 825,580 / 4,204,430 / 5,310,810;
/// * `keyframe_scan` (scans that became keyframes): 1,478,120 / 5,164,310 / 5,312,850;
/// * the parts of `push_scan` (the firmware's `Probe`): `frontend` (checks, preprocessing,
///   ICP; every scan) 828,130 / 4,226,100 / 5,305,440; `gpe` (the GPE update) 3,500 /
///   4,400 / 4,410; `keyframe_update` (frame node, submap and local map of a keyframe)
///   570,830 / 1,025,890 / 1,295,490; `loop_search` (the windowed search, which finds no
///   candidate yet in these scans, and keeping the keyframe's scan for the far search)
///   4,920 / 8,810 / 8,810;
/// * `backend_working` (back-end steps that worked: the optimizer, or the far loop search in
///   the turns it leaves idle): 412,170 / 626,140 / 626,140 (3 steps, all the optimizer's);
/// * `backend_optimizer` (back-end steps that advanced the optimizer: chunks of at most
///   `backend.work_budget` work units, solves of 5 iterations at most): the same 3 steps; on
///   these scans the graph is small (164 nodes) and every solve ends within one step's
///   budget, so these are whole solves. The whole log, where steps are cut by the budget, is
///   [`intel_whole_log_backend_chunks_stay_bounded`].
///
/// The ceilings leave about 25 %. Issue 8's targets are far above them: front-end + GPE
/// median <= 5 M and p99 <= 10 M instructions (a 10 Hz LiDAR under 10 % of a 1 GHz A9 on
/// average), GPE update p99 <= 1 M.
const BUDGETS: [(&str, u64, u64, u64); 9] = [
    ("push_scan", 1_100_000, 5_570_000, 6_640_000),
    ("frontend_gpe", 1_030_000, 5_250_000, 6_640_000),
    ("keyframe_scan", 1_850_000, 6_450_000, 6_640_000),
    ("frontend", 1_030_000, 5_280_000, 6_630_000),
    ("gpe", 4_400, 5_500, 5_600),
    ("keyframe_update", 715_000, 1_280_000, 1_620_000),
    ("loop_search", 6_200, 11_000, 11_000),
    ("backend_working", 515_000, 785_000, 785_000),
    ("backend_optimizer", 515_000, 785_000, 785_000),
];

/// Stack high-water budget (issue 8: at most 64 KiB).
const STACK_BUDGET_BYTES: u64 = 64 * 1024;

#[test]
fn intel_mapper_on_the_a9_matches_x86_within_budget() {
    let Some(clf) = cloi_host::dataset::shared_file("carmen/intel.clf") else {
        return;
    };
    let dir = workspace_root().join("target").join("qemu-mapper");
    std::fs::create_dir_all(&dir).unwrap();
    let dir = dir.canonicalize().unwrap();
    let log = dir.join(format!("intel-{SCANS}.cloilog"));
    let report =
        cloi_host::io::cloilog::carmen_to_cloilog(&clf, &log, false, None, Some(SCANS)).unwrap();
    assert_eq!(report.scans, SCANS);
    assert_eq!(report.input.damaged, 0);

    build_firmware().expect("firmware builds");
    let elf = firmware_elf("cloi-mapper");
    let fw_map = dir.join("firmware.cloimap");
    let fw = run_mapper_saving(&elf, &log, &dir.join("poses.txt"), Some(&fw_map), 600)
        .expect("mapper firmware run");
    std::fs::write(dir.join("firmware.log"), &fw.log).unwrap();
    println!("{}", fw.log);

    // x86-64: `cloi map LOG --deterministic --profile home --quiet --out DIR`.
    let profile = Profile::Home;
    let mut config = MapConfig::preset(profile);
    config.run.deterministic = true;
    let host_cfg = config.to_core(&profile.core_config());
    // The firmware names its preset (it prints no `Debug`, see its mapper.rs); the preset must
    // be what `cloi map --profile home` runs.
    assert_eq!(fw.config, "MapperConfig::home");
    assert_eq!(
        format!("{:?}", MapperConfig::home()),
        format!("{host_cfg:?}"),
        "MapperConfig::home differs from `cloi map --profile home`"
    );
    let out = dir.join("host");
    let settings = MapSettings {
        profile,
        config,
        out: out.clone(),
        deterministic: true,
        backend_delay_s: 0.0,
        backend_iterations_per_scan: BACKEND_ITERATIONS,
        max_scans: None,
        stamps: StampPolicy::FileOrder,
        progress: false,
        keep_gpe: true,
        save_map: Some(dir.join("host.cloimap")),
        localize: None,
        visual: None,
    };
    let input = open_input(&log, &InputOptions::default()).unwrap();
    let host = run(input, &settings).expect("cloi map on x86-64");

    // Every scan ran; the same scans were accepted on both.
    assert_eq!(fw.scans, SCANS);
    assert_eq!(fw.rejected, host.report.scans_rejected, "{}", fw.log);
    assert_eq!(fw.poses.len(), host.gpe.len());
    assert_eq!(fw.counters["keyframes"], host.report.keyframes);
    assert_eq!(fw.counters["loop_closures"], host.report.loop_closures);
    assert!(fw.counters["keyframes"] > 10, "{}", fw.log);

    // Real-time poses, bit for bit.
    for (i, (h, a)) in host.gpe.iter().zip(&fw.poses).enumerate() {
        assert_eq!(h.0, a.t_ns, "scan {i}: time");
        let hp = [h.1.x, h.1.y, h.1.theta];
        for (k, (hv, av)) in hp.iter().zip(&a.pose).enumerate() {
            assert_eq!(
                hv.to_bits(),
                av.to_bits(),
                "scan {i}: real-time pose component {k}: x86-64 {hv} vs Cortex-A9 {av}"
            );
        }
    }
    // Final keyframe poses: the VERTEX lines of graph.g2o (shortest round-trip decimals).
    let g2o = std::fs::read_to_string(out.join("graph.g2o")).unwrap();
    let vertices: Vec<(u32, [f64; 3])> = g2o
        .lines()
        .filter(|l| l.starts_with("VERTEX_SE2 "))
        .map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            let v = |i: usize| f[i].parse::<f64>().unwrap();
            (f[1].parse().unwrap(), [v(2), v(3), v(4)])
        })
        .collect();
    assert_eq!(vertices.len(), fw.keyframes.len());
    for ((serial, pose), k) in vertices.iter().zip(&fw.keyframes) {
        assert_eq!(*serial, k.serial);
        for (c, (hv, av)) in pose.iter().zip(&k.pose).enumerate() {
            assert_eq!(
                hv.to_bits(),
                av.to_bits(),
                "keyframe {serial}: component {c}: x86-64 {hv} vs Cortex-A9 {av}"
            );
        }
    }

    // The saved map: the same bytes from both machines, and the A9 reads the host's file into
    // its static pools with the same contents.
    let host_map = dir.join("host.cloimap");
    assert_eq!(
        std::fs::read(&fw_map).expect("firmware map"),
        std::fs::read(&host_map).expect("host map"),
        "the maps saved on x86-64 and on the Cortex-A9 differ"
    );
    let loaded = cloi_host::io::map_file::load_map(&host_map).expect("host reads its map");
    let on_a9 = load_map_firmware(&elf, &host_map).expect("firmware loads the map");
    println!("map on the A9: {on_a9:?}");
    let s = loaded.summary;
    for (key, want) in [
        ("map_nodes", s.nodes),
        ("map_edges", s.edges),
        ("map_submaps", s.submaps),
        ("map_next_serial", s.next_serial),
    ] {
        assert_eq!(on_a9[key], want.to_string(), "{key}");
    }
    assert_eq!(
        on_a9["map_checksum"],
        format!("{:016x}", map_checksum(&loaded))
    );
    assert_eq!(s.nodes as usize, vertices_in(&out));

    // Instruction budgets per section; the printed percentiles are those of the pose file.
    let accepted: Vec<u64> = fw.poses.iter().map(|p| p.push_scan).collect();
    assert_eq!(fw.sections["push_scan"], Percentiles::of(&accepted));
    for (name, median, p99, max) in BUDGETS {
        let p = fw.sections[name];
        println!(
            "{name}: n {} min {} median {} p99 {} max {}",
            p.n, p.min, p.median, p.p99, p.max
        );
        assert!(p.n > 0, "{name}: no samples");
        assert!(p.median <= median, "{name}: median {} > {median}", p.median);
        assert!(p.p99 <= p99, "{name}: p99 {} > {p99}", p.p99);
        assert!(p.max <= max, "{name}: max {} > {max}", p.max);
    }
    assert!(
        fw.stack_used_bytes > 0 && fw.stack_used_bytes <= STACK_BUDGET_BYTES,
        "stack high-water {} B (budget {STACK_BUDGET_BYTES} B)",
        fw.stack_used_bytes
    );
    let last = host.gpe.last().unwrap().1;
    println!(
        "{} keyframes, final real-time pose {:.6} {:.6} {:.6} (identical on both)",
        vertices.len(),
        last.x,
        last.y,
        last.theta
    );

    localization_on_the_a9_matches_x86(&elf, &dir, &log, &host_map, &fw);
}

/// The A9 localizes in the saved map (issue 17): the firmware reads the host's map into its
/// static pools and tracks the same scans in it (`localize=MAP initial=0,0,0`; the map's frame
/// is the first scan's pose), as `cloi localize MAP LOG --initial-pose 0,0,0 --deterministic`
/// does on x86-64: the same real-time poses to the bit, the same localization counters, and a
/// scan costs fewer instructions than mapping it did (`mapping`: the mapping run over the
/// same log): no submap, no graph, no back-end.
fn localization_on_the_a9_matches_x86(
    elf: &std::path::Path,
    dir: &std::path::Path,
    log: &std::path::Path,
    map: &std::path::Path,
    mapping: &cloi_qemu_tests::mapper::MapperRun,
) {
    let fw = run_localizer(
        elf,
        log,
        &dir.join("localized.txt"),
        map,
        Some([0.0; 3]),
        600,
    )
    .expect("localizing firmware run");
    std::fs::write(dir.join("firmware-localize.log"), &fw.log).unwrap();
    let profile = Profile::Home;
    let mut config = MapConfig::preset(profile);
    config.run.deterministic = true;
    let settings = MapSettings {
        profile,
        config,
        out: dir.join("host-localize"),
        deterministic: true,
        backend_delay_s: 0.0,
        backend_iterations_per_scan: BACKEND_ITERATIONS,
        max_scans: None,
        stamps: StampPolicy::FileOrder,
        progress: false,
        keep_gpe: true,
        save_map: None,
        localize: Some(LocalizeIn {
            map: map.to_path_buf(),
            initial_pose: Some(cloi_core::Se2::IDENTITY),
            extend: false,
        }),
        visual: None,
    };
    let input = open_input(log, &InputOptions::default()).unwrap();
    let host = run(input, &settings).expect("cloi localize on x86-64");
    assert_eq!(fw.scans, SCANS);
    assert_eq!(fw.poses.len(), host.gpe.len(), "{}", fw.log);
    for (i, (h, a)) in host.gpe.iter().zip(&fw.poses).enumerate() {
        assert_eq!(h.0, a.t_ns, "scan {i}: time");
        for (k, (hv, av)) in [h.1.x, h.1.y, h.1.theta].iter().zip(&a.pose).enumerate() {
            assert_eq!(
                hv.to_bits(),
                av.to_bits(),
                "localized scan {i}: pose component {k}: x86-64 {hv} vs Cortex-A9 {av}"
            );
        }
    }
    let loc = &host.report.extra["localization"];
    for key in ["keyframes", "matches", "misses", "fixes", "lost"] {
        assert_eq!(
            fw.counters[&format!("localize_{key}")],
            loc[key].as_u64().expect(key),
            "{key}: {loc}"
        );
    }
    let localized = fw.counters["localized_scans"];
    let fraction = localized as f64 / fw.poses.len() as f64;
    assert!(
        (fraction - loc["localized_fraction"].as_f64().unwrap()).abs() < 1e-12,
        "{loc}"
    );
    // The scans that made the map are found in it again.
    assert!(
        fraction > 0.9,
        "localized {localized} of {}",
        fw.poses.len()
    );
    let (l, m) = (fw.sections["push_scan"], mapping.sections["push_scan"]);
    println!(
        "push_scan localizing: median {} p99 {} max {}; mapping: median {} p99 {} max {}",
        l.median, l.p99, l.max, m.median, m.p99, m.max
    );
    for (name, median, p99, max) in LOCALIZE_BUDGETS {
        let p = fw.sections[name];
        println!(
            "localizing {name}: n {} min {} median {} p99 {} max {}",
            p.n, p.min, p.median, p.p99, p.max
        );
        assert!(p.n > 0, "{name}: no samples");
        assert!(p.median <= median, "{name}: median {} > {median}", p.median);
        assert!(p.p99 <= p99, "{name}: p99 {} > {p99}", p.p99);
        assert!(p.max <= max, "{name}: max {} > {max}", p.max);
    }
}

/// Instruction budgets of localizing the same 1,000 scans in their own map: (name, median,
/// p99, max), about 25 % above what was measured. `loop_search` is here the match of a
/// keyframe in the saved map (ICP against the occupied cells of the 16 nearest submaps):
/// 1,769,890 / 8,750,030 / 9,142,830 over 164 keyframes (the points are gathered and arranged
/// again only when the nearest submaps change: the dear keyframes); `push_scan` 789,230 /
/// 7,555,940 / 10,249,680, against mapping's 822,450 / 4,143,890 / 5,550,200 on these scans,
/// whose loop search finds nothing to search yet.
const LOCALIZE_BUDGETS: [(&str, u64, u64, u64); 3] = [
    ("push_scan", 990_000, 9_450_000, 12_800_000),
    ("frontend", 1_030_000, 5_280_000, 6_630_000),
    ("loop_search", 2_220_000, 10_950_000, 11_450_000),
];

/// FNV-1a (64 bits) of every node pose's bits and every stored submap's cells, as the
/// firmware's `load=` computes it.
fn map_checksum(map: &cloi_host::io::map_file::LoadedMap) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut eat = |bytes: &[u8]| {
        for &b in bytes {
            h = (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
        }
    };
    for n in &map.nodes {
        for v in [n.pose.x, n.pose.y, n.pose.theta] {
            eat(&v.to_bits().to_le_bytes());
        }
    }
    let per = map.summary.grid.cells();
    for (slot, m) in map.submaps.iter().enumerate() {
        if m.in_use {
            let cells: Vec<u8> = map.cells[slot * per..(slot + 1) * per]
                .iter()
                .map(|&c| c as u8)
                .collect();
            eat(&cells);
        }
    }
    h
}

/// Keyframes in the host's `graph.g2o`.
fn vertices_in(out: &std::path::Path) -> usize {
    std::fs::read_to_string(out.join("graph.g2o"))
        .expect("graph.g2o")
        .lines()
        .filter(|l| l.starts_with("VERTEX_SE2 "))
        .count()
}

/// Most instructions of one back-end step that advances the optimizer, on the whole log
/// (issue 14: bounded by work, not by iterations). The firmware records each scan's largest
/// optimizer step of the up to `backend.steps_per_frame` it runs: max 4,626,670 measured,
/// median 3,352,120, over 1,048 scans.
const OPTIMIZER_STEP_MAX: u64 = 5_000_000;
/// Most instructions of any back-end step on the whole log (each scan's largest: max 6,156,400
/// measured, median 3,159,800, 6,173 scans). Above the optimizer's: the far search's
/// refinement of a found match (windowed correlative match and ICP against the submap,
/// `mapper/far/accept.rs`) still runs whole, and a branch-and-bound turn of 1,100 evaluations
/// can reach 6.3 M (evaluations cost 1,300 to 5,700 instructions).
const BACKEND_STEP_MAX: u64 = 7_500_000;

/// The whole of intel.clf (13,631 scans, 2,720 frame nodes at the end; 2 to 4 minutes under
/// QEMU on the shared box): no back-end step exceeds its ceiling above. The first 1,000 scans
/// above never exercise this: their graph has 164 nodes and every solve ends within one
/// step's budget. Here the solves span many steps: the gate's odometry chain and support test,
/// the minimum-degree ordering of up to 2,720 nodes, the factorization, the substitutions and
/// the innovation tests each stop where the budget runs out, and the far search spreads its
/// branch and bound and its pyramid builds over the turns the optimizer leaves idle.
#[test]
fn intel_whole_log_backend_chunks_stay_bounded() {
    let Some(clf) = cloi_host::dataset::shared_file("carmen/intel.clf") else {
        return;
    };
    let dir = workspace_root().join("target").join("qemu-mapper-whole");
    std::fs::create_dir_all(&dir).unwrap();
    let dir = dir.canonicalize().unwrap();
    let log = dir.join("intel.cloilog");
    let report = cloi_host::io::cloilog::carmen_to_cloilog(&clf, &log, false, None, None).unwrap();
    assert!(report.scans > 13_000, "{} scans", report.scans);

    build_firmware().expect("firmware builds");
    let elf = firmware_elf("cloi-mapper");
    let fw = run_mapper(&elf, &log, &dir.join("poses.txt")).expect("mapper firmware run");
    std::fs::write(dir.join("firmware.log"), &fw.log).unwrap();
    assert!(fw.counters["keyframes"] > 2_000, "{}", fw.log);
    for (name, max) in [
        ("backend_optimizer", OPTIMIZER_STEP_MAX),
        ("backend_working", BACKEND_STEP_MAX),
    ] {
        let p = fw.sections[name];
        println!(
            "{name}: n {} min {} median {} p99 {} max {}",
            p.n, p.min, p.median, p.p99, p.max
        );
        assert!(p.n > 1_000, "{name}: {} scans", p.n);
        assert!(p.max <= max, "{name}: max {} > {max}", p.max);
    }
}
