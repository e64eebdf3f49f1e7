//! The built-in simulated robot: a thread answering the loop's SYNC on the in-process bus
//! with the simulator's twin ([`sim::twin::SimRobot`], endless scenarios), so that
//! `fulcrumd` with no CAN interface shows detections as a simulated surgeon moves.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, Sender, channel};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use hw_io::can::{CanBus, InProcessEndpoint, Message, unix_time_now_us};
use nalgebra::Vector3;
use sim::scenario::TruthState;
use sim::twin::{SimRobot, TwinConfig, TwinConfigError};

use crate::config::Config;

/// Samples of ground truth kept for the log (16 s at 1 kHz).
const TRUTH_SAMPLES: usize = 16_384;

/// The ground truth of one answered SYNC: sample index (= the loop's cycle number), true
/// state, true pivot (metres, robot base frame) while inside.
type TruthSample = (u64, TruthState, Option<Vector3<f64>>);

/// The running simulated robot.
pub struct SimRobotThread {
    thread: JoinHandle<()>,
    truth: Receiver<String>,
    answered: Arc<AtomicU64>,
    recent: Arc<Mutex<VecDeque<TruthSample>>>,
    /// What real-time set-up the thread got (one line for the log).
    pub priority_note: String,
}

/// Why the simulated robot could not start.
#[derive(Debug, thiserror::Error)]
pub enum SimStartError {
    /// The twin's configuration is invalid.
    #[error(transparent)]
    Config(#[from] TwinConfigError),
    /// The thread could not be spawned.
    #[error("cannot spawn the simulated robot thread: {0}")]
    Spawn(std::io::Error),
}

/// The twin the daemon simulates: the default surgeon (seeded), endless, on the controller's
/// own nominal kinematics and encoder configuration. The twin advances one 1 ms sample per
/// SYNC: with a loop period other than 1 ms the simulated surgeon moves faster or slower.
pub fn twin_config(cfg: &Config, seed: u64) -> TwinConfig {
    let mut t = TwinConfig::default();
    t.scenario.seed = seed;
    t.kinematics = cfg.kinematics;
    t.encoder = cfg.bus.encoder;
    t.endless = true;
    t
}

/// Starts the simulated robot on `endpoint`; it stops when `stop` is set.
pub fn spawn(
    mut endpoint: InProcessEndpoint,
    cfg: &Config,
    seed: u64,
    stop: &'static AtomicBool,
    period_s: f64,
) -> Result<SimRobotThread, SimStartError> {
    let mut robot = SimRobot::new(&twin_config(cfg, seed))?;
    let sim_priority = cfg.realtime.sched_fifo_priority.saturating_sub(1);
    let (tx, rx): (Sender<String>, Receiver<String>) = channel();
    let answered = Arc::new(AtomicU64::new(0));
    let count = answered.clone();
    let recent = Arc::new(Mutex::new(VecDeque::with_capacity(TRUTH_SAMPLES)));
    let recent_sim = recent.clone();
    let (note_tx, note_rx) = channel::<String>();
    let thread = std::thread::Builder::new()
        .name("fulcrumd-sim".into())
        .spawn(move || {
            // The simulated robot plays hardware: give it real-time priority just below the
            // loop's when permitted (quietly without), so that it answers in time.
            let rt = crate::rt::RealtimeConfig {
                sched_fifo_priority: sim_priority,
                cpu_affinity: Vec::new(),
                lock_memory: false,
                prefault_stack_bytes: 0,
                require: false,
            };
            use crate::rt::StepOutcome;
            let note = match crate::rt::apply_to_current_thread(&rt).map(|r| r.sched_fifo) {
                Ok(StepOutcome::Applied) => format!("SCHED_FIFO priority {sim_priority}, just below the loop's"),
                Ok(StepOutcome::Skipped) => "normal priority (the loop's real-time priority is off)".to_string(),
                Ok(StepOutcome::Refused { .. }) => {
                    "normal priority (real-time priority refused: see the warning)".into()
                }
                Err(e) => format!("normal priority ({e})"),
            };
            let _ = note_tx.send(note);
            let mut last_error_sample = u64::MAX;
            while !stop.load(Ordering::Relaxed) {
                let rx = match endpoint.recv_timeout(Duration::from_millis(100)) {
                    Ok(Some(f)) => f,
                    Ok(None) => continue,
                    Err(_) => break,
                };
                let Ok(Message::Sync { counter }) = Message::decode(&rx.frame) else { continue };
                match robot.on_sync(counter, unix_time_now_us()) {
                    Ok(Some(frames)) => {
                        for f in frames.iter() {
                            let _ = endpoint.send(&f.frame);
                        }
                        count.fetch_add(1, Ordering::Relaxed);
                        if let (Some(k), Ok(mut q)) = (robot.sample(), recent_sim.lock()) {
                            if q.len() == TRUTH_SAMPLES {
                                q.pop_front();
                            }
                            let t = robot.truth();
                            q.push_back((k, t.state, t.fulcrum_base_m));
                        }
                        for e in robot.events() {
                            let t = e.sample as f64 * period_s;
                            let what = if e.insertion { "inserted into" } else { "extracted from" };
                            let _ = tx.send(format!("{t:9.3} s  truth    {what} trocar {}", e.trocar));
                        }
                    }
                    Ok(None) => {}
                    Err(e) => {
                        let s = robot.samples_done();
                        if s != last_error_sample {
                            let _ = tx.send(format!("simulated robot: {e}"));
                            last_error_sample = s;
                        }
                    }
                }
            }
        })
        .map_err(SimStartError::Spawn)?;
    let priority_note = note_rx.recv_timeout(Duration::from_secs(2)).unwrap_or_else(|_| "priority unknown".into());
    Ok(SimRobotThread { thread, truth: rx, answered, recent, priority_note })
}

impl SimRobotThread {
    /// Hands every pending truth line to `f`.
    pub fn drain_truth(&self, mut f: impl FnMut(&str)) {
        while let Ok(line) = self.truth.try_recv() {
            f(&line);
        }
    }

    /// The ground truth at the loop's cycle `sequence` (the twin answers one sample per
    /// SYNC, so sample k is cycle k), when it is still among the last 16 s.
    pub fn truth_at(&self, sequence: u64) -> Option<(TruthState, Option<Vector3<f64>>)> {
        let q = self.recent.lock().ok()?;
        let first = q.front()?.0;
        let i = usize::try_from(sequence.checked_sub(first)?).ok()?;
        q.get(i).filter(|s| s.0 == sequence).map(|s| (s.1, s.2))
    }

    /// Waits for the thread to end (set the stop flag first); returns the SYNCs answered.
    pub fn join(self) -> u64 {
        let _ = self.thread.join();
        self.answered.load(Ordering::Relaxed)
    }
}
