//! fulcrumd: the trocar daemon, and its tools (`monitor`, `replay`).
//!
//! `fulcrumd` runs the 1 kHz loop: on the CAN interface of the config (or `--iface`), or,
//! when none is configured, on the built-in simulated robot (an in-process bus), printing
//! detections as the simulated surgeon moves. See `docs/daemon.md` (commands, stale-data policy,
//! the demo's first minute) and `docs/systemd.md` (running it as a service).
//!
//! Exit codes: 0 success; 1 `replay` found a difference; 2 error; 141 the standard output was
//! closed by its reader (`fulcrumd monitor | head`: no message; `monitor` still writes its
//! samples and summary files).

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use clap::{Args, Parser, Subcommand};
use controller::config::Config;
use controller::daemon::{self, RunOptions};
use controller::process;
use controller::replay;
use estimator::trocar::DetectorMode;
use hw_io::ipc::{Continuity, FulcrumSubscriber, HealthFlags, OutputState, UnknownState};
use hw_io::outln;
use hw_io::stdout::{BROKEN_PIPE_EXIT, is_broken_pipe};

#[global_allocator]
static ALLOC: hw_io::rt_alloc::RtPoolAllocator = hw_io::rt_alloc::RtPoolAllocator::new();

/// Command line of fulcrumd.
#[derive(Parser, Debug)]
#[command(version, about = "comanip trocar daemon: 1 kHz fulcrum estimates from the encoder bus, over iceoryx2")]
#[command(args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    run: RunArgs,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the daemon (the default).
    Run(RunArgs),
    /// Show the live estimates of a running daemon.
    Monitor(MonitorArgs),
    /// Rerun the detector over a flight recording or a candump log.
    Replay(ReplayArgs),
}

#[derive(Args, Debug, Clone)]
struct RunArgs {
    /// Configuration file (TOML). Without it, the built-in defaults (identical to
    /// configs/fulcrumd.toml) are used.
    #[arg(long)]
    config: Option<PathBuf>,
    /// CAN interface (overrides bus.iface): can0, vcan0, ... Without one, the built-in
    /// simulated robot.
    #[arg(long)]
    iface: Option<String>,
    /// Detector mode (overrides detector.mode): paper or fast.
    #[arg(long, value_parser = parse_mode)]
    mode: Option<DetectorMode>,
    /// Stop after this many cycles (default: run until SIGINT/SIGTERM).
    #[arg(long)]
    cycles: Option<u64>,
    /// Recording directory (overrides recorder.dir).
    #[arg(long)]
    record_dir: Option<PathBuf>,
    /// Do not record (overrides recorder.enabled).
    #[arg(long)]
    no_record: bool,
    /// Output service name (overrides output.service).
    #[arg(long)]
    service: Option<String>,
    /// Seed of the built-in simulated surgeon.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Write the run summary (counters, timing, allocations) as JSON to this file at exit.
    #[arg(long)]
    summary_json: Option<PathBuf>,
}

#[derive(Args, Debug)]
struct MonitorArgs {
    /// Output service name.
    #[arg(long, default_value = "comanip/fulcrum")]
    service: String,
    /// Samples this subscriber's buffer holds (at most the daemon's `output.subscriber_buffer`
    /// when the daemon created the service; when the monitor starts first, the daemon's value
    /// must be at most this).
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..=65536))]
    buffer: u32,
    /// Exit after receiving this many samples.
    #[arg(long)]
    count: Option<u64>,
    /// Exit after this many seconds.
    #[arg(long)]
    duration_s: Option<f64>,
    /// Print every sample (default: state and health changes, and a status line per second).
    #[arg(long)]
    all: bool,
    /// Write the subscriber's counters as JSON to this file at exit.
    #[arg(long)]
    summary_json: Option<PathBuf>,
    /// Write every received sample as one JSON line to this file (receive time, continuity,
    /// run, sequence, state, health, trocar, fulcrum, joints); for tests and diagnosis.
    #[arg(long)]
    samples_out: Option<PathBuf>,
}

#[derive(Args, Debug)]
struct ReplayArgs {
    /// A flight recording: its directory, or one of its files (the whole run is read).
    #[arg(long)]
    recording: Option<PathBuf>,
    /// A candump log (`candump -l` format).
    #[arg(long)]
    candump: Option<PathBuf>,
    /// Configuration for a candump replay (default: the recording's, else the defaults).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Detector mode for a candump replay (overrides the configuration).
    #[arg(long, value_parser = parse_mode)]
    mode: Option<DetectorMode>,
    /// Ground truth (truth.jsonl from `simrobot generate`) to score a candump replay against.
    #[arg(long)]
    truth: Option<PathBuf>,
    /// Write the replay report as JSON to this file.
    #[arg(long)]
    report_json: Option<PathBuf>,
}

fn parse_mode(s: &str) -> Result<DetectorMode, String> {
    match s {
        "paper" => Ok(DetectorMode::Paper),
        "fast" => Ok(DetectorMode::Fast),
        other => Err(format!("unknown mode {other:?}: expected paper or fast")),
    }
}

fn load_config(path: &Option<PathBuf>) -> Result<(Config, String), String> {
    match path {
        Some(p) => {
            let text =
                std::fs::read_to_string(p).map_err(|e| format!("cannot read config file {}: {e}", p.display()))?;
            let cfg = Config::from_toml(&text, p).map_err(|e| e.to_string())?;
            Ok((cfg, text))
        }
        None => Ok((Config::default(), String::new())),
    }
}

/// Why a subcommand failed.
#[derive(Debug)]
enum CliError {
    /// Printed as `fulcrumd: <message>`, exit code 2.
    Message(String),
    /// The reader of the standard output went away: quiet exit, [`BROKEN_PIPE_EXIT`].
    StdoutClosed,
}

impl From<String> for CliError {
    fn from(m: String) -> Self {
        Self::Message(m)
    }
}

impl From<std::io::Error> for CliError {
    /// An error writing to the standard output.
    fn from(e: std::io::Error) -> Self {
        if is_broken_pipe(&e) { Self::StdoutClosed } else { Self::Message(format!("writing to standard output: {e}")) }
    }
}

/// Writes `value` as JSON to `path` if given ([`process::write_json`]).
fn write_json(path: &Option<PathBuf>, value: &impl serde::Serialize) -> Result<(), String> {
    process::write_json(path.as_deref(), value).map_err(|e| e.to_string())
}

fn run(args: RunArgs) -> Result<(), String> {
    let (mut cfg, _) = load_config(&args.config)?;
    if let Some(i) = args.iface {
        cfg.bus.iface = i;
    }
    if let Some(m) = args.mode {
        cfg.detector.mode = m;
    }
    if let Some(d) = args.record_dir {
        cfg.recorder.dir = d;
    }
    if args.no_record {
        cfg.recorder.enabled = false;
    }
    if let Some(s) = args.service {
        cfg.output.service = s;
    }
    // Re-validate the overridden configuration; record the effective one.
    let config_toml = toml::to_string(&cfg).map_err(|e| format!("cannot serialise the configuration: {e}"))?;
    let cfg = Config::from_toml(&config_toml, std::path::Path::new("<command line>")).map_err(|e| e.to_string())?;
    process::install_stop_handlers();
    let summary = daemon::run(
        RunOptions { config: cfg, config_toml, max_cycles: args.cycles, sim_seed: args.seed },
        &process::STOP,
    )
    .map_err(|e| e.to_string())?;
    let t = &summary.timing;
    tracing::info!(
        "stopped after {} cycles ({} valid, {} published, {} publish errors, {} overruns); \
         period error p50/p99/p99.9/max {:.0}/{:.0}/{:.0}/{:.0} us; compute {:.1}/{:.1}/{:.1}/{:.1} us; \
         real-time thread allocations {}",
        summary.cycles,
        summary.valid_cycles,
        summary.published,
        summary.publish_errors,
        summary.overruns,
        t.wake_late.p50_us,
        t.wake_late.p99_us,
        t.wake_late.p999_us,
        t.wake_late.max_us,
        t.compute.p50_us,
        t.compute.p99_us,
        t.compute.p999_us,
        t.compute.max_us,
        summary.alloc.rt_thread_system_allocs
    );
    let a = &summary.acquisition;
    tracing::info!(
        "bus: {} frames, {} dropped by the kernel (receive queue full), {} incomplete cycles, {} late TPDOs, \
         {} unknown-id, {} wrong-DLC, {} malformed, {} EMCY; recorder: {} records dropped at the queue",
        a.frames,
        summary.bus_dropped_rx_frames,
        a.incomplete_cycles,
        a.late_tpdos,
        a.unknown_id_frames,
        a.wrong_dlc_frames,
        a.malformed_frames,
        a.emcy_frames,
        summary.recorder_queue_drops
    );
    write_json(&args.summary_json, &summary)
}

#[derive(Default, serde::Serialize)]
struct MonitorSummary {
    received: u64,
    missed: u64,
    restarts: u64,
    rejected: u64,
    valid: u64,
    invalid: u64,
    inside: u64,
    /// Samples flagged valid although a data-invalidating health flag was set (must be 0).
    valid_with_invalidating_flags: u64,
    /// Samples with a non-finite float (must be 0).
    non_finite: u64,
    first_sequence: Option<u64>,
    last_sequence: Option<u64>,
    /// Longest time between two consecutive samples, milliseconds.
    max_gap_ms: f64,
}

fn monitor(args: MonitorArgs) -> Result<(), CliError> {
    process::install_stop_handlers();
    let opts = hw_io::ipc::PublisherOptions { subscriber_buffer: args.buffer as usize, ..Default::default() };
    let mut sub = FulcrumSubscriber::connect_with(&args.service, &opts).map_err(|e| e.to_string())?;
    let mut samples_out = match &args.samples_out {
        Some(p) => Some(std::io::BufWriter::new(
            std::fs::File::create(p).map_err(|e| format!("cannot create {}: {e}", p.display()))?,
        )),
        None => None,
    };
    tracing::info!("monitor: waiting for samples on {:?}", args.service);
    let start = Instant::now();
    let mut s = MonitorSummary::default();
    // The last printed state and health; `None` before the first sample.
    let mut last: Option<(Result<OutputState, UnknownState>, HealthFlags)> = None;
    let mut last_status = Instant::now();
    let mut last_rx: Option<Instant> = None;
    // The first failed write to the standard output ends the loop; the files are still written.
    let mut printed: Result<(), std::io::Error> = Ok(());
    while printed.is_ok()
        && !process::STOP.load(Ordering::Relaxed)
        && args.count.is_none_or(|c| s.received < c)
        && args.duration_s.is_none_or(|d| start.elapsed().as_secs_f64() < d)
    {
        let r = match sub.wait(Duration::from_millis(200)) {
            Ok(Some(r)) => r,
            Ok(None) => continue,
            Err(e) => {
                tracing::warn!("monitor: {e}");
                continue;
            }
        };
        let now = Instant::now();
        let state = r.sample.state();
        if let Err(unknown) = state {
            tracing::warn!("sample {}: {unknown}: counted invalid", r.sample.sequence);
        }
        if let (Some(w), Ok(line)) =
            (samples_out.as_mut(), controller::monitor::SampleLine::new(controller::rt::monotonic_now_ns(), &r))
        {
            let written =
                serde_json::to_writer(&mut *w, &line).map_err(std::io::Error::from).and_then(|()| w.write_all(b"\n"));
            if let Err(e) = written {
                return Err(format!("writing the samples file: {e}").into());
            }
        }
        if let Some(prev) = last_rx {
            s.max_gap_ms = s.max_gap_ms.max(now.duration_since(prev).as_secs_f64() * 1e3);
        }
        last_rx = Some(now);
        let x = &r.sample;
        s.received += 1;
        s.first_sequence.get_or_insert(x.sequence);
        s.last_sequence = Some(x.sequence);
        if x.is_valid() {
            s.valid += 1;
            if x.health().intersects(HealthFlags::INVALIDATING) {
                s.valid_with_invalidating_flags += 1;
            }
        } else {
            s.invalid += 1;
        }
        if state == Ok(OutputState::Inside) {
            s.inside += 1;
        }
        let floats = x.fulcrum_base_m.iter().chain(&x.wrist_base_m).chain(&x.axis_base).chain(&x.joints_rad);
        if !floats.chain([x.residual_m, x.fulcrum_std_m, x.conditioning].iter()).all(|v| v.is_finite()) {
            s.non_finite += 1;
        }
        match r.event {
            Continuity::Restart => tracing::info!("daemon (re)started: run {:016x}", x.run_id),
            Continuity::Gap { missed } => tracing::warn!("missed {missed} samples before {}", x.sequence),
            _ => {}
        }
        let state_text = state.map_or_else(|UnknownState(v)| format!("unknown({v})"), |s| s.to_string());
        if args.all || last != Some((state, x.health())) {
            let f = x.fulcrum_base_m;
            printed = outln!(
                "seq {:>9}  {:<7}  trocar {}  fulcrum ({:+.4}, {:+.4}, {:+.4}) m  std {:.2} mm  health {}",
                x.sequence,
                state_text,
                x.trocar_id,
                f[0],
                f[1],
                f[2],
                x.fulcrum_std_m * 1e3,
                x.health()
            );
            last = Some((state, x.health()));
        } else if last_status.elapsed() >= Duration::from_secs(1) {
            printed =
                outln!("seq {:>9}  {:<7}  ({} received, {} missed)", x.sequence, state_text, s.received, s.missed);
            last_status = Instant::now();
        }
    }
    if let Some(mut w) = samples_out {
        w.flush().map_err(|e| format!("writing the samples file: {e}"))?;
    }
    let c = sub.counters();
    s.missed = c.missed;
    s.restarts = c.restarts;
    s.rejected = c.rejected;
    tracing::info!(
        "monitor: {} received, {} missed, {} restarts, {} valid, {} invalid",
        s.received,
        s.missed,
        s.restarts,
        s.valid,
        s.invalid
    );
    write_json(&args.summary_json, &s)?;
    Ok(printed?)
}

fn replay_cmd(args: ReplayArgs) -> Result<bool, CliError> {
    match (&args.recording, &args.candump) {
        (Some(rec), None) => {
            let r = replay::replay_recording(rec).map_err(|e| e.to_string())?;
            outln!(
                "replay of run {:016x}: {} records, {} identical, {} mismatches{}{}",
                r.run_id,
                r.records,
                r.identical,
                r.mismatches,
                r.starts_at.map_or(String::new(), |s| format!(
                    "; the recording starts at cycle {s} (older files deleted): not comparable"
                )),
                r.gap_at.map_or(String::new(), |s| format!("; records missing at cycle {s}: compared up to there"))
            )?;
            for t in &r.truncations {
                outln!("truncated frame (the daemon was stopped mid-write): {t}")?;
            }
            write_json(&args.report_json, &r)?;
            Ok(r.reproduced())
        }
        (rec, Some(log)) => {
            let (mut cfg, records) = match rec {
                Some(rec) => {
                    let (cfg, _, records, _) = replay::load_recording(rec).map_err(|e| e.to_string())?;
                    (cfg, Some(records))
                }
                None => (load_config(&args.config)?.0, None),
            };
            if let Some(m) = args.mode {
                cfg.detector.mode = m;
            }
            let out = replay::replay_candump(log, &cfg).map_err(|e| e.to_string())?;
            let a = &out.acquisition;
            outln!(
                "candump replay ({:?} mode): {} cycles, {} incomplete, {} late TPDOs, {} unknown-id, {} wrong-DLC frames",
                cfg.detector.mode,
                out.cycles.len(),
                a.incomplete_cycles,
                a.late_tpdos,
                a.unknown_id_frames,
                a.wrong_dlc_frames
            )?;
            let mut ok = true;
            if let Some(records) = records {
                let c = replay::compare_with_recording(&out, &records, &cfg).map_err(|e| e.to_string())?;
                outln!(
                    "against the recording: aligned at log cycle {:?}, {} compared, {} identical inputs, {} identical outputs",
                    c.offset,
                    c.compared,
                    c.identical_inputs,
                    c.identical_outputs
                )?;
                ok = c.offset.is_some() && c.compared > 0 && c.identical_outputs == c.compared;
                write_json(&args.report_json, &c)?;
            }
            if let Some(truth) = &args.truth {
                let score = controller::scoring::score_log(&out, truth).map_err(|e| e.to_string())?;
                outln!("{}", score.describe())?;
                write_json(&args.report_json, &score)?;
            }
            Ok(ok)
        }
        (None, None) => Err(CliError::Message("give --recording, --candump, or both".into())),
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    process::init_logging();
    let result = match cli.command {
        None => run(cli.run).map(|()| true).map_err(CliError::from),
        Some(Command::Run(a)) => run(a).map(|()| true).map_err(CliError::from),
        Some(Command::Monitor(a)) => monitor(a).map(|()| true),
        Some(Command::Replay(a)) => replay_cmd(a),
    };
    match result {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::from(1),
        Err(CliError::StdoutClosed) => ExitCode::from(BROKEN_PIPE_EXIT),
        Err(CliError::Message(e)) => {
            eprintln!("fulcrumd: {e}");
            ExitCode::from(2)
        }
    }
}
