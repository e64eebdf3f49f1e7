//! Health conditions for people: a line per *lasting* condition, short flaps counted.
//!
//! The loop reports every change of the lasting health flags (a node stale, in EMCY, without
//! heartbeat, ...: `LogEvent::Health`). On a loaded machine a node can go stale for a few
//! milliseconds several times a minute; a line per flap buries what matters. [`HealthLog`]
//! turns the changes into:
//! - one line when a condition has lasted [`LASTING_S`] (with the instant it began), and one
//!   when it clears (with its duration);
//! - a summary of the shorter ones every 10 s (`flaps`), with their counts per condition.
//!
//! Times are seconds of loop time (cycle number × period). Every change is still in the
//! flight recording and the published samples: this is only what is printed.

use std::collections::BTreeMap;

use hw_io::ipc::HealthFlags;

/// A condition that lasts this long gets its own lines, seconds.
pub const LASTING_S: f64 = 0.1;

/// Flags that can be set at once (the bits of [`HealthFlags`], unknown ones included).
const BITS: usize = 32;

/// The aggregator. Not for the real-time loop (it formats strings): the daemon's supervisor
/// thread feeds it.
#[derive(Debug, Default)]
pub struct HealthLog {
    active: HealthFlags,
    since_s: [f64; BITS],
    announced: HealthFlags,
    flaps: BTreeMap<String, u64>,
}

/// A line to print.
#[derive(Debug, Clone, PartialEq)]
pub enum HealthLine {
    /// A condition has lasted [`LASTING_S`]: its name and when it began, seconds.
    Began {
        /// Flag name.
        name: String,
        /// Start, seconds of loop time.
        since_s: f64,
    },
    /// A lasting condition cleared: its name, when, and how long it lasted, seconds.
    Cleared {
        /// Flag name.
        name: String,
        /// End, seconds of loop time.
        at_s: f64,
        /// Duration, seconds.
        lasted_s: f64,
    },
}

impl std::fmt::Display for HealthLine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            HealthLine::Began { name, since_s } => write!(f, "{since_s:9.3} s  health {name} (lasting)"),
            HealthLine::Cleared { name, at_s, lasted_s } => {
                write!(f, "{at_s:9.3} s  health {name} cleared after {lasted_s:.3} s")
            }
        }
    }
}

impl HealthLog {
    /// A log with no condition active.
    pub fn new() -> Self {
        Self::default()
    }

    /// The lasting flags changed to `new` at `t_s` (seconds of loop time). Returns the lines
    /// of lasting conditions that cleared.
    pub fn change(&mut self, t_s: f64, new: HealthFlags) -> Vec<HealthLine> {
        let mut out = Vec::new();
        for b in 0..BITS {
            let bit = HealthFlags::from_bits_retain(1 << b);
            let (was, is) = (self.active.contains(bit), new.contains(bit));
            if is && !was {
                self.since_s[b] = t_s;
            } else if was && !is {
                let name = bit.to_string();
                if self.announced.contains(bit) {
                    out.push(HealthLine::Cleared { name, at_s: t_s, lasted_s: t_s - self.since_s[b] });
                    self.announced.remove(bit);
                } else {
                    *self.flaps.entry(name).or_insert(0) += 1;
                }
            }
        }
        self.active = new;
        out
    }

    /// Time has reached `now_s` (seconds of loop time): the lines of conditions that have now
    /// lasted [`LASTING_S`].
    pub fn tick(&mut self, now_s: f64) -> Vec<HealthLine> {
        let mut out = Vec::new();
        for b in 0..BITS {
            let bit = HealthFlags::from_bits_retain(1 << b);
            if self.active.contains(bit) && !self.announced.contains(bit) && now_s - self.since_s[b] >= LASTING_S {
                self.announced.insert(bit);
                out.push(HealthLine::Began { name: bit.to_string(), since_s: self.since_s[b] });
            }
        }
        out
    }

    /// The short conditions since the last call, as one line (`None` when there were none),
    /// e.g. "short health conditions: node2-stale ×3".
    pub fn flaps(&mut self) -> Option<String> {
        if self.flaps.is_empty() {
            return None;
        }
        let parts: Vec<String> = self.flaps.iter().map(|(n, c)| format!("{n} ×{c}")).collect();
        self.flaps.clear();
        Some(format!("short health conditions (under {LASTING_S} s each): {}", parts.join(", ")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hw_io::ipc::HealthFlags as h;

    #[test]
    fn short_flaps_are_counted_not_printed() {
        let mut log = HealthLog::new();
        let mut lines = Vec::new();
        for k in 0..7 {
            let t = k as f64 * 1.3;
            lines.extend(log.change(t, h::NODE_STALE[1]));
            lines.extend(log.tick(t + 0.01));
            lines.extend(log.change(t + 0.02, h::empty()));
            lines.extend(log.tick(t + 0.9));
        }
        assert!(lines.is_empty(), "{lines:?}");
        assert_eq!(log.flaps().as_deref(), Some("short health conditions (under 0.1 s each): node2-stale ×7"));
        assert_eq!(log.flaps(), None, "the counts start again");
    }

    #[test]
    fn a_lasting_condition_gets_a_start_and_an_end_line() {
        let mut log = HealthLog::new();
        assert!(log.change(10.0, h::NODE_EMCY[0]).is_empty());
        assert!(log.tick(10.05).is_empty());
        let began = log.tick(10.15);
        assert_eq!(began, vec![HealthLine::Began { name: "node1-emcy".into(), since_s: 10.0 }]);
        assert!(log.tick(11.0).is_empty(), "announced once");
        let cleared = log.change(12.5, h::empty());
        assert_eq!(cleared, vec![HealthLine::Cleared { name: "node1-emcy".into(), at_s: 12.5, lasted_s: 2.5 }]);
        assert_eq!(log.flaps(), None, "a lasting condition is not a flap");
        assert_eq!(cleared[0].to_string(), "   12.500 s  health node1-emcy cleared after 2.500 s");
    }

    #[test]
    fn conditions_are_followed_one_by_one() {
        let mut log = HealthLog::new();
        log.change(0.0, h::NODE_STALE[0] | h::NODE_HEARTBEAT[2]);
        log.change(0.05, h::NODE_HEARTBEAT[2]);
        let began = log.tick(1.0);
        assert_eq!(began.len(), 1);
        assert_eq!(log.flaps().as_deref(), Some("short health conditions (under 0.1 s each): node1-stale ×1"));
    }
}
