//! Mapper mode: the real [`Mapper`] (`home` profile, sensor set L) on a recorded `.cloilog`
//! streamed from the host through semihosting.
//!
//! The events are fed exactly as `cloi map --deterministic` feeds them (`Driver::feed` and
//! `drive` in `linux-host/src/map/run.rs`), through the core's [`Feeder`]: odometry records
//! are pushed until the first scan that carries its own odometry pose, from then on the
//! scan's pose is pushed at the scan's stamp instead; gyro records are pushed as they come; a
//! scan that odometry does not cover yet waits in the feeder's queue ([`SCAN_SLOTS`]), and
//! every scan the feeder pushes to [`Mapper::push_scan`] (with `deadline_passed = false`) is
//! followed by one back-end step of [`BACKEND_ITERATIONS_PER_SCAN`] Gauss-Newton iterations.
//! At the end of the log the held scans are pushed, an optimization is requested and the
//! back-end runs until it is idle, as on the host.
//!
//! The resources ([`HomeResources`], about 10.9 MB) are one static; nothing is allocated.
//! The A9 global timer (under `-icount shift=0`) counts the instructions of every call. The
//! output file gets, through `SYS_WRITE`:
//!
//! ```text
//! # scan t_ns x y theta keyframe push_scan_instructions backend_instructions
//! scan 976052857387156000 0e0 0e0 -2.458e-3 1 184530 1200
//! # keyframe serial x y theta
//! keyframe 0 0e0 0e0 -2.458e-3
//! ```
//!
//! `scan` lines carry the real-time pose (GPE) of every accepted scan, `keyframe` lines the
//! final (optimized) pose of every keyframe left in the graph, all in Rust's shortest
//! round-trip form, so parsing gives back the exact `f64` bits. The console gets the
//! configuration (`config=` its `Debug` form, for the host to compare with its own) and the
//! instruction percentiles per section (nearest rank).

use core::fmt::Write as _;

use cloi_core::frontend::BeamGeometry;
use cloi_core::mapper::mapfile::{write_map, MapReader};
use cloi_core::mapper::sync::SYNC_SLOTS;
use cloi_core::mapper::{
    BackendStep, Feeder, Mapper, MapperConfig, Probe, Pushed, ScanInput, ScanSlots, Section,
};
use cloi_core::profile::HomeResources;
use cloi_core::sensor::log::{
    LogError, LogReader, LogRecord, ReadError, MAX_BEAMS, MIN_READER_BUFFER,
};
use cloi_core::Se2;
use semihosting::fs::File;
use semihosting::println;

use crate::semihost_io::{c_path, ChunkedFile, MapFile, OutBuffer, CHUNK};
use crate::statics::TakeOnce;
use crate::stats::{quantile, MAX_SCANS};
use crate::timer;

/// Back-end iterations after every scan (`cloi map --backend-iterations`, default 5).
pub const BACKEND_ITERATIONS_PER_SCAN: u32 = 5;

/// The `home` profile's configuration: the core's, which `cloi map --profile home` also uses
/// (a host test checks its preset maps to it). The QEMU test compares its `Debug` form with
/// the host's, so the two cannot drift apart unnoticed.
pub fn home_config() -> MapperConfig {
    MapperConfig::home()
}

/// Everything the per-event step keeps between records.
pub struct State {
    /// The mapper over the static resources.
    pub mapper: Mapper<'static>,
    /// Decoded ranges of the current scan.
    ranges: &'static mut [f32; MAX_BEAMS],
    /// How events reach the mapper: the same `Feeder` as `cloi map` (odometry on scans, stamps
    /// in file order, scans held until odometry covers them, shortest range).
    feeder: Feeder<'static>,
}

/// Scans one record can push: the one it brings or the oldest held one it evicts, then every
/// held one that the record's data releases.
pub const MAX_PUSHED: usize = SYNC_SLOTS + 1;

/// What one record did: the instructions of its sensor push and one [`ScanCost`] per scan the
/// feeder pushed to the mapper because of it (in push order).
#[derive(Clone, Copy, Debug, Default)]
pub struct EventCost {
    /// The record was a scan.
    pub scan: bool,
    /// Instructions of odometry and gyro pushes.
    pub sensors: u64,
    /// The scans pushed, `pushed[..count]`.
    pub pushed: [ScanCost; MAX_PUSHED],
    /// Scans pushed.
    pub count: usize,
}

impl EventCost {
    /// The scans pushed, in order.
    pub fn scans(&self) -> &[ScanCost] {
        self.pushed.get(..self.count).unwrap_or(&[])
    }

    fn add(&mut self, cost: ScanCost) {
        if let Some(slot) = self.pushed.get_mut(self.count) {
            *slot = cost;
            self.count += 1;
        }
    }
}

/// What one scan pushed to the mapper did, with the instructions of each call.
#[derive(Clone, Copy, Debug, Default)]
pub struct ScanCost {
    /// The scan was accepted: its real-time output.
    pub output: Option<cloi_core::mapper::FrameOutput>,
    /// The scan's own stamp (the mapper's may have been moved forward in file order).
    pub stamp: i64,
    /// Instructions of `push_scan` (front-end, GPE, keyframe, loop search).
    pub push_scan: u64,
    /// Instructions of the largest back-end step after the scan (the frame's share is up to
    /// `backend.steps_per_frame` steps, as `Mapper::step_backend_frame` runs them).
    pub backend: u64,
    /// Instructions of the largest of those steps that advanced the optimizer.
    pub backend_optimizer: u64,
    /// The first back-end step had nothing to do.
    pub backend_idle: bool,
    /// A back-end step advanced the optimizer (rather than the far loop search that takes
    /// the turns it leaves idle).
    pub backend_optimized: bool,
    /// Instructions of each part of `push_scan`, indexed by [`section_index`]: front-end,
    /// GPE, keyframe, loop search (zero for a part that did not run).
    pub sections: [u64; 4],
    /// The loop-closure search ran during the scan.
    pub loop_search: bool,
}

/// The slot of a measured [`Section`] in [`EventCost::sections`].
pub fn section_index(section: Section) -> Option<usize> {
    match section {
        Section::Frontend => Some(0),
        Section::Gpe => Some(1),
        Section::Keyframe => Some(2),
        Section::LoopSearch => Some(3),
        Section::Done => None,
    }
}

/// A [`Probe`] that charges the instructions between two sections to the first. The timer
/// reads at the boundaries (a few dozen instructions) are charged too.
#[derive(Default)]
struct SectionTimer {
    current: Option<usize>,
    since: u64,
    counts: [u64; 4],
    loop_search: bool,
}

impl Probe for SectionTimer {
    fn enter(&mut self, section: Section) {
        let now = timer::ticks();
        if let Some(slot) = self.current.and_then(|c| self.counts.get_mut(c)) {
            *slot += (now - self.since) * timer::INSTRUCTIONS_PER_TICK;
        }
        self.loop_search |= section == Section::LoopSearch;
        self.current = section_index(section);
        self.since = timer::ticks();
    }
}

fn measure<T>(f: impl FnOnce() -> T) -> (T, u64) {
    let start = timer::ticks();
    let value = core::hint::black_box(f());
    let end = timer::ticks();
    (value, (end - start) * timer::INSTRUCTIONS_PER_TICK)
}

/// The one per-record step of the firmware's main loop: the host driver's `feed`, then the
/// deterministic schedule's back-end step after every scan pushed.
pub fn process_event(state: &mut State, record: &LogRecord<'_>) -> EventCost {
    let mut cost = EventCost::default();
    let mut probe = SectionTimer::default();
    match record {
        LogRecord::Odometry(o) => {
            let (mapper, feeder) = (&mut state.mapper, &mut state.feeder);
            let (_, n) = measure(|| feeder.odometry(mapper, o.stamp.as_nanos(), o.pose));
            cost.sensors = n;
        }
        LogRecord::Gyro(g) => {
            let (mapper, feeder) = (&mut state.mapper, &mut state.feeder);
            let (_, n) = measure(|| feeder.gyro(mapper, g.stamp.as_nanos(), g.yaw_rate));
            cost.sensors = n;
        }
        LogRecord::Scan(s) => {
            cost.scan = true;
            // The decoder checked the beam count against MAX_BEAMS, so this cannot fail.
            let ranges = s.ranges_into(&mut state.ranges[..]).unwrap_or(&[]);
            let g = s.meta.geometry;
            let input = ScanInput {
                stamp: s.meta.stamp.as_nanos(),
                ranges,
                geometry: BeamGeometry {
                    angle_min: g.angle_min,
                    angle_increment: g.angle_increment,
                    range_min: g.range_min,
                    range_max: g.range_max,
                    time_increment: 0.0,
                },
                mounting: s.meta.laser_offset,
            };
            let (mapper, feeder) = (&mut state.mapper, &mut state.feeder);
            // The scan's own odometry pose (if any) is pushed inside, as on the host.
            let (pushed, n) =
                measure(|| feeder.scan_probed(mapper, &input, s.meta.odom, false, &mut probe));
            if let Some(p) = pushed {
                cost.add(after_push(&mut state.mapper, p, n, &probe));
            }
        }
        LogRecord::Unknown { .. } => {}
    }
    release(state, &mut cost, false);
    cost
}

/// At the end of the log: pushes the scans still held, as the host does.
pub fn finish_input(state: &mut State) -> EventCost {
    let mut cost = EventCost::default();
    release(state, &mut cost, true);
    cost
}

/// Pushes the held scans the feeder releases (all of them at the end of the log).
fn release(state: &mut State, cost: &mut EventCost, at_end: bool) {
    while cost.count < MAX_PUSHED {
        let mut probe = SectionTimer::default();
        let (mapper, feeder) = (&mut state.mapper, &mut state.feeder);
        let (pushed, n) = measure(|| {
            if at_end {
                feeder.finish_probed(mapper, false, &mut probe)
            } else {
                feeder.next_probed(mapper, false, &mut probe)
            }
        });
        let Some(p) = pushed else {
            break;
        };
        cost.add(after_push(&mut state.mapper, p, n, &probe));
    }
}

/// The cost of one pushed scan (`push_scan` instructions `n`), with the back-end step after
/// it.
fn after_push(mapper: &mut Mapper<'_>, p: Pushed, n: u64, probe: &SectionTimer) -> ScanCost {
    let mut cost = ScanCost {
        output: p.result.ok(),
        stamp: p.stamp,
        push_scan: n,
        sections: probe.counts,
        loop_search: probe.loop_search,
        ..ScanCost::default()
    };
    // The steps of `Mapper::step_backend_frame`, each measured on its own.
    for i in 0..mapper.config().backend.steps_per_frame.max(1) {
        let steps = mapper.stats().backend_steps;
        let (step, instructions) = measure(|| mapper.step_backend(BACKEND_ITERATIONS_PER_SCAN));
        cost.backend = cost.backend.max(instructions);
        if mapper.stats().backend_steps != steps {
            cost.backend_optimized = true;
            cost.backend_optimizer = cost.backend_optimizer.max(instructions);
        }
        if step == BackendStep::Idle {
            cost.backend_idle = i == 0;
            break;
        }
    }
    cost
}

static RESOURCES: TakeOnce<HomeResources> = TakeOnce::new(HomeResources::new());
/// The scans the feeder holds until odometry covers them (about 35 kB).
static SCAN_SLOTS: TakeOnce<ScanSlots> = TakeOnce::new(ScanSlots::new());
static RANGES: TakeOnce<[f32; MAX_BEAMS]> = TakeOnce::new([0.0; MAX_BEAMS]);
static READ_BUFFER: TakeOnce<[u8; MIN_READER_BUFFER + CHUNK]> =
    TakeOnce::new([0; MIN_READER_BUFFER + CHUNK]);
/// Per scan: instructions of `push_scan`, of the back-end step after it, and flags.
static SCAN_COUNTS: TakeOnce<[u32; MAX_SCANS]> = TakeOnce::new([0; MAX_SCANS]);
static BACKEND_COUNTS: TakeOnce<[u32; MAX_SCANS]> = TakeOnce::new([0; MAX_SCANS]);
static OPTIMIZER_COUNTS: TakeOnce<[u32; MAX_SCANS]> = TakeOnce::new([0; MAX_SCANS]);
static FLAGS: TakeOnce<[u8; MAX_SCANS]> = TakeOnce::new([0; MAX_SCANS]);
/// Per scan: instructions of each part of `push_scan` (see [`EventCost::sections`]).
static SECTION_COUNTS: TakeOnce<[[u32; 4]; MAX_SCANS]> = TakeOnce::new([[0; 4]; MAX_SCANS]);
static SCRATCH: TakeOnce<[u32; MAX_SCANS]> = TakeOnce::new([0; MAX_SCANS]);
static OUT: TakeOnce<OutBuffer> = TakeOnce::new(OutBuffer::new());

const FLAG_ACCEPTED: u8 = 1;
const FLAG_KEYFRAME: u8 = 2;
const FLAG_BACKEND_WORKED: u8 = 4;
const FLAG_LOOP_SEARCH: u8 = 8;
const FLAG_BACKEND_OPTIMIZED: u8 = 16;

/// Prints `stat=NAME n= min= median= p99= max= mean=` over the counts whose flags match.
fn print_stat(
    name: &str,
    counts: impl Iterator<Item = u32>,
    flags: &[u8],
    keep: impl Fn(u8) -> bool,
    scratch: &mut [u32],
) {
    let mut n = 0;
    for (c, &f) in counts.zip(flags) {
        if keep(f) {
            if let Some(slot) = scratch.get_mut(n) {
                *slot = c;
                n += 1;
            }
        }
    }
    let sorted = &mut scratch[..n];
    cloi_core::sort::sort(sorted);
    let total: u64 = sorted.iter().map(|&c| u64::from(c)).sum();
    println!(
        "stat={name} n={n} min={} median={} p99={} max={} mean={} total={total}",
        quantile(sorted, 0),
        quantile(sorted, 50),
        quantile(sorted, 99),
        quantile(sorted, 100),
        if n > 0 { total / n as u64 } else { 0 },
    );
}

/// A saved map to localize in instead of mapping (`cloi localize`), and the robot's pose in it
/// at the first scan (`None`: global localization).
#[derive(Clone, Copy, Debug)]
pub struct LocalizeIn<'a> {
    /// Path of the `.cloimap`.
    pub map: &'a str,
    /// The robot's pose in the map at the first scan, if known.
    pub initial: Option<Se2>,
}

/// Runs the mapper over `log_path` (or, with `localize`, localizes in a saved map), writing
/// poses to `out_path`. Returns an error message.
pub fn run(
    log_path: &str,
    out_path: &str,
    save_path: Option<&str>,
    localize: Option<LocalizeIn<'_>>,
) -> Result<(), &'static str> {
    let (Some(resources), Some(ranges), Some(read_buffer), Some(out)) = (
        RESOURCES.take(),
        RANGES.take(),
        READ_BUFFER.take(),
        OUT.take(),
    ) else {
        return Err("mapper started twice");
    };
    let (Some(scan_counts), Some(backend_counts), Some(flags), Some(scratch)) = (
        SCAN_COUNTS.take(),
        BACKEND_COUNTS.take(),
        FLAGS.take(),
        SCRATCH.take(),
    ) else {
        return Err("mapper started twice");
    };
    let Some(optimizer_counts) = OPTIMIZER_COUNTS.take() else {
        return Err("mapper started twice");
    };
    let (Some(section_counts), Some(held)) = (SECTION_COUNTS.take(), SCAN_SLOTS.take()) else {
        return Err("mapper started twice");
    };
    let config = home_config();
    // The name of the preset, not its `Debug`: the QEMU test compares that preset with
    // `cloi map --profile home` on the host, and `Debug` formatting nests `dyn Debug` calls,
    // which the static stack bound would have to refuse as recursion.
    println!("config=MapperConfig::home");
    println!("backend_iterations_per_scan={BACKEND_ITERATIONS_PER_SCAN}");
    let mut path = [0u8; 512];
    let mapper = match localize {
        None => {
            let (mapper, setup) = measure(move || resources.mapper(config));
            println!("setup_instructions={setup}");
            mapper.map_err(|_| "the home configuration does not fit the home resources")?
        }
        Some(l) => localizer(resources, config, l, &mut path)?,
    };
    let mut state = State {
        mapper,
        ranges,
        feeder: Feeder::new(true, config.min_range, held),
    };

    let log_c = c_path(log_path, &mut path).ok_or("log path too long")?;
    let file = File::open(log_c).map_err(|_| "cannot open the log (SYS_OPEN)")?;
    let log_bytes = file.metadata().map(|m| m.len()).unwrap_or(0);
    let out_c = c_path(out_path, &mut path).ok_or("output path too long")?;
    let mut out_file = File::create(out_c).map_err(|_| "cannot create the output (SYS_OPEN)")?;
    let mode = if localize.is_some() {
        "localize"
    } else {
        "mapper"
    };
    println!("mode={mode} profile=home log={log_path} log_bytes={log_bytes} chunk_bytes={CHUNK}");
    let _ = writeln!(
        out,
        "# scan t_ns x y theta keyframe push_scan_instructions backend_instructions"
    );

    let mut reader =
        LogReader::new(ChunkedFile(file), read_buffer).map_err(|_| "read buffer too small")?;
    let (mut scans, mut records, mut rejected, mut localized) = (0usize, 0u64, 0u64, 0u64);
    let (mut sensors_total, mut decode_total) = (0u64, 0u64);
    loop {
        let (next, n) = measure(|| reader.next_record());
        decode_total += n;
        let (cost, ended) = match next {
            Ok(Some(record)) => {
                records += 1;
                (process_event(&mut state, &record), false)
            }
            // The end of the log releases the scans still waiting for odometry.
            Ok(None) => (finish_input(&mut state), true),
            Err(e) => {
                match e {
                    ReadError::Log { error, offset } => println!(
                        "mapper_error=\"{}\" offset={offset}",
                        log_error_name(&error)
                    ),
                    ReadError::Source(_) => println!("mapper_error=\"SYS_READ failed\""),
                }
                return Err("the log is damaged or unreadable");
            }
        };
        sensors_total += cost.sensors;
        for cost in cost.scans() {
            if let (Some(s), Some(b), Some(o), Some(f), Some(parts)) = (
                scan_counts.get_mut(scans),
                backend_counts.get_mut(scans),
                optimizer_counts.get_mut(scans),
                flags.get_mut(scans),
                section_counts.get_mut(scans),
            ) {
                *o = u32::try_from(cost.backend_optimizer).unwrap_or(u32::MAX);
                *s = u32::try_from(cost.push_scan).unwrap_or(u32::MAX);
                for (p, &c) in parts.iter_mut().zip(&cost.sections) {
                    *p = u32::try_from(c).unwrap_or(u32::MAX);
                }
                *b = u32::try_from(cost.backend).unwrap_or(u32::MAX);
                *f = if cost.backend_idle {
                    0
                } else {
                    FLAG_BACKEND_WORKED
                };
                if cost.loop_search {
                    *f |= FLAG_LOOP_SEARCH;
                }
                if cost.backend_optimized {
                    *f |= FLAG_BACKEND_OPTIMIZED;
                }
                if let Some(o) = &cost.output {
                    *f |= FLAG_ACCEPTED | if o.keyframe { FLAG_KEYFRAME } else { 0 };
                }
            }
            scans += 1;
            let Some(o) = cost.output else {
                rejected += 1;
                continue;
            };
            localized += u64::from(o.localized);
            if out.len + 256 > out.bytes.len() {
                out.flush_to(&mut out_file)
                    .map_err(|_| "cannot write the output (SYS_WRITE)")?;
            }
            let _ = writeln!(
                out,
                "scan {} {:e} {:e} {:e} {} {} {}",
                cost.stamp,
                o.pose.x,
                o.pose.y,
                o.pose.theta,
                u8::from(o.keyframe),
                cost.push_scan,
                cost.backend
            );
        }
        if ended {
            break;
        }
    }

    // Settle the back-end as the host does: one final optimization over everything.
    let mapper = &mut state.mapper;
    let ((), settle) = measure(|| {
        mapper.request_optimization();
        while mapper.step_backend(BACKEND_ITERATIONS_PER_SCAN) == BackendStep::Working {}
    });
    let _ = writeln!(out, "# keyframe serial x y theta");
    let graph = mapper.graph();
    for (m, n) in mapper.nodes().iter().zip(graph.nodes()) {
        if out.len + 256 > out.bytes.len() {
            out.flush_to(&mut out_file)
                .map_err(|_| "cannot write the output (SYS_WRITE)")?;
        }
        let _ = writeln!(
            out,
            "keyframe {} {:e} {:e} {:e}",
            m.serial, n.pose.x, n.pose.y, n.pose.theta
        );
    }
    out.flush_to(&mut out_file)
        .map_err(|_| "cannot write the output (SYS_WRITE)")?;
    drop(out_file);
    if let Some(save) = save_path {
        let save_c = c_path(save, &mut path).ok_or("map path too long")?;
        let file = File::create(save_c).map_err(|_| "cannot create the map file (SYS_OPEN)")?;
        let (written, instructions) =
            measure(|| write_map(&mapper.saved_map(), &mut MapFile::new(file)));
        let bytes = written.map_err(|_| "cannot write the map file (SYS_WRITE)")?;
        println!("map_saved_bytes={bytes} map_save_instructions={instructions}");
    }

    let s = mapper.stats();
    println!(
        "mapper_records={records} mapper_scans={scans} mapper_rejected={rejected} \
         keyframes={} nodes={} edges={} submaps={} loop_closures={} optimizations={} \
         backend_steps={} gpe_solved={} gpe_predicted={} keyframes_dropped={} \
         submaps_recycled={} prunes={} nodes_pruned={} icp_failures={} loop_searches={}",
        s.keyframes,
        graph.node_count(),
        graph.edge_count(),
        s.submaps,
        s.loop_closures,
        s.optimizations,
        s.backend_steps,
        s.gpe_solved,
        s.gpe_predicted,
        s.keyframes_dropped,
        s.submaps_recycled,
        s.prunes,
        s.nodes_pruned,
        s.icp_failures,
        s.loop_searches
    );
    let kept = scans.min(MAX_SCANS);
    let (sc, bc, fl) = (
        &scan_counts[..kept],
        &backend_counts[..kept],
        &flags[..kept],
    );
    let sc = || sc.iter().copied();
    let accepted = |f: u8| f & FLAG_ACCEPTED != 0;
    print_stat("push_scan", sc(), fl, accepted, scratch);
    print_stat(
        "frontend_gpe",
        sc(),
        fl,
        |f| accepted(f) && f & FLAG_KEYFRAME == 0,
        scratch,
    );
    print_stat(
        "keyframe_scan",
        sc(),
        fl,
        |f| f & FLAG_KEYFRAME != 0,
        scratch,
    );
    // The parts of push_scan (SectionTimer): front-end and GPE on every accepted scan, the
    // keyframe part on every accepted scan (the selection test; a keyframe's updates on
    // keyframes), the loop search where it ran.
    let part = |i: usize| section_counts[..kept].iter().map(move |p| p[i]);
    print_stat("frontend", part(0), fl, accepted, scratch);
    print_stat("gpe", part(1), fl, accepted, scratch);
    print_stat(
        "keyframe_update",
        part(2),
        fl,
        |f| f & FLAG_KEYFRAME != 0,
        scratch,
    );
    print_stat(
        "loop_search",
        part(3),
        fl,
        |f| f & FLAG_LOOP_SEARCH != 0,
        scratch,
    );
    // Per scan, its largest back-end step (of up to `backend.steps_per_frame`).
    print_stat("backend_step", bc.iter().copied(), fl, |_| true, scratch);
    print_stat(
        "backend_working",
        bc.iter().copied(),
        fl,
        |f| f & FLAG_BACKEND_WORKED != 0,
        scratch,
    );
    // The optimizer's chunks alone (the far loop search takes the other working steps).
    print_stat(
        "backend_optimizer",
        optimizer_counts[..kept].iter().copied(),
        fl,
        |f| f & FLAG_BACKEND_OPTIMIZED != 0,
        scratch,
    );
    println!(
        "sensors_instructions_total={sensors_total} decode_instructions_total={decode_total} \
         settle_instructions={settle}"
    );
    if scans > MAX_SCANS {
        println!("scans_not_in_percentiles={}", scans - MAX_SCANS);
    }
    if let Some(c) = mapper.localize_counters() {
        println!(
            "localized_scans={localized} localize_keyframes={} localize_matches={} \
             localize_misses={} localize_fixes={} localize_lost={}",
            c.keyframes, c.matches, c.misses, c.fixes, c.lost
        );
    }
    Ok(())
}

/// A mapper localizing in the saved map `l.map`, read into `resources`' pools (no heap);
/// prints the instructions the read and the start took.
fn localizer(
    resources: &'static mut HomeResources,
    config: MapperConfig,
    l: LocalizeIn<'_>,
    path: &mut [u8; 512],
) -> Result<Mapper<'static>, &'static str> {
    let c = c_path(l.map, path).ok_or("map path too long")?;
    let file = File::open(c).map_err(|_| "cannot open the map file (SYS_OPEN)")?;
    let mut input = MapFile::new(file);
    let mut parts = resources.parts();
    let (read, instructions) = measure(|| {
        MapReader::open(&mut input).and_then(|r| r.read_into_parts(config.grid, &mut parts))
    });
    if let Err(e) = read {
        println!("map_error=\"{e}\"");
        return Err("the map file was refused");
    }
    println!("map_load_instructions={instructions}");
    parts
        .localize(config, l.initial)
        .map_err(|_| "the saved map does not fit the home configuration")
}

/// The variant of a log error, printed without its fields: `LogError`'s `Display` nests
/// formatting calls (`write!`), which the static stack bound would have to refuse as recursion.
fn log_error_name(e: &LogError) -> &'static str {
    match e {
        LogError::BadMagic => "bad magic",
        LogError::UnsupportedVersion { .. } => "unsupported version",
        LogError::BadHeaderLength { .. } => "bad header length",
        LogError::Truncated { .. } => "truncated",
        LogError::RecordTooLarge { .. } => "record too large",
        LogError::TooManyBeams { .. } => "too many beams",
        LogError::BadLength { .. } => "bad record length",
        LogError::BadChecksum { .. } => "bad checksum",
        LogError::CountMismatch { .. } => "record count mismatch",
        LogError::BufferTooSmall { .. } => "buffer too small",
    }
}

/// Reads the saved map at `map_path` into the `home` profile's static pools (no heap, as a
/// session that starts from a saved map would) and prints what it holds, the instructions the
/// read took and an FNV-1a checksum of every node pose's bits and every stored submap's cells
/// (the host computes the same over its own read of the file).
pub fn load(map_path: &str) -> Result<(), &'static str> {
    let Some(resources) = RESOURCES.take() else {
        return Err("resources taken twice");
    };
    let mut path = [0u8; 512];
    let c = c_path(map_path, &mut path).ok_or("map path too long")?;
    let file = File::open(c).map_err(|_| "cannot open the map file (SYS_OPEN)")?;
    let mut input = MapFile::new(file);
    let grid = MapperConfig::home().grid;
    let mut storage = resources.map_storage(grid);
    let (read, instructions) =
        measure(|| MapReader::open(&mut input).and_then(|r| r.read_into(&mut storage)));
    let summary = match read {
        Ok(s) => s,
        Err(e) => {
            println!("map_error=\"{e}\"");
            return Err("the map file was refused");
        }
    };
    let mut hash = Fnv::new();
    for n in storage.graph.nodes() {
        for v in [n.pose.x, n.pose.y, n.pose.theta] {
            hash.bytes(&v.to_bits().to_le_bytes());
        }
    }
    let per = grid.cells();
    for (slot, m) in storage.submaps.iter().enumerate() {
        if m.in_use {
            for &c in storage
                .cells
                .get(slot * per..(slot + 1) * per)
                .unwrap_or_default()
            {
                hash.bytes(&[c as u8]);
            }
        }
    }
    println!(
        "map_nodes={} map_edges={} map_submaps={} map_next_serial={} \
         map_load_instructions={instructions} map_checksum={:016x}",
        summary.nodes, summary.edges, summary.submaps, summary.next_serial, hash.0
    );
    Ok(())
}

/// FNV-1a, 64 bits.
struct Fnv(u64);

impl Fnv {
    fn new() -> Self {
        Fnv(0xcbf2_9ce4_8422_2325)
    }

    fn bytes(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
        }
    }
}
