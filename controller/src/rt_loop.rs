//! The 1 kHz cycle of fulcrumd, on any [`CanBus`].
//!
//! Per cycle (absolute deadlines, `clock_nanosleep(TIMER_ABSTIME)`, no busy-polling):
//! 1. wait for the cycle's deadline ([`Periodic`]);
//! 2. drain frames that arrived since the previous cycle's collection ended (late TPDOs are
//!    counted, EMCY and heartbeats taken into account);
//! 3. send SYNC; collect this cycle's TPDOs until all three are in or `frame_deadline_us`
//!    after the SYNC, blocking in the bus's receive (ppoll / condition variable);
//! 4. [`Acquisition::end_cycle`] → [`Estimation::process`] → publish a [`FulcrumSample`];
//! 5. account: timing histograms, counters, one [`CycleRecord`] to the flight recorder and
//!    state/health changes to the log hand-off — both through lock-free SPSC queues; the
//!    loop never blocks on them, never allocates, never does file I/O or logging itself.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use hw_io::can::{CanBus, CanFrame, RecvError, SyncSource, TimedFrame};
use hw_io::ipc::{FulcrumSample, STATE_INVALID, health as flags};
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
    /// The published state changed (`STATE_*` of [`hw_io::ipc`]).
    State {
        /// Cycle number.
        sequence: u64,
        /// New state.
        state: u32,
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
        old: u32,
        /// New flags.
        new: u32,
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
    last_state: u32,
    last_trocar: u32,
    last_health: u32,
    prev_cycle_ns: u32,
    /// A frame read after its cycle's window closed (bus time): handled between cycles, first
    /// thing in the next cycle.
    pending: Option<TimedFrame>,
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
            last_state: u32::MAX,
            last_trocar: 0,
            last_health: 0,
            prev_cycle_ns: 0,
            pending: None,
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
    pub fn cycles(&self) -> u64 {
        self.sequence
    }

    /// Frames dropped by the bus's receive queue.
    pub fn bus_dropped_rx_frames(&self) -> u64 {
        self.bus.dropped_rx_frames()
    }

    /// Runs cycles until `stop()` returns true (checked once per cycle) or `max_cycles`.
    /// Allocation-free. Fails only if the monotonic clock fails.
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

    /// Collects this cycle's frames by bus time ([`LoopParams::cut_by_bus_time`]): frames
    /// before the SYNC's echo are between cycles; after it, a frame stamped at most
    /// `frame_deadline_ns` after the echo belongs to the cycle, the first one stamped later
    /// closes it (kept for the next cycle's between-cycles handling). The loop waits until
    /// `deadline` (monotonic clock, counted from after the send, so every frame of the window
    /// is queued by then), then takes what is queued without waiting.
    fn collect_by_bus_time(&mut self, sync_frame: &CanFrame, deadline: u64) {
        let window_us = self.params.frame_deadline_ns / 1000;
        let mut echo_us: Option<u64> = None;
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
                None if f.frame == *sync_frame => echo_us = Some(f.unix_time_us),
                // Queued before our SYNC went out.
                None => self.acquisition.on_frame_between_cycles(&f.frame, now),
                Some(t0) if f.unix_time_us <= t0.saturating_add(window_us) => self.acquisition.on_frame(&f.frame, now),
                Some(_) => {
                    self.pending = Some(f);
                    break;
                }
            }
        }
    }

    /// One cycle, woken at `woke_ns` (`late_ns` after its deadline, `skipped` periods
    /// skipped before it).
    fn cycle(&mut self, woke_ns: u64, late_ns: u64, skipped: u64, sink: &mut impl CycleSink) {
        let seq = self.sequence;
        // 2. Frames since the last collection ended are late (TPDOs) or status.
        if let Some(f) = self.pending.take() {
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
                self.collect_by_bus_time(&sync_frame, deadline);
            }
        } else {
            self.collect_until(sync_ns, deadline);
        }

        let collected_ns = monotonic_now_ns();
        let mut input = self.acquisition.end_cycle(collected_ns, sync_failed);
        if skipped > 0 {
            input.flags |= flags::OVERRUN;
        }
        // 4. Estimate and publish.
        let output = self.estimation.process(&input);
        let mut sample = output.to_sample();
        sample.sequence = seq;
        sample.run_id = self.params.run_id;
        sample.timestamp_ns = sync_ns;
        sample.wake_late_ns = late_ns.min(u64::from(u32::MAX)) as u32;
        sample.prev_cycle_compute_ns = self.prev_cycle_ns;
        let published = sink.publish(&sample);
        let done_ns = monotonic_now_ns();
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
        let compute_ns = done_ns.saturating_sub(collected_ns);
        let cycle_ns = done_ns.saturating_sub(woke_ns);
        self.timing.wake_late.record(late_ns);
        self.timing.compute.record(compute_ns);
        self.timing.cycle.record(cycle_ns);
        self.prev_cycle_ns = cycle_ns.min(u64::from(u32::MAX)) as u32;
        let record = CycleRecord {
            sequence: seq,
            sync_ns,
            input,
            output,
            wake_late_ns: sample.wake_late_ns,
            compute_ns: compute_ns.min(u64::from(u32::MAX)) as u32,
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
        if output.state != STATE_INVALID && (output.state != self.last_state || output.trocar_id != self.last_trocar) {
            log(LogEvent::State {
                sequence: seq,
                state: output.state,
                trocar_id: output.trocar_id,
                fulcrum_base_m: output.fulcrum_base_m,
            });
            self.last_state = output.state;
            self.last_trocar = output.trocar_id;
        }
        // Lasting health conditions only; per-cycle ones are counted.
        let h = output.health & !(flags::OVERRUN | flags::INCOMPLETE_CYCLE | flags::DETECTOR_RESET);
        if h != self.last_health {
            log(LogEvent::Health { sequence: seq, old: self.last_health, new: h });
            self.last_health = h;
        }
        if input.flags & flags::INCOMPLETE_CYCLE != 0 {
            p.incomplete_cycles.fetch_add(1, Ordering::Relaxed);
        }
        if output.state != STATE_INVALID {
            p.valid_cycles.fetch_add(1, Ordering::Relaxed);
        }
        self.progress.record_cycle(output.state != STATE_INVALID, output.state, output.health);
        self.sequence += 1;
    }
}
