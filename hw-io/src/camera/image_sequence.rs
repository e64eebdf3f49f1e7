//! A camera source that plays a directory of PNG images listed in an index file
//! (`docs/frames.md`, "Image-sequence directories").
//!
//! The index, `frames.txt` in the directory by default, has one line per frame:
//!
//! ```text
//! # comanip frame index 1
//! # t_mid_ns exposure_ns left.png [right.png]
//! 1000000000 16000000 frame_000000_left.png frame_000000_right.png
//! 1033333333 16000000 frame_000001_left.png frame_000001_right.png
//! ```
//!
//! Times are nanoseconds (the exposure's mid time on the recording's clock); file names are
//! relative to the directory. Every line names the same number of eyes (1 or 2); every image has
//! the size and colour type of the first (8-bit grey, RGB or RGBA, RGBA delivered as RGB). Lines
//! starting with `#` and empty lines are skipped. `simrobot render` and `simrobot generate`
//! write such a directory.
//!
//! Two timings ([`Timing`]): `Recorded` delivers the recorded timestamps as fast as asked (an
//! offline pipeline beside a candump log of the same run); `Paced` plays the frames at their
//! recorded intervals and stamps them on this machine's `CLOCK_MONOTONIC` (a live-like source).

use std::fs;
use std::path::{Path, PathBuf};
use std::time::Duration;

use super::{CameraSource, FrameFormat, Next, SourceCounters};
use crate::frame::{FormatError, FrameMeta, ImageLayout, LayoutError, PixelFormat, monotonic_now_ns};

/// The index file's default name in the directory.
pub const DEFAULT_INDEX: &str = "frames.txt";

/// How frames are timed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Timing {
    /// The recorded timestamps, as fast as [`CameraSource::next_into`] is called.
    #[default]
    Recorded,
    /// At the recorded intervals (`next_into` sleeps until each frame is due, at most its
    /// timeout), stamped on `CLOCK_MONOTONIC`: the first frame at the time it is delivered.
    Paced,
}

/// Settings of an [`ImageSequence`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ImageSequenceConfig {
    /// The directory holding the images.
    pub dir: PathBuf,
    /// The index file, relative to `dir` unless absolute. Default [`DEFAULT_INDEX`].
    pub index: PathBuf,
    /// Recorded or paced timing.
    pub timing: Timing,
    /// Start again at the first frame after the last (paced timing keeps the intervals; the
    /// sequence number goes on).
    pub repeat: bool,
    /// Camera rig id written into the frames' metadata.
    pub camera_id: u32,
}

impl ImageSequenceConfig {
    /// The defaults for directory `dir`: its `frames.txt`, recorded timing, no repeat, camera 0.
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self {
            dir: dir.into(),
            index: PathBuf::from(DEFAULT_INDEX),
            timing: Timing::Recorded,
            repeat: false,
            camera_id: 0,
        }
    }
}

/// One frame of the index.
#[derive(Clone, Debug, PartialEq, Eq)]
struct Entry {
    t_mid_ns: u64,
    exposure_ns: u32,
    files: Vec<PathBuf>,
}

/// Why an [`ImageSequence`] could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum ImageSequenceOpenError {
    /// The index file cannot be read.
    #[error("cannot read the frame index {path}: {source}")]
    ReadIndex {
        /// The index file.
        path: PathBuf,
        /// The system's reason.
        source: std::io::Error,
    },
    /// A line of the index is malformed.
    #[error("{path}:{line}: {reason}")]
    Index {
        /// The index file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        reason: &'static str,
    },
    /// The index lists no frame.
    #[error("{0}: no frame listed")]
    Empty(PathBuf),
    /// The first image cannot be read; its format is the sequence's.
    #[error(transparent)]
    First(#[from] ImageSequenceError),
}

/// Why one frame could not be delivered. The frame is skipped and counted as dropped; the next
/// call goes on with the next frame.
#[derive(Debug, thiserror::Error)]
pub enum ImageSequenceError {
    /// The caller's buffer is not one frame.
    #[error("buffer of {got} bytes, one frame is {expected}")]
    Buffer {
        /// [`FrameFormat::payload_bytes`].
        expected: usize,
        /// The buffer's length.
        got: usize,
    },
    /// An image cannot be read or decoded.
    #[error("cannot decode {path}: {source}")]
    Decode {
        /// The image file.
        path: PathBuf,
        /// The decoder's reason.
        source: image::ImageError,
    },
    /// An image's size or colour type differs from the first image's.
    #[error("{path}: {found}, the sequence is {expected}")]
    Mismatch {
        /// The image file.
        path: PathBuf,
        /// Its size and format.
        found: String,
        /// The first image's.
        expected: String,
    },
    /// An image's colour type is not 8-bit grey, RGB or RGBA.
    #[error("{path}: colour type {color:?} is not 8-bit grey, RGB or RGBA")]
    ColorType {
        /// The image file.
        path: PathBuf,
        /// Its colour type.
        color: image::ColorType,
    },
    /// The image is too large or its layout is not usable.
    #[error("{path}: {source}")]
    Layout {
        /// The image file.
        path: PathBuf,
        /// Why.
        source: FormatError,
    },
}

/// A directory of PNG images played as a camera source (see the module's doc).
#[derive(Debug)]
pub struct ImageSequence {
    config: ImageSequenceConfig,
    entries: Vec<Entry>,
    format: FrameFormat,
    next: usize,
    sequence: u64,
    counters: SourceCounters,
    /// Paced timing: `CLOCK_MONOTONIC` of the first frame minus its recorded time, and the
    /// recorded span of one pass (for repeats), nanoseconds.
    clock_offset_ns: Option<i128>,
    pass: u64,
}

impl ImageSequence {
    /// Reads the index and the first image (whose size and colour type are the sequence's).
    pub fn open(config: ImageSequenceConfig) -> Result<Self, ImageSequenceOpenError> {
        let path = config.dir.join(&config.index);
        let text = fs::read_to_string(&path)
            .map_err(|source| ImageSequenceOpenError::ReadIndex { path: path.clone(), source })?;
        let entries = parse_index(&text, &path)?;
        let Some(first) = entries.first() else {
            return Err(ImageSequenceOpenError::Empty(path));
        };
        let first_path = config.dir.join(&first.files[0]);
        let image = decode(&first_path)?;
        let format = FrameFormat::new(first.files.len() as u32, layout_of(&image, &first_path)?)
            .map_err(|source| ImageSequenceError::Layout { path: first_path, source })?;
        Ok(Self {
            config,
            entries,
            format,
            next: 0,
            sequence: 0,
            counters: SourceCounters::default(),
            clock_offset_ns: None,
            pass: 0,
        })
    }

    /// Frames listed in the index.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// True when the index lists no frame (never: [`open`](Self::open) refuses it).
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    fn fill(&self, entry: &Entry, dst: &mut [u8]) -> Result<(), ImageSequenceError> {
        let eye_bytes = self.format.layout.eye_bytes();
        for (eye, file) in entry.files.iter().enumerate() {
            let path = self.config.dir.join(file);
            let image = decode(&path)?;
            let layout = layout_of(&image, &path)?;
            if layout != self.format.layout {
                return Err(ImageSequenceError::Mismatch {
                    path,
                    found: describe(&layout),
                    expected: describe(&self.format.layout),
                });
            }
            let out = &mut dst[eye * eye_bytes..(eye + 1) * eye_bytes];
            match image {
                image::DynamicImage::ImageLuma8(img) => out.copy_from_slice(img.as_raw()),
                image::DynamicImage::ImageRgb8(img) => out.copy_from_slice(img.as_raw()),
                image::DynamicImage::ImageRgba8(img) => {
                    for (o, i) in out.chunks_exact_mut(3).zip(img.as_raw().chunks_exact(4)) {
                        o.copy_from_slice(&i[..3]);
                    }
                }
                other => return Err(ImageSequenceError::ColorType { path, color: other.color() }),
            }
        }
        Ok(())
    }

    /// The recorded span of one pass plus one mean frame interval, nanoseconds (for repeats).
    fn pass_span_ns(&self) -> u64 {
        let first = self.entries.first().map_or(0, |e| e.t_mid_ns);
        let last = self.entries.last().map_or(0, |e| e.t_mid_ns);
        let n = self.entries.len() as u64;
        let span = last.saturating_sub(first);
        span + if n > 1 { span / (n - 1) } else { 33_333_333 }
    }
}

impl CameraSource for ImageSequence {
    type Error = ImageSequenceError;

    fn format(&self) -> FrameFormat {
        self.format
    }

    fn next_into(&mut self, dst: &mut [u8], timeout: Duration) -> Result<Next, ImageSequenceError> {
        let expected = self.format.payload_bytes();
        if dst.len() != expected {
            return Err(ImageSequenceError::Buffer { expected, got: dst.len() });
        }
        if self.next >= self.entries.len() {
            if !self.config.repeat {
                return Ok(Next::End);
            }
            self.next = 0;
            self.pass += 1;
        }
        let entry = &self.entries[self.next];
        let recorded_ns = entry.t_mid_ns.saturating_add(self.pass.saturating_mul(self.pass_span_ns()));
        let timestamp_ns = match self.config.timing {
            Timing::Recorded => recorded_ns,
            Timing::Paced => {
                let now = monotonic_now_ns();
                let offset = *self.clock_offset_ns.get_or_insert(i128::from(now) - i128::from(recorded_ns));
                let due = (i128::from(recorded_ns) + offset).max(0) as u64;
                if due > now {
                    let wait = Duration::from_nanos(due - now);
                    if wait > timeout {
                        std::thread::sleep(timeout);
                        return Ok(Next::Timeout);
                    }
                    std::thread::sleep(wait);
                }
                due
            }
        };
        let entry = entry.clone();
        self.next += 1;
        if let Err(e) = self.fill(&entry, dst) {
            self.counters.dropped += 1;
            self.sequence += 1; // the lost frame keeps its number: the gap shows downstream
            return Err(e);
        }
        let meta = FrameMeta {
            sequence: self.sequence,
            camera_id: self.config.camera_id,
            timestamp_ns,
            exposure_ns: entry.exposure_ns,
            eyes: self.format.eyes,
            layout: self.format.layout,
        };
        self.sequence += 1;
        self.counters.delivered += 1;
        Ok(Next::Frame(meta))
    }

    fn counters(&self) -> SourceCounters {
        self.counters
    }
}

fn parse_index(text: &str, path: &Path) -> Result<Vec<Entry>, ImageSequenceOpenError> {
    let err = |line: usize, reason: &'static str| ImageSequenceOpenError::Index { path: path.to_owned(), line, reason };
    let mut entries: Vec<Entry> = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let fields: Vec<&str> = line.split_whitespace().collect();
        if !(3..=4).contains(&fields.len()) {
            return Err(err(i + 1, "expected `t_mid_ns exposure_ns left.png [right.png]`"));
        }
        let t_mid_ns = fields[0].parse().map_err(|_| err(i + 1, "t_mid_ns is not a non-negative integer"))?;
        let exposure_ns = fields[1].parse().map_err(|_| err(i + 1, "exposure_ns is not an integer in 0..2^32"))?;
        let files: Vec<PathBuf> = fields[2..].iter().map(PathBuf::from).collect();
        if let Some(prev) = entries.last() {
            if prev.files.len() != files.len() {
                return Err(err(i + 1, "every line must name the same number of eyes"));
            }
            if t_mid_ns <= prev.t_mid_ns {
                return Err(err(i + 1, "timestamps must increase"));
            }
        }
        entries.push(Entry { t_mid_ns, exposure_ns, files });
    }
    Ok(entries)
}

fn decode(path: &Path) -> Result<image::DynamicImage, ImageSequenceError> {
    image::ImageReader::open(path)
        .map_err(|e| ImageSequenceError::Decode { path: path.to_owned(), source: image::ImageError::IoError(e) })?
        .with_guessed_format()
        .map_err(|e| ImageSequenceError::Decode { path: path.to_owned(), source: image::ImageError::IoError(e) })?
        .decode()
        .map_err(|source| ImageSequenceError::Decode { path: path.to_owned(), source })
}

fn layout_of(image: &image::DynamicImage, path: &Path) -> Result<ImageLayout, ImageSequenceError> {
    let format = match image {
        image::DynamicImage::ImageLuma8(_) => PixelFormat::Gray8,
        image::DynamicImage::ImageRgb8(_) | image::DynamicImage::ImageRgba8(_) => PixelFormat::Rgb8,
        other => return Err(ImageSequenceError::ColorType { path: path.to_owned(), color: other.color() }),
    };
    ImageLayout::packed(image.width(), image.height(), format)
        .map_err(|e: LayoutError| ImageSequenceError::Layout { path: path.to_owned(), source: FormatError::Layout(e) })
}

fn describe(l: &ImageLayout) -> String {
    format!("{}×{} {}", l.width, l.height, l.format)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn index_lines_are_parsed_and_malformed_lines_refused_with_their_number() {
        let p = Path::new("frames.txt");
        let ok = parse_index("# header\n\n10 5 a.png b.png\n20 5 c.png d.png\n", p).unwrap();
        assert_eq!(ok.len(), 2);
        assert_eq!(ok[1].t_mid_ns, 20);
        assert_eq!(ok[1].files, vec![PathBuf::from("c.png"), PathBuf::from("d.png")]);
        let line_of = |text: &str| match parse_index(text, p) {
            Err(ImageSequenceOpenError::Index { line, .. }) => line,
            other => panic!("{other:?}"),
        };
        assert_eq!(line_of("10 5\n"), 1);
        assert_eq!(line_of("10 5 a b c\n"), 1);
        assert_eq!(line_of("x 5 a\n"), 1);
        assert_eq!(line_of("10 -5 a\n"), 1);
        assert_eq!(line_of("10 5 a\n20 5 a b\n"), 2);
        assert_eq!(line_of("10 5 a\n# c\n10 5 b\n"), 3);
    }
}
