//! `comanip-camera`: a camera source published on the frame service, and a frame monitor
//! (`docs/frames.md`).
//!
//! - [`pump`]: frames of any [`CameraSource`] written straight into loaned shared-memory slots of
//!   a [`FramePublisher`] (one copy from the device or file, none after), until the source ends,
//!   a frame budget is spent or the stop flag is set. Source errors skip the frame, are counted
//!   and logged; nothing is lost silently.
//! - [`Monitor`]: what a frame subscriber saw: frames in order or not, transport losses, the
//!   source's own losses, publisher restarts, timestamps that do not increase, and the age of
//!   each frame on arrival (now − mid-exposure time, both `CLOCK_MONOTONIC`).
//!
//! Lower priority than fulcrumd: it runs as an ordinary process (`Nice`, `CPUWeight` in its
//! unit), never on the loop's core.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use hw_io::camera::{CameraSource, Next, SourceCounters};
use hw_io::frame::FrameMeta;
use hw_io::ipc::{Continuity, FrameCounters, FramePublisher, PublishError, ReceivedFrame};
use serde::Serialize;
use tracing::{info, warn};

/// How often [`pump`] logs its counters, and waits at most for a frame per try.
pub const REPORT_PERIOD: Duration = Duration::from_secs(10);

/// What [`pump`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct PumpSummary {
    /// Frames sent on the frame service.
    pub published: u64,
    /// Frames the source could not deliver (its errors: a corrupt file, a short buffer), skipped.
    pub source_errors: u64,
    /// The source's counters at the end (delivered, and frames it knows it lost).
    pub source_delivered: u64,
    /// See [`SourceCounters::dropped`].
    pub source_dropped: u64,
    /// Frames that could not be sent (no free shared-memory slot, delivery failed).
    pub publish_errors: u64,
    /// True when the source said it had no more frames.
    pub source_ended: bool,
}

/// Why [`pump`] stopped early.
#[derive(Debug, thiserror::Error)]
pub enum PumpError {
    /// The source's format is not the publisher's.
    #[error("the source delivers {source_bytes}-byte frames, the frame service was created for {service_bytes}")]
    Format {
        /// Bytes of one source frame.
        source_bytes: usize,
        /// Bytes of one frame of the publisher.
        service_bytes: usize,
    },
    /// Sending failed 100 times in a row: the shared memory is not usable.
    #[error("publishing failed {0} times in a row, last: {1}")]
    Publish(u64, #[source] PublishError),
}

/// Publishes `source`'s frames until it ends, `max_frames` were sent, or `stop` is set. Frames
/// are written by the source straight into the publisher's shared-memory slot.
pub fn pump<S: CameraSource>(
    source: &mut S,
    publisher: &mut FramePublisher,
    max_frames: Option<u64>,
    stop: &AtomicBool,
) -> Result<PumpSummary, PumpError> {
    let (source_bytes, service_bytes) = (source.format().payload_bytes(), publisher.format().payload_bytes());
    if source_bytes != service_bytes || source.format() != publisher.format() {
        return Err(PumpError::Format { source_bytes, service_bytes });
    }
    let mut summary = PumpSummary::default();
    let mut failures_in_a_row = 0u64;
    let mut last_report = Instant::now();
    while !stop.load(Ordering::Relaxed) && max_frames.is_none_or(|m| summary.published < m) {
        let mut slot = match publisher.loan() {
            Ok(slot) => slot,
            Err(e) => {
                summary.publish_errors += 1;
                failures_in_a_row += 1;
                if failures_in_a_row >= 100 {
                    return Err(PumpError::Publish(failures_in_a_row, e));
                }
                warn!("cannot loan a frame slot: {e}");
                std::thread::sleep(Duration::from_millis(10));
                continue;
            }
        };
        match source.next_into(slot.pixels_mut(), Duration::from_millis(200)) {
            Ok(Next::Frame(meta)) => {
                slot.set_source_dropped(source.counters().dropped);
                match slot.send(meta.timestamp_ns, meta.exposure_ns) {
                    Ok(_) => {
                        summary.published += 1;
                        failures_in_a_row = 0;
                    }
                    Err(e) => {
                        summary.publish_errors += 1;
                        failures_in_a_row += 1;
                        if failures_in_a_row >= 100 {
                            return Err(PumpError::Publish(failures_in_a_row, e));
                        }
                        warn!("frame {} not sent: {e}", meta.sequence);
                    }
                }
            }
            Ok(Next::Timeout) => {}
            Ok(Next::End) => {
                summary.source_ended = true;
                break;
            }
            Err(e) => {
                summary.source_errors += 1;
                warn!("camera source: frame skipped: {e}");
            }
        }
        if last_report.elapsed() >= REPORT_PERIOD {
            last_report = Instant::now();
            let c = source.counters();
            info!(
                "frames published {}, source delivered {} dropped {} errors {}, publish errors {}",
                summary.published, c.delivered, c.dropped, summary.source_errors, summary.publish_errors
            );
        }
    }
    let c: SourceCounters = source.counters();
    summary.source_delivered = c.delivered;
    summary.source_dropped = c.dropped;
    Ok(summary)
}

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
    use hw_io::frame::{FrameFormat, ImageLayout, PixelFormat};
    use hw_io::ipc::{FrameSubscriber, PublisherOptions};

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
