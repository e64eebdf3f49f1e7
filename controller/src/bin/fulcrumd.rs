//! fulcrumd: the trocar daemon.
//!
//! Today it runs the trocar detector over the built-in simulated surgeon and prints every
//! state change next to the ground truth, then a summary. The command line stays the same
//! when the 1 kHz CAN loop lands.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;
use controller::config::Config;
use controller::demo;
use estimator::trocar::{DetectorMode, TrocarState};
use sim::scenario::ScenarioConfig;
use sim::score;

/// Command line of fulcrumd.
#[derive(Parser, Debug)]
#[command(version, about = "comanip trocar daemon (today: on the built-in simulated robot)")]
struct Cli {
    /// Configuration file (TOML). Without it, the built-in defaults (identical to
    /// configs/fulcrumd.toml) are used.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Override the detector mode of the config: paper or fast.
    #[arg(long, value_parser = parse_mode)]
    mode: Option<DetectorMode>,
    /// Simulated insert/extract cycles.
    #[arg(long, default_value_t = 6)]
    cycles: usize,
    /// Seed of the simulated surgeon.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

fn parse_mode(s: &str) -> Result<DetectorMode, String> {
    match s {
        "paper" => Ok(DetectorMode::Paper),
        "fast" => Ok(DetectorMode::Fast),
        other => Err(format!("unknown mode {other:?}: expected paper or fast")),
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let mut cfg = match &cli.config {
        Some(p) => match Config::load(p) {
            Ok(c) => c,
            Err(e) => {
                eprintln!("fulcrumd: {e}");
                return ExitCode::from(2);
            }
        },
        None => Config::default(),
    };
    if let Some(m) = cli.mode {
        cfg.detector.mode = m;
    }
    let scenario = ScenarioConfig { seed: cli.seed, cycles: cli.cycles, ..Default::default() };
    println!(
        "fulcrumd: built-in simulated robot, {} cycles through {} trocars, detector mode {:?}",
        scenario.cycles,
        scenario.trocars_base_m.len(),
        cfg.detector.mode
    );
    let result = demo::run(
        &cfg.detector,
        &scenario,
        |c| match (c.state, c.fulcrum_base_m) {
            (TrocarState::Inside { id }, Some(f)) => println!(
                "{:8.3} s  DETECTED  inside trocar #{id} at ({:+.4}, {:+.4}, {:+.4}) m, error {:.1} mm",
                c.t_s,
                f[0],
                f[1],
                f[2],
                c.error_m.map_or(f64::NAN, |e| e * 1e3)
            ),
            _ => println!("{:8.3} s  DETECTED  outside", c.t_s),
        },
        |t, trocar, insertion| {
            println!(
                "{t:8.3} s  truth     {} trocar {trocar}",
                if insertion { "inserted into" } else { "extracted from" }
            )
        },
    );
    let s = match result {
        Ok(s) => s,
        Err(e) => {
            eprintln!("fulcrumd: {e}");
            return ExitCode::from(2);
        }
    };
    println!(
        "summary: insertions {}/{} (mean delay {:.3} s), extractions {}/{} (mean delay {:.3} s), false detections {}, RMS error {:.2} mm",
        s.insertions_detected,
        s.insertions,
        score::mean(&s.insertion_delays_s),
        s.extractions_detected,
        s.extractions,
        score::mean(&s.extraction_delays_s),
        s.false_detections,
        s.rms_error_m * 1e3
    );
    ExitCode::SUCCESS
}
