//! `simrobot`: the simulated Achilles robot on the encoder bus (see `docs/simulator.md`).
//!
//! - `simrobot generate --out DIR`: writes a whole run offline: `DIR/bus.log` (candump `-l`
//!   format: the controller's SYNCs and the nodes' answers) and `DIR/truth.jsonl` (ground
//!   truth). Deterministic: the same configuration and seed give the same bytes.
//! - `simrobot live --iface vcan0`: answers the controller's SYNCs on a SocketCAN interface
//!   and prints the true insertions and extractions as they happen.
//! - `simrobot render --out DIR`: renders stereo endoscope frames of a moving instrument
//!   (`DIR/frame_NNNNNN_{left,right}.png`, masks) and their ground truth (`DIR/truth.jsonl`);
//!   `--samples` writes one image per realism option instead (`docs/vision.md`).
//!
//! Exit codes: 0 success; 1 run-time error; 2 bad command line or configuration; 3 the CAN
//! interface cannot be opened (no CAN in the kernel, no such interface); 141 the standard
//! output was closed by its reader (`simrobot generate | head -1`: no message; `live` still
//! finishes its truth and summary files).

use std::fs::File;
use std::io::{self, BufWriter, IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use clap::{Args, Parser, Subcommand};
use hw_io::can::candump::CandumpWriter;
use hw_io::can::{
    CanBus, CanFrame, CanId, Message, OpenError, RecvError, SYNC_COB_ID, SocketCanBus, SyncCounter, SyncSource,
    TimedFrame,
};
use hw_io::outln;
use hw_io::stdout::{BROKEN_PIPE_EXIT, is_broken_pipe};
use sim::endoscope::config::ConfigError as EndoscopeConfigError;
use sim::endoscope::output::{OutputError, Sequence, render_sequence, write_samples};
use sim::endoscope::{DemoMotion, EndoscopeConfig, InstrumentMesh, ObjError};
use sim::live_camera::{LiveCamera, LiveCameraConfig};
use sim::truth_file::{DEFAULT_STATE_EVERY, EndoscopeRecord, ScenarioStart, TruthHeader, TruthWriteError, TruthWriter};
use sim::twin::{SYNC_PERIOD_US, SimRobot, TwinConfig, TwinConfigError, TwinError, TwinEvent};
use sim::world::{DEFAULT_KEEP_NS, FrameWriter, FramesError, World, WorldError};

/// Default epoch of `generate`: Unix time of the first SYNC, seconds (2023-11-14).
const DEFAULT_EPOCH_S: u64 = 1_700_000_000;

#[derive(Parser, Debug)]
#[command(name = "simrobot", version, about = "The simulated Achilles robot on the encoder bus (docs/simulator.md)")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Write a whole run offline: DIR/bus.log (candump -l) and DIR/truth.jsonl.
    Generate(GenerateArgs),
    /// Answer the controller's SYNCs on a SocketCAN interface.
    Live(LiveArgs),
    /// Render stereo endoscope frames and their ground truth (docs/vision.md).
    Render(RenderArgs),
}

#[derive(Args, Debug)]
struct RenderArgs {
    /// Output directory (created if needed).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Renderer configuration (TOML, every key optional; see docs/vision.md). Defaults when absent.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Seed of the tissue texture and the noise (overrides seed).
    #[arg(long, value_name = "S")]
    seed: Option<u64>,
    /// Number of stereo frames.
    #[arg(long, value_name = "N", default_value_t = 30)]
    frames: u64,
    /// Speed factor of the demo motion (1: calm; 4: quick moves).
    #[arg(long, value_name = "X", default_value_t = 1.0)]
    speed: f64,
    /// Mid time of the first frame's exposure, nanoseconds.
    #[arg(long, value_name = "NS", default_value_t = 1_000_000_000)]
    t0_ns: u64,
    /// The instrument mesh from this OBJ (metres, instrument frame; docs/vision.md) instead
    /// of the parametric one.
    #[arg(long, value_name = "FILE")]
    obj: Option<PathBuf>,
    /// Also write the parametric instrument mesh to DIR/instrument.obj.
    #[arg(long)]
    write_obj: bool,
    /// Do not write the label masks.
    #[arg(long)]
    no_masks: bool,
    /// Write one sample image per realism option into DIR instead of a sequence.
    #[arg(long)]
    samples: bool,
    /// Print the configuration in use as TOML and exit.
    #[arg(long)]
    print_config: bool,
}

#[derive(Args, Debug)]
struct Common {
    /// Twin configuration (TOML; see configs/simrobot.toml). Defaults when absent.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Scenario seed (overrides scenario.seed).
    #[arg(long, value_name = "S")]
    seed: Option<u64>,
    /// Insert/extract cycles (overrides scenario.cycles).
    #[arg(long, value_name = "N")]
    cycles: Option<usize>,
    /// Leave the endoscope-holder arm's nodes off the bus (overrides endoscope_arm.enabled):
    /// the tool arm's three nodes only, the bus as before the endoscope arm.
    #[arg(long)]
    no_endoscope: bool,
}

#[derive(Args, Debug)]
struct GenerateArgs {
    /// Output directory (created if needed).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    #[command(flatten)]
    common: Common,
    /// About this many minutes of motion: sets the cycles from the mean cycle duration
    /// (mean of scenario.inside_s, plus mean of scenario.outside_s, plus 0.9 s of extraction).
    #[arg(long, value_name = "M", conflicts_with = "cycles")]
    minutes: Option<f64>,
    /// Write a state line to truth.jsonl every K samples (1 = every sample).
    #[arg(long, value_name = "K", default_value_t = DEFAULT_STATE_EVERY)]
    state_every: u64,
    /// Unix time of the first SYNC, seconds.
    #[arg(long, value_name = "SECONDS", default_value_t = DEFAULT_EPOCH_S)]
    epoch_s: u64,
    /// Interface name written in bus.log.
    #[arg(long, value_name = "NAME", default_value = "vcan0")]
    iface: String,
    /// Also render the stereo endoscope on the endoscope arm looking at the instrument:
    /// DIR/frames/frame_NNNNNN_{left,right}.png (and _mask.png) and DIR/frames/truth.jsonl, each frame
    /// stamped with its exposure's mid time on the bus clock.
    #[arg(long)]
    frames: bool,
    /// With --frames: frames per second (overrides the renderer's timing.fps).
    #[arg(long, value_name = "FPS")]
    fps: Option<f64>,
    /// With --frames: the renderer's configuration (TOML, docs/vision.md); default: the
    /// renderer's defaults with the tissue placed for the twin (docs/simulator.md).
    #[arg(long, value_name = "FILE")]
    endoscope_config: Option<PathBuf>,
    /// With --frames: a second instrument from the other side, moving about the instrument's
    /// tip and nearer the endoscope (turns realism.second_instrument on): clutter and
    /// passing occlusions (docs/tracking.md, sim::world::World::set_second_instrument).
    #[arg(long)]
    second_instrument: bool,
    /// With --frames: an occluder plate hiding FRACTION of the instrument (tip end first, in
    /// the left eye) from START_S for DURATION_S seconds after the first frame; repeatable
    /// (docs/tracking.md). The truth gives each eye's visible fraction.
    #[arg(long, value_name = "START_S:DURATION_S:FRACTION")]
    occlude: Vec<sim::world::OcclusionWindow>,
}

#[derive(Args, Debug)]
struct LiveArgs {
    /// SocketCAN interface.
    #[arg(long, value_name = "IFACE", default_value = "vcan0")]
    iface: String,
    #[command(flatten)]
    common: Common,
    /// Go on with the next scenario (seed + 1) when one is over (overrides endless).
    #[arg(long)]
    endless: bool,
    /// Also write the ground truth to this file (time base: the first SYNC's receive time).
    #[arg(long, value_name = "FILE")]
    truth: Option<PathBuf>,
    /// With --truth: a state line every K samples.
    #[arg(long, value_name = "K", default_value_t = DEFAULT_STATE_EVERY)]
    state_every: u64,
    /// Run the nodes' schedules (heartbeats, `dropout_windows_us`, `emcy.at_us`) on the twin's
    /// own clock, 1 ms per answered SYNC from the first, instead of the wall clock: a fault
    /// then hits the same samples however fast the controller sends SYNCs (HIL tests with a
    /// slower controller period). The truth file's times are then on that clock too.
    #[arg(long)]
    twin_clock: bool,
    /// At the end, also write the counts (SYNCs answered, frames sent, ...) as JSON to this file.
    #[arg(long, value_name = "FILE")]
    summary_json: Option<PathBuf>,
    /// Also film the two arms with the stereo endoscope on the endoscope arm and publish the
    /// frames on the frame service, in step with the bus (docs/frames.md): frame n's exposure
    /// is centred on t0 + n/fps on CLOCK_MONOTONIC, rendered from the arms' states at the
    /// SYNCs' receive times.
    #[arg(long)]
    camera: bool,
    /// With --camera: the frame service's name.
    #[arg(long, value_name = "NAME", default_value = hw_io::ipc::DEFAULT_FRAME_SERVICE)]
    camera_service: String,
    /// With --camera: frames per second (overrides the renderer's timing.fps).
    #[arg(long, value_name = "FPS")]
    fps: Option<f64>,
    /// With --camera: the renderer's configuration (TOML, docs/vision.md); default: the
    /// renderer's defaults with the tissue placed for the twin (docs/simulator.md).
    #[arg(long, value_name = "FILE")]
    endoscope_config: Option<PathBuf>,
}

/// Why the configuration could not be loaded.
#[derive(Debug, thiserror::Error)]
enum ConfigError {
    #[error("cannot read {path}: {source}")]
    Read { path: PathBuf, source: io::Error },
    #[error("{path}: {source}")]
    Parse { path: PathBuf, source: toml::de::Error },
    #[error("--minutes {0}: must be a positive number of minutes up to 10000")]
    Minutes(f64),
    #[error("--state-every must be at least 1")]
    StateEvery,
    #[error("--frames needs the endoscope arm (remove --no-endoscope, or set endoscope_arm.enabled = true)")]
    FramesWithoutEndoscope,
    #[error("--fps {0}: must be a finite number of frames per second in (0, 1000]")]
    Fps(f64),
    #[error("{path}: {source}")]
    EndoscopeParse { path: PathBuf, source: toml::de::Error },
    #[error("renderer configuration: {0}")]
    Endoscope(#[from] EndoscopeConfigError),
    #[error("the world of the two arms: {0}")]
    World(#[from] WorldError),
    #[error(transparent)]
    Twin(#[from] TwinConfigError),
}

/// Why `generate` failed.
#[derive(Debug, thiserror::Error)]
enum GenerateError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("--iface {0:?}: not a valid interface name")]
    Iface(String),
    #[error("cannot create {path}: {source}")]
    Create { path: PathBuf, source: io::Error },
    #[error("writing {path}: {source}")]
    Write { path: PathBuf, source: io::Error },
    #[error("{path}: {source}")]
    Truth { path: PathBuf, source: TruthWriteError },
    #[error("simulated robot: {0}")]
    Twin(#[from] TwinError),
    #[error("frames: {0}")]
    Frames(#[from] FramesError),
    #[error("frames: {0}")]
    World(#[from] WorldError),
    #[error("writing to standard output: {0}")]
    Stdout(io::Error),
}

/// Why `render` failed.
#[derive(Debug, thiserror::Error)]
enum RenderCmdError {
    #[error("cannot read {path}: {source}")]
    Read { path: PathBuf, source: io::Error },
    #[error("{path}: {source}")]
    Parse { path: PathBuf, source: toml::de::Error },
    #[error("--speed {0}: must be a finite positive number")]
    Speed(f64),
    #[error("{path}: {source}")]
    Obj { path: PathBuf, source: ObjError },
    #[error("configuration: {0}")]
    Config(#[from] EndoscopeConfigError),
    #[error(transparent)]
    Output(#[from] OutputError),
    #[error("printing the configuration: {0}")]
    Toml(#[from] toml::ser::Error),
    #[error("writing to standard output: {0}")]
    Stdout(io::Error),
}

/// Why `live` failed.
#[derive(Debug, thiserror::Error)]
enum LiveError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Open(#[from] OpenError),
    #[error("cannot install the SIGINT/SIGTERM handler: {0}")]
    Signal(nix::Error),
    #[error("receiving from the CAN bus: {0}")]
    Recv(RecvError),
    #[error("cannot create {path}: {source}")]
    Create { path: PathBuf, source: io::Error },
    #[error("{path}: {source}")]
    Truth { path: PathBuf, source: TruthWriteError },
    #[error("simulated robot: {0}")]
    Twin(#[from] TwinError),
    #[error("writing to standard output: {0}")]
    Stdout(io::Error),
    #[error("the live camera: {0}")]
    Camera(#[from] sim::live_camera::LiveCameraError),
}

fn load_config(common: &Common) -> Result<TwinConfig, ConfigError> {
    let mut config = match &common.config {
        Some(path) => {
            let text =
                std::fs::read_to_string(path).map_err(|source| ConfigError::Read { path: path.clone(), source })?;
            toml::from_str(&text).map_err(|source| ConfigError::Parse { path: path.clone(), source })?
        }
        None => TwinConfig::default(),
    };
    if let Some(seed) = common.seed {
        config.scenario.seed = seed;
    }
    if let Some(cycles) = common.cycles {
        config.scenario.cycles = cycles;
    }
    if common.no_endoscope {
        config.endoscope_arm.enabled = false;
    }
    Ok(config)
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::Generate(args) => match generate(&args) {
            Ok(()) => ExitCode::SUCCESS,
            Err(GenerateError::Stdout(e)) if is_broken_pipe(&e) => ExitCode::from(BROKEN_PIPE_EXIT),
            Err(e) => {
                eprintln!("simrobot generate: error: {e}");
                ExitCode::from(if matches!(e, GenerateError::Config(_) | GenerateError::Iface(_)) { 2 } else { 1 })
            }
        },
        Command::Render(args) => match render(&args) {
            Ok(()) => ExitCode::SUCCESS,
            Err(RenderCmdError::Stdout(e)) if is_broken_pipe(&e) => ExitCode::from(BROKEN_PIPE_EXIT),
            Err(e) => {
                eprintln!("simrobot render: error: {e}");
                let usage = matches!(
                    e,
                    RenderCmdError::Read { .. }
                        | RenderCmdError::Parse { .. }
                        | RenderCmdError::Speed(_)
                        | RenderCmdError::Obj { .. }
                        | RenderCmdError::Config(_)
                );
                ExitCode::from(if usage { 2 } else { 1 })
            }
        },
        Command::Live(args) => match live(&args) {
            Ok(()) => ExitCode::SUCCESS,
            Err(LiveError::Stdout(e)) if is_broken_pipe(&e) => ExitCode::from(BROKEN_PIPE_EXIT),
            Err(e) => {
                eprintln!("simrobot live: error: {e}");
                ExitCode::from(match e {
                    LiveError::Config(_) => 2,
                    LiveError::Open(_) => 3,
                    _ => 1,
                })
            }
        },
    }
}

// ----------------------------------------------------------------------------------------
// generate

/// Frames written so far, and frames of earlier SYNCs still to be written (bus order).
struct BusLog<W: Write> {
    writer: CandumpWriter<W>,
    pending: Vec<TimedFrame>,
    frames: u64,
}

impl<W: Write> BusLog<W> {
    /// Writes the pending frames that win the bus before `(t_us, id)`, all when `None`.
    fn flush_before(&mut self, before: Option<(u64, u32)>) -> io::Result<()> {
        let n = match before {
            Some(key) => self.pending.partition_point(|f| (f.unix_time_us, f.frame.id().raw()) < key),
            None => self.pending.len(),
        };
        for f in &self.pending[..n] {
            self.writer.write(f)?;
        }
        self.frames += n as u64;
        self.pending.drain(..n);
        Ok(())
    }

    /// Writes `frame` at `t_us` after the pending frames that come before it.
    fn write(&mut self, frame: TimedFrame) -> io::Result<()> {
        self.flush_before(Some((frame.unix_time_us, frame.frame.id().raw())))?;
        self.writer.write(&frame)?;
        self.frames += 1;
        Ok(())
    }

    /// Queues frames for later (they are sent after the current SYNC).
    fn queue(&mut self, frames: &[TimedFrame]) {
        self.pending.extend_from_slice(frames);
        // Stable: frames of one node with the same time and ID keep their order.
        self.pending.sort_by_key(|f| (f.unix_time_us, f.frame.id().raw()));
    }
}

fn create(path: &Path) -> Result<File, GenerateError> {
    File::create(path).map_err(|source| GenerateError::Create { path: path.to_owned(), source })
}

fn progress_bar(total: u64) -> indicatif::ProgressBar {
    if !io::stderr().is_terminal() {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(total);
    if let Ok(style) = indicatif::ProgressStyle::with_template(
        "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} samples ({percent}%, eta {eta})",
    ) {
        bar.set_style(style);
    }
    bar
}

fn generate(args: &GenerateArgs) -> Result<(), GenerateError> {
    let started = Instant::now();
    let mut config = load_config(&args.common)?;
    config.endless = false; // a file has an end
    if args.state_every == 0 {
        return Err(ConfigError::StateEvery.into());
    }
    if let Some(minutes) = args.minutes {
        if !(minutes.is_finite() && minutes > 0.0 && minutes <= 10_000.0) {
            return Err(ConfigError::Minutes(minutes).into());
        }
        let s = &config.scenario;
        // The extraction (from the final depth, some 7 cm, plus 3 cm out at 8-16 cm/s) comes
        // on top of inside_s: about 0.9 s per cycle.
        let mean_cycle_s = (s.inside_s[0] + s.inside_s[1]) / 2.0 + (s.outside_s[0] + s.outside_s[1]) / 2.0 + 0.9;
        config.scenario.cycles = ((minutes * 60.0 / mean_cycle_s.max(1e-3)).round() as usize).max(1);
    }
    let mut robot = SimRobot::new(&config).map_err(ConfigError::from)?;
    let t0_us = args.epoch_s.saturating_mul(1_000_000);
    let mut frames_out = match args.frames {
        true => Some(frames_setup(args, &config, t0_us)?),
        false => None,
    };
    std::fs::create_dir_all(&args.out).map_err(|source| GenerateError::Create { path: args.out.clone(), source })?;
    let bus_path = args.out.join("bus.log");
    let truth_path = args.out.join("truth.jsonl");
    let writer = CandumpWriter::new(BufWriter::with_capacity(1 << 20, create(&bus_path)?), &args.iface)
        .map_err(|_| GenerateError::Iface(args.iface.clone()))?;
    let mut bus = BusLog { writer, pending: Vec::with_capacity(64), frames: 0 };
    let bus_err = |source| GenerateError::Write { path: bus_path.clone(), source };
    let truth_err = |source| GenerateError::Truth { path: truth_path.clone(), source };
    let mut header = TruthHeader::new(&config.scenario, t0_us, args.state_every);
    header.twin = Some(config.clone());
    let mut truth =
        TruthWriter::new(BufWriter::with_capacity(1 << 16, create(&truth_path)?), &header).map_err(truth_err)?;
    truth.scenario(ScenarioStart { sample: 0, seed: config.scenario.seed }).map_err(truth_err)?;

    let total = robot.scenario().truth.len() as u64;
    let bar = progress_bar(total);
    let mut sync = SyncSource::new();
    let mut twin_time = Duration::ZERO;
    let mut events = 0u64;
    let mut i = 0u64;
    loop {
        let t_us = t0_us.saturating_add(i.saturating_mul(SYNC_PERIOD_US));
        let counter = sync.next_counter();
        let step = Instant::now();
        let answer = robot.on_sync(counter, t_us)?;
        twin_time += step.elapsed();
        let Some(frames) = answer else { break };
        let sync_frame = CanFrame::new_standard(SYNC_COB_ID, &[counter]).map_err(|e| bus_err(io::Error::other(e)))?;
        bus.write(TimedFrame { frame: sync_frame, unix_time_us: t_us }).map_err(bus_err)?;
        bus.queue(&frames);
        truth.sample(t_us, robot.truth(), robot.events()).map_err(truth_err)?;
        if let (true, Some(joints)) = (robot.endoscope_tpdos_sent(), robot.endoscope_joints()) {
            truth.endoscope(&EndoscopeRecord { sample: i, unix_time_us: t_us, joints }).map_err(truth_err)?;
        }
        if let Some((world, writer)) = frames_out.as_mut() {
            world.record(t_us.saturating_mul(1000), &robot)?;
            while writer.ready(world) {
                writer.write_next(world)?;
            }
        }
        events += robot.events().len() as u64;
        i += 1;
        if i.is_multiple_of(4096) {
            bar.set_position(i);
        }
    }
    bus.flush_before(None).map_err(bus_err)?;
    bus.writer.flush().map_err(bus_err)?;
    truth.finish().map_err(truth_err)?;
    bar.finish_and_clear();
    let frames_summary = match frames_out {
        Some((_, writer)) => {
            let (n, with, fps) = (writer.frames(), writer.frames_with_instrument(), writer.fps());
            writer.finish()?;
            Some((n, with, fps))
        }
        None => None,
    };

    let elapsed = started.elapsed().as_secs_f64();
    let size = |p: &Path| std::fs::metadata(p).map(|m| m.len()).unwrap_or(0);
    let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
    let motion_s = i as f64 * SYNC_PERIOD_US as f64 * 1e-6;
    let twin_s = twin_time.as_secs_f64();
    outln!(
        "simrobot generate: seed {}, {} cycles, {} samples = {:.1} s ({:.1} min) of motion, {} true events",
        config.scenario.seed,
        config.scenario.cycles,
        i,
        motion_s,
        motion_s / 60.0,
        events
    )
    .map_err(GenerateError::Stdout)?;
    outln!("  {}: {} frames, {:.1} MiB", bus_path.display(), bus.frames, mib(size(&bus_path)))
        .map_err(GenerateError::Stdout)?;
    outln!("  {}: {:.1} MiB", truth_path.display(), mib(size(&truth_path))).map_err(GenerateError::Stdout)?;
    if let Some((n, with, fps)) = frames_summary {
        outln!(
            "  {}: {n} stereo frames at {} fps, the instrument visible (>= {} px, left eye) in {with} ({:.1} %)",
            args.out.join("frames").display(),
            fps,
            sim::world::VISIBLE_MIN_PX,
            if n > 0 { with as f64 * 100.0 / n as f64 } else { 0.0 }
        )
        .map_err(GenerateError::Stdout)?;
    }
    outln!(
        "  took {:.2} s: twin (inverse kinematics + nodes) {:.2} s = {:.2} us/sample, scenario generation and writing {:.2} s",
        elapsed,
        twin_s,
        if i > 0 { twin_s * 1e6 / i as f64 } else { 0.0 },
        elapsed - twin_s
    )
    .map_err(GenerateError::Stdout)
}

/// The renderer configuration of `generate --frames` and `live --camera`: the file or the
/// default, then `--fps`.
fn frames_config(endoscope_config: &Option<PathBuf>, fps: Option<f64>) -> Result<EndoscopeConfig, ConfigError> {
    let mut cfg = match endoscope_config {
        Some(path) => {
            let text =
                std::fs::read_to_string(path).map_err(|source| ConfigError::Read { path: path.clone(), source })?;
            toml::from_str(&text).map_err(|source| ConfigError::EndoscopeParse { path: path.clone(), source })?
        }
        None => sim::world::default_endoscope_config(),
    };
    if let Some(fps) = fps {
        if !(fps.is_finite() && fps > 0.0 && fps <= 1000.0) {
            return Err(ConfigError::Fps(fps));
        }
        cfg.timing.fps = fps;
        // The exposure cannot exceed the frame period.
        cfg.timing.exposure_s = cfg.timing.exposure_s.min(1.0 / fps);
    }
    cfg.validate()?;
    Ok(cfg)
}

/// The world and the frame writer of `generate --frames`: frames from the first SYNC
/// (`t0_us`) into `DIR/frames`.
fn frames_setup(args: &GenerateArgs, config: &TwinConfig, t0_us: u64) -> Result<(World, FrameWriter), GenerateError> {
    if !config.endoscope_arm.enabled {
        return Err(ConfigError::FramesWithoutEndoscope.into());
    }
    let mut cfg = frames_config(&args.endoscope_config, args.fps)?;
    if args.second_instrument {
        cfg.realism.second_instrument = true;
    }
    let mesh = cfg.instrument.mesh().map_err(|e| ConfigError::Endoscope(e.into()))?;
    let mut world = World::new(config, &cfg.instrument, DEFAULT_KEEP_NS).map_err(ConfigError::from)?;
    if args.second_instrument {
        world.set_second_instrument(true);
    }
    let mut writer = FrameWriter::new(
        &args.out.join("frames"),
        &cfg,
        mesh,
        t0_us.saturating_mul(1000),
        &config.endoscope_arm.rcm_in_tool_base,
    )?;
    writer.set_occlusions(args.occlude.clone());
    Ok((world, writer))
}

// ----------------------------------------------------------------------------------------
// render

fn render(args: &RenderArgs) -> Result<(), RenderCmdError> {
    let mut cfg: EndoscopeConfig = match &args.config {
        Some(path) => {
            let text =
                std::fs::read_to_string(path).map_err(|source| RenderCmdError::Read { path: path.clone(), source })?;
            toml::from_str(&text).map_err(|source| RenderCmdError::Parse { path: path.clone(), source })?
        }
        None => EndoscopeConfig::default(),
    };
    if let Some(seed) = args.seed {
        cfg.seed = seed;
    }
    if !(args.speed.is_finite() && args.speed > 0.0) {
        return Err(RenderCmdError::Speed(args.speed));
    }
    if args.print_config {
        let text = toml::to_string(&cfg)?;
        return outln!("{text}").map_err(RenderCmdError::Stdout);
    }
    cfg.validate()?;
    if args.samples {
        let written = write_samples(&cfg, &args.out, args.t0_ns, args.speed)?;
        for p in written {
            outln!("{}", p.display()).map_err(RenderCmdError::Stdout)?;
        }
        return Ok(());
    }
    let mesh = match &args.obj {
        Some(path) => {
            InstrumentMesh::load_obj(path).map_err(|source| RenderCmdError::Obj { path: path.clone(), source })?
        }
        None => cfg.instrument.mesh().map_err(EndoscopeConfigError::from)?,
    };
    if args.write_obj {
        std::fs::create_dir_all(&args.out).map_err(|source| OutputError::Io { path: args.out.clone(), source })?;
        let path = args.out.join("instrument.obj");
        let io = |source| OutputError::Io { path: path.clone(), source };
        let mut w = BufWriter::new(File::create(&path).map_err(io)?);
        mesh.write_obj(&mut w).map_err(io)?;
        w.flush().map_err(io)?;
    }
    let bar = indicatif::ProgressBar::new(args.frames);
    if !io::stderr().is_terminal() {
        bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    let motion = DemoMotion { speed: args.speed, ..Default::default() };
    let seq = Sequence { frames: args.frames, t0_ns: args.t0_ns, masks: !args.no_masks };
    let summary = render_sequence(&cfg, mesh, &motion, &seq, &args.out, |n| bar.set_position(n))?;
    bar.finish_and_clear();
    let k = &cfg.camera.intrinsics;
    outln!(
        "simrobot render: {} stereo frames {}x{} per eye into {} (truth.jsonl); rendering {:.1} ms per stereo frame ({:.1} frames/s), {:.2} s in all with PNG encoding",
        summary.frames,
        k.width,
        k.height,
        args.out.display(),
        if summary.frames > 0 { summary.render_s * 1e3 / summary.frames as f64 } else { 0.0 },
        if summary.render_s > 0.0 { summary.frames as f64 / summary.render_s } else { 0.0 },
        summary.total_s
    )
    .map_err(RenderCmdError::Stdout)
}

// ----------------------------------------------------------------------------------------
// live

static STOP: AtomicBool = AtomicBool::new(false);

extern "C" fn on_signal(_: nix::libc::c_int) {
    STOP.store(true, Ordering::SeqCst);
}

fn install_signal_handlers() -> Result<(), nix::Error> {
    use nix::sys::signal::{SaFlags, SigAction, SigHandler, SigSet, Signal, sigaction};
    let action = SigAction::new(SigHandler::Handler(on_signal), SaFlags::empty(), SigSet::empty());
    // SAFETY: the handler only stores to an atomic, which is async-signal-safe.
    unsafe {
        sigaction(Signal::SIGINT, &action)?;
        sigaction(Signal::SIGTERM, &action)?;
    }
    Ok(())
}

fn print_event(e: &TwinEvent) -> io::Result<()> {
    let what = if e.insertion { "insertion into" } else { "extraction from" };
    outln!("{:>10.3} s  sample {:>9}  {what} trocar {}", e.t_s, e.sample, e.trocar)
}

/// What `live` did; printed at the end and written by `--summary-json`.
#[derive(Debug, Default, serde::Serialize)]
struct LiveCounts {
    syncs: u64,
    frames_sent: u64,
    send_errors: u64,
    last_send_error: Option<String>,
    ignored: u64,
    bad_syncs: u64,
    sync_gaps: u64,
    error_frames: u64,
    events: u64,
    /// SYNCs answered by the endoscope arm's nodes (two TPDOs each; every 10th SYNC).
    endoscope_tpdo_syncs: u64,
    /// Frames the kernel dropped because this socket's receive queue was full (`SO_RXQ_OVFL`).
    dropped_rx_frames: u64,
    /// --camera: SYNCs recorded into the world the camera films, and refused (out of order).
    world_samples: u64,
    /// See `world_samples`.
    world_refused: u64,
    /// --camera: CLOCK_MONOTONIC time of the first and last recorded SYNC, nanoseconds.
    world_first_mono_ns: Option<u64>,
    /// See `world_first_mono_ns`.
    world_last_mono_ns: Option<u64>,
    /// --camera: what the camera published (frames, the renderer's skipped frames).
    camera: Option<sim::live_camera::CameraCounts>,
}

fn live(args: &LiveArgs) -> Result<(), LiveError> {
    let mut config = load_config(&args.common)?;
    if args.endless {
        config.endless = true;
    }
    if args.state_every == 0 {
        return Err(ConfigError::StateEvery.into());
    }
    let mut robot = SimRobot::new(&config).map_err(ConfigError::from)?;
    // --camera: the world both arms live in, shared with the camera thread (1 s of history).
    let camera_setup = if args.camera {
        if !config.endoscope_arm.enabled {
            return Err(ConfigError::FramesWithoutEndoscope.into());
        }
        let cfg = frames_config(&args.endoscope_config, args.fps)?;
        let world = World::new(&config, &cfg.instrument, 1_000_000_000).map_err(ConfigError::from)?;
        let mesh = cfg.instrument.mesh().map_err(|e| ConfigError::Endoscope(e.into()))?;
        Some((std::sync::Arc::new(std::sync::Mutex::new(world)), cfg, mesh))
    } else {
        None
    };
    install_signal_handlers().map_err(LiveError::Signal)?;
    let mut bus = SocketCanBus::open(&args.iface)?;
    let mut camera = None;
    let mut shared_world = None;
    if let Some((world, cfg, mesh)) = camera_setup {
        outln!(
            "simrobot live: camera on {}: {}×{} stereo at {} fps",
            args.camera_service,
            cfg.camera.intrinsics.width,
            cfg.camera.intrinsics.height,
            cfg.timing.fps
        )
        .map_err(LiveError::Stdout)?;
        let live_cfg = LiveCameraConfig { endoscope: cfg, mesh, service: args.camera_service.clone(), camera_id: 0 };
        camera = Some(LiveCamera::spawn(std::sync::Arc::clone(&world), live_cfg)?);
        shared_world = Some(world);
    }
    // CLOCK_REALTIME − CLOCK_MONOTONIC, re-read every second: the world is recorded on the
    // camera's clock (CLOCK_MONOTONIC) at each SYNC's kernel receive time (CLOCK_REALTIME).
    let mut clock_offset = (hw_io::frame::realtime_minus_monotonic_ns(), Instant::now());
    // Like fulcrumd: a receive queue for bursts (a flood of foreign frames must not push the
    // controller's SYNCs out of a full default queue).
    if let Err(e) = bus.set_receive_buffer(4 << 20) {
        eprintln!("simrobot live: cannot enlarge the CAN receive queue ({e}); frames may be dropped in bursts");
    }
    let truth_file = match &args.truth {
        Some(path) => {
            Some((path.clone(), File::create(path).map_err(|source| LiveError::Create { path: path.clone(), source })?))
        }
        None => None,
    };
    let mut truth_file = truth_file;
    let mut truth: Option<(PathBuf, TruthWriter<BufWriter<File>>)> = None;
    let endoscope = if config.endoscope_arm.enabled {
        format!(
            " and endoscope arm nodes {:?} (every {}th SYNC)",
            config.endoscope_arm.node_ids, config.endoscope_arm.transmission_type
        )
    } else {
        String::new()
    };
    outln!(
        "simrobot live: {} answering SYNC (0x080) as nodes {:?}{endoscope}, seed {}, {} cycles{}",
        args.iface,
        config.encoder.node_ids,
        config.scenario.seed,
        config.scenario.cycles,
        if config.endless { ", endless" } else { "" }
    )
    .map_err(LiveError::Stdout)?;
    let mut counts = LiveCounts::default();
    let mut counter_check = SyncCounter::new();
    let mut seed = robot.scenario_seed();
    let mut first_sync_us: Option<u64> = None;
    // Kernel drops on our socket are reported when they happen, at most every 10 s.
    let mut drops_reported = (0u64, Instant::now());
    let result = loop {
        let drops = bus.dropped_rx_frames();
        if drops != drops_reported.0 && drops_reported.1.elapsed() >= Duration::from_secs(10) {
            eprintln!(
                "simrobot live: {} CAN frames dropped by the kernel (receive queue full), {drops} in all",
                drops - drops_reported.0
            );
            drops_reported = (drops, Instant::now());
        }
        if STOP.load(Ordering::SeqCst) {
            break outln!("simrobot live: stopped by signal").map_err(LiveError::Stdout);
        }
        let rx = match bus.recv_timeout(Duration::from_millis(100)) {
            Ok(Some(rx)) => rx,
            Ok(None) => continue,
            Err(RecvError::ErrorFrame(_)) => {
                counts.error_frames += 1;
                continue;
            }
            Err(RecvError::NotClassicCan) => {
                counts.ignored += 1;
                continue;
            }
            Err(e) => break Err(LiveError::Recv(e)),
        };
        if rx.frame.id() != CanId::Standard(SYNC_COB_ID) {
            counts.ignored += 1;
            continue;
        }
        let counter = match Message::decode(&rx.frame) {
            Ok(Message::Sync { counter }) => counter,
            _ => {
                counts.bad_syncs += 1;
                continue;
            }
        };
        if counter_check.observe(counter).is_err() {
            counts.sync_gaps += 1;
        }
        let t_us = if args.twin_clock {
            first_sync_us.get_or_insert(rx.unix_time_us).saturating_add(counts.syncs.saturating_mul(SYNC_PERIOD_US))
        } else {
            rx.unix_time_us
        };
        let frames = match robot.on_sync(counter, t_us) {
            Ok(Some(frames)) => frames,
            Ok(None) => {
                break outln!("simrobot live: scenario over").map_err(LiveError::Stdout);
            }
            Err(e) => break Err(e.into()),
        };
        if let Some(world) = &shared_world {
            if clock_offset.1.elapsed() >= Duration::from_secs(1) {
                clock_offset = (hw_io::frame::realtime_minus_monotonic_ns(), Instant::now());
            }
            let t_mono_ns = (i128::from(rx.unix_time_us) * 1000 - clock_offset.0).max(0) as u64;
            match sim::live_camera::lock(world).record(t_mono_ns, &robot) {
                Ok(_) => {
                    counts.world_samples += 1;
                    counts.world_first_mono_ns.get_or_insert(t_mono_ns);
                    counts.world_last_mono_ns = Some(t_mono_ns);
                }
                Err(_) => counts.world_refused += 1,
            }
        }
        for f in &frames {
            match bus.send(&f.frame) {
                Ok(()) => counts.frames_sent += 1,
                Err(e) => {
                    counts.send_errors += 1;
                    counts.last_send_error = Some(e.to_string());
                }
            }
        }
        counts.syncs += 1;
        if let Some((path, file)) = truth_file.take() {
            let mut header = TruthHeader::new(&config.scenario, t_us, args.state_every);
            header.twin = Some(config.clone());
            let writer = TruthWriter::new(BufWriter::new(file), &header)
                .map_err(|source| LiveError::Truth { path: path.clone(), source });
            match writer {
                Ok(mut w) => {
                    let start = ScenarioStart { sample: 0, seed };
                    if let Err(source) = w.scenario(start) {
                        break Err(LiveError::Truth { path, source });
                    }
                    truth = Some((path, w));
                }
                Err(e) => break Err(e),
            }
        }
        if robot.scenario_seed() != seed {
            seed = robot.scenario_seed();
            if let Err(e) = outln!(
                "simrobot live: next scenario, seed {seed}, starts at sample {} after a transition",
                robot.scenario_start_sample()
            ) {
                break Err(LiveError::Stdout(e));
            }
            if let Some((path, w)) = truth.as_mut()
                && let Err(source) = w.scenario(ScenarioStart { sample: robot.scenario_start_sample(), seed })
            {
                break Err(LiveError::Truth { path: path.clone(), source });
            }
        }
        if let Some((path, w)) = truth.as_mut()
            && let Err(source) = w.sample(t_us, robot.truth(), robot.events())
        {
            break Err(LiveError::Truth { path: path.clone(), source });
        }
        if robot.endoscope_tpdos_sent() {
            counts.endoscope_tpdo_syncs += 1;
            if let (Some((path, w)), Some(joints), Some(sample)) =
                (truth.as_mut(), robot.endoscope_joints(), robot.sample())
                && let Err(source) = w.endoscope(&EndoscopeRecord { sample, unix_time_us: t_us, joints })
            {
                break Err(LiveError::Truth { path: path.clone(), source });
            }
        }
        counts.events += robot.events().len() as u64;
        if let Err(e) = robot.events().iter().try_for_each(print_event) {
            break Err(LiveError::Stdout(e));
        }
    };
    counts.dropped_rx_frames = bus.dropped_rx_frames();
    let mut result = result;
    if let Some(camera) = camera {
        match camera.stop() {
            Ok(c) => {
                let _ = outln!(
                    "simrobot live: camera published {} frames, skipped {} (the renderer was late), {} rendered \
                     before the SYNCs covered their exposure, {} errors",
                    c.published,
                    c.skipped,
                    c.uncovered,
                    c.errors
                );
                counts.camera = Some(c);
            }
            Err(e) => result = result.and(Err(e.into())),
        }
    }
    // The files are finished whatever happened to the standard output; the first failed write
    // to it (a closed pipe) is the result if nothing else failed.
    let mut printed = Ok(());
    if let Some((path, w)) = truth {
        match w.finish() {
            Ok(_) => printed = outln!("simrobot live: ground truth in {}", path.display()),
            Err(source) => eprintln!("simrobot live: error: {}: {source}", path.display()),
        }
    }
    let summary = outln!(
        "simrobot live: {} SYNCs answered, {} frames sent, {} send errors, {} true events, {} SYNC counter gaps, \
         {} bad SYNCs, {} other frames ignored, {} error frames, {} frames dropped by the kernel (receive queue full)",
        counts.syncs,
        counts.frames_sent,
        counts.send_errors,
        counts.events,
        counts.sync_gaps,
        counts.bad_syncs,
        counts.ignored,
        counts.error_frames,
        counts.dropped_rx_frames
    );
    printed = printed.and(summary);
    if let Some(e) = &counts.last_send_error {
        printed = printed.and(outln!("simrobot live: last send error: {e}"));
    }
    if let Some(path) = &args.summary_json {
        let written =
            serde_json::to_string_pretty(&counts).map_err(io::Error::from).and_then(|text| std::fs::write(path, text));
        if let Err(source) = written {
            let _ = io::stdout().flush();
            return Err(LiveError::Create { path: path.clone(), source });
        }
    }
    let _ = io::stdout().flush();
    result.and(printed.map_err(LiveError::Stdout))
}
