//! `comanip-camera`: a camera source published on the frame service, and a frame monitor
//! (`docs/frames.md`).
//!
//! - [`pump`] (from `hw_io::camera`): frames of any `CameraSource` written straight into
//!   loaned shared-memory slots of a `FramePublisher` (one copy from the device or file, none
//!   after), until the source ends, a frame budget is spent or the stop flag is set. Source
//!   errors skip the frame, are counted and logged; nothing is lost silently.
//! - [`Monitor`]: what a frame subscriber saw: frames in order or not, transport losses, the
//!   source's own losses, publisher restarts, timestamps that do not increase, and the age of
//!   each frame on arrival (now − mid-exposure time, both `CLOCK_MONOTONIC`).
//!
//! Lower priority than fulcrumd: it runs as an ordinary process (`Nice`, `CPUWeight` in its
//! unit), never on the loop's core.

pub use hw_io::camera::{PumpError, PumpSummary, pump};
use hw_io::frame::FrameMeta;
use hw_io::ipc::{Continuity, FrameCounters, ReceivedFrame};
use serde::Serialize;

/// What a frame monitor saw (`comanip-camera monitor`, `--summary-json`).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct MonitorSummary {
    /// Frames accepted.
    pub received: u64,
    /// Frames lost in the transport (sequence gaps).
    pub missed: u64,
    /// Publisher restarts.
    pub restarts: u64,
    /// Frames refused for their header.
    pub rejected: u64,
    /// Frames the camera source lost, as the last header said.
    pub source_dropped: u64,
    /// Frames whose mid-exposure time did not increase over the previous frame's (same run).
    pub timestamps_not_increasing: u64,
    /// Sequence of the first and last frame received.
    pub first_sequence: Option<u64>,
    /// See `first_sequence`.
    pub last_sequence: Option<u64>,
    /// Mid-exposure time of the first and last frame, nanoseconds of `CLOCK_MONOTONIC`.
    pub first_timestamp_ns: Option<u64>,
    /// See `first_timestamp_ns`.
    pub last_timestamp_ns: Option<u64>,
    /// Median age of a frame on arrival (arrival − mid-exposure time), milliseconds; meaningful
    /// for sources stamped on this machine's `CLOCK_MONOTONIC`.
    pub median_age_ms: Option<f64>,
    /// Largest age on arrival, milliseconds.
    pub max_age_ms: Option<f64>,
    /// Frame format seen (`W×H format ×eyes`).
    pub format: Option<String>,
}

/// Accumulates a [`MonitorSummary`] frame by frame.
#[derive(Debug, Default)]
pub struct Monitor {
    summary: MonitorSummary,
    ages_ms: Vec<f64>,
    last: Option<FrameMeta>,
}

impl Monitor {
    /// Records `frame`, received at `now_ns` (`CLOCK_MONOTONIC`); returns its age, milliseconds.
    pub fn record(&mut self, frame: &ReceivedFrame, now_ns: u64) -> f64 {
        let m = *frame.meta();
        let s = &mut self.summary;
        if let Some(last) = self.last
            && frame.event != Continuity::Restart
            && frame.event != Continuity::First
            && m.timestamp_ns <= last.timestamp_ns
        {
            s.timestamps_not_increasing += 1;
        }
        s.first_sequence.get_or_insert(m.sequence);
        s.first_timestamp_ns.get_or_insert(m.timestamp_ns);
        s.last_sequence = Some(m.sequence);
        s.last_timestamp_ns = Some(m.timestamp_ns);
        s.format = Some(format!("{}×{} {} ×{}", m.layout.width, m.layout.height, m.layout.format, m.eyes));
        let age_ms = (now_ns as f64 - m.timestamp_ns as f64) / 1e6;
        self.ages_ms.push(age_ms);
        self.last = Some(m);
        age_ms
    }

    /// The summary, with the subscriber's counters.
    pub fn summary(&self, counters: FrameCounters) -> MonitorSummary {
        let mut s = self.summary.clone();
        s.received = counters.received;
        s.missed = counters.missed;
        s.restarts = counters.restarts;
        s.rejected = counters.rejected;
        s.source_dropped = counters.source_dropped;
        let mut ages = self.ages_ms.clone();
        ages.sort_by(f64::total_cmp);
        s.median_age_ms = ages.get(ages.len() / 2).copied();
        s.max_age_ms = ages.last().copied();
        s
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;
    use hw_io::camera::{CameraSource, Next, SourceCounters};
    use hw_io::frame::{FrameFormat, ImageLayout, PixelFormat};
    use hw_io::ipc::{FramePublisher, FrameSubscriber, PublisherOptions};
    use std::sync::atomic::AtomicBool;
    use std::time::Duration;

    /// Five frames; the third fails; then the end.
    struct Fake {
        n: u64,
        format: FrameFormat,
        counters: SourceCounters,
    }

    #[derive(Debug, thiserror::Error)]
    #[error("broken frame")]
    struct Broken;

    impl CameraSource for Fake {
        type Error = Broken;
        fn format(&self) -> FrameFormat {
            self.format
        }
        fn next_into(&mut self, dst: &mut [u8], _: Duration) -> Result<Next, Broken> {
            let n = self.n;
            self.n += 1;
            match n {
                2 => {
                    self.counters.dropped += 1;
                    Err(Broken)
                }
                0..5 => {
                    dst.fill(n as u8);
                    self.counters.delivered += 1;
                    let meta = FrameMeta {
                        sequence: n,
                        camera_id: 0,
                        timestamp_ns: 100 * n,
                        exposure_ns: 7,
                        eyes: self.format.eyes,
                        layout: self.format.layout,
                    };
                    Ok(Next::Frame(meta))
                }
                _ => Ok(Next::End),
            }
        }
        fn counters(&self) -> SourceCounters {
            self.counters
        }
    }

    #[test]
    fn pump_publishes_every_good_frame_and_counts_the_bad_one() {
        let service = format!("comanip-test/{}/pump", std::process::id());
        let format = FrameFormat::new(1, ImageLayout::packed(4, 2, PixelFormat::Gray8).unwrap()).unwrap();
        let opts = PublisherOptions { subscriber_buffer: 8, ..PublisherOptions::frames() };
        let mut sub = FrameSubscriber::connect(&service, &opts).unwrap();
        let mut publisher = FramePublisher::create(&service, format, 0, &opts).unwrap();
        let mut source = Fake { n: 0, format, counters: SourceCounters::default() };
        let summary = pump(&mut source, &mut publisher, None, &AtomicBool::new(false)).unwrap();
        assert_eq!((summary.published, summary.source_errors, summary.source_dropped), (4, 1, 1));
        assert!(summary.source_ended);
        let mut got = Vec::new();
        while let Some(f) = sub.try_recv().unwrap() {
            got.push((f.meta().timestamp_ns, f.pixels()[0], f.header().source_dropped));
        }
        assert_eq!(got, vec![(0, 0, 0), (100, 1, 0), (300, 3, 1), (400, 4, 1)]);
        // A source of another format is refused.
        let other = FrameFormat::new(2, format.layout).unwrap();
        let mut source = Fake { n: 0, format: other, counters: SourceCounters::default() };
        assert!(matches!(
            pump(&mut source, &mut publisher, None, &AtomicBool::new(false)),
            Err(PumpError::Format { .. })
        ));
    }
}
