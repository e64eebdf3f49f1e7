//! The real-time side allocates nothing: recorder pushes, the periodic clock and the progress
//! counter, checked with a counting global allocator (per-thread counts, so parallel tests and
//! the writer thread do not disturb the measure).

use controller::recorder::{self, RecorderConfig, RunInfo};
use controller::rt::{Periodic, monotonic_now_ns, sleep_until_ns};
use controller::watchdog::LoopProgress;
use serde::{Deserialize, Serialize};

#[global_allocator]
static GLOBAL: hw_io::rt_alloc::RtPoolAllocator = hw_io::rt_alloc::RtPoolAllocator::new();

fn allocs() -> u64 {
    hw_io::rt_alloc::thread_system_allocs()
}

#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
struct Cycle {
    seq: u64,
    q: [f64; 6],
}

#[test]
fn the_counter_sees_allocations() {
    let before = allocs();
    let v = std::hint::black_box(Vec::<u8>::with_capacity(64));
    drop(v);
    assert_eq!(allocs() - before, 1, "one allocation");
}

#[test]
fn producer_push_allocates_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = RecorderConfig { dir: dir.path().to_owned(), flush_interval_ms: 10, ..Default::default() };
    let (mut p, h) = recorder::start::<Cycle, 1024>(&cfg, RunInfo::new("test", "")).unwrap();
    let before = allocs();
    let mut accepted = 0u64;
    for seq in 0..20_000u64 {
        // Pushes beyond the capacity are refused: that path must not allocate either.
        accepted += u64::from(p.push(Cycle { seq, q: [seq as f64; 6] }));
    }
    let during = allocs() - before;
    let s = h.shutdown().unwrap();
    assert_eq!(during, 0, "push allocated {during} times");
    assert_eq!(s.pushed, accepted);
    assert_eq!(s.pushed + s.dropped_queue_full, 20_000);
    assert_eq!(s.written, accepted);
}

#[test]
fn clock_and_progress_allocate_nothing() {
    let progress = LoopProgress::new();
    let mut periodic = Periodic::new(1_000_000).unwrap();
    let before = allocs();
    let mut late = 0;
    for _ in 0..100 {
        let tick = periodic.wait().unwrap();
        late += tick.late_ns;
        progress.record_cycle(true, 1, 0);
    }
    sleep_until_ns(monotonic_now_ns() + 100_000).unwrap();
    let n = allocs() - before;
    assert_eq!(n, 0, "the clock or the progress counter allocated {n} times");
    assert_eq!(progress.snapshot().cycles, 100);
    std::hint::black_box(late);
}
