//! The built-in simulated robot: a thread answering the loop's SYNC on the in-process bus
//! with the simulator's twin ([`sim::twin::SimRobot`], endless scenarios), so that
//! `fulcrumd` with no CAN interface shows detections as a simulated surgeon moves.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, Sender, channel};
use std::thread::JoinHandle;
use std::time::Duration;

use hw_io::can::{CanBus, InProcessEndpoint, Message, unix_time_now_us};
use sim::twin::{SimRobot, TwinConfig, TwinConfigError};

use crate::config::Config;

/// The running simulated robot.
pub struct SimRobotThread {
    thread: JoinHandle<()>,
    truth: Receiver<String>,
    answered: Arc<AtomicU64>,
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
            let _ = crate::rt::apply_to_current_thread(&rt);
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
    Ok(SimRobotThread { thread, truth: rx, answered })
}

impl SimRobotThread {
    /// Hands every pending truth line to `f`.
    pub fn drain_truth(&self, mut f: impl FnMut(&str)) {
        while let Ok(line) = self.truth.try_recv() {
            f(&line);
        }
    }

    /// Waits for the thread to end (set the stop flag first); returns the SYNCs answered.
    pub fn join(self) -> u64 {
        let _ = self.thread.join();
        self.answered.load(Ordering::Relaxed)
    }
}
