//! fulcrumd's process: threads, start-up, shutdown, summary.
//!
//! Threads:
//! - `fulcrumd-rt`: the 1 kHz loop ([`RtLoop`]). Real-time set-up from `[realtime]`, then
//!   creates its iceoryx2 publisher, marks itself real-time for the pool allocator
//!   ([`hw_io::rt_alloc`]) and loops. Hands records and log events to lock-free queues.
//! - `recorder-writer`: drains the flight recorder's queue to disk (lower priority).
//! - `fulcrumd-watchdog`: systemd notifications (READY after the first valid cycle,
//!   WATCHDOG pings while the loop advances, STATUS once a second).
//! - `fulcrumd-sim`: the built-in simulated robot (only when no CAN interface is configured):
//!   answers the loop's SYNC on the in-process bus.
//! - the main thread: turns log events into `tracing` lines (journald-friendly), prints the
//!   simulated truth next to them, and waits for the stop signal.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use hw_io::can::{CanBus, InProcessBus, SocketCanBus};
use hw_io::ipc::{FulcrumPublisher, FulcrumSample, OutputState, PublisherOptions};
use serde::Serialize;
use tracing::{info, warn};

use crate::config::Config;
use crate::cycle::{Acquisition, AcquisitionError, AcquisitionStats, Estimation, EstimationError};
use crate::health_log::HealthLog;
use crate::process::{self, RtJoinError, RtSpawnError, RtThread};
use crate::recorder::{self, RecorderProducer, RecorderStatsSnapshot, RunInfo};
use crate::recording_dir;
use crate::rt_loop::{
    CycleRecord, CycleSink, LogEvent, LogQueue, LoopCounters, LoopError, LoopParams, LoopTiming, RECORD_KIND, RtLoop,
    TimingSummary,
};
use crate::sim_robot::{self, SimRobotThread, SimStartError};
use crate::watchdog::{LoopProgress, WatchdogHandle};

/// Receive queue asked for on a SocketCAN interface by default, bytes (the kernel doubles it:
/// about 4000 classic frames, half a second of a saturated 1 Mbit/s bus); the configuration's
/// `bus.receive_buffer_bytes` sets it.
pub const CAN_RECEIVE_BUFFER_BYTES: usize = crate::config::DEFAULT_RECEIVE_BUFFER_BYTES;

/// Capacity of the flight recorder queue, records (about 4 s at 1 kHz).
pub const RECORDER_QUEUE: usize = 4096;

/// How to run the daemon.
#[derive(Clone, Debug)]
pub struct RunOptions {
    /// Validated configuration.
    pub config: Config,
    /// The configuration as TOML (stored in recordings so `replay` rebuilds the detector).
    pub config_toml: String,
    /// Stop after this many cycles (None: until SIGINT/SIGTERM).
    pub max_cycles: Option<u64>,
    /// Seed of the built-in simulated robot's surgeon.
    pub sim_seed: u64,
}

pub use crate::process::AllocSummary;

/// What a run did; printed at exit and optionally written as JSON.
#[derive(Clone, Debug, Default, Serialize)]
pub struct RunSummary {
    /// The bus the loop ran on (`in-process simulated robot` or the interface name).
    pub bus: String,
    /// Identifier of this run (in every published sample and recording file).
    pub run_id: u64,
    /// Cycle period, microseconds.
    pub period_us: u32,
    /// Cycles run.
    pub cycles: u64,
    /// Cycles with a valid estimate.
    pub valid_cycles: u64,
    /// Samples published.
    pub published: u64,
    /// Publications that failed.
    pub publish_errors: u64,
    /// Periods skipped by overruns.
    pub overruns: u64,
    /// Log events dropped (log queue full).
    pub log_drops: u64,
    /// Records dropped at the recorder's queue (full).
    pub recorder_queue_drops: u64,
    /// The flight recorder's own counters (None when recording was off).
    pub recorder: Option<RecorderStatsSnapshot>,
    /// First file of the recording (None when recording was off).
    pub recording: Option<PathBuf>,
    /// Frames the bus backend dropped (receive queue full).
    pub bus_dropped_rx_frames: u64,
    /// Acquisition counters.
    pub acquisition: AcquisitionStats,
    /// Loop timing, microseconds.
    pub timing: TimingSummary,
    /// Allocations of the real-time thread.
    pub alloc: AllocSummary,
    /// Real-time set-up, step by step.
    pub realtime: Vec<String>,
    /// Simulated robot: SYNCs answered (0 on a real bus).
    pub sim_syncs_answered: u64,
    /// The loop's full timing histograms (nanoseconds, 1 µs buckets), for plots; not in the
    /// JSON summary.
    #[serde(skip)]
    pub timing_histograms: Option<LoopTiming>,
}

/// Why the daemon could not be configured ([`Configured::new`]): nothing was started.
#[derive(Debug, thiserror::Error)]
pub enum ConfigureError {
    /// The encoder or health configuration cannot build acquisition.
    #[error("configuration: {0}")]
    Acquisition(#[from] AcquisitionError),
    /// The encoder, kinematic or detector configuration cannot build estimation.
    #[error("configuration: {0}")]
    Estimation(#[from] EstimationError),
    /// No recording directory could be chosen (the packaged default is not writable and the
    /// user has no state directory).
    #[error(transparent)]
    RecordingDir(#[from] crate::recording_dir::RecordingDirError),
}

/// Why the daemon could not start ([`Configured::start`]). What had started is stopped
/// (the stop flag is set).
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// The flight recorder could not start.
    #[error("flight recorder: {0}")]
    Recorder(#[from] recorder::StartError),
    /// The CAN interface could not be opened.
    #[error("CAN interface {iface}: {source}")]
    Bus {
        /// Interface name.
        iface: String,
        /// Why.
        source: hw_io::can::OpenError,
    },
    /// The in-process bus of the built-in simulated robot has no free endpoint.
    #[error("simulated robot: {0}")]
    SimBus(#[from] hw_io::can::EndpointError),
    /// The built-in simulated robot could not start.
    #[error("simulated robot: {0}")]
    Sim(#[from] SimStartError),
    /// The real-time thread could not be set up (real-time set-up with `realtime.require =
    /// true`, the iceoryx2 publisher, the thread itself).
    #[error(transparent)]
    Rt(#[from] RtSpawnError<RtSetupError>),
}

/// Why the real-time thread's own set-up failed (inside [`Configured::start`]).
#[derive(Debug, thiserror::Error)]
pub enum RtSetupError {
    /// The iceoryx2 publisher could not be created.
    #[error("output service: {0}")]
    Publisher(#[from] hw_io::ipc::CreateError),
}

/// Why a run ended in error ([`Running::shutdown`]).
#[derive(Debug, thiserror::Error)]
pub enum ShutdownError {
    /// The real-time thread panicked or gave no result.
    #[error(transparent)]
    Rt(#[from] RtJoinError),
    /// The loop stopped on its own (the monotonic clock failed).
    #[error("thread: the loop stopped: {0}")]
    Loop(#[from] LoopError),
}

/// Why the daemon could not run ([`run`]): the error of the phase that failed.
#[derive(Debug, thiserror::Error)]
pub enum DaemonError {
    /// Configuring failed.
    #[error(transparent)]
    Configure(#[from] ConfigureError),
    /// Starting failed.
    #[error(transparent)]
    Start(#[from] StartError),
    /// The run ended in error.
    #[error(transparent)]
    Shutdown(#[from] ShutdownError),
}

struct DaemonSink {
    publisher: FulcrumPublisher,
    recorder: Option<RecorderProducer<CycleRecord>>,
    log: heapless::spsc::Producer<'static, LogEvent>,
}

impl CycleSink for DaemonSink {
    fn publish(&mut self, sample: &FulcrumSample) -> bool {
        self.publisher.publish(sample).is_ok()
    }
    fn record(&mut self, record: &CycleRecord) -> bool {
        match &mut self.recorder {
            Some(r) => r.push(*record),
            None => true,
        }
    }
    fn log(&mut self, event: LogEvent) -> bool {
        self.log.enqueue(event).is_ok()
    }
}

/// What the real-time thread returns (its allocations are counted by [`process::spawn_realtime`]).
struct RtResult {
    result: Result<(), LoopError>,
    cycles: u64,
    acquisition: AcquisitionStats,
    timing: TimingSummary,
    histograms: LoopTiming,
    bus_dropped: u64,
}

/// What the simulated truth says next to a detection (the built-in simulated robot only):
/// the true trocar and the fulcrum's error, or what is wrong with the detection.
pub fn truth_note(
    state: OutputState,
    fulcrum_base_m: [f64; 3],
    truth: Option<(sim::scenario::TruthState, Option<nalgebra::Vector3<f64>>)>,
) -> String {
    use sim::scenario::TruthState;
    let Some((truth_state, pivot)) = truth else { return String::new() };
    match (state, truth_state, pivot) {
        (OutputState::Inside, TruthState::Inside { index }, Some(p)) => {
            let err_mm = (nalgebra::Vector3::from(fulcrum_base_m) - p).norm() * 1e3;
            format!(" [truth: trocar {index}, fulcrum {err_mm:.1} mm from the true pivot]")
        }
        (OutputState::Inside, _, _) => " [truth: outside: a FALSE detection]".to_string(),
        (OutputState::Outside, TruthState::Inside { index }, _) => format!(" [truth: still inside trocar {index}]"),
        (OutputState::Outside, _, _) => " [truth: outside]".to_string(),
        (OutputState::Invalid, _, _) => String::new(),
    }
}

fn log_event(e: &LogEvent, period_s: f64, sim: Option<&SimRobotThread>, health: &mut HealthLog) {
    match *e {
        LogEvent::State { sequence, state, trocar_id, fulcrum_base_m: f } => {
            let t = sequence as f64 * period_s;
            let note = truth_note(state, f, sim.and_then(|s| s.truth_at(sequence)));
            if state == OutputState::Inside {
                info!(
                    "{t:9.3} s  DETECTED inside trocar #{trocar_id}, fulcrum ({:+.4}, {:+.4}, {:+.4}) m{note}",
                    f[0], f[1], f[2]
                );
            } else {
                info!("{t:9.3} s  DETECTED {state}{note}");
            }
        }
        LogEvent::Health { sequence, old: _, new } => {
            // Lasting conditions get their own lines, short flaps a count (health_log).
            for line in health.change(sequence as f64 * period_s, new) {
                info!("{line}");
            }
        }
        LogEvent::Overrun { sequence, skipped } => {
            tracing::debug!("cycle {sequence}: overrun, {skipped} period(s) skipped");
        }
        LogEvent::PublishFailed { sequence } => warn!("cycle {sequence}: publishing failed"),
    }
}

/// The periodic report (`period`: "last 10 s", or "since the last report" at shutdown):
/// incomplete cycles and overruns, frames the bus dropped, health flaps, each since the
/// counts in `reported` / `reported_drops` (updated).
fn report_counts(
    c: &LoopCounters,
    reported: &mut (u64, u64),
    reported_drops: &mut u64,
    health_log: &mut HealthLog,
    period: &str,
) {
    let now = (c.incomplete_cycles.load(Ordering::Relaxed), c.overruns.load(Ordering::Relaxed));
    if now != *reported {
        warn!(
            "{period}: {} incomplete cycles (a TPDO missed its deadline; data not used), {} overruns",
            now.0 - reported.0,
            now.1 - reported.1
        );
        *reported = now;
    }
    let drops = c.bus_dropped_rx_frames.load(Ordering::Relaxed);
    if drops != *reported_drops {
        warn!("{}", drops_line(period, drops - *reported_drops, drops));
        *reported_drops = drops;
    }
    if let Some(line) = health_log.flaps() {
        warn!("{period}: {line}");
    }
}

/// The warning about frames the bus dropped: `new` over `period` ("last 10 s", ...), `total`
/// since start-up (frames).
pub fn drops_line(period: &str, new: u64, total: u64) -> String {
    format!(
        "{period}: {new} CAN frames dropped by the kernel (receive queue full; {total} since start-up): \
         a lost EMCY or heartbeat goes unseen, a lost TPDO makes its cycle incomplete"
    )
}

/// Phase 1, configured: the pipeline built and the recording directory chosen from a validated
/// configuration; no thread, no bus, no file yet (ros2_control's "unconfigured → inactive",
/// copper's `new`).
pub struct Configured {
    opts: RunOptions,
    acquisition: Acquisition,
    estimation: Estimation,
    run_info: RunInfo,
    params: LoopParams,
    /// The recorder's configuration with the chosen directory; `None` when recording is off.
    recorder: Option<recorder::RecorderConfig>,
}

impl Configured {
    /// Builds acquisition and estimation from `opts.config` and chooses the recording
    /// directory (the packaged default, unwritable for an ordinary user, falls back to the
    /// user's state directory with a warning: [`recording_dir::choose`]).
    ///
    /// **Not for the real-time loop:** allocates, reads the environment.
    pub fn new(opts: RunOptions) -> Result<Self, ConfigureError> {
        let cfg = &opts.config;
        let acquisition = Acquisition::new(&cfg.bus.encoder, cfg.health)?.with_other_nodes(&cfg.bus.other_node_ids);
        let estimation = Estimation::new(&cfg.bus.encoder, &cfg.kinematics, &cfg.detector)?;
        let run_info = RunInfo::new(RECORD_KIND, opts.config_toml.clone());
        let params = LoopParams {
            period_ns: u64::from(cfg.cycle.period_us) * 1000,
            frame_deadline_ns: u64::from(cfg.cycle.frame_deadline_us) * 1000,
            run_id: run_info.run_id,
            max_cycles: opts.max_cycles,
            cut_by_bus_time: false,
        };
        let recorder = if cfg.recorder.enabled {
            let chosen = recording_dir::choose(
                &cfg.recorder.dir,
                std::path::Path::new(recording_dir::PACKAGED_DIR),
                std::env::var_os("XDG_STATE_HOME"),
                std::env::var_os("HOME"),
            )?;
            if let Some(w) = &chosen.warning {
                warn!("{w}");
            }
            Some(recorder::RecorderConfig { dir: chosen.dir, ..cfg.recorder.clone() })
        } else {
            None
        };
        Ok(Self { opts, acquisition, estimation, run_info, params, recorder })
    }

    /// Identifier of the run to be (in every published sample and recording file).
    pub fn run_id(&self) -> u64 {
        self.run_info.run_id
    }

    /// Starts the run: the flight recorder's writer thread, the systemd supervisor, the bus
    /// (the CAN interface, or the in-process bus and the simulated robot's thread), then the
    /// real-time thread, returning once its set-up is done ([`process::spawn_realtime`]). On an
    /// error `stop` is set, so that what had started stops.
    ///
    /// **Not for the real-time loop:** spawns threads, opens the bus and files.
    pub fn start(self, stop: &'static AtomicBool) -> Result<Running, StartError> {
        let result = self.start_inner(stop);
        if result.is_err() {
            stop.store(true, Ordering::Relaxed);
        }
        result
    }

    fn start_inner(self, stop: &'static AtomicBool) -> Result<Running, StartError> {
        let Self { opts, acquisition, estimation, run_info, mut params, recorder: rec_cfg } = self;
        let cfg = &opts.config;
        let run_id = run_info.run_id;
        let period_s = f64::from(cfg.cycle.period_us) * 1e-6;

        // Flight recorder.
        let (rec_producer, rec_handle) = match &rec_cfg {
            Some(rec_cfg) => {
                let (p, h) = recorder::start::<CycleRecord, RECORDER_QUEUE>(rec_cfg, run_info)?;
                info!("flight recorder: {}", h.first_file().display());
                (Some(p), Some(h))
            }
            None => {
                info!("flight recorder: off");
                (None, None)
            }
        };
        let recording = rec_handle.as_ref().map(|h| h.first_file().to_path_buf());

        // Log hand-off: one queue for the run, leaked (a few tens of KiB once per process run).
        let queue: &'static mut LogQueue = Box::leak(Box::new(LogQueue::new()));
        let (log_tx, log_rx) = queue.split();

        let counters = Arc::new(LoopCounters::default());
        let progress = LoopProgress::new();
        let watchdog = process::start_watchdog(progress.clone());

        // The bus, and the simulated robot when there is no interface.
        let mut sim: Option<SimRobotThread> = None;
        let (bus, bus_name): (Box<dyn CanBus + Send>, String) = if cfg.bus.iface.is_empty() {
            let bus = InProcessBus::new();
            let endpoint = bus.endpoint()?;
            let controller = bus.endpoint()?;
            let thread = sim_robot::spawn(endpoint, cfg, opts.sim_seed, stop, period_s)?;
            info!("simulated robot: {}", thread.priority_note);
            sim = Some(thread);
            (Box::new(controller), "in-process simulated robot".to_string())
        } else {
            let mut b = SocketCanBus::open(&cfg.bus.iface)
                .map_err(|source| StartError::Bus { iface: cfg.bus.iface.clone(), source })?;
            // The SYNC's own echo is the time reference of the collection window (docs/daemon.md).
            b.receive_own_frames(true).map_err(|e| StartError::Bus {
                iface: cfg.bus.iface.clone(),
                source: hw_io::can::OpenError::Io { interface: cfg.bus.iface.clone(), source: e },
            })?;
            params.cut_by_bus_time = true;
            // A receive queue for bursts: with the default (about 200 frames) a 2 kHz flood of
            // junk frames overflowed it during a 67 ms stall of the loop (docs/hil.md), and the
            // kernel drops what does not fit, EMCY frames included.
            match b.set_receive_buffer(cfg.bus.receive_buffer_bytes) {
                Ok(n) => info!("CAN receive queue: {n} bytes (kernel drops counted: SO_RXQ_OVFL)"),
                Err(e) => warn!("CAN receive queue: cannot enlarge it ({e}); frames may be dropped in bursts"),
            }
            (Box::new(b), cfg.bus.iface.clone())
        };
        info!(
            "fulcrumd: run {run_id:016x}, bus {bus_name}, {} Hz, detector {:?}, output service {:?}",
            1_000_000 / cfg.cycle.period_us,
            cfg.detector.mode,
            cfg.output.service
        );

        // The real-time thread: the publisher and the loop are built on it (set-up), then it loops.
        let service = cfg.output.service.clone();
        let publisher_options =
            PublisherOptions { subscriber_buffer: cfg.output.subscriber_buffer, ..PublisherOptions::default() };
        let rt_counters = counters.clone();
        let rt_progress = progress.clone();
        let setup = move || -> Result<_, RtSetupError> {
            let publisher = FulcrumPublisher::create(&service, &publisher_options)?;
            let sink = DaemonSink { publisher, recorder: rec_producer, log: log_tx };
            let lp = RtLoop::new(bus, acquisition, estimation, params, rt_counters, rt_progress);
            Ok((sink, lp))
        };
        let body = move |(sink, lp): &mut (DaemonSink, RtLoop<Box<dyn CanBus + Send>>)| {
            lp.run(sink, || stop.load(Ordering::Relaxed))
        };
        // After the counted real-time section: the summaries allocate.
        let finish = |(_sink, lp): (DaemonSink, RtLoop<Box<dyn CanBus + Send>>), result| RtResult {
            result,
            cycles: lp.cycles(),
            acquisition: *lp.acquisition_stats(),
            timing: lp.timing().summary(),
            histograms: lp.timing().clone(),
            bus_dropped: lp.bus_dropped_rx_frames(),
        };
        let rt = process::spawn_realtime("fulcrumd-rt", 8 << 20, cfg.realtime.clone(), setup, body, finish)?;
        // Refused steps were already warned about (with what would permit them) by rt.
        for line in rt.realtime_report().iter().filter(|l| !l.contains("refused")) {
            info!("real-time: {line}");
        }
        Ok(Running {
            period_us: cfg.cycle.period_us,
            period_s,
            run_id,
            bus_name,
            recording,
            rec_handle,
            watchdog,
            sim,
            rt,
            counters,
            progress,
            log_rx,
            stop,
            health_log: HealthLog::new(),
            reported: (0, 0),
            reported_drops: 0,
        })
    }
}

/// Phase 2, running: the real-time thread loops; the main thread supervises
/// ([`Running::supervise`]) and then shuts down ([`Running::shutdown`]) (ros2_control's
/// "active", copper's `start` … `stop`).
pub struct Running {
    period_us: u32,
    period_s: f64,
    run_id: u64,
    bus_name: String,
    recording: Option<PathBuf>,
    rec_handle: Option<recorder::RecorderHandle>,
    watchdog: Option<WatchdogHandle>,
    sim: Option<SimRobotThread>,
    rt: RtThread<RtResult>,
    counters: Arc<LoopCounters>,
    progress: LoopProgress,
    log_rx: heapless::spsc::Consumer<'static, LogEvent>,
    stop: &'static AtomicBool,
    health_log: HealthLog,
    /// Incomplete cycles and overruns as of the last 10 s report.
    reported: (u64, u64),
    /// Frames the bus dropped as of the last report.
    reported_drops: u64,
}

impl Running {
    /// The supervision on the calling (main) thread until the loop ends (the stop flag or
    /// `max_cycles`): every 10 ms the log events the loop handed over become `tracing` lines
    /// (with the simulated truth beside them); every 10 s a warning on the per-cycle
    /// conditions (incomplete cycles, overruns) if any occurred, one on the frames the bus
    /// dropped (receive queue full) if any were, and the health flaps.
    ///
    /// **Not for the real-time loop:** logs.
    pub fn supervise(&mut self) {
        let mut last_report = std::time::Instant::now();
        while !self.rt.is_finished() {
            std::thread::sleep(Duration::from_millis(10));
            if last_report.elapsed() >= Duration::from_secs(10) {
                last_report = std::time::Instant::now();
                report_counts(
                    &self.counters,
                    &mut self.reported,
                    &mut self.reported_drops,
                    &mut self.health_log,
                    "last 10 s",
                );
            }
            let now_s = self.progress.snapshot().cycles as f64 * self.period_s;
            for line in self.health_log.tick(now_s) {
                warn!("{line}");
            }
            self.drain_log();
            if let Some(s) = &self.sim {
                s.drain_truth(|line| info!("{line}"));
            }
        }
    }

    /// The log events the loop handed over, as `tracing` lines.
    fn drain_log(&mut self) {
        while let Some(e) = self.log_rx.dequeue() {
            log_event(&e, self.period_s, self.sim.as_ref(), &mut self.health_log);
        }
    }

    /// Stops the run and collects its summary: sets the stop flag, joins the real-time thread,
    /// logs what remains (the last drop count, log events, the simulated truth), joins the
    /// simulated robot, stops the systemd supervisor and the flight recorder (warning if they
    /// fail), and fails if the loop stopped on its own or its thread panicked.
    ///
    /// **Not for the real-time loop:** joins threads, flushes files.
    pub fn shutdown(mut self) -> Result<RunSummary, ShutdownError> {
        self.stop.store(true, Ordering::Relaxed);
        let realtime = self.rt.realtime_report().to_vec();
        let (rt, alloc) = self.rt.join()?;
        while let Some(e) = self.log_rx.dequeue() {
            log_event(&e, self.period_s, self.sim.as_ref(), &mut self.health_log);
        }
        // What happened since the last 10 s report (short health conditions, incomplete
        // cycles, dropped frames) is told too: a run that ends within 10 s of a burst would
        // otherwise never say so.
        report_counts(
            &self.counters,
            &mut self.reported,
            &mut self.reported_drops,
            &mut self.health_log,
            "since the last report",
        );
        let sim_syncs_answered = match self.sim {
            Some(s) => {
                s.drain_truth(|line| info!("{line}"));
                s.join()
            }
            None => 0,
        };
        process::stop_watchdog(self.watchdog);
        let recorder = match self.rec_handle {
            Some(h) => match h.shutdown() {
                Ok(s) => Some(s),
                Err(e) => {
                    warn!("flight recorder shutdown: {e}");
                    None
                }
            },
            None => None,
        };
        rt.result?;
        let p = &self.counters;
        Ok(RunSummary {
            bus: self.bus_name,
            run_id: self.run_id,
            period_us: self.period_us,
            cycles: rt.cycles,
            valid_cycles: p.valid_cycles.load(Ordering::Relaxed),
            published: p.published.load(Ordering::Relaxed),
            publish_errors: p.publish_errors.load(Ordering::Relaxed),
            overruns: p.overruns.load(Ordering::Relaxed),
            log_drops: p.log_drops.load(Ordering::Relaxed),
            recorder_queue_drops: p.recorder_drops.load(Ordering::Relaxed),
            recorder,
            recording: self.recording,
            bus_dropped_rx_frames: rt.bus_dropped,
            acquisition: rt.acquisition,
            timing: rt.timing,
            alloc,
            realtime,
            sim_syncs_answered,
            timing_histograms: Some(rt.histograms),
        })
    }
}

/// Runs the daemon until `stop` is set (or `max_cycles`): [`Configured::new`] →
/// [`Configured::start`] → [`Running::supervise`] → [`Running::shutdown`]. Returns the summary.
///
/// **Not for the real-time loop:** the whole process's lifetime.
pub fn run(opts: RunOptions, stop: &'static AtomicBool) -> Result<RunSummary, DaemonError> {
    let mut running = Configured::new(opts)?.start(stop)?;
    running.supervise();
    Ok(running.shutdown()?)
}
