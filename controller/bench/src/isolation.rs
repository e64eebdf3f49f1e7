//! Isolation: fulcrumd's loop timing alone and beside another process (issue 18: "fulcrumd's
//! loop unaffected: overruns and p99.9 period error within noise of the run without
//! tracking"; `docs/tracking.md` "Isolation").
//!
//! Runs alternate, A B A B …: the loop alone, then the loop while a command given on the
//! command line (e.g. `comanip-tracker live` under `taskset -c 0 nice -n 15`) runs in its own
//! process group, started a few seconds before the loop and stopped (SIGTERM, then SIGKILL)
//! after it. Interleaving spreads the shared machine's other load over both conditions.
//! Each run reports the loop's overruns and period-error percentiles (the daemon's own
//! histograms, `comanip-bench loop`), and each CPU's busy fraction during the run
//! (`/proc/stat`), which shows whether the other process really loaded the machine.

use std::fmt::Write as _;
use std::os::unix::process::CommandExt as _;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use controller::daemon::RunSummary;

/// What to measure.
#[derive(Clone, Debug)]
pub struct IsolationOptions {
    /// The command run beside the loop (`sh -c`), in its own process group.
    pub beside: String,
    /// Pairs of runs (alone, beside).
    pub pairs: usize,
    /// Seconds of loop per run.
    pub seconds: u64,
    /// Seconds between starting the command and starting the loop.
    pub warm_up_s: f64,
}

/// One run's figures.
#[derive(Clone, Debug, serde::Serialize)]
pub struct IsolationRun {
    /// Run number (0 first).
    pub index: usize,
    /// `alone` or `beside`.
    pub condition: &'static str,
    /// Cycles run.
    pub cycles: u64,
    /// Periods skipped by overruns.
    pub overruns: u64,
    /// Period error (wake-up lateness) percentiles, microseconds: p50, p99, p99.9, max.
    pub period_error_us: [f64; 4],
    /// Whole cycle (wake-up → published) p99.9, microseconds.
    pub cycle_p999_us: f64,
    /// Each CPU's busy fraction during the loop (0..1), from `/proc/stat`.
    pub cpu_busy: Vec<f64>,
    /// The command was still running at the end of the loop (`None` when alone).
    pub beside_alive: Option<bool>,
}

/// Medians of one condition.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct ConditionMedians {
    /// Median overruns per run.
    pub overruns: f64,
    /// Median p99 period error, microseconds.
    pub p99_us: f64,
    /// Median p99.9 period error, microseconds.
    pub p999_us: f64,
    /// Median max period error, microseconds.
    pub max_us: f64,
}

/// The whole measurement.
#[derive(Clone, Debug, serde::Serialize)]
pub struct IsolationReport {
    /// The command run beside.
    pub beside: String,
    /// The machine (CPUs, model).
    pub machine: String,
    /// Every run, in order.
    pub runs: Vec<IsolationRun>,
    /// Medians alone.
    pub alone: ConditionMedians,
    /// Medians beside.
    pub with: ConditionMedians,
}

/// Why the measurement failed.
#[derive(Debug, thiserror::Error)]
pub enum IsolationError {
    /// The loop failed.
    #[error("loop run {index}: {message}")]
    Loop {
        /// Run number.
        index: usize,
        /// Why.
        message: String,
    },
    /// The command could not be started.
    #[error("cannot start `{command}`: {source}")]
    Spawn {
        /// The command.
        command: String,
        /// The OS error.
        source: std::io::Error,
    },
    /// Nothing to run.
    #[error("pairs and seconds must be at least 1")]
    Empty,
}

/// Per-CPU `(busy, total)` jiffies from `/proc/stat` (empty when unreadable).
fn cpu_times() -> Vec<(u64, u64)> {
    let Ok(text) = std::fs::read_to_string("/proc/stat") else { return Vec::new() };
    text.lines()
        .filter(|l| l.starts_with("cpu") && l.as_bytes().get(3).is_some_and(u8::is_ascii_digit))
        .map(|l| {
            let v: Vec<u64> = l.split_whitespace().skip(1).filter_map(|x| x.parse().ok()).collect();
            let total: u64 = v.iter().sum();
            // idle + iowait are not busy.
            let idle = v.get(3).copied().unwrap_or(0) + v.get(4).copied().unwrap_or(0);
            (total - idle, total)
        })
        .collect()
}

fn busy_between(a: &[(u64, u64)], b: &[(u64, u64)]) -> Vec<f64> {
    a.iter()
        .zip(b)
        .map(|(x, y)| {
            let total = y.1.saturating_sub(x.1);
            if total == 0 { 0.0 } else { y.0.saturating_sub(x.0) as f64 / total as f64 }
        })
        .collect()
}

/// The machine: online CPUs and the model name.
pub fn machine() -> String {
    let cpus = std::thread::available_parallelism().map_or(0, std::num::NonZeroUsize::get);
    let model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|t| {
            t.lines()
                .find(|l| l.starts_with("model name"))
                .map(|l| l.split(':').nth(1).unwrap_or("").trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    format!("{cpus} vCPU, {model}")
}

fn spawn(command: &str) -> Result<Child, IsolationError> {
    Command::new("sh")
        .arg("-c")
        .arg(command)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .process_group(0)
        .spawn()
        .map_err(|source| IsolationError::Spawn { command: command.to_string(), source })
}

/// Stops the command's whole process group: SIGTERM, up to 3 s for every member to end, then
/// SIGKILL.
fn stop(child: &mut Child) {
    let Ok(pgid) = i32::try_from(child.id()) else { return };
    // SAFETY: kill(2) on the process group this module created (`process_group(0)`: its id is
    // the child's pid); no memory is involved.
    unsafe { libc::kill(-pgid, libc::SIGTERM) };
    // Wait for the whole group (not only the shell) to go, so that its members can finish
    // (write their summaries); the shell itself is reaped as it ends.
    let deadline = Instant::now() + Duration::from_secs(3);
    while Instant::now() < deadline {
        let _ = child.try_wait();
        // SAFETY: signal 0 only asks whether a member of the group still exists.
        if unsafe { libc::kill(-pgid, 0) } != 0 {
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    // SAFETY: as above; members that ignored SIGTERM are killed.
    unsafe { libc::kill(-pgid, libc::SIGKILL) };
    let _ = child.wait();
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) }
}

fn medians(runs: &[IsolationRun], condition: &str) -> ConditionMedians {
    let sel: Vec<&IsolationRun> = runs.iter().filter(|r| r.condition == condition).collect();
    ConditionMedians {
        overruns: median(sel.iter().map(|r| r.overruns as f64).collect()),
        p99_us: median(sel.iter().map(|r| r.period_error_us[1]).collect()),
        p999_us: median(sel.iter().map(|r| r.period_error_us[2]).collect()),
        max_us: median(sel.iter().map(|r| r.period_error_us[3]).collect()),
    }
}

/// Runs the measurement; `run_loop(seconds)` runs the loop once and returns its summary.
/// `progress` is told each finished run.
pub fn run(
    opts: &IsolationOptions,
    run_loop: &mut dyn FnMut(u64) -> Result<RunSummary, String>,
    progress: &mut dyn FnMut(&IsolationRun),
) -> Result<IsolationReport, IsolationError> {
    if opts.pairs == 0 || opts.seconds == 0 {
        return Err(IsolationError::Empty);
    }
    let mut runs = Vec::new();
    for index in 0..2 * opts.pairs {
        let beside = index % 2 == 1;
        let mut child = if beside { Some(spawn(&opts.beside)?) } else { None };
        if beside {
            std::thread::sleep(Duration::try_from_secs_f64(opts.warm_up_s.max(0.0)).unwrap_or(Duration::ZERO));
        }
        let before = cpu_times();
        let result = run_loop(opts.seconds);
        let after = cpu_times();
        let alive = child.as_mut().map(|c| matches!(c.try_wait(), Ok(None)));
        if let Some(c) = child.as_mut() {
            stop(c);
        }
        let s = result.map_err(|message| IsolationError::Loop { index, message })?;
        let t = &s.timing;
        let r = IsolationRun {
            index,
            condition: if beside { "beside" } else { "alone" },
            cycles: s.cycles,
            overruns: s.overruns,
            period_error_us: [t.wake_late.p50_us, t.wake_late.p99_us, t.wake_late.p999_us, t.wake_late.max_us],
            cycle_p999_us: t.cycle.p999_us,
            cpu_busy: busy_between(&before, &after),
            beside_alive: alive,
        };
        progress(&r);
        runs.push(r);
    }
    Ok(IsolationReport {
        beside: opts.beside.clone(),
        machine: machine(),
        alone: medians(&runs, "alone"),
        with: medians(&runs, "beside"),
        runs,
    })
}

impl IsolationReport {
    /// The Markdown table of every run, the medians and the ratios.
    pub fn markdown(&self) -> String {
        let mut m = String::new();
        let _ = writeln!(m, "Machine: {}. Beside: `{}`.\n", self.machine, self.beside);
        let _ = writeln!(
            m,
            "| run | condition | cycles | overruns | period error p50 / p99 / p99.9 / max (µs) | cycle p99.9 (µs) | CPU busy | command alive |"
        );
        let _ = writeln!(m, "|---|---|---|---|---|---|---|---|");
        for r in &self.runs {
            let busy: Vec<String> = r.cpu_busy.iter().map(|b| format!("{:.0} %", b * 100.0)).collect();
            let _ = writeln!(
                m,
                "| {} | {} | {} | {} | {:.0} / {:.0} / {:.0} / {:.0} | {:.0} | {} | {} |",
                r.index,
                r.condition,
                r.cycles,
                r.overruns,
                r.period_error_us[0],
                r.period_error_us[1],
                r.period_error_us[2],
                r.period_error_us[3],
                r.cycle_p999_us,
                busy.join(", "),
                r.beside_alive.map_or("—", |a| if a { "yes" } else { "NO (ended early)" })
            );
        }
        let ratio = |b: f64, a: f64| if a > 0.0 { format!("{:.2}", b / a) } else { "—".into() };
        let (a, b) = (&self.alone, &self.with);
        let _ = writeln!(m, "\n| median | overruns | p99 (µs) | p99.9 (µs) | max (µs) |");
        let _ = writeln!(m, "|---|---|---|---|---|");
        let _ = writeln!(m, "| alone | {} | {:.0} | {:.0} | {:.0} |", a.overruns, a.p99_us, a.p999_us, a.max_us);
        let _ = writeln!(m, "| beside | {} | {:.0} | {:.0} | {:.0} |", b.overruns, b.p99_us, b.p999_us, b.max_us);
        let _ = writeln!(
            m,
            "| ratio beside / alone | {} | {} | {} | {} |",
            ratio(b.overruns, a.overruns),
            ratio(b.p99_us, a.p99_us),
            ratio(b.p999_us, a.p999_us),
            ratio(b.max_us, a.max_us)
        );
        m
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn medians_and_busy_fractions() {
        assert_eq!(median(vec![3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(vec![4.0, 1.0, 2.0, 3.0]), 2.5);
        assert!(median(Vec::new()).is_nan());
        let b = busy_between(&[(10, 100), (0, 100)], &[(60, 200), (100, 200)]);
        assert_eq!(b, vec![0.5, 1.0]);
    }

    #[test]
    fn the_command_runs_in_its_own_group_and_is_stopped_with_its_children() {
        let dir = std::env::temp_dir().join(format!("comanip-isolation-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap_or_default();
        let marker = dir.join("child.pid");
        // A shell whose child ignores SIGTERM: the SIGKILL of the group must end it too.
        let mut c = spawn(&format!(
            "sh -c 'trap \"\" TERM; echo $$ > {}; while :; do sleep 0.05; done' & wait",
            marker.display()
        ))
        .unwrap_or_else(|e| panic!("{e}"));
        let t0 = Instant::now();
        while !marker.exists() && t0.elapsed() < Duration::from_secs(5) {
            std::thread::sleep(Duration::from_millis(20));
        }
        let pid: i32 = std::fs::read_to_string(&marker).unwrap_or_default().trim().parse().unwrap_or(0);
        assert!(pid > 0, "the command did not start");
        stop(&mut c);
        std::thread::sleep(Duration::from_millis(100));
        // Gone, or a zombie waiting for its new parent to reap it (state Z).
        let state = std::fs::read_to_string(format!("/proc/{pid}/stat"))
            .ok()
            .and_then(|t| t.rsplit_once(") ").and_then(|(_, rest)| rest.chars().next()));
        assert!(matches!(state, None | Some('Z' | 'X')), "the grandchild {pid} survived the stop: state {state:?}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
