//! The real control loop ([`RtLoop`]) against a scripted bus on which the simulated robot
//! answers each SYNC at once (virtual time: 1 ms per SYNC), with injected faults. Checks the
//! health flags, that no estimate built on stale data is published as valid, that nothing
//! is NaN, recovery, and that the loop allocates nothing.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use controller::config::Config;
use controller::cycle::{Acquisition, Estimation};
use controller::rt_loop::{CycleRecord, CycleSink, LogEvent, LoopCounters, LoopParams, RtLoop};
use controller::watchdog::LoopProgress;
use hw_io::can::{CanBus, CanFrame, Message, RecvError, SendError, TimedFrame};
use hw_io::ipc::{FulcrumSample, HealthFlags, OutputState};
use sim::encoders::EmcyInjection;
use sim::twin::{SimRobot, TwinConfig};

#[global_allocator]
static GLOBAL: hw_io::rt_alloc::RtPoolAllocator = hw_io::rt_alloc::RtPoolAllocator::new();
fn allocs() -> u64 {
    hw_io::rt_alloc::thread_system_allocs()
}

/// The simulated robot's answers (computed before the loop runs, so that the robot's own
/// work is not counted), delivered on the spot, plus injected junk frames.
struct ScriptedBus {
    answers: Vec<Vec<TimedFrame>>,
    queue: VecDeque<TimedFrame>,
    syncs: u64,
    /// Junk frames injected after each SYNC's answer: (from sync, to sync, frames).
    junk: Vec<CanFrame>,
    junk_window: (u64, u64),
    /// Echo the loop's SYNC (stamped `sync index * 1000` µs), as SocketCAN with
    /// `receive_own_frames` does: before the answers, or (`echo_last`) after them, as a loaded
    /// kernel can deliver it.
    echo: bool,
    echo_last: bool,
    /// Every frame on the bus in order, as candump would log it.
    log: Vec<TimedFrame>,
}

impl CanBus for ScriptedBus {
    fn send(&mut self, frame: &CanFrame) -> Result<(), SendError> {
        if let Ok(Message::Sync { .. }) = Message::decode(frame) {
            let t_us = self.syncs * 1000;
            let echo = TimedFrame { frame: *frame, unix_time_us: t_us };
            // The log never grows past its capacity (0 in the allocation tests).
            if self.log.len() < self.log.capacity() {
                self.log.push(echo);
            }
            if self.echo && !self.echo_last {
                self.queue.push_back(echo);
            }
            if let Some(frames) = self.answers.get(self.syncs as usize) {
                for f in frames {
                    self.queue.push_back(*f);
                    if self.log.len() < self.log.capacity() {
                        self.log.push(*f);
                    }
                }
            }
            if self.echo && self.echo_last {
                self.queue.push_back(echo);
            }
            if (self.junk_window.0..self.junk_window.1).contains(&self.syncs) {
                for j in &self.junk {
                    self.queue.push_back(TimedFrame { frame: *j, unix_time_us: t_us });
                }
            }
            self.syncs += 1;
        }
        Ok(())
    }
    fn recv_timeout(&mut self, _timeout: Duration) -> Result<Option<TimedFrame>, RecvError> {
        Ok(self.queue.pop_front())
    }
}

#[derive(Default)]
struct Collect {
    samples: Vec<FulcrumSample>,
}

impl CycleSink for Collect {
    fn publish(&mut self, sample: &FulcrumSample) -> bool {
        if self.samples.len() < self.samples.capacity() {
            self.samples.push(*sample);
        }
        true
    }
    fn record(&mut self, _: &CycleRecord) -> bool {
        true
    }
    fn log(&mut self, _: LogEvent) -> bool {
        true
    }
}

/// The daemon's defaults, but for the heartbeat timeout. The twin's nodes run on the bus's
/// virtual clock (1 ms per SYNC: a heartbeat every 100 cycles) while the loop runs its cycles
/// 20 µs apart, and the health monitor times the heartbeats on the monotonic clock. With the
/// default 350 ms, a stall of this test process (descheduled on a loaded host) flagged
/// NODE_HEARTBEAT on every node and invalidated the cycles up to the next heartbeat: it failed
/// `a_node_silent_for_200_ms_is_flagged_stale_then_recovers` once at load 9, and a SIGSTOP of
/// 0.5 s reproduces it. Here heartbeats come every 100 cycles whatever the host does, so the
/// timeout only has to outlast any stall; the heartbeat rule itself is tested on explicit times
/// in `controller/src/health.rs`.
fn config() -> Config {
    let mut cfg = Config::default();
    cfg.health.heartbeat_timeout_ms = 600_000;
    cfg
}

fn run(
    twin: TwinConfig,
    cycles: u64,
    junk: Vec<CanFrame>,
    junk_window: (u64, u64),
) -> (Vec<FulcrumSample>, RtLoop<ScriptedBus>, u64) {
    let cfg = config();
    let mut robot = SimRobot::new(&twin).unwrap();
    let mut sync = hw_io::can::SyncSource::new();
    let answers = (0..cycles)
        .map(|k| match robot.on_sync(sync.next_counter(), k * 1000).unwrap() {
            Some(frames) => frames.to_vec(),
            None => Vec::new(),
        })
        .collect();
    let bus = ScriptedBus {
        answers,
        queue: VecDeque::with_capacity(1024),
        syncs: 0,
        junk,
        junk_window,
        echo: false,
        echo_last: false,
        log: Vec::new(),
    };
    let acq = Acquisition::new(&cfg.bus.encoder, cfg.health).unwrap();
    let est = Estimation::new(&cfg.bus.encoder, &cfg.kinematics, &cfg.detector).unwrap();
    let params = LoopParams {
        period_ns: 20_000,
        frame_deadline_ns: 5_000_000,
        run_id: 7,
        max_cycles: Some(cycles),
        cut_by_bus_time: false,
    };
    let mut lp = RtLoop::new(bus, acq, est, params, Arc::new(LoopCounters::default()), LoopProgress::new());
    let mut sink = Collect { samples: Vec::with_capacity(cycles as usize) };
    let before = allocs();
    lp.run(&mut sink, || false).unwrap();
    let n = allocs() - before;
    (sink.samples, lp, n)
}

fn twin() -> TwinConfig {
    let mut t = TwinConfig::default();
    t.scenario.cycles = 2;
    t.endless = true;
    t
}

fn assert_never_invalid_data_as_valid(samples: &[FulcrumSample]) {
    for s in samples {
        let floats = s.fulcrum_base_m.iter().chain(&s.wrist_base_m).chain(&s.axis_base).chain(&s.joints_rad);
        assert!(floats.chain([s.residual_m, s.fulcrum_std_m, s.conditioning].iter()).all(|v| v.is_finite()));
        if s.health().intersects(HealthFlags::INVALIDATING) {
            assert_eq!(
                s.state(),
                Ok(OutputState::Invalid),
                "seq {}: flags {} but state {}",
                s.sequence,
                s.health(),
                s.state
            );
            assert_eq!(s.fulcrum(), None);
        }
    }
}

#[test]
fn clean_run_detects_insertions_publishes_every_cycle_and_allocates_nothing() {
    let (samples, lp, n_alloc) = run(twin(), 30_000, Vec::new(), (0, 0));
    assert_eq!(samples.len(), 30_000);
    assert!(samples.iter().enumerate().all(|(i, s)| s.sequence == i as u64 && s.run_id == 7));
    assert_eq!(n_alloc, 0, "the loop allocated {n_alloc} times");
    assert_eq!(lp.acquisition_stats().incomplete_cycles, 0);
    let valid = samples.iter().filter(|s| s.is_valid()).count();
    assert_eq!(valid, 30_000);
    let inside = samples.iter().filter(|s| s.state() == Ok(OutputState::Inside)).count();
    assert!(inside > 5_000, "inside {inside} cycles");
    assert_never_invalid_data_as_valid(&samples);
}

#[test]
fn a_node_silent_for_200_ms_is_flagged_stale_then_recovers() {
    let mut t = twin();
    // Node 2 stops answering from 3.0 s to 3.2 s (inside the first trocar).
    t.nodes[1].dropout_windows_us = vec![[3_000_000, 3_200_000]];
    let (samples, lp, _) = run(t, 8_000, Vec::new(), (0, 0));
    assert_never_invalid_data_as_valid(&samples);
    let stale: Vec<_> = samples.iter().filter(|s| s.health().intersects(HealthFlags::NODE_STALE[1])).collect();
    // Stale from the 3rd missed cycle to the end of the window.
    assert!((195..=200).contains(&stale.len()), "{} stale cycles", stale.len());
    assert!(samples[3_000..3_200].iter().all(|s| s.state() == Ok(OutputState::Invalid)));
    assert!(samples[3_200].is_valid(), "valid again at once: {:#x}", samples[3_200].health);
    assert!(samples[3_200].health().intersects(HealthFlags::DETECTOR_RESET));
    let bad: Vec<_> = samples[3_300..].iter().filter(|s| !s.is_valid()).map(|s| (s.sequence, s.health)).collect();
    assert!(bad.is_empty(), "{:?}", &bad[..bad.len().min(5)]);
    assert_eq!(lp.acquisition_stats().incomplete_cycles, 200);
}

/// Short gaps (a node silent for up to `max_gap_s`, 50 ms) freeze the detector: the trocar
/// is kept, no reset, no extraction, every cycle of the gap invalid. A longer gap resets.
#[test]
fn a_short_gap_keeps_the_trocar_and_a_long_one_resets() {
    // Where the instrument is inside a detected trocar in the gap-free run.
    let (clean, _, _) = run(twin(), 8_000, Vec::new(), (0, 0));
    let start = (2_000..7_000)
        .find(|&i| clean[i..i + 400].iter().all(|s| s.state() == Ok(OutputState::Inside)))
        .expect("an insertion in the first 7 s");
    let at = start + 150;
    for (gap_ms, resets) in [(3u64, false), (20, false), (50, false), (60, true)] {
        let mut t = twin();
        t.nodes[1].dropout_windows_us = vec![[at as u64 * 1000, (at as u64 + gap_ms) * 1000]];
        let (samples, _, _) = run(t, at as u64 + 300, Vec::new(), (0, 0));
        assert_never_invalid_data_as_valid(&samples);
        let gap = &samples[at..at + gap_ms as usize];
        assert!(gap.iter().all(|s| s.state() == Ok(OutputState::Invalid)), "{gap_ms} ms: a gap cycle was valid");
        let after = &samples[at + gap_ms as usize];
        assert!(after.is_valid(), "{gap_ms} ms: not valid after the gap: {:#x}", after.health);
        assert_eq!(after.health().intersects(HealthFlags::DETECTOR_RESET), resets, "{gap_ms} ms: reset flag");
        if !resets {
            // The trocar is kept through the gap and after it, with the same id.
            assert_eq!(after.state(), Ok(OutputState::Inside), "{gap_ms} ms: the trocar was dropped");
            assert_eq!(after.trocar_id, samples[at - 1].trocar_id);
            assert!(samples[at + gap_ms as usize..].iter().take(200).all(|s| s.state() == Ok(OutputState::Inside)));
        } else {
            assert_eq!(after.state(), Ok(OutputState::Outside), "a long gap must reset to outside");
        }
    }
}

/// Random TPDO loss (1 % per frame on every node: a lost frame every ~33 cycles) leaves the
/// detection as it is without loss: the gaps freeze and resume, nothing resets.
#[test]
fn random_tpdo_loss_changes_no_detection() {
    let (clean, _, _) = run(twin(), 20_000, Vec::new(), (0, 0));
    let mut t = twin();
    for node in &mut t.nodes {
        node.dropout_probability = 0.01;
    }
    let (lossy, lp, _) = run(t, 20_000, Vec::new(), (0, 0));
    assert_never_invalid_data_as_valid(&lossy);
    assert!(lp.acquisition_stats().incomplete_cycles > 300, "the loss did not happen");
    assert!(
        lossy.iter().all(|s| !s.health().intersects(HealthFlags::DETECTOR_RESET)),
        "a short gap reset the detector"
    );
    // The same insertions and extractions as the loss-free run, each within a few cycles of
    // it (a lost line near a decision moves the decision by a sample or two).
    let transitions = |v: &[FulcrumSample]| {
        let mut last = OutputState::Outside;
        let mut out = Vec::new();
        for (i, s) in v.iter().enumerate() {
            let state = s.state().expect("a known state");
            if state.is_valid() {
                if state != last {
                    out.push((i, state));
                }
                last = state;
            }
        }
        out
    };
    let (a, b) = (transitions(&clean), transitions(&lossy));
    assert!(a.len() >= 2, "the clean run should insert and extract: {a:?}");
    assert_eq!(a.len(), b.len(), "clean {a:?} lossy {b:?}");
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.1, y.1);
        assert!(x.0.abs_diff(y.0) <= 10, "a decision moved from cycle {} to {}", x.0, y.0);
    }
}

#[test]
fn an_emcy_burst_invalidates_until_cleared() {
    let mut t = twin();
    t.nodes[2].emcy = (0..5)
        .map(|k| EmcyInjection {
            at_us: 2_000_000 + k * 10_000,
            duration_us: 5_000,
            code: 0x7305,
            register: 1,
            vendor: [0; 5],
        })
        .collect();
    let (samples, lp, _) = run(t, 4_000, Vec::new(), (0, 0));
    assert_never_invalid_data_as_valid(&samples);
    let flagged = samples.iter().filter(|s| s.health().intersects(HealthFlags::NODE_EMCY[2])).count();
    assert!((20..=35).contains(&flagged), "{flagged} cycles flagged");
    assert!(samples[2_100..].iter().all(|s| s.is_valid()));
    assert_eq!(lp.acquisition_stats().emcy_frames, 10);
}

#[test]
fn a_flood_of_malformed_frames_is_counted_and_changes_nothing() {
    let junk = vec![
        CanFrame::new_standard(0x181, &[1, 2, 3]).unwrap(), // TPDO of node 1 with a wrong DLC
        CanFrame::new_standard(0x7FF, &[0; 8]).unwrap(),    // unknown COB-ID
        CanFrame::new_extended(0x181, &[0; 8]).unwrap(),    // extended ID
        CanFrame::new_standard(0x701, &[0x42]).unwrap(),    // unknown NMT state
    ];
    let (clean, _, _) = run(twin(), 3_000, Vec::new(), (0, 0));
    let (flooded, lp, n_alloc) = run(twin(), 3_000, junk, (500, 2_500));
    assert_eq!(n_alloc, 0);
    let s = lp.acquisition_stats();
    assert_eq!(s.wrong_dlc_frames, 2_000);
    assert_eq!(s.unknown_id_frames, 4_000);
    assert_eq!(s.malformed_frames, 2_000);
    // Junk arrives after the TPDOs: the estimates are those of the clean run.
    assert!(clean.iter().zip(&flooded).all(|(a, b)| a.state == b.state && a.fulcrum_base_m == b.fulcrum_base_m));
}

/// With `cut_by_bus_time`, the loop cuts the bus into cycles by the frames' bus timestamps
/// (window after its SYNC's echo), not by when it reads them: here every frame is readable at
/// once, and node 3 answers 700 µs after the SYNC, past a 500 µs window, so its TPDO is late in
/// every cycle although the loop reads it in time. The candump replay of the same bus applies
/// the same rule: its cycles' inputs equal the loop's, cycle by cycle. Also when the echo of
/// the SYNC reaches the loop after the answers.
#[test]
fn cutting_by_bus_time_matches_the_candump_replay() {
    for (node3_latency_us, echo_last) in [(400, false), (700, false), (400, true), (700, true)] {
        let cycles = 600u64;
        let mut t = twin();
        t.nodes[2].latency_us = node3_latency_us;
        let mut robot = SimRobot::new(&t).unwrap();
        let mut sync = hw_io::can::SyncSource::new();
        let answers = (0..cycles)
            .map(|k| robot.on_sync(sync.next_counter(), k * 1000).unwrap().map(|f| f.to_vec()).unwrap_or_default())
            .collect();
        let bus = ScriptedBus {
            answers,
            queue: VecDeque::with_capacity(1024),
            syncs: 0,
            junk: Vec::new(),
            junk_window: (0, 0),
            echo: true,
            echo_last,
            log: Vec::with_capacity(8 * cycles as usize),
        };
        let mut cfg = config();
        cfg.cycle.frame_deadline_us = 500;
        let acq = Acquisition::new(&cfg.bus.encoder, cfg.health).unwrap();
        let est = Estimation::new(&cfg.bus.encoder, &cfg.kinematics, &cfg.detector).unwrap();
        let params = LoopParams {
            period_ns: 20_000,
            frame_deadline_ns: 500_000,
            run_id: 7,
            max_cycles: Some(cycles),
            cut_by_bus_time: true,
        };
        let mut lp = RtLoop::new(bus, acq, est, params, Arc::new(LoopCounters::default()), LoopProgress::new());
        let mut sink = Records { records: Vec::with_capacity(cycles as usize) };
        let before = allocs();
        lp.run(&mut sink, || false).unwrap();
        assert_eq!(allocs() - before, 0, "the loop allocated");
        let stats = *lp.acquisition_stats();
        let late = node3_latency_us > 500;
        if late {
            // Every node-3 TPDO is late (the last one was never read: the loop stopped).
            assert_eq!(stats.late_tpdos, cycles - 1, "{stats:?}");
            assert_eq!(stats.incomplete_cycles, cycles);
            assert!(sink.records.iter().all(|r| r.input.received_mask == 0b011));
        } else {
            assert_eq!((stats.late_tpdos, stats.incomplete_cycles), (0, 0), "{stats:?}");
        }
        // The same bus as a candump log, through `replay --candump`.
        let mut text = Vec::new();
        let mut w = hw_io::can::candump::CandumpWriter::new(&mut text, "vcan0").unwrap();
        for f in &lp_bus_log(&lp) {
            w.write(f).unwrap();
        }
        w.flush().unwrap();
        drop(w);
        let replayed = controller::replay::replay_candump_reader(&text[..], &cfg).unwrap();
        assert_eq!(replayed.cycles.len(), sink.records.len());
        let c = controller::replay::compare_with_recording(&replayed, &sink.records, &cfg).unwrap();
        assert_eq!(c.offset, Some(0), "{c:?}");
        assert_eq!((c.compared, c.identical_inputs, c.identical_outputs), (cycles, cycles, cycles), "{c:?}");
    }
}

fn lp_bus_log(lp: &RtLoop<ScriptedBus>) -> Vec<TimedFrame> {
    lp.bus().log.clone()
}

struct Records {
    records: Vec<CycleRecord>,
}

impl CycleSink for Records {
    fn publish(&mut self, _: &FulcrumSample) -> bool {
        true
    }
    fn record(&mut self, record: &CycleRecord) -> bool {
        self.records.push(*record);
        true
    }
    fn log(&mut self, _: LogEvent) -> bool {
        true
    }
}

/// Frames the bus dropped (its receive queue full) reach the loop's counters, which the
/// daemon's main thread reports every 10 s while running, and the summary at exit.
#[test]
fn frames_the_bus_dropped_are_in_the_loop_counters() {
    let bus = hw_io::can::InProcessBus::with_capacity(2, 16);
    let controller = bus.endpoint().unwrap();
    let mut flood = bus.endpoint().unwrap();
    // 100 frames at a 16-frame queue nobody reads yet: 84 dropped.
    for k in 0..100u8 {
        flood.send(&CanFrame::new_standard(0x7FF, &[k]).unwrap()).unwrap();
    }
    let cfg = Config::default();
    let acq = Acquisition::new(&cfg.bus.encoder, cfg.health).unwrap();
    let est = Estimation::new(&cfg.bus.encoder, &cfg.kinematics, &cfg.detector).unwrap();
    let params = LoopParams {
        period_ns: 200_000,
        frame_deadline_ns: 50_000,
        run_id: 1,
        max_cycles: Some(3),
        cut_by_bus_time: false,
    };
    let counters = Arc::new(LoopCounters::default());
    let mut lp = RtLoop::new(controller, acq, est, params, counters.clone(), LoopProgress::new());
    lp.run(&mut Collect::default(), || false).unwrap();
    assert_eq!(lp.bus_dropped_rx_frames(), 84);
    assert_eq!(counters.bus_dropped_rx_frames.load(std::sync::atomic::Ordering::Relaxed), 84);
    // The 16 that fit were read (and counted as unknown-ID frames), not lost.
    assert_eq!(lp.acquisition_stats().unknown_id_frames, 16);
}
