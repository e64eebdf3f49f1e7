//! iceoryx2 publish → receive latency between two processes, for the subscriber library's
//! blocking wait ([`hw_io::ipc::FulcrumSubscriber::wait`]), as a guidance-force module uses it.
//!
//! The publisher (the calling process) stamps `timestamp_ns` with `CLOCK_MONOTONIC` right
//! before `publish`, on a thread paced at 1 kHz by `clock_nanosleep(TIMER_ABSTIME)` and
//! marked real-time for [`hw_io::rt_alloc`] (as fulcrumd does). The subscriber is the same
//! executable re-run with [`ROLE_ENV`] set: it reads `CLOCK_MONOTONIC` as soon as `wait`
//! returns and sends back its latency histogram. Both run at normal priority. The first
//! [`WARM_UP`] samples are not counted.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::Duration;

use hw_io::ipc::{Continuity, FulcrumPublisher, FulcrumSample, FulcrumSubscriber, HealthFlags, PublisherOptions};
use hw_io::rt_alloc;
use serde::{Deserialize, Serialize};

use controller::rt::monotonic_now_ns;
use controller::timing::Histogram;

/// Environment variable that makes the executable act as the subscriber.
pub const ROLE_ENV: &str = "COMANIP_BENCH_IPC_SUBSCRIBER";
const SERVICE_ENV: &str = "COMANIP_BENCH_IPC_SERVICE";
const COUNT_ENV: &str = "COMANIP_BENCH_IPC_COUNT";
const PARENT_ENV: &str = "COMANIP_BENCH_IPC_PARENT";
/// Samples published before measuring.
pub const WARM_UP: u64 = 500;
const PERIOD_NS: i64 = 1_000_000;

/// What the subscriber measured.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct IpcReport {
    /// Samples measured.
    pub samples: u64,
    /// Samples the subscriber library counted as missed.
    pub missed: u64,
    /// Gaps or restarts seen.
    pub gaps_or_restarts: u64,
    /// Latency quantiles, microseconds: p50, p99, p99.9, max.
    pub latency_us: [f64; 4],
    /// Latency histogram, (bucket start µs, count).
    pub buckets: Vec<(u64, u32)>,
    /// System allocations of the publisher's real-time thread while publishing.
    pub publisher_rt_allocs: u64,
}

/// Why the latency benchmark failed.
#[derive(Debug, thiserror::Error)]
pub enum IpcBenchError {
    /// The publisher could not be created.
    #[error("publisher: {0}")]
    Publisher(#[from] hw_io::ipc::CreateError),
    /// The subscriber process failed.
    #[error("subscriber process: {0}")]
    Subscriber(String),
    /// A publication failed.
    #[error("publish: {0}")]
    Publish(String),
}

/// Runs the publisher side with `count` measured samples; spawns the subscriber.
pub fn run(count: u64) -> Result<IpcReport, IpcBenchError> {
    let name = format!("comanip-bench/{}/ipc-latency", std::process::id());
    let mut publisher = FulcrumPublisher::create(&name, &PublisherOptions::default())?;
    let exe = std::env::current_exe().map_err(|e| IpcBenchError::Subscriber(e.to_string()))?;
    let mut child = Command::new(exe)
        .env(ROLE_ENV, "1")
        .env(SERVICE_ENV, &name)
        .env(COUNT_ENV, count.to_string())
        .env(PARENT_ENV, std::process::id().to_string())
        .stdout(Stdio::piped())
        .spawn()
        .map_err(|e| IpcBenchError::Subscriber(e.to_string()))?;
    let stdout = child.stdout.take().ok_or_else(|| IpcBenchError::Subscriber("no stdout".into()))?;
    let mut lines = BufReader::new(stdout).lines();
    if lines.next().and_then(Result::ok).as_deref() != Some("READY") {
        let _ = child.kill();
        return Err(IpcBenchError::Subscriber("did not start".into()));
    }
    let mut next = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: writes into the local timespec.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut next) };
    let mut sample = FulcrumSample::invalid(HealthFlags::empty());
    sample.run_id = monotonic_now_ns() ^ (u64::from(std::process::id()) << 32);
    let mut allocs = 0;
    for seq in 0..WARM_UP + count {
        if seq == WARM_UP / 2 {
            rt_alloc::prefault_pool();
            rt_alloc::enter_realtime();
            allocs = rt_alloc::thread_system_allocs();
        }
        next.tv_nsec += PERIOD_NS;
        if next.tv_nsec >= 1_000_000_000 {
            next.tv_nsec -= 1_000_000_000;
            next.tv_sec += 1;
        }
        // SAFETY: sleeps until the absolute time in the local timespec.
        unsafe { libc::clock_nanosleep(libc::CLOCK_MONOTONIC, libc::TIMER_ABSTIME, &next, std::ptr::null_mut()) };
        sample.sequence = seq;
        sample.timestamp_ns = monotonic_now_ns();
        if let Err(e) = publisher.publish(&sample) {
            rt_alloc::leave_realtime();
            let _ = child.kill();
            return Err(IpcBenchError::Publish(e.to_string()));
        }
    }
    allocs = rt_alloc::thread_system_allocs() - allocs;
    rt_alloc::leave_realtime();
    let text: String = lines.map_while(Result::ok).collect::<Vec<_>>().join("\n");
    let status = child.wait().map_err(|e| IpcBenchError::Subscriber(e.to_string()))?;
    if !status.success() {
        return Err(IpcBenchError::Subscriber(format!("exited with {status}: {text}")));
    }
    let mut report: IpcReport =
        serde_json::from_str(&text).map_err(|e| IpcBenchError::Subscriber(format!("bad report: {e}")))?;
    report.publisher_rt_allocs = allocs;
    Ok(report)
}

/// The subscriber side (called by `main` when [`ROLE_ENV`] is set). Prints `READY`, then its
/// report as JSON.
pub fn subscriber_main() -> Result<(), String> {
    let name = std::env::var(SERVICE_ENV).map_err(|_| "no service name".to_string())?;
    let count: u64 = std::env::var(COUNT_ENV).ok().and_then(|c| c.parse().ok()).ok_or("no sample count")?;
    // Die quietly with the publisher: without it there is nothing to measure (and nobody to
    // read an error). The parent may already be gone before the request takes effect.
    // SAFETY: prctl with integer arguments only.
    unsafe { libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM as libc::c_ulong) };
    let parent: Option<i32> = std::env::var(PARENT_ENV).ok().and_then(|p| p.parse().ok());
    if parent.is_some_and(|p| p != std::os::unix::process::parent_id() as i32) {
        return Ok(());
    }
    let mut sub = FulcrumSubscriber::connect(&name).map_err(|e| e.to_string())?;
    hw_io::outln!("READY").map_err(|e| format!("writing to standard output: {e}"))?;
    let mut hist = Histogram::new(20_000);
    let mut gaps = 0;
    let mut measured = 0;
    while measured < count {
        let r = sub.wait(Duration::from_secs(2)).map_err(|e| e.to_string())?.ok_or("no sample within 2 s")?;
        let now = monotonic_now_ns();
        if !matches!(r.event, Continuity::First | Continuity::InOrder) {
            gaps += 1;
        }
        if r.sample.sequence >= WARM_UP {
            hist.record(now.saturating_sub(r.sample.timestamp_ns));
            measured += 1;
        }
    }
    let s = hist.summary();
    let report = IpcReport {
        samples: measured,
        missed: sub.counters().missed,
        gaps_or_restarts: gaps,
        latency_us: [s.p50_us, s.p99_us, s.p999_us, s.max_us],
        buckets: hist.buckets().collect(),
        publisher_rt_allocs: 0,
    };
    let json = serde_json::to_string(&report).map_err(|e| e.to_string())?;
    hw_io::outln!("{json}").map_err(|e| format!("writing to standard output: {e}"))?;
    Ok(())
}
