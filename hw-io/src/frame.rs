//! Camera frames as they cross a boundary: pixel formats, image layouts and the metadata of one
//! (stereo) frame. No dependency, always built: the camera sources (V4L2, image-sequence
//! directories, the simulator), the shared-memory frame transport and the processes that read
//! frames all speak these types.
//!
//! A frame is one exposure of a rig of `eyes` cameras (1: mono, 2: stereo, left first), all of
//! the same [`ImageLayout`]; its pixels are the eyes' images one after the other, each
//! `stride × height` bytes, rows top to bottom.
//!
//! Units: pixels; bytes; times in nanoseconds of `CLOCK_MONOTONIC`, the clock V4L2 drivers
//! stamp frames with and the daemons' cycle clock. The CAN receive timestamps
//! (`hw_io::can::TimedFrame::unix_time_us`, the kernel's `SO_TIMESTAMPNS`) are on
//! `CLOCK_REALTIME` instead: pair a frame with encoder readings through
//! [`realtime_minus_monotonic_ns`], sampled near the frame's time (the two clocks differ by a
//! constant unless the wall clock is stepped or slewed, which a robot PC should not do while it
//! runs).

use core::fmt;

/// Largest width or height accepted, pixels (a corrupt header must not make a reader allocate
/// gigabytes).
pub const MAX_DIMENSION: u32 = 8192;

/// Largest size of one eye's image, bytes (64 MiB).
pub const MAX_EYE_BYTES: usize = 64 << 20;

/// How the bytes of one pixel are laid out. On the wire (frame headers) it is the `u32` of the
/// variant.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u32)]
pub enum PixelFormat {
    /// 8-bit grey, 1 byte per pixel. Wire value 1.
    Gray8 = 1,
    /// 8-bit sRGB, bytes R, G, B, 3 bytes per pixel. Wire value 2.
    Rgb8 = 2,
    /// YUV 4:2:2 as V4L2's `YUYV` (Y0 U Y1 V per two pixels), 2 bytes per pixel; the width is
    /// even. Wire value 3.
    Yuyv = 3,
}

/// A pixel-format code that is not a [`PixelFormat`] (a newer or corrupt writer).
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("unknown pixel format {0} (known: 1 gray8, 2 rgb8, 3 yuyv)")]
pub struct UnknownPixelFormat(pub u32);

impl PixelFormat {
    /// Bytes per pixel.
    pub const fn bytes_per_pixel(self) -> u32 {
        match self {
            Self::Gray8 => 1,
            Self::Rgb8 => 3,
            Self::Yuyv => 2,
        }
    }

    /// The wire code.
    pub const fn code(self) -> u32 {
        self as u32
    }

    /// The format of a wire code.
    pub const fn from_code(code: u32) -> Result<Self, UnknownPixelFormat> {
        match code {
            1 => Ok(Self::Gray8),
            2 => Ok(Self::Rgb8),
            3 => Ok(Self::Yuyv),
            other => Err(UnknownPixelFormat(other)),
        }
    }

    /// Lower-case name (`gray8`, `rgb8`, `yuyv`).
    pub const fn name(self) -> &'static str {
        match self {
            Self::Gray8 => "gray8",
            Self::Rgb8 => "rgb8",
            Self::Yuyv => "yuyv",
        }
    }
}

impl fmt::Display for PixelFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Why an [`ImageLayout`] is not usable.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum LayoutError {
    /// Width or height is zero or above [`MAX_DIMENSION`].
    #[error("image size {width}×{height} pixels outside 1..={MAX_DIMENSION}")]
    Size {
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
    },
    /// The row stride is shorter than a row's pixels.
    #[error("row stride {stride} bytes is shorter than a row ({min} bytes)")]
    Stride {
        /// Stride, bytes.
        stride: u32,
        /// Bytes of one row's pixels.
        min: u32,
    },
    /// `YUYV` needs an even width.
    #[error("YUYV needs an even width, got {0} pixels")]
    OddYuyvWidth(u32),
    /// One eye's image is above [`MAX_EYE_BYTES`].
    #[error("one image is {0} bytes, above the {MAX_EYE_BYTES}-byte limit")]
    TooLarge(usize),
}

/// The layout of one eye's image.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ImageLayout {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Bytes from one row's start to the next's (≥ `width × bytes_per_pixel`).
    pub stride: u32,
    /// Pixel format.
    pub format: PixelFormat,
}

impl ImageLayout {
    /// A layout without row padding (`stride = width × bytes_per_pixel`), checked.
    pub fn packed(width: u32, height: u32, format: PixelFormat) -> Result<Self, LayoutError> {
        let stride = width.saturating_mul(format.bytes_per_pixel());
        let layout = Self { width, height, stride, format };
        layout.validate()?;
        Ok(layout)
    }

    /// Checks the size limits, the stride and the format's constraints.
    pub fn validate(&self) -> Result<(), LayoutError> {
        if self.width == 0 || self.height == 0 || self.width > MAX_DIMENSION || self.height > MAX_DIMENSION {
            return Err(LayoutError::Size { width: self.width, height: self.height });
        }
        let min = self.width * self.format.bytes_per_pixel();
        if self.stride < min {
            return Err(LayoutError::Stride { stride: self.stride, min });
        }
        if self.format == PixelFormat::Yuyv && !self.width.is_multiple_of(2) {
            return Err(LayoutError::OddYuyvWidth(self.width));
        }
        let bytes = self.eye_bytes();
        if bytes > MAX_EYE_BYTES {
            return Err(LayoutError::TooLarge(bytes));
        }
        Ok(())
    }

    /// Bytes of one row's pixels (without padding).
    pub const fn row_bytes(&self) -> usize {
        self.width as usize * self.format.bytes_per_pixel() as usize
    }

    /// Bytes of one eye's image: `stride × height`.
    pub const fn eye_bytes(&self) -> usize {
        self.stride as usize * self.height as usize
    }
}

/// What a camera rig delivers, fixed for a source's life: the number of eyes and each eye's
/// layout.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct FrameFormat {
    /// 1 (mono) or 2 (stereo, left first).
    pub eyes: u32,
    /// Each eye's image layout.
    pub layout: ImageLayout,
}

/// Why a [`FrameFormat`] is not usable.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum FormatError {
    /// Not 1 or 2 eyes.
    #[error("{0} eyes: a rig has 1 (mono) or 2 (stereo)")]
    Eyes(u32),
    /// The layout of each eye.
    #[error(transparent)]
    Layout(#[from] LayoutError),
}

impl FrameFormat {
    /// A checked format.
    pub fn new(eyes: u32, layout: ImageLayout) -> Result<Self, FormatError> {
        let format = Self { eyes, layout };
        format.validate()?;
        Ok(format)
    }

    /// Checks the number of eyes and the layout.
    pub fn validate(&self) -> Result<(), FormatError> {
        if !(1..=2).contains(&self.eyes) {
            return Err(FormatError::Eyes(self.eyes));
        }
        self.layout.validate()?;
        Ok(())
    }

    /// Bytes of one frame's pixels: `eyes × stride × height`.
    pub const fn payload_bytes(&self) -> usize {
        self.eyes as usize * self.layout.eye_bytes()
    }
}

/// The metadata of one frame (one exposure of every eye of the rig).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameMeta {
    /// 0 for a source's first frame, +1 per frame it delivers (a gap means frames were lost
    /// before this point and are counted by the source).
    pub sequence: u64,
    /// Which camera rig (configured; 0 for the first endoscope).
    pub camera_id: u32,
    /// Mid time of the exposure, nanoseconds of `CLOCK_MONOTONIC`.
    pub timestamp_ns: u64,
    /// Exposure time, nanoseconds (0 when unknown).
    pub exposure_ns: u32,
    /// Number of eyes, 1 (mono) or 2 (stereo, left first).
    pub eyes: u32,
    /// Each eye's image layout.
    pub layout: ImageLayout,
}

impl FrameMeta {
    /// The frame's format (eyes and layout).
    pub const fn format(&self) -> FrameFormat {
        FrameFormat { eyes: self.eyes, layout: self.layout }
    }

    /// Bytes of the frame's pixels: `eyes × stride × height`.
    pub const fn payload_bytes(&self) -> usize {
        self.eyes as usize * self.layout.eye_bytes()
    }
}

/// `CLOCK_REALTIME − CLOCK_MONOTONIC` now, nanoseconds: add it to a frame's `CLOCK_MONOTONIC`
/// timestamp to compare it with CAN receive timestamps (Unix time). Read as the middle of two
/// `CLOCK_MONOTONIC` reads around one `CLOCK_REALTIME` read (error below a microsecond).
pub fn realtime_minus_monotonic_ns() -> i128 {
    let a = i128::from(monotonic_now_ns());
    let real = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos() as i128);
    let b = i128::from(monotonic_now_ns());
    real - (a + b) / 2
}

/// `CLOCK_MONOTONIC` now, nanoseconds since an arbitrary origin (boot). The one clock read of
/// the workspace: fulcrumd's loop (`controller::rt`), frame timestamps, the simulated camera.
///
/// **Real-time (1 kHz loop):** allocation-free, no system call (vDSO).
pub fn monotonic_now_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: `ts` is a valid, writable timespec. With CLOCK_MONOTONIC and a valid pointer,
    // clock_gettime cannot fail on Linux; 0 is returned if it ever did.
    if unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) } != 0 {
        return 0;
    }
    (ts.tv_sec.max(0) as u64).saturating_mul(1_000_000_000).saturating_add(ts.tv_nsec.max(0) as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_clock_offset_matches_the_two_clocks_read_directly() {
        let off = realtime_minus_monotonic_ns();
        let mono = i128::from(monotonic_now_ns());
        let real = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos() as i128;
        // Read a few microseconds apart: within 50 ms even on a loaded machine.
        assert!((real - mono - off).abs() < 50_000_000, "{off}");
        // Unix time is decades past the boot time.
        assert!(off > 1_500_000_000 * 1_000_000_000i128);
    }

    #[test]
    fn pixel_format_codes_round_trip_and_unknown_codes_are_refused() {
        for f in [PixelFormat::Gray8, PixelFormat::Rgb8, PixelFormat::Yuyv] {
            assert_eq!(PixelFormat::from_code(f.code()), Ok(f));
        }
        assert_eq!(PixelFormat::from_code(0), Err(UnknownPixelFormat(0)));
        assert_eq!(PixelFormat::from_code(4), Err(UnknownPixelFormat(4)));
    }

    #[test]
    fn layouts_are_checked() {
        let l = ImageLayout::packed(640, 480, PixelFormat::Rgb8).unwrap();
        assert_eq!((l.stride, l.eye_bytes(), l.row_bytes()), (1920, 921_600, 1920));
        assert!(matches!(ImageLayout::packed(0, 480, PixelFormat::Rgb8), Err(LayoutError::Size { .. })));
        assert!(matches!(ImageLayout::packed(9000, 480, PixelFormat::Gray8), Err(LayoutError::Size { .. })));
        assert_eq!(ImageLayout::packed(641, 480, PixelFormat::Yuyv), Err(LayoutError::OddYuyvWidth(641)));
        let short = ImageLayout { width: 640, height: 480, stride: 1000, format: PixelFormat::Rgb8 };
        assert_eq!(short.validate(), Err(LayoutError::Stride { stride: 1000, min: 1920 }));
        let huge = ImageLayout { width: 8192, height: 8192, stride: 8192 * 3, format: PixelFormat::Rgb8 };
        assert!(matches!(huge.validate(), Err(LayoutError::TooLarge(_))));
        let meta = FrameMeta { sequence: 0, camera_id: 0, timestamp_ns: 1, exposure_ns: 0, eyes: 2, layout: l };
        assert_eq!(meta.payload_bytes(), 2 * 921_600);
        assert_eq!(meta.format().payload_bytes(), 2 * 921_600);
        assert_eq!(FrameFormat::new(3, l), Err(FormatError::Eyes(3)));
        assert_eq!(FrameFormat::new(0, l), Err(FormatError::Eyes(0)));
        assert!(matches!(FrameFormat::new(2, short), Err(FormatError::Layout(LayoutError::Stride { .. }))));
    }
}
