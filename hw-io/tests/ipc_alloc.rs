//! Publishing at 1 kHz from a real-time thread makes no system allocation when that thread is
//! marked with `rt_alloc::enter_realtime`, and does make one per sample when it is not (so the
//! test is sensitive and iceoryx2's per-sample `Rc` is real).
//!
//! This binary's global allocator is `RtPoolAllocator`, exactly as fulcrumd declares it. Only one
//! test here marks a thread real-time, so the process-wide real-time counters are its own.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use hw_io::ipc::{Continuity, FulcrumPublisher, FulcrumSample, FulcrumSubscriber, HealthFlags, PublisherOptions};
use hw_io::rt_alloc::{self, RtPoolAllocator};

#[global_allocator]
static ALLOC: RtPoolAllocator = RtPoolAllocator::new();

fn service(test: &str) -> String {
    format!("comanip-test/{}/{test}", std::process::id())
}

fn sample(run_id: u64, sequence: u64) -> FulcrumSample {
    let mut s = FulcrumSample::invalid(HealthFlags::empty());
    s.run_id = run_id;
    s.sequence = sequence;
    s
}

/// Publishes `count` samples (sequence from `first`) and reads them all back on the same thread.
fn publish_and_drain(publisher: &mut FulcrumPublisher, subscriber: &mut FulcrumSubscriber, first: u64, count: u64) {
    for seq in first..first + count {
        publisher.publish(&sample(1, seq)).unwrap();
        if seq % 16 == 15 {
            while let Some(r) = subscriber.try_recv().unwrap() {
                assert_eq!(r.event, if r.sample.sequence == 0 { Continuity::First } else { Continuity::InOrder });
            }
        }
    }
    while subscriber.try_recv().unwrap().is_some() {}
}

#[test]
fn publishing_in_realtime_mode_makes_no_system_allocation() {
    std::thread::spawn(|| {
        let name = service("realtime");
        let mut subscriber = FulcrumSubscriber::connect(&name).unwrap();
        let mut publisher = FulcrumPublisher::create(&name, &PublisherOptions::default()).unwrap();
        publish_and_drain(&mut publisher, &mut subscriber, 0, 100); // warm-up: connections
        rt_alloc::prefault_pool();

        const N: u64 = 100_000;
        let before = rt_alloc::stats();
        let thread_before = rt_alloc::thread_system_allocs();
        rt_alloc::enter_realtime();
        publish_and_drain(&mut publisher, &mut subscriber, 100, N);
        rt_alloc::leave_realtime();
        let thread_allocs = rt_alloc::thread_system_allocs() - thread_before;
        let after = rt_alloc::stats();

        assert_eq!(thread_allocs, 0, "system allocations by the real-time thread");
        assert_eq!(after.realtime_system_allocs, before.realtime_system_allocs);
        assert_eq!(after.realtime_system_frees, before.realtime_system_frees);
        assert_eq!(after.pool_fallbacks, before.pool_fallbacks);
        assert!(after.pool_allocs - before.pool_allocs >= N, "every publish took a pool block: {after:?}");
        assert_eq!(after.pool_in_use, before.pool_in_use, "every block returned");
        assert!(after.pool_high_water <= 8, "a handful of blocks suffice: {after:?}");
        let c = subscriber.counters();
        assert_eq!((c.received, c.missed, c.restarts), (100 + N, 0, 0));
    })
    .join()
    .unwrap();
}

#[test]
fn publishing_without_realtime_mode_allocates_once_per_sample() {
    std::thread::spawn(|| {
        let name = service("not-realtime");
        let mut subscriber = FulcrumSubscriber::connect(&name).unwrap();
        let mut publisher = FulcrumPublisher::create(&name, &PublisherOptions::default()).unwrap();
        publish_and_drain(&mut publisher, &mut subscriber, 0, 100);

        const N: u64 = 1000;
        let before = rt_alloc::thread_system_allocs();
        publish_and_drain(&mut publisher, &mut subscriber, 100, N);
        let allocs = rt_alloc::thread_system_allocs() - before;
        assert!(allocs >= N, "{allocs} system allocations for {N} publishes");
        assert_eq!(subscriber.counters().received, 100 + N);
    })
    .join()
    .unwrap();
}
