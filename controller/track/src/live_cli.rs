//! `comanip-track live`: the live loop ([`crate::live::run`]) on iceoryx2 and the bus, its
//! status lines, summary and latency figures.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use controller::process::{STOP, install_stop_handlers, write_json};
use hw_io::ipc::{
    CalibrationSample, FrameSubscriber, Publisher, PublisherOptions, Subscriber, TrackSample, TrackStatus,
};

use crate::config::TrackFile;
use crate::input::{iso, read_stereo, read_truth_rig};
use crate::live::{BusJoints, FrameClock, LiveCounters, LiveTracker, LoopOptions, Rig, run as run_loop};

/// The command line of `comanip-track live` (flattened into the command by `main.rs`).
#[derive(Clone, Debug, clap::Args)]
pub struct LiveArgs {
    /// The left and right eyes' camera_info YAML (default: the configuration's
    /// `[rig] cameras`).
    #[arg(long, num_args = 2, value_names = ["LEFT", "RIGHT"])]
    pub cameras: Vec<PathBuf>,
    /// The bus interface the passive listener opens (default: fulcrumd's configuration's
    /// `[bus] iface`).
    #[arg(long, conflicts_with = "candump")]
    pub iface: Option<String>,
    /// Both arms' joints from a recorded candump log replayed through the bus listener
    /// instead of the bus (replays, tests).
    #[arg(long)]
    pub candump: Option<PathBuf>,
    /// Added to each frame's timestamp to get the candump log's clock, nanoseconds (0: the
    /// frames carry the log's clock, as `comanip-camera images` plays a recorded run).
    #[arg(long, default_value_t = 0, allow_hyphen_values = true)]
    pub candump_offset_ns: i64,
    /// Instead of an offset: a frame's time on the log's clock is the recorded time of its
    /// sequence number in this frames.txt (frames played with `comanip-camera images
    /// --paced`, stamped live).
    #[arg(long, requires = "candump", conflicts_with = "candump_offset_ns")]
    pub candump_frames_index: Option<PathBuf>,
    /// Take the rig (hand-eye, the endoscope arm in the tool arm's base, the instrument) from
    /// a simulated run's truth.jsonl header (an exact calibration) instead of the config.
    #[arg(long)]
    pub rig_from_truth: Option<PathBuf>,
    /// Frame service.
    #[arg(long, default_value = hw_io::ipc::DEFAULT_FRAME_SERVICE)]
    pub frame_service: String,
    /// Calibration service (`comanip-calib live`).
    #[arg(long, default_value = hw_io::ipc::DEFAULT_CALIBRATION_SERVICE)]
    pub calibration_service: String,
    /// Output service.
    #[arg(long, default_value = hw_io::ipc::DEFAULT_TRACK_SERVICE)]
    pub output_service: String,
    /// Stop after this many frames.
    #[arg(long)]
    pub frames: Option<u64>,
    /// Stop when no frame came for this long after the first one, seconds (default: never).
    #[arg(long)]
    pub idle_timeout_s: Option<f64>,
    /// Seconds between two status lines on the log.
    #[arg(long, default_value_t = 5.0)]
    pub status_every_s: f64,
    /// Write the run's summary here (JSON) at exit.
    #[arg(long)]
    pub summary_json: Option<PathBuf>,
    /// Also write every published sample here (JSON Lines), for tests and offline checks.
    #[arg(long)]
    pub samples_jsonl: Option<PathBuf>,
}

/// Why `comanip-track live` failed.
#[derive(Debug, thiserror::Error)]
pub enum LiveCliError {
    /// A command-line or configuration problem.
    #[error("{0}")]
    Setup(String),
    /// A file.
    #[error(transparent)]
    Input(#[from] crate::input::SequenceError),
    /// The model.
    #[error(transparent)]
    Model(#[from] crate::run::RunError),
    /// The tracker.
    #[error(transparent)]
    Build(#[from] crate::live::LiveBuildError),
    /// Shared memory.
    #[error("{what}: {message}")]
    Ipc {
        /// Which service.
        what: &'static str,
        /// Why.
        message: String,
    },
    /// The loop.
    #[error(transparent)]
    Loop(#[from] crate::live::LiveError),
    /// An output file.
    #[error("{path}: {message}")]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        message: String,
    },
}

/// A latency histogram: 0.1 ms bins up to 2 s (the last bin holds everything above).
#[derive(Clone, Debug)]
pub struct LatencyHistogram {
    bins: Vec<u64>,
    count: u64,
    max_ns: u64,
}

impl Default for LatencyHistogram {
    fn default() -> Self {
        Self { bins: vec![0; 20_001], count: 0, max_ns: 0 }
    }
}

impl LatencyHistogram {
    /// Adds one latency, nanoseconds.
    pub fn add(&mut self, ns: u64) {
        let i = ((ns / 100_000) as usize).min(self.bins.len() - 1);
        self.bins[i] += 1;
        self.count += 1;
        self.max_ns = self.max_ns.max(ns);
    }

    /// The `q` quantile (0..=1), milliseconds (upper edge of its bin); `None` when empty.
    pub fn quantile_ms(&self, q: f64) -> Option<f64> {
        if self.count == 0 {
            return None;
        }
        let target = ((q * self.count as f64).ceil() as u64).clamp(1, self.count);
        let mut seen = 0;
        for (i, n) in self.bins.iter().enumerate() {
            seen += n;
            if seen >= target {
                return Some((i + 1) as f64 * 0.1);
            }
        }
        Some(self.max_ns as f64 * 1e-6)
    }

    /// `{count, p50_ms, p99_ms, max_ms}`.
    pub fn summary(&self) -> LatencySummary {
        LatencySummary {
            count: self.count,
            p50_ms: self.quantile_ms(0.5),
            p99_ms: self.quantile_ms(0.99),
            max_ms: (self.count > 0).then_some(self.max_ns as f64 * 1e-6),
        }
    }
}

/// Latency percentiles, milliseconds.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct LatencySummary {
    /// Samples.
    pub count: u64,
    /// Median.
    pub p50_ms: Option<f64>,
    /// 99th percentile.
    pub p99_ms: Option<f64>,
    /// Largest.
    pub max_ms: Option<f64>,
}

/// What `comanip-track live --summary-json` writes.
#[derive(Clone, Debug, serde::Serialize)]
pub struct LiveSummary {
    /// Mode and particles.
    pub mode: String,
    /// Particles.
    pub particles: usize,
    /// Frame counters.
    pub counters: LiveCounters,
    /// Samples published.
    pub published: u64,
    /// Seconds from the first frame received to the last sample.
    pub seconds: f64,
    /// Frames tracked per second over that time.
    pub processed_fps: f64,
    /// Frame mid-exposure time → sample published (meaningful when the frames are stamped on
    /// this machine's `CLOCK_MONOTONIC`, i.e. live; not for recorded timestamps).
    pub frame_to_publish: LatencySummary,
    /// Frame taken from the frame service → sample published (the tracker's own latency).
    pub receive_to_publish: LatencySummary,
    /// Whether any sample used a live calibration.
    pub live_calibration_seen: bool,
}

fn new_run_id() -> u64 {
    use std::hash::BuildHasher;
    std::hash::RandomState::new().hash_one((std::time::SystemTime::now(), std::process::id(), "comanip-track"))
}

fn ipc_err(what: &'static str) -> impl Fn(&dyn std::fmt::Display) -> LiveCliError {
    move |e| LiveCliError::Ipc { what, message: e.to_string() }
}

/// Builds the live tracker from the configuration and the command line.
pub fn build(
    file: &TrackFile,
    fcfg: &controller::config::Config,
    args: &LiveArgs,
) -> Result<LiveTracker, LiveCliError> {
    let cameras: [PathBuf; 2] = match (args.cameras.as_slice(), &file.rig.cameras) {
        ([l, r], _) => [l.clone(), r.clone()],
        ([], Some(c)) => c.clone(),
        _ => {
            return Err(LiveCliError::Setup(
                "no cameras: give --cameras LEFT RIGHT or [rig] cameras in the configuration".into(),
            ));
        }
    };
    let (intrinsics, right_from_left) = read_stereo([&cameras[0], &cameras[1]])?;
    let (hand_eye, ecm_in_tool_base, instrument) = match &args.rig_from_truth {
        Some(t) => read_truth_rig(t)?,
        None => (iso(&file.rig.hand_eye), iso(&file.rig.endoscope_in_tool_base), file.rig.instrument),
    };
    let model = crate::run::build_model_for(instrument, &file.tool, fcfg)?;
    let cfg = file.tracker(intrinsics[0].width as usize, intrinsics[0].height as usize);
    let rig = Rig { intrinsics, right_from_left, hand_eye };
    Ok(LiveTracker::new(cfg, model, rig, ecm_in_tool_base, new_run_id())?)
}

fn open_jsonl(path: Option<&Path>) -> Result<Option<std::io::BufWriter<std::fs::File>>, LiveCliError> {
    path.map(|p| {
        std::fs::File::create(p)
            .map(std::io::BufWriter::new)
            .map_err(|e| LiveCliError::Write { path: p.to_owned(), message: e.to_string() })
    })
    .transpose()
}

/// One sample as a JSON object (the `--samples-jsonl` line).
pub fn sample_json(s: &TrackSample, received_ns: u64) -> serde_json::Value {
    serde_json::json!({
        "sequence": s.sequence,
        "status": s.status().map_or("UNKNOWN", TrackStatus::name),
        "reasons": s.reasons().to_string(),
        "frame_sequence": s.frame_sequence,
        "frame_timestamp_ns": s.frame_timestamp_ns,
        "received_ns": received_ns,
        "published_ns": s.published_ns,
        "calibration_source": s.calibration_source,
        "calibration_sequence": s.calibration_sequence,
        "tip_camera_m": s.tip_camera_m,
        "tip_camera_wxyz": s.tip_camera_wxyz,
        "tip_base_m": s.tip_base_m,
        "tip_base_wxyz": s.tip_base_wxyz,
        "jaw_rad": s.jaw_rad,
        "spread_m": s.spread_m,
        "best_cost_px": s.best_cost_px,
        "frames_processed": s.frames_processed,
        "frames_skipped": s.frames_skipped,
        "frames_rejected": s.frames_rejected,
        "frames_invalid": s.frames_invalid,
    })
}

/// Both arms' joints through the passive bus listener (`controller::bus_listen`): on
/// fulcrumd's bus (`[bus] iface` of its configuration, or `--iface`), frames on
/// `CLOCK_MONOTONIC`; or a candump log replayed through the listener's `CanBus` input
/// (`--candump`), frames mapped by `--candump-offset-ns` or `--candump-frames-index`.
/// Readings are refused by `rules` (the configuration's `[joints]`); a replayed log waits
/// [`REPLAY_CATCH_UP`] instead of `rules.wait` (the whole log is read as fast as possible).
pub fn open_joints(
    fcfg: &controller::config::Config,
    args: &LiveArgs,
    rules: &crate::config::JointsRules,
) -> Result<BusJoints, LiveCliError> {
    use controller::bus_listen::{BusListener, ListenConfig, ListenerThread};
    let mut lcfg = ListenConfig::from_daemon(fcfg);
    let listen_err = |e: controller::bus_listen::ListenError| LiveCliError::Setup(format!("bus listener: {e}"));
    match &args.candump {
        Some(p) => {
            let clock = match &args.candump_frames_index {
                Some(index) => FrameClock::Index(read_frame_times(index)?),
                None => FrameClock::Offset(args.candump_offset_ns),
            };
            // The whole log is read at once: keep all of it (10 minutes of the tool arm).
            lcfg.history = REPLAY_HISTORY;
            let bus = hw_io::can::ReplayBus::open(p, hw_io::can::Pacing::AsFastAsPossible)
                .map_err(|e| LiveCliError::Setup(e.to_string()))?;
            let listener =
                ListenerThread::spawn(BusListener::new(bus, &lcfg).map_err(listen_err)?).map_err(listen_err)?;
            Ok(BusJoints::new(listener, clock, REPLAY_CATCH_UP).with_staleness(rules.tool, rules.endoscope))
        }
        None => {
            let iface = args.iface.clone().unwrap_or_else(|| fcfg.bus.iface.clone());
            if iface.is_empty() {
                return Err(LiveCliError::Setup(
                    "no bus: fulcrumd's configuration has [bus] iface = \"\" (its simulated robot); give --iface or --candump"
                        .into(),
                ));
            }
            let listener = ListenerThread::open(&iface, &lcfg).map_err(listen_err)?;
            tracing::info!(iface = %iface, "listening to the bus (passive: nothing is sent)");
            tracing::info!(
                tool_max_gap_ms = rules.tool.max_gap_ns as f64 / 1e6,
                tool_max_age_ms = rules.tool.max_age_ns as f64 / 1e6,
                endoscope_max_gap_ms = rules.endoscope.max_gap_ns as f64 / 1e6,
                endoscope_max_age_ms = rules.endoscope.max_age_ns as f64 / 1e6,
                wait_ms = rules.wait.as_secs_f64() * 1e3,
                "joint readings around a frame's time"
            );
            Ok(BusJoints::new(listener, FrameClock::Monotonic, rules.wait).with_staleness(rules.tool, rules.endoscope))
        }
    }
}

/// `seconds` as a duration, refused unless finite and positive (a command-line value).
fn positive_seconds(option: &str, seconds: f64) -> Result<Duration, LiveCliError> {
    match Duration::try_from_secs_f64(seconds) {
        Ok(d) if seconds > 0.0 => Ok(d),
        _ => Err(LiveCliError::Setup(format!("{option} must be a positive number of seconds, not {seconds}"))),
    }
}

/// Tool-arm samples kept when a candump log is replayed (the whole log is read at once).
pub const REPLAY_HISTORY: usize = 600_000;

/// How long a frame waits for a replayed log to be read past its time.
pub const REPLAY_CATCH_UP: Duration = Duration::from_secs(10);

/// The recorded mid-exposure times of a `frames.txt` (nanoseconds, in order).
pub fn read_frame_times(path: &Path) -> Result<Vec<u64>, LiveCliError> {
    let text = std::fs::read_to_string(path).map_err(|e| LiveCliError::Setup(format!("{}: {e}", path.display())))?;
    let mut times = Vec::new();
    for line in text.lines().map(str::trim).filter(|l| !l.is_empty() && !l.starts_with('#')) {
        let t = line.split_whitespace().next().and_then(|t| t.parse::<u64>().ok()).ok_or_else(|| {
            LiveCliError::Setup(format!("{}: not `t_mid_ns exposure_ns left right`: {line}", path.display()))
        })?;
        times.push(t);
    }
    if times.is_empty() {
        return Err(LiveCliError::Setup(format!("{}: no frames listed", path.display())));
    }
    Ok(times)
}

/// Makes the calling thread the tracking thread: puts it below the bus listener started before
/// (`controller::rt::lower_current_thread`; on a busy CPU a frame's step, hundreds of
/// milliseconds on a slow machine, must not keep the listener from the bus, or every frame's
/// joints read as stale: seen in the one-CPU HIL guest, docs/hil.md). The tracker's worker
/// threads (`track::Workers`) are started by its first step, from this thread, so they inherit
/// the lowered priority: call it before the first frame. Logged, never fatal.
pub fn become_the_tracking_thread() {
    let lowered = controller::rt::lower_current_thread();
    match &lowered {
        controller::rt::Lowered::Unchanged { reason } => {
            tracing::warn!(%reason, "the tracking thread could not be put below the bus listener")
        }
        l => tracing::info!(tracking_thread = %l, "the tracking threads run below the bus listener"),
    }
}

/// Runs `comanip-track live` until a stop condition (signal, `--frames`, idle timeout).
pub fn run(file: &TrackFile, fcfg: &controller::config::Config, args: &LiveArgs) -> Result<(), LiveCliError> {
    let every = positive_seconds("--status-every-s", args.status_every_s)?.max(Duration::from_millis(100));
    let idle_timeout = args.idle_timeout_s.map(|s| positive_seconds("--idle-timeout-s", s)).transpose()?;
    let mut live = build(file, fcfg, args)?;
    let mut joints = open_joints(fcfg, args, &file.joints.resolve(fcfg.cycle.period_us))?;
    become_the_tracking_thread();
    install_stop_handlers();
    let mut frames = FrameSubscriber::connect(&args.frame_service, &PublisherOptions::frames())
        .map_err(|e| ipc_err("frame service")(&e))?;
    let mut calibration = Subscriber::<CalibrationSample>::connect(&args.calibration_service)
        .map_err(|e| ipc_err("calibration service")(&e))?;
    let mut publisher = Publisher::<TrackSample>::create(&args.output_service, &PublisherOptions::default())
        .map_err(|e| ipc_err("track service")(&e))?;
    let cfg = *live.config();
    tracing::info!(
        mode = crate::run::mode_name(cfg.mode),
        particles = cfg.particles,
        threads = if cfg.threads == 0 { track::workers::available_threads() } else { cfg.threads },
        width = cfg.width,
        height = cfg.height,
        frames = %args.frame_service,
        output = %args.output_service,
        "comanip-track live: waiting for frames; calibration from the configuration until {} publishes a valid one",
        args.calibration_service
    );
    let mut jsonl = open_jsonl(args.samples_jsonl.as_deref())?;
    let mut frame_lat = LatencyHistogram::default();
    let mut recv_lat = LatencyHistogram::default();
    let mut first: Option<Instant> = None;
    let mut last = Instant::now();
    let mut last_status = Instant::now();
    let mut published = 0u64;
    let mut live_calibration_seen = false;
    let mut write_error: Option<String> = None;
    let mut on_sample = |s: &TrackSample, received_ns: u64| {
        let now = Instant::now();
        first.get_or_insert(now);
        last = now;
        published += 1;
        live_calibration_seen |= s.calibration_source == 1;
        if s.frame_timestamp_ns > 0 {
            frame_lat.add(s.published_ns.saturating_sub(s.frame_timestamp_ns));
        }
        recv_lat.add(s.published_ns.saturating_sub(received_ns));
        if let Some(w) = jsonl.as_mut()
            && let Err(e) = writeln!(w, "{}", sample_json(s, received_ns))
        {
            write_error.get_or_insert(e.to_string());
        }
        if now.duration_since(last_status) >= every {
            last_status = now;
            tracing::info!(
                sample = s.sequence,
                status = s.status().map_or("UNKNOWN", TrackStatus::name),
                reasons = %s.reasons(),
                processed = s.frames_processed,
                skipped = s.frames_skipped,
                rejected = s.frames_rejected,
                invalid = s.frames_invalid,
                "status"
            );
        }
    };
    let opts = LoopOptions { max_frames: args.frames, idle_timeout, stop: &STOP };
    let result = run_loop(&mut live, &mut frames, &mut joints, &mut calibration, &mut publisher, &opts, &mut on_sample);
    let counters = result?;
    if let Some(mut w) = jsonl {
        w.flush().map_err(|e| LiveCliError::Write {
            path: args.samples_jsonl.clone().unwrap_or_default(),
            message: e.to_string(),
        })?;
    }
    if let Some(e) = write_error {
        return Err(LiveCliError::Write { path: args.samples_jsonl.clone().unwrap_or_default(), message: e });
    }
    let seconds = first.map_or(0.0, |f| last.duration_since(f).as_secs_f64());
    let summary = LiveSummary {
        mode: crate::run::mode_name(cfg.mode).into(),
        particles: cfg.particles,
        counters,
        published,
        seconds,
        processed_fps: if seconds > 0.0 { counters.processed.saturating_sub(1) as f64 / seconds } else { 0.0 },
        frame_to_publish: frame_lat.summary(),
        receive_to_publish: recv_lat.summary(),
        live_calibration_seen,
    };
    tracing::info!(
        processed = counters.processed,
        skipped = counters.skipped,
        rejected = counters.rejected,
        invalid = counters.invalid,
        tracking = counters.by_status[1],
        uncertain = counters.by_status[2],
        lost = counters.by_status[3],
        fps = summary.processed_fps,
        stopped_by_signal = STOP.load(Ordering::Relaxed),
        "comanip-track live: stopped"
    );
    write_json(args.summary_json.as_deref(), &summary).map_err(|e| LiveCliError::Write {
        path: args.summary_json.clone().unwrap_or_default(),
        message: e.to_string(),
    })?;
    Ok(())
}
