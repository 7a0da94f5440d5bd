//! `cloi map`: drives the core [`Mapper`] over an input stream and writes the results.
//!
//! Two schedules:
//! * **deterministic** (`--deterministic`): one thread; after every scan the back-end gets a
//!   fixed budget of Gauss-Newton iterations (or, with `--backend-delay S`, runs only once per
//!   `S` seconds of data, to completion). The same input gives bit-identical outputs.
//! * **threaded** (default): the real-time part (front-end and GPE) on the calling thread and the
//!   back-end on a second thread at the lowest scheduling priority that takes one iteration at a time under the mapper's lock and
//!   yields between steps. A frame whose lock wait plus processing exceeds the GPE deadline is
//!   given the worst-case prediction on the next frame.
//!
//! Every accepted scan's final pose is its reference keyframe's optimized pose composed with the
//! front-end motion since that keyframe, so `trajectory.tum` has one pose per accepted scan with
//! the scan's own time stamp.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicI64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use cloi_core::frontend::visual::TrackStats;
use cloi_core::frontend::visual::VoStats;
use cloi_core::frontend::{BeamGeometry, GridParams};
use cloi_core::geom::Se2;
use cloi_core::graph::EdgeKind;
use cloi_core::mapper::sync::{SyncStats, SYNC_SLOTS, SYNC_WAIT_NS};
use cloi_core::mapper::{
    BackendStep, BackendWorker, Feeder, FrameOutput, LinkQueues, LocalizeCounters, Mapper,
    MapperError, MapperStats, ScanInput, ScanSlots, VisualCounters, LINK_CAPACITY,
};
use cloi_core::sensor::{ImageView, Timestamp};
use cloi_core::storage::NodeId;
use serde_json::json;

use super::config::{MapConfig, Profile};
use super::input::{ImageEvent, InputStats, InputStream, SensorEvent};
use super::output::{
    compose_global_grid, peak_heap_bytes, peak_rss_bytes, MapProgress, MapReport, SubmapView,
    TumWriter,
};
use super::resources::{HeapResources, VisualCalibration};
use super::spool::{Latency, ScanRecord, ScanSpool};
use crate::graph_io::{write_g2o, FileEdge, GraphFile};
use crate::io::map_out::{write_map_server, write_result_mcap, ResultMcap, TrajectoryPicture};

/// Settings of one `cloi map` run.
#[derive(Debug, Clone)]
pub struct MapSettings {
    /// Memory profile (fixes the resources and the submap grid).
    pub profile: Profile,
    /// The host configuration (preset plus overrides).
    pub config: MapConfig,
    /// Output directory.
    pub out: PathBuf,
    /// Interleave the back-end with fixed budgets on one thread.
    pub deterministic: bool,
    /// Run the back-end only once per this many seconds of data (0: after every scan).
    pub backend_delay_s: f64,
    /// Back-end iterations per scan in the deterministic schedule.
    pub backend_iterations_per_scan: u32,
    /// Stop after this many scans.
    pub max_scans: Option<u64>,
    /// What to do with time stamps that step back.
    pub stamps: StampPolicy,
    /// Show a progress bar (when stderr is a terminal).
    pub progress: bool,
    /// Also return every real-time pose in [`MapRun::gpe`], bit-exact (for comparisons with
    /// another build; held in memory, so it grows with the run).
    pub keep_gpe: bool,
    /// Save the final map (`.cloimap`) here.
    pub save_map: Option<PathBuf>,
    /// Start in a saved map: localize in it (`cloi localize`) or extend it (`cloi map
    /// --load`).
    pub localize: Option<LocalizeIn>,
    /// Sensor set C: camera 0's calibration; its visual keyframes are the frame nodes and the
    /// input's scans are left out.
    pub visual: Option<VisualCalibration>,
}

/// The saved map a run starts in.
#[derive(Debug, Clone)]
pub struct LocalizeIn {
    /// The saved map (`.cloimap`).
    pub map: PathBuf,
    /// The robot's pose in the map at the first scan, if known (else global localization).
    pub initial_pose: Option<Se2>,
    /// Map on from the first fix (a new session of the saved map), instead of only
    /// localizing.
    pub extend: bool,
}

/// What `cloi map` does with a time stamp that is not after the previous one of its stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum StampPolicy {
    /// The input's order is the true order (a log file written as the data came, whose
    /// stamps jitter, like intel.clf's): the mapper gets the stamp moved to 1 µs after the
    /// previous one; the outputs keep the original stamp; the repairs are counted.
    FileOrder,
    /// The mapper rejects the event and counts it.
    Reject,
}

/// What a run produced, besides the files.
#[derive(Debug, Clone)]
pub struct MapRun {
    /// The report written to `report.json` (the trajectories are in `trajectory.tum` and
    /// `gpe.tum`, written as they are computed and never held whole).
    pub report: MapReport,
    /// With [`MapSettings::keep_gpe`]: the real-time pose of every accepted scan.
    pub gpe: Vec<(i64, Se2)>,
    /// The mapper's counters.
    pub stats: MapperStats,
    /// What the user should know about the run (scans mapped without odometry cover).
    pub warnings: Vec<String>,
}

/// State of the real-time loop shared by both schedules.
struct Driver<'s> {
    /// The accepted scans, on disk until the end of the run.
    records: ScanSpool,
    /// The first error of the spool (a full disk), reported when the run ends.
    spool_error: Option<anyhow::Error>,
    /// The previous accepted scan's real-time and front-end poses.
    previous: Option<(Se2, Se2)>,
    /// Largest step of the real-time pose beyond the front-end's step, metres.
    gpe_max_jump: f64,
    /// Wall time of the real-time part per scan (front-end, GPE, keyframe, loop search), µs.
    scan_us: Latency,
    /// Live scans not yet through the mapper: stamp and when the device's last byte arrived.
    arrivals: VecDeque<(i64, Instant)>,
    /// From a live scan's last byte to its pose, µs.
    live_us: Latency,
    first_stamp: Option<i64>,
    last_stamp: i64,
    rejected: u64,
    /// Images the camera stage could not take (no storage for the camera, unusable sizes).
    images_refused: u64,
    deadline: Duration,
    late: bool,
    /// How events reach the mapper (shared with the firmware).
    feeder: Feeder<'s>,
    /// Accepted scans whose pose was tied to the map (all when mapping).
    localized: u64,
    /// Sensor set C: images are the frames, scans are left out (and counted).
    camera_frames: bool,
    scans_left_out: u64,
    /// Sensor set C: the fused wheel+gyro pose of every posed image, for `odometry.tum`: on
    /// disk like the frames, each in a record's `frontend` (the other fields unused).
    wheel: Option<ScanSpool>,
}

/// What the input still owes the mapper: one event, or the scans held at its end.
enum Feed<'e> {
    Event(&'e SensorEvent),
    End,
}

impl Driver<'_> {
    /// Feeds one event (or the end of the input) and calls `after_scan` with the data stamp
    /// of every scan it pushed to the mapper (none, one, or several held ones).
    fn feed(
        &mut self,
        mapper: &mut Mapper<'_>,
        feed: Feed<'_>,
        started: Instant,
        after_scan: &mut dyn FnMut(&mut Mapper<'_>, i64),
    ) {
        let mut pushed = None;
        match feed {
            Feed::Event(SensorEvent::Odometry { t_ns, pose }) => {
                let _ = self.feeder.odometry(mapper, *t_ns, *pose);
            }
            Feed::Event(SensorEvent::Gyro { t_ns, yaw_rate }) => {
                let _ = self.feeder.gyro(mapper, *t_ns, *yaw_rate);
            }
            Feed::Event(SensorEvent::Scan(_)) if self.camera_frames => {
                self.scans_left_out += 1;
            }
            Feed::Event(SensorEvent::Scan(s)) => {
                let input = ScanInput {
                    stamp: s.t_ns,
                    ranges: &s.ranges,
                    geometry: BeamGeometry {
                        angle_min: s.angle_min,
                        angle_increment: s.angle_increment,
                        range_min: s.range_min,
                        range_max: s.range_max,
                        time_increment: s.time_increment,
                    },
                    mounting: s.laser_offset,
                };
                if let Some(r) = s.received {
                    self.arrivals.push_back((s.t_ns, r));
                }
                let t0 = Instant::now();
                pushed = self
                    .feeder
                    .scan(mapper, &input, s.odom, self.late)
                    .map(|p| (p, t0));
            }
            Feed::Event(SensorEvent::Image(i)) => {
                let t0 = Instant::now();
                if let Some(out) = self.image(mapper, i) {
                    // A posed image is a frame, as a scan is for a LiDAR.
                    self.scan_us.add(t0.elapsed().as_secs_f64() * 1e6);
                    self.accept(mapper, &out, i.t_ns);
                    self.wheel_pose(mapper, i.t_ns);
                    self.late = started.elapsed() > self.deadline;
                    after_scan(mapper, i.t_ns);
                }
            }
            Feed::End => {}
        }
        let at_end = matches!(feed, Feed::End);
        loop {
            let (p, t0) = match pushed.take() {
                Some(p) => p,
                None => {
                    let t0 = Instant::now();
                    let next = if at_end {
                        self.feeder.finish(mapper, self.late)
                    } else {
                        self.feeder.next(mapper, self.late)
                    };
                    match next {
                        Some(p) => (p, t0),
                        None => break,
                    }
                }
            };
            self.scan_us.add(t0.elapsed().as_secs_f64() * 1e6);
            self.arrived(p.stamp);
            match p.result {
                Ok(out) => self.accept(mapper, &out, p.stamp),
                Err(_) => self.rejected += 1,
            }
            self.late = started.elapsed() > self.deadline;
            after_scan(mapper, p.stamp);
        }
    }

    /// A live scan stamped `stamp` has its pose: its latency since its last byte arrived
    /// (scans dropped on the way are forgotten).
    fn arrived(&mut self, stamp: i64) {
        while let Some(&(t, received)) = self.arrivals.front() {
            if t > stamp {
                break;
            }
            self.arrivals.pop_front();
            if t == stamp {
                self.live_us.add(received.elapsed().as_secs_f64() * 1e6);
            }
        }
    }

    /// Hands one image to the camera stage; refusals are counted there or, for an image the
    /// mapper has no storage for, here. The image's pose when the camera maps.
    fn image(&mut self, mapper: &mut Mapper<'_>, i: &ImageEvent) -> Option<FrameOutput> {
        let view = ImageView::new_checked(
            Timestamp::from_nanos(i.t_ns),
            i.width,
            i.height,
            i.stride,
            i.format,
            &i.data,
        );
        let Ok(view) = view else {
            self.images_refused += 1;
            return None;
        };
        match self
            .feeder
            .image(mapper, i.camera, i.t_ns, &view, self.late)
        {
            Ok(out) => out.frame,
            Err(MapperError::NoCamera) => {
                self.images_refused += 1;
                None
            }
            Err(_) => None,
        }
    }

    /// Records the fused wheel+gyro pose of the image stamped `stamp` (sensor set C).
    fn wheel_pose(&mut self, mapper: &Mapper<'_>, stamp: i64) {
        let (Some(spool), Some(pose)) = (&mut self.wheel, mapper.wheel_pose_at(stamp)) else {
            return;
        };
        let record = ScanRecord {
            stamp,
            reference: 0,
            reference_frontend: Se2::IDENTITY,
            rel: Se2::IDENTITY,
            gpe: pose,
            frontend: pose,
        };
        if let Err(e) = spool.push(&record) {
            self.spool_error.get_or_insert(e);
        }
    }

    /// Records an accepted scan under its original stamp `stamp`.
    fn accept(&mut self, mapper: &Mapper<'_>, out: &FrameOutput, stamp: i64) {
        let reference = mapper
            .keyframe_frontend(out.reference_serial)
            .unwrap_or(Se2::IDENTITY);
        self.first_stamp.get_or_insert(stamp);
        self.last_stamp = self.last_stamp.max(stamp);
        if let Some((gpe, frontend)) = self.previous {
            let g = gpe.between(&out.pose);
            let o = frontend.between(&out.frontend);
            self.gpe_max_jump = self.gpe_max_jump.max((g.x - o.x).hypot(g.y - o.y));
        }
        self.previous = Some((out.pose, out.frontend));
        self.localized += u64::from(out.localized);
        let record = ScanRecord {
            stamp,
            reference: out.reference_serial,
            reference_frontend: reference,
            rel: reference.between(&out.frontend),
            gpe: out.pose,
            frontend: out.frontend,
        };
        if let Err(e) = self.records.push(&record) {
            self.spool_error.get_or_insert(e);
        }
    }
}

/// Runs the mapper over `input` and writes every output into `settings.out`.
///
/// # Errors
/// Unreadable input, an unusable configuration, or an output that cannot be written.
pub fn run(input: InputStream, settings: &MapSettings) -> Result<MapRun> {
    settings.config.validate()?;
    std::fs::create_dir_all(&settings.out)
        .with_context(|| format!("creating {}", settings.out.display()))?;
    let cfg = settings.config.to_core(&settings.profile.core_config());
    let progress = MapProgress::with_visibility(input.size(), settings.progress);
    let stats_handle = input.stats_handle();
    let wall = Instant::now();
    let mut res = HeapResources::new(settings.profile.spec());
    if let Some(calibration) = settings.visual {
        if settings.localize.is_some() {
            bail!("--sensors C maps a new map only (no --load or cloi localize yet)");
        }
        res.enable_visual(calibration);
    }
    // The queues between the two threads of the threaded schedule (about 100 kB).
    let mut queues = Box::new(LinkQueues::new());
    let mapper = match &settings.localize {
        None => res.mapper(cfg),
        Some(target) => {
            let mut parts = res.parts();
            crate::io::map_file::read_map_into(&target.map, cfg.grid, &mut parts)?;
            if target.extend {
                parts.extend(cfg, target.initial_pose)
            } else {
                parts.localize(cfg, target.initial_pose)
            }
        }
    }
    .map_err(|e| anyhow!("profile {:?}: {e}", settings.profile))?;
    let run = drive(mapper, &mut queues, input, settings, &progress)?;
    // The outputs are composed from the copies `drive` made: the profile's resources, the
    // largest part of the process, go before the global grid and the picture are built.
    drop(res);
    progress.finish();
    let wall_seconds = wall.elapsed().as_secs_f64();
    let input_stats = stats_handle.lock().map(|s| s.clone()).unwrap_or_default();
    finish(run, settings, wall_seconds, &input_stats)
}

/// What the mapper thread hands back.
struct Finished {
    stamps_repaired: u64,
    sync: SyncStats,
    scan_us: Latency,
    live_us: Latency,
    records: ScanSpool,
    gpe_max_jump: f64,
    /// Largest heap in use while mapping (before the outputs were composed), when measured.
    mapping_peak_heap_bytes: Option<u64>,
    /// `(serial, global pose, front-end pose)` of every keyframe in the final graph.
    keyframe_poses: Vec<(u32, Se2, Se2)>,
    stats: MapperStats,
    nodes: usize,
    edges: usize,
    g2o: String,
    /// Loop edges in the final graph.
    loop_edges: usize,
    /// Those switched off by the max-mixture at the final poses, as `(from, to)` vertex ids.
    switched_off: Vec<(i64, i64)>,
    submaps: Vec<(Se2, Vec<i8>)>,
    grid: GridParams,
    rejected: u64,
    /// Counters of each camera track.
    cameras: Vec<TrackStats>,
    images_refused: u64,
    first_stamp: Option<i64>,
    last_stamp: i64,
    /// Localization-only mode, or the start of a session extending a saved map: its counters
    /// and the scans localized.
    localization: Option<(LocalizeCounters, u64)>,
    /// A session extending a saved map: serial of its first frame node once it joined.
    session_first: Option<u32>,
    /// Sensor set C: the wheel+gyro pose per image, the scans left out, and the visual
    /// front-end's counters.
    camera_run: Option<CameraRun>,
}

/// What a sensor set C run adds to the outputs.
struct CameraRun {
    wheel: Option<ScanSpool>,
    scans_left_out: u64,
    counters: VisualCounters,
    odometry: VoStats,
}

fn drive<'r>(
    mut mapper: Mapper<'r>,
    queues: &'r mut LinkQueues,
    input: InputStream,
    settings: &MapSettings,
    progress: &MapProgress,
) -> Result<Finished> {
    // The scans waiting for odometry (about 35 kB: on the heap, not the stack).
    let mut held = Box::new(ScanSlots::new());
    let mut driver = Driver {
        records: ScanSpool::new()?,
        spool_error: None,
        previous: None,
        gpe_max_jump: 0.0,
        scan_us: Latency::new(),
        arrivals: VecDeque::new(),
        live_us: Latency::new(),
        first_stamp: None,
        last_stamp: 0,
        rejected: 0,
        images_refused: 0,
        deadline: Duration::from_micros(settings.config.gpe.deadline_us),
        late: false,
        feeder: Feeder::new(
            settings.stamps == StampPolicy::FileOrder,
            mapper.config().min_range,
            &mut held,
        ),
        localized: 0,
        camera_frames: settings.visual.is_some(),
        scans_left_out: 0,
        wheel: match settings.visual {
            Some(_) => Some(ScanSpool::new()?),
            None => None,
        },
    };
    let stats_handle = input.stats_handle();
    let max_scans = settings.max_scans.unwrap_or(u64::MAX);
    let mut scans = 0u64;
    let delay_ns = (settings.backend_delay_s * 1e9) as i64;
    if settings.deterministic {
        let mut next_backend = i64::MIN;
        // The back-end's turn after every scan the mapper took (by the scan's data time).
        let iterations = settings.backend_iterations_per_scan;
        let mut step_backend = |m: &mut Mapper<'_>, t_ns: i64| {
            if delay_ns <= 0 {
                m.step_backend_frame(iterations);
            } else if t_ns >= next_backend {
                next_backend = t_ns + delay_ns;
                while m.step_backend(iterations) == BackendStep::Working {}
            }
        };
        for ev in input {
            let ev = ev?;
            let is_scan = matches!(ev, SensorEvent::Scan(_));
            if is_scan && scans >= max_scans {
                break;
            }
            // No deadline in the deterministic schedule: timing must not change results.
            driver.feed(
                &mut mapper,
                Feed::Event(&ev),
                Instant::now(),
                &mut step_backend,
            );
            driver.late = false;
            if is_scan {
                scans += 1;
                if scans.is_multiple_of(200) {
                    if let Ok(s) = stats_handle.lock() {
                        progress.update(&s, "");
                    }
                }
            }
        }
        driver.feed(&mut mapper, Feed::End, Instant::now(), &mut step_backend);
    } else {
        // The real-time part feeds on this thread; once the mapper has a back-end to run (at
        // once for a new map, after the join for a session extending a saved one) it moves
        // into a worker on a second thread, the two joined by the core's queues.
        let done = AtomicBool::new(false);
        let data_time = AtomicI64::new(i64::MIN);
        let fault = injected_fault();
        let iterations = settings.backend_iterations_per_scan.max(1);
        let mut queues = Some(queues);
        std::thread::scope(|s| -> Result<()> {
            let mut backend = None;
            // However the feeding below ends, a panic included, the back-end thread must
            // stop too: the scope waits for it before the panic can reach the user.
            let _stop_backend = StopOnDrop(&done);
            let mut result = Ok(());
            for ev in input {
                let ev = match ev {
                    Ok(ev) => ev,
                    Err(e) => {
                        result = Err(e);
                        break;
                    }
                };
                let is_scan = matches!(ev, SensorEvent::Scan(_));
                if is_scan && scans >= max_scans {
                    break;
                }
                if is_scan && scans == 10 && fault == Some(InjectedFault::Frontend) {
                    panic!("injected front-end failure ({FAULT_ENV})");
                }
                if backend.is_none() && !mapper.localizing() {
                    if let Some(q) = queues.take() {
                        let worker = mapper.detach_backend(q)?;
                        let (done, data_time) = (&done, &data_time);
                        backend = Some(s.spawn(move || {
                            run_worker(worker, done, data_time, delay_ns, iterations, fault)
                        }));
                    }
                }
                // A replayed scan waits for the back-end; one that arrived from a device
                // does not (live, the back-end keeps up or the GPE carries the pose), nor
                // one whose back-end is held back on purpose (`--backend-delay`).
                let pace =
                    delay_ns <= 0 && matches!(&ev, SensorEvent::Scan(s) if s.received.is_none());
                if let Err(e) = wait_for_backend(&mut mapper, backend.as_ref(), pace) {
                    result = Err(e);
                    break;
                }
                let started = Instant::now();
                let detached = backend.is_some();
                driver.feed(&mut mapper, Feed::Event(&ev), started, &mut |m, t_ns| {
                    data_time.store(t_ns, Ordering::Release);
                    if detached {
                        m.step_far_search();
                    } else {
                        // Localizing in a frozen map: no optimizer work, only the searches.
                        m.step_backend_frame(iterations);
                    }
                });
                if is_scan {
                    scans += 1;
                    if scans.is_multiple_of(200) {
                        if let Ok(s) = stats_handle.lock() {
                            progress.update(&s, "");
                        }
                    }
                }
            }
            if result.is_ok() {
                driver.feed(&mut mapper, Feed::End, Instant::now(), &mut |_, _| {});
            }
            done.store(true, Ordering::Release);
            if let Some(handle) = backend {
                let worker = handle
                    .join()
                    .map_err(|_| anyhow!("the back-end thread panicked"))?;
                mapper.attach_backend(worker);
            }
            result
        })?;
    }
    // Settle the back-end: a final optimization over everything.
    mapper.request_optimization();
    while mapper.step_backend(settings.backend_iterations_per_scan.max(1)) == BackendStep::Working {
    }
    // The heap's high-water mark of mapping itself, before the outputs' copies below.
    let mapping_peak_heap_bytes = peak_heap_bytes();
    let g = mapper.graph();
    let file = GraphFile {
        ids: mapper.nodes().iter().map(|m| i64::from(m.serial)).collect(),
        poses: g.nodes().iter().map(|n| n.pose).collect(),
        fixed: vec![false; g.node_count()],
        has_vertices: true,
        edges: g
            .edges()
            .iter()
            .filter(|e| e.kind != EdgeKind::Prior)
            .map(|e| FileEdge {
                from: e.from.0 as usize,
                to: e.to.0 as usize,
                measurement: e.measurement,
                information: e.information,
            })
            .collect(),
        duplicate_pairs: 0,
    };
    let g2o = write_g2o(&file, &file.poses);
    // Loop edges the max-mixture has switched off at the final poses (as file vertex ids).
    let node_pose = |id: NodeId| g.node(id).map(|n| n.pose);
    let mut loop_edges = 0;
    let mut switched_off = Vec::new();
    for e in g.edges().iter().filter(|e| e.kind == EdgeKind::Loop) {
        loop_edges += 1;
        if let (Some(a), Some(b)) = (node_pose(e.from), node_pose(e.to)) {
            if !e.is_active_at(&a, &b) {
                switched_off.push((file.ids[e.from.0 as usize], file.ids[e.to.0 as usize]));
            }
        }
    }
    if let Some(e) = driver.spool_error.take() {
        return Err(e);
    }
    if let Some(path) = &settings.save_map {
        crate::io::map_file::save_map(&mapper.saved_map(), path)?;
    }
    Ok(Finished {
        keyframe_poses: mapper
            .nodes()
            .iter()
            .zip(g.nodes())
            .map(|(m, n)| (m.serial, n.pose, m.frontend))
            .collect(),
        stats: mapper.stats(),
        nodes: g.node_count(),
        edges: g.edge_count(),
        g2o,
        loop_edges,
        switched_off,
        submaps: mapper
            .submaps()
            .map(|(pose, cells)| (pose, cells.to_vec()))
            .collect(),
        grid: mapper.config().grid,
        records: driver.records,
        gpe_max_jump: driver.gpe_max_jump,
        mapping_peak_heap_bytes,
        scan_us: driver.scan_us,
        live_us: driver.live_us,
        stamps_repaired: driver.feeder.stamps_repaired,
        sync: driver.feeder.sync_stats(),
        rejected: driver.rejected,
        cameras: mapper.camera_stats().collect(),
        images_refused: driver.images_refused,
        first_stamp: driver.first_stamp,
        last_stamp: driver.last_stamp,
        localization: mapper.localize_counters().map(|c| (c, driver.localized)),
        session_first: mapper.session_first_serial(),
        camera_run: mapper
            .visual_counters()
            .zip(mapper.visual_odometry_stats())
            .map(|(counters, odometry)| CameraRun {
                wheel: driver.wheel.take(),
                scans_left_out: driver.scans_left_out,
                counters,
                odometry,
            }),
    })
}

/// Unknown submaps (all cells `unknown`) covering the keyframes' poses, one per half a
/// submap's side.
fn unknown_views<'a>(
    keyframes: &[(u32, Se2, Se2)],
    grid: GridParams,
    unknown: &'a [i8],
) -> Vec<SubmapView<'a>> {
    let step = 0.5 * f64::from(grid.side) * f64::from(grid.resolution);
    let mut cells = std::collections::BTreeSet::new();
    let mut views = Vec::new();
    for (_, pose, _) in keyframes {
        let cell = (
            (pose.x / step).floor() as i64,
            (pose.y / step).floor() as i64,
        );
        if pose.is_finite() && cells.insert(cell) {
            views.push(SubmapView {
                origin: Se2::new(cell.0 as f64 * step, cell.1 as f64 * step, 0.0),
                side: grid.side as usize,
                resolution: grid.resolution,
                cells: unknown,
            });
        }
    }
    views
}

fn finish(
    mut f: Finished,
    settings: &MapSettings,
    wall_seconds: f64,
    input_stats: &InputStats,
) -> Result<MapRun> {
    if f.records.is_empty() {
        let why = if input_stats.scans == 0 {
            format!(
                "the input has no laser scan ({} odometry, {} gyro samples, {} records skipped): \
                 for a bag, check --scan-topic (and that it holds sensor_msgs/msg/LaserScan); \
                 for a CARMEN log, check --laser; g2o and TUM files are not sensor logs",
                input_stats.odometry, input_stats.gyro, input_stats.skipped
            )
        } else {
            format!(
                "none of its {} scans was accepted ({} rejected; see the warnings above and \
                 the mapper's counters): are the ranges valid and do odometry stamps overlap \
                 the scans'?",
                input_stats.scans, f.rejected
            )
        };
        bail!("no map: {why}");
    }
    // A scan hangs off its reference keyframe; when pruning removed that keyframe, off the
    // nearest kept one, through the front-end motion between the two.
    let poses: std::collections::BTreeMap<u32, (Se2, Se2)> = f
        .keyframe_poses
        .iter()
        .map(|&(serial, global, frontend)| (serial, (global, frontend)))
        .collect();
    let place = |r: &ScanRecord| -> Option<Se2> {
        // Localizing, the map does not move: the real-time pose is the final one. So for the
        // scans of a session extending a map before it joined the map (no node of this
        // session to hang off yet).
        let joined = f.session_first.is_some_and(|first| r.reference >= first);
        if f.localization.is_some() && !joined {
            return Some(r.gpe);
        }
        if let Some((p, _)) = poses.get(&r.reference) {
            return Some(p.compose(&r.rel));
        }
        let before = poses.range(..r.reference).next_back();
        let after = poses.range(r.reference..).next();
        let (_, (g, fk)) = match (before, after) {
            (Some(b), Some(a)) => {
                if r.reference - b.0 <= a.0 - r.reference {
                    b
                } else {
                    a
                }
            }
            (Some(b), None) => b,
            (None, Some(a)) => a,
            (None, None) => return None,
        };
        Some(
            g.compose(&fk.between(&r.reference_frontend))
                .compose(&r.rel),
        )
    };
    // Every file goes into a staging folder first and the set replaces the previous run's
    // together, report.json last (see `OutputSet`). The scans are read back from the spool once
    // and each pose goes straight into the files, so no output grows the process with the
    // length of the run.
    let set = crate::io::atomic::OutputSet::begin(&settings.out)?;
    let out = set.folder();
    crate::io::atomic::write_file(&out.join("graph.g2o"), f.g2o.as_bytes())?;
    let views: Vec<SubmapView<'_>> = f
        .submaps
        .iter()
        .map(|(origin, cells)| SubmapView {
            origin: *origin,
            side: f.grid.side as usize,
            resolution: f.grid.resolution,
            cells,
        })
        .collect();
    // Without a LiDAR there is no occupancy to draw: unknown cells around the keyframes
    // frame the picture of the trajectory.
    let unknown = vec![0i8; f.grid.side as usize * f.grid.side as usize];
    let views = if views.is_empty() {
        unknown_views(&f.keyframe_poses, f.grid, &unknown)
    } else {
        views
    };
    let grid = compose_global_grid(&views)?;
    write_map_server(out, "map", &grid.as_grid_ref())?;
    let accepted = f.records.len();
    let mut trajectory = TumWriter::create(&out.join("trajectory.tum"))?;
    let mut gpe = TumWriter::create(&out.join("gpe.tum"))?;
    let mut picture = TrajectoryPicture::new(grid.as_grid_ref())?;
    let mut result: Option<ResultMcap> = None;
    let mut kept = Vec::new();
    for r in f.records.into_records()? {
        let r = r?;
        gpe.push(r.stamp, &r.gpe)?;
        if settings.keep_gpe {
            kept.push((r.stamp, r.gpe));
        }
        let Some(p) = place(&r) else {
            continue;
        };
        trajectory.push(r.stamp, &p)?;
        picture.push(p.x, p.y);
        let mcap = match &mut result {
            Some(m) => m,
            None => result.insert(ResultMcap::create(
                &out.join("result.mcap"),
                &grid.as_grid_ref(),
                r.stamp,
            )?),
        };
        mcap.pose(r.stamp, (p.x, p.y, p.theta))?;
    }
    trajectory.commit()?;
    gpe.commit()?;
    if let Some(spool) = f.camera_run.as_mut().and_then(|c| c.wheel.take()) {
        let mut wheel = TumWriter::create(&out.join("odometry.tum"))?;
        for r in spool.into_records()? {
            let r = r?;
            wheel.push(r.stamp, &r.frontend)?;
        }
        wheel.commit()?;
    }
    picture.write_png(&out.join("map.png"))?;
    match result {
        Some(m) => m.finish()?,
        None => write_result_mcap(&out.join("result.mcap"), &grid.as_grid_ref(), &[])?,
    }
    let jump = f.gpe_max_jump;

    let data_seconds = (f.last_stamp - f.first_stamp.unwrap_or(f.last_stamp)) as f64 * 1e-9;
    let s = f.stats;
    let mut report = MapReport {
        scans: accepted + f.rejected,
        scans_rejected: f.rejected,
        keyframes: s.keyframes as u64,
        nodes: f.nodes as u64,
        edges: f.edges as u64,
        loop_closures: s.loop_closures as u64,
        data_seconds,
        wall_seconds,
        peak_heap_bytes: peak_heap_bytes(),
        peak_rss_bytes: peak_rss_bytes(),
        gpe_max_jump_m: jump,
        gpe_rate_hz: accepted as f64 / wall_seconds.max(1e-9),
        extra: Default::default(),
    };
    report.add_input_stats(input_stats);
    report
        .extra
        .insert("profile".into(), serde_json::to_value(settings.profile)?);
    report
        .extra
        .insert("deterministic".into(), json!(settings.deterministic));
    report.extra.insert(
        "reproducibility".into(),
        json!(if settings.deterministic {
            "deterministic"
        } else {
            "threaded"
        }),
    );
    report
        .extra
        .insert("backend_delay_s".into(), json!(settings.backend_delay_s));
    report.extra.insert(
        "mapping_peak_heap_bytes".into(),
        json!(f.mapping_peak_heap_bytes),
    );
    report
        .extra
        .insert("speed_x_realtime".into(), json!(report.speed()));
    report.extra.insert("mapper".into(), stats_json(&s));
    report
        .extra
        .insert("stamps_repaired".into(), json!(f.stamps_repaired));
    let sync = f.sync;
    report.extra.insert(
        "sync".into(),
        json!({
            "held": sync.held,
            "waited": sync.waited,
            "evicted": sync.evicted,
            "too_long": sync.too_long,
            "wait_s": SYNC_WAIT_NS as f64 * 1e-9,
            "slots": SYNC_SLOTS,
            "note": "scans held until wheel odometry (and gyro) covered their time; waited: \
                     released after the wait without cover; evicted: released early because \
                     the queue was full; too_long: rejected, more beams than a slot",
        }),
    );
    report.extra.insert(
        "loop_edges".into(),
        json!({
            "in_graph": f.loop_edges,
            "active": f.loop_edges - f.switched_off.len(),
            "switched_off": f.switched_off.len(),
            "switched_off_edges": f.switched_off,
            "note": "loop edges of graph.g2o; switched off: the max-mixture's null hypothesis \
                     explains them better at the final poses, so they do not act on the map \
                     (vertex ids as in graph.g2o)",
        }),
    );
    if let Some((c, localized)) = f.localization {
        report.extra.insert(
            "localization".into(),
            localization_json(&c, localized, accepted, f.first_stamp),
        );
    }
    let mut warnings = Vec::new();
    if let Some(target) = settings.localize.as_ref().filter(|t| t.extend) {
        report.extra.insert(
            "session".into(),
            json!({
                "extends": target.map.display().to_string(),
                "joined": f.session_first.is_some(),
                "first_serial": f.session_first,
                "note": "a session extending a saved map: localized in it until the first fix, \
                         mapping from there; first_serial is the serial of its first keyframe",
            }),
        );
        if f.session_first.is_none() {
            warnings.push(format!(
                "the run never found itself in {}: nothing was added to the map (is it the same \
                 place? try --initial-pose)",
                target.map.display()
            ));
        }
    }
    if input_stats.images > 0 {
        report
            .extra
            .insert("cameras".into(), cameras_json(&f.cameras, f.images_refused));
    }
    if let Some(c) = &f.camera_run {
        let n = &c.counters;
        let o = &c.odometry;
        report.extra.insert(
            "visual".into(),
            json!({
                "frames": n.frames,
                "frames_without_odometry": n.no_odometry,
                "frames_refused_by_vo": n.refused,
                "keyframes": n.keyframes,
                "frame_nodes": n.nodes,
                "unsolved_keyframes": n.unsolved,
                "landmarks": o.landmarks,
                "outliers_dropped": o.outliers_dropped,
                "solve_failures": o.solve_failures,
                "scans_left_out": c.scans_left_out,
                "note": "sensor set C: camera 0's visual keyframes are the frame nodes; \
                         odometry.tum is the fused wheel+gyro pose of every posed image",
            }),
        );
        if c.scans_left_out > 0 {
            warnings.push(format!(
                "--sensors C: {} scans of the input were left out",
                c.scans_left_out
            ));
        }
    }
    warnings.extend(sync_warnings(&sync));
    warnings.extend(camera_warnings(&f.cameras, f.images_refused));
    let us = &f.scan_us;
    report.extra.insert(
        "realtime_us_per_scan".into(),
        json!({
            "median": us.quantile(0.5),
            "p99": us.quantile(0.99),
            "max": us.max(),
            "note": "wall time of push_scan (front-end, GPE, keyframe, loop search) on the host; \
                     median and p99 to 1 %",
        }),
    );
    let live = &f.live_us;
    if let Some(max) = live.max() {
        let ms = |us: Option<f64>| us.map(|u| u * 1e-3);
        report.extra.insert(
            "live_latency_ms".into(),
            json!({
                "median": ms(live.quantile(0.5)),
                "p99": ms(live.quantile(0.99)),
                "max": max * 1e-3,
                "note": "host wall time from the arrival of a live scan's last byte to its pose \
                         (the channel, waiting for odometry, the real-time part); median and \
                         p99 to 1 %",
            }),
        );
    }
    report.write(&out.join("report.json"))?;
    set.commit("report.json")?;
    Ok(MapRun {
        report,
        gpe: kept,
        stats: s,
        warnings,
    })
}

/// The localization-only mode's counters for `report.json`.
fn localization_json(
    c: &LocalizeCounters,
    localized: u64,
    accepted: u64,
    first_stamp: Option<i64>,
) -> serde_json::Value {
    let to_fix = c
        .first_fix_stamp
        .zip(first_stamp)
        .map(|(fix, first)| (fix - first) as f64 * 1e-9);
    json!({
        "localized_fraction": localized as f64 / accepted.max(1) as f64,
        "time_to_first_fix_s": to_fix,
        "fixes": c.fixes,
        "lost": c.lost,
        "keyframes": c.keyframes,
        "matches": c.matches,
        "misses": c.misses,
        "uninformative": c.uninformative,
        "global_searches": c.global_searches,
        "hypotheses": c.hypotheses,
        "refuted": c.refuted,
        "note": "localized: scans whose pose was tied to a confirmed match with the saved map; \
                 fixes: times tracking started (initial pose or a confirmed global match); \
                 time to first fix in data seconds from the first scan",
    })
}

/// The camera stage's counters for `report.json`.
fn cameras_json(cameras: &[TrackStats], refused: u64) -> serde_json::Value {
    let per_camera: Vec<_> = cameras
        .iter()
        .enumerate()
        .filter(|(_, c)| c.frames + c.out_of_order + c.unreadable > 0)
        .map(|(i, c)| {
            let mean = |sum: u64, n: u32| sum as f64 / f64::from(n.max(1));
            json!({
                "camera": i,
                "frames": c.frames,
                "out_of_order": c.out_of_order,
                "unreadable": c.unreadable,
                "low_feature_frames": c.low_features,
                "features_min": c.min_features,
                "features_mean": mean(c.features, c.frames),
                "tracked_mean": mean(c.tracked, c.frames.saturating_sub(1)),
            })
        })
        .collect();
    json!({
        "tracks": per_camera,
        "refused": refused,
        "note": "each image's FAST/BRIEF features matched to the same camera's previous image \
                 (section III-B.1's front-end); camera frames do not join the pose graph yet. \
                 low_feature_frames: fewer than 20 features; refused: images the mapper had no \
                 storage for (a third camera, a frame above 1280x1024) or unusable sizes",
    })
}

/// Warnings for camera images the mapper could not use.
fn camera_warnings(cameras: &[TrackStats], refused: u64) -> Vec<String> {
    let mut w = Vec::new();
    if refused > 0 {
        w.push(format!(
            "{refused} camera images refused (a third camera, a frame larger than the camera \
             storage, or unusable sizes); see report.json \"cameras\""
        ));
    }
    for (i, c) in cameras.iter().enumerate() {
        if c.out_of_order + c.unreadable > 0 {
            w.push(format!(
                "camera {i}: {} images out of order and {} unreadable were skipped",
                c.out_of_order, c.unreadable
            ));
        }
        if c.frames > 0 && u64::from(c.low_features) * 2 > u64::from(c.frames) {
            w.push(format!(
                "camera {i}: {} of {} images have fewer than 20 features (a plain ceiling, a \
                 dark scene or a dirty lens?)",
                c.low_features, c.frames
            ));
        }
    }
    w
}

/// Warnings for scans that reached the mapper without odometry around their time.
fn sync_warnings(s: &SyncStats) -> Vec<String> {
    let mut w = Vec::new();
    if s.waited > 0 {
        w.push(format!(
            "{} scans waited {:.1} s of data time without odometry covering them and were \
             mapped with the odometry there was (report.json: sync.waited)",
            s.waited,
            SYNC_WAIT_NS as f64 * 1e-9
        ));
    }
    if s.evicted > 0 {
        w.push(format!(
            "{} scans left the odometry wait early because {SYNC_SLOTS} scans were already \
             waiting (report.json: sync.evicted)",
            s.evicted
        ));
    }
    if s.too_long > 0 {
        w.push(format!(
            "{} scans were rejected: they had to wait for odometry but have more beams than a \
             waiting slot holds (report.json: sync.too_long)",
            s.too_long
        ));
    }
    w
}

fn stats_json(s: &MapperStats) -> serde_json::Value {
    json!({
        "scans": s.scans,
        "scans_out_of_order": s.scans_out_of_order,
        "scans_empty": s.scans_empty,
        "beams_invalid": s.beams_invalid,
        "icp_failures": s.icp_failures,
        "icp_degenerate": s.icp_degenerate,
        "odometry_gaps": s.odometry_gaps,
        "odometry_stalls": s.odometry_stalls,
        "scans_not_deskewed": s.scans_not_deskewed,
        "odometry_rejected": s.odometry_rejected,
        "keyframes": s.keyframes,
        "keyframes_dropped": s.keyframes_dropped,
        "link_overflows": s.link_overflows,
        "submaps": s.submaps,
        "submaps_recycled": s.submaps_recycled,
        "loop_searches": s.loop_searches,
        "loop_closures": s.loop_closures,
        "loops_no_match": s.loops_no_match,
        "loops_rejected": s.loops_rejected,
        "loops_unconfirmed": s.loops_unconfirmed,
        "far_searches": s.far_searches,
        "far_hypotheses": s.far_hypotheses,
        "far_confirmed": s.far_confirmed,
        "far_refuted": s.far_refuted,
        "gpe_solved": s.gpe_solved,
        "gpe_predicted": s.gpe_predicted,
        "optimizations": s.optimizations,
        "backend_steps": s.backend_steps,
        "optimization_failures": s.optimization_failures,
        "loop_groups_removed": s.loop_groups_removed,
        "loop_edges_removed": s.loop_edges_removed,
        "consistency_rounds": s.consistency_rounds,
        "loop_groups_tested": s.loop_groups_tested,
        "prunes": s.prunes,
        "nodes_pruned": s.nodes_pruned,
    })
}

/// Hidden test hook: `CLOI_MAP_INJECT_FAULT=frontend|backend` makes that thread of the
/// threaded schedule panic, so tests can check that a failure in either thread ends the
/// run with an error instead of a hang.
const FAULT_ENV: &str = "CLOI_MAP_INJECT_FAULT";

/// The thread a test asked to fail (see [`FAULT_ENV`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum InjectedFault {
    Frontend,
    Backend,
}

fn injected_fault() -> Option<InjectedFault> {
    match std::env::var(FAULT_ENV).ok()?.as_str() {
        "frontend" => Some(InjectedFault::Frontend),
        "backend" => Some(InjectedFault::Backend),
        _ => None,
    }
}

/// The back-end thread: steps the detached back-end until `done`, sleeping while it is idle.
/// With a delay it only takes the real-time part's messages, and once per `delay_ns` of data
/// time (as published in `data_time`) runs the due optimization to its end.
fn run_worker<'r>(
    mut worker: BackendWorker<'r>,
    done: &AtomicBool,
    data_time: &AtomicI64,
    delay_ns: i64,
    iterations: u32,
    fault: Option<InjectedFault>,
) -> BackendWorker<'r> {
    // Lowest priority for the back-end (nice 19 under Linux's normal policy): the real-time
    // part comes first whenever both want a core.
    let _ = thread_priority::set_current_thread_priority(thread_priority::ThreadPriority::Min);
    let mut next_run = i64::MIN;
    let mut steps = 0u32;
    while !done.load(Ordering::Acquire) {
        let now = data_time.load(Ordering::Acquire);
        let step = if delay_ns > 0 && now < next_run {
            worker.receive();
            BackendStep::Idle
        } else {
            worker.step(iterations)
        };
        steps += u32::from(step != BackendStep::Idle);
        if fault == Some(InjectedFault::Backend) && steps >= 10 {
            panic!("injected back-end failure ({FAULT_ENV})");
        }
        match step {
            BackendStep::Idle => std::thread::sleep(Duration::from_millis(1)),
            BackendStep::Finished if delay_ns > 0 => next_run = now.saturating_add(delay_ns),
            _ => std::thread::yield_now(),
        }
    }
    worker
}

/// Waits while the detached back-end has more than half a queue of messages to take, and,
/// with `pace`, while it optimizes and its last finished optimization lacks more than
/// [`PACE_KEYFRAMES`] of the keyframes sent: a log replays as fast as the back-end keeps up,
/// as it does on a robot whose data come in real time. The far loop search runs meanwhile.
/// An error when the back-end's thread has stopped.
fn wait_for_backend(
    mapper: &mut Mapper<'_>,
    backend: Option<&std::thread::ScopedJoinHandle<'_, BackendWorker<'_>>>,
    pace: bool,
) -> Result<()> {
    let Some(handle) = backend else {
        return Ok(());
    };
    loop {
        if handle.is_finished() {
            return Err(anyhow!("the back-end thread stopped during the run"));
        }
        let keeps_up = mapper
            .backend_lag()
            .is_none_or(|(lag, idle)| !pace || idle || lag <= PACE_KEYFRAMES);
        if keeps_up && mapper.backend_backlog() <= LINK_CAPACITY / 2 {
            return Ok(());
        }
        if !mapper.step_far_search() {
            std::thread::yield_now();
        }
    }
}

/// Keyframes a replay may run ahead of the back-end's last finished optimization.
const PACE_KEYFRAMES: u32 = 1;

/// Raises its flag when dropped, also while a panic unwinds.
struct StopOnDrop<'a>(&'a AtomicBool);

impl Drop for StopOnDrop<'_> {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Release);
    }
}

/// The directory name used when `--out` is not given.
pub fn default_out(input: Option<&Path>) -> PathBuf {
    match input.and_then(|p| p.file_stem()) {
        Some(stem) => PathBuf::from("out").join(stem),
        None => PathBuf::from("out").join("sim-home"),
    }
}
