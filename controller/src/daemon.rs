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
use crate::cycle::{Acquisition, AcquisitionStats, Estimation};
use crate::health_log::HealthLog;
use crate::recorder::{self, RecorderProducer, RecorderStatsSnapshot, RunInfo};
use crate::recording_dir;
use crate::rt::{self, RealtimeReport};
use crate::rt_loop::{
    CycleRecord, CycleSink, LogEvent, LogQueue, LoopCounters, LoopParams, LoopTiming, RECORD_KIND, RtLoop,
    TimingSummary,
};
use crate::sim_robot::{self, SimRobotThread};
use crate::watchdog::{self, LoopProgress, Watchdog};

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

/// Allocation figures of the real-time thread over its loop.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct AllocSummary {
    /// System-allocator calls made by the real-time thread during the loop (target: 0).
    pub rt_thread_system_allocs: u64,
    /// Small blocks the pool served (iceoryx2's per-sample block, freed in the same cycle).
    pub pool_allocs: u64,
    /// Pool exhaustion fallbacks to the system allocator.
    pub pool_fallbacks: u64,
    /// Most pool blocks in use at once.
    pub pool_high_water: usize,
}

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

/// Why the daemon could not run.
#[derive(Debug, thiserror::Error)]
pub enum DaemonError {
    /// The configuration cannot build the pipeline.
    #[error("configuration: {0}")]
    Config(String),
    /// The CAN interface could not be opened.
    #[error("CAN interface {iface}: {source}")]
    Bus {
        /// Interface name.
        iface: String,
        /// Why.
        source: hw_io::can::OpenError,
    },
    /// The iceoryx2 publisher could not be created.
    #[error("output service: {0}")]
    Publisher(#[from] hw_io::ipc::CreateError),
    /// The flight recorder could not start.
    #[error("flight recorder: {0}")]
    Recorder(#[from] recorder::StartError),
    /// No recording directory could be chosen (the packaged default is not writable and the
    /// user has no state directory).
    #[error(transparent)]
    RecordingDir(#[from] crate::recording_dir::RecordingDirError),
    /// Real-time set-up failed with `realtime.require = true`.
    #[error("real-time set-up: {0}")]
    Realtime(#[from] rt::RealtimeError),
    /// The built-in simulated robot could not start.
    #[error("simulated robot: {0}")]
    Sim(String),
    /// A thread could not be spawned or died.
    #[error("thread: {0}")]
    Thread(String),
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

/// What the real-time thread returns.
struct RtResult {
    error: Option<String>,
    cycles: u64,
    acquisition: AcquisitionStats,
    timing: TimingSummary,
    histograms: LoopTiming,
    alloc: AllocSummary,
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

/// The warning about frames the bus dropped: `new` over `period` ("last 10 s", ...), `total`
/// since start-up (frames).
pub fn drops_line(period: &str, new: u64, total: u64) -> String {
    format!(
        "{period}: {new} CAN frames dropped by the kernel (receive queue full; {total} since start-up): \
         a lost EMCY or heartbeat goes unseen, a lost TPDO makes its cycle incomplete"
    )
}

/// Runs the daemon until `stop` is set (or `max_cycles`). Returns the summary.
pub fn run(opts: RunOptions, stop: &'static AtomicBool) -> Result<RunSummary, DaemonError> {
    let cfg = &opts.config;
    let acquisition = Acquisition::new(&cfg.bus.encoder, cfg.health).map_err(|e| DaemonError::Config(e.to_string()))?;
    let estimation = Estimation::new(&cfg.bus.encoder, &cfg.kinematics, &cfg.detector)
        .map_err(|e| DaemonError::Config(e.to_string()))?;
    let run_info = RunInfo::new(RECORD_KIND, opts.config_toml.clone());
    let run_id = run_info.run_id;
    let mut params = LoopParams {
        period_ns: u64::from(cfg.cycle.period_us) * 1000,
        frame_deadline_ns: u64::from(cfg.cycle.frame_deadline_us) * 1000,
        run_id,
        max_cycles: opts.max_cycles,
        cut_by_bus_time: false,
    };
    let period_s = f64::from(cfg.cycle.period_us) * 1e-6;

    // Flight recorder.
    let (rec_producer, rec_handle) = if cfg.recorder.enabled {
        // The packaged default directory, unwritable for an ordinary user: the user's state
        // directory instead, with a warning (recording_dir).
        let chosen = recording_dir::choose(
            &cfg.recorder.dir,
            std::path::Path::new(recording_dir::PACKAGED_DIR),
            std::env::var_os("XDG_STATE_HOME"),
            std::env::var_os("HOME"),
        )?;
        if let Some(w) = &chosen.warning {
            warn!("{w}");
        }
        let rec_cfg = recorder::RecorderConfig { dir: chosen.dir, ..cfg.recorder.clone() };
        let (p, h) = recorder::start::<CycleRecord, RECORDER_QUEUE>(&rec_cfg, run_info)?;
        info!("flight recorder: {}", h.first_file().display());
        (Some(p), Some(h))
    } else {
        info!("flight recorder: off");
        (None, None)
    };
    let recording = rec_handle.as_ref().map(|h| h.first_file().to_path_buf());

    // Log hand-off: one queue for the run, leaked (a few tens of KiB once per process run).
    let queue: &'static mut LogQueue = Box::leak(Box::new(LogQueue::new()));
    let (log_tx, mut log_rx) = queue.split();

    let counters = Arc::new(LoopCounters::default());
    let progress = LoopProgress::new();
    let watchdog = match Watchdog::spawn(progress.clone(), watchdog::default_status) {
        Ok(w) => Some(w),
        Err(e) => {
            warn!("systemd watchdog supervisor: {e}; running without it");
            None
        }
    };

    // The bus, and the simulated robot when there is no interface.
    let mut sim: Option<SimRobotThread> = None;
    let (bus, bus_name): (Box<dyn CanBus + Send>, String) = if cfg.bus.iface.is_empty() {
        let bus = InProcessBus::new();
        let endpoint = bus.endpoint().map_err(|e| DaemonError::Sim(e.to_string()))?;
        let controller = bus.endpoint().map_err(|e| DaemonError::Sim(e.to_string()))?;
        let thread = sim_robot::spawn(endpoint, cfg, opts.sim_seed, stop, period_s)
            .map_err(|e| DaemonError::Sim(e.to_string()))?;
        info!("simulated robot: {}", thread.priority_note);
        sim = Some(thread);
        (Box::new(controller), "in-process simulated robot".to_string())
    } else {
        let mut b = SocketCanBus::open(&cfg.bus.iface)
            .map_err(|source| DaemonError::Bus { iface: cfg.bus.iface.clone(), source })?;
        // The SYNC's own echo is the time reference of the collection window (docs/daemon.md).
        b.receive_own_frames(true).map_err(|e| DaemonError::Bus {
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

    // The real-time thread.
    let (ready_tx, ready_rx) = std::sync::mpsc::channel::<Result<Vec<String>, DaemonError>>();
    let rt_cfg = cfg.realtime.clone();
    let service = cfg.output.service.clone();
    let publisher_options =
        PublisherOptions { subscriber_buffer: cfg.output.subscriber_buffer, ..PublisherOptions::default() };
    let rt_counters = counters.clone();
    let rt_progress = progress.clone();
    let handle = std::thread::Builder::new()
        .name("fulcrumd-rt".into())
        .stack_size(8 << 20)
        .spawn(move || -> Option<RtResult> {
            let report: RealtimeReport = match rt::apply_to_current_thread(&rt_cfg) {
                Ok(r) => r,
                Err(e) => {
                    let _ = ready_tx.send(Err(e.into()));
                    return None;
                }
            };
            let publisher = match FulcrumPublisher::create(&service, &publisher_options) {
                Ok(p) => p,
                Err(e) => {
                    let _ = ready_tx.send(Err(e.into()));
                    return None;
                }
            };
            let mut sink = DaemonSink { publisher, recorder: rec_producer, log: log_tx };
            let mut lp = RtLoop::new(bus, acquisition, estimation, params, rt_counters, rt_progress);
            hw_io::rt_alloc::prefault_pool();
            let lines = report.steps().iter().map(|(step, outcome)| format!("{step}: {outcome}")).collect();
            let _ = ready_tx.send(Ok(lines));
            drop(ready_tx);
            hw_io::rt_alloc::enter_realtime();
            let before = hw_io::rt_alloc::thread_system_allocs();
            let pool_before = hw_io::rt_alloc::stats();
            let result = lp.run(&mut sink, || stop.load(Ordering::Relaxed));
            let allocs = hw_io::rt_alloc::thread_system_allocs() - before;
            hw_io::rt_alloc::leave_realtime();
            let pool = hw_io::rt_alloc::stats();
            Some(RtResult {
                error: result.err().map(|e| e.to_string()),
                cycles: lp.cycles(),
                acquisition: *lp.acquisition_stats(),
                timing: lp.timing().summary(),
                histograms: lp.timing().clone(),
                alloc: AllocSummary {
                    rt_thread_system_allocs: allocs,
                    pool_allocs: pool.pool_allocs - pool_before.pool_allocs,
                    pool_fallbacks: pool.pool_fallbacks - pool_before.pool_fallbacks,
                    pool_high_water: pool.pool_high_water,
                },
                bus_dropped: lp.bus_dropped_rx_frames(),
            })
        })
        .map_err(|e| DaemonError::Thread(e.to_string()))?;
    let realtime = match ready_rx.recv() {
        Ok(Ok(lines)) => lines,
        Ok(Err(e)) => {
            stop.store(true, Ordering::Relaxed);
            let _ = handle.join();
            return Err(e);
        }
        Err(_) => {
            stop.store(true, Ordering::Relaxed);
            let _ = handle.join();
            return Err(DaemonError::Thread("the real-time thread died during set-up".into()));
        }
    };
    // Refused steps were already warned about (with what would permit them) by rt.
    for line in realtime.iter().filter(|l| !l.contains("refused")) {
        info!("real-time: {line}");
    }

    // Main thread: log hand-off and the simulated truth, until the loop ends; every 10 s a
    // line on the per-cycle conditions (incomplete cycles, overruns) if any occurred, and one
    // on the frames the bus dropped (receive queue full) if any were.
    let mut last_report = std::time::Instant::now();
    let mut health_log = HealthLog::new();
    let mut reported = (0u64, 0u64);
    let mut reported_drops = 0u64;
    while !handle.is_finished() {
        std::thread::sleep(Duration::from_millis(10));
        if last_report.elapsed() >= Duration::from_secs(10) {
            last_report = std::time::Instant::now();
            let now = (counters.incomplete_cycles.load(Ordering::Relaxed), counters.overruns.load(Ordering::Relaxed));
            if now != reported {
                warn!(
                    "last 10 s: {} incomplete cycles (a TPDO missed its deadline; data not used), {} overruns",
                    now.0 - reported.0,
                    now.1 - reported.1
                );
                reported = now;
            }
            let drops = counters.bus_dropped_rx_frames.load(Ordering::Relaxed);
            if drops != reported_drops {
                warn!("{}", drops_line("last 10 s", drops - reported_drops, drops));
                reported_drops = drops;
            }
            if let Some(line) = health_log.flaps() {
                warn!("last 10 s: {line}");
            }
        }
        let now_s = progress.snapshot().cycles as f64 * period_s;
        for line in health_log.tick(now_s) {
            warn!("{line}");
        }
        while let Some(e) = log_rx.dequeue() {
            log_event(&e, period_s, sim.as_ref(), &mut health_log);
        }
        if let Some(s) = &sim {
            s.drain_truth(|line| info!("{line}"));
        }
    }
    stop.store(true, Ordering::Relaxed);
    let rt = handle.join().map_err(|_| DaemonError::Thread("the real-time thread panicked".into()))?;
    let drops = counters.bus_dropped_rx_frames.load(Ordering::Relaxed);
    if drops != reported_drops {
        warn!("{}", drops_line("since the last report", drops - reported_drops, drops));
    }
    while let Some(e) = log_rx.dequeue() {
        log_event(&e, period_s, sim.as_ref(), &mut health_log);
    }
    let sim_syncs_answered = match sim {
        Some(s) => {
            s.drain_truth(|line| info!("{line}"));
            s.join()
        }
        None => 0,
    };
    if let Some(w) = watchdog
        && let Err(e) = w.shutdown()
    {
        warn!("{e}");
    }
    let recorder = match rec_handle {
        Some(h) => match h.shutdown() {
            Ok(s) => Some(s),
            Err(e) => {
                warn!("flight recorder shutdown: {e}");
                None
            }
        },
        None => None,
    };
    let rt = rt.ok_or_else(|| DaemonError::Thread("the real-time thread returned no result".into()))?;
    if let Some(e) = &rt.error {
        return Err(DaemonError::Thread(format!("the loop stopped: {e}")));
    }
    let p = &counters;
    Ok(RunSummary {
        bus: bus_name,
        run_id,
        period_us: cfg.cycle.period_us,
        cycles: rt.cycles,
        valid_cycles: p.valid_cycles.load(Ordering::Relaxed),
        published: p.published.load(Ordering::Relaxed),
        publish_errors: p.publish_errors.load(Ordering::Relaxed),
        overruns: p.overruns.load(Ordering::Relaxed),
        log_drops: p.log_drops.load(Ordering::Relaxed),
        recorder_queue_drops: p.recorder_drops.load(Ordering::Relaxed),
        recorder,
        recording,
        bus_dropped_rx_frames: rt.bus_dropped,
        acquisition: rt.acquisition,
        timing: rt.timing,
        alloc: rt.alloc,
        realtime,
        sim_syncs_answered,
        timing_histograms: Some(rt.histograms),
    })
}
