//! The SYNC counter rule: 1, 2, ..., 240, 1, ... (CiA 301 synchronous counter, overflow 240).
//!
//! [`SyncSource`] produces the counters the controller sends, one per 1 ms cycle;
//! [`SyncCounter`] checks the counters a listener sees and reports every gap.
//!
//! ```
//! use hw_io::can::{CounterError, SyncCounter, SyncSource};
//! let mut source = SyncSource::new();
//! let mut tracker = SyncCounter::new();
//! assert_eq!(tracker.observe(source.next_counter()), Ok(()));   // 1
//! let _lost = source.next_counter();                             // 2 never arrives
//! assert_eq!(
//!     tracker.observe(source.next_counter()),                    // 3
//!     Err(CounterError::Gap { expected: 2, got: 3 })
//! );
//! assert_eq!(tracker.observe(source.next_counter()), Ok(()));   // 4: back in step
//! ```

use super::frame::CanFrame;
use super::protocol::{Message, SYNC_COUNTER_MAX};

/// The counter that follows `counter` (240 wraps to 1). Values outside 1..=240 give 1.
pub const fn next_sync_counter(counter: u8) -> u8 {
    if counter >= 1 && counter < SYNC_COUNTER_MAX { counter + 1 } else { 1 }
}

/// Generates the SYNC counters of the controller: 1, 2, ..., 240, 1, ...
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SyncSource {
    last: u8,
}

impl SyncSource {
    /// A source whose first counter is 1.
    pub const fn new() -> Self {
        Self { last: 0 }
    }

    /// The next counter, 1..=240.
    ///
    /// **Real-time (1 kHz loop):** allocation-free.
    pub fn next_counter(&mut self) -> u8 {
        self.last = next_sync_counter(self.last);
        self.last
    }

    /// The next SYNC frame (COB-ID 0x080, DLC 1). Allocation-free.
    ///
    /// **Real-time (1 kHz loop):** called once a cycle, before the SYNC is sent.
    pub fn next_frame(&mut self) -> CanFrame {
        let counter = self.next_counter();
        let mut data = [0u8; 8];
        data[0] = counter;
        CanFrame::standard_masked(super::protocol::SYNC_COB_ID, 1, data)
    }

    /// The next SYNC as a [`Message`].
    ///
    /// **Real-time (1 kHz loop):** allocation-free.
    pub fn next_message(&mut self) -> Message {
        Message::Sync { counter: self.next_counter() }
    }
}

/// A SYNC counter that does not follow the previous one.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum CounterError {
    /// A counter outside 1..=240.
    #[error("SYNC counter {got} outside 1..=240")]
    OutOfRange {
        /// The counter seen.
        got: u8,
    },
    /// The counter is not the successor of the previous one: SYNCs were lost, repeated or
    /// reordered. The tracker re-synchronises on `got`.
    #[error("SYNC counter gap: expected {expected}, got {got}")]
    Gap {
        /// The counter that should have come, 1..=240.
        expected: u8,
        /// The counter seen, 1..=240.
        got: u8,
    },
}

impl CounterError {
    /// For a [`CounterError::Gap`]: how many SYNCs were skipped, assuming they were lost
    /// (0..=239; 239 for a repeated counter). `None` for an out-of-range counter.
    pub fn skipped(&self) -> Option<u8> {
        match *self {
            CounterError::OutOfRange { .. } => None,
            CounterError::Gap { expected, got } => {
                let n = u16::from(SYNC_COUNTER_MAX);
                let skipped = (u16::from(got) + n - u16::from(expected)) % n;
                Some(skipped as u8)
            }
        }
    }
}

/// Tracks the SYNC counters seen on the bus and reports gaps.
///
/// The first counter seen (after [`SyncCounter::new`] or [`SyncCounter::reset`]) is
/// accepted whatever it is; each later one must be the successor of the previous one.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SyncCounter {
    last: Option<u8>,
}

impl SyncCounter {
    /// A tracker that has seen nothing yet.
    pub const fn new() -> Self {
        Self { last: None }
    }

    /// Forget the previous counter (e.g. after the bus was restarted).
    pub fn reset(&mut self) {
        self.last = None;
    }

    /// The last valid counter seen, if any.
    pub const fn last(&self) -> Option<u8> {
        self.last
    }

    /// The counter expected next, if one was seen.
    pub fn expected(&self) -> Option<u8> {
        self.last.map(next_sync_counter)
    }

    /// Check one counter. On a gap, the tracker re-synchronises on `got`, so one lost SYNC
    /// gives exactly one error. An out-of-range counter leaves the tracker unchanged.
    ///
    /// **Real-time (1 kHz loop):** called for every SYNC seen; allocation-free.
    pub fn observe(&mut self, got: u8) -> Result<(), CounterError> {
        if !(1..=SYNC_COUNTER_MAX).contains(&got) {
            return Err(CounterError::OutOfRange { got });
        }
        let expected = self.expected();
        self.last = Some(got);
        match expected {
            Some(expected) if expected != got => Err(CounterError::Gap { expected, got }),
            _ => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn source_wraps_from_240_to_1() {
        let mut s = SyncSource::new();
        let seq: Vec<u8> = (0..481).map(|_| s.next_counter()).collect();
        assert_eq!(seq[0], 1);
        assert_eq!(seq[239], 240);
        assert_eq!(seq[240], 1);
        assert_eq!(seq[480], 1);
        assert!(seq.iter().all(|c| (1..=240).contains(c)));
    }

    #[test]
    fn source_frames_decode_as_sync() {
        let mut s = SyncSource::new();
        for expected in 1..=240u8 {
            assert_eq!(Message::decode(&s.next_frame()), Ok(Message::Sync { counter: expected }));
        }
        assert_eq!(s.next_message(), Message::Sync { counter: 1 });
    }

    #[test]
    fn tracker_accepts_a_full_wrap_and_reports_gaps() {
        let mut s = SyncSource::new();
        let mut t = SyncCounter::new();
        for _ in 0..1000 {
            assert_eq!(t.observe(s.next_counter()), Ok(()));
        }
        // Lose 3 SYNCs across the wrap.
        let mut t = SyncCounter::new();
        t.observe(239).unwrap();
        let err = t.observe(3).unwrap_err();
        assert_eq!(err, CounterError::Gap { expected: 240, got: 3 });
        assert_eq!(err.skipped(), Some(3));
        assert_eq!(t.observe(4), Ok(()));
        // Repeated counter.
        assert_eq!(t.observe(4), Err(CounterError::Gap { expected: 5, got: 4 }));
        assert_eq!(t.observe(4).unwrap_err().skipped(), Some(239));
    }

    #[test]
    fn tracker_refuses_out_of_range_without_losing_step() {
        let mut t = SyncCounter::new();
        t.observe(10).unwrap();
        assert_eq!(t.observe(0), Err(CounterError::OutOfRange { got: 0 }));
        assert_eq!(t.observe(241), Err(CounterError::OutOfRange { got: 241 }));
        assert_eq!(t.observe(11), Ok(()));
        t.reset();
        assert_eq!(t.observe(200), Ok(()));
    }

    #[test]
    fn next_counter_of_garbage_restarts_at_1() {
        assert_eq!(next_sync_counter(0), 1);
        assert_eq!(next_sync_counter(240), 1);
        assert_eq!(next_sync_counter(255), 1);
        assert_eq!(next_sync_counter(7), 8);
    }
}
