//! systemd supervision: readiness, watchdog pings tied to the loop's progress, status lines.
//!
//! The real-time loop only stores atomics into a [`LoopProgress`] once a cycle
//! ([`LoopProgress::record_cycle`]: no allocation, no system call). A supervisor thread (normal
//! priority) started by [`Watchdog::spawn`] reads them and talks to systemd over the
//! `NOTIFY_SOCKET` datagram socket:
//!
//! - `READY=1` once the loop reports its first valid cycle (so `systemctl start` returns only
//!   when the daemon really works; `TimeoutStartSec=` bounds the wait);
//! - `WATCHDOG=1` every half `WatchdogSec=`, but only if the cycle counter advanced since the
//!   previous ping: a stalled loop stops the pings and systemd restarts the service;
//! - `STATUS=...` about once a second (`systemctl status` shows it);
//! - `STOPPING=1` on [`WatchdogHandle::shutdown`].
//!
//! Outside systemd (`NOTIFY_SOCKET` unset) the supervisor does nothing and nothing fails.
//! `sd-notify` supplies the message formats ([`sd_notify::NotifyState`]) and the
//! `WATCHDOG_USEC`/`WATCHDOG_PID` parsing; the datagrams are sent from one socket kept open
//! (which also supports abstract `@` socket names).

use std::io;
use std::os::linux::net::SocketAddrExt;
use std::os::unix::net::{SocketAddr, UnixDatagram};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

use sd_notify::NotifyState;

/// How often a `STATUS=` line is sent.
pub const STATUS_INTERVAL: Duration = Duration::from_secs(1);
/// How often the supervisor looks for the first valid cycle before `READY=1`.
const READY_POLL: Duration = Duration::from_millis(10);

// ---------------------------------------------------------------------------------------------
// Loop side

#[derive(Debug, Default)]
struct ProgressInner {
    cycles: AtomicU64,
    first_valid_seen: AtomicBool,
    last_state: AtomicU32,
    last_health: AtomicU32,
}

/// The loop's progress, shared (cheap to clone) between the real-time loop and the supervisor.
#[derive(Clone, Debug, Default)]
pub struct LoopProgress {
    inner: Arc<ProgressInner>,
}

/// A copy of [`LoopProgress`] at one instant.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ProgressSnapshot {
    /// Cycles completed since start.
    pub cycles: u64,
    /// Whether a valid cycle has been seen (the daemon is ready).
    pub first_valid_seen: bool,
    /// The loop's state code at its last cycle (meaning defined by the loop).
    pub last_state: u32,
    /// The loop's health flags at its last cycle (bit meanings defined by the loop).
    pub last_health: u32,
}

impl LoopProgress {
    /// A counter at zero.
    pub fn new() -> Self {
        Self::default()
    }

    /// Called by the real-time loop once a cycle: stores `state` and `health`, marks the first
    /// valid cycle when `valid`, then increments the cycle counter.
    ///
    /// **Real-time (1 kHz loop):** called once a cycle; relaxed atomic stores only.
    #[inline]
    pub fn record_cycle(&self, valid: bool, state: u32, health: u32) {
        let p = &*self.inner;
        p.last_state.store(state, Ordering::Relaxed);
        p.last_health.store(health, Ordering::Relaxed);
        if valid && !p.first_valid_seen.load(Ordering::Relaxed) {
            p.first_valid_seen.store(true, Ordering::Relaxed);
        }
        // Release: a reader that sees the new count also sees the stores above.
        p.cycles.fetch_add(1, Ordering::Release);
    }

    /// Reads the progress.
    pub fn snapshot(&self) -> ProgressSnapshot {
        let p = &*self.inner;
        let cycles = p.cycles.load(Ordering::Acquire);
        ProgressSnapshot {
            cycles,
            first_valid_seen: p.first_valid_seen.load(Ordering::Relaxed),
            last_state: p.last_state.load(Ordering::Relaxed),
            last_health: p.last_health.load(Ordering::Relaxed),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// systemd environment

/// Where and how often to notify systemd.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SystemdNotify {
    /// The notification socket: a path, or an abstract name starting with `@`.
    pub socket: PathBuf,
    /// `WatchdogSec=` as passed in `WATCHDOG_USEC`; `None` when the watchdog is off.
    pub watchdog: Option<Duration>,
}

impl SystemdNotify {
    /// From the environment systemd sets: `NOTIFY_SOCKET`, and `WATCHDOG_USEC` (honoured only
    /// if `WATCHDOG_PID` is unset or this process). `None` outside systemd.
    pub fn from_env() -> Option<Self> {
        let socket = std::env::var_os("NOTIFY_SOCKET")?;
        if socket.is_empty() {
            return None;
        }
        Some(Self { socket: PathBuf::from(socket), watchdog: sd_notify::watchdog_enabled() })
    }
}

/// A datagram socket connected to systemd.
struct Notifier {
    sock: UnixDatagram,
    send_errors: u64,
    last_error_log: Option<Instant>,
}

impl Notifier {
    fn connect(target: &std::path::Path) -> io::Result<Self> {
        let sock = UnixDatagram::unbound()?;
        let bytes = target.as_os_str().as_encoded_bytes();
        if let Some(name) = bytes.strip_prefix(b"@") {
            sock.connect_addr(&SocketAddr::from_abstract_name(name)?)?;
        } else {
            sock.connect(target)?;
        }
        Ok(Self { sock, send_errors: 0, last_error_log: None })
    }

    fn send(&mut self, states: &[NotifyState<'_>]) -> bool {
        let mut msg = String::new();
        for s in states {
            msg.push_str(&s.to_string());
            msg.push('\n');
        }
        match self.sock.send(msg.as_bytes()) {
            Ok(n) if n == msg.len() => true,
            result => {
                self.send_errors += 1;
                if self.last_error_log.is_none_or(|t| t.elapsed() >= Duration::from_secs(1)) {
                    tracing::warn!(?result, "watchdog: cannot notify systemd");
                    self.last_error_log = Some(Instant::now());
                }
                false
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Supervisor

/// What the supervisor sent, returned by [`WatchdogHandle::shutdown`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WatchdogReport {
    /// Whether `READY=1` was sent.
    pub ready_sent: bool,
    /// `WATCHDOG=1` pings sent.
    pub pings_sent: u64,
    /// Pings withheld because the loop had not advanced.
    pub pings_withheld: u64,
    /// `STATUS=` lines sent.
    pub status_sent: u64,
    /// Datagrams that could not be sent.
    pub send_errors: u64,
}

/// Why the supervisor could not start.
#[derive(Debug, thiserror::Error)]
pub enum WatchdogSpawnError {
    /// The notification socket could not be opened or connected.
    #[error("watchdog: cannot connect to NOTIFY_SOCKET {socket}: {source}")]
    Connect {
        /// The socket.
        socket: PathBuf,
        /// OS error.
        source: io::Error,
    },
    /// A zero watchdog period.
    #[error("watchdog: WATCHDOG_USEC is 0")]
    ZeroWatchdog,
    /// The thread could not be spawned.
    #[error("watchdog: cannot spawn the supervisor thread: {0}")]
    Spawn(io::Error),
}

/// Why [`WatchdogHandle::shutdown`] could not return a report.
#[derive(Debug, thiserror::Error)]
pub enum WatchdogJoinError {
    /// The supervisor thread panicked (a bug, most likely in the status function).
    #[error("watchdog: the supervisor thread panicked")]
    Panicked,
}

/// Starts the supervisor.
pub struct Watchdog;

impl Watchdog {
    /// Supervises `progress` for the systemd found in the environment ([`SystemdNotify::from_env`]);
    /// outside systemd returns an inactive handle. `status` turns a snapshot into the `STATUS=` text.
    pub fn spawn<F>(progress: LoopProgress, status: F) -> Result<WatchdogHandle, WatchdogSpawnError>
    where
        F: FnMut(&ProgressSnapshot) -> String + Send + 'static,
    {
        Self::spawn_with(progress, status, SystemdNotify::from_env())
    }

    /// As [`Watchdog::spawn`], with the socket and watchdog period given (`None`: inactive).
    pub fn spawn_with<F>(
        progress: LoopProgress,
        status: F,
        target: Option<SystemdNotify>,
    ) -> Result<WatchdogHandle, WatchdogSpawnError>
    where
        F: FnMut(&ProgressSnapshot) -> String + Send + 'static,
    {
        let Some(target) = target else {
            tracing::debug!("watchdog: not under systemd (NOTIFY_SOCKET unset): supervisor inactive");
            return Ok(WatchdogHandle { stop: Arc::new(AtomicBool::new(false)), thread: None });
        };
        if target.watchdog == Some(Duration::ZERO) {
            return Err(WatchdogSpawnError::ZeroWatchdog);
        }
        let notifier = Notifier::connect(&target.socket)
            .map_err(|source| WatchdogSpawnError::Connect { socket: target.socket.clone(), source })?;
        let stop = Arc::new(AtomicBool::new(false));
        let sup =
            Supervisor { progress, status, notifier, ping_every: target.watchdog.map(|w| w / 2), stop: stop.clone() };
        let thread = thread::Builder::new()
            .name("watchdog".into())
            .spawn(move || sup.run())
            .map_err(WatchdogSpawnError::Spawn)?;
        Ok(WatchdogHandle { stop, thread: Some(thread) })
    }
}

/// The running supervisor. Dropping it shuts it down too (sending `STOPPING=1`).
pub struct WatchdogHandle {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<WatchdogReport>>,
}

impl WatchdogHandle {
    /// Whether a supervisor thread runs (false outside systemd).
    pub fn is_active(&self) -> bool {
        self.thread.is_some()
    }

    /// Sends `STOPPING=1`, stops the supervisor and returns what it sent.
    pub fn shutdown(mut self) -> Result<WatchdogReport, WatchdogJoinError> {
        self.stop_thread()
    }

    fn stop_thread(&mut self) -> Result<WatchdogReport, WatchdogJoinError> {
        let Some(t) = self.thread.take() else { return Ok(WatchdogReport::default()) };
        self.stop.store(true, Ordering::SeqCst);
        t.thread().unpark();
        t.join().map_err(|_| WatchdogJoinError::Panicked)
    }
}

impl Drop for WatchdogHandle {
    fn drop(&mut self) {
        let _ = self.stop_thread();
    }
}

struct Supervisor<F> {
    progress: LoopProgress,
    status: F,
    notifier: Notifier,
    ping_every: Option<Duration>,
    stop: Arc<AtomicBool>,
}

impl<F: FnMut(&ProgressSnapshot) -> String> Supervisor<F> {
    fn run(mut self) -> WatchdogReport {
        let mut report = WatchdogReport::default();
        // Phase 1: wait for the first valid cycle.
        loop {
            if self.stop.load(Ordering::SeqCst) {
                return self.finish(report);
            }
            let snap = self.progress.snapshot();
            if snap.first_valid_seen {
                let text = (self.status)(&snap);
                let mut states = vec![NotifyState::Ready, NotifyState::Status(&text)];
                if self.ping_every.is_some() {
                    states.push(NotifyState::Watchdog);
                }
                if self.notifier.send(&states) {
                    report.ready_sent = true;
                    report.status_sent += 1;
                    report.pings_sent += u64::from(self.ping_every.is_some());
                    tracing::info!(cycles = snap.cycles, "watchdog: first valid cycle: READY=1 sent");
                }
                break;
            }
            thread::park_timeout(READY_POLL);
        }
        // Phase 2: pings and status.
        let start = Instant::now();
        let mut last_pinged = self.progress.snapshot().cycles;
        let mut last_advance = Instant::now();
        let mut next_ping = self.ping_every.map(|p| start + p);
        let mut next_status = start + STATUS_INTERVAL;
        let mut stalled = false;
        loop {
            if self.stop.load(Ordering::SeqCst) {
                return self.finish(report);
            }
            let now = Instant::now();
            if let (Some(at), Some(every)) = (next_ping, self.ping_every)
                && now >= at
            {
                let cycles = self.progress.snapshot().cycles;
                if cycles != last_pinged {
                    if self.notifier.send(&[NotifyState::Watchdog]) {
                        report.pings_sent += 1;
                    }
                    if stalled {
                        tracing::warn!(cycles, "watchdog: the loop advances again: pings resumed");
                    }
                    last_pinged = cycles;
                    last_advance = now;
                    stalled = false;
                } else {
                    report.pings_withheld += 1;
                    if !stalled {
                        tracing::error!(
                            cycles,
                            "watchdog: the loop has not advanced for {} ms: WATCHDOG=1 withheld (systemd \
                             restarts the service after WatchdogSec)",
                            now.duration_since(last_advance).as_millis()
                        );
                    }
                    stalled = true;
                }
                // Keep the cadence; after a long scheduling delay, restart it from now.
                let mut next = at + every;
                if next <= now {
                    next = now + every;
                }
                next_ping = Some(next);
            }
            if now >= next_status {
                let snap = self.progress.snapshot();
                let mut text = (self.status)(&snap);
                if stalled {
                    text = format!("STALLED for {} ms: {text}", now.duration_since(last_advance).as_millis());
                }
                if self.notifier.send(&[NotifyState::Status(&text)]) {
                    report.status_sent += 1;
                }
                next_status += STATUS_INTERVAL;
                if next_status <= now {
                    next_status = now + STATUS_INTERVAL;
                }
            }
            let wake = next_ping.map_or(next_status, |p| p.min(next_status));
            thread::park_timeout(wake.saturating_duration_since(Instant::now()));
        }
    }

    fn finish(mut self, mut report: WatchdogReport) -> WatchdogReport {
        let snap = self.progress.snapshot();
        let text = format!("stopping after {} cycles", snap.cycles);
        self.notifier.send(&[NotifyState::Stopping, NotifyState::Status(&text)]);
        report.send_errors = self.notifier.send_errors;
        report
    }
}

/// A default `STATUS=` text: `cycle N, state S, health 0xHHHHHHHH`.
pub fn default_status(s: &ProgressSnapshot) -> String {
    format!("cycle {}, state {}, health {:#010x}", s.cycles, s.last_state, s.last_health)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::process::Command;

    /// Collects the datagrams arriving on `sock` for `for_time`, each split into its lines.
    fn collect(sock: &UnixDatagram, for_time: Duration) -> Vec<(Instant, String)> {
        let end = Instant::now() + for_time;
        let mut got = Vec::new();
        let mut buf = [0u8; 4096];
        loop {
            let left = end.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return got;
            }
            sock.set_read_timeout(Some(left)).unwrap();
            match sock.recv(&mut buf) {
                Ok(n) => {
                    let at = Instant::now();
                    for line in String::from_utf8_lossy(&buf[..n]).lines() {
                        got.push((at, line.to_string()));
                    }
                }
                Err(e) if matches!(e.kind(), io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut) => return got,
                Err(e) => panic!("recv: {e}"),
            }
        }
    }

    fn count(msgs: &[(Instant, String)], line: &str) -> usize {
        msgs.iter().filter(|(_, l)| l == line).count()
    }

    /// A loop stand-in: advances `progress` every millisecond while `run` is set.
    fn fake_loop(progress: LoopProgress, run: Arc<AtomicBool>, quit: Arc<AtomicBool>) -> JoinHandle<()> {
        thread::spawn(move || {
            while !quit.load(Ordering::SeqCst) {
                if run.load(Ordering::SeqCst) {
                    progress.record_cycle(true, 2, 0);
                }
                thread::sleep(Duration::from_millis(1));
            }
        })
    }

    #[test]
    fn without_systemd_the_supervisor_is_inactive_and_does_not_fail() {
        let h = Watchdog::spawn_with(LoopProgress::new(), default_status, None).unwrap();
        assert!(!h.is_active());
        assert_eq!(h.shutdown().unwrap(), WatchdogReport::default());
    }

    #[test]
    fn unreachable_socket_is_a_typed_error() {
        let dir = tempfile::tempdir().unwrap();
        let target = SystemdNotify { socket: dir.path().join("nobody-listens"), watchdog: None };
        let e = Watchdog::spawn_with(LoopProgress::new(), default_status, Some(target)).err().unwrap();
        assert!(matches!(e, WatchdogSpawnError::Connect { .. }), "{e}");
    }

    #[test]
    fn progress_snapshot_reflects_the_loop() {
        let p = LoopProgress::new();
        assert_eq!(p.snapshot(), ProgressSnapshot::default());
        p.record_cycle(false, 1, 0x10);
        assert_eq!(
            p.snapshot(),
            ProgressSnapshot { cycles: 1, first_valid_seen: false, last_state: 1, last_health: 0x10 }
        );
        p.record_cycle(true, 2, 0);
        p.record_cycle(false, 3, 0x1);
        let s = p.snapshot();
        assert_eq!((s.cycles, s.first_valid_seen, s.last_state, s.last_health), (3, true, 3, 1));
        assert_eq!(default_status(&s), "cycle 3, state 3, health 0x00000001");
    }

    #[test]
    fn ready_after_first_valid_cycle_and_pings_only_while_the_loop_advances() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("notify.sock");
        let sock = UnixDatagram::bind(&path).unwrap();
        let progress = LoopProgress::new();
        // Invalid cycles advance the counter but must not make the daemon ready.
        for _ in 0..10 {
            progress.record_cycle(false, 0, 1);
        }
        let target = SystemdNotify { socket: path.clone(), watchdog: Some(Duration::from_millis(200)) };
        let h = Watchdog::spawn_with(progress.clone(), default_status, Some(target)).unwrap();
        assert!(h.is_active());

        let before = collect(&sock, Duration::from_millis(300));
        assert_eq!(count(&before, "READY=1"), 0, "READY before a valid cycle: {before:?}");
        assert_eq!(count(&before, "WATCHDOG=1"), 0, "pings before READY: {before:?}");

        let run = Arc::new(AtomicBool::new(true));
        let quit = Arc::new(AtomicBool::new(false));
        let looper = fake_loop(progress.clone(), run.clone(), quit.clone());
        let running = collect(&sock, Duration::from_millis(1300));
        assert_eq!(count(&running, "READY=1"), 1, "{running:?}");
        // Pings every 100 ms for ~1.3 s: expect about 13; a shared machine may delay a few.
        let pings = count(&running, "WATCHDOG=1");
        assert!((6..=16).contains(&pings), "{pings} pings while running: {running:?}");
        assert!(running.iter().any(|(_, l)| l.starts_with("STATUS=cycle ")), "{running:?}");

        // Stall the loop: after one ping interval of grace, no more pings.
        run.store(false, Ordering::SeqCst);
        let _grace = collect(&sock, Duration::from_millis(250));
        let stalled = collect(&sock, Duration::from_millis(1200));
        assert_eq!(count(&stalled, "WATCHDOG=1"), 0, "pings while stalled: {stalled:?}");
        assert!(stalled.iter().any(|(_, l)| l.starts_with("STATUS=STALLED for ")), "{stalled:?}");

        // The loop resumes: pings resume.
        run.store(true, Ordering::SeqCst);
        let resumed = collect(&sock, Duration::from_millis(500));
        assert!(count(&resumed, "WATCHDOG=1") >= 2, "{resumed:?}");

        let report = h.shutdown().unwrap();
        let last = collect(&sock, Duration::from_millis(200));
        assert_eq!(count(&last, "STOPPING=1"), 1, "{last:?}");
        assert!(report.ready_sent);
        assert!(report.pings_withheld >= 5, "{report:?}");
        assert_eq!(report.send_errors, 0);
        quit.store(true, Ordering::SeqCst);
        looper.join().unwrap();
    }

    #[test]
    fn no_watchdog_means_no_pings_but_ready_and_stopping() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("notify.sock");
        let sock = UnixDatagram::bind(&path).unwrap();
        let progress = LoopProgress::new();
        progress.record_cycle(true, 1, 0);
        let target = SystemdNotify { socket: path, watchdog: None };
        let h = Watchdog::spawn_with(progress.clone(), |_| "custom status".into(), Some(target)).unwrap();
        let msgs = collect(&sock, Duration::from_millis(300));
        assert_eq!(count(&msgs, "READY=1"), 1, "{msgs:?}");
        assert_eq!(count(&msgs, "STATUS=custom status"), 1, "{msgs:?}");
        assert_eq!(count(&msgs, "WATCHDOG=1"), 0, "{msgs:?}");
        h.shutdown().unwrap();
        let last = collect(&sock, Duration::from_millis(200));
        assert_eq!(count(&last, "STOPPING=1"), 1, "{last:?}");
    }

    #[test]
    fn abstract_socket_names_are_supported() {
        let name = format!("comanip-test-{}-{}", std::process::id(), crate::recorder::new_run_id());
        let sock = UnixDatagram::bind_addr(&SocketAddr::from_abstract_name(name.as_bytes()).unwrap()).unwrap();
        let progress = LoopProgress::new();
        progress.record_cycle(true, 1, 0);
        let target = SystemdNotify { socket: PathBuf::from(format!("@{name}")), watchdog: None };
        let h = Watchdog::spawn_with(progress, default_status, Some(target)).unwrap();
        let msgs = collect(&sock, Duration::from_millis(300));
        assert_eq!(count(&msgs, "READY=1"), 1, "{msgs:?}");
        h.shutdown().unwrap();
    }

    /// Child: uses the environment (NOTIFY_SOCKET, WATCHDOG_USEC) as under systemd.
    #[test]
    #[ignore = "run by environment_path_in_a_child_process"]
    fn child_watchdog_from_env() {
        if std::env::var_os("COMANIP_WATCHDOG_CHILD").is_none() {
            return;
        }
        let target = SystemdNotify::from_env().expect("NOTIFY_SOCKET set by the parent");
        assert_eq!(target.watchdog, Some(Duration::from_millis(200)));
        let progress = LoopProgress::new();
        let run = Arc::new(AtomicBool::new(true));
        let quit = Arc::new(AtomicBool::new(false));
        let looper = fake_loop(progress.clone(), run, quit.clone());
        let h = Watchdog::spawn(progress, default_status).unwrap();
        assert!(h.is_active());
        thread::sleep(Duration::from_millis(600));
        let report = h.shutdown().unwrap();
        assert!(report.ready_sent && report.pings_sent >= 3, "{report:?}");
        quit.store(true, Ordering::SeqCst);
        looper.join().unwrap();
    }

    #[test]
    fn environment_path_in_a_child_process() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("notify.sock");
        let sock = UnixDatagram::bind(&path).unwrap();
        let out = Command::new(std::env::current_exe().unwrap())
            .args(["--exact", "watchdog::tests::child_watchdog_from_env", "--ignored", "--nocapture"])
            .env("COMANIP_WATCHDOG_CHILD", "1")
            .env("NOTIFY_SOCKET", &path)
            .env("WATCHDOG_USEC", "200000")
            .env_remove("WATCHDOG_PID")
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(
            out.status.success() && stdout.contains("1 passed"),
            "{stdout}\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let msgs = collect(&sock, Duration::from_millis(100));
        assert_eq!(count(&msgs, "READY=1"), 1, "{msgs:?}");
        assert!(count(&msgs, "WATCHDOG=1") >= 3, "{msgs:?}");
        assert_eq!(count(&msgs, "STOPPING=1"), 1, "{msgs:?}");
    }
}
