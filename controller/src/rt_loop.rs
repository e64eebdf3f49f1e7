//! The 1 kHz cycle of fulcrumd, on any [`CanBus`].
//!
//! Per cycle (absolute deadlines, `clock_nanosleep(TIMER_ABSTIME)`, no busy-polling):
//! 1. wait for the cycle's deadline ([`Periodic`]);
//! 2. drain frames that arrived since the previous cycle's collection ended (late TPDOs are
//!    counted, EMCY and heartbeats taken into account);
//! 3. send SYNC; collect this cycle's TPDOs until all three are in or `frame_deadline_us`
//!    after the SYNC, blocking in the bus's receive (ppoll / condition variable); on
//!    SocketCAN the window is in bus time, from the kernel stamp of the SYNC's own echo
//!    ([`LoopParams::cut_by_bus_time`]), the rule `replay --candump` applies to a log;
//! 4. [`Acquisition::end_cycle`] → [`Estimation::process`] → publish a [`FulcrumSample`];
//! 5. account: timing histograms, counters, one [`CycleRecord`] to the flight recorder and
//!    state/health changes to the log hand-off — both through lock-free SPSC queues; the
//!    loop never blocks on them, never allocates, never does file I/O or logging itself.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use hw_io::can::{CanBus, CanFrame, RecvError, SyncSource, TimedFrame, unix_time_now_us};
use hw_io::ipc::{FulcrumSample, HealthFlags as Flags, OutputState};
use serde::{Deserialize, Serialize};

use crate::cycle::{Acquisition, AcquisitionStats, CycleInput, CycleOutput, Estimation};
use crate::rt::{ClockError, PeriodError, Periodic, monotonic_now_ns};
use crate::timing::{Histogram, Summary};
use crate::watchdog::LoopProgress;

/// Flight-recorder record of one cycle: everything needed to replay the estimation bit for
/// bit, and the cycle's timings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CycleRecord {
    /// Cycle number since start-up.
    pub sequence: u64,
    /// Instant the SYNC was sent, nanoseconds of `CLOCK_MONOTONIC`.
    pub sync_ns: u64,
    /// What acquisition delivered (raw counts, received nodes, health flags).
    pub input: CycleInput,
    /// What was published.
    pub output: CycleOutput,
    /// Wake-up lateness after the cycle's deadline, nanoseconds.
    pub wake_late_ns: u32,
    /// From the end of frame collection to the publication, nanoseconds.
    pub compute_ns: u32,
    /// From wake-up to the publication, nanoseconds.
    pub cycle_ns: u32,
}

/// Kind string of [`CycleRecord`] recordings.
pub const RECORD_KIND: &str = "fulcrumd.cycle.v1";

/// What the loop hands to the logging thread (lock-free, `Copy`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LogEvent {
    /// The published state changed (to outside or inside: invalid cycles are counted, not
    /// logged as state changes).
    State {
        /// Cycle number.
        sequence: u64,
        /// New state.
        state: OutputState,
        /// Trocar identity when inside.
        trocar_id: u32,
        /// Fulcrum, metres, robot base frame (zero unless inside).
        fulcrum_base_m: [f64; 3],
    },
    /// The health flags changed.
    Health {
        /// Cycle number.
        sequence: u64,
        /// Previous flags.
        old: Flags,
        /// New flags.
        new: Flags,
    },
    /// One or more periods were skipped because a cycle overran.
    Overrun {
        /// Cycle number.
        sequence: u64,
        /// Periods skipped.
        skipped: u64,
    },
    /// Publishing failed this cycle.
    PublishFailed {
        /// Cycle number.
        sequence: u64,
    },
}

/// With [`LoopParams::cut_by_bus_time`]: how long the loop waits for its SYNC's echo at most,
/// nanoseconds (100 ms). The echo is normally queued during the send itself.
pub const ECHO_WAIT_NS: u64 = 100_000_000;

/// With [`LoopParams::cut_by_bus_time`]: frames held while the loop waits for its SYNC's echo,
/// and frames held after a window closed, at most (more are handled between cycles at once).
pub const EARLY_FRAMES: usize = 32;

/// Capacity of the log hand-off queue (events). Overflowing events are counted.
pub const LOG_QUEUE: usize = 1024;

/// Lock-free single-producer single-consumer queue of [`LogEvent`]s.
pub type LogQueue = heapless::spsc::Queue<LogEvent, LOG_QUEUE>;

/// Counters the loop updates (relaxed atomics), readable from any thread while it runs. The
/// cycle count itself lives in [`LoopProgress`] (shared with the watchdog), not twice.
#[derive(Debug, Default)]
pub struct LoopCounters {
    /// Cycles whose published estimate was valid.
    pub valid_cycles: AtomicU64,
    /// Samples published.
    pub published: AtomicU64,
    /// Publications that failed.
    pub publish_errors: AtomicU64,
    /// Periods skipped by overruns.
    pub overruns: AtomicU64,
    /// Records the flight recorder's queue refused (full).
    pub recorder_drops: AtomicU64,
    /// Log events the log queue refused (full).
    pub log_drops: AtomicU64,
    /// Cycles that lacked at least one TPDO at their deadline.
    pub incomplete_cycles: AtomicU64,
    /// Frames the bus backend dropped since start-up because its receive queue was full
    /// ([`CanBus::dropped_rx_frames`]; on SocketCAN the kernel's `SO_RXQ_OVFL` count), as of
    /// the end of the last cycle.
    pub bus_dropped_rx_frames: AtomicU64,
}

/// Where the loop puts its per-cycle outputs; implemented by the daemon (iceoryx2
/// publisher, recorder producer) and by tests.
pub trait CycleSink {
    /// Publishes one sample; false when it failed (counted).
    fn publish(&mut self, sample: &FulcrumSample) -> bool;
    /// Hands one record to the flight recorder; false when its queue was full (counted).
    fn record(&mut self, record: &CycleRecord) -> bool;
    /// Hands one log event to the logging thread; false when its queue was full (counted).
    fn log(&mut self, event: LogEvent) -> bool;
}

/// Timing of the loop, collected allocation-free.
#[derive(Clone, Debug)]
pub struct LoopTiming {
    /// Wake-up lateness after each deadline (period error), nanoseconds.
    pub wake_late: Histogram,
    /// End of frame collection → publication, nanoseconds.
    pub compute: Histogram,
    /// Wake-up → publication, nanoseconds.
    pub cycle: Histogram,
}

/// Timing summaries, microseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TimingSummary {
    /// Period error: wake-up lateness after the deadline.
    pub wake_late: Summary,
    /// Compute: end of frame collection → publication.
    pub compute: Summary,
    /// Whole cycle: wake-up → publication (includes waiting for the TPDOs).
    pub cycle: Summary,
}

impl LoopTiming {
    fn new() -> Self {
        Self { wake_late: Histogram::new(20_000), compute: Histogram::new(20_000), cycle: Histogram::new(20_000) }
    }

    /// p50/p99/p99.9/max of each.
    pub fn summary(&self) -> TimingSummary {
        TimingSummary {
            wake_late: self.wake_late.summary(),
            compute: self.compute.summary(),
            cycle: self.cycle.summary(),
        }
    }
}

/// Why the loop stopped on its own.
#[derive(Debug, thiserror::Error)]
pub enum LoopError {
    /// The period is invalid (zero).
    #[error(transparent)]
    Period(#[from] PeriodError),
    /// The monotonic clock failed.
    #[error(transparent)]
    Clock(#[from] ClockError),
}

/// Parameters of the loop.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoopParams {
    /// Cycle period, nanoseconds.
    pub period_ns: u64,
    /// Frame collection deadline after SYNC, nanoseconds.
    pub frame_deadline_ns: u64,
    /// Random identifier of this run (published in every sample).
    pub run_id: u64,
    /// Stop after this many cycles (None: until stopped).
    pub max_cycles: Option<u64>,
    /// The bus echoes the loop's own frames with their bus timestamps (SocketCAN with
    /// [`hw_io::can::SocketCanBus::receive_own_frames`]). Then a frame belongs to the cycle when
    /// its **bus timestamp** is at most `frame_deadline_ns` after the SYNC's echo, whenever the
    /// loop gets to read it; a later one is late. This is the rule `fulcrumd replay --candump`
    /// applies to a candump log of the bus, so the log reproduces the loop's cycles exactly even
    /// when the loop's thread is woken late. false: the frames the loop has read before its
    /// deadline (monotonic clock) belong to the cycle.
    pub cut_by_bus_time: bool,
}

/// The control loop's state. Build it (allocates), then [`RtLoop::run`] (does not).
pub struct RtLoop<B: CanBus> {
    bus: B,
    sync: SyncSource,
    acquisition: Acquisition,
    estimation: Estimation,
    params: LoopParams,
    counters: Arc<LoopCounters>,
    progress: LoopProgress,
    timing: LoopTiming,
    sequence: u64,
    /// The last valid state logged with its trocar, `None` before the first valid cycle.
    last_state: Option<(OutputState, u32)>,
    last_health: Flags,
    prev_cycle_ns: u32,
    /// Frames read after their cycle's window closed (bus time): handled between cycles,
    /// first thing in the next cycle.
    pending: heapless::Deque<TimedFrame, EARLY_FRAMES>,
    /// Frames read before the SYNC's echo, sorted by stamp once it is in.
    early: heapless::Vec<TimedFrame, EARLY_FRAMES>,
}

impl<B: CanBus> RtLoop<B> {
    /// A loop on `bus`. Allocates its histograms here.
    pub fn new(
        bus: B,
        acquisition: Acquisition,
        estimation: Estimation,
        params: LoopParams,
        counters: Arc<LoopCounters>,
        progress: LoopProgress,
    ) -> Self {
        Self {
            bus,
            sync: SyncSource::new(),
            acquisition,
            estimation,
            params,
            counters,
            progress,
            timing: LoopTiming::new(),
            sequence: 0,
            last_state: None,
            last_health: Flags::empty(),
            prev_cycle_ns: 0,
            pending: heapless::Deque::new(),
            early: heapless::Vec::new(),
        }
    }

    /// The bus the loop runs on.
    pub fn bus(&self) -> &B {
        &self.bus
    }

    /// Acquisition counters.
    pub fn acquisition_stats(&self) -> &AcquisitionStats {
        self.acquisition.stats()
    }

    /// Timing histograms.
    pub fn timing(&self) -> &LoopTiming {
        &self.timing
    }

    /// Cycles run so far.
    ///
    /// **Real-time (1 kHz loop):** a field read.
    pub fn cycles(&self) -> u64 {
        self.sequence
    }

    /// Frames dropped by the bus's receive queue.
    ///
    /// **Real-time (1 kHz loop):** called every cycle (by the accounting); allocation-free.
    pub fn bus_dropped_rx_frames(&self) -> u64 {
        self.bus.dropped_rx_frames()
    }

    /// Runs cycles until `stop()` returns true (checked once per cycle) or `max_cycles`.
    /// Fails only if the monotonic clock fails.
    ///
    /// **Real-time (1 kHz loop):** this is the loop. Allocation-free (with a `stop` that does not
    /// allocate), sleeps until each absolute deadline, waits only in the bus's bounded receive,
    /// no file I/O, no logging.
    pub fn run(&mut self, sink: &mut impl CycleSink, mut stop: impl FnMut() -> bool) -> Result<(), LoopError> {
        let period = self.params.period_ns;
        let mut periodic = Periodic::starting_at(monotonic_now_ns() + period, period)?;
        while !stop() && self.params.max_cycles.is_none_or(|m| self.sequence < m) {
            let tick = periodic.wait()?;
            self.cycle(tick.woke_ns, tick.late_ns, tick.overruns, sink);
        }
        Ok(())
    }

    /// Collects this cycle's frames until all TPDOs are in or `deadline` (monotonic clock):
    /// what the loop has read by then belongs to the cycle.
    fn collect_until(&mut self, sync_ns: u64, deadline: u64) {
        let mut now = sync_ns;
        while !self.acquisition.is_complete() && now < deadline {
            match self.bus.recv_timeout(Duration::from_nanos(deadline - now)) {
                Ok(Some(f)) => {
                    now = monotonic_now_ns();
                    self.acquisition.on_frame(&f.frame, now);
                }
                Ok(None) => break,
                Err(_) => {
                    self.acquisition.on_bus_error();
                    break;
                }
            }
        }
    }

    /// Collects this cycle's frames by bus time ([`LoopParams::cut_by_bus_time`]): a frame
    /// stamped before the SYNC's echo is between cycles; one stamped at most
    /// `frame_deadline_ns` after the echo belongs to the cycle; the first one stamped later
    /// closes it (it and the frames read with it are handled between cycles, first thing in the
    /// next cycle). Frames read before the echo are held (up to [`EARLY_FRAMES`]) and sorted
    /// by their stamps once the echo is in: under load the kernel can hand the loop the
    /// nodes' answers before its own echo. Once the echo is in, the loop waits until the end
    /// of the window (mapped from the wall clock of the stamps to the monotonic clock), then
    /// takes what is queued without waiting. The echo is awaited up to [`ECHO_WAIT_NS`] (the
    /// cycle then overruns); without it the cycle closes incomplete.
    fn collect_by_bus_time(&mut self, sync_frame: &CanFrame, sync_ns: u64) {
        let window_us = self.params.frame_deadline_ns / 1000;
        let mut echo_us: Option<u64> = None;
        let mut deadline = sync_ns.saturating_add(self.params.frame_deadline_ns.max(ECHO_WAIT_NS));
        self.early.clear();
        while !self.acquisition.is_complete() {
            let wait = deadline.saturating_sub(monotonic_now_ns());
            let f = match self.bus.recv_timeout(Duration::from_nanos(wait)) {
                Ok(Some(f)) => f,
                Ok(None) => break,
                Err(_) => {
                    self.acquisition.on_bus_error();
                    break;
                }
            };
            let now = monotonic_now_ns();
            match echo_us {
                None if f.frame == *sync_frame => {
                    let t0 = f.unix_time_us;
                    echo_us = Some(t0);
                    // The window ends at echo + frame deadline (wall clock of the stamps).
                    let left_us = t0.saturating_add(window_us).saturating_sub(unix_time_now_us());
                    deadline = now.saturating_add(left_us.saturating_mul(1000));
                    // Frames read before the echo: those stamped before it first.
                    for k in 0..self.early.len() {
                        if self.early[k].unix_time_us < t0 {
                            self.acquisition.on_frame_between_cycles(&self.early[k].frame, now);
                        }
                    }
                    let mut closed = false;
                    for k in 0..self.early.len() {
                        let e = self.early[k];
                        if e.unix_time_us < t0 {
                            continue;
                        }
                        closed |= e.unix_time_us > t0.saturating_add(window_us);
                        if closed {
                            self.hold(e, now);
                        } else {
                            self.acquisition.on_frame(&e.frame, now);
                        }
                    }
                    self.early.clear();
                    if closed {
                        break;
                    }
                }
                None => {
                    if self.early.is_full() {
                        let oldest = self.early.remove(0);
                        self.acquisition.on_frame_between_cycles(&oldest.frame, now);
                    }
                    let _ = self.early.push(f);
                }
                Some(t0) if f.unix_time_us <= t0.saturating_add(window_us) => self.acquisition.on_frame(&f.frame, now),
                Some(_) => {
                    self.hold(f, now);
                    break;
                }
            }
        }
        // No echo came: whatever was read is between cycles.
        let now = monotonic_now_ns();
        for k in 0..self.early.len() {
            self.acquisition.on_frame_between_cycles(&self.early[k].frame, now);
        }
        self.early.clear();
    }

    /// Keeps a frame read after its cycle's window for the next cycle's between-cycles
    /// handling (or handles it now when the holding queue is full).
    fn hold(&mut self, f: TimedFrame, now_ns: u64) {
        if let Err(f) = self.pending.push_back(f) {
            self.acquisition.on_frame_between_cycles(&f.frame, now_ns);
        }
    }

    /// One cycle, woken at `woke_ns` (`late_ns` after its deadline, `skipped` periods
    /// skipped before it): [`Self::collect`] → [`Self::process`] → [`Self::account`], as copper
    /// splits a task into preprocess / process / postprocess.
    ///
    /// **Real-time (1 kHz loop):** allocation-free; blocks only in the bus's bounded receive.
    fn cycle(&mut self, woke_ns: u64, late_ns: u64, skipped: u64, sink: &mut impl CycleSink) {
        let collected = self.collect();
        let processed = self.process(&collected, late_ns, skipped, sink);
        self.account(&collected, &processed, woke_ns, late_ns, skipped, sink);
        self.sequence += 1;
    }

    /// Steps 2 and 3 of the cycle: drains the frames that arrived since the previous
    /// collection ended (late TPDOs, status), sends SYNC and collects this cycle's TPDOs until
    /// all are in or the frame deadline (bus time on SocketCAN, monotonic clock otherwise).
    ///
    /// **Real-time (1 kHz loop):** allocation-free; waits only in the bus's receive, bounded by
    /// the frame deadline (by [`ECHO_WAIT_NS`] for the SYNC's echo); no I/O besides the bus.
    fn collect(&mut self) -> Collected {
        // 2. Frames since the last collection ended are late (TPDOs) or status.
        while let Some(f) = self.pending.pop_front() {
            self.acquisition.on_frame_between_cycles(&f.frame, monotonic_now_ns());
        }
        loop {
            match self.bus.recv_timeout(Duration::ZERO) {
                Ok(Some(f)) => self.acquisition.on_frame_between_cycles(&f.frame, monotonic_now_ns()),
                Ok(None) | Err(RecvError::EndOfReplay) => break,
                Err(_) => {
                    self.acquisition.on_bus_error();
                    break;
                }
            }
        }
        // 3. SYNC, then collect.
        let sync_frame = self.sync.next_frame();
        let sync_failed = self.bus.send(&sync_frame).is_err();
        let sync_ns = monotonic_now_ns();
        self.acquisition.start_cycle();
        let deadline = sync_ns + self.params.frame_deadline_ns;
        if self.params.cut_by_bus_time {
            if !sync_failed {
                self.collect_by_bus_time(&sync_frame, sync_ns);
            }
        } else {
            self.collect_until(sync_ns, deadline);
        }
        Collected { sync_ns, sync_failed, collected_ns: monotonic_now_ns() }
    }

    /// Step 4 of the cycle, the time-critical part: [`Acquisition::end_cycle`] →
    /// [`Estimation::process`] (deterministic: what `replay` reruns bit for bit) → one
    /// [`FulcrumSample`] published through `sink`.
    ///
    /// **Real-time (1 kHz loop):** allocation-free (the publisher's per-sample block comes from
    /// the pool allocator), never blocks, no I/O besides the publication.
    fn process(&mut self, c: &Collected, late_ns: u64, skipped: u64, sink: &mut impl CycleSink) -> Processed {
        let mut input = self.acquisition.end_cycle(c.collected_ns, c.sync_failed);
        if skipped > 0 {
            input.flags |= Flags::OVERRUN;
        }
        // 4. Estimate and publish.
        let output = self.estimation.process(&input);
        let mut sample = output.to_sample();
        sample.sequence = self.sequence;
        sample.run_id = self.params.run_id;
        sample.timestamp_ns = c.sync_ns;
        sample.wake_late_ns = saturate_u32(late_ns);
        sample.prev_cycle_compute_ns = self.prev_cycle_ns;
        let published = sink.publish(&sample);
        Processed { input, output, published, done_ns: monotonic_now_ns() }
    }

    /// Step 5 of the cycle, best-effort and not time-critical (after the publication): timing
    /// histograms, counters, the [`CycleRecord`] for the flight recorder, state and health
    /// changes and overruns for the log hand-off, the watchdog's progress. A full queue is
    /// counted, never waited on.
    ///
    /// **Real-time (1 kHz loop):** allocation-free, never blocks (lock-free SPSC queues and
    /// relaxed atomics), no I/O, no logging itself.
    fn account(
        &mut self,
        c: &Collected,
        r: &Processed,
        woke_ns: u64,
        late_ns: u64,
        skipped: u64,
        sink: &mut impl CycleSink,
    ) {
        let seq = self.sequence;
        let Processed { input, output, published, done_ns } = *r;
        // 5. Account.
        let p = &self.counters;
        if published {
            p.published.fetch_add(1, Ordering::Relaxed);
        } else {
            p.publish_errors.fetch_add(1, Ordering::Relaxed);
            if !sink.log(LogEvent::PublishFailed { sequence: seq }) {
                p.log_drops.fetch_add(1, Ordering::Relaxed);
            }
        }
        let compute_ns = done_ns.saturating_sub(c.collected_ns);
        let cycle_ns = done_ns.saturating_sub(woke_ns);
        self.timing.wake_late.record(late_ns);
        self.timing.compute.record(compute_ns);
        self.timing.cycle.record(cycle_ns);
        self.prev_cycle_ns = saturate_u32(cycle_ns);
        let record = CycleRecord {
            sequence: seq,
            sync_ns: c.sync_ns,
            input,
            output,
            wake_late_ns: saturate_u32(late_ns),
            compute_ns: saturate_u32(compute_ns),
            cycle_ns: self.prev_cycle_ns,
        };
        if !sink.record(&record) {
            p.recorder_drops.fetch_add(1, Ordering::Relaxed);
        }
        let mut log = |e| {
            if !sink.log(e) {
                p.log_drops.fetch_add(1, Ordering::Relaxed);
            }
        };
        if skipped > 0 {
            p.overruns.fetch_add(skipped, Ordering::Relaxed);
            log(LogEvent::Overrun { sequence: seq, skipped });
        }
        // State changes of valid estimates only: a one-cycle data gap is not a state change
        // (it is counted, and the daemon reports counts periodically).
        let valid = output.state.is_valid();
        let state = (output.state, output.trocar_id);
        if valid && self.last_state != Some(state) {
            log(LogEvent::State {
                sequence: seq,
                state: output.state,
                trocar_id: output.trocar_id,
                fulcrum_base_m: output.fulcrum_base_m,
            });
            self.last_state = Some(state);
        }
        // Lasting health conditions only; per-cycle ones are counted.
        let h = output.health - (Flags::OVERRUN | Flags::INCOMPLETE_CYCLE | Flags::DETECTOR_RESET);
        if h != self.last_health {
            log(LogEvent::Health { sequence: seq, old: self.last_health, new: h });
            self.last_health = h;
        }
        if input.flags.contains(Flags::INCOMPLETE_CYCLE) {
            p.incomplete_cycles.fetch_add(1, Ordering::Relaxed);
        }
        if valid {
            p.valid_cycles.fetch_add(1, Ordering::Relaxed);
        }
        p.bus_dropped_rx_frames.store(self.bus.dropped_rx_frames(), Ordering::Relaxed);
        // The watchdog stores them in atomics: their wire `u32`s.
        self.progress.record_cycle(valid, output.state.into(), output.health.bits());
    }
}

/// What [`RtLoop::collect`] hands to the rest of the cycle (nanoseconds of `CLOCK_MONOTONIC`).
#[derive(Clone, Copy, Debug)]
struct Collected {
    /// Instant the SYNC was sent.
    sync_ns: u64,
    /// The SYNC could not be sent (the cycle is flagged, nothing was collected on SocketCAN).
    sync_failed: bool,
    /// Instant the collection ended.
    collected_ns: u64,
}

/// What [`RtLoop::process`] hands to [`RtLoop::account`].
#[derive(Clone, Copy, Debug)]
struct Processed {
    /// What acquisition delivered.
    input: CycleInput,
    /// What was published.
    output: CycleOutput,
    /// The publication succeeded.
    published: bool,
    /// Instant the publication returned, nanoseconds of `CLOCK_MONOTONIC`.
    done_ns: u64,
}

/// A duration in nanoseconds as the `u32` of a record or sample, saturated (4.29 s).
fn saturate_u32(ns: u64) -> u32 {
    ns.min(u64::from(u32::MAX)) as u32
}
