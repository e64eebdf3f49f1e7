//! `comanip-calib`: dual RCM-arm calibration from tool lines and encoders
//! (`docs/calibration.md`).

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use comanip_calib::detect::{DetectorChoice, detect_dir};
use comanip_calib::run::{Pipeline, all_failed, calibrate, default_protocol, generate};
use comanip_calib::sweep::{SweepOptions, run_sweep};
use sim::calib::NoiseUnits;

#[derive(Parser)]
#[command(name = "comanip-calib", version, about = "Dual RCM-arm calibration: simulate, calibrate, sweep")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum Units {
    /// ρ in millimetres (reproduces the paper's figures).
    Mm,
    /// ρ in metres (the hard case).
    M,
}

impl From<Units> for NoiseUnits {
    fn from(u: Units) -> Self {
        match u {
            Units::Mm => NoiseUnits::Millimetre,
            Units::M => NoiseUnits::Metre,
        }
    }
}

/// The protocol's grid and kinematic noise (`generate`, `pixels`).
#[derive(clap::Args)]
struct GridArgs {
    /// Values per ECM joint (n_e⁴ ECM poses).
    #[arg(long, default_value_t = 3)]
    n_e: usize,
    /// Values per PSM joint (n_t² PSM poses).
    #[arg(long, default_value_t = 3)]
    n_t: usize,
    /// Noise σ of δ = (ρ, φ).
    #[arg(long, default_value_t = 0.01)]
    sigma: f64,
    /// Unit of ρ.
    #[arg(long, value_enum, default_value = "mm")]
    units: Units,
}

#[derive(Subcommand)]
enum Command {
    /// Simulate a dataset with the paper's protocol and write it with its ground truth.
    Generate {
        /// Dataset file to write (JSON).
        #[arg(long)]
        dataset: PathBuf,
        /// Ground-truth file to write (JSON).
        #[arg(long)]
        truth: PathBuf,
        #[command(flatten)]
        grid: GridArgs,
        /// Pixel noise σ on the line points.
        #[arg(long, default_value_t = 0.0)]
        pixel_sigma: f64,
        /// Seed.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Fraction (0..=1) of the lines to replace by wrong ones (simulated detector errors;
        /// the truth file lists them).
        #[arg(long, default_value_t = 0.0)]
        wrong_lines: f64,
    },
    /// Calibrate: dataset → result file.
    ///
    /// Exit status: 0 when at least one requested pipeline produced a result, 1 when every
    /// requested pipeline failed (or an input is unreadable). A pipeline fails on degenerate
    /// or ambiguous data, and ours also when its selection-aware stage cannot model the data,
    /// unless --accept-unrefined. The result file lists every requested pipeline's result or
    /// its failure (`failures`), and is written in every case.
    Calibrate {
        /// Dataset file (JSON).
        #[arg(long)]
        dataset: PathBuf,
        /// Override the dataset's intrinsics with an OpenCV or ROS camera_info YAML file.
        #[arg(long)]
        intrinsics: Option<PathBuf>,
        /// Ground-truth file: print the errors of the result.
        #[arg(long)]
        truth: Option<PathBuf>,
        /// Result file to write (JSON).
        #[arg(long)]
        out: PathBuf,
        /// Also write the residual figure (SVG): the observed lines in the image coloured by
        /// their distance to the calibrated tool axis, and each pipeline's histogram.
        #[arg(long)]
        plot: Option<PathBuf>,
        /// Pipeline(s) to run (`both`: each runs whatever the other does).
        #[arg(long, value_enum, default_value = "both")]
        pipeline: Pipeline,
        /// Accept our pipeline's unrefined (border-guarded) estimate when its selection-aware
        /// stage cannot model the data (otherwise that is a failure of our pipeline).
        #[arg(long)]
        accept_unrefined: bool,
        /// Take the dataset's noise model as known up to a common scale: our pipeline solves,
        /// then solves again with every standard deviation multiplied by the fit's robust scale
        /// (written as `noise_scale`). For a noise model that is a guess (a live session's);
        /// the line fit does not depend on the scale, the shaft-position terms and the
        /// selection-aware stage do.
        #[arg(long)]
        estimate_noise_scale: bool,
        /// How often the selection-aware stage's move test may refuse a stage that is in fact
        /// consistent with the guarded fit: a probability in (0, 1), default 0.0001 (the χ²₆
        /// quantile 27.86 as the limit; nominal: the statistic's tail is heavier). Smaller
        /// refuses fewer good calibrations and lets larger moves through.
        #[arg(long, value_parser = parse_probability)]
        false_refusal_probability: Option<f64>,
        /// Search our pipeline's candidate solutions on every observation. By default a
        /// dataset of at least 480 observations is searched on 240 of them, spread over it,
        /// and the chosen solution and its runner-up are then refined and judged on all
        /// (written as `searched_on`); about half the solve time on 729 observations.
        #[arg(long)]
        search_on_all: bool,
    },
    /// Detect the instrument shaft's lines in a directory of images; write them as JSON.
    Detect {
        /// Images: an image-sequence directory (frames.txt) or a directory of PNG files.
        #[arg(long)]
        images: PathBuf,
        /// The camera: a ROS camera_info or OpenCV calibration YAML file (intrinsics and
        /// distortion; the images' size).
        #[arg(long)]
        camera: PathBuf,
        /// Lines file to write (JSON).
        #[arg(long, default_value = "lines.json")]
        out: PathBuf,
        /// Also write an overlay PNG per image into this directory (contours green, centreline
        /// blue, end points red).
        #[arg(long)]
        overlay: Option<PathBuf>,
        /// The detector.
        #[arg(long, value_enum, default_value = "ours")]
        detector: DetectorChoice,
        /// With frames.txt: the right eye's images instead of the left's.
        #[arg(long)]
        right: bool,
    },
    /// Calibration from pixels: the protocol's poses rendered by the simulated stereo
    /// endoscope, the lines detected (ours and the paper's detector), both pipelines run on
    /// them and on the exact lines of the same poses; writes pixels.md and the datasets.
    Pixels {
        /// Output directory.
        #[arg(long, default_value = "docs/calibration/pixels")]
        out_dir: PathBuf,
        /// The protocol's grid and noise (n_e 1..=4, n_t 1..=8 here).
        #[command(flatten)]
        grid: GridArgs,
        /// Seed of the kinematic noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Our pipeline's pixel σ of the detected lines, pixels (the truth lines have none);
        /// default: `live`'s.
        #[arg(long, default_value_t = comanip_calib::live_config::NoiseSection::default().pixel_px)]
        sigma_px: f64,
    },
    /// Calibration from a recorded run (`simrobot generate --frames`): both arms' joints from
    /// the candump log, matched to the stereo frames by time, the tool line detected in both
    /// eyes; both pipelines on truth, paper-detected and ours-detected lines.
    FromRun {
        /// The run's directory (bus.log, truth.jsonl, frames/).
        #[arg(long)]
        run: PathBuf,
        /// fulcrumd's configuration (TOML) for the tool arm's acquisition and estimation;
        /// default: the built-in one.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Use every K-th usable frame (K ≥ 1).
        #[arg(long, default_value_t = 1)]
        every: usize,
        /// Noise model: pixel σ of the lines, pixels (default: `live`'s).
        #[arg(long, default_value_t = 1.2)]
        sigma_px: f64,
        /// Noise model: rotation σ per axis of the camera and tool-line frames, milliradians
        /// (0 with --noise-mm 0: no arms' noise, and our pipeline uses the lines alone).
        #[arg(long, default_value_t = 4.0)]
        noise_mrad: f64,
        /// Noise model: translation σ per axis of the camera and tool-line frames, millimetres.
        #[arg(long, default_value_t = 1.2)]
        noise_mm: f64,
        /// Take the noise model as stated; by default it is known up to a scale our pipeline
        /// estimates (as `live` does: the model is a guess for a recorded run).
        #[arg(long)]
        noise_as_stated: bool,
        /// Output directory (from-run.md and the datasets).
        #[arg(long, default_value = "docs/calibration/from-run")]
        out_dir: PathBuf,
    },
    /// Live calibration (issue 19): collect observations while the team works, solve when
    /// the predicted precision reaches the target, write the result file, publish the
    /// calibration. Without `--replay`: the process on the bus (frames from the frame service,
    /// both arms from a passive CAN socket, the tool line from fulcrumd; settings in
    /// `--live-config`; SIGUSR1 asks for a solve now; SIGINT/SIGTERM stop it). `--replay DIR`
    /// runs the same loop in time order over a recorded run (`simrobot generate --frames`) and
    /// reports against the run's truth.
    Live {
        /// A recorded run's directory (bus.log, truth.jsonl, frames/). Without it: the live
        /// process on the bus.
        #[arg(long)]
        replay: Option<PathBuf>,
        /// The live process's settings (TOML, configs/comanip-calib.toml); default: the
        /// built-in ones (bus can0, simrobot's default endoscope).
        #[arg(long)]
        live_config: Option<PathBuf>,
        /// The live process: a JSON summary written at exit (counts, the first publication).
        #[arg(long)]
        summary_json: Option<PathBuf>,
        /// With --replay: fulcrumd's configuration (TOML); default: the built-in one.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Target: predicted RMS translation at the mean fulcrum, millimetres.
        #[arg(long, default_value_t = 1.0)]
        target_mm: f64,
        /// Target: predicted RMS rotation, degrees.
        #[arg(long, default_value_t = 0.2)]
        target_deg: f64,
        /// Noise model: pixel σ of the line points, pixels.
        #[arg(long, default_value_t = 1.2)]
        noise_px: f64,
        /// Noise model: rotation σ per axis of the camera and tool-line frames, milliradians.
        #[arg(long, default_value_t = 4.0)]
        noise_mrad: f64,
        /// Noise model: translation σ per axis of the camera and tool-line frames, millimetres.
        #[arg(long, default_value_t = 1.2)]
        noise_mm: f64,
        /// The versioned result file (JSON, with covariance).
        #[arg(long, default_value = "calibration-live.json")]
        out: PathBuf,
        /// The replay's report (Markdown).
        #[arg(long)]
        report: Option<PathBuf>,
        /// With --replay: write the observations kept at the end as a calibration dataset
        /// (`DIR/dataset.json`, with the noise model) and the run's truth (`DIR/truth.json`),
        /// to re-solve them with `calibrate`.
        #[arg(long)]
        save_dataset: Option<PathBuf>,
    },
    /// Subscribe to the calibration service and write every message as a JSON line (a
    /// tracker's view of `live`; used by the HIL test). Stops at SIGINT/SIGTERM.
    Monitor {
        /// The calibration service.
        #[arg(long, default_value = hw_io::ipc::DEFAULT_CALIBRATION_SERVICE)]
        service: String,
        /// JSON Lines output (one message per line); default: standard output.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Run the protocol sweeps; write sweep.md and SVG box plots into a directory.
    Sweep {
        /// Output directory.
        #[arg(long, default_value = "docs/calibration")]
        out_dir: PathBuf,
        /// Trials per condition.
        #[arg(long, default_value_t = 30)]
        trials: usize,
        /// A small sweep (σ = 0.01 at 3⁴×3², grid 2⁴×2², 4 initial quaternions) for smoke tests.
        #[arg(long)]
        quick: bool,
        /// Base seed.
        #[arg(long, default_value_t = 1000)]
        seed: u64,
        /// Run the generalisation protocol instead: this many random scene geometries per set
        /// (tuning seeds 9000.., held-out seeds 7000..), `--trials` each, writing
        /// generalisation.md.
        #[arg(long)]
        geometries: Option<usize>,
        /// With --geometries: only the held-out set.
        #[arg(long)]
        held_out_only: bool,
        /// With --geometries: the held-out set's first geometry seed (geometry `i` drawn with
        /// seed + i). 7000: the first held-out set (reported since session 8); 7100: the
        /// second (session 31); another seed draws a fresh set, never looked at, for a choice
        /// made after those were studied.
        #[arg(long, default_value_t = 7000)]
        held_out_seed: u64,
        /// With --geometries: the tuning set's first geometry seed.
        #[arg(long, default_value_t = 9000)]
        tuning_seed: u64,
    },
}

/// Set by SIGUSR1: `live` solves now.
static REQUEST: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

extern "C" fn on_request(_: libc::c_int) {
    REQUEST.store(true, std::sync::atomic::Ordering::Relaxed);
}

/// SIGUSR1 sets [`REQUEST`] (a failure to install it is reported, the process runs on).
/// `--false-refusal-probability`: a probability strictly between 0 and 1.
fn parse_probability(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(p) if p > 0.0 && p < 1.0 => Ok(p),
        Ok(p) => Err(format!("{p} is not a probability strictly between 0 and 1")),
        Err(e) => Err(format!("not a number: {e}")),
    }
}

fn install_request_handler() {
    use nix::sys::signal::{SaFlags, SigAction, SigHandler, SigSet, Signal, sigaction};
    let action = SigAction::new(SigHandler::Handler(on_request), SaFlags::SA_RESTART, SigSet::empty());
    // SAFETY: the handler only stores to an atomic, which is async-signal-safe.
    if let Err(e) = unsafe { sigaction(Signal::SIGUSR1, &action) } {
        eprintln!("comanip-calib: cannot install the SIGUSR1 handler: {e}");
    }
}

/// `comanip-calib monitor`: every calibration message as one JSON line until SIGINT/SIGTERM.
fn monitor(service: &str, out: Option<&std::path::Path>) -> Result<(), Box<dyn std::error::Error>> {
    use std::io::Write as _;
    controller::process::install_stop_handlers();
    let mut sub = hw_io::ipc::Subscriber::<hw_io::ipc::CalibrationSample>::connect(service)
        .map_err(|e| format!("{service}: {e}"))?;
    let mut w: Box<dyn std::io::Write> = match out {
        Some(p) => Box::new(std::fs::File::create(p).map_err(|e| format!("{}: {e}", p.display()))?),
        None => Box::new(std::io::stdout()),
    };
    eprintln!("comanip-calib monitor: subscribed to {service}");
    let mut refused = 0u64;
    while !controller::process::STOP.load(std::sync::atomic::Ordering::Relaxed) {
        match sub.wait(std::time::Duration::from_millis(100)) {
            Ok(Some(rx)) => {
                let s = rx.sample;
                let state = match s.state() {
                    Some(hw_io::ipc::CalibrationState::Collecting) => "collecting",
                    Some(hw_io::ipc::CalibrationState::Valid) => "valid",
                    Some(hw_io::ipc::CalibrationState::Drift) => "drift",
                    None => "unknown",
                };
                let line = serde_json::json!({
                    "state": state, "sequence": s.sequence, "run_id": s.run_id, "timestamp_ns": s.timestamp_ns,
                    "observations": s.observations, "drifts": s.drifts, "translation_m": s.translation_m,
                    "quaternion_wxyz": s.quaternion_wxyz, "covariance": s.covariance.to_vec(),
                    "predicted_fulcrum_m": s.predicted_fulcrum_m, "predicted_origin_m": s.predicted_origin_m,
                    "predicted_rotation_rad": s.predicted_rotation_rad, "mean_fulcrum_m": s.mean_fulcrum_m,
                });
                writeln!(w, "{line}")?;
                w.flush()?;
            }
            Ok(None) => {}
            Err(hw_io::ipc::WaitError::Recv(e)) => {
                refused += 1;
                eprintln!("comanip-calib monitor: refused: {e}");
            }
            Err(e) => return Err(format!("{service}: {e}").into()),
        }
    }
    eprintln!("comanip-calib monitor: stopped ({refused} refused)");
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        // The reader of the standard output went away (`comanip-calib ... | head`): quietly.
        Err(e) if e.downcast_ref::<std::io::Error>().is_some_and(hw_io::stdout::is_broken_pipe) => {
            ExitCode::from(hw_io::stdout::BROKEN_PIPE_EXIT)
        }
        Err(e) => {
            eprintln!("comanip-calib: error: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<(), Box<dyn std::error::Error>> {
    match cli.command {
        Command::Generate { dataset, truth, grid, pixel_sigma, seed, wrong_lines } => {
            let mut p = default_protocol();
            p.n_e = grid.n_e;
            p.n_t = grid.n_t;
            p.sigma = grid.sigma;
            p.units = grid.units.into();
            p.pixel_sigma_px = pixel_sigma;
            p.seed = seed;
            let g = generate(&p, wrong_lines, &dataset, &truth)?;
            hw_io::outln!(
                "{} observations kept ({} with a wrong line), {} of {} dropped (tool not in view), {} not generated (tool through the endoscope); wrote {} and {}",
                g.kept,
                g.wrong,
                g.dropped,
                g.generated,
                g.collided,
                dataset.display(),
                truth.display()
            )?;
        }
        Command::Calibrate {
            dataset,
            intrinsics,
            truth,
            out,
            plot,
            pipeline,
            accept_unrefined,
            false_refusal_probability,
            estimate_noise_scale,
            search_on_all,
        } => {
            let s = calibrate(
                &dataset,
                intrinsics.as_deref(),
                truth.as_deref(),
                &out,
                plot.as_deref(),
                pipeline,
                comanip_calib::run::OursOptions {
                    accept_unrefined,
                    estimate_noise_scale,
                    false_refusal_probability,
                    search_on_all,
                },
            )?;
            for r in &s {
                match r.errors {
                    Some(e) => hw_io::outln!(
                        "{}: e_t = {:.3} % ({:.3} mm), e_R = {:.4}°, {:.2} ms",
                        r.pipeline,
                        e.translation_rel * 100.0,
                        e.translation_m * 1e3,
                        e.rotation_rad.to_degrees(),
                        r.solve_ms
                    )?,
                    None => hw_io::outln!("{}: {:.2} ms", r.pipeline, r.solve_ms)?,
                }
                if let Some(w) = &r.warning {
                    eprintln!("comanip-calib: warning: {}: {w} (accepted by --accept-unrefined)", r.pipeline);
                }
                if let Some(f) = &r.failure {
                    eprintln!("comanip-calib: error: {f}");
                }
            }
            hw_io::outln!("wrote {}", out.display())?;
            if let Some(p) = &plot {
                hw_io::outln!("wrote {}", p.display())?;
            }
            if all_failed(&s) {
                return Err("every requested pipeline failed (see the result file's `failures`)".into());
            }
        }
        Command::Detect { images, camera, out, overlay, detector, right } => {
            let text = std::fs::read_to_string(&camera).map_err(|e| format!("{}: {e}", camera.display()))?;
            let k =
                hw_io::calib_files::parse_intrinsics_yaml(&text).map_err(|e| format!("{}: {e}", camera.display()))?;
            let bar = comanip_calib::sweep::progress_bar(0, "images");
            let s = detect_dir(&images, k, detector, right, &out, overlay.as_deref(), |n, total| {
                bar.set_length(total as u64);
                bar.set_position(n as u64);
            })?;
            bar.finish_and_clear();
            hw_io::outln!(
                "{} images: a shaft in {}, none in {}, {} unreadable; {:.2} ms per image (median); wrote {}",
                s.images,
                s.with_shaft,
                s.images - s.with_shaft - s.failed,
                s.failed,
                s.median_ms,
                out.display()
            )?;
            if s.failed > 0 {
                return Err(format!("{} image(s) could not be examined (listed in {})", s.failed, out.display()).into());
            }
        }
        Command::Pixels { out_dir, grid, seed, sigma_px } => {
            use comanip_calib::detect::make_detector;
            use comanip_calib::pixels::{PixelProtocol, calibrate_all, render_and_detect, report_markdown};
            let p = PixelProtocol {
                n_e: grid.n_e,
                n_t: grid.n_t,
                sigma: grid.sigma,
                units: grid.units.into(),
                seed,
                detected_sigma_px: sigma_px,
                ..PixelProtocol::default()
            };
            let k = p.endoscope.camera.intrinsics;
            let mut detectors = vec![make_detector(DetectorChoice::Paper, k)?, make_detector(DetectorChoice::Ours, k)?];
            let bar = comanip_calib::sweep::progress_bar(0, "poses");
            let run = render_and_detect(&p, &mut detectors, |n, total| {
                bar.set_length(total as u64);
                bar.set_position(n as u64);
            })?;
            bar.finish_and_clear();
            let rows = calibrate_all(&run);
            std::fs::create_dir_all(&out_dir).map_err(|e| format!("{}: {e}", out_dir.display()))?;
            let command = std::env::args().collect::<Vec<_>>().join(" ");
            let md = report_markdown(&p, &run, &rows, &command);
            let path = out_dir.join("pixels.md");
            std::fs::write(&path, &md).map_err(|e| format!("{}: {e}", path.display()))?;
            comanip_calib::pixels::write_datasets(&run, &p, &out_dir)?;
            hw_io::outln!("{md}")?;
            hw_io::outln!("wrote {}", path.display())?;
        }
        Command::FromRun { run, config, every, sigma_px, noise_mrad, noise_mm, noise_as_stated, out_dir } => {
            use comanip_calib::bus_run::{read_run, to_pixel_run};
            use comanip_calib::detect::make_detector;
            use comanip_calib::pixels::calibrate_all;
            let cfg = match &config {
                Some(p) => {
                    let text = std::fs::read_to_string(p).map_err(|e| format!("{}: {e}", p.display()))?;
                    toml::from_str::<controller::config::Config>(&text).map_err(|e| format!("{}: {e}", p.display()))?
                }
                None => controller::config::Config::default(),
            };
            if every == 0 {
                return Err("--every must be at least 1".into());
            }
            let mut data = read_run(&run, &cfg)?;
            let usable = data.frames.len();
            data.frames = data.frames.into_iter().step_by(every).collect();
            let k = data.intrinsics;
            let mut detectors = vec![make_detector(DetectorChoice::Paper, k)?, make_detector(DetectorChoice::Ours, k)?];
            let bar = comanip_calib::sweep::progress_bar(0, "frames");
            let noise = estimator::calib::KinematicNoise {
                rot_rad: noise_mrad * 1e-3,
                trans_m: noise_mm * 1e-3,
                pixel_px: sigma_px,
            };
            if !noise.is_valid() {
                return Err("noise σ must be finite and ≥ 0 (not all 0)".into());
            }
            let (pr, trocar, f_ref) =
                to_pixel_run(&data, &run.join("frames"), &mut detectors, noise, !noise_as_stated, |n, total| {
                    bar.set_length(total as u64);
                    bar.set_position(n as u64);
                })?;
            bar.finish_and_clear();
            let rows = calibrate_all(&pr);
            let mut md = String::new();
            use std::fmt::Write as _;
            let command = std::env::args().collect::<Vec<_>>().join(" ");
            let _ = writeln!(md, "<!-- written by `{command}` -->");
            let _ = writeln!(
                md,
                "{} frames listed; {usable} with both arms' joints and the instrument inside a trocar (left out: {} without a cycle, {} without endoscope joints, {} outside); every {every}th used; trocar {trocar}: {} frames.\n",
                data.listed,
                data.no_cycle,
                data.no_ecm,
                data.outside,
                pr.poses.len()
            );
            let nearest = data.trocars_b.iter().map(|t| (t - f_ref).norm()).fold(f64::INFINITY, f64::min);
            let _ = writeln!(
                md,
                "The trocar's median fulcrum (fulcrumd's estimate) is {:.1} mm from the nearest true trocar; it is the origin of `{{t}}` and of the truth `T_e_t`.\n",
                nearest * 1e3
            );
            let _ = writeln!(
                md,
                "| detector | truth lines | detected | angle median / p95 (°) | offset median / p95 (px) | ms per image (median) |"
            );
            let _ = writeln!(md, "|---|---|---|---|---|---|");
            md.push_str(&comanip_calib::pixels::detection_rows(&pr));
            let _ = writeln!(
                md,
                "\n| lines | eyes | observations | paper pipeline | our pipeline |\n|---|---|---|---|---|"
            );
            md.push_str(&comanip_calib::pixels::calibration_rows(&rows));
            std::fs::create_dir_all(&out_dir).map_err(|e| format!("{}: {e}", out_dir.display()))?;
            let path = out_dir.join("from-run.md");
            std::fs::write(&path, &md).map_err(|e| format!("{}: {e}", path.display()))?;
            hw_io::outln!("{md}")?;
            hw_io::outln!("wrote {}", path.display())?;
        }
        Command::Monitor { service, out } => monitor(&service, out.as_deref())?,
        Command::Live { replay: None, live_config, summary_json, .. } => {
            controller::process::init_logging();
            controller::process::install_stop_handlers();
            install_request_handler();
            let path = live_config.unwrap_or_else(|| PathBuf::from("(built-in)"));
            let file = if path.is_file() {
                comanip_calib::live_config::LiveConfig::load(&path)?
            } else if path.as_os_str() == "(built-in)" {
                comanip_calib::live_config::LiveConfig::default()
            } else {
                return Err(format!("{}: no such file", path.display()).into());
            };
            let resolved = file.resolve(&path)?;
            let summary = comanip_calib::live_process::run(&resolved, &controller::process::STOP, &REQUEST)?;
            if let Some(p) = &summary_json {
                std::fs::write(p, serde_json::to_string_pretty(&summary)?)
                    .map_err(|e| format!("{}: {e}", p.display()))?;
            }
        }
        Command::Live {
            replay: Some(dir),
            config,
            target_mm,
            target_deg,
            noise_px,
            noise_mrad,
            noise_mm,
            out,
            report,
            save_dataset,
            ..
        } => {
            use comanip_calib::live::{ReplayOptions, progress_line, replay as run_replay, report_markdown};
            let cfg = match &config {
                Some(p) => {
                    let text = std::fs::read_to_string(p).map_err(|e| format!("{}: {e}", p.display()))?;
                    toml::from_str::<controller::config::Config>(&text).map_err(|e| format!("{}: {e}", p.display()))?
                }
                None => controller::config::Config::default(),
            };
            let noise = estimator::calib::KinematicNoise {
                rot_rad: noise_mrad * 1e-3,
                trans_m: noise_mm * 1e-3,
                pixel_px: noise_px,
            };
            if !(noise.is_valid() && target_mm > 0.0 && target_deg > 0.0) {
                return Err("noise σ must be finite and ≥ 0 (not all 0), targets > 0".into());
            }
            let opts = ReplayOptions {
                noise,
                target_translation_m: target_mm * 1e-3,
                target_rotation_rad: target_deg.to_radians(),
                log_every_s: 10.0,
            };
            let bar = comanip_calib::sweep::progress_bar(0, "frames");
            if let Ok(style) = indicatif::ProgressStyle::with_template("{spinner} [{elapsed_precise}] {msg}") {
                bar.set_style(style);
            }
            let r = run_replay(&dir, &cfg, &opts, |p, t| bar.set_message(progress_line(p, t)))?;
            bar.finish_and_clear();
            let command = std::env::args().collect::<Vec<_>>().join(" ");
            let md = report_markdown(&r, &opts, &command);
            if let Some(path) = &report {
                std::fs::write(path, &md).map_err(|e| format!("{}: {e}", path.display()))?;
            }
            hw_io::outln!("{md}")?;
            if let Some(dir) = &save_dataset {
                comanip_calib::live::write_dataset(&r, &opts, dir)?;
                hw_io::outln!("wrote {}", dir.join("dataset.json").display())?;
            }
            let chosen = r.published.as_ref().or(r.at_end.as_ref());
            let Some((cal, _)) = chosen else {
                return Err("no calibration: too little data (see the report)".into());
            };
            let entry =
                comanip_calib::convert::result_json("ours", &cal.pose, &cal.ours.residuals, Some(&cal.ours), 0.0);
            let file = hw_io::calib_files::ResultFile {
                format: hw_io::calib_files::RESULT_FORMAT.into(),
                version: hw_io::calib_files::CALIB_FILE_VERSION,
                results: vec![entry],
                failures: Vec::new(),
            };
            std::fs::write(&out, hw_io::calib_files::to_json(&file)).map_err(|e| format!("{}: {e}", out.display()))?;
            hw_io::outln!("wrote {}", out.display())?;
        }
        Command::Sweep {
            out_dir,
            trials,
            geometries: Some(n),
            held_out_only,
            seed,
            held_out_seed,
            tuning_seed,
            ..
        } => {
            let mut opts = comanip_calib::generalise::GeneralisationOptions::full(n);
            opts.trials = trials;
            opts.trial_seed = seed;
            opts.held_out_only = held_out_only;
            opts.held_out_seed = held_out_seed;
            opts.tuning_seed = tuning_seed;
            let command = std::env::args().collect::<Vec<_>>().join(" ");
            comanip_calib::generalise::run_generalisation(&opts, &out_dir, &command)?;
            hw_io::outln!("wrote {}", out_dir.join("generalisation.md").display())?;
        }
        Command::Sweep { out_dir, trials, quick, seed, geometries: None, .. } => {
            let mut opts = SweepOptions::full();
            opts.trials = trials;
            opts.seed = seed;
            if quick {
                opts.sigmas = vec![0.01];
                opts.grid = vec![(2, 2)];
                opts.init_quaternions = 4;
            }
            let command = std::env::args().collect::<Vec<_>>().join(" ");
            run_sweep(&opts, &out_dir, &command)?;
            hw_io::outln!("wrote {}", out_dir.join("sweep.md").display())?;
        }
    }
    Ok(())
}
