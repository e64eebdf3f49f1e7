//! Real-time set-up of the 1 kHz thread, and its clock.
//!
//! [`apply_to_current_thread`] performs, in order, the steps of a [`RealtimeConfig`] on the calling
//! thread: CPU affinity, `SCHED_FIFO`, `mlockall`, stack prefault. Each step ends
//! [`StepOutcome::Applied`], [`StepOutcome::Skipped`] (off in the configuration) or
//! [`StepOutcome::Refused`] (the kernel or a limit said no: the reason names the missing
//! capability or limit). With `require = false` a refusal degrades with a `tracing` warning; with
//! `require = true` it is a [`RealtimeError`]. `docs/realtime.md` explains each step.
//!
//! [`Periodic`] paces a loop on absolute `CLOCK_MONOTONIC` deadlines with `clock_nanosleep`
//! (`TIMER_ABSTIME`): no drift, no busy-polling, no allocation. A cycle that overran skips the
//! deadlines already passed instead of running a burst of late cycles, and reports them.

use std::fmt;

use nix::errno::Errno;
use nix::sched::{CpuSet, sched_setaffinity};
use nix::sys::mman::{MlockAllFlags, mlockall};
use nix::sys::resource::{RLIM_INFINITY, Resource, getrlimit};
use nix::sys::time::TimeSpec;
use nix::time::{ClockId, ClockNanosleepFlags, clock_nanosleep};
use nix::unistd::Pid;
use serde::{Deserialize, Serialize};

/// Nanoseconds in a second.
const NS_PER_S: u64 = 1_000_000_000;
/// Largest accepted `prefault_stack_bytes`, bytes (64 MiB).
pub const MAX_PREFAULT_STACK_BYTES: usize = 64 * 1024 * 1024;
/// Stack kept free below the prefaulted region (guard page, signal frames, callees), bytes.
pub const STACK_MARGIN_BYTES: usize = 64 * 1024;
/// `sched_setscheduler` flag: threads and processes created by the real-time thread start as
/// `SCHED_OTHER` (linux/sched.h; not exported by the libc crate).
const SCHED_RESET_ON_FORK: libc::c_int = 0x4000_0000;
/// Capability number of `CAP_IPC_LOCK` (linux/capability.h).
const CAP_IPC_LOCK: u32 = 14;
/// Capability number of `CAP_SYS_NICE` (linux/capability.h).
const CAP_SYS_NICE: u32 = 23;

// ---------------------------------------------------------------------------------------------
// Configuration

/// Real-time settings of the 1 kHz thread. Keys of the `[realtime]` table.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RealtimeConfig {
    /// `SCHED_FIFO` priority of the thread: 0 = leave the scheduler alone, 1..=99 (default 80).
    /// Needs `RLIMIT_RTPRIO` >= the priority (systemd `LimitRTPRIO=`) or `CAP_SYS_NICE`.
    pub sched_fifo_priority: u8,
    /// CPUs the thread may run on (indices from 0); empty = leave the affinity alone (default).
    pub cpu_affinity: Vec<usize>,
    /// Lock all current and future memory of the process (`mlockall(MCL_CURRENT | MCL_FUTURE)`),
    /// default true. Needs `RLIMIT_MEMLOCK` = unlimited (systemd `LimitMEMLOCK=infinity`) or `CAP_IPC_LOCK`.
    pub lock_memory: bool,
    /// Bytes of the thread's stack touched once now so that the loop takes no page fault on it,
    /// bytes (0 = skip; default 512 KiB; at most 64 MiB).
    pub prefault_stack_bytes: usize,
    /// true: a refused step is an error; false (default): it is a warning and the loop runs without it.
    pub require: bool,
}

impl Default for RealtimeConfig {
    fn default() -> Self {
        Self {
            sched_fifo_priority: 80,
            cpu_affinity: Vec::new(),
            lock_memory: true,
            prefault_stack_bytes: 512 * 1024,
            require: false,
        }
    }
}

/// A real-time configuration value out of range; the message names the key.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RealtimeConfigError {
    /// `sched_fifo_priority` above 99.
    #[error("realtime.sched_fifo_priority = {value}: must be 0 (off) or 1..=99")]
    Priority {
        /// Configured value.
        value: u8,
    },
    /// A CPU index that this machine does not have.
    #[error("realtime.cpu_affinity: CPU {index} does not exist (this machine has {available} CPUs, 0..={last})", last = available.saturating_sub(1))]
    CpuOutOfRange {
        /// The index.
        index: usize,
        /// CPUs configured on the machine.
        available: usize,
    },
    /// `prefault_stack_bytes` above [`MAX_PREFAULT_STACK_BYTES`].
    #[error("realtime.prefault_stack_bytes = {value}: must be at most {max} bytes", max = MAX_PREFAULT_STACK_BYTES)]
    PrefaultTooLarge {
        /// Configured value, bytes.
        value: usize,
    },
}

/// CPUs configured on this machine (`sysconf(_SC_NPROCESSORS_CONF)`).
pub fn configured_cpus() -> usize {
    // SAFETY: sysconf has no memory-safety preconditions.
    let n = unsafe { libc::sysconf(libc::_SC_NPROCESSORS_CONF) };
    if n > 0 { n as usize } else { std::thread::available_parallelism().map_or(1, |n| n.get()) }
}

impl RealtimeConfig {
    /// Checks the priority range, the CPU indices against [`configured_cpus`] and the prefault size.
    pub fn validate(&self) -> Result<(), RealtimeConfigError> {
        if self.sched_fifo_priority > 99 {
            return Err(RealtimeConfigError::Priority { value: self.sched_fifo_priority });
        }
        let available = configured_cpus().min(CpuSet::count());
        if let Some(&index) = self.cpu_affinity.iter().find(|&&i| i >= available) {
            return Err(RealtimeConfigError::CpuOutOfRange { index, available });
        }
        if self.prefault_stack_bytes > MAX_PREFAULT_STACK_BYTES {
            return Err(RealtimeConfigError::PrefaultTooLarge { value: self.prefault_stack_bytes });
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------------
// Report

/// One step of [`apply_to_current_thread`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RtStep {
    /// `sched_setaffinity` (key `cpu_affinity`).
    CpuAffinity,
    /// `sched_setscheduler(SCHED_FIFO)` (key `sched_fifo_priority`).
    SchedFifo,
    /// `mlockall` (key `lock_memory`).
    MemoryLock,
    /// Stack prefault (key `prefault_stack_bytes`).
    StackPrefault,
}

impl fmt::Display for RtStep {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            RtStep::CpuAffinity => "cpu_affinity",
            RtStep::SchedFifo => "sched_fifo",
            RtStep::MemoryLock => "lock_memory",
            RtStep::StackPrefault => "prefault_stack",
        })
    }
}

/// How one step ended.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum StepOutcome {
    /// Done.
    Applied,
    /// Off in the configuration.
    Skipped,
    /// Not permitted or not possible; `reason` names the limit or capability that is missing.
    Refused {
        /// Why, and what would permit it.
        reason: String,
    },
}

impl StepOutcome {
    /// True for [`StepOutcome::Refused`].
    pub fn is_refused(&self) -> bool {
        matches!(self, StepOutcome::Refused { .. })
    }
}

impl fmt::Display for StepOutcome {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            StepOutcome::Applied => f.write_str("applied"),
            StepOutcome::Skipped => f.write_str("skipped (off in the configuration)"),
            StepOutcome::Refused { reason } => write!(f, "refused: {reason}"),
        }
    }
}

/// What [`apply_to_current_thread`] did, step by step.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RealtimeReport {
    /// CPU affinity.
    pub cpu_affinity: StepOutcome,
    /// `SCHED_FIFO`.
    pub sched_fifo: StepOutcome,
    /// `mlockall`.
    pub memory_lock: StepOutcome,
    /// Stack prefault.
    pub stack_prefault: StepOutcome,
}

impl RealtimeReport {
    fn all_skipped() -> Self {
        Self {
            cpu_affinity: StepOutcome::Skipped,
            sched_fifo: StepOutcome::Skipped,
            memory_lock: StepOutcome::Skipped,
            stack_prefault: StepOutcome::Skipped,
        }
    }

    /// The four steps with their outcomes, in the order they are performed.
    pub fn steps(&self) -> [(RtStep, &StepOutcome); 4] {
        [
            (RtStep::CpuAffinity, &self.cpu_affinity),
            (RtStep::SchedFifo, &self.sched_fifo),
            (RtStep::MemoryLock, &self.memory_lock),
            (RtStep::StackPrefault, &self.stack_prefault),
        ]
    }

    /// True when no step was refused.
    pub fn fully_applied(&self) -> bool {
        self.steps().iter().all(|(_, o)| !o.is_refused())
    }

    fn slot(&mut self, step: RtStep) -> &mut StepOutcome {
        match step {
            RtStep::CpuAffinity => &mut self.cpu_affinity,
            RtStep::SchedFifo => &mut self.sched_fifo,
            RtStep::MemoryLock => &mut self.memory_lock,
            RtStep::StackPrefault => &mut self.stack_prefault,
        }
    }
}

impl fmt::Display for RealtimeReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, (step, outcome)) in self.steps().iter().enumerate() {
            if i > 0 {
                f.write_str("; ")?;
            }
            write!(f, "{step}: {outcome}")?;
        }
        Ok(())
    }
}

/// Why [`apply_to_current_thread`] failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RealtimeError {
    /// The configuration is invalid (nothing was applied).
    #[error(transparent)]
    Config(#[from] RealtimeConfigError),
    /// A step was refused and `realtime.require = true` (the steps before it stay applied).
    #[error("real-time step {step} refused and realtime.require = true: {reason}")]
    Refused {
        /// The step.
        step: RtStep,
        /// Why, and what would permit it.
        reason: String,
    },
}

// ---------------------------------------------------------------------------------------------
// Apply

/// Applies `config` to the calling thread (affinity, scheduler and stack are per thread; the
/// memory lock is for the whole process). Call it at the start of the real-time thread, after
/// the helper threads are spawned: `SCHED_RESET_ON_FORK` keeps threads spawned later from
/// inheriting `SCHED_FIFO`, but not the CPU affinity.
pub fn apply_to_current_thread(config: &RealtimeConfig) -> Result<RealtimeReport, RealtimeError> {
    config.validate()?;
    let mut report = RealtimeReport::all_skipped();
    if !config.cpu_affinity.is_empty() {
        settle(&mut report, RtStep::CpuAffinity, set_affinity(&config.cpu_affinity), config.require)?;
    }
    if config.sched_fifo_priority > 0 {
        settle(&mut report, RtStep::SchedFifo, set_fifo(config.sched_fifo_priority), config.require)?;
    }
    if config.lock_memory {
        settle(&mut report, RtStep::MemoryLock, lock_memory(), config.require)?;
    }
    if config.prefault_stack_bytes > 0 {
        settle(&mut report, RtStep::StackPrefault, prefault_stack(config.prefault_stack_bytes), config.require)?;
    }
    Ok(report)
}

fn settle(report: &mut RealtimeReport, step: RtStep, outcome: StepOutcome, require: bool) -> Result<(), RealtimeError> {
    if let StepOutcome::Refused { reason } = &outcome {
        if require {
            return Err(RealtimeError::Refused { step, reason: reason.clone() });
        }
        tracing::warn!(%step, %reason, "real-time step refused: running without it (realtime.require = false)");
    }
    *report.slot(step) = outcome;
    Ok(())
}

fn set_affinity(cpus: &[usize]) -> StepOutcome {
    let mut set = CpuSet::new();
    for &cpu in cpus {
        if let Err(e) = set.set(cpu) {
            return StepOutcome::Refused { reason: format!("CPU {cpu} cannot be put in a CPU set: {e}") };
        }
    }
    match sched_setaffinity(Pid::from_raw(0), &set) {
        Ok(()) => StepOutcome::Applied,
        Err(Errno::EINVAL) => StepOutcome::Refused {
            reason: format!(
                "sched_setaffinity: EINVAL: none of CPUs {cpus:?} is allowed for this process \
                 (cgroup cpuset, systemd CPUAffinity=/AllowedCPUs=, taskset)"
            ),
        },
        Err(e) => StepOutcome::Refused { reason: format!("sched_setaffinity({cpus:?}): {e}") },
    }
}

fn limit_text(resource: Resource) -> String {
    let show = |v: libc::rlim_t| if v == RLIM_INFINITY { "unlimited".to_string() } else { v.to_string() };
    match getrlimit(resource) {
        Ok((soft, hard)) => format!("soft {}, hard {}", show(soft), show(hard)),
        Err(e) => format!("unreadable: {e}"),
    }
}

fn set_fifo(priority: u8) -> StepOutcome {
    let param = libc::sched_param { sched_priority: libc::c_int::from(priority) };
    // SAFETY: `param` is a valid sched_param; pid 0 is the calling thread.
    let rc = unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO | SCHED_RESET_ON_FORK, &param) };
    if rc == 0 {
        return StepOutcome::Applied;
    }
    let e = Errno::last();
    let reason = if e == Errno::EPERM {
        format!(
            "sched_setscheduler(SCHED_FIFO, {priority}): EPERM: needs RLIMIT_RTPRIO >= {priority} \
             (now {}; systemd LimitRTPRIO=, or /etc/security/limits.conf rtprio) or CAP_SYS_NICE (held: {}); \
             with both, the cgroup may have no real-time budget (cgroup v1 cpu.rt_runtime_us = 0)",
            limit_text(Resource::RLIMIT_RTPRIO),
            yes_no(has_capability(CAP_SYS_NICE))
        )
    } else {
        format!("sched_setscheduler(SCHED_FIFO, {priority}): {e}")
    };
    StepOutcome::Refused { reason }
}

fn yes_no(b: Option<bool>) -> &'static str {
    match b {
        Some(true) => "yes",
        Some(false) => "no",
        None => "unknown",
    }
}

/// Whether the process holds capability `cap` in its effective set (from /proc/self/status).
fn has_capability(cap: u32) -> Option<bool> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let hex = status.lines().find_map(|l| l.strip_prefix("CapEff:"))?.trim();
    let bits = u64::from_str_radix(hex, 16).ok()?;
    Some(bits & (1u64 << cap) != 0)
}

fn lock_memory() -> StepOutcome {
    let limited = match getrlimit(Resource::RLIMIT_MEMLOCK) {
        Ok((soft, _)) => soft != RLIM_INFINITY,
        Err(_) => true,
    };
    let ipc_lock = has_capability(CAP_IPC_LOCK);
    if limited && ipc_lock != Some(true) {
        // mlockall(MCL_FUTURE) would succeed while the process is small, and then every mmap
        // (a heap or a thread stack growing) past the limit would fail: refuse up front.
        return StepOutcome::Refused {
            reason: format!(
                "RLIMIT_MEMLOCK is limited ({}) and CAP_IPC_LOCK is not held ({}): with MCL_FUTURE every \
                 allocation past the limit would fail; set LimitMEMLOCK=infinity (systemd) or \
                 memlock unlimited (limits.conf)",
                limit_text(Resource::RLIMIT_MEMLOCK),
                yes_no(ipc_lock)
            ),
        };
    }
    match mlockall(MlockAllFlags::MCL_CURRENT | MlockAllFlags::MCL_FUTURE) {
        Ok(()) => StepOutcome::Applied,
        Err(e) => StepOutcome::Refused {
            reason: format!(
                "mlockall(MCL_CURRENT | MCL_FUTURE): {e}: needs LimitMEMLOCK=infinity or CAP_IPC_LOCK (RLIMIT_MEMLOCK {})",
                limit_text(Resource::RLIMIT_MEMLOCK)
            ),
        },
    }
}

/// Bytes of the calling thread's stack below the current frame, or `None` if unknown.
pub fn stack_bytes_left() -> Option<usize> {
    let mut attr = std::mem::MaybeUninit::<libc::pthread_attr_t>::uninit();
    // SAFETY: pthread_getattr_np initialises `attr` on success, which is checked; it is destroyed below.
    if unsafe { libc::pthread_getattr_np(libc::pthread_self(), attr.as_mut_ptr()) } != 0 {
        return None;
    }
    let mut addr: *mut libc::c_void = std::ptr::null_mut();
    let mut size: libc::size_t = 0;
    // SAFETY: `attr` was initialised above; the out-pointers are valid.
    let rc = unsafe { libc::pthread_attr_getstack(attr.as_ptr(), &mut addr, &mut size) };
    // SAFETY: `attr` was initialised by pthread_getattr_np.
    unsafe { libc::pthread_attr_destroy(attr.as_mut_ptr()) };
    if rc != 0 || size == 0 {
        return None;
    }
    let marker = 0u8;
    let here = std::hint::black_box(&marker) as *const u8 as usize;
    let low = addr as usize;
    (here > low && here <= low + size).then(|| here - low)
}

fn prefault_stack(bytes: usize) -> StepOutcome {
    match stack_bytes_left() {
        None => {
            StepOutcome::Refused { reason: "the thread's stack bounds are unknown (pthread_getattr_np failed)".into() }
        }
        Some(left) if bytes.saturating_add(STACK_MARGIN_BYTES) > left => StepOutcome::Refused {
            reason: format!(
                "the thread's stack has {left} bytes left, fewer than prefault_stack_bytes = {bytes} plus a \
                 {STACK_MARGIN_BYTES}-byte margin: spawn the real-time thread with a larger stack \
                 (std::thread::Builder::stack_size) or lower the key"
            ),
        },
        Some(_) => {
            touch_stack(bytes);
            StepOutcome::Applied
        }
    }
}

/// Bytes of stack one [`touch_stack`] frame touches.
const TOUCH_CHUNK: usize = 16 * 1024;

/// Writes one byte per 4 KiB of `bytes` of stack below the caller, recursively.
#[inline(never)]
fn touch_stack(bytes: usize) {
    let mut chunk = [0u8; TOUCH_CHUNK];
    let mut i = 0;
    while i < TOUCH_CHUNK {
        // SAFETY: `i < TOUCH_CHUNK`, inside `chunk`. Volatile so that the write is not elided.
        unsafe { std::ptr::write_volatile(chunk.as_mut_ptr().add(i), 1) };
        i += 4096;
    }
    if bytes > TOUCH_CHUNK {
        touch_stack(bytes - TOUCH_CHUNK);
    }
    // Keeps `chunk` alive across the call (no tail call reusing the frame).
    std::hint::black_box(&chunk);
}

// ---------------------------------------------------------------------------------------------
// Clock

/// `CLOCK_MONOTONIC` now, nanoseconds since an arbitrary origin (boot): hw-io's, the one clock
/// read of the workspace (frames are stamped with it too).
///
/// **Real-time (1 kHz loop):** called several times a cycle; allocation-free, no system call (vDSO).
pub use hw_io::frame::monotonic_now_ns;

/// Why the clock could not be slept on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ClockError {
    /// `clock_nanosleep` failed with something else than `EINTR` (not expected on Linux).
    #[error("clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME): {0}")]
    Sleep(Errno),
}

/// Sleeps until `CLOCK_MONOTONIC` reaches `deadline_ns` (nanoseconds, as [`monotonic_now_ns`]);
/// returns at once if it has passed. Retries after signals (`EINTR`). Allocation-free.
pub fn sleep_until_ns(deadline_ns: u64) -> Result<(), ClockError> {
    let ts = TimeSpec::new((deadline_ns / NS_PER_S) as libc::time_t, (deadline_ns % NS_PER_S) as libc::c_long);
    loop {
        match clock_nanosleep(ClockId::CLOCK_MONOTONIC, ClockNanosleepFlags::TIMER_ABSTIME, &ts) {
            Ok(_) => return Ok(()),
            Err(Errno::EINTR) => continue,
            Err(e) => return Err(ClockError::Sleep(e)),
        }
    }
}

/// A zero period.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum PeriodError {
    /// The period must be at least 1 ns.
    #[error("the period must be at least 1 ns")]
    Zero,
}

/// One wake-up of [`Periodic::wait`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Tick {
    /// The deadline slept to, nanoseconds ([`monotonic_now_ns`] clock).
    pub deadline_ns: u64,
    /// When the thread woke, nanoseconds (same clock).
    pub woke_ns: u64,
    /// `woke_ns - deadline_ns` (0 if it woke early, which the kernel does not do), nanoseconds.
    pub late_ns: u64,
    /// Deadlines skipped because they had already passed when `wait` was called (the previous
    /// cycle overran); 0 normally.
    pub overruns: u64,
}

/// Absolute-deadline pacing: deadline `k` is `first + k * period`, whatever the wake-up jitter.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Periodic {
    period_ns: u64,
    next_deadline_ns: u64,
}

impl Periodic {
    /// First deadline one period from now; `period_ns` in nanoseconds (1 kHz: 1 000 000).
    pub fn new(period_ns: u64) -> Result<Self, PeriodError> {
        Self::starting_at(monotonic_now_ns().saturating_add(period_ns), period_ns)
    }

    /// First deadline at `first_deadline_ns` ([`monotonic_now_ns`] clock), then every `period_ns`.
    pub fn starting_at(first_deadline_ns: u64, period_ns: u64) -> Result<Self, PeriodError> {
        if period_ns == 0 {
            return Err(PeriodError::Zero);
        }
        Ok(Self { period_ns, next_deadline_ns: first_deadline_ns })
    }

    /// The period, nanoseconds.
    pub fn period_ns(&self) -> u64 {
        self.period_ns
    }

    /// The deadline the next [`Periodic::wait`] sleeps to if it is not already past, nanoseconds.
    pub fn next_deadline_ns(&self) -> u64 {
        self.next_deadline_ns
    }

    /// Sleeps to the next deadline. If it (and perhaps more) has already passed, the passed
    /// deadlines are skipped, not caught up with a burst: the thread sleeps to the first future
    /// deadline and `overruns` counts the skipped ones.
    ///
    /// **Real-time (1 kHz loop):** called once a cycle; allocation-free, sleeps with
    /// `clock_nanosleep(TIMER_ABSTIME)` until the deadline, never longer.
    pub fn wait(&mut self) -> Result<Tick, ClockError> {
        let now = monotonic_now_ns();
        let mut deadline = self.next_deadline_ns;
        let mut overruns = 0;
        if deadline <= now {
            overruns = (now - deadline) / self.period_ns + 1;
            deadline = deadline.saturating_add(overruns.saturating_mul(self.period_ns));
        }
        sleep_until_ns(deadline)?;
        let woke_ns = monotonic_now_ns();
        self.next_deadline_ns = deadline.saturating_add(self.period_ns);
        Ok(Tick { deadline_ns: deadline, woke_ns, late_ns: woke_ns.saturating_sub(deadline), overruns })
    }
}

// ---------------------------------------------------------------------------------------------
// A worker thread below the threads that feed it

/// Niceness added to a time-shared thread by [`lower_current_thread`] (the kernel's weight
/// ratio per nice step is about 1.25: five steps give the other threads about 3× the CPU).
pub const LOWER_NICE_STEPS: i32 = 5;

/// What [`lower_current_thread`] did to the calling thread's scheduling.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Lowered {
    /// A real-time thread (`SCHED_FIFO` or `SCHED_RR`, `policy` names it) moved from priority
    /// `from` to `to` = `from` − 1, same policy.
    RealTime {
        /// `"SCHED_FIFO"` or `"SCHED_RR"`.
        policy: &'static str,
        /// Priority before (1..=99).
        from: i32,
        /// Priority after.
        to: i32,
    },
    /// A time-shared thread (`SCHED_OTHER`, `SCHED_BATCH`) moved from niceness `from` to `to`
    /// (at most 19).
    Niced {
        /// Niceness before (−20..=19).
        from: i32,
        /// Niceness after.
        to: i32,
    },
    /// Nothing was changed; the reason says why (already at the lowest priority of its
    /// policy, `SCHED_IDLE`, or a call the kernel refused).
    Unchanged {
        /// Why, for the log.
        reason: String,
    },
}

impl fmt::Display for Lowered {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::RealTime { policy, from, to } => write!(f, "{policy} priority {from} -> {to}"),
            Self::Niced { from, to } => write!(f, "nice {from} -> {to}"),
            Self::Unchanged { reason } => write!(f, "unchanged: {reason}"),
        }
    }
}

/// Puts the calling thread (and every thread it creates afterwards, which inherit it) just
/// below the process's other threads: a real-time thread one priority lower in the same policy,
/// a time-shared one [`LOWER_NICE_STEPS`] nicer (per-thread niceness, Linux). Needs no
/// privilege (lowering is always allowed). Used by the image processes: their bus listener
/// thread keeps the process's priority, the heavy per-frame work runs below it, so a long
/// frame never makes the listener fall behind the bus on a busy CPU (docs/hil.md). Never
/// fails: a refusal is reported as [`Lowered::Unchanged`].
pub fn lower_current_thread() -> Lowered {
    // SAFETY: plain syscalls on the calling thread (pid 0); `param` is a valid out-pointer.
    let policy = unsafe { libc::sched_getscheduler(0) };
    if policy < 0 {
        return Lowered::Unchanged { reason: format!("sched_getscheduler: {}", Errno::last()) };
    }
    let policy = policy & !SCHED_RESET_ON_FORK;
    if policy == libc::SCHED_FIFO || policy == libc::SCHED_RR {
        let name = if policy == libc::SCHED_FIFO { "SCHED_FIFO" } else { "SCHED_RR" };
        let mut param = libc::sched_param { sched_priority: 0 };
        // SAFETY: as above.
        if unsafe { libc::sched_getparam(0, &mut param) } != 0 {
            return Lowered::Unchanged { reason: format!("sched_getparam: {}", Errno::last()) };
        }
        let from = param.sched_priority;
        if from <= 1 {
            return Lowered::Unchanged { reason: format!("{name} priority {from} is already the lowest") };
        }
        let to = libc::sched_param { sched_priority: from - 1 };
        // SAFETY: as above.
        if unsafe { libc::sched_setscheduler(0, policy, &to) } != 0 {
            return Lowered::Unchanged {
                reason: format!("sched_setscheduler({name}, {}): {}", from - 1, Errno::last()),
            };
        }
        return Lowered::RealTime { policy: name, from, to: from - 1 };
    }
    if policy == libc::SCHED_IDLE {
        return Lowered::Unchanged { reason: "SCHED_IDLE is already below every other policy".into() };
    }
    // SAFETY: gettid has no arguments and cannot fail.
    let tid = unsafe { libc::gettid() };
    let Ok(who) = libc::id_t::try_from(tid) else {
        return Lowered::Unchanged { reason: format!("thread id {tid} out of range") };
    };
    Errno::clear();
    // SAFETY: as above; -1 is a valid niceness, hence the errno check.
    let from = unsafe { libc::getpriority(libc::PRIO_PROCESS, who) };
    if from == -1 && Errno::last_raw() != 0 {
        return Lowered::Unchanged { reason: format!("getpriority: {}", Errno::last()) };
    }
    let to = (from + LOWER_NICE_STEPS).min(19);
    if to == from {
        return Lowered::Unchanged { reason: format!("nice {from} is already the lowest") };
    }
    // SAFETY: as above.
    if unsafe { libc::setpriority(libc::PRIO_PROCESS, who, to) } != 0 {
        return Lowered::Unchanged { reason: format!("setpriority(nice {to}): {}", Errno::last()) };
    }
    Lowered::Niced { from, to }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::process::Command;
    use std::time::Duration;

    /// Runs the ignored test `name` of this binary in a child process with `COMANIP_RT_CHILD=1`
    /// and asserts that it passed (so process-wide effects stay out of the test harness).
    fn run_child(name: &str) {
        let exe = std::env::current_exe().unwrap();
        let out = Command::new(exe)
            .args(["--exact", name, "--ignored", "--nocapture", "--test-threads=1"])
            .env("COMANIP_RT_CHILD", "1")
            .output()
            .unwrap();
        let stdout = String::from_utf8_lossy(&out.stdout);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "child {name} failed: {}\n{stdout}\n{stderr}", out.status);
        assert!(stdout.contains("1 passed"), "child {name} did not run:\n{stdout}\n{stderr}");
    }

    fn in_child() -> bool {
        std::env::var_os("COMANIP_RT_CHILD").is_some()
    }

    #[test]
    fn defaults_are_documented_values() {
        let c = RealtimeConfig::default();
        assert_eq!(c.sched_fifo_priority, 80);
        assert!(c.cpu_affinity.is_empty());
        assert!(c.lock_memory);
        assert_eq!(c.prefault_stack_bytes, 512 * 1024);
        assert!(!c.require);
        assert_eq!(c.validate(), Ok(()));
        let parsed: RealtimeConfig = toml::from_str("").unwrap();
        assert_eq!(parsed, c);
        assert!(toml::from_str::<RealtimeConfig>("sched_fifo_prio = 3\n").is_err(), "unknown key accepted");
    }

    #[test]
    fn validation_names_the_key() {
        let e = RealtimeConfig { sched_fifo_priority: 100, ..Default::default() }.validate().unwrap_err();
        assert_eq!(e, RealtimeConfigError::Priority { value: 100 });
        assert!(e.to_string().contains("realtime.sched_fifo_priority"), "{e}");
        let n = configured_cpus();
        let e = RealtimeConfig { cpu_affinity: vec![0, n], ..Default::default() }.validate().unwrap_err();
        assert_eq!(e, RealtimeConfigError::CpuOutOfRange { index: n, available: n });
        assert!(e.to_string().contains("realtime.cpu_affinity") && e.to_string().contains(&n.to_string()), "{e}");
        assert!(RealtimeConfig { cpu_affinity: vec![n - 1], ..Default::default() }.validate().is_ok());
        let e = RealtimeConfig { prefault_stack_bytes: MAX_PREFAULT_STACK_BYTES + 1, ..Default::default() }
            .validate()
            .unwrap_err();
        assert!(e.to_string().contains("realtime.prefault_stack_bytes"), "{e}");
        // An invalid config is an error even with require = false, before anything is applied.
        let bad = RealtimeConfig { sched_fifo_priority: 200, ..Default::default() };
        assert!(matches!(apply_to_current_thread(&bad), Err(RealtimeError::Config(_))));
    }

    #[test]
    fn all_off_skips_every_step() {
        let c = RealtimeConfig {
            sched_fifo_priority: 0,
            lock_memory: false,
            prefault_stack_bytes: 0,
            ..Default::default()
        };
        let r = apply_to_current_thread(&c).unwrap();
        assert_eq!(r, RealtimeReport::all_skipped());
        assert!(r.fully_applied());
        assert_eq!(
            r.to_string(),
            "cpu_affinity: skipped (off in the configuration); sched_fifo: skipped (off in the configuration); \
             lock_memory: skipped (off in the configuration); prefault_stack: skipped (off in the configuration)"
        );
    }

    #[test]
    fn report_formats_refusals_with_their_reason() {
        let mut r = RealtimeReport::all_skipped();
        r.sched_fifo = StepOutcome::Refused { reason: "EPERM: needs LimitRTPRIO".into() };
        r.memory_lock = StepOutcome::Applied;
        assert!(!r.fully_applied());
        let s = r.to_string();
        assert!(s.contains("sched_fifo: refused: EPERM: needs LimitRTPRIO"), "{s}");
        assert!(s.contains("lock_memory: applied"), "{s}");
    }

    #[test]
    fn stack_prefault_is_refused_on_a_small_stack_and_applied_on_a_large_one() {
        let cfg = |bytes| RealtimeConfig {
            sched_fifo_priority: 0,
            lock_memory: false,
            prefault_stack_bytes: bytes,
            ..Default::default()
        };
        let small = std::thread::Builder::new()
            .stack_size(256 * 1024)
            .spawn(move || apply_to_current_thread(&cfg(512 * 1024)))
            .unwrap()
            .join()
            .unwrap()
            .unwrap();
        match &small.stack_prefault {
            StepOutcome::Refused { reason } => assert!(reason.contains("stack_size"), "{reason}"),
            other => panic!("expected a refusal, got {other}"),
        }
        // With require = true the same refusal is an error.
        let err = std::thread::Builder::new()
            .stack_size(256 * 1024)
            .spawn(move || apply_to_current_thread(&RealtimeConfig { require: true, ..cfg(512 * 1024) }))
            .unwrap()
            .join()
            .unwrap()
            .unwrap_err();
        assert!(matches!(err, RealtimeError::Refused { step: RtStep::StackPrefault, .. }), "{err}");
        let large = std::thread::Builder::new()
            .stack_size(4 * 1024 * 1024)
            .spawn(move || {
                let before = stack_bytes_left();
                (apply_to_current_thread(&cfg(2 * 1024 * 1024)), before)
            })
            .unwrap()
            .join()
            .unwrap();
        assert_eq!(large.0.unwrap().stack_prefault, StepOutcome::Applied);
        let left = large.1.unwrap();
        assert!(left > 3 * 1024 * 1024 && left <= 4 * 1024 * 1024 + 4096, "stack left {left}");
    }

    /// Child: privileged apply (this sandbox runs as root with CAP_SYS_NICE and CAP_IPC_LOCK).
    #[test]
    #[ignore = "run by apply_happy_path_in_a_child_process"]
    fn child_apply_happy_path() {
        if !in_child() {
            return;
        }
        let cfg = RealtimeConfig {
            sched_fifo_priority: 10,
            cpu_affinity: vec![0],
            lock_memory: true,
            prefault_stack_bytes: 256 * 1024,
            require: true,
        };
        let privileged = has_capability(CAP_SYS_NICE) == Some(true) && has_capability(CAP_IPC_LOCK) == Some(true);
        let result = std::thread::Builder::new()
            .stack_size(2 * 1024 * 1024)
            .spawn(move || {
                let r = apply_to_current_thread(&cfg);
                // SAFETY: sched_getscheduler / sched_getparam on the calling thread.
                let policy = unsafe { libc::sched_getscheduler(0) };
                let mut p = libc::sched_param { sched_priority: 0 };
                // SAFETY: `p` is a valid, writable `sched_param` for the call's duration.
                unsafe { libc::sched_getparam(0, &mut p) };
                let affinity = nix::sched::sched_getaffinity(Pid::from_raw(0)).unwrap();
                let only0 = affinity.is_set(0).unwrap() && (1..configured_cpus()).all(|c| !affinity.is_set(c).unwrap());
                // A thread spawned from the real-time thread starts as SCHED_OTHER.
                // SAFETY: sched_getscheduler on the calling thread; no pointer is passed.
                let child_policy = std::thread::spawn(|| unsafe { libc::sched_getscheduler(0) }).join().unwrap();
                (r, policy, p.sched_priority, only0, child_policy)
            })
            .unwrap()
            .join()
            .unwrap();
        if !privileged {
            // Without the capabilities (and with the default limits) require = true must fail.
            assert!(result.0.is_err(), "unprivileged apply with require = true succeeded: {:?}", result.0);
            return;
        }
        let report = result.0.unwrap();
        eprintln!("privileged child report: {report}");
        assert!(report.fully_applied(), "{report}");
        assert_eq!(report.cpu_affinity, StepOutcome::Applied);
        assert_eq!(report.sched_fifo, StepOutcome::Applied);
        assert_eq!(report.memory_lock, StepOutcome::Applied);
        assert_eq!(report.stack_prefault, StepOutcome::Applied);
        assert_eq!(result.1 & !SCHED_RESET_ON_FORK, libc::SCHED_FIFO);
        assert_eq!(result.2, 10);
        assert!(result.3, "affinity is not {{0}}");
        assert_eq!(result.4, libc::SCHED_OTHER, "SCHED_RESET_ON_FORK did not apply");
        let status = std::fs::read_to_string("/proc/self/status").unwrap();
        let locked_kb: u64 = status
            .lines()
            .find_map(|l| l.strip_prefix("VmLck:"))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .unwrap();
        assert!(locked_kb > 0, "VmLck is 0 after mlockall");
    }

    #[test]
    fn apply_happy_path_in_a_child_process() {
        run_child("rt::tests::child_apply_happy_path");
    }

    /// Child: drops to `nobody` with RLIMIT_RTPRIO = 0 and a small RLIMIT_MEMLOCK, then applies.
    #[test]
    #[ignore = "run by apply_refusal_path_in_a_child_process"]
    fn child_apply_refusal_path() {
        if !in_child() {
            return;
        }
        use nix::sys::resource::setrlimit;
        setrlimit(Resource::RLIMIT_RTPRIO, 0, 0).unwrap();
        setrlimit(Resource::RLIMIT_MEMLOCK, 64 * 1024, 64 * 1024).unwrap();
        // SAFETY: plain syscalls; 65534 is `nobody`. Dropping the uid clears the capabilities.
        unsafe {
            if libc::geteuid() == 0 {
                assert_eq!(libc::setgroups(0, std::ptr::null()), 0);
                assert_eq!(libc::setresgid(65534, 65534, 65534), 0);
                assert_eq!(libc::setresuid(65534, 65534, 65534), 0);
            }
        }
        assert_eq!(has_capability(CAP_SYS_NICE), Some(false));
        let cfg = RealtimeConfig {
            sched_fifo_priority: 80,
            cpu_affinity: vec![0],
            lock_memory: true,
            prefault_stack_bytes: 64 * 1024,
            require: false,
        };
        let cfg_require =
            RealtimeConfig { require: true, cpu_affinity: vec![], prefault_stack_bytes: 0, ..cfg.clone() };
        let (report, policy) = std::thread::Builder::new()
            .stack_size(1024 * 1024)
            .spawn(move || {
                let r = apply_to_current_thread(&cfg);
                // SAFETY: sched_getscheduler on the calling thread; no pointer is passed.
                (r, unsafe { libc::sched_getscheduler(0) })
            })
            .unwrap()
            .join()
            .unwrap();
        let report = report.expect("require = false must not fail");
        assert_eq!(report.cpu_affinity, StepOutcome::Applied, "affinity needs no privilege");
        match &report.sched_fifo {
            StepOutcome::Refused { reason } => {
                assert!(reason.contains("EPERM") && reason.contains("LimitRTPRIO") && reason.contains("CAP_SYS_NICE"))
            }
            other => panic!("sched_fifo: {other}"),
        }
        match &report.memory_lock {
            StepOutcome::Refused { reason } => assert!(reason.contains("LimitMEMLOCK"), "{reason}"),
            other => panic!("lock_memory: {other}"),
        }
        assert_eq!(report.stack_prefault, StepOutcome::Applied);
        assert_eq!(policy, libc::SCHED_OTHER, "the scheduler changed although refused");
        assert!(!report.fully_applied());
        // require = true turns the first refusal into an error naming the step.
        let err = apply_to_current_thread(&cfg_require).unwrap_err();
        assert!(matches!(err, RealtimeError::Refused { step: RtStep::SchedFifo, .. }), "{err}");
        assert!(err.to_string().contains("realtime.require = true"), "{err}");
    }

    #[test]
    fn apply_refusal_path_in_a_child_process() {
        run_child("rt::tests::child_apply_refusal_path");
    }

    /// The niceness of the calling thread (Linux: per thread).
    fn thread_nice() -> i32 {
        // SAFETY: gettid cannot fail; getpriority on the calling thread's id.
        let tid = libc::id_t::try_from(unsafe { libc::gettid() }).unwrap();
        // SAFETY: as above.
        unsafe { libc::getpriority(libc::PRIO_PROCESS, tid) }
    }

    /// The calling thread's (policy, priority).
    fn thread_sched() -> (libc::c_int, libc::c_int) {
        let mut q = libc::sched_param { sched_priority: 0 };
        // SAFETY: pid 0 is the calling thread; `q` is a valid out-pointer.
        assert_eq!(unsafe { libc::sched_getparam(0, &mut q) }, 0);
        // SAFETY: as above.
        (unsafe { libc::sched_getscheduler(0) }, q.sched_priority)
    }

    /// Sets the calling thread's policy and priority; true on success.
    fn set_thread_sched(policy: libc::c_int, priority: libc::c_int) -> bool {
        let p = libc::sched_param { sched_priority: priority };
        // SAFETY: pid 0 is the calling thread; `p` is a valid sched_param.
        unsafe { libc::sched_setscheduler(0, policy, &p) == 0 }
    }

    #[test]
    fn a_lowered_thread_is_nicer_than_the_threads_beside_it_and_its_children_inherit() {
        // On a fresh thread, so the test harness's threads keep their niceness.
        std::thread::spawn(|| {
            let before = thread_nice();
            let sibling = std::thread::spawn(thread_nice);
            let lowered = lower_current_thread();
            let after = thread_nice();
            let child = std::thread::spawn(thread_nice).join().unwrap();
            assert_eq!(sibling.join().unwrap(), before, "a thread started before keeps its niceness");
            if before >= 19 {
                assert!(matches!(lowered, Lowered::Unchanged { .. }), "{lowered}");
                assert_eq!(after, before);
            } else {
                assert_eq!(lowered, Lowered::Niced { from: before, to: (before + LOWER_NICE_STEPS).min(19) });
                assert_eq!(after, (before + LOWER_NICE_STEPS).min(19));
                assert_eq!(child, after, "threads created afterwards inherit it");
            }
            // Again and again: it saturates at 19 and then says so.
            for _ in 0..8 {
                lower_current_thread();
            }
            assert_eq!(thread_nice(), 19);
            assert!(matches!(lower_current_thread(), Lowered::Unchanged { .. }));
        })
        .join()
        .unwrap();
    }

    #[test]
    fn a_lowered_real_time_thread_is_one_priority_below_in_the_same_policy() {
        std::thread::spawn(|| {
            if !set_thread_sched(libc::SCHED_RR, 10) {
                eprintln!("SCHED_RR refused here ({}): the real-time path is not exercised", Errno::last());
                return;
            }
            assert_eq!(lower_current_thread(), Lowered::RealTime { policy: "SCHED_RR", from: 10, to: 9 });
            assert_eq!(thread_sched(), (libc::SCHED_RR, 9));
            let child = std::thread::spawn(thread_sched);
            assert_eq!(child.join().unwrap(), (libc::SCHED_RR, 9), "threads created afterwards inherit it");
            assert!(set_thread_sched(libc::SCHED_FIFO, 1));
            assert!(matches!(lower_current_thread(), Lowered::Unchanged { .. }), "FIFO 1 is the floor");
            assert_eq!(thread_sched(), (libc::SCHED_FIFO, 1));
        })
        .join()
        .unwrap();
    }

    #[test]
    fn periodic_keeps_absolute_deadlines_and_skips_after_a_stall() {
        const PERIOD: u64 = 1_000_000;
        let mut p = Periodic::new(PERIOD).unwrap();
        let first = p.next_deadline_ns();
        let mut ticks = Vec::with_capacity(500);
        for i in 0..500 {
            ticks.push(p.wait().unwrap());
            if i == 250 {
                std::thread::sleep(Duration::from_millis(5));
            }
        }
        assert_eq!(ticks[0].deadline_ns, first + PERIOD * ticks[0].overruns);
        for w in ticks.windows(2) {
            assert_eq!(w[1].deadline_ns - w[0].deadline_ns, PERIOD * (1 + w[1].overruns), "{w:?}");
        }
        for t in &ticks {
            assert!(t.woke_ns >= t.deadline_ns, "woke before its deadline: {t:?}");
            assert_eq!(t.late_ns, t.woke_ns - t.deadline_ns);
        }
        let stall = ticks[251];
        assert!((5..=50).contains(&stall.overruns), "5 ms stall reported as {} overruns", stall.overruns);
        let mut late: Vec<u64> = ticks.iter().map(|t| t.late_ns).collect();
        late.sort_unstable();
        let median = late[late.len() / 2];
        assert!(median < 2_000_000, "median lateness {median} ns");
        let total_overruns: u64 = ticks.iter().map(|t| t.overruns).sum();
        eprintln!(
            "periodic 1 ms x 500: median late {} us, p99 {} us, max {} us, overruns {} (stall tick {})",
            median / 1000,
            late[late.len() * 99 / 100] / 1000,
            late[late.len() - 1] / 1000,
            total_overruns,
            stall.overruns
        );
    }

    #[test]
    fn zero_period_is_refused_and_past_deadlines_do_not_burst() {
        assert_eq!(Periodic::new(0), Err(PeriodError::Zero));
        // First deadline 10 periods in the past: one wait skips them all.
        let period = 1_000_000;
        let mut p = Periodic::starting_at(monotonic_now_ns() - 10 * period, period).unwrap();
        let t = p.wait().unwrap();
        assert!(t.overruns >= 10, "{t:?}");
        let t2 = p.wait().unwrap();
        assert_eq!(t2.deadline_ns, t.deadline_ns + period * (1 + t2.overruns));
        // sleep_until_ns on a past deadline returns at once.
        let before = monotonic_now_ns();
        sleep_until_ns(before - 1).unwrap();
        assert!(monotonic_now_ns() - before < 50_000_000);
    }
}
