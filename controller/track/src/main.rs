//! `comanip-track`: particle-filter tool tracking (`docs/tracking.md`).

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use comanip_track::config::TrackFile;
use comanip_track::experiment::{self, ConvergeResults, RatePoint};
use comanip_track::input::{Sequence, read_sequence};
use comanip_track::robustness::{self, NoiseLevel, NoiseSweep, SceneRun};
use comanip_track::run::{RunOptions, build_model, mode_name, track, write_jsonl};
use track::Mode;

#[derive(Parser)]
#[command(
    name = "comanip-track",
    version,
    about = "Particle-filter tool tracking from stereo frames and the arm's encoders"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum ModeArg {
    /// The paper's method, faithful.
    Paper,
    /// Ours.
    Ours,
}

impl From<ModeArg> for Mode {
    fn from(m: ModeArg) -> Self {
        match m {
            ModeArg::Paper => Mode::Paper,
            ModeArg::Ours => Mode::Ours,
        }
    }
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum FormatArg {
    /// One JSON object per line.
    Json,
    /// One fixed-width text line per sample.
    Text,
}

#[derive(clap::Args)]
struct Common {
    /// Tracker configuration (TOML, configs/comanip-track.toml).
    #[arg(long)]
    config: Option<PathBuf>,
    /// fulcrumd's configuration (the tool arm's encoders and kinematics); default: its defaults.
    #[arg(long)]
    fulcrumd_config: Option<PathBuf>,
    /// Measurement and filter (overrides the configuration's `mode`).
    #[arg(long, value_enum)]
    mode: Option<ModeArg>,
    /// Particles (overrides the configuration).
    #[arg(long)]
    particles: Option<usize>,
    /// Threads of the particle loops, the tracking thread included (overrides the
    /// configuration's `threads`; 0: the processors available to the process).
    #[arg(long)]
    threads: Option<usize>,
}

#[derive(Subcommand)]
enum Command {
    /// Track a recorded sequence offline: one JSON line per frame.
    Run {
        /// The frames directory (frames.txt, PNGs, truth.jsonl).
        #[arg(long)]
        frames: PathBuf,
        /// The candump log of the bus (both arms).
        #[arg(long)]
        candump: PathBuf,
        /// The left and right eyes' camera_info YAML.
        #[arg(long, num_args = 2, value_names = ["LEFT", "RIGHT"])]
        cameras: Vec<PathBuf>,
        /// Output, JSON Lines.
        #[arg(long)]
        out: PathBuf,
        /// Write overlays (PNG) into this directory.
        #[arg(long)]
        overlay: Option<PathBuf>,
        /// First frame.
        #[arg(long, default_value_t = 0)]
        first: usize,
        /// Frames to track (default: all).
        #[arg(long)]
        count: Option<usize>,
        #[command(flatten)]
        common: Common,
    },
    /// The live process: frames from the frame service, both arms' joints from the bus, the
    /// calibration from `comanip-calib live`; one TrackSample per frame on the track service.
    Live {
        #[command(flatten)]
        args: comanip_track::live_cli::LiveArgs,
        #[command(flatten)]
        common: Common,
    },
    /// Convergence from perturbed starts (the paper's protocol) on `simrobot generate --frames`
    /// runs; writes the trials as JSON.
    Converge {
        /// Run directories (DIR/bus.log, DIR/frames).
        #[arg(long, required = true, num_args = 1..)]
        run: Vec<PathBuf>,
        /// Trials per run.
        #[arg(long, default_value_t = 10)]
        trials: usize,
        /// Frames per trial.
        #[arg(long, default_value_t = 15)]
        frames_per_trial: usize,
        /// Initial tip position error, millimetres.
        #[arg(long, default_value_t = 13.0)]
        pos_mm: f64,
        /// Initial orientation error, degrees.
        #[arg(long, default_value_t = 10.0)]
        rot_deg: f64,
        /// Seed of the starts.
        #[arg(long, default_value_t = 7)]
        seed: u64,
        /// Fewest instrument pixels in each eye for a frame to be used.
        #[arg(long, default_value_t = 400)]
        min_px: u64,
        /// Output (JSON).
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        common: Common,
    },
    /// Frames per second against particle count on a run's frames.
    Rate {
        /// Run directory.
        #[arg(long)]
        run: PathBuf,
        /// Particle counts.
        #[arg(long, num_args = 1.., default_values_t = [100usize, 250, 500, 1000, 2000])]
        counts: Vec<usize>,
        /// Frames per count.
        #[arg(long, default_value_t = 10)]
        frames: usize,
        /// Output (JSON, appended to when it exists).
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        common: Common,
    },
    /// Joint-sensor noise (the paper's Fig. 10-11): `converge`'s trials with Gaussian noise
    /// added to every encoder reading the tracker gets, at each level; writes the sweep as
    /// JSON.
    Noise {
        /// Run directories (DIR/bus.log, DIR/frames).
        #[arg(long, required = true, num_args = 1..)]
        run: Vec<PathBuf>,
        /// Noise levels: standard deviation per joint, milliradians.
        #[arg(long, num_args = 1.., default_values_t = [0.0f64, 2.0, 5.0, 10.0])]
        sigmas_mrad: Vec<f64>,
        /// Trials per run and level.
        #[arg(long, default_value_t = 5)]
        trials: usize,
        /// Frames per trial.
        #[arg(long, default_value_t = 20)]
        frames_per_trial: usize,
        /// Initial tip position error, millimetres (0: particles started at the truth).
        #[arg(long, default_value_t = 13.0)]
        pos_mm: f64,
        /// Initial orientation error, degrees.
        #[arg(long, default_value_t = 10.0)]
        rot_deg: f64,
        /// Seed of the starts (the same starts at every level).
        #[arg(long, default_value_t = 7)]
        seed: u64,
        /// Fewest instrument pixels in each eye for a frame to be used.
        #[arg(long, default_value_t = 400)]
        min_px: u64,
        /// Output (JSON).
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        common: Common,
    },
    /// Scene conditions (second instrument, smoke, occluder windows from `simrobot generate
    /// --second-instrument / --occlude`, realism.smoke): each run tracked over the frames
    /// where the instrument is in view; summaries, loss and recovery per occluder window;
    /// appends to the JSON output.
    Scenes {
        /// `CONDITION=DIR` pairs (DIR: a `simrobot generate --frames` output).
        #[arg(long, required = true, num_args = 1..)]
        run: Vec<String>,
        /// Fewest instrument pixels (unoccluded) in each eye for a frame to be tracked.
        #[arg(long, default_value_t = 400)]
        min_px: u64,
        /// Output (JSON, appended to when it exists: one entry per condition, sequence, mode).
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        common: Common,
    },
    /// Subscribe to the tracking service (what `live` publishes) and print every sample, one
    /// line each, as any consumer receives it (refused samples on standard error); a summary
    /// (samples per status, refused, missed, restarts, latency) on standard error at the end.
    /// Stops at SIGINT/SIGTERM, after `--count` samples or `--idle-timeout-s`; exits non-zero
    /// when it stopped idle without a sample.
    Monitor {
        /// The tracking service.
        #[arg(long, default_value = hw_io::ipc::DEFAULT_TRACK_SERVICE)]
        service: String,
        /// Line format: `json` (the `live --samples-jsonl` object) or `text`.
        #[arg(long, value_enum, default_value = "text")]
        format: FormatArg,
        /// Output; default: standard output.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Stop after this many samples.
        #[arg(long)]
        count: Option<u64>,
        /// Stop when nothing arrived for this many seconds.
        #[arg(long)]
        idle_timeout_s: Option<f64>,
        /// Write the summary as JSON to this file as well.
        #[arg(long)]
        summary_json: Option<PathBuf>,
    },
    /// The camera-to-base calibration off by known errors (`T_b_e` moved about the endoscope's
    /// RCM in a random direction per trial): the kinematics alone and the tracker against the
    /// truth in the camera frame (docs/tracking.md, "When the calibration is off").
    CalibError {
        /// Run directories (DIR/bus.log, DIR/frames).
        #[arg(long, required = true, num_args = 1..)]
        run: Vec<PathBuf>,
        /// Calibration errors, `MM:DEG` (translation millimetres, rotation degrees), each a level.
        #[arg(long, required = true, num_args = 1..)]
        levels: Vec<String>,
        /// Also run with `g_CB` in the state (the paper's Eq. 17-18): `MRAD:MM` per frame.
        #[arg(long)]
        augment: Option<String>,
        /// Trials per run and level.
        #[arg(long, default_value_t = 5)]
        trials: usize,
        /// Frames per trial.
        #[arg(long, default_value_t = 20)]
        frames_per_trial: usize,
        /// Seed of the starts and the error directions.
        #[arg(long, default_value_t = 21)]
        seed: u64,
        /// Fewest instrument pixels in each eye for a frame to be used.
        #[arg(long, default_value_t = 400)]
        min_px: u64,
        /// Output (JSON): every run's trials.
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        common: Common,
    },
    /// Summaries and plots from `converge` and `rate` outputs.
    Report {
        /// `converge` outputs.
        #[arg(long, num_args = 1..)]
        converge: Vec<PathBuf>,
        /// `rate` output.
        #[arg(long)]
        rate: Option<PathBuf>,
        /// Frames at the end of each converged trial counted as "after convergence".
        #[arg(long, default_value_t = 5)]
        tail: usize,
        /// Plot directory.
        #[arg(long)]
        plots: PathBuf,
        /// `noise` outputs for one plot (Fig. 10 style: error against the level), one per
        /// mode; the plot is named after the first file's stem.
        #[arg(long, num_args = 1..)]
        noise: Vec<PathBuf>,
        /// `noise` outputs for one plot of the error per frame (Fig. 11 style).
        #[arg(long, num_args = 1..)]
        noise_frames: Vec<PathBuf>,
        /// `scenes` output: tables and one plot per condition and sequence.
        #[arg(long)]
        scenes: Option<PathBuf>,
    },
}

/// A progress bar on standard error counting `total` `unit`s (`frames`, `trials`), with the
/// bar's message (`set_message`) before it; hidden when standard error is not a terminal
/// (CI, output sent to a file).
fn bar(total: u64, unit: &str) -> indicatif::ProgressBar {
    if !std::io::stderr().is_terminal() {
        return indicatif::ProgressBar::hidden();
    }
    let b = indicatif::ProgressBar::new(total);
    let template = format!("{{msg}} {{bar:40}} {{pos}}/{{len}} {unit} {{elapsed}} (eta {{eta}})");
    if let Ok(style) = indicatif::ProgressStyle::with_template(&template) {
        b.set_style(style);
    }
    b
}

fn setup(common: &Common) -> Result<(TrackFile, controller::config::Config), String> {
    let mut file = match &common.config {
        Some(p) => TrackFile::load(p).map_err(|e| e.to_string())?,
        None => TrackFile::default(),
    };
    if let Some(m) = common.mode {
        file.mode = m.into();
    }
    if let Some(n) = common.particles {
        file.particles = Some(n);
    }
    if let Some(n) = common.threads {
        file.threads = Some(n);
    }
    let fcfg = match &common.fulcrumd_config {
        Some(p) => controller::config::Config::load(p).map_err(|e| e.to_string())?,
        None => controller::config::Config::default(),
    };
    Ok((file, fcfg))
}

fn open_run(dir: &Path, fcfg: &controller::config::Config) -> Result<Sequence, String> {
    let f = dir.join("frames");
    read_sequence(&f, &dir.join("bus.log"), [&f.join("left.yaml"), &f.join("right.yaml")], fcfg)
        .map_err(|e| e.to_string())
}

fn size(seq: &Sequence) -> (usize, usize) {
    (seq.intrinsics[0].width as usize, seq.intrinsics[0].height as usize)
}

/// Two positive numbers `A:B`.
fn pair(what: &str, s: &str) -> Result<(f64, f64), String> {
    let bad = || format!("{what}: `{s}` is not two numbers ≥ 0 as A:B");
    let (a, b) = s.split_once(':').ok_or_else(bad)?;
    let (a, b): (f64, f64) = (a.trim().parse().map_err(|_| bad())?, b.trim().parse().map_err(|_| bad())?);
    if !(a.is_finite() && b.is_finite() && a >= 0.0 && b >= 0.0) {
        return Err(bad());
    }
    Ok((a, b))
}

/// `comanip-track calib-error` (`comanip_track::calib_error`).
#[allow(clippy::too_many_arguments, reason = "the subcommand's options")]
fn calib_error(
    runs: &[PathBuf],
    levels: &[String],
    augment: Option<&str>,
    trials: usize,
    frames: usize,
    seed: u64,
    min_px: u64,
    out: &Path,
    common: &Common,
) -> Result<(), String> {
    use comanip_track::calib_error::{CalibErrorLevel, CalibErrorRun, run_level, summarise};
    let (file, fcfg) = setup(common)?;
    let levels: Vec<CalibErrorLevel> = levels
        .iter()
        .map(|l| {
            pair("--levels", l)
                .map(|(mm, deg)| CalibErrorLevel { translation_m: mm * 1e-3, rotation_rad: deg.to_radians() })
        })
        .collect::<Result<_, _>>()?;
    let augment = augment.map(|a| pair("--augment", a).map(|(mrad, mm)| [mrad * 1e-3, mm * 1e-3])).transpose()?;
    let seqs: Vec<(String, Sequence)> = runs
        .iter()
        .map(|dir| {
            let label = dir.file_name().map_or_else(|| dir.display().to_string(), |n| n.to_string_lossy().into());
            open_run(dir, &fcfg).map(|s| (label, s))
        })
        .collect::<Result<_, _>>()?;
    let configs = 1 + usize::from(augment.is_some());
    let b = bar((levels.len() * configs * seqs.len() * trials * frames) as u64, "frames");
    let mut all = Vec::new();
    for level in &levels {
        for c in 0..configs {
            let mut trials_out = Vec::new();
            let mut particles = 0;
            let mut name = String::new();
            for (k, (label, seq)) in seqs.iter().enumerate() {
                let model = build_model(seq, &file.tool, &fcfg).map_err(|e| e.to_string())?;
                let (w, h) = size(seq);
                let mut cfg = file.tracker(w, h);
                if c == 1 {
                    cfg.camera_noise = augment;
                }
                particles = cfg.particles;
                name = format!("{}{}", mode_name(cfg.mode), if cfg.camera_noise.is_some() { " + g_CB" } else { "" });
                let t =
                    run_level(seq, label, &model, cfg, *level, trials, frames, seed + k as u64, min_px, &|| b.inc(1))
                        .map_err(|e| e.to_string())?;
                trials_out.extend(t);
            }
            all.push(CalibErrorRun { level: *level, config: name, particles, trials: trials_out });
        }
    }
    b.finish_and_clear();
    println!(
        "| error (mm / °) | config | trials | kinematics mm median / p95 | tracker mm median / p95 | kinematics ° median | tracker ° median | tracker closer | LOST |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for r in &all {
        let s = summarise(r);
        println!(
            "| {:.1} / {:.1} | {} | {} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} | {:.2} | {} / {} | {} |",
            s.error_mm,
            s.error_deg,
            s.config,
            s.trials,
            s.kinematics_mm.0,
            s.kinematics_mm.1,
            s.tracker_mm.0,
            s.tracker_mm.1,
            s.kinematics_deg.0,
            s.tracker_deg.0,
            s.tracker_closer,
            s.frames,
            s.lost
        );
    }
    std::fs::write(out, serde_json::to_string(&all).map_err(|e| e.to_string())?)
        .map_err(|e| format!("{}: {e}", out.display()))
}

/// `comanip-track monitor` (`comanip_track::monitor`).
fn monitor(
    service: &str,
    format: FormatArg,
    out: Option<&Path>,
    count: Option<u64>,
    idle_timeout_s: Option<f64>,
    summary_json: Option<&Path>,
) -> Result<(), String> {
    use comanip_track::monitor::{MonitorFormat, MonitorOptions, StopReason};
    let idle_timeout = match idle_timeout_s {
        Some(s) if s.is_finite() && s > 0.0 => Some(std::time::Duration::from_secs_f64(s)),
        Some(s) => return Err(format!("--idle-timeout-s must be a positive number of seconds, not {s}")),
        None => None,
    };
    controller::process::install_stop_handlers();
    let mut sub =
        hw_io::ipc::Subscriber::<hw_io::ipc::TrackSample>::connect(service).map_err(|e| format!("{service}: {e}"))?;
    let mut w: Box<dyn std::io::Write> = match out {
        Some(p) => {
            Box::new(std::io::BufWriter::new(std::fs::File::create(p).map_err(|e| format!("{}: {e}", p.display()))?))
        }
        None => Box::new(std::io::stdout().lock()),
    };
    eprintln!("comanip-track monitor: subscribed to {service}");
    let opts = MonitorOptions {
        format: match format {
            FormatArg::Json => MonitorFormat::Json,
            FormatArg::Text => MonitorFormat::Text,
        },
        count,
        idle_timeout,
    };
    let summary = comanip_track::monitor::monitor(&mut sub, &opts, &mut w, &controller::process::STOP)
        .map_err(|e| format!("{service}: {e}"))?;
    let ms = |v: Option<f64>| v.map_or_else(|| "-".to_string(), |v| format!("{v:.2}"));
    eprintln!(
        "comanip-track monitor: {} samples (TRACKING {}, UNCERTAIN {}, LOST {}, INVALID {}), {} refused, {} missed, {} restarts, latency p50 {} ms p99 {} ms, stopped: {:?}",
        summary.received,
        summary.tracking,
        summary.uncertain,
        summary.lost,
        summary.invalid,
        summary.refused,
        summary.missed,
        summary.restarts,
        ms(summary.latency_ms_p50),
        ms(summary.latency_ms_p99),
        summary.stopped
    );
    if let Some(p) = summary_json {
        let text = serde_json::to_string_pretty(&summary).map_err(|e| e.to_string())?;
        std::fs::write(p, text + "\n").map_err(|e| format!("{}: {e}", p.display()))?;
    }
    if summary.stopped == StopReason::Idle && summary.received == 0 && summary.refused == 0 {
        return Err(format!("{service}: nothing received within the idle timeout"));
    }
    Ok(())
}

fn main() -> ExitCode {
    controller::process::init_logging();
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("comanip-track: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<(), String> {
    match cli.command {
        Command::Run { frames, candump, cameras, out, overlay, first, count, common } => {
            let (file, fcfg) = setup(&common)?;
            let [l, r] = cameras.as_slice() else { return Err("--cameras takes LEFT RIGHT".into()) };
            let seq = read_sequence(&frames, &candump, [l, r], &fcfg).map_err(|e| e.to_string())?;
            let model = build_model(&seq, &file.tool, &fcfg).map_err(|e| e.to_string())?;
            let (w, h) = size(&seq);
            let cfg = file.tracker(w, h);
            if let Some(d) = &overlay {
                std::fs::create_dir_all(d).map_err(|e| format!("{}: {e}", d.display()))?;
            }
            let n = count.unwrap_or(usize::MAX);
            let b = bar(seq.frames.len().saturating_sub(first).min(n) as u64, "frames");
            let res = track(
                &seq,
                &model,
                cfg,
                &RunOptions {
                    first,
                    count: n,
                    start_joints: None,
                    overlay: overlay.as_deref(),
                    progress: &|k| b.set_position(k as u64),
                    encoder_noise: None,
                },
            )
            .map_err(|e| e.to_string())?;
            b.finish_and_clear();
            write_jsonl(&out, &res).map_err(|e| e.to_string())?;
            let tracked = res.iter().filter(|r| r.status == "TRACKING").count();
            let lost = res.iter().filter(|r| r.status == "LOST").count();
            let mut errs: Vec<f64> = res.iter().filter_map(|r| r.error_mm).collect();
            let (med, p95) = experiment::median_p95(&mut errs);
            let mean_ms = res.iter().map(|r| r.step_ms).sum::<f64>() / res.len().max(1) as f64;
            println!(
                "comanip-track run ({}, {} particles): {} frames, {} TRACKING, {} LOST; tip error vs truth median {:.2} mm, p95 {:.2} mm; {:.1} ms per frame; {}",
                mode_name(cfg.mode),
                cfg.particles,
                res.len(),
                tracked,
                lost,
                med,
                p95,
                mean_ms,
                out.display()
            );
            Ok(())
        }
        Command::Live { args, common } => {
            let (file, fcfg) = setup(&common)?;
            comanip_track::live_cli::run(&file, &fcfg, &args).map_err(|e| e.to_string())
        }
        Command::Monitor { service, format, out, count, idle_timeout_s, summary_json } => {
            monitor(&service, format, out.as_deref(), count, idle_timeout_s, summary_json.as_deref())
        }
        Command::Converge { run, trials, frames_per_trial, pos_mm, rot_deg, seed, min_px, out, common } => {
            let (file, fcfg) = setup(&common)?;
            let mut all = Vec::new();
            let mut cfg0 = None;
            let b = bar((trials * run.len() * frames_per_trial) as u64, "frames");
            for (k, dir) in run.iter().enumerate() {
                let seq = open_run(dir, &fcfg)?;
                let model = build_model(&seq, &file.tool, &fcfg).map_err(|e| e.to_string())?;
                let (w, h) = size(&seq);
                let cfg = file.tracker(w, h);
                cfg0 = Some(cfg);
                let label = dir.file_name().map_or_else(|| dir.display().to_string(), |n| n.to_string_lossy().into());
                b.set_message(label.clone());
                let t = experiment::converge(
                    &seq,
                    &label,
                    &model,
                    cfg,
                    trials,
                    frames_per_trial,
                    pos_mm * 1e-3,
                    rot_deg.to_radians(),
                    seed + k as u64,
                    min_px,
                    0.0,
                    &|| b.inc(1),
                )
                .map_err(|e| e.to_string())?;
                all.extend(t);
            }
            b.finish_and_clear();
            let cfg = cfg0.ok_or("no run")?;
            let res = ConvergeResults::of_trials(&cfg, all);
            let s = experiment::summarise(&res, 5);
            println!("{}", serde_json::to_string_pretty(&s).unwrap_or_default());
            std::fs::write(&out, serde_json::to_string(&res).unwrap_or_default())
                .map_err(|e| format!("{}: {e}", out.display()))
        }
        Command::CalibError { run, levels, augment, trials, frames_per_trial, seed, min_px, out, common } => {
            calib_error(&run, &levels, augment.as_deref(), trials, frames_per_trial, seed, min_px, &out, &common)
        }
        Command::Rate { run, counts, frames, out, common } => {
            let (file, fcfg) = setup(&common)?;
            let seq = open_run(&run, &fcfg)?;
            let model = build_model(&seq, &file.tool, &fcfg).map_err(|e| e.to_string())?;
            let (w, h) = size(&seq);
            let first = seq.frames.iter().position(|f| f.truth.is_some_and(|t| t.instrument_px[0] > 400)).unwrap_or(0);
            let mut points: Vec<RatePoint> =
                std::fs::read_to_string(&out).ok().and_then(|t| serde_json::from_str(&t).ok()).unwrap_or_default();
            let b = bar((counts.len() * (frames + 1)) as u64, "frames");
            for n in counts {
                b.set_message(format!("{n} particles"));
                let mut cfg = file.tracker(w, h);
                cfg.particles = n;
                let res = track(
                    &seq,
                    &model,
                    cfg,
                    &RunOptions {
                        first,
                        count: frames + 1,
                        start_joints: None,
                        overlay: None,
                        progress: &|_| b.inc(1),
                        encoder_noise: None,
                    },
                )
                .map_err(|e| e.to_string())?;
                // The first frame initialises (and warms the caches): not counted.
                let mut ms: Vec<f64> = res.iter().skip(1).filter(|r| r.step_ms > 0.0).map(|r| r.step_ms).collect();
                let (med, _) = experiment::median_p95(&mut ms);
                b.suspend(|| {
                    println!(
                        "{} {n} particles: median {med:.1} ms per frame = {:.2} fps",
                        mode_name(cfg.mode),
                        1e3 / med
                    );
                });
                points.retain(|p| !(p.mode == mode_name(cfg.mode) && p.particles == n));
                points.push(RatePoint { mode: mode_name(cfg.mode).into(), particles: n, step_ms: med, fps: 1e3 / med });
            }
            b.finish_and_clear();
            points.sort_by(|a, b| (a.mode.as_str(), a.particles).cmp(&(b.mode.as_str(), b.particles)));
            std::fs::write(&out, serde_json::to_string_pretty(&points).unwrap_or_default())
                .map_err(|e| format!("{}: {e}", out.display()))
        }
        Command::Noise { run, sigmas_mrad, trials, frames_per_trial, pos_mm, rot_deg, seed, min_px, out, common } => {
            let (file, fcfg) = setup(&common)?;
            let mut seqs = Vec::new();
            for dir in &run {
                let seq = open_run(dir, &fcfg)?;
                let model = build_model(&seq, &file.tool, &fcfg).map_err(|e| e.to_string())?;
                let label = dir.file_name().map_or_else(|| dir.display().to_string(), |n| n.to_string_lossy().into());
                seqs.push((seq, model, label));
            }
            let b = bar((trials * run.len() * sigmas_mrad.len() * frames_per_trial) as u64, "frames");
            let mut levels = Vec::new();
            for &sigma in &sigmas_mrad {
                if !(sigma.is_finite() && sigma >= 0.0) {
                    return Err(format!("--sigmas-mrad {sigma}: must be finite and >= 0"));
                }
                b.set_message(format!("σ {sigma} mrad"));
                let mut all = Vec::new();
                let mut cfg0 = None;
                for (k, (seq, model, label)) in seqs.iter().enumerate() {
                    let (w, h) = size(seq);
                    let cfg = file.tracker(w, h);
                    cfg0 = Some(cfg);
                    let t = experiment::converge(
                        seq,
                        label,
                        model,
                        cfg,
                        trials,
                        frames_per_trial,
                        pos_mm * 1e-3,
                        rot_deg.to_radians(),
                        seed + k as u64,
                        min_px,
                        sigma * 1e-3,
                        &|| b.inc(1),
                    )
                    .map_err(|e| e.to_string())?;
                    all.extend(t);
                }
                let cfg = cfg0.ok_or("no run")?;
                let res = ConvergeResults::of_trials(&cfg, all);
                let sm = experiment::summarise(&res, 5);
                b.suspend(|| println!("sigma {sigma} mrad: {}", serde_json::to_string(&sm).unwrap_or_default()));
                levels.push(NoiseLevel { sigma_mrad: sigma, results: res });
            }
            b.finish_and_clear();
            let sweep = NoiseSweep { pos_mm, rot_deg, levels };
            std::fs::write(&out, serde_json::to_string(&sweep).unwrap_or_default())
                .map_err(|e| format!("{}: {e}", out.display()))
        }
        Command::Scenes { run, min_px, out, common } => {
            let (file, fcfg) = setup(&common)?;
            let mut runs: Vec<SceneRun> =
                std::fs::read_to_string(&out).ok().and_then(|t| serde_json::from_str(&t).ok()).unwrap_or_default();
            for pair in &run {
                let Some((condition, dir)) = pair.split_once('=') else {
                    return Err(format!("--run {pair}: expected CONDITION=DIR"));
                };
                let dir = PathBuf::from(dir);
                let seq = open_run(&dir, &fcfg)?;
                let model = build_model(&seq, &file.tool, &fcfg).map_err(|e| e.to_string())?;
                let (w, h) = size(&seq);
                let cfg = file.tracker(w, h);
                let label = dir.file_name().map_or_else(|| dir.display().to_string(), |n| n.to_string_lossy().into());
                let b = bar(seq.frames.len() as u64, "frames");
                let r = robustness::scene(&seq, &label, condition, &model, cfg, min_px, &|k| b.set_position(k as u64))
                    .map_err(|e| e.to_string())?;
                b.finish_and_clear();
                println!("{}", serde_json::to_string(&robustness::summarise_condition(&r)).unwrap_or_default());
                for wsum in robustness::summarise_windows(&r) {
                    println!("{}", serde_json::to_string(&wsum).unwrap_or_default());
                }
                runs.retain(|x| !(x.condition == r.condition && x.sequence == r.sequence && x.mode == r.mode));
                runs.push(r);
            }
            std::fs::write(&out, serde_json::to_string(&runs).unwrap_or_default())
                .map_err(|e| format!("{}: {e}", out.display()))
        }
        Command::Report { converge, rate, tail, plots, noise, noise_frames, scenes } => {
            std::fs::create_dir_all(&plots).map_err(|e| format!("{}: {e}", plots.display()))?;
            let read_sweeps = |files: &[PathBuf]| -> Result<Vec<NoiseSweep>, String> {
                files
                    .iter()
                    .map(|p| {
                        let t = std::fs::read_to_string(p).map_err(|e| format!("{}: {e}", p.display()))?;
                        serde_json::from_str(&t).map_err(|e| format!("{}: {e}", p.display()))
                    })
                    .collect()
            };
            let stem = |files: &[PathBuf]| {
                files
                    .first()
                    .and_then(|p| p.file_stem())
                    .map_or_else(|| "noise".to_string(), |s| s.to_string_lossy().into())
            };
            if !noise.is_empty() {
                let sw = read_sweeps(&noise)?;
                for s in &sw {
                    for l in &s.levels {
                        let sm = experiment::summarise(&l.results, tail);
                        println!("noise {} mrad: {}", l.sigma_mrad, serde_json::to_string(&sm).unwrap_or_default());
                    }
                }
                let title = format!(
                    "Joint-sensor noise: starts {} mm / {}°, median tip error",
                    sw.first().map_or(0.0, |s| s.pos_mm),
                    sw.first().map_or(0.0, |s| s.rot_deg)
                );
                robustness::plot_noise(&plots.join(format!("{}.svg", stem(&noise))), &sw, tail, &title)
                    .map_err(|e| e.to_string())?;
            }
            if !noise_frames.is_empty() {
                let sw = read_sweeps(&noise_frames)?;
                for s in &sw {
                    for l in &s.levels {
                        let sm = experiment::summarise(&l.results, tail);
                        println!("noise {} mrad: {}", l.sigma_mrad, serde_json::to_string(&sm).unwrap_or_default());
                    }
                }
                robustness::plot_noise_frames(
                    &plots.join(format!("{}.svg", stem(&noise_frames))),
                    &sw,
                    "Trajectories from the truth under joint-sensor noise: median tip error",
                )
                .map_err(|e| e.to_string())?;
            }
            if let Some(p) = &scenes {
                let t = std::fs::read_to_string(p).map_err(|e| format!("{}: {e}", p.display()))?;
                let runs: Vec<SceneRun> = serde_json::from_str(&t).map_err(|e| format!("{}: {e}", p.display()))?;
                for r in &runs {
                    println!("{}", serde_json::to_string(&robustness::summarise_condition(r)).unwrap_or_default());
                    for wsum in robustness::summarise_windows(r) {
                        println!("{}", serde_json::to_string(&wsum).unwrap_or_default());
                    }
                }
                let mut keys: Vec<(String, String)> =
                    runs.iter().map(|r| (r.condition.clone(), r.sequence.clone())).collect();
                keys.sort();
                keys.dedup();
                for (c, sq) in keys {
                    let group: Vec<&SceneRun> = runs.iter().filter(|r| r.condition == c && r.sequence == sq).collect();
                    let name: String = format!("scene_{c}_{sq}")
                        .chars()
                        .map(|ch| if ch.is_ascii_alphanumeric() { ch } else { '_' })
                        .collect();
                    robustness::plot_scene(&plots.join(format!("{name}.svg")), &group, &format!("{c}, {sq}"))
                        .map_err(|e| e.to_string())?;
                }
            }
            let mut results = Vec::new();
            for p in &converge {
                let t = std::fs::read_to_string(p).map_err(|e| format!("{}: {e}", p.display()))?;
                let r: ConvergeResults = serde_json::from_str(&t).map_err(|e| format!("{}: {e}", p.display()))?;
                println!("{}", serde_json::to_string(&experiment::summarise(&r, tail)).unwrap_or_default());
                results.push(r);
            }
            if !results.is_empty() {
                let frames = results.iter().flat_map(|r| r.trials.iter().map(|t| t.errors.len())).max().unwrap_or(1);
                experiment::plot_convergence(&plots.join("convergence.svg"), &results, frames)
                    .map_err(|e| e.to_string())?;
            }
            if let Some(p) = rate {
                let t = std::fs::read_to_string(&p).map_err(|e| format!("{}: {e}", p.display()))?;
                let pts: Vec<RatePoint> = serde_json::from_str(&t).map_err(|e| format!("{}: {e}", p.display()))?;
                experiment::plot_rate(&plots.join("rate.svg"), &pts).map_err(|e| e.to_string())?;
            }
            Ok(())
        }
    }
}
