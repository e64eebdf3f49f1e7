//! A bus that plays back a candump log, for replaying recorded runs.
//!
//! The whole log is read when the bus is built; after that `recv_timeout` allocates
//! nothing. Frames come back with their recorded timestamps, either as fast as they are
//! asked for ([`Pacing::AsFastAsPossible`], deterministic) or at the recorded intervals
//! ([`Pacing::RealTime`]). Sent frames go nowhere; they are counted.
//!
//! ```
//! use std::time::Duration;
//! use hw_io::can::{CanBus, Pacing, RecvError, ReplayBus};
//! let log = "(1.000000) can0 080#01\n(1.001000) can0 181#0100000002000000\n";
//! let mut bus = ReplayBus::from_reader(log.as_bytes(), Pacing::AsFastAsPossible).unwrap();
//! assert_eq!(bus.recv_timeout(Duration::ZERO).unwrap().unwrap().unix_time_us, 1_000_000);
//! assert_eq!(bus.recv_timeout(Duration::ZERO).unwrap().unwrap().frame.dlc(), 8);
//! assert!(matches!(bus.recv_timeout(Duration::ZERO), Err(RecvError::EndOfReplay)));
//! ```

use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use super::bus::{CanBus, RecvError, SendError};
use super::candump::{CandumpReadError, CandumpReader, LineError};
use super::frame::{CanFrame, TimedFrame};

/// How fast a [`ReplayBus`] hands out frames.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pacing {
    /// Every frame is available at once: deterministic, for tests and offline analysis.
    AsFastAsPossible,
    /// Each frame becomes available at its recorded offset from the first frame, measured
    /// from the first `recv_timeout` call.
    RealTime,
}

/// Why a log file could not be opened for replay.
#[derive(Debug, thiserror::Error)]
pub enum ReplayOpenError {
    /// The file could not be opened.
    #[error("cannot open candump log {path:?}: {source}")]
    Open {
        /// The file.
        path: PathBuf,
        /// The operating-system error.
        #[source]
        source: std::io::Error,
    },
    /// The file is not a valid candump log.
    #[error("candump log {path:?}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// What is wrong, with the line number.
        #[source]
        source: CandumpReadError,
    },
}

/// A [`CanBus`] that replays frames from a candump log.
#[derive(Debug)]
pub struct ReplayBus {
    frames: Vec<TimedFrame>,
    next: usize,
    pacing: Pacing,
    started: Option<Instant>,
    sent: u64,
    skipped_lines: u64,
}

impl ReplayBus {
    /// Read a candump log file. CAN FD and error-frame lines are skipped and counted
    /// ([`ReplayBus::skipped_lines`]); any other malformed line is an error.
    pub fn open(path: impl AsRef<Path>, pacing: Pacing) -> Result<Self, ReplayOpenError> {
        let path = path.as_ref();
        let file =
            std::fs::File::open(path).map_err(|source| ReplayOpenError::Open { path: path.to_owned(), source })?;
        Self::from_reader(std::io::BufReader::new(file), pacing)
            .map_err(|source| ReplayOpenError::Read { path: path.to_owned(), source })
    }

    /// Read a candump log from any reader; same rules as [`ReplayBus::open`].
    pub fn from_reader(reader: impl BufRead, pacing: Pacing) -> Result<Self, CandumpReadError> {
        let mut reader = CandumpReader::new(reader);
        let mut frames = Vec::new();
        let mut skipped_lines = 0;
        loop {
            match reader.next_record() {
                Ok(Some(rec)) => frames.push(rec.timed),
                Ok(None) => break,
                Err(CandumpReadError::Malformed { kind: LineError::CanFd | LineError::ErrorFrame { .. }, .. }) => {
                    skipped_lines += 1
                }
                Err(e) => return Err(e),
            }
        }
        let mut bus = Self::from_frames(frames, pacing);
        bus.skipped_lines = skipped_lines;
        Ok(bus)
    }

    /// Replay frames given directly, in order.
    pub fn from_frames(frames: Vec<TimedFrame>, pacing: Pacing) -> Self {
        Self { frames, next: 0, pacing, started: None, sent: 0, skipped_lines: 0 }
    }

    /// Frames not yet handed out.
    pub fn remaining(&self) -> usize {
        self.frames.len() - self.next
    }

    /// Frames passed to `send` (they are not replayed or stored).
    pub fn sent_frames(&self) -> u64 {
        self.sent
    }

    /// Log lines skipped because they hold CAN FD or error frames.
    pub fn skipped_lines(&self) -> u64 {
        self.skipped_lines
    }

    /// Start over from the first frame.
    pub fn rewind(&mut self) {
        self.next = 0;
        self.started = None;
    }

    /// When frame `index` is due, as an offset from the first recv, for real-time pacing.
    fn due_offset(&self, index: usize) -> Duration {
        let first = self.frames.first().map_or(0, |f| f.unix_time_us);
        let t = self.frames.get(index).map_or(first, |f| f.unix_time_us);
        Duration::from_micros(t.saturating_sub(first))
    }
}

impl CanBus for ReplayBus {
    fn send(&mut self, _frame: &CanFrame) -> Result<(), SendError> {
        self.sent += 1;
        Ok(())
    }

    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<TimedFrame>, RecvError> {
        let Some(&frame) = self.frames.get(self.next) else {
            return Err(RecvError::EndOfReplay);
        };
        if self.pacing == Pacing::RealTime {
            let now = Instant::now();
            let started = *self.started.get_or_insert(now);
            let due = started.checked_add(self.due_offset(self.next)).unwrap_or(now);
            if due > now {
                let wait = due - now;
                if wait > timeout {
                    std::thread::sleep(timeout);
                    return Ok(None);
                }
                std::thread::sleep(wait);
            }
        }
        self.next += 1;
        Ok(Some(frame))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LOG: &str = "(10.000000) can0 080#01\n\
                       (10.000000) can0 123##1AA\n\
                       (10.030000) can0 080#02\n\
                       (10.060000) can0 20000004#0000000000000000\n\
                       (10.060000) can0 080#03\n";

    #[test]
    fn as_fast_as_possible_replays_in_order_and_skips_unsupported() {
        let mut bus = ReplayBus::from_reader(LOG.as_bytes(), Pacing::AsFastAsPossible).unwrap();
        assert_eq!(bus.skipped_lines(), 2);
        assert_eq!(bus.remaining(), 3);
        bus.send(&CanFrame::new_standard(0x80, &[9]).unwrap()).unwrap();
        assert_eq!(bus.sent_frames(), 1);
        let counters: Vec<u8> =
            (0..3).map(|_| bus.recv_timeout(Duration::ZERO).unwrap().unwrap().frame.data()[0]).collect();
        assert_eq!(counters, [1, 2, 3]);
        assert!(matches!(bus.recv_timeout(Duration::ZERO), Err(RecvError::EndOfReplay)));
        bus.rewind();
        assert_eq!(bus.remaining(), 3);
    }

    #[test]
    fn real_time_pacing_waits_for_recorded_offsets() {
        let mut bus = ReplayBus::from_reader(LOG.as_bytes(), Pacing::RealTime).unwrap();
        let t0 = Instant::now();
        assert!(bus.recv_timeout(Duration::ZERO).unwrap().is_some());
        // Frame 2 is due 30 ms after frame 1: a 5 ms wait times out.
        assert!(bus.recv_timeout(Duration::from_millis(5)).unwrap().is_none());
        let f = bus.recv_timeout(Duration::from_secs(1)).unwrap().unwrap();
        assert_eq!(f.unix_time_us, 10_030_000);
        assert!(t0.elapsed() >= Duration::from_millis(30));
        let f = bus.recv_timeout(Duration::from_secs(1)).unwrap().unwrap();
        assert_eq!(f.frame.data(), &[3]);
        assert!(t0.elapsed() >= Duration::from_millis(60));
    }

    #[test]
    fn malformed_log_is_refused_with_line_number() {
        let err =
            ReplayBus::from_reader("(1.0) can0 080#01\n(1.1) can0 080#0\n".as_bytes(), Pacing::RealTime).unwrap_err();
        assert_eq!(err.line(), Some(2));
        let err = ReplayBus::open("/nonexistent/comanip.log", Pacing::RealTime).unwrap_err();
        assert!(matches!(err, ReplayOpenError::Open { .. }));
    }
}
