//! `comanip-bench`: the benchmarks of docs/BENCHMARKS.md.
//!
//! `comanip-bench detection [--seeds 11,12,13,14] [--cycles 90] [--out DIR]`

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use controller::bench::report::{DetectionOptions, run_detection};
use hw_io::rt_alloc::RtPoolAllocator;

#[global_allocator]
static ALLOC: RtPoolAllocator = RtPoolAllocator::new();

#[derive(Parser)]
#[command(version, about = "comanip benchmarks: detection quality (paper vs fast), loop timing, IPC latency")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Detection benchmark: the paper mode and the fast mode's three settings on the same traces.
    Detection(DetectionArgs),
}

#[derive(clap::Args)]
struct DetectionArgs {
    /// Scenario seeds (each runs in each of the three placements).
    #[arg(long, value_delimiter = ',', default_values_t = [11u64, 12, 13, 14])]
    seeds: Vec<u64>,
    /// Insert/extract cycles per trace.
    #[arg(long, default_value_t = 90)]
    cycles: usize,
    /// Directory for the report and plots.
    #[arg(long)]
    out: Option<PathBuf>,
    /// fulcrumd configuration whose `[detector]` tables (paper and fast parameters) the
    /// benchmark uses; default: the built-in defaults (= configs/fulcrumd.toml).
    #[arg(long)]
    config: Option<PathBuf>,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::Detection(a) => {
            let detector = match &a.config {
                Some(p) => match controller::config::Config::load(p) {
                    Ok(c) => c.detector,
                    Err(e) => {
                        eprintln!("comanip-bench: {e}");
                        return ExitCode::from(2);
                    }
                },
                None => Default::default(),
            };
            let opts = DetectionOptions { seeds: a.seeds, cycles_per_trace: a.cycles, detector, ..Default::default() };
            match run_detection(&opts, &|| eprint!(".")) {
                Ok(r) => {
                    eprintln!();
                    println!("{}", r.markdown());
                    if let Some(dir) = a.out {
                        let _ = std::fs::create_dir_all(&dir);
                        let _ = std::fs::write(dir.join("detection.md"), r.markdown());
                    }
                    ExitCode::SUCCESS
                }
                Err(e) => {
                    eprintln!("comanip-bench: error: {e}");
                    ExitCode::FAILURE
                }
            }
        }
    }
}
