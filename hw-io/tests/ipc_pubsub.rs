//! The fulcrum output within one process: start order, blocking wait, continuity, version
//! refusal, overflow, capacity limits, signal handlers. Every test uses its own service name.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::time::{Duration, Instant};

use hw_io::ipc::{
    ConnectError, Continuity, CreateError, FULCRUM_SAMPLE_VERSION, FulcrumPublisher, FulcrumSample, FulcrumSubscriber,
    HealthFlags, OpenError, OutputState, PublisherOptions, RecvError, WaitError,
};
use nix::time::{ClockId, clock_gettime};

fn service(test: &str) -> String {
    format!("comanip-test/{}/{test}", std::process::id())
}

fn sample(run_id: u64, sequence: u64) -> FulcrumSample {
    let mut s = FulcrumSample::invalid(HealthFlags::empty());
    s.run_id = run_id;
    s.sequence = sequence;
    s
}

fn thread_cpu_time() -> Duration {
    let ts = clock_gettime(ClockId::CLOCK_THREAD_CPUTIME_ID).unwrap();
    Duration::new(ts.tv_sec() as u64, ts.tv_nsec() as u32)
}

#[test]
fn subscriber_started_before_the_daemon_receives_every_field_in_order() {
    let name = service("sub-first");
    let mut sub = FulcrumSubscriber::connect(&name).unwrap();
    assert!(sub.try_recv().unwrap().is_none());
    let mut publisher = FulcrumPublisher::create(&name, &PublisherOptions::default()).unwrap();
    let mut inside = sample(42, 0);
    inside.state = OutputState::Inside.into();
    inside.fulcrum_base_m = [0.1, -0.2, 0.3];
    inside.joints_rad = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
    inside.timestamp_ns = 123_456_789;
    inside.prev_cycle_compute_ns = 77;
    for seq in 0..10 {
        publisher.publish(&FulcrumSample { sequence: seq, ..inside }).unwrap();
    }
    assert_eq!(publisher.published(), 10);
    for seq in 0..10 {
        let r = sub.wait(Duration::from_secs(1)).unwrap().expect("a sample");
        assert_eq!(r.sample, FulcrumSample { sequence: seq, ..inside });
        assert_eq!(r.event, if seq == 0 { Continuity::First } else { Continuity::InOrder });
    }
    assert_eq!(r_fulcrum(&mut sub, &mut publisher, inside), Some([0.1, -0.2, 0.3]));
    let c = sub.counters();
    assert_eq!((c.received, c.missed, c.restarts, c.rejected), (11, 0, 0, 0));
}

fn r_fulcrum(sub: &mut FulcrumSubscriber, publisher: &mut FulcrumPublisher, s: FulcrumSample) -> Option<[f64; 3]> {
    publisher.publish(&FulcrumSample { sequence: 10, ..s }).unwrap();
    sub.try_recv().unwrap().and_then(|r| r.sample.fulcrum())
}

#[test]
fn wait_times_out_without_busy_polling() {
    let name = service("timeout");
    let mut sub = FulcrumSubscriber::connect(&name).unwrap();
    let cpu = thread_cpu_time();
    let start = Instant::now();
    assert!(sub.wait(Duration::from_millis(300)).unwrap().is_none());
    let waited = start.elapsed();
    let used = thread_cpu_time() - cpu;
    assert!(waited >= Duration::from_millis(300), "returned after {waited:?}");
    assert!(used < Duration::from_millis(30), "{used:?} of CPU in a 300 ms wait");
}

#[test]
fn blocked_wait_wakes_up_when_the_daemon_publishes() {
    let name = service("wake");
    let mut sub = FulcrumSubscriber::connect(&name).unwrap();
    let publisher_name = name.clone();
    const N: u64 = 10;
    let publisher = std::thread::spawn(move || {
        let mut publisher = FulcrumPublisher::create(&publisher_name, &PublisherOptions::default()).unwrap();
        let mut sent = Vec::new();
        for seq in 0..N {
            // Irregular gaps, so that the publications fall anywhere in wait()'s 100 ms re-check.
            std::thread::sleep(Duration::from_millis(20 + 17 * (seq % 4)));
            sent.push(Instant::now());
            publisher.publish(&sample(1, seq)).unwrap();
        }
        std::thread::sleep(Duration::from_millis(100)); // keep the publisher alive meanwhile
        sent
    });
    let mut woke = Vec::new();
    for seq in 0..N {
        let r = sub.wait(Duration::from_secs(5)).unwrap().expect("woken by the publish");
        woke.push(Instant::now());
        assert_eq!(r.sample.sequence, seq);
    }
    let sent = publisher.join().unwrap();
    let mut delays: Vec<Duration> = woke.iter().zip(&sent).map(|(w, s)| w.duration_since(*s)).collect();
    delays.sort();
    // Woken by the notification (well under 1 ms unloaded), not by the 100 ms re-check (which
    // would give a median of about 50 ms).
    assert!(delays[N as usize / 2] < Duration::from_millis(15), "wake-up delays {delays:?}");
}

#[test]
fn a_sequence_jump_is_a_gap_and_a_new_run_is_a_restart() {
    let name = service("continuity");
    let mut publisher = FulcrumPublisher::create(&name, &PublisherOptions::default()).unwrap();
    let mut sub = FulcrumSubscriber::connect(&name).unwrap();
    for (run, seq) in [(5, 10), (5, 11), (5, 15), (6, 0), (6, 1), (6, 0)] {
        publisher.publish(&sample(run, seq)).unwrap();
    }
    let events: Vec<_> = std::iter::from_fn(|| sub.try_recv().unwrap()).map(|r| r.event).collect();
    use Continuity::*;
    assert_eq!(events, [First, InOrder, Gap { missed: 3 }, Restart, InOrder, Restart]);
    let c = sub.counters();
    assert_eq!((c.received, c.missed, c.restarts), (6, 3, 2));
}

#[test]
fn a_slow_subscriber_loses_the_oldest_samples_and_sees_the_gap() {
    let name = service("overflow");
    let opts = PublisherOptions { subscriber_buffer: 8, ..PublisherOptions::default() };
    let mut publisher = FulcrumPublisher::create(&name, &opts).unwrap();
    let mut sub = FulcrumSubscriber::connect_with(&name, &opts).unwrap();
    publisher.publish(&sample(1, 0)).unwrap();
    assert_eq!(sub.try_recv().unwrap().unwrap().event, Continuity::First);
    // 100 samples into a buffer of 8 that nobody reads: the publisher neither blocks nor fails.
    for seq in 1..=100 {
        publisher.publish(&sample(1, seq)).unwrap();
    }
    let got: Vec<_> = std::iter::from_fn(|| sub.try_recv().unwrap()).collect();
    assert_eq!(got.len(), 8);
    assert_eq!(got[0].sample.sequence, 93);
    assert_eq!(got[0].event, Continuity::Gap { missed: 92 });
    assert!(got[1..].iter().all(|r| r.event == Continuity::InOrder));
    assert_eq!(sub.counters().missed, 92);
}

#[test]
fn samples_of_another_layout_version_are_refused_and_counted() {
    let name = service("version");
    let mut publisher = FulcrumPublisher::create(&name, &PublisherOptions::default()).unwrap();
    let mut sub = FulcrumSubscriber::connect(&name).unwrap();
    publisher.publish(&sample(3, 0)).unwrap();
    publisher.publish(&FulcrumSample { version: FULCRUM_SAMPLE_VERSION + 1, ..sample(3, 1) }).unwrap();
    publisher.publish(&sample(3, 2)).unwrap();
    assert_eq!(sub.try_recv().unwrap().unwrap().event, Continuity::First);
    match sub.try_recv() {
        Err(RecvError::VersionMismatch { type_name, found, expected }) => {
            assert_eq!((found, expected), (FULCRUM_SAMPLE_VERSION + 1, FULCRUM_SAMPLE_VERSION));
            assert_eq!(type_name, "comanip::FulcrumSample");
        }
        other => panic!("expected a version mismatch, got {other:?}"),
    }
    // The refused sample does not take part in continuity: 2 follows 0 with a gap of one.
    let r = sub.try_recv().unwrap().unwrap();
    assert_eq!((r.sample.sequence, r.event), (2, Continuity::Gap { missed: 1 }));
    // wait() reports it the same way.
    publisher.publish(&FulcrumSample { version: 0, ..sample(3, 3) }).unwrap();
    assert!(matches!(sub.wait(Duration::from_secs(1)), Err(WaitError::Recv(RecvError::VersionMismatch { .. }))));
    assert_eq!(sub.counters().rejected, 2);
    assert_eq!(sub.counters().received, 2);
}

#[test]
fn a_second_daemon_on_the_same_output_is_refused() {
    let name = service("second-daemon");
    let _first = FulcrumPublisher::create(&name, &PublisherOptions::default()).unwrap();
    let second = FulcrumPublisher::create(&name, &PublisherOptions::default());
    assert!(matches!(second, Err(CreateError::Publisher(_))), "{second:?}");
}

#[test]
fn subscribers_beyond_the_limit_are_refused_until_one_leaves() {
    let name = service("max-subscribers");
    let opts = PublisherOptions { max_subscribers: 2, ..PublisherOptions::default() };
    let mut publisher = FulcrumPublisher::create(&name, &opts).unwrap();
    let a = FulcrumSubscriber::connect_with(&name, &opts).unwrap();
    let _b = FulcrumSubscriber::connect_with(&name, &opts).unwrap();
    assert!(matches!(FulcrumSubscriber::connect_with(&name, &opts), Err(ConnectError::Subscriber(_))));
    drop(a);
    let mut c = FulcrumSubscriber::connect_with(&name, &opts).unwrap();
    publisher.publish(&sample(9, 0)).unwrap();
    assert_eq!(c.wait(Duration::from_secs(1)).unwrap().map(|r| r.sample.run_id), Some(9));
}

#[test]
fn mismatched_capacities_are_an_error_not_a_silent_downgrade() {
    let name = service("mismatch");
    let _sub = FulcrumSubscriber::connect(&name).unwrap(); // creates with the defaults (buffer 64)
    let bigger = PublisherOptions { subscriber_buffer: 128, ..PublisherOptions::default() };
    assert!(matches!(FulcrumPublisher::create(&name, &bigger), Err(CreateError::Open(OpenError::Service(_)))));
    assert!(FulcrumPublisher::create(&name, &PublisherOptions::default()).is_ok());
}

#[test]
fn invalid_names_and_options_are_typed_errors() {
    assert!(matches!(FulcrumSubscriber::connect(""), Err(ConnectError::Open(OpenError::InvalidServiceName { .. }))));
    assert!(matches!(
        FulcrumPublisher::create(&"x".repeat(10_000), &PublisherOptions::default()),
        Err(CreateError::Open(OpenError::InvalidServiceName { .. }))
    ));
    let zero = PublisherOptions { subscriber_buffer: 0, ..PublisherOptions::default() };
    assert!(matches!(
        FulcrumPublisher::create(&service("bad-opts"), &zero),
        Err(CreateError::Open(OpenError::InvalidOptions(_)))
    ));
    let history = PublisherOptions { history: 65, ..PublisherOptions::default() };
    assert!(matches!(
        FulcrumSubscriber::connect_with(&service("bad-opts"), &history),
        Err(ConnectError::Open(OpenError::InvalidOptions(_)))
    ));
}

#[test]
fn default_options_install_no_signal_handler() {
    let name = service("signals");
    let mut sub = FulcrumSubscriber::connect(&name).unwrap();
    let mut publisher = FulcrumPublisher::create(&name, &PublisherOptions::default()).unwrap();
    publisher.publish(&sample(1, 0)).unwrap();
    assert!(sub.wait(Duration::from_secs(1)).unwrap().is_some());
    assert!(sub.wait(Duration::from_millis(5)).unwrap().is_none());
    assert!(!publisher.termination_requested());
    for signal in [libc::SIGINT, libc::SIGTERM, libc::SIGQUIT, libc::SIGUSR1] {
        // SAFETY: querying (not changing) the disposition into a zeroed struct.
        let mut action: libc::sigaction = unsafe { std::mem::zeroed() };
        // SAFETY: a null new action only queries; `action` is valid and writable.
        assert_eq!(unsafe { libc::sigaction(signal, std::ptr::null(), &mut action) }, 0);
        // No handler function: the default, or "ignored" as inherited from the parent (a
        // shell's background job starts with SIGINT and SIGQUIT ignored).
        assert!(
            action.sa_sigaction == libc::SIG_DFL || action.sa_sigaction == libc::SIG_IGN,
            "signal {signal} has a handler ({:#x})",
            action.sa_sigaction
        );
    }
}

#[test]
fn payload_type_name_is_stable_for_other_languages() {
    use iceoryx2::prelude::ZeroCopySend;
    // SAFETY: `type_name` only returns the name given in `#[type_name]`.
    assert_eq!(unsafe { <FulcrumSample as ZeroCopySend>::type_name() }, "comanip::FulcrumSample");
}

#[test]
fn layout_table_of_docs_output_md_matches_the_struct() {
    use std::mem::{offset_of, size_of};
    let expected: [(&str, &str, usize); 20] = [
        ("version", "`u32`", offset_of!(FulcrumSample, version)),
        ("state", "`u32`", offset_of!(FulcrumSample, state)),
        ("sequence", "`u64`", offset_of!(FulcrumSample, sequence)),
        ("run_id", "`u64`", offset_of!(FulcrumSample, run_id)),
        ("timestamp_ns", "`u64`", offset_of!(FulcrumSample, timestamp_ns)),
        ("health", "`u32`", offset_of!(FulcrumSample, health)),
        ("trocar_id", "`u32`", offset_of!(FulcrumSample, trocar_id)),
        ("fulcrum_base_m", "`[f64; 3]`", offset_of!(FulcrumSample, fulcrum_base_m)),
        ("residual_m", "`f64`", offset_of!(FulcrumSample, residual_m)),
        ("fulcrum_std_m", "`f64`", offset_of!(FulcrumSample, fulcrum_std_m)),
        ("conditioning", "`f64`", offset_of!(FulcrumSample, conditioning)),
        ("wrist_base_m", "`[f64; 3]`", offset_of!(FulcrumSample, wrist_base_m)),
        ("axis_base", "`[f64; 3]`", offset_of!(FulcrumSample, axis_base)),
        ("joints_rad", "`[f64; 6]`", offset_of!(FulcrumSample, joints_rad)),
        ("window_fill", "`u16`", offset_of!(FulcrumSample, window_fill)),
        ("window_len", "`u16`", offset_of!(FulcrumSample, window_len)),
        ("fit_lines", "`u16`", offset_of!(FulcrumSample, fit_lines)),
        ("reserved", "`u16`", offset_of!(FulcrumSample, reserved)),
        ("wake_late_ns", "`u32`", offset_of!(FulcrumSample, wake_late_ns)),
        ("prev_cycle_compute_ns", "`u32`", offset_of!(FulcrumSample, prev_cycle_compute_ns)),
    ];
    let doc = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/output.md")).unwrap();
    let section = doc.split("## Message layout").nth(1).unwrap().split("\n### ").next().unwrap();
    let rows: Vec<Vec<&str>> = section
        .lines()
        .filter(|l| l.starts_with("| `"))
        .map(|l| l.split('|').map(str::trim).filter(|c| !c.is_empty()).collect())
        .collect();
    assert_eq!(rows.len(), expected.len(), "one row per field");
    for (row, (name, ty, offset)) in rows.iter().zip(expected) {
        assert_eq!(row[0], format!("`{name}`"));
        assert_eq!(row[1], ty, "type of {name}");
        assert_eq!(row[2].parse::<usize>().unwrap(), offset, "offset of {name}");
    }
    // The last field (u32) ends the struct: no trailing padding.
    assert_eq!(offset_of!(FulcrumSample, prev_cycle_compute_ns) + 4, size_of::<FulcrumSample>());
    assert!(doc.contains(&format!("`0x{:04X}`", HealthFlags::INVALIDATING.bits())));
}
