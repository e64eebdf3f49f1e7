//! The fulcrum output between real processes: a daemon SIGKILLed and restarted under a running
//! subscriber, subscribers SIGKILLed and restarted under a running daemon, and what SIGTERM does
//! to a daemon with and without iceoryx2's signal handlers.
//!
//! The children are this test binary itself, re-executed on the test `child_process_entry` with
//! the role in the environment variable `COMANIP_IPC_TEST_CHILD`; without that variable that
//! test returns at once.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::io::{BufRead, BufReader};
use std::os::unix::process::ExitStatusExt;
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use hw_io::ipc::{Continuity, FulcrumPublisher, FulcrumSample, FulcrumSubscriber, HealthFlags, PublisherOptions};

const CHILD_ENV: &str = "COMANIP_IPC_TEST_CHILD";
const SERVICE_ENV: &str = "COMANIP_IPC_TEST_SERVICE";
const RUN_ID_ENV: &str = "COMANIP_IPC_TEST_RUN_ID";
const MAX_SUBSCRIBERS_ENV: &str = "COMANIP_IPC_TEST_MAX_SUBSCRIBERS";
/// A child never outlives this, whatever happens to its parent.
const CHILD_LIFETIME: Duration = Duration::from_secs(30);

fn service(test: &str) -> String {
    format!("comanip-test/{}/{test}", std::process::id())
}

fn sample(run_id: u64, sequence: u64) -> FulcrumSample {
    let mut s = FulcrumSample::invalid(HealthFlags::empty());
    s.run_id = run_id;
    s.sequence = sequence;
    s
}

/// A child process, SIGKILLed when dropped (a failing test leaves none behind).
struct ChildGuard(Child);

impl ChildGuard {
    fn spawn(role: &str, service: &str, extra: &[(&str, String)]) -> Self {
        let mut command = Command::new(std::env::current_exe().unwrap());
        command
            .args(["child_process_entry", "--exact", "--nocapture", "--test-threads=1", "--quiet"])
            .env(CHILD_ENV, role)
            .env(SERVICE_ENV, service)
            .stdin(Stdio::null())
            .stdout(Stdio::piped());
        for (k, v) in extra {
            command.env(k, v);
        }
        Self(command.spawn().unwrap())
    }

    /// SIGKILL, then reap; asserts that SIGKILL is what ended it.
    fn sigkill(mut self) {
        self.0.kill().unwrap();
        let status = self.0.wait().unwrap();
        assert_eq!(status.signal(), Some(libc::SIGKILL), "{status:?}");
    }

    /// The next stdout line starting with `CHILD:`, without the prefix; `None` at end of output.
    fn report(&mut self) -> Option<String> {
        let out = self.0.stdout.as_mut()?;
        let mut reader = BufReader::new(out);
        let mut line = String::new();
        loop {
            line.clear();
            if reader.read_line(&mut line).ok()? == 0 {
                return None;
            }
            if let Some(rest) = line.trim_end().strip_prefix("CHILD:") {
                return Some(rest.to_owned());
            }
        }
    }
}

impl Drop for ChildGuard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn env_u64(key: &str) -> u64 {
    std::env::var(key).ok().and_then(|v| v.parse().ok()).unwrap_or_else(|| panic!("{key} not set"))
}

/// Test helper, not a test: the body of the child processes (see the module documentation).
#[test]
fn child_process_entry() {
    let Ok(role) = std::env::var(CHILD_ENV) else { return };
    iceoryx2::prelude::set_log_level(iceoryx2::prelude::LogLevel::Error);
    let name = std::env::var(SERVICE_ENV).unwrap();
    let code = match role.as_str() {
        "publisher" => child_publisher(&name),
        "subscriber" => child_subscriber(&name),
        "sigterm-default" | "sigterm-iceoryx2" => child_sigterm(&name, role == "sigterm-iceoryx2"),
        _ => 2,
    };
    std::process::exit(code);
}

/// Publishes run `RUN_ID_ENV` at 1 kHz from sequence 0 until killed.
fn child_publisher(name: &str) -> i32 {
    let run_id = env_u64(RUN_ID_ENV);
    let mut publisher = FulcrumPublisher::create(name, &PublisherOptions::default()).unwrap();
    let start = Instant::now();
    let mut seq = 0;
    while start.elapsed() < CHILD_LIFETIME {
        publisher.publish(&sample(run_id, seq)).unwrap();
        seq += 1;
        std::thread::sleep(Duration::from_millis(1));
    }
    0
}

/// Receives 20 samples, reports `CHILD:ok <run_id> <first event>`, then idles until killed.
fn child_subscriber(name: &str) -> i32 {
    let opts = PublisherOptions { max_subscribers: env_u64(MAX_SUBSCRIBERS_ENV) as usize, ..Default::default() };
    let mut sub = FulcrumSubscriber::connect_with(name, &opts).unwrap();
    let first = sub.wait(Duration::from_secs(2)).unwrap().expect("a sample within 2 s");
    for _ in 0..19 {
        let r = sub.wait(Duration::from_secs(1)).unwrap().expect("a sample within 1 s");
        assert_eq!(r.event, Continuity::InOrder);
    }
    println!("CHILD:ok {} {:?}", first.sample.run_id, first.event);
    std::thread::sleep(CHILD_LIFETIME);
    0
}

/// Creates a publisher, raises SIGTERM at itself, exits 0 if it survived and iceoryx2 reported it.
fn child_sigterm(name: &str, iceoryx2_signal_handlers: bool) -> i32 {
    let opts = PublisherOptions { iceoryx2_signal_handlers, ..Default::default() };
    let publisher = FulcrumPublisher::create(name, &opts).unwrap();
    // SAFETY: sends a signal to this process; no memory is involved.
    unsafe { libc::raise(libc::SIGTERM) };
    std::thread::sleep(Duration::from_millis(50));
    if publisher.termination_requested() { 0 } else { 3 }
}

#[test]
fn daemon_sigkilled_and_restarted_under_a_running_subscriber_is_a_restart() {
    let name = service("daemon-restart");
    let mut sub = FulcrumSubscriber::connect(&name).unwrap(); // before any daemon
    let a = ChildGuard::spawn("publisher", &name, &[(RUN_ID_ENV, "1001".into())]);
    let first = sub.wait(Duration::from_secs(5)).unwrap().expect("daemon A publishes");
    assert_eq!((first.sample.run_id, first.event), (1001, Continuity::First));
    for _ in 0..20 {
        let r = sub.wait(Duration::from_secs(1)).unwrap().expect("daemon A keeps publishing");
        assert_eq!((r.sample.run_id, r.event), (1001, Continuity::InOrder));
    }
    a.sigkill();
    while let Some(r) = sub.try_recv().unwrap() {
        assert_eq!((r.sample.run_id, r.event), (1001, Continuity::InOrder)); // A's last samples
    }
    assert!(sub.wait(Duration::from_millis(50)).unwrap().is_none(), "nothing while no daemon runs");

    let restarted = Instant::now();
    let _b = ChildGuard::spawn("publisher", &name, &[(RUN_ID_ENV, "2002".into())]);
    let r = sub.wait(Duration::from_secs(1)).unwrap().expect("daemon B's first sample within 1 s");
    let delay = restarted.elapsed();
    eprintln!("daemon restart: first sample of the new run {delay:?} after its spawn");
    assert!(delay < Duration::from_secs(1));
    assert_eq!((r.sample.run_id, r.event), (2002, Continuity::Restart));
    for _ in 0..20 {
        let r = sub.wait(Duration::from_secs(1)).unwrap().expect("daemon B keeps publishing");
        assert_eq!((r.sample.run_id, r.event), (2002, Continuity::InOrder));
    }
    let c = sub.counters();
    assert_eq!((c.restarts, c.missed, c.rejected), (1, 0, 0));
}

#[test]
fn subscribers_sigkilled_and_restarted_under_a_running_daemon_keep_receiving() {
    let name = service("subscriber-restart");
    let max_subscribers = 2;
    let opts = PublisherOptions { max_subscribers, ..Default::default() };
    let stop = Arc::new(AtomicBool::new(false));
    let daemon = {
        let (name, stop) = (name.clone(), stop.clone());
        let (ready_tx, ready_rx) = std::sync::mpsc::channel();
        let handle = std::thread::spawn(move || {
            let mut publisher = FulcrumPublisher::create(&name, &opts).unwrap();
            ready_tx.send(()).unwrap();
            let mut seq = 0;
            while !stop.load(Ordering::Relaxed) {
                publisher.publish(&sample(77, seq)).unwrap(); // never fails, subscribers or not
                seq += 1;
                std::thread::sleep(Duration::from_millis(1));
            }
            seq
        });
        ready_rx.recv().unwrap();
        handle
    };
    // Twice as many subscriber lives as slots: dead subscribers' slots must be reclaimed.
    for round in 0..2 * max_subscribers {
        let mut child = ChildGuard::spawn("subscriber", &name, &[(MAX_SUBSCRIBERS_ENV, max_subscribers.to_string())]);
        let report = child.report();
        assert_eq!(report.as_deref(), Some("ok 77 First"), "subscriber {round}");
        child.sigkill();
    }
    stop.store(true, Ordering::Relaxed);
    let published = daemon.join().unwrap();
    assert!(published > 4 * 20, "{published}");
}

#[test]
fn sigterm_ends_the_daemon_unless_iceoryx2_handlers_are_asked_for() {
    let mut default = ChildGuard::spawn("sigterm-default", &service("sigterm-default"), &[]);
    let status = default.0.wait().unwrap();
    assert_eq!(status.signal(), Some(libc::SIGTERM), "default options: SIGTERM keeps its default action");

    let mut handled = ChildGuard::spawn("sigterm-iceoryx2", &service("sigterm-iceoryx2"), &[]);
    let status = handled.0.wait().unwrap();
    assert!(status.success(), "with iceoryx2's handlers the daemon survives and sees the request: {status:?}");
}
