//! How a received message follows the previous one, from its `(run_id, sequence)`: the same
//! rules for every [`Message`](super::Message) (`docs/output.md`, "Continuity and restarts").

/// How a received message follows the previous one (see `docs/output.md`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Continuity {
    /// The first message this subscriber receives: nothing to compare with.
    First,
    /// Same publisher run, `sequence` is the previous one plus 1.
    InOrder,
    /// Same publisher run, `sequence` jumped forward: `missed` messages were lost (this
    /// subscriber's buffer overflowed because it read too slowly, or it was not reading).
    Gap {
        /// Messages between the previous one and this one that never arrived.
        missed: u64,
    },
    /// The publisher restarted: a new `run_id`, or the sequence went back within the same
    /// `run_id`. Not an error: estimates start afresh (the detector refills its window).
    Restart,
}

/// Continuity of `(run_id, sequence)` pairs.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct ContinuityTracker {
    last: Option<(u64, u64)>,
}

impl ContinuityTracker {
    /// How `(run_id, sequence)` follows the previous pair observed; remembers it.
    pub(crate) fn observe(&mut self, run_id: u64, sequence: u64) -> Continuity {
        let event = match self.last {
            None => Continuity::First,
            Some((last_run, _)) if last_run != run_id => Continuity::Restart,
            Some((_, last_seq)) if sequence <= last_seq => Continuity::Restart,
            Some((_, last_seq)) if sequence == last_seq + 1 => Continuity::InOrder,
            Some((_, last_seq)) => Continuity::Gap { missed: sequence - last_seq - 1 },
        };
        self.last = Some((run_id, sequence));
        event
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn continuity_of_run_and_sequence() {
        let mut t = ContinuityTracker::default();
        assert_eq!(t.observe(7, 100), Continuity::First);
        assert_eq!(t.observe(7, 101), Continuity::InOrder);
        assert_eq!(t.observe(7, 105), Continuity::Gap { missed: 3 });
        assert_eq!(t.observe(7, 106), Continuity::InOrder);
        // A new run, even with a larger sequence.
        assert_eq!(t.observe(8, 107), Continuity::Restart);
        // The sequence goes back (or repeats) within one run_id: a restart too.
        assert_eq!(t.observe(8, 3), Continuity::Restart);
        assert_eq!(t.observe(8, 3), Continuity::Restart);
        assert_eq!(t.observe(8, 4), Continuity::InOrder);
        assert_eq!(t.observe(8, u64::MAX), Continuity::Gap { missed: u64::MAX - 5 });
    }
}
