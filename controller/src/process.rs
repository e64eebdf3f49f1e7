//! The skeleton of a comanip process: what `fulcrumd` does around its loop and what the next
//! processes (a tracking process `comanip-track`, live calibration `comanip-calib live`) reuse.
//!
//! | Piece | Here | Used by fulcrumd in |
//! |---|---|---|
//! | Logging: `tracing` to standard error (journald-friendly), iceoryx2's own messages routed into it | [`init_logging`] | `main` |
//! | SIGINT / SIGTERM set a stop flag, checked by the loops | [`STOP`], [`install_stop_handlers`] | `main`, then every thread |
//! | A real-time thread: `[realtime]` set-up ([`crate::rt`]), a set-up step that may allocate, a ready handshake, then the body with the pool allocator in real-time mode and its allocations counted | [`spawn_realtime`], [`RtThread`], [`AllocSummary`] | `daemon::Configured::start` |
//! | systemd: READY after the first valid cycle, WATCHDOG pings while cycles advance, STATUS ([`crate::watchdog`]) | [`start_watchdog`], [`stop_watchdog`] | `daemon::Configured::start`, `daemon::Running::shutdown` |
//! | The run summary as JSON (`--summary-json`) | [`write_json`] | `main` |
//!
//! A new process follows fulcrumd's phases (`docs/daemon.md`, "Phases"):
//!
//! 1. `main`: [`init_logging`], [`install_stop_handlers`], load and validate its configuration.
//! 2. configure (no threads): build its pipeline, fail with a typed error naming the key.
//! 3. start: [`start_watchdog`] with its own [`LoopProgress`] (the loop calls
//!    [`LoopProgress::record_cycle`] once a cycle), then [`spawn_realtime`] with its
//!    `[realtime]` settings (a tracking process at camera rate gives a priority below
//!    fulcrumd's 80), a set-up closure that builds its loop (publishers, buffers) and a body
//!    that runs it until [`STOP`].
//! 4. supervise on the main thread (logging what the loop hands over through lock-free
//!    queues) until [`RtThread::is_finished`].
//! 5. shut down: [`RtThread::join`], [`stop_watchdog`], then its summary, [`write_json`].

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::thread::JoinHandle;

use serde::Serialize;
use tracing::warn;

use crate::rt::{self, RealtimeConfig, RealtimeError};
use crate::watchdog::{self, LoopProgress, Watchdog, WatchdogHandle};

// ---------------------------------------------------------------------------------------------
// Logging

/// Installs the process's `tracing` subscriber: standard error, level from `RUST_LOG` (default
/// `info`), timestamps and colours only on a terminal (journald adds its own timestamps), and
/// routes iceoryx2's own messages into it (its "no config file" notice, expected, at debug).
///
/// **Not for the real-time loop:** call once, at the start of `main`.
pub fn init_logging() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let terminal = std::io::stderr().is_terminal();
    // journald adds its own timestamps: none when not on a terminal, and never ANSI colours.
    let builder = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).with_ansi(terminal);
    if terminal {
        builder.init();
    } else {
        builder.without_time().init();
    }
    // iceoryx2's own messages join the same stream (and its "no config file" notice, expected
    // here, goes to debug).
    hw_io::ipc::route_iceoryx2_logs_to_tracing();
}

// ---------------------------------------------------------------------------------------------
// Stop flag

/// The process's stop flag: set by SIGINT and SIGTERM once [`install_stop_handlers`] ran,
/// read (relaxed) once a cycle by the loops and by the supervision.
pub static STOP: AtomicBool = AtomicBool::new(false);

extern "C" fn on_stop_signal(_: libc::c_int) {
    STOP.store(true, Ordering::Relaxed);
}

/// Makes SIGINT and SIGTERM set [`STOP`] (`SA_RESTART`: interrupted system calls resume). A
/// handler that cannot be installed is warned about; the process runs on without it.
///
/// **Not for the real-time loop:** a system call; call once from `main`.
pub fn install_stop_handlers() {
    use nix::sys::signal::{SaFlags, SigAction, SigHandler, SigSet, Signal, sigaction};
    let action = SigAction::new(SigHandler::Handler(on_stop_signal), SaFlags::SA_RESTART, SigSet::empty());
    for sig in [Signal::SIGINT, Signal::SIGTERM] {
        // SAFETY: the handler only stores to an atomic, which is async-signal-safe.
        if let Err(e) = unsafe { sigaction(sig, &action) } {
            warn!("cannot install the {sig} handler: {e}");
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Real-time thread

/// Allocation figures of a real-time thread over its body ([`spawn_realtime`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct AllocSummary {
    /// System-allocator calls made by the real-time thread during the loop (target: 0).
    pub rt_thread_system_allocs: u64,
    /// Small blocks the pool served (iceoryx2's per-sample block, freed in the same cycle).
    pub pool_allocs: u64,
    /// Pool exhaustion fallbacks to the system allocator.
    pub pool_fallbacks: u64,
    /// Most pool blocks in use at once.
    pub pool_high_water: usize,
}

/// Why a real-time thread did not get to its body ([`spawn_realtime`]). `E` is the error of the
/// caller's set-up step.
#[derive(Debug, thiserror::Error)]
pub enum RtSpawnError<E: std::error::Error + 'static> {
    /// The thread could not be created.
    #[error("thread: cannot spawn {name}: {source}")]
    Spawn {
        /// The thread's name.
        name: String,
        /// Why.
        source: std::io::Error,
    },
    /// The real-time set-up failed with `realtime.require = true`.
    #[error("real-time set-up: {0}")]
    Realtime(#[from] RealtimeError),
    /// The caller's set-up step failed.
    #[error(transparent)]
    Setup(E),
    /// The thread ended (panicked) before its handshake.
    #[error("thread: the real-time thread died during set-up")]
    DiedDuringSetup,
}

/// A real-time thread past its set-up, running its body ([`spawn_realtime`]).
pub struct RtThread<T> {
    /// `None` only when the set-up failed, which [`spawn_realtime`] reports itself.
    handle: JoinHandle<Option<(T, AllocSummary)>>,
    realtime: Vec<String>,
}

/// Why a real-time thread gave no result ([`RtThread::join`]).
#[derive(Debug, thiserror::Error)]
pub enum RtJoinError {
    /// The body panicked.
    #[error("thread: the real-time thread panicked")]
    Panicked,
    /// The thread returned without running its body.
    #[error("thread: the real-time thread returned no result")]
    NoResult,
}

impl<T> RtThread<T> {
    /// The real-time set-up, one `step: outcome` line per step (`rt::RealtimeReport::steps`),
    /// refused steps included (they were already warned about by [`crate::rt`]).
    pub fn realtime_report(&self) -> &[String] {
        &self.realtime
    }

    /// The body has returned (or panicked).
    pub fn is_finished(&self) -> bool {
        self.handle.is_finished()
    }

    /// Waits for the body; its result and the allocations it made.
    pub fn join(self) -> Result<(T, AllocSummary), RtJoinError> {
        self.handle.join().map_err(|_| RtJoinError::Panicked)?.ok_or(RtJoinError::NoResult)
    }
}

/// Spawns the thread `name` (`stack_bytes` of stack), applies `realtime` to it
/// ([`rt::apply_to_current_thread`]: SCHED_FIFO, affinity, mlockall, stack prefault), runs
/// `setup` there (it may allocate: publishers, buffers, the loop's state), prefaults the pool
/// allocator ([`hw_io::rt_alloc`]) and hands the report back: this returns only then, so a
/// failed set-up is an error here, before anything runs. The thread then marks itself real-time
/// for the pool allocator, runs `body` on what `setup` built and counts the system
/// allocations it made meanwhile ([`AllocSummary`]); then, out of real-time mode and uncounted,
/// `finish` turns the state and the body's result into the thread's result (it may allocate:
/// summaries, copies of histograms) and the state is dropped there, on the thread.
///
/// **Not for the real-time loop:** spawns a thread and waits for its set-up.
pub fn spawn_realtime<S, R, T, E>(
    name: &str,
    stack_bytes: usize,
    realtime: RealtimeConfig,
    setup: impl FnOnce() -> Result<S, E> + Send + 'static,
    body: impl FnOnce(&mut S) -> R + Send + 'static,
    finish: impl FnOnce(S, R) -> T + Send + 'static,
) -> Result<RtThread<T>, RtSpawnError<E>>
where
    T: Send + 'static,
    E: std::error::Error + Send + 'static,
{
    let (ready_tx, ready_rx) = mpsc::channel::<Result<Vec<String>, RtSpawnError<E>>>();
    let handle = std::thread::Builder::new()
        .name(name.into())
        .stack_size(stack_bytes)
        .spawn(move || -> Option<(T, AllocSummary)> {
            let report = match rt::apply_to_current_thread(&realtime) {
                Ok(r) => r,
                Err(e) => {
                    let _ = ready_tx.send(Err(e.into()));
                    return None;
                }
            };
            let mut state = match setup() {
                Ok(s) => s,
                Err(e) => {
                    let _ = ready_tx.send(Err(RtSpawnError::Setup(e)));
                    return None;
                }
            };
            hw_io::rt_alloc::prefault_pool();
            let lines = report.steps().iter().map(|(step, outcome)| format!("{step}: {outcome}")).collect();
            let _ = ready_tx.send(Ok(lines));
            drop(ready_tx);
            hw_io::rt_alloc::enter_realtime();
            let before = hw_io::rt_alloc::thread_system_allocs();
            let pool_before = hw_io::rt_alloc::stats();
            let result = body(&mut state);
            let allocs = hw_io::rt_alloc::thread_system_allocs() - before;
            hw_io::rt_alloc::leave_realtime();
            let pool = hw_io::rt_alloc::stats();
            let alloc = AllocSummary {
                rt_thread_system_allocs: allocs,
                pool_allocs: pool.pool_allocs - pool_before.pool_allocs,
                pool_fallbacks: pool.pool_fallbacks - pool_before.pool_fallbacks,
                pool_high_water: pool.pool_high_water,
            };
            Some((finish(state, result), alloc))
        })
        .map_err(|source| RtSpawnError::Spawn { name: name.into(), source })?;
    match ready_rx.recv() {
        Ok(Ok(realtime)) => Ok(RtThread { handle, realtime }),
        Ok(Err(e)) => {
            let _ = handle.join();
            Err(e)
        }
        Err(_) => {
            let _ = handle.join();
            Err(RtSpawnError::DiedDuringSetup)
        }
    }
}

// ---------------------------------------------------------------------------------------------
// systemd

/// Starts the systemd supervisor ([`Watchdog::spawn`], STATUS from
/// [`watchdog::default_status`]) on `progress`: READY after the first valid cycle, WATCHDOG
/// pings while cycles advance. Outside systemd it does nothing. If it cannot start, a warning
/// and `None`: the process runs without it.
///
/// **Not for the real-time loop:** spawns a thread.
pub fn start_watchdog(progress: LoopProgress) -> Option<WatchdogHandle> {
    match Watchdog::spawn(progress, watchdog::default_status) {
        Ok(w) => Some(w),
        Err(e) => {
            warn!("systemd watchdog supervisor: {e}; running without it");
            None
        }
    }
}

/// Stops the systemd supervisor started by [`start_watchdog`], warning if it had failed.
///
/// **Not for the real-time loop:** joins a thread.
pub fn stop_watchdog(watchdog: Option<WatchdogHandle>) {
    if let Some(w) = watchdog
        && let Err(e) = w.shutdown()
    {
        warn!("{e}");
    }
}

// ---------------------------------------------------------------------------------------------
// Summary

/// Why a JSON summary or report could not be written ([`write_json`]).
#[derive(Debug, thiserror::Error)]
pub enum WriteJsonError {
    /// The value does not serialise (a non-string map key, ...).
    #[error("cannot serialise {path} as JSON: {source}", path = .path.display())]
    Serialize {
        /// The file.
        path: PathBuf,
        /// Why.
        source: serde_json::Error,
    },
    /// The file could not be written.
    #[error("cannot write {path}: {source}", path = .path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
}

/// Writes `value` as pretty JSON to `path` (the run summary of `--summary-json`, a report),
/// replacing the file; nothing without a path.
///
/// **Not for the real-time loop:** allocates and writes a file.
pub fn write_json(path: Option<&Path>, value: &impl Serialize) -> Result<(), WriteJsonError> {
    let Some(p) = path else { return Ok(()) };
    let text = serde_json::to_string_pretty(value)
        .map_err(|source| WriteJsonError::Serialize { path: p.to_owned(), source })?;
    std::fs::write(p, text).map_err(|source| WriteJsonError::Write { path: p.to_owned(), source })
}
