//! `comanip-calib`: dual RCM-arm calibration from tool lines and encoders
//! (`docs/calibration.md`).

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
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
    },
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
        Command::Generate { dataset, truth, n_e, n_t, sigma, units, pixel_sigma, seed, wrong_lines } => {
            let mut p = default_protocol();
            p.n_e = n_e;
            p.n_t = n_t;
            p.sigma = sigma;
            p.units = match units {
                Units::Mm => NoiseUnits::Millimetre,
                Units::M => NoiseUnits::Metre,
            };
            p.pixel_sigma_px = pixel_sigma;
            p.seed = seed;
            let g = generate(&p, wrong_lines, &dataset, &truth)?;
            hw_io::outln!(
                "{} observations kept ({} with a wrong line), {} of {} dropped (tool not in view); wrote {} and {}",
                g.kept,
                g.wrong,
                g.dropped,
                g.generated,
                dataset.display(),
                truth.display()
            )?;
        }
        Command::Calibrate { dataset, intrinsics, truth, out, plot, pipeline, accept_unrefined } => {
            let s = calibrate(
                &dataset,
                intrinsics.as_deref(),
                truth.as_deref(),
                &out,
                plot.as_deref(),
                pipeline,
                accept_unrefined,
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
        Command::Sweep { out_dir, trials, geometries: Some(n), held_out_only, seed, .. } => {
            let mut opts = comanip_calib::generalise::GeneralisationOptions::full(n);
            opts.trials = trials;
            opts.trial_seed = seed;
            opts.held_out_only = held_out_only;
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
