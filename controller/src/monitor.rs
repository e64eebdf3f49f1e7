//! One line of `fulcrumd monitor --samples-out`: a received sample and when it arrived, as
//! JSON. The monitor writes it; tests and diagnosis tools read it back with the same type.

use hw_io::ipc::{Continuity, HealthFlags, OutputState, Received, UnknownState};
use serde::{Deserialize, Serialize};

/// Continuity of a sample against the previous one (see [`Continuity`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SampleEvent {
    /// The first sample this subscriber received.
    First,
    /// The next sequence number of the same run.
    InOrder,
    /// Samples were missed before this one (`missed` says how many).
    Gap,
    /// A new daemon run.
    Restart,
}

/// One line of `monitor --samples-out`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SampleLine {
    /// Receive time, nanoseconds of `CLOCK_MONOTONIC` (same clock as `timestamp_ns`).
    pub rx_ns: u64,
    /// Continuity against the previous sample.
    pub event: SampleEvent,
    /// Samples missed before this one (gap only), else 0.
    pub missed: u64,
    /// The daemon run's identifier.
    pub run_id: u64,
    /// Cycle number within the run.
    pub sequence: u64,
    /// SYNC instant of the cycle, nanoseconds of `CLOCK_MONOTONIC`.
    pub timestamp_ns: u64,
    /// Invalid, outside or inside (in JSON its wire value: 0, 1, 2).
    pub state: OutputState,
    /// Health flags (in JSON their `u32` bits).
    pub health: HealthFlags,
    /// Trocar identity while inside, else 0.
    pub trocar_id: u32,
    /// Fulcrum, metres, robot base frame.
    pub fulcrum_base_m: [f64; 3],
    /// Joint angles 1..6, radians.
    pub joints_rad: [f64; 6],
    /// Lines in the detector's deciding window.
    pub window_fill: u16,
}

impl SampleLine {
    /// The line of sample `r`, received at `rx_ns` (nanoseconds of `CLOCK_MONOTONIC`);
    /// [`UnknownState`] when the sample's state is no [`OutputState`].
    pub fn new(rx_ns: u64, r: &Received) -> Result<Self, UnknownState> {
        let (event, missed) = match r.event {
            Continuity::First => (SampleEvent::First, 0),
            Continuity::InOrder => (SampleEvent::InOrder, 0),
            Continuity::Gap { missed } => (SampleEvent::Gap, missed),
            Continuity::Restart => (SampleEvent::Restart, 0),
        };
        let x = &r.sample;
        Ok(Self {
            rx_ns,
            event,
            missed,
            run_id: x.run_id,
            sequence: x.sequence,
            timestamp_ns: x.timestamp_ns,
            state: x.state()?,
            health: x.health(),
            trocar_id: x.trocar_id,
            fulcrum_base_m: x.fulcrum_base_m,
            joints_rad: x.joints_rad,
            window_fill: x.window_fill,
        })
    }
}
