//! `comanip-bench`: the benchmarks of docs/BENCHMARKS.md.
//!
//! - `comanip-bench all` — everything below, then writes docs/BENCHMARKS.md and the SVG
//!   figures under docs/benchmarks/ (run from the repository root, release build).
//! - `comanip-bench detection [--seeds 11,12,13,14] [--cycles 90] [--config fulcrumd.toml]`
//! - `comanip-bench loop [--seconds 60]` — the daemon on its in-process simulated robot.
//! - `comanip-bench ipc [--samples 20000]` — iceoryx2 latency between two processes.
//! - `comanip-bench isolation --beside "<command>" [--pairs 4] [--seconds 20] [--loop-cpu 1]` —
//!   the loop alone and beside a command, interleaved (`docs/tracking.md` "Isolation").
//! - `comanip-bench shaft [--frames-per-family 14] [--tuning] [--peers] [--out DIR] [--figures DIR]`
//!   — the shaft detectors (ours, the paper's, OpenCV peers) on rendered frames
//!   (`docs/detection.md`).

use std::fmt::Write as _;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::AtomicBool;

use clap::{Parser, Subcommand};
use comanip_bench::bus_loss::{LossReport, run_bus_loss};
use comanip_bench::families::{FAMILIES, FamilyOptions, FamilyReport, REPORT_SEEDS, TUNING_SEEDS, run_families};
use comanip_bench::ipc::{self, IpcReport};
use comanip_bench::plots;
use comanip_bench::report::{DetectionOptions, DetectionReport, run_detection};
use controller::config::Config;
use controller::daemon::{self, RunOptions, RunSummary};
use hw_io::rt_alloc::RtPoolAllocator;

#[global_allocator]
static ALLOC: RtPoolAllocator = RtPoolAllocator::new();

static STOP: AtomicBool = AtomicBool::new(false);

#[derive(Parser)]
#[command(version, about = "comanip benchmarks: detection quality (paper vs fast), loop timing, IPC latency")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Every benchmark; writes the Markdown report and the SVG figures.
    All(AllArgs),
    /// Detection benchmark: the paper mode and the fast mode's three settings on the same traces.
    Detection(DetectionArgs),
    /// Loop timing: the daemon on the in-process simulated robot.
    Loop(LoopArgs),
    /// iceoryx2 publish → blocking-wait receive latency between two processes.
    Ipc(IpcArgs),
    /// Detection per motion-style family: tuning families marked, held-out families reported.
    Families(FamiliesArgs),
    /// The daemon's stale-data policy under random TPDO loss and bursts of missing TPDOs.
    BusLoss(BusLossArgs),
    /// Shaft detectors on rendered endoscope frames: ours, the paper's, OpenCV peers.
    Shaft(ShaftArgs),
    /// The loop's timing alone and beside another process, runs interleaved (A B A B ...).
    Isolation(IsolationArgs),
}

#[derive(clap::Args)]
struct IsolationArgs {
    /// The command run beside the loop (`sh -c`, its own process group; apply the unit's
    /// priority yourself: `taskset -c 0 nice -n 15 ...`).
    #[arg(long)]
    beside: String,
    /// Pairs of runs (alone, beside), interleaved.
    #[arg(long, default_value_t = 4)]
    pairs: usize,
    /// Seconds of loop per run.
    #[arg(long, default_value_t = 20)]
    seconds: u64,
    /// Seconds between starting the command and starting the loop.
    #[arg(long, default_value_t = 3.0)]
    warm_up_s: f64,
    /// The loop thread's CPU (fulcrumd's `[realtime] cpu_affinity`; docs/realtime.md: 1 on a
    /// 2-core PC); negative: not pinned.
    #[arg(long, default_value_t = 1, allow_hyphen_values = true)]
    loop_cpu: i64,
    /// Also write the runs as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
}

#[derive(clap::Args)]
struct ShaftArgs {
    /// Seeds per scenario family (9 families in the report set, 4 in the tuning set: 3 of them in the report too, and `blur`).
    #[arg(long, default_value_t = 14)]
    frames_per_family: usize,
    /// Run the tuning set (tuning families, tuning seeds): the only frames to tune on.
    #[arg(long)]
    tuning: bool,
    /// Clutter levels (clean, default, smoke, second, all); default: all five.
    #[arg(long, value_delimiter = ',')]
    levels: Option<Vec<String>>,
    /// Also run the OpenCV peers (EdgeDrawing/EDLines and LSD, each with the paper's pairing).
    #[arg(long)]
    peers: bool,
    /// Python interpreter of the peers.
    #[arg(long, default_value = "python3")]
    python: String,
    /// The peers' script (default: controller/bench/peers/opencv_lines.py of this source tree).
    #[arg(long)]
    peers_script: Option<PathBuf>,
    /// Directory of table.md and results.json (and the figures unless --figures).
    #[arg(long, default_value = "target/shaft-bench")]
    out: PathBuf,
    /// Directory of the overlay PNGs and the SVG.
    #[arg(long)]
    figures: Option<PathBuf>,
    /// Instead of the benchmark: classify ours' misses by the stage that lost the shaft
    /// (`shaft::diagnose`; meant for `--tuning`). Prints the tables only.
    #[arg(long)]
    diagnose: bool,
}

#[derive(clap::Args)]
struct BusLossArgs {
    /// Scenario seeds of the traces (placement C1).
    #[arg(long = "loss-seeds", value_delimiter = ',', default_values_t = [101u64, 102, 103, 104])]
    loss_seeds: Vec<u64>,
    /// Insert/extract cycles per trace.
    #[arg(long = "loss-cycles", default_value_t = 90)]
    loss_cycles: usize,
}

#[derive(clap::Args)]
struct FamiliesArgs {
    /// Scenario seeds (each family runs once per seed). Default: the report seeds (never used
    /// for tuning); `--tuning` uses the tuning seeds and the tuning families only.
    #[arg(long = "family-seeds", value_delimiter = ',')]
    family_seeds: Option<Vec<u64>>,
    /// Insert/extract cycles per trace.
    #[arg(long = "family-cycles", default_value_t = 100)]
    family_cycles: usize,
    /// Run only the tuning families on the tuning seeds (what the thresholds were chosen on).
    #[arg(long)]
    tuning: bool,
    /// fulcrumd configuration whose `[detector]` tables the benchmark uses.
    #[arg(long = "family-config")]
    family_config: Option<PathBuf>,
    /// Print the sample indices of every false detection (diagnosis).
    #[arg(long)]
    list_false: bool,
}

#[derive(clap::Args)]
struct DetectionArgs {
    /// Scenario seeds (each runs in each of the three placements).
    #[arg(long, value_delimiter = ',', default_values_t = [101u64, 102, 103, 104])]
    seeds: Vec<u64>,
    /// Insert/extract cycles per trace.
    #[arg(long, default_value_t = 90)]
    cycles: usize,
    /// fulcrumd configuration whose `[detector]` tables (paper and fast parameters) the
    /// benchmark uses; default: the built-in defaults (= configs/fulcrumd.toml).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Simulate a perfectly calibrated arm (separates the estimator's own localisation error
    /// from the arm's calibration error).
    #[arg(long)]
    no_model_error: bool,
}

#[derive(clap::Args)]
struct LoopArgs {
    /// Seconds of daemon run (1000 cycles per second).
    #[arg(long, default_value_t = 60)]
    seconds: u64,
}

#[derive(clap::Args)]
struct IpcArgs {
    /// Samples measured (1 kHz, after 500 warm-up samples).
    #[arg(long, default_value_t = 20_000)]
    samples: u64,
}

#[derive(clap::Args)]
struct AllArgs {
    #[command(flatten)]
    detection: DetectionArgs,
    #[command(flatten)]
    looping: LoopArgs,
    #[command(flatten)]
    ipc: IpcArgs,
    #[command(flatten)]
    families: FamiliesArgs,
    #[command(flatten)]
    loss: BusLossArgs,
    /// The Markdown report to write.
    #[arg(long, default_value = "docs/BENCHMARKS.md")]
    report: PathBuf,
    /// Directory of the SVG figures (linked relative to the report).
    #[arg(long, default_value = "docs/benchmarks")]
    figures: PathBuf,
}

fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.trim().to_owned())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let kernel = std::fs::read_to_string("/proc/sys/kernel/osrelease").unwrap_or_default();
    let nproc = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(0);
    let mem_gib = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|s| s.lines().next().and_then(|l| l.split_whitespace().nth(1)).and_then(|k| k.parse::<f64>().ok()))
        .map_or(0.0, |kib| kib / 1024.0 / 1024.0);
    format!("{cpu}, {nproc} CPUs, {mem_gib:.0} GiB, Linux {} (shared machine)", kernel.trim())
}

fn detection(a: &DetectionArgs) -> Result<DetectionReport, String> {
    let detector = match &a.config {
        Some(p) => Config::load(p).map_err(|e| e.to_string())?.detector,
        None => Default::default(),
    };
    let opts = DetectionOptions {
        seeds: a.seeds.clone(),
        cycles_per_trace: a.cycles,
        detector,
        model_error: !a.no_model_error,
        ..Default::default()
    };
    let traces = (opts.seeds.len() * opts.placements.len()) as u64;
    let bar = if std::io::stderr().is_terminal() {
        let b = indicatif::ProgressBar::new(traces);
        b.set_message("traces");
        b
    } else {
        indicatif::ProgressBar::hidden()
    };
    let r = run_detection(&opts, &|| bar.inc(1)).map_err(|e| e.to_string())?;
    bar.finish_and_clear();
    Ok(r)
}

fn families(a: &FamiliesArgs) -> Result<FamilyReport, String> {
    let detector = match &a.family_config {
        Some(p) => Config::load(p).map_err(|e| e.to_string())?.detector,
        None => Default::default(),
    };
    let seeds = match (&a.family_seeds, a.tuning) {
        (Some(s), _) => s.clone(),
        (None, true) => TUNING_SEEDS.to_vec(),
        (None, false) => REPORT_SEEDS.to_vec(),
    };
    let opts = FamilyOptions { seeds, cycles_per_trace: a.family_cycles, tuning_only: a.tuning, detector };
    let n_fam = FAMILIES.iter().filter(|f| f.tuned || !opts.tuning_only).count();
    let bar = if std::io::stderr().is_terminal() {
        let b = indicatif::ProgressBar::new((n_fam * opts.seeds.len()) as u64);
        b.set_message("traces");
        b
    } else {
        indicatif::ProgressBar::hidden()
    };
    let r = run_families(&opts, &|| bar.inc(1)).map_err(|e| e.to_string())?;
    bar.finish_and_clear();
    if a.list_false {
        for f in &r.families {
            for (set, c) in r.settings.iter().zip(&f.cells) {
                if !c.false_at.is_empty() {
                    eprintln!("{} / {}: false detections at (seed, sample) {:?}", f.family.key, set.key, c.false_at);
                }
            }
        }
    }
    Ok(r)
}

fn bus_loss(a: &BusLossArgs) -> Result<LossReport, String> {
    let n = (a.loss_seeds.len() * comanip_bench::bus_loss::CONDITIONS.len()) as u64;
    let bar = if std::io::stderr().is_terminal() {
        let b = indicatif::ProgressBar::new(n);
        b.set_message("runs");
        b
    } else {
        indicatif::ProgressBar::hidden()
    };
    let r = run_bus_loss(&a.loss_seeds, a.loss_cycles, &|| bar.inc(1)).map_err(|e| e.to_string())?;
    bar.finish_and_clear();
    Ok(r)
}

fn shaft(a: &ShaftArgs) -> Result<String, String> {
    use comanip_bench::shaft::{self, PeerOptions, ShaftOptions, peers, scenes};
    let levels = match &a.levels {
        None => scenes::ClutterLevel::ALL.to_vec(),
        Some(keys) => keys
            .iter()
            .map(|k| scenes::ClutterLevel::from_key(k).ok_or_else(|| format!("unknown clutter level {k}")))
            .collect::<Result<_, _>>()?,
    };
    if a.diagnose {
        let set = if a.tuning { scenes::SeedSet::Tuning } else { scenes::SeedSet::Report };
        let d = shaft::diagnose::run(&shaft::intrinsics(), set, a.frames_per_family, &levels, &|| {})
            .map_err(|e| e.to_string())?;
        return Ok(d.markdown());
    }
    let work_dir = std::env::temp_dir().join(format!("comanip-shaft-{}", std::process::id()));
    let opts = ShaftOptions {
        set: if a.tuning { scenes::SeedSet::Tuning } else { scenes::SeedSet::Report },
        frames_per_family: a.frames_per_family,
        levels,
        peers: a.peers.then(|| PeerOptions {
            python: a.python.clone(),
            script: a.peers_script.clone().unwrap_or_else(peers::default_script),
            work_dir: work_dir.clone(),
        }),
    };
    let k = shaft::intrinsics();
    let (mut detectors, pairing) = shaft_detectors(&k)?;
    let bar = if std::io::stderr().is_terminal() {
        let b = indicatif::ProgressBar::new(0);
        b.set_message("frames (render, detect)");
        b
    } else {
        indicatif::ProgressBar::hidden()
    };
    let r = shaft::run(&opts, &mut detectors, pairing.as_deref(), &|done, total| {
        bar.set_length(total);
        bar.set_position(done);
    });
    bar.finish_and_clear();
    let _ = std::fs::remove_dir_all(&work_dir);
    let r = r.map_err(|e| e.to_string())?;
    let figures = a.figures.clone().unwrap_or_else(|| a.out.clone());
    let written = r.write(&a.out, &figures).map_err(|e| e.to_string())?;
    eprintln!("comanip-bench shaft: wrote {} files under {} and {}", written.len(), a.out.display(), figures.display());
    Ok(r.markdown())
}

/// The shaft pairing the peers get: a segment list (measured pixels) to at most one shaft.
type BoxedPairing = Box<dyn Fn(&[vision::Segment]) -> Option<vision::ShaftDetection>>;

/// The shaft detectors of a run, in report order.
type Detectors = Vec<Box<dyn vision::ShaftDetector>>;

/// The detectors under test, in report order, and the paper's pairing for the peers.
fn shaft_detectors(k: &estimator::calib::Intrinsics) -> Result<(Detectors, Option<BoxedPairing>), String> {
    let ours = vision::ours::OursDetector::new(*k, vision::ours::OursConfig::default()).map_err(|e| e.to_string())?;
    let paper = vision::paper::PaperDetector::new(*k);
    let k = *k;
    let pairing: BoxedPairing = Box::new(move |s| vision::paper::pair_shaft(&k, s));
    Ok((vec![Box::new(ours), Box::new(paper)], Some(pairing)))
}

fn run_loop(a: &LoopArgs) -> Result<RunSummary, String> {
    let mut config = Config::default();
    config.recorder.enabled = false;
    config.output.service = format!("comanip-bench/{}/loop", std::process::id());
    let config_toml = toml::to_string(&config).map_err(|e| e.to_string())?;
    let opts = RunOptions { config, config_toml, max_cycles: Some(a.seconds * 1000), sim_seed: 1 };
    daemon::run(opts, &STOP).map_err(|e| e.to_string())
}

fn isolation(a: &IsolationArgs) -> Result<String, String> {
    if !(a.warm_up_s.is_finite() && (0.0..=600.0).contains(&a.warm_up_s)) {
        return Err(format!("--warm-up-s must be in [0, 600] seconds, not {}", a.warm_up_s));
    }
    let opts = comanip_bench::isolation::IsolationOptions {
        beside: a.beside.clone(),
        pairs: a.pairs,
        seconds: a.seconds,
        warm_up_s: a.warm_up_s,
    };
    let mut run_loop = |seconds: u64| {
        // The daemon's shutdown sets the stop flag: clear it for the next run.
        STOP.store(false, std::sync::atomic::Ordering::Relaxed);
        let mut config = Config::default();
        config.recorder.enabled = false;
        config.output.service = format!("comanip-bench/{}/isolation", std::process::id());
        if let Ok(cpu) = usize::try_from(a.loop_cpu) {
            config.realtime.cpu_affinity = vec![cpu];
        }
        let config_toml = toml::to_string(&config).map_err(|e| e.to_string())?;
        let opts = RunOptions { config, config_toml, max_cycles: Some(seconds * 1000), sim_seed: 1 };
        daemon::run(opts, &STOP).map_err(|e| e.to_string())
    };
    let report = comanip_bench::isolation::run(&opts, &mut run_loop, &mut |r| {
        eprintln!(
            "comanip-bench isolation: run {} {}: {} overruns, period error p99.9 {:.0} µs, max {:.0} µs, CPU busy {:?}",
            r.index, r.condition, r.overruns, r.period_error_us[2], r.period_error_us[3], r.cpu_busy
        );
    })
    .map_err(|e| e.to_string())?;
    if let Some(p) = &a.json {
        std::fs::write(p, serde_json::to_string_pretty(&report).map_err(|e| e.to_string())?)
            .map_err(|e| format!("{}: {e}", p.display()))?;
    }
    Ok(report.markdown())
}

fn loop_markdown(s: &RunSummary) -> String {
    let t = &s.timing;
    let mut m = String::new();
    let _ = writeln!(
        m,
        "{} cycles ({} s at {} µs), {} published, {} overruns, {} incomplete cycles, {} system allocations on the \
         real-time thread.\n",
        s.cycles,
        s.cycles * u64::from(s.period_us) / 1_000_000,
        s.period_us,
        s.published,
        s.overruns,
        s.acquisition.incomplete_cycles,
        s.alloc.rt_thread_system_allocs
    );
    let _ = writeln!(m, "| µs | p50 | p99 | p99.9 | max |");
    let _ = writeln!(m, "|---|---|---|---|---|");
    for (name, x) in [
        ("period error (wake-up lateness)", &t.wake_late),
        ("compute (frames in → published)", &t.compute),
        ("whole cycle (wake-up → published)", &t.cycle),
    ] {
        let _ = writeln!(m, "| {name} | {:.0} | {:.0} | {:.0} | {:.0} |", x.p50_us, x.p99_us, x.p999_us, x.max_us);
    }
    m
}

fn ipc_markdown(r: &IpcReport) -> String {
    format!(
        "{} samples at 1 kHz (after {} warm-up), missed {}, gaps or restarts {}, {} system allocations on the \
         publishing thread.\n\n| µs | p50 | p99 | p99.9 | max |\n|---|---|---|---|---|\n| publish → `wait()` returns \
         | {:.1} | {:.1} | {:.1} | {:.1} |\n",
        r.samples,
        ipc::WARM_UP,
        r.missed,
        r.gaps_or_restarts,
        r.publisher_rt_allocs,
        r.latency_us[0],
        r.latency_us[1],
        r.latency_us[2],
        r.latency_us[3]
    )
}

fn all(a: &AllArgs) -> Result<(), String> {
    let started = std::time::Instant::now();
    std::fs::create_dir_all(&a.figures).map_err(|e| format!("{}: {e}", a.figures.display()))?;
    eprintln!("comanip-bench: detection ...");
    let det = detection(&a.detection)?;
    eprintln!("comanip-bench: motion-style families ...");
    let fam = families(&a.families)?;
    eprintln!("comanip-bench: bus loss and gaps ...");
    let loss = bus_loss(&a.loss)?;
    eprintln!("comanip-bench: loop timing ({} s) ...", a.looping.seconds);
    let lp = run_loop(&a.looping)?;
    eprintln!("comanip-bench: iceoryx2 latency ({} samples) ...", a.ipc.samples);
    let ipc = ipc::run(a.ipc.samples).map_err(|e| e.to_string())?;

    let fig = |name: &str| a.figures.join(name);
    let rel = |name: &str| {
        let dir = a.report.parent().unwrap_or(Path::new("."));
        a.figures.strip_prefix(dir).unwrap_or(&a.figures).join(name).display().to_string()
    };
    plots::delay_histograms(&det, &fig("delays.svg")).map_err(|e| e.to_string())?;
    plots::timeline(&det.timeline, &fig("timeline.svg")).map_err(|e| e.to_string())?;
    let steps: Vec<(&str, Vec<(f64, u64)>)> = det
        .settings
        .iter()
        .filter(|s| s.setting.key == "paper" || s.setting.key == "fast")
        .map(|s| (s.setting.key, s.step_times.buckets().map(|(ns, c)| (ns as f64, c)).collect()))
        .collect();
    plots::duration_histogram("detector step time", "ns", &steps, 3000.0, &fig("step_time.svg"))
        .map_err(|e| e.to_string())?;
    if let Some(h) = &lp.timing_histograms {
        let conv =
            |hist: &controller::timing::Histogram| hist.buckets().map(|(us, c)| (us as f64, u64::from(c))).collect();
        plots::duration_histogram(
            "daemon loop timing (in-process simulated robot)",
            "µs",
            &[("period error", conv(&h.wake_late)), ("compute", conv(&h.compute)), ("whole cycle", conv(&h.cycle))],
            1000.0,
            &fig("loop_timing.svg"),
        )
        .map_err(|e| e.to_string())?;
    }
    let ipc_buckets: Vec<(f64, u64)> = ipc.buckets.iter().map(|(us, c)| (*us as f64, u64::from(*c))).collect();
    plots::duration_histogram(
        "iceoryx2 publish → receive latency",
        "µs",
        &[("blocking wait", ipc_buckets)],
        500.0,
        &fig("ipc_latency.svg"),
    )
    .map_err(|e| e.to_string())?;

    let mut md = String::new();
    let _ = writeln!(md, "# Benchmarks\n");
    let _ = writeln!(
        md,
        "Generated by `cargo run --release --bin comanip-bench -- all` (from the repository root; {:.0} s). \
         Machine: {}. Medians and ratios come from this one run; the machine is shared, so tail latencies \
         include other tenants' load. Method and definitions: [benchmark-method.md](benchmark-method.md).\n",
        started.elapsed().as_secs_f64(),
        machine()
    );
    let _ = writeln!(md, "## Detection: the paper's method and ours on the same traces\n");
    md.push_str(&det.markdown());
    let _ = writeln!(md, "![insertion and extraction delays]({})\n", rel("delays.svg"));
    let _ = writeln!(md, "![timeline of the first trace]({})\n", rel("timeline.svg"));
    let _ = writeln!(md, "![detector step time]({})\n", rel("step_time.svg"));
    let _ = writeln!(md, "## Detection per motion-style family: tuned and held-out surgeons\n");
    let _ = writeln!(
        md,
        "The same four settings on nine families of simulated surgeons (`comanip-bench families`; families, seeds \
         and what was tuned on what: [benchmark-method.md](benchmark-method.md#motion-style-families)). Targets \
         (fast mode, held-out families): 0 false detections, 0 samples inside more than 20 mm off, every \
         insertion detected, mean delay within 1.1x the motion-only bound, the trocar list exact. The `aim` \
         family is geometrically an insertion when the instrument length is unknown (every line passes through \
         the port while the tip advances to it): with the paper's information it is declared early, at the \
         right port; with the length, never.\n"
    );
    md.push_str(&fam.markdown());
    let _ = writeln!(md);
    let _ = writeln!(md, "## Bus loss and gaps\n");
    let _ = writeln!(
        md,
        "`comanip-bench bus-loss`: the daemon's own decoding and stale-data policy (`Estimation`) on the benchmark's \
         traces with TPDO frames dropped before acquisition (method: [benchmark-method.md](benchmark-method.md#bus-loss-and-gaps)). \
         Spurious extractions and resets per hour of simulated motion (counts in brackets).\n"
    );
    md.push_str(&loss.markdown());
    let _ = writeln!(md, "## Loop timing: fulcrumd on the in-process simulated robot\n");
    md.push_str(&loop_markdown(&lp));
    let _ = writeln!(md, "\n![loop timing]({})\n", rel("loop_timing.svg"));
    let _ = writeln!(md, "## iceoryx2 latency between two processes\n");
    md.push_str(&ipc_markdown(&ipc));
    let _ = writeln!(md, "\n![iceoryx2 latency]({})", rel("ipc_latency.svg"));
    std::fs::write(&a.report, md).map_err(|e| format!("{}: {e}", a.report.display()))?;
    eprintln!("comanip-bench: wrote {} and {}/*.svg", a.report.display(), a.figures.display());
    Ok(())
}

fn main() -> ExitCode {
    // iceoryx2's messages (the loop and IPC benchmarks open services, in this process and in
    // the IPC subscriber child) through tracing; without a subscriber they are dropped, as the
    // report is the output here.
    hw_io::ipc::route_iceoryx2_logs_to_tracing();
    if std::env::var_os(ipc::ROLE_ENV).is_some() {
        return match ipc::subscriber_main() {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                eprintln!("comanip-bench (ipc subscriber): {e}");
                ExitCode::FAILURE
            }
        };
    }
    let cli = Cli::parse();
    // The report to print, if the command has one (`all` writes files).
    let result = match &cli.command {
        Command::All(a) => all(a).map(|()| None),
        Command::Detection(a) => detection(a).map(|r| Some(r.markdown())),
        Command::Loop(a) => run_loop(a).map(|s| Some(loop_markdown(&s))),
        Command::Ipc(a) => ipc::run(a.samples).map(|r| Some(ipc_markdown(&r))).map_err(|e| e.to_string()),
        Command::Families(a) => families(a).map(|r| Some(r.markdown())),
        Command::BusLoss(a) => bus_loss(a).map(|r| Some(r.markdown())),
        Command::Shaft(a) => shaft(a).map(Some),
        Command::Isolation(a) => isolation(a).map(Some),
    };
    let printed = match &result {
        Ok(Some(report)) => hw_io::outln!("{report}"),
        _ => Ok(()),
    };
    match (result, printed) {
        (Ok(_), Ok(())) => ExitCode::SUCCESS,
        // The reader of the standard output went away (`comanip-bench ... | head`): quietly.
        (Ok(_), Err(e)) if hw_io::stdout::is_broken_pipe(&e) => ExitCode::from(hw_io::stdout::BROKEN_PIPE_EXIT),
        (Ok(_), Err(e)) => {
            eprintln!("comanip-bench: error: writing to standard output: {e}");
            ExitCode::FAILURE
        }
        (Err(e), _) => {
            eprintln!("comanip-bench: error: {e}");
            ExitCode::FAILURE
        }
    }
}
