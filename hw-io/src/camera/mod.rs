//! Camera sources: where frames come from before they enter the frame transport
//! ([`crate::ipc::FramePublisher`]). Feature `camera`.
//!
//! Every source implements [`CameraSource`]: a fixed [`FrameFormat`] (eyes and image layout),
//! and [`CameraSource::next_into`], which waits for the next frame and writes its pixels into a
//! buffer the caller owns, usually a loaned shared-memory slot of the frame transport (one copy
//! from the device or file into shared memory, none after it). Timestamps are the exposure's
//! mid time in nanoseconds of `CLOCK_MONOTONIC` (the CAN receive timestamps are Unix time: see
//! [`crate::frame`] for pairing them).
//!
//! Sources: a directory of PNG images with a timestamps file ([`image_sequence`]), Video4Linux2
//! capture devices (`v4l2`, feature `v4l2`), and the simulated endoscope (`sim::camera`, in the
//! simulator crate). [`pump`] (with feature `ipc`) publishes any of them on the frame service.

use core::time::Duration;

pub mod image_sequence;
pub mod png;
#[cfg(feature = "ipc")]
mod pump;
#[cfg(feature = "v4l2")]
pub mod v4l2;

#[cfg(feature = "ipc")]
pub use pump::{PumpError, PumpSummary, REPORT_PERIOD, pump};

pub use crate::frame::FrameFormat;
use crate::frame::FrameMeta;

/// What [`CameraSource::next_into`] found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Next {
    /// A frame: its pixels are in the caller's buffer; its metadata here (the sequence numbers
    /// the source's frames 0, 1, 2, ...; a jump means the source lost frames, also counted in
    /// [`SourceCounters::dropped`]).
    Frame(FrameMeta),
    /// No frame within the timeout (a live source); the caller may try again.
    Timeout,
    /// The source has no more frames (the end of a file sequence).
    End,
}

/// What a source has done since it was opened.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SourceCounters {
    /// Frames written into callers' buffers.
    pub delivered: u64,
    /// Frames the source knows it lost (a capture driver's sequence gap, a file that could not
    /// be read and was skipped).
    pub dropped: u64,
}

/// A source of frames (one camera rig: mono or stereo).
pub trait CameraSource {
    /// Why a frame could not be delivered.
    type Error: core::error::Error + Send + Sync + 'static;

    /// The eyes and layout of every frame this source delivers.
    fn format(&self) -> FrameFormat;

    /// Waits at most `timeout` for the next frame and writes its pixels into `dst`, the eyes one
    /// after the other, each `stride × height` bytes (`dst.len()` must be
    /// [`FrameFormat::payload_bytes`]; a source returns an error otherwise).
    fn next_into(&mut self, dst: &mut [u8], timeout: Duration) -> Result<Next, Self::Error>;

    /// What the source has done since it was opened.
    fn counters(&self) -> SourceCounters;
}
