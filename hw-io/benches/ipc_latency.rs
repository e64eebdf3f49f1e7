//! Publish → receive latency of the fulcrum output between two processes at 1 kHz, with the
//! subscriber blocked in `FulcrumSubscriber::wait` (the event listener), as a guidance-force
//! module would use it.
//!
//! `cargo bench -p hw-io --bench ipc_latency` (optionally `-- <samples>`, default 10 000).
//!
//! The publisher (this process) stamps `timestamp_ns` with `CLOCK_MONOTONIC` right before
//! `publish`, on a thread paced by `clock_nanosleep(TIMER_ABSTIME)` and marked real-time for
//! `rt_alloc` (as fulcrumd does); the subscriber (this binary re-executed with
//! `COMANIP_BENCH_ROLE=subscriber`) reads `CLOCK_MONOTONIC` as soon as `wait` returns. Both run
//! at normal priority. The first 500 samples are a warm-up and are not counted.

use std::io::{BufRead, BufReader, Write};
use std::process::{Command, Stdio};
use std::time::Duration;

use hw_io::ipc::{Continuity, FulcrumPublisher, FulcrumSample, FulcrumSubscriber, PublisherOptions};
use hw_io::rt_alloc::{self, RtPoolAllocator};

#[global_allocator]
static ALLOC: RtPoolAllocator = RtPoolAllocator::new();

const ROLE_ENV: &str = "COMANIP_BENCH_ROLE";
const SERVICE_ENV: &str = "COMANIP_BENCH_SERVICE";
const COUNT_ENV: &str = "COMANIP_BENCH_COUNT";
const WARM_UP: u64 = 500;
const PERIOD_NS: i64 = 1_000_000;

fn monotonic() -> libc::timespec {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: writes into the local timespec.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts
}

fn monotonic_ns() -> u64 {
    let ts = monotonic();
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

fn main() {
    if std::env::var(ROLE_ENV).as_deref() == Ok("subscriber") {
        subscriber();
        return;
    }
    // `cargo bench` passes `--bench`; the first numeric argument, if any, is the sample count.
    let count: u64 = std::env::args().skip(1).find_map(|a| a.parse().ok()).unwrap_or(10_000);
    publisher(count);
}

fn publisher(count: u64) {
    let name = format!("comanip-bench/{}/ipc_latency", std::process::id());
    let mut publisher = FulcrumPublisher::create(&name, &PublisherOptions::default()).expect("publisher");
    let mut child = Command::new(std::env::current_exe().expect("own path"))
        .env(ROLE_ENV, "subscriber")
        .env(SERVICE_ENV, &name)
        .env(COUNT_ENV, count.to_string())
        .stdout(Stdio::piped())
        .spawn()
        .expect("subscriber process");
    let mut lines = BufReader::new(child.stdout.take().expect("piped stdout")).lines();
    assert_eq!(lines.next().and_then(Result::ok).as_deref(), Some("READY"), "subscriber did not start");

    let run_id = monotonic_ns() ^ (u64::from(std::process::id()) << 32);
    let mut next = monotonic();
    let mut sample = FulcrumSample::invalid(0);
    sample.run_id = run_id;
    for seq in 0..WARM_UP + count {
        if seq == WARM_UP / 2 {
            rt_alloc::prefault_pool();
            rt_alloc::enter_realtime();
        }
        next.tv_nsec += PERIOD_NS;
        if next.tv_nsec >= 1_000_000_000 {
            next.tv_nsec -= 1_000_000_000;
            next.tv_sec += 1;
        }
        // SAFETY: sleeps until the absolute time in the local timespec.
        unsafe { libc::clock_nanosleep(libc::CLOCK_MONOTONIC, libc::TIMER_ABSTIME, &next, std::ptr::null_mut()) };
        sample.sequence = seq;
        sample.timestamp_ns = monotonic_ns();
        publisher.publish(&sample).expect("publish");
    }
    rt_alloc::leave_realtime();
    let stats = rt_alloc::stats();

    let report: Vec<String> = lines.map_while(Result::ok).collect();
    let status = child.wait().expect("subscriber exit");
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("model name")).map(|l| l.split(':').nth(1).unwrap_or("").trim().to_owned())
        })
        .unwrap_or_else(|| "unknown".into());
    let kernel = std::fs::read_to_string("/proc/sys/kernel/osrelease").unwrap_or_default();
    let nproc = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(0);
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "ipc_latency: publish -> blocking wait() return, 2 processes, 1 kHz, normal priority");
    let _ = writeln!(out, "machine: nproc {nproc}, CPU {cpu}, Linux {}", kernel.trim());
    let _ = writeln!(
        out,
        "publisher real-time thread: {} system allocations, {} pool allocations, pool high-water {} blocks",
        stats.realtime_system_allocs, stats.pool_allocs, stats.pool_high_water
    );
    for line in report {
        let _ = writeln!(out, "{line}");
    }
    assert!(status.success(), "subscriber failed: {status:?}");
}

fn subscriber() {
    let name = std::env::var(SERVICE_ENV).expect("service name");
    let count: u64 = std::env::var(COUNT_ENV).ok().and_then(|c| c.parse().ok()).expect("sample count");
    let mut sub = FulcrumSubscriber::connect(&name).expect("subscriber");
    println!("READY");
    let mut latencies_ns: Vec<u64> = Vec::with_capacity(count as usize);
    let mut restarts_or_gaps = 0u64;
    while (latencies_ns.len() as u64) < count {
        let r = sub.wait(Duration::from_secs(2)).expect("wait").expect("a sample within 2 s");
        let now = monotonic_ns();
        if !matches!(r.event, Continuity::First | Continuity::InOrder) {
            restarts_or_gaps += 1;
        }
        if r.sample.sequence >= WARM_UP {
            latencies_ns.push(now.saturating_sub(r.sample.timestamp_ns));
        }
    }
    latencies_ns.sort_unstable();
    let pct = |p: f64| {
        let i = ((p * latencies_ns.len() as f64).ceil() as usize).clamp(1, latencies_ns.len()) - 1;
        latencies_ns[i] as f64 / 1000.0
    };
    let c = sub.counters();
    println!("samples: {count} (after {WARM_UP} warm-up), missed {}, gaps or restarts {restarts_or_gaps}", c.missed);
    println!(
        "latency us: p50 {:.1}  p99 {:.1}  p99.9 {:.1}  max {:.1}  (min {:.1})",
        pct(0.50),
        pct(0.99),
        pct(0.999),
        pct(1.0),
        latencies_ns[0] as f64 / 1000.0
    );
}
