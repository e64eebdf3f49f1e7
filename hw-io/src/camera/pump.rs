//! Publishing a camera source on the frame service: [`pump`]. Features `camera` and `ipc`.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use serde::Serialize;
use tracing::{info, warn};

use super::{CameraSource, Next, SourceCounters};
use crate::ipc::{FramePublisher, PublishError};

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
