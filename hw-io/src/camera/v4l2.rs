//! Video4Linux2 capture devices (`/dev/videoN`) as a [`CameraSource`]. Feature `v4l2`; Linux,
//! 64-bit targets.
//!
//! [`V4l2Source::open`] opens the device, checks that it captures and streams, negotiates the
//! pixel format, the size and the frame rate of a [`V4l2Config`], maps the driver's buffers
//! (memory-mapped streaming I/O) and starts streaming. [`CameraSource::next_into`] waits for a
//! filled buffer, copies its pixels into the caller's buffer (one copy: from the driver's mapping
//! into, usually, a loaned shared-memory slot), gives the buffer back to the driver and returns the
//! frame's metadata.
//!
//! - **Formats.** `YUYV`, `RGB3` (RGB24) and `GREY` are delivered as they are, as
//!   [`PixelFormat::Yuyv`], [`PixelFormat::Rgb8`] and [`PixelFormat::Gray8`]; `MJPG` (motion
//!   JPEG, what most USB cameras send at high resolutions) is decoded to [`PixelFormat::Rgb8`]
//!   with `zune-jpeg`, including the streams of UVC cameras that leave out the Huffman tables
//!   ([`decode_mjpeg`]). Rows are repacked: the device's row padding (`bytesperline`) is
//!   dropped, so each eye's stride is `width × bytes per pixel`.
//! - **Stereo.** [`Stereo::SideBySide`]: the device delivers both eyes in one frame, the left
//!   eye in the left half of each row and the right eye in the right half (how stereo endoscopes
//!   usually arrive on one capture card). Each frame is split into two eyes of half the width,
//!   left first, one after the other in the caller's buffer.
//! - **Timestamps.** The driver stamps each buffer on `CLOCK_MONOTONIC`
//!   (`V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC`, required: any other clock is
//!   [`TimestampError::ClockNotMonotonic`]) at the start of exposure (`TSTAMP_SRC_SOE`) or, most
//!   often, at the end of the frame (`TSTAMP_SRC_EOF`). The delivered
//!   [`FrameMeta::timestamp_ns`] is the exposure's mid time: `SOE + exposure/2` or
//!   `EOF − exposure/2`. The exposure is [`V4l2Config::exposure_ns`] when given, else the
//!   device's `V4L2_CID_EXPOSURE_ABSOLUTE` when exposure is manual; otherwise it is unknown
//!   ([`FrameMeta::exposure_ns`] = 0) and the frame interval stands in for it (the longest exposure
//!   possible at that rate): the mid time is then off by at most half a frame interval, and by
//!   the sensor's read-out time for EOF stamps (which mark the end of the read-out, not of the
//!   exposure). See [`mid_exposure_ns`].
//! - **Dropped frames.** Gaps in the driver's sequence numbers, buffers the driver flags as
//!   erroneous (`V4L2_BUF_FLAG_ERROR`), buffers shorter than the negotiated image and MJPEG
//!   frames that do not decode are counted in [`SourceCounters::dropped`];
//!   [`FrameMeta::sequence`] jumps by as many.
//!
//! Nothing a device delivers makes this panic: sizes, indices and stamps from the driver are
//! checked, and bad ones are a typed error or a counted drop.
//!
//! Why no binding crate: the `v4l` crate (and every other V4L2 crate on crates.io but a few small
//! ones) generates its bindings with bindgen at build time, which needs libclang on every machine
//! that builds the workspace, CI included. The dozen structures and ioctls used here are written
//! out below, each checked at compile time against the kernel ABI's size.

use core::time::Duration;
use std::fs::OpenOptions;
use std::io;
use std::os::fd::{AsRawFd, OwnedFd};
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};
use std::time::Instant;

use super::{CameraSource, FrameFormat, Next, SourceCounters};
use crate::frame::{FrameMeta, ImageLayout, LayoutError, PixelFormat};
use sys::Pod as _;

#[cfg(not(all(target_os = "linux", target_pointer_width = "64")))]
compile_error!("hw-io's `v4l2` feature supports 64-bit Linux only (the V4L2 structures below are that ABI's)");

// -------------------------------------------------------------------------------------------------
// Configuration
// -------------------------------------------------------------------------------------------------

/// A V4L2 pixel format code (four characters, as `v4l2-ctl --list-formats` prints them).
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct FourCc(pub u32);

impl FourCc {
    /// `YUYV`: YUV 4:2:2, delivered as [`PixelFormat::Yuyv`].
    pub const YUYV: Self = Self::new(*b"YUYV");
    /// `RGB3` (RGB24): 8-bit R, G, B, delivered as [`PixelFormat::Rgb8`].
    pub const RGB3: Self = Self::new(*b"RGB3");
    /// `GREY`: 8-bit grey, delivered as [`PixelFormat::Gray8`].
    pub const GREY: Self = Self::new(*b"GREY");
    /// `MJPG`: motion JPEG (not supported yet).
    pub const MJPG: Self = Self::new(*b"MJPG");

    /// The code of four ASCII characters.
    pub const fn new(chars: [u8; 4]) -> Self {
        Self(u32::from_le_bytes(chars))
    }
}

impl core::fmt::Display for FourCc {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        for b in self.0.to_le_bytes() {
            let c = if b.is_ascii_graphic() || b == b' ' { char::from(b) } else { '?' };
            write!(f, "{c}")?;
        }
        Ok(())
    }
}

impl core::fmt::Debug for FourCc {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(f, "FourCc({self})")
    }
}

/// The format to capture in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum CaptureFormat {
    /// `YUYV` (YUV 4:2:2), delivered as [`PixelFormat::Yuyv`]; the width (of each eye) is even.
    #[default]
    Yuyv,
    /// `RGB3` (RGB24), delivered as [`PixelFormat::Rgb8`].
    Rgb24,
    /// `GREY`, delivered as [`PixelFormat::Gray8`].
    Grey,
    /// `MJPG` (motion JPEG), decoded and delivered as [`PixelFormat::Rgb8`]. Decoding allocates
    /// (the decoder's tables and rows) and costs CPU time per frame (not measured yet).
    Mjpeg,
}

impl CaptureFormat {
    /// The V4L2 code.
    pub const fn fourcc(self) -> FourCc {
        match self {
            Self::Yuyv => FourCc::YUYV,
            Self::Rgb24 => FourCc::RGB3,
            Self::Grey => FourCc::GREY,
            Self::Mjpeg => FourCc::MJPG,
        }
    }

    /// The pixel format delivered (MJPEG is decoded to RGB).
    pub const fn pixel_format(self) -> PixelFormat {
        match self {
            Self::Yuyv => PixelFormat::Yuyv,
            Self::Rgb24 | Self::Mjpeg => PixelFormat::Rgb8,
            Self::Grey => PixelFormat::Gray8,
        }
    }
}

/// How the eyes of the rig arrive.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Stereo {
    /// One camera: each captured frame is one eye.
    #[default]
    Mono,
    /// Two eyes side by side in each captured frame: the left eye is the left half of each row,
    /// the right eye the right half. Delivered as two eyes of half the captured width.
    SideBySide,
}

/// What to open and how to capture.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct V4l2Config {
    /// The device node, e.g. `/dev/video0`.
    pub device: PathBuf,
    /// The capture format.
    pub format: CaptureFormat,
    /// Width of the captured frame, pixels (both eyes for [`Stereo::SideBySide`]).
    pub width_px: u32,
    /// Height of the captured frame, pixels.
    pub height_px: u32,
    /// Frames per second to ask for; 0 keeps the device's rate. A device may round it (read the
    /// result with [`V4l2Source::frame_interval_ns`]).
    pub frame_rate_hz: u32,
    /// Mono or side-by-side stereo.
    pub stereo: Stereo,
    /// Number of driver buffers to map, 2..=32 (4 is a good default: one with the caller, the
    /// others queued; more absorb longer stalls of the reader before the driver drops frames).
    pub buffers: u32,
    /// The rig's id, copied into [`FrameMeta::camera_id`].
    pub camera_id: u32,
    /// The exposure time when known from outside (the camera is set to it), nanoseconds; `None`
    /// reads it from the device (manual exposure only), else it is unknown (module docs).
    pub exposure_ns: Option<u32>,
}

impl Default for V4l2Config {
    /// `/dev/video0`, YUYV 640×480 pixels at the device's rate, mono, 4 buffers, camera 0.
    fn default() -> Self {
        Self {
            device: PathBuf::from("/dev/video0"),
            format: CaptureFormat::Yuyv,
            width_px: 640,
            height_px: 480,
            frame_rate_hz: 0,
            stereo: Stereo::Mono,
            buffers: 4,
            camera_id: 0,
            exposure_ns: None,
        }
    }
}

/// Fewest and most driver buffers [`V4l2Config::buffers`] may ask for.
pub const BUFFERS_RANGE: core::ops::RangeInclusive<u32> = 2..=32;

// -------------------------------------------------------------------------------------------------
// Errors
// -------------------------------------------------------------------------------------------------

/// Why [`V4l2Source::open`] failed (opening the device, negotiating, mapping, starting).
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    /// The device node does not exist.
    #[error("{0}: no such device (is the camera plugged in and its driver loaded? `ls /dev/video*`)")]
    DeviceMissing(PathBuf),
    /// Opening the node was refused.
    #[error("{0}: permission denied (add the user to the `video` group, or run as root)")]
    PermissionDenied(PathBuf),
    /// Opening the node failed otherwise.
    #[error("{path}: cannot open: {source}")]
    Open {
        /// The device node.
        path: PathBuf,
        /// The system's error.
        source: io::Error,
    },
    /// The node is not a V4L2 device (`VIDIOC_QUERYCAP` refused).
    #[error("{path}: not a Video4Linux2 device ({source})")]
    NotV4l2 {
        /// The device node.
        path: PathBuf,
        /// The system's error.
        source: io::Error,
    },
    /// The device does not capture video with streaming I/O (an output, a metadata or a radio
    /// node, or a read()-only driver).
    #[error("{path}: '{card}' is not a video capture device with streaming I/O (capabilities {caps:#010x})")]
    NotCapture {
        /// The device node.
        path: PathBuf,
        /// The device's name.
        card: String,
        /// Its `device_caps` bits.
        caps: u32,
    },
    /// The configuration is not usable.
    #[error("v4l2 configuration: {0}")]
    Config(&'static str),
    /// The device does not offer the requested format.
    #[error("{path}: format {requested} not offered by the device; it offers: {}", list_fourccs(offered))]
    FormatNotOffered {
        /// The device node.
        path: PathBuf,
        /// The requested code.
        requested: FourCc,
        /// What the device offers (`VIDIOC_ENUM_FMT`).
        offered: Vec<FourCc>,
    },
    /// The device set another size than the one asked for.
    #[error("{path}: asked for {width_px}×{height_px} pixels, the device set {got_width_px}×{got_height_px}")]
    SizeNotApplied {
        /// The device node.
        path: PathBuf,
        /// Requested width, pixels.
        width_px: u32,
        /// Requested height, pixels.
        height_px: u32,
        /// Width the device set, pixels.
        got_width_px: u32,
        /// Height the device set, pixels.
        got_height_px: u32,
    },
    /// The device reported a row length shorter than a row of pixels.
    #[error("{path}: the device's row length {bytes_per_line} bytes is shorter than a row ({min_bytes} bytes)")]
    BadStride {
        /// The device node.
        path: PathBuf,
        /// `bytesperline`, bytes.
        bytes_per_line: u32,
        /// `width × bytes per pixel`, bytes.
        min_bytes: u32,
    },
    /// The delivered eye layout is invalid (a side-by-side width that does not split into two
    /// eyes of the format's constraints, sizes above the limits).
    #[error("v4l2 eye layout: {0}")]
    Layout(#[from] LayoutError),
    /// The driver gave fewer buffers than needed for streaming.
    #[error("{path}: the driver gave {got} buffers, at least 2 are needed")]
    TooFewBuffers {
        /// The device node.
        path: PathBuf,
        /// Buffers granted.
        got: u32,
    },
    /// A driver buffer is smaller than the negotiated image.
    #[error("{path}: driver buffer of {length} bytes, the image needs {needed} bytes")]
    BufferTooSmall {
        /// The device node.
        path: PathBuf,
        /// Buffer length, bytes.
        length: u32,
        /// Image size, bytes.
        needed: usize,
    },
    /// A V4L2 request failed.
    #[error("{path}: {op} failed: {source}")]
    Ioctl {
        /// The device node.
        path: PathBuf,
        /// The request (`VIDIOC_S_FMT`, `mmap`, ...).
        op: &'static str,
        /// The system's error.
        source: io::Error,
    },
}

fn list_fourccs(codes: &[FourCc]) -> String {
    if codes.is_empty() {
        return "nothing".into();
    }
    codes.iter().map(ToString::to_string).collect::<Vec<_>>().join(", ")
}

/// Why [`V4l2Source`]'s [`CameraSource::next_into`] failed.
#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    /// The caller's buffer does not have [`FrameFormat::payload_bytes`].
    #[error("destination buffer of {got} bytes, a frame needs {expected} bytes")]
    Destination {
        /// Bytes needed.
        expected: usize,
        /// Bytes given.
        got: usize,
    },
    /// A V4L2 request (or `poll`) failed; `ENODEV` means the camera was unplugged.
    #[error("{op} failed: {source}")]
    Ioctl {
        /// The request.
        op: &'static str,
        /// The system's error.
        source: io::Error,
    },
    /// The driver returned a buffer index it never gave.
    #[error("the driver returned buffer index {index}, it has {count} buffers")]
    BadIndex {
        /// The index returned.
        index: u32,
        /// Buffers mapped.
        count: usize,
    },
    /// The buffer's timestamp is not on `CLOCK_MONOTONIC`.
    #[error(transparent)]
    Timestamp(#[from] TimestampError),
}

/// Why a buffer's timestamp cannot give a `CLOCK_MONOTONIC` mid-exposure time.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum TimestampError {
    /// The driver's clock is not `CLOCK_MONOTONIC` (`V4L2_BUF_FLAG_TIMESTAMP_*` bits given).
    #[error(
        "the driver's timestamps are not on CLOCK_MONOTONIC (buffer flags {0:#x}): frames cannot be related to the robot's clocks"
    )]
    ClockNotMonotonic(u32),
    /// The timestamp is negative or its microseconds are out of range.
    #[error("invalid buffer timestamp {sec} s {usec} µs")]
    Invalid {
        /// Seconds.
        sec: i64,
        /// Microseconds.
        usec: i64,
    },
}

// -------------------------------------------------------------------------------------------------
// Pure logic: timestamps, sequence numbers, copy and split (unit-tested on synthetic buffers)
// -------------------------------------------------------------------------------------------------

/// `V4L2_BUF_FLAG_TIMESTAMP_MASK`.
const TIMESTAMP_MASK: u32 = 0xe000;
/// `V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC`.
const TIMESTAMP_MONOTONIC: u32 = 0x2000;
/// `V4L2_BUF_FLAG_TSTAMP_SRC_MASK`.
const TSTAMP_SRC_MASK: u32 = 0x7_0000;
/// `V4L2_BUF_FLAG_TSTAMP_SRC_SOE` (`_EOF` is 0).
const TSTAMP_SRC_SOE: u32 = 0x1_0000;
/// `V4L2_BUF_FLAG_ERROR`.
const BUF_FLAG_ERROR: u32 = 0x40;

/// The exposure's mid time, nanoseconds of `CLOCK_MONOTONIC`, from a buffer's timestamp
/// (`sec`, `usec`: the `timeval` of `CLOCK_MONOTONIC` the driver wrote) and flags.
///
/// `exposure_ns` is the exposure time when known; otherwise `frame_interval_ns` (the longest
/// exposure possible at that rate, 0 if unknown too) stands in for it. Start-of-exposure stamps
/// (`TSTAMP_SRC_SOE`) are moved forward by half the exposure, end-of-frame stamps (`EOF`, and
/// any other source code) back by it.
pub fn mid_exposure_ns(
    sec: i64,
    usec: i64,
    flags: u32,
    exposure_ns: Option<u32>,
    frame_interval_ns: u64,
) -> Result<u64, TimestampError> {
    if flags & TIMESTAMP_MASK != TIMESTAMP_MONOTONIC {
        return Err(TimestampError::ClockNotMonotonic(flags));
    }
    if sec < 0 || !(0..1_000_000).contains(&usec) {
        return Err(TimestampError::Invalid { sec, usec });
    }
    let stamp_ns = (sec as u64).saturating_mul(1_000_000_000).saturating_add(usec as u64 * 1000);
    let half_ns = exposure_ns.map_or(frame_interval_ns, u64::from) / 2;
    Ok(if flags & TSTAMP_SRC_MASK == TSTAMP_SRC_SOE {
        stamp_ns.saturating_add(half_ns)
    } else {
        stamp_ns.saturating_sub(half_ns)
    })
}

/// Turns the driver's 32-bit sequence numbers (one per frame it captured, wrapping) into the
/// source's 64-bit frame positions and counts the frames the driver skipped.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SequenceTracker {
    last: Option<u32>,
    position: u64,
}

impl SequenceTracker {
    /// Feeds the driver's sequence number of the next dequeued buffer; returns its position (0
    /// for the first buffer, +1 per frame the driver captured since) and how many frames the
    /// driver skipped before it. A number that goes back (a driver restart) counts no gap and
    /// advances by one.
    pub fn next(&mut self, driver_sequence: u32) -> (u64, u64) {
        let Some(last) = self.last else {
            self.last = Some(driver_sequence);
            return (0, 0);
        };
        self.last = Some(driver_sequence);
        let step = driver_sequence.wrapping_sub(last);
        // A step above half the range is a backward jump (a restart), not 2^31 lost frames.
        let gap = if step == 0 || step > u32::MAX / 2 { 0 } else { u64::from(step - 1) };
        self.position += 1 + gap;
        (self.position, gap)
    }
}

/// Why a captured buffer cannot be copied out (it is then counted as dropped).
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum CopyError {
    /// The buffer holds fewer bytes than the image needs.
    #[error("captured buffer holds {got} bytes, the image needs {needed} bytes")]
    Short {
        /// Bytes needed.
        needed: usize,
        /// Bytes held.
        got: usize,
    },
    /// The destination does not have `eyes × eye_bytes`.
    #[error("destination of {got} bytes, expected {expected} bytes")]
    Destination {
        /// Bytes needed.
        expected: usize,
        /// Bytes given.
        got: usize,
    },
}

/// Copies one captured image (`src`, rows `src_stride` bytes apart) into `dst` as `eyes` eye
/// images of layout `eye` one after the other (each row packed to `eye.stride` bytes): with one
/// eye, row by row; with two, each source row's left half goes to the left eye and its right
/// half to the right eye. The captured width is `eyes × eye.width` pixels.
pub fn copy_eyes(src: &[u8], src_stride: usize, eye: &ImageLayout, eyes: u32, dst: &mut [u8]) -> Result<(), CopyError> {
    let eyes = eyes as usize;
    let eye_row = eye.row_bytes();
    let expected = eyes * eye.eye_bytes();
    if dst.len() != expected {
        return Err(CopyError::Destination { expected, got: dst.len() });
    }
    let rows = eye.height as usize;
    // The last row needs only its pixels, not the padding after it.
    let needed = if rows == 0 { 0 } else { (rows - 1) * src_stride + eyes * eye_row };
    if src.len() < needed || src_stride < eyes * eye_row {
        return Err(CopyError::Short { needed: needed.max(rows * eyes * eye_row), got: src.len() });
    }
    let eye_bytes = eye.eye_bytes();
    let dst_stride = eye.stride as usize;
    for (e, out) in dst.chunks_exact_mut(eye_bytes).enumerate() {
        for (r, out_row) in out.chunks_exact_mut(dst_stride).enumerate() {
            let start = r * src_stride + e * eye_row;
            if let (Some(from), Some(to)) = (src.get(start..start + eye_row), out_row.get_mut(..eye_row)) {
                to.copy_from_slice(from);
            }
        }
    }
    Ok(())
}

/// The eye layout of a captured `width_px × height_px` frame of `format`: the whole frame for
/// [`Stereo::Mono`], its half width for [`Stereo::SideBySide`] (the width must split evenly, and
/// each half of a YUYV frame must be of even width).
pub fn eye_layout(
    width_px: u32,
    height_px: u32,
    format: PixelFormat,
    stereo: Stereo,
) -> Result<ImageLayout, LayoutError> {
    let eye_width = match stereo {
        Stereo::Mono => width_px,
        Stereo::SideBySide if width_px.is_multiple_of(2) => width_px / 2,
        // An odd side-by-side width: the halves differ; refuse as a size error.
        Stereo::SideBySide => return Err(LayoutError::Size { width: width_px, height: height_px }),
    };
    ImageLayout::packed(eye_width, height_px, format)
}

/// An APP0 segment saying "AVI1" (AVI motion JPEG): frames without Huffman tables use the
/// standard ones (ITU T.81 Annex K.3).
const AVI1_APP0: [u8; 16] = [0xFF, 0xE0, 0x00, 0x0E, b'A', b'V', b'I', b'1', 0, 0, 0, 0, 0, 0, 0, 0];

/// Whether a JPEG starts well (SOI) and reaches its first scan (SOS) without a DHT segment.
fn lacks_huffman_tables(jpeg: &[u8]) -> bool {
    if jpeg.get(..2) != Some(&[0xFF, 0xD8][..]) {
        return false;
    }
    let mut i = 2;
    while let Some(&[0xFF, marker, hi, lo]) = jpeg.get(i..i + 4) {
        match marker {
            0xC4 => return false,
            0xDA => return true,
            0xFF => i += 1, // fill byte
            _ => i += 2 + usize::from(u16::from_be_bytes([hi, lo])),
        }
    }
    false
}

/// Why an MJPEG frame did not decode (it is then counted as dropped).
#[derive(Debug, thiserror::Error)]
pub enum MjpegError {
    /// The JPEG data is invalid or truncated.
    #[error("MJPEG frame does not decode: {0}")]
    Decode(#[source] zune_jpeg::errors::DecodeErrors),
    /// The frame's size is not the negotiated one.
    #[error("MJPEG frame of {width}×{height} pixels, the stream is {expected_width}×{expected_height}")]
    Size {
        /// Frame width, pixels.
        width: usize,
        /// Frame height, pixels.
        height: usize,
        /// Negotiated width, pixels.
        expected_width: u32,
        /// Negotiated height, pixels.
        expected_height: u32,
    },
    /// The decoder panicked on this frame (caught: a device's bytes must not stop the source).
    #[error("the JPEG decoder panicked on this frame")]
    Panicked,
}

/// Decodes one MJPEG frame (`src`, a JPEG image; UVC cameras' frames without Huffman tables
/// get the standard ones) of `width_px × height_px` pixels into `rgb`, packed 8-bit RGB rows
/// (`width_px × 3` bytes each; `rgb.len()` must be `width_px × height_px × 3`).
///
/// **Not for the real-time loop:** allocates the decoder's state.
pub fn decode_mjpeg(src: &[u8], width_px: u32, height_px: u32, rgb: &mut [u8]) -> Result<(), MjpegError> {
    use zune_jpeg::zune_core::{bytestream::ZCursor, colorspace::ColorSpace, options::DecoderOptions};
    // UVC cameras leave the (standard) Huffman tables out of their frames. zune-jpeg fills in
    // the standard ones for frames marked as AVI MJPEG (an `AVI1` APP0 segment): mark such
    // frames (a copy: this allocates, once per frame).
    let patched;
    let data = if lacks_huffman_tables(src) {
        patched = [&src[..2], &AVI1_APP0[..], &src[2..]].concat();
        &patched[..]
    } else {
        src
    };
    let run = || {
        let options = DecoderOptions::default().jpeg_set_out_colorspace(ColorSpace::RGB);
        let mut decoder = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(data), options);
        decoder.decode_headers().map_err(MjpegError::Decode)?;
        let (width, height) = decoder.dimensions().unwrap_or((0, 0));
        let size_error = MjpegError::Size { width, height, expected_width: width_px, expected_height: height_px };
        if (width, height) != (width_px as usize, height_px as usize) || decoder.output_buffer_size() != Some(rgb.len())
        {
            return Err(size_error);
        }
        decoder.decode_into(rgb).map_err(MjpegError::Decode)
    };
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(run)).unwrap_or(Err(MjpegError::Panicked))
}

// -------------------------------------------------------------------------------------------------
// The kernel ABI (include/uapi/linux/videodev2.h), 64-bit Linux
// -------------------------------------------------------------------------------------------------

mod sys {
    //! The V4L2 structures and requests used, as in `linux/videodev2.h`. Each request code is
    //! computed from the size of its argument (`_IOWR('V', nr, T)`), and each size is checked
    //! against the kernel's at compile time, so an argument can never disagree with its code.

    pub const BUF_TYPE_VIDEO_CAPTURE: u32 = 1;
    pub const MEMORY_MMAP: u32 = 1;
    pub const FIELD_NONE: u32 = 1;
    pub const CAP_VIDEO_CAPTURE: u32 = 0x1;
    pub const CAP_STREAMING: u32 = 0x0400_0000;
    pub const CAP_DEVICE_CAPS: u32 = 0x8000_0000;
    pub const CAP_TIMEPERFRAME: u32 = 0x1000;
    pub const CID_EXPOSURE_AUTO: u32 = 0x009a_0901;
    pub const CID_EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
    pub const EXPOSURE_MANUAL: i32 = 1;

    #[repr(C)]
    #[derive(Clone, Copy)]
    pub struct Capability {
        pub driver: [u8; 16],
        pub card: [u8; 32],
        pub bus_info: [u8; 32],
        pub version: u32,
        pub capabilities: u32,
        pub device_caps: u32,
        pub reserved: [u32; 3],
    }

    #[repr(C)]
    #[derive(Clone, Copy)]
    pub struct FmtDesc {
        pub index: u32,
        pub type_: u32,
        pub flags: u32,
        pub description: [u8; 32],
        pub pixelformat: u32,
        pub mbus_code: u32,
        pub reserved: [u32; 3],
    }

    #[repr(C)]
    #[derive(Clone, Copy)]
    pub struct PixFormat {
        pub width: u32,
        pub height: u32,
        pub pixelformat: u32,
        pub field: u32,
        pub bytesperline: u32,
        pub sizeimage: u32,
        pub colorspace: u32,
        pub priv_: u32,
        pub flags: u32,
        pub ycbcr_enc: u32,
        pub quantization: u32,
        pub xfer_func: u32,
    }

    /// `struct v4l2_format`: the type, then a 200-byte union aligned to 8 (it holds pointers),
    /// of which only `pix` is used.
    #[repr(C)]
    #[derive(Clone, Copy)]
    pub struct Format {
        pub type_: u32,
        pub pad: u32,
        pub pix: PixFormat,
        pub rest: [u8; 152],
        pub align: [u64; 0],
    }

    #[repr(C)]
    #[derive(Clone, Copy)]
    pub struct RequestBuffers {
        pub count: u32,
        pub type_: u32,
        pub memory: u32,
        pub capabilities: u32,
        pub flags: u8,
        pub reserved: [u8; 3],
    }

    #[repr(C)]
    #[derive(Clone, Copy)]
    pub struct Timeval {
        pub sec: i64,
        pub usec: i64,
    }

    #[repr(C)]
    #[derive(Clone, Copy)]
    pub struct Timecode {
        pub type_: u32,
        pub flags: u32,
        pub frames: u8,
        pub seconds: u8,
        pub minutes: u8,
        pub hours: u8,
        pub userbits: [u8; 4],
    }

    /// `struct v4l2_buffer`; the union `m` is read as its `__u32 offset` (MMAP) plus padding.
    #[repr(C)]
    #[derive(Clone, Copy)]
    pub struct Buffer {
        pub index: u32,
        pub type_: u32,
        pub bytesused: u32,
        pub flags: u32,
        pub field: u32,
        pub pad0: u32,
        pub timestamp: Timeval,
        pub timecode: Timecode,
        pub sequence: u32,
        pub memory: u32,
        pub m_offset: u32,
        pub m_pad: u32,
        pub length: u32,
        pub reserved2: u32,
        pub request_fd: u32,
        pub pad1: u32,
    }

    #[repr(C)]
    #[derive(Clone, Copy)]
    pub struct Fract {
        pub numerator: u32,
        pub denominator: u32,
    }

    #[repr(C)]
    #[derive(Clone, Copy)]
    pub struct CaptureParm {
        pub capability: u32,
        pub capturemode: u32,
        pub timeperframe: Fract,
        pub extendedmode: u32,
        pub readbuffers: u32,
        pub reserved: [u32; 4],
    }

    /// `struct v4l2_streamparm`: the type, then a 200-byte union of which `capture` is used.
    #[repr(C)]
    #[derive(Clone, Copy)]
    pub struct StreamParm {
        pub type_: u32,
        pub capture: CaptureParm,
        pub rest: [u8; 160],
    }

    #[repr(C)]
    #[derive(Clone, Copy)]
    pub struct Control {
        pub id: u32,
        pub value: i32,
    }

    // Sizes from the kernel headers (gcc, x86_64 and aarch64 alike).
    const _: () = assert!(size_of::<Capability>() == 104);
    const _: () = assert!(size_of::<FmtDesc>() == 64);
    const _: () = assert!(size_of::<PixFormat>() == 48);
    const _: () = assert!(size_of::<Format>() == 208 && align_of::<Format>() == 8);
    const _: () = assert!(size_of::<RequestBuffers>() == 20);
    const _: () = assert!(size_of::<Buffer>() == 88 && core::mem::offset_of!(Buffer, sequence) == 56);
    const _: () = assert!(core::mem::offset_of!(Buffer, m_offset) == 64 && core::mem::offset_of!(Buffer, length) == 72);
    const _: () = assert!(size_of::<StreamParm>() == 204);
    const _: () = assert!(size_of::<Control>() == 8);

    /// Plain old data whose all-zero bytes are a valid value (what V4L2 expects before filling
    /// in the fields of a request).
    ///
    /// # Safety
    /// Implementors are `repr(C)` structs of integers and arrays of integers only.
    pub unsafe trait Pod: Copy {
        fn zeroed() -> Self {
            // SAFETY: Pod types consist of integers only, for which all-zero bytes are valid.
            unsafe { core::mem::zeroed() }
        }
    }
    // SAFETY: each is a repr(C) struct of integers and integer arrays (above).
    unsafe impl Pod for Capability {}
    // SAFETY: as above.
    unsafe impl Pod for FmtDesc {}
    // SAFETY: as above.
    unsafe impl Pod for Format {}
    // SAFETY: as above.
    unsafe impl Pod for RequestBuffers {}
    // SAFETY: as above.
    unsafe impl Pod for Buffer {}
    // SAFETY: as above.
    unsafe impl Pod for StreamParm {}
    // SAFETY: as above.
    unsafe impl Pod for Control {}
    // SAFETY: a single integer.
    unsafe impl Pod for i32 {}

    const IOC_WRITE: u64 = 1;
    const IOC_READ: u64 = 2;

    const fn ioc<T>(dir: u64, nr: u8) -> u64 {
        (dir << 30) | ((size_of::<T>() as u64) << 16) | ((b'V' as u64) << 8) | nr as u64
    }

    pub const QUERYCAP: u64 = ioc::<Capability>(IOC_READ, 0);
    pub const ENUM_FMT: u64 = ioc::<FmtDesc>(IOC_READ | IOC_WRITE, 2);
    pub const S_FMT: u64 = ioc::<Format>(IOC_READ | IOC_WRITE, 5);
    pub const REQBUFS: u64 = ioc::<RequestBuffers>(IOC_READ | IOC_WRITE, 8);
    pub const QUERYBUF: u64 = ioc::<Buffer>(IOC_READ | IOC_WRITE, 9);
    pub const QBUF: u64 = ioc::<Buffer>(IOC_READ | IOC_WRITE, 15);
    pub const DQBUF: u64 = ioc::<Buffer>(IOC_READ | IOC_WRITE, 17);
    pub const STREAMON: u64 = ioc::<i32>(IOC_WRITE, 18);
    pub const STREAMOFF: u64 = ioc::<i32>(IOC_WRITE, 19);
    pub const G_PARM: u64 = ioc::<StreamParm>(IOC_READ | IOC_WRITE, 21);
    pub const S_PARM: u64 = ioc::<StreamParm>(IOC_READ | IOC_WRITE, 22);
    pub const G_CTRL: u64 = ioc::<Control>(IOC_READ | IOC_WRITE, 27);

    // The codes of linux/videodev2.h (as printed by a C program including it).
    const _: () = assert!(QUERYCAP == 0x8068_5600 && ENUM_FMT == 0xc040_5602 && S_FMT == 0xc0d0_5605);
    const _: () = assert!(REQBUFS == 0xc014_5608 && QUERYBUF == 0xc058_5609 && QBUF == 0xc058_560f);
    const _: () = assert!(DQBUF == 0xc058_5611 && STREAMON == 0x4004_5612 && STREAMOFF == 0x4004_5613);
    const _: () = assert!(G_PARM == 0xc0cc_5615 && S_PARM == 0xc0cc_5616 && G_CTRL == 0xc008_561b);

    /// `ioctl(fd, request, arg)`, retried on `EINTR`. `request` must be one of the codes above
    /// built from `T` (its size is part of the code, so the kernel copies exactly `T`'s bytes).
    pub fn ioctl<T: Pod>(fd: i32, request: u64, arg: &mut T) -> std::io::Result<()> {
        loop {
            // SAFETY: `arg` is a valid, exclusively borrowed `T` of the size the request encodes
            // (`ioc::<T>`), so the kernel reads and writes only inside it.
            let r = unsafe { libc::ioctl(fd, request as libc::Ioctl, core::ptr::from_mut(arg).cast::<libc::c_void>()) };
            if r != -1 {
                return Ok(());
            }
            let e = std::io::Error::last_os_error();
            if e.kind() != std::io::ErrorKind::Interrupted {
                return Err(e);
            }
        }
    }
}

/// A driver buffer mapped into this process.
struct Mapping {
    ptr: *mut u8,
    len: usize,
}

// SAFETY: the mapping is owned by one `Mapping` and only read through `&self` while the buffer is
// dequeued; moving it to another thread moves that ownership.
unsafe impl Send for Mapping {}

impl Mapping {
    fn bytes(&self) -> &[u8] {
        // SAFETY: `ptr` is a live MAP_SHARED mapping of `len` bytes (unmapped only in Drop); it is
        // read only between DQBUF and QBUF, while the driver does not write the buffer.
        unsafe { core::slice::from_raw_parts(self.ptr, self.len) }
    }
}

impl Drop for Mapping {
    fn drop(&mut self) {
        // SAFETY: `ptr`/`len` are exactly what mmap returned; nothing borrows the mapping here.
        unsafe {
            libc::munmap(self.ptr.cast(), self.len);
        }
    }
}

/// What the device agreed to (after `VIDIOC_S_FMT` / `VIDIOC_S_PARM`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DeviceFormat {
    /// Pixel format code.
    pub fourcc: FourCc,
    /// Captured width, pixels (both eyes for side-by-side).
    pub width_px: u32,
    /// Captured height, pixels.
    pub height_px: u32,
    /// Bytes from one captured row's start to the next's (`bytesperline` as the driver reports
    /// it: 0 may mean packed rows; meaningless for MJPEG).
    pub bytes_per_line: u32,
    /// Bytes of one captured image (`sizeimage`).
    pub size_image_bytes: u32,
}

/// A V4L2 capture device streaming through mapped buffers; see the module docs.
pub struct V4l2Source {
    // Declared before `fd`: unmapped before the descriptor closes.
    buffers: Vec<Mapping>,
    fd: OwnedFd,
    path: PathBuf,
    format: FrameFormat,
    device: DeviceFormat,
    /// Bytes between rows of the image copied out (the device's, or the decoded RGB's).
    src_stride: usize,
    /// MJPEG: the decoded full frame (both eyes), `height × width × 3` bytes.
    mjpeg_scratch: Option<Vec<u8>>,
    camera_id: u32,
    exposure_ns: Option<u32>,
    frame_interval_ns: u64,
    tracker: SequenceTracker,
    counters: SourceCounters,
}

impl core::fmt::Debug for V4l2Source {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("V4l2Source")
            .field("path", &self.path)
            .field("format", &self.format)
            .field("device", &self.device)
            .field("buffers", &self.buffers.len())
            .field("counters", &self.counters)
            .finish_non_exhaustive()
    }
}

/// A NUL-terminated name from a V4L2 structure.
fn c_name(bytes: &[u8]) -> String {
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    String::from_utf8_lossy(bytes.get(..end).unwrap_or_default()).into_owned()
}

impl V4l2Source {
    /// Opens `config.device`, negotiates format, size and rate, maps the buffers and starts
    /// streaming.
    ///
    /// **Not for the real-time loop:** opens a file, allocates, maps memory.
    pub fn open(config: &V4l2Config) -> Result<Self, OpenError> {
        let path = config.device.clone();
        if !BUFFERS_RANGE.contains(&config.buffers) {
            return Err(OpenError::Config("buffers must be 2..=32"));
        }
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(libc::O_NONBLOCK | libc::O_CLOEXEC)
            .open(&path)
            .map_err(|e| match e.kind() {
                io::ErrorKind::NotFound => OpenError::DeviceMissing(path.clone()),
                io::ErrorKind::PermissionDenied => OpenError::PermissionDenied(path.clone()),
                _ => OpenError::Open { path: path.clone(), source: e },
            })?;
        let fd = OwnedFd::from(file);
        let raw = fd.as_raw_fd();
        let ioctl_err = |op: &'static str| {
            let path = path.clone();
            move |source: io::Error| OpenError::Ioctl { path, op, source }
        };

        let mut cap = sys::Capability::zeroed();
        sys::ioctl(raw, sys::QUERYCAP, &mut cap).map_err(|source| OpenError::NotV4l2 { path: path.clone(), source })?;
        let caps = if cap.capabilities & sys::CAP_DEVICE_CAPS != 0 { cap.device_caps } else { cap.capabilities };
        if caps & sys::CAP_VIDEO_CAPTURE == 0 || caps & sys::CAP_STREAMING == 0 {
            return Err(OpenError::NotCapture { path, card: c_name(&cap.card), caps });
        }

        // Formats offered.
        let requested = config.format.fourcc();
        let offered = enum_formats(raw).map_err(ioctl_err("VIDIOC_ENUM_FMT"))?;
        if !offered.contains(&requested) {
            return Err(OpenError::FormatNotOffered { path, requested, offered });
        }
        let pixel_format = config.format.pixel_format();
        let mjpeg = config.format == CaptureFormat::Mjpeg;
        if config.stereo == Stereo::SideBySide && !config.width_px.is_multiple_of(2) {
            return Err(OpenError::Config("side-by-side stereo needs an even width_px (two equal halves)"));
        }
        let layout = eye_layout(config.width_px, config.height_px, pixel_format, config.stereo)?;
        let eyes = match config.stereo {
            Stereo::Mono => 1,
            Stereo::SideBySide => 2,
        };

        // Format and size.
        let mut fmt = sys::Format::zeroed();
        fmt.type_ = sys::BUF_TYPE_VIDEO_CAPTURE;
        fmt.pix.width = config.width_px;
        fmt.pix.height = config.height_px;
        fmt.pix.pixelformat = requested.0;
        fmt.pix.field = sys::FIELD_NONE;
        sys::ioctl(raw, sys::S_FMT, &mut fmt).map_err(ioctl_err("VIDIOC_S_FMT"))?;
        if fmt.pix.pixelformat != requested.0 {
            return Err(OpenError::FormatNotOffered { path, requested, offered });
        }
        if (fmt.pix.width, fmt.pix.height) != (config.width_px, config.height_px) {
            return Err(OpenError::SizeNotApplied {
                path,
                width_px: config.width_px,
                height_px: config.height_px,
                got_width_px: fmt.pix.width,
                got_height_px: fmt.pix.height,
            });
        }
        let min_bytes = config.width_px.saturating_mul(pixel_format.bytes_per_pixel());
        // The rows copied out: the device's (0 means packed), or, for MJPEG, the decoded RGB
        // image's (a compressed frame has no line length).
        let bytes_per_line = if fmt.pix.bytesperline == 0 { min_bytes } else { fmt.pix.bytesperline };
        if bytes_per_line < min_bytes && !mjpeg {
            return Err(OpenError::BadStride { path, bytes_per_line, min_bytes });
        }
        let device = DeviceFormat {
            fourcc: requested,
            width_px: fmt.pix.width,
            height_px: fmt.pix.height,
            bytes_per_line: fmt.pix.bytesperline,
            size_image_bytes: fmt.pix.sizeimage,
        };
        let src_stride = if mjpeg { min_bytes as usize } else { bytes_per_line as usize };
        // A compressed frame has no fixed size: any buffer can hold one (a short one is a drop).
        let needed = if mjpeg { 1 } else { (config.height_px as usize - 1) * src_stride + min_bytes as usize };
        let mjpeg_scratch = mjpeg.then(|| vec![0u8; config.height_px as usize * min_bytes as usize]);

        // Frame rate.
        let frame_interval_ns = set_frame_rate(raw, config.frame_rate_hz).map_err(ioctl_err("VIDIOC_S_PARM"))?;
        let exposure_ns = config.exposure_ns.or_else(|| read_exposure_ns(raw));

        // Buffers: request, map, queue.
        let mut req = sys::RequestBuffers::zeroed();
        req.count = config.buffers;
        req.type_ = sys::BUF_TYPE_VIDEO_CAPTURE;
        req.memory = sys::MEMORY_MMAP;
        sys::ioctl(raw, sys::REQBUFS, &mut req).map_err(ioctl_err("VIDIOC_REQBUFS"))?;
        if req.count < 2 {
            return Err(OpenError::TooFewBuffers { path, got: req.count });
        }
        let mut buffers = Vec::with_capacity(req.count as usize);
        for index in 0..req.count {
            let mut buf = capture_buffer(index);
            sys::ioctl(raw, sys::QUERYBUF, &mut buf).map_err(ioctl_err("VIDIOC_QUERYBUF"))?;
            if (buf.length as usize) < needed {
                return Err(OpenError::BufferTooSmall { path, length: buf.length, needed });
            }
            // SAFETY: a fresh shared mapping of the driver buffer `index` at the offset and length
            // the driver gave; the kernel checks both against the buffer.
            let ptr = unsafe {
                libc::mmap(
                    core::ptr::null_mut(),
                    buf.length as usize,
                    libc::PROT_READ | libc::PROT_WRITE,
                    libc::MAP_SHARED,
                    raw,
                    libc::off_t::from(buf.m_offset),
                )
            };
            if ptr == libc::MAP_FAILED {
                return Err(ioctl_err("mmap")(io::Error::last_os_error()));
            }
            buffers.push(Mapping { ptr: ptr.cast(), len: buf.length as usize });
            sys::ioctl(raw, sys::QBUF, &mut buf).map_err(ioctl_err("VIDIOC_QBUF"))?;
        }
        let mut ty = sys::BUF_TYPE_VIDEO_CAPTURE as i32;
        sys::ioctl(raw, sys::STREAMON, &mut ty).map_err(ioctl_err("VIDIOC_STREAMON"))?;

        Ok(Self {
            buffers,
            fd,
            path,
            format: FrameFormat { eyes, layout },
            device,
            src_stride,
            mjpeg_scratch,
            camera_id: config.camera_id,
            exposure_ns,
            frame_interval_ns,
            tracker: SequenceTracker::default(),
            counters: SourceCounters::default(),
        })
    }

    /// The device node.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// What the device agreed to: the captured frame (both eyes for side-by-side).
    pub fn device_format(&self) -> DeviceFormat {
        self.device
    }

    /// The device's frame interval, nanoseconds (0 when the driver does not say).
    pub fn frame_interval_ns(&self) -> u64 {
        self.frame_interval_ns
    }

    /// The exposure time used for the mid-exposure timestamps, nanoseconds (`None`: unknown,
    /// the frame interval stands in for it).
    pub fn exposure_ns(&self) -> Option<u32> {
        self.exposure_ns
    }

    fn requeue(&self, index: u32) -> Result<(), CaptureError> {
        let mut buf = capture_buffer(index);
        sys::ioctl(self.fd.as_raw_fd(), sys::QBUF, &mut buf)
            .map_err(|source| CaptureError::Ioctl { op: "VIDIOC_QBUF", source })
    }
}

impl Drop for V4l2Source {
    fn drop(&mut self) {
        let mut ty = sys::BUF_TYPE_VIDEO_CAPTURE as i32;
        let _ = sys::ioctl(self.fd.as_raw_fd(), sys::STREAMOFF, &mut ty);
    }
}

fn capture_buffer(index: u32) -> sys::Buffer {
    let mut buf = sys::Buffer::zeroed();
    buf.index = index;
    buf.type_ = sys::BUF_TYPE_VIDEO_CAPTURE;
    buf.memory = sys::MEMORY_MMAP;
    buf
}

/// `VIDIOC_ENUM_FMT` over every index (at most 256).
fn enum_formats(fd: i32) -> io::Result<Vec<FourCc>> {
    let mut out = Vec::new();
    for index in 0..256 {
        let mut d = sys::FmtDesc::zeroed();
        d.index = index;
        d.type_ = sys::BUF_TYPE_VIDEO_CAPTURE;
        match sys::ioctl(fd, sys::ENUM_FMT, &mut d) {
            Ok(()) => out.push(FourCc(d.pixelformat)),
            Err(e) if e.raw_os_error() == Some(libc::EINVAL) => break,
            Err(e) => return Err(e),
        }
    }
    Ok(out)
}

/// Asks for `rate_hz` (0: keep) when the device can set its rate; returns the frame interval in
/// force, nanoseconds (0 when unknown).
fn set_frame_rate(fd: i32, rate_hz: u32) -> io::Result<u64> {
    let mut p = sys::StreamParm::zeroed();
    p.type_ = sys::BUF_TYPE_VIDEO_CAPTURE;
    if sys::ioctl(fd, sys::G_PARM, &mut p).is_err() {
        return Ok(if rate_hz > 0 { 1_000_000_000 / u64::from(rate_hz) } else { 0 });
    }
    if rate_hz > 0 && p.capture.capability & sys::CAP_TIMEPERFRAME != 0 {
        p.capture.timeperframe = sys::Fract { numerator: 1, denominator: rate_hz };
        sys::ioctl(fd, sys::S_PARM, &mut p)?;
    }
    let t = p.capture.timeperframe;
    Ok(if t.denominator == 0 {
        0
    } else {
        u64::from(t.numerator).saturating_mul(1_000_000_000) / u64::from(t.denominator)
    })
}

/// The exposure time when the device is in manual exposure and says it
/// (`V4L2_CID_EXPOSURE_ABSOLUTE`, units of 100 µs), nanoseconds.
fn read_exposure_ns(fd: i32) -> Option<u32> {
    let mut auto = sys::Control { id: sys::CID_EXPOSURE_AUTO, value: 0 };
    if sys::ioctl(fd, sys::G_CTRL, &mut auto).is_ok() && auto.value != sys::EXPOSURE_MANUAL {
        return None;
    }
    let mut abs = sys::Control { id: sys::CID_EXPOSURE_ABSOLUTE, value: 0 };
    sys::ioctl(fd, sys::G_CTRL, &mut abs).ok()?;
    u32::try_from(abs.value).ok()?.checked_mul(100_000)
}

impl CameraSource for V4l2Source {
    type Error = CaptureError;

    fn format(&self) -> FrameFormat {
        self.format
    }

    /// Waits at most `timeout` for a filled buffer (`poll`), copies and splits it into `dst`,
    /// and queues the buffer again. Buffers the driver flags as erroneous or that are shorter
    /// than the image are counted as dropped and skipped (the wait goes on until `timeout`).
    ///
    /// **Not for the real-time loop:** blocks up to `timeout`; allocation-free, except for
    /// MJPEG (the decoder allocates per frame).
    fn next_into(&mut self, dst: &mut [u8], timeout: Duration) -> Result<Next, CaptureError> {
        let expected = self.format.payload_bytes();
        if dst.len() != expected {
            return Err(CaptureError::Destination { expected, got: dst.len() });
        }
        let fd = self.fd.as_raw_fd();
        // A timeout too long for the clock (Duration::MAX) waits without end.
        let deadline = Instant::now().checked_add(timeout);
        loop {
            let left = deadline.map_or(Duration::MAX, |d| d.saturating_duration_since(Instant::now()));
            let mut pfd = libc::pollfd { fd, events: libc::POLLIN, revents: 0 };
            let ms = if deadline.is_none() {
                -1
            } else {
                i32::try_from(left.as_nanos().div_ceil(1_000_000)).unwrap_or(i32::MAX)
            };
            // SAFETY: one valid pollfd, count 1.
            let n = unsafe { libc::poll(&mut pfd, 1, ms) };
            if n < 0 {
                let e = io::Error::last_os_error();
                if e.kind() == io::ErrorKind::Interrupted {
                    continue;
                }
                return Err(CaptureError::Ioctl { op: "poll", source: e });
            }
            if n == 0 {
                return Ok(Next::Timeout);
            }
            let mut buf = capture_buffer(0);
            match sys::ioctl(fd, sys::DQBUF, &mut buf) {
                Ok(()) => {}
                Err(e) if e.raw_os_error() == Some(libc::EAGAIN) => {
                    // Readable but nothing to dequeue: an error condition (streaming stopped by
                    // the driver) would make poll return at once forever; do not spin on it.
                    if pfd.revents & (libc::POLLERR | libc::POLLHUP | libc::POLLNVAL) != 0 {
                        return Err(CaptureError::Ioctl {
                            op: "poll",
                            source: io::Error::from_raw_os_error(libc::EIO),
                        });
                    }
                    if left.is_zero() {
                        return Ok(Next::Timeout);
                    }
                    continue;
                }
                Err(source) => return Err(CaptureError::Ioctl { op: "VIDIOC_DQBUF", source }),
            }
            let Some(map) = self.buffers.get(buf.index as usize) else {
                return Err(CaptureError::BadIndex { index: buf.index, count: self.buffers.len() });
            };
            let (position, gap) = self.tracker.next(buf.sequence);
            self.counters.dropped += gap;
            let used = (buf.bytesused as usize).min(map.len);
            let src = map.bytes().get(..used).unwrap_or_default();
            let copied = if buf.flags & BUF_FLAG_ERROR != 0 {
                false
            } else if let Some(scratch) = self.mjpeg_scratch.as_mut() {
                decode_mjpeg(src, self.device.width_px, self.device.height_px, scratch).is_ok()
                    && copy_eyes(scratch, self.src_stride, &self.format.layout, self.format.eyes, dst).is_ok()
            } else {
                copy_eyes(src, self.src_stride, &self.format.layout, self.format.eyes, dst).is_ok()
            };
            let stamp = mid_exposure_ns(
                buf.timestamp.sec,
                buf.timestamp.usec,
                buf.flags,
                self.exposure_ns,
                self.frame_interval_ns,
            );
            self.requeue(buf.index)?;
            if !copied {
                self.counters.dropped += 1;
                continue;
            }
            let timestamp_ns = match stamp {
                Ok(t) => t,
                Err(e) => {
                    // The frame's position is used up: keep positions = delivered + dropped.
                    self.counters.dropped += 1;
                    return Err(e.into());
                }
            };
            self.counters.delivered += 1;
            return Ok(Next::Frame(FrameMeta {
                sequence: position,
                camera_id: self.camera_id,
                timestamp_ns,
                exposure_ns: self.exposure_ns.unwrap_or(0),
                eyes: self.format.eyes,
                layout: self.format.layout,
            }));
        }
    }

    fn counters(&self) -> SourceCounters {
        self.counters
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MONO_EOF: u32 = TIMESTAMP_MONOTONIC;
    const MONO_SOE: u32 = TIMESTAMP_MONOTONIC | TSTAMP_SRC_SOE;

    #[test]
    fn fourcc_codes_and_names() {
        assert_eq!(FourCc::YUYV.0, 0x5659_5559);
        assert_eq!(FourCc::RGB3.to_string(), "RGB3");
        assert_eq!(FourCc(0x0000_4142).to_string(), "BA??");
        assert_eq!(list_fourccs(&[FourCc::YUYV, FourCc::GREY]), "YUYV, GREY");
        assert_eq!(list_fourccs(&[]), "nothing");
        assert_eq!(CaptureFormat::Mjpeg.pixel_format(), PixelFormat::Rgb8);
        assert_eq!(CaptureFormat::Grey.pixel_format(), PixelFormat::Gray8);
    }

    #[test]
    fn timestamps_move_to_mid_exposure() {
        // EOF stamp 10 s + 500 µs, exposure 10 ms known: 5 ms earlier.
        assert_eq!(mid_exposure_ns(10, 500, MONO_EOF, Some(10_000_000), 33_333_333), Ok(10_000_500_000 - 5_000_000));
        // SOE stamp: 5 ms later.
        assert_eq!(mid_exposure_ns(10, 500, MONO_SOE, Some(10_000_000), 33_333_333), Ok(10_000_500_000 + 5_000_000));
        // Unknown exposure: half the frame interval.
        assert_eq!(mid_exposure_ns(1, 0, MONO_EOF, None, 40_000_000), Ok(1_000_000_000 - 20_000_000));
        // Nothing known: the stamp itself.
        assert_eq!(mid_exposure_ns(1, 0, MONO_SOE, None, 0), Ok(1_000_000_000));
        // Never below zero.
        assert_eq!(mid_exposure_ns(0, 10, MONO_EOF, Some(1_000_000), 0), Ok(0));
    }

    #[test]
    fn timestamps_on_other_clocks_or_invalid_are_refused() {
        // TIMESTAMP_UNKNOWN (0) and TIMESTAMP_COPY (0x4000).
        assert_eq!(mid_exposure_ns(1, 0, 0, None, 0), Err(TimestampError::ClockNotMonotonic(0)));
        assert_eq!(mid_exposure_ns(1, 0, 0x4000, None, 0), Err(TimestampError::ClockNotMonotonic(0x4000)));
        assert_eq!(mid_exposure_ns(-1, 0, MONO_EOF, None, 0), Err(TimestampError::Invalid { sec: -1, usec: 0 }));
        assert_eq!(
            mid_exposure_ns(1, 1_000_000, MONO_EOF, None, 0),
            Err(TimestampError::Invalid { sec: 1, usec: 1_000_000 })
        );
    }

    #[test]
    fn sequence_gaps_are_counted_and_wraps_are_not_gaps() {
        let mut t = SequenceTracker::default();
        assert_eq!(t.next(100), (0, 0));
        assert_eq!(t.next(101), (1, 0));
        assert_eq!(t.next(104), (4, 2));
        let mut w = SequenceTracker::default();
        assert_eq!(w.next(u32::MAX - 1), (0, 0));
        assert_eq!(w.next(u32::MAX), (1, 0));
        assert_eq!(w.next(0), (2, 0));
        assert_eq!(w.next(2), (4, 1));
        // A restart (backwards) is no gap.
        assert_eq!(w.next(0), (5, 0));
        // A repeated number (a driver bug) is no gap either.
        assert_eq!(w.next(0), (6, 0));
    }

    /// A synthetic captured image: byte = row × 16 + column byte (mod 256), padding 0xEE.
    fn synthetic(width_bytes: usize, stride: usize, rows: usize) -> Vec<u8> {
        let mut v = vec![0xEE; stride * rows];
        for r in 0..rows {
            for c in 0..width_bytes {
                v[r * stride + c] = (r * 16 + c) as u8;
            }
        }
        v
    }

    #[test]
    fn mono_copy_drops_row_padding() {
        let eye = eye_layout(4, 3, PixelFormat::Rgb8, Stereo::Mono).unwrap();
        assert_eq!((eye.stride, eye.eye_bytes()), (12, 36));
        let src = synthetic(12, 16, 3);
        let mut dst = vec![0; 36];
        copy_eyes(&src, 16, &eye, 1, &mut dst).unwrap();
        for r in 0..3 {
            for c in 0..12 {
                assert_eq!(dst[r * 12 + c], (r * 16 + c) as u8);
            }
        }
        assert!(!dst.contains(&0xEE));
    }

    #[test]
    fn side_by_side_split_gives_the_two_halves() {
        // 8×2 YUYV captured (16 bytes per row, stride 20): two 4×2 eyes of 8 bytes per row.
        let eye = eye_layout(8, 2, PixelFormat::Yuyv, Stereo::SideBySide).unwrap();
        assert_eq!((eye.width, eye.stride), (4, 8));
        let src = synthetic(16, 20, 2);
        let mut dst = vec![0; 32];
        copy_eyes(&src, 20, &eye, 2, &mut dst).unwrap();
        let (left, right) = dst.split_at(16);
        for r in 0..2 {
            assert_eq!(&left[r * 8..r * 8 + 8], &src[r * 20..r * 20 + 8]);
            assert_eq!(&right[r * 8..r * 8 + 8], &src[r * 20 + 8..r * 20 + 16]);
        }
    }

    #[test]
    fn side_by_side_widths_must_split_into_valid_eyes() {
        assert!(matches!(eye_layout(641, 480, PixelFormat::Rgb8, Stereo::SideBySide), Err(LayoutError::Size { .. })));
        // 2 × 321 YUYV: each eye's width is odd.
        assert_eq!(eye_layout(642, 480, PixelFormat::Yuyv, Stereo::SideBySide), Err(LayoutError::OddYuyvWidth(321)));
        assert!(eye_layout(644, 480, PixelFormat::Yuyv, Stereo::SideBySide).is_ok());
    }

    #[test]
    fn short_buffers_and_wrong_destinations_are_errors_not_panics() {
        let eye = eye_layout(4, 3, PixelFormat::Gray8, Stereo::Mono).unwrap();
        let mut dst = vec![0; 12];
        // Last row without padding is enough: 2 × 8 + 4 bytes.
        assert!(copy_eyes(&[1; 20], 8, &eye, 1, &mut dst).is_ok());
        assert_eq!(copy_eyes(&[1; 19], 8, &eye, 1, &mut dst), Err(CopyError::Short { needed: 20, got: 19 }));
        assert!(matches!(copy_eyes(&[], 8, &eye, 1, &mut dst), Err(CopyError::Short { .. })));
        // A stride shorter than a row (a lying driver).
        assert!(matches!(copy_eyes(&[1; 100], 2, &eye, 1, &mut dst), Err(CopyError::Short { .. })));
        assert_eq!(
            copy_eyes(&[1; 20], 8, &eye, 1, &mut [0; 11]),
            Err(CopyError::Destination { expected: 12, got: 11 })
        );
        // Every length of source from 0 to full: no panic, Ok only when complete.
        let eye2 = eye_layout(4, 3, PixelFormat::Gray8, Stereo::SideBySide).unwrap();
        let mut dst2 = vec![0; 12];
        for len in 0..=40 {
            let r = copy_eyes(&vec![7; len], 10, &eye2, 2, &mut dst2);
            assert_eq!(r.is_ok(), len >= 24, "len {len}");
        }
    }

    /// A `w × h` RGB image: the left half red, the right half blue (JPEG blocks of 8 pixels
    /// never straddle the boundary when `w / 2` is a multiple of 16).
    fn red_blue(w: usize, h: usize) -> Vec<u8> {
        let mut v = Vec::with_capacity(w * h * 3);
        for _ in 0..h {
            for x in 0..w {
                v.extend_from_slice(if x < w / 2 { &[220, 20, 30] } else { &[20, 30, 220] });
            }
        }
        v
    }

    fn jpeg(rgb: &[u8], w: u16, h: u16) -> Vec<u8> {
        let mut out = Vec::new();
        jpeg_encoder::Encoder::new(&mut out, 95).encode(rgb, w, h, jpeg_encoder::ColorType::Rgb).unwrap();
        out
    }

    /// The JPEG without its DHT (Huffman table) segments, as UVC cameras send MJPEG.
    fn without_dht(jpeg: &[u8]) -> Vec<u8> {
        let mut out = jpeg[..2].to_vec();
        let mut i = 2;
        while i + 4 <= jpeg.len() && jpeg[i] == 0xFF {
            let marker = jpeg[i + 1];
            if marker == 0xDA {
                break; // start of scan: the entropy-coded data follows
            }
            let len = usize::from(u16::from_be_bytes([jpeg[i + 2], jpeg[i + 3]]));
            if marker != 0xC4 {
                out.extend_from_slice(&jpeg[i..i + 2 + len]);
            }
            i += 2 + len;
        }
        out.extend_from_slice(&jpeg[i..]);
        out
    }

    fn near(px: &[u8], want: [u8; 3]) -> bool {
        px.iter().zip(want).all(|(&a, b)| a.abs_diff(b) <= 12)
    }

    #[test]
    fn mjpeg_frames_decode_to_rgb_and_split_side_by_side() {
        let (w, h) = (64u32, 16u32);
        let data = jpeg(&red_blue(64, 16), 64, 16);
        let mut rgb = vec![0; (w * h * 3) as usize];
        decode_mjpeg(&data, w, h, &mut rgb).unwrap();
        assert!(near(&rgb[..3], [220, 20, 30]) && near(&rgb[rgb.len() - 3..], [20, 30, 220]));
        // Side by side: each eye is one colour.
        let eye = eye_layout(w, h, PixelFormat::Rgb8, Stereo::SideBySide).unwrap();
        let mut eyes = vec![0; 2 * eye.eye_bytes()];
        copy_eyes(&rgb, (w * 3) as usize, &eye, 2, &mut eyes).unwrap();
        let (left, right) = eyes.split_at(eye.eye_bytes());
        assert!(left.chunks_exact(3).all(|p| near(p, [220, 20, 30])));
        assert!(right.chunks_exact(3).all(|p| near(p, [20, 30, 220])));
    }

    #[test]
    fn mjpeg_without_huffman_tables_decodes_like_the_full_jpeg() {
        let data = jpeg(&red_blue(32, 8), 32, 8);
        let bare = without_dht(&data);
        assert!(bare.len() < data.len() - 100, "the DHT segments were removed");
        let (mut a, mut b) = (vec![0; 32 * 8 * 3], vec![0; 32 * 8 * 3]);
        decode_mjpeg(&data, 32, 8, &mut a).unwrap();
        decode_mjpeg(&bare, 32, 8, &mut b).unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn bad_mjpeg_frames_are_errors_not_panics() {
        let data = jpeg(&red_blue(32, 8), 32, 8);
        let mut rgb = vec![0; 32 * 8 * 3];
        // Another size than negotiated.
        assert!(matches!(
            decode_mjpeg(&data, 16, 8, &mut vec![0; 16 * 8 * 3]),
            Err(MjpegError::Size { width: 32, .. })
        ));
        // A wrong output buffer.
        assert!(matches!(decode_mjpeg(&data, 32, 8, &mut [0; 10]), Err(MjpegError::Size { .. })));
        // Garbage and every truncation of the headers: an error, never a frame.
        assert!(decode_mjpeg(&[0xAB; 500], 32, 8, &mut rgb).is_err());
        assert!(decode_mjpeg(&[], 32, 8, &mut rgb).is_err());
        let scan = data.windows(2).position(|m| m == [0xFF, 0xDA]).unwrap();
        for len in 0..scan {
            assert!(decode_mjpeg(&data[..len], 32, 8, &mut rgb).is_err(), "prefix of {len} bytes");
        }
    }

    #[test]
    fn opening_a_missing_device_is_a_typed_error() {
        let config = V4l2Config { device: "/dev/comanip-no-such-video".into(), ..V4l2Config::default() };
        let e = V4l2Source::open(&config).unwrap_err();
        assert!(matches!(e, OpenError::DeviceMissing(_)), "{e}");
        assert!(e.to_string().contains("no such device"), "{e}");
        let bad = V4l2Config { buffers: 1, ..V4l2Config::default() };
        assert!(matches!(V4l2Source::open(&bad), Err(OpenError::Config(_))));
    }

    #[test]
    fn a_file_that_is_not_a_v4l2_device_is_a_typed_error() {
        let config = V4l2Config { device: "/dev/null".into(), ..V4l2Config::default() };
        let e = V4l2Source::open(&config).unwrap_err();
        assert!(matches!(e, OpenError::NotV4l2 { .. }), "{e}");
    }
}
