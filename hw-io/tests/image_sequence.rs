//! Image-sequence directories as a camera source: frames in index order with their recorded
//! timestamps, stereo eyes in order, a corrupt image skipped and counted, a mismatched image
//! refused, paced timing on CLOCK_MONOTONIC, repeat.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a panic is a failed test")]

use std::path::Path;
use std::time::Duration;

use hw_io::camera::image_sequence::{
    ImageSequence, ImageSequenceConfig, ImageSequenceError, ImageSequenceOpenError, Timing,
};
use hw_io::camera::{CameraSource, Next};
use hw_io::frame::PixelFormat;

fn rgb(n: u8, eye: u8) -> image::RgbImage {
    image::RgbImage::from_fn(8, 6, |x, y| image::Rgb([n, eye, (x + 8 * y) as u8]))
}

/// Writes `frames` stereo frames at 30 fps from t = 1 s, and the index.
fn write_dir(dir: &Path, frames: u8) {
    let mut index = String::from("# comanip frame index 1\n");
    for n in 0..frames {
        for (eye, name) in [(0u8, "left"), (1, "right")] {
            rgb(n, eye).save(dir.join(format!("f{n}_{name}.png"))).unwrap();
        }
        index += &format!("{} 16000000 f{n}_left.png f{n}_right.png\n", 1_000_000_000 + u64::from(n) * 33_333_333);
    }
    std::fs::write(dir.join("frames.txt"), index).unwrap();
}

#[test]
fn frames_come_in_index_order_with_their_recorded_timestamps() {
    let dir = tempfile::tempdir().unwrap();
    write_dir(dir.path(), 5);
    let mut src = ImageSequence::open(ImageSequenceConfig::new(dir.path())).unwrap();
    let f = src.format();
    assert_eq!((f.eyes, f.layout.width, f.layout.height, f.layout.format), (2, 8, 6, PixelFormat::Rgb8));
    let mut buf = vec![0u8; f.payload_bytes()];
    for n in 0..5u8 {
        let Next::Frame(m) = src.next_into(&mut buf, Duration::ZERO).unwrap() else { panic!() };
        assert_eq!(
            (m.sequence, m.timestamp_ns, m.exposure_ns),
            (u64::from(n), 1_000_000_000 + u64::from(n) * 33_333_333, 16_000_000)
        );
        let half = buf.len() / 2;
        assert_eq!(&buf[..half], rgb(n, 0).as_raw().as_slice());
        assert_eq!(&buf[half..], rgb(n, 1).as_raw().as_slice());
    }
    assert_eq!(src.next_into(&mut buf, Duration::ZERO).unwrap(), Next::End);
    assert_eq!(src.counters().delivered, 5);
    // A wrong buffer is refused.
    assert!(matches!(src.next_into(&mut [0u8; 3], Duration::ZERO), Err(ImageSequenceError::Buffer { got: 3, .. })));
}

#[test]
fn a_corrupt_image_is_skipped_counted_and_leaves_a_sequence_gap() {
    let dir = tempfile::tempdir().unwrap();
    write_dir(dir.path(), 4);
    std::fs::write(dir.path().join("f1_right.png"), b"not a png").unwrap();
    image::RgbImage::new(4, 4).save(dir.path().join("f2_left.png")).unwrap();
    let mut src = ImageSequence::open(ImageSequenceConfig::new(dir.path())).unwrap();
    let mut buf = vec![0u8; src.format().payload_bytes()];
    assert!(matches!(src.next_into(&mut buf, Duration::ZERO), Ok(Next::Frame(m)) if m.sequence == 0));
    assert!(matches!(src.next_into(&mut buf, Duration::ZERO), Err(ImageSequenceError::Decode { .. })));
    assert!(matches!(src.next_into(&mut buf, Duration::ZERO), Err(ImageSequenceError::Mismatch { .. })));
    assert!(matches!(src.next_into(&mut buf, Duration::ZERO), Ok(Next::Frame(m)) if m.sequence == 3));
    assert_eq!((src.counters().delivered, src.counters().dropped), (2, 2));
}

#[test]
fn malformed_or_missing_indexes_are_typed_errors() {
    let dir = tempfile::tempdir().unwrap();
    assert!(matches!(
        ImageSequence::open(ImageSequenceConfig::new(dir.path())),
        Err(ImageSequenceOpenError::ReadIndex { .. })
    ));
    std::fs::write(dir.path().join("frames.txt"), "# nothing\n").unwrap();
    assert!(matches!(ImageSequence::open(ImageSequenceConfig::new(dir.path())), Err(ImageSequenceOpenError::Empty(_))));
    std::fs::write(dir.path().join("frames.txt"), "1 2 missing.png\n").unwrap();
    let e = ImageSequence::open(ImageSequenceConfig::new(dir.path())).unwrap_err();
    assert!(matches!(e, ImageSequenceOpenError::First(ImageSequenceError::Decode { .. })), "{e}");
    assert!(e.to_string().contains("missing.png"), "{e}");
}

#[test]
fn paced_timing_keeps_the_recorded_intervals_on_the_monotonic_clock_and_repeats() {
    let dir = tempfile::tempdir().unwrap();
    write_dir(dir.path(), 3);
    let mut cfg = ImageSequenceConfig::new(dir.path());
    cfg.timing = Timing::Paced;
    cfg.repeat = true;
    let mut src = ImageSequence::open(cfg).unwrap();
    let mut buf = vec![0u8; src.format().payload_bytes()];
    let now = || {
        let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
        // SAFETY: valid timespec pointer.
        unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
        ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
    };
    let before = now();
    let mut stamps = Vec::new();
    while stamps.len() < 7 {
        if let Next::Frame(m) = src.next_into(&mut buf, Duration::from_secs(1)).unwrap() {
            assert!(now() >= m.timestamp_ns, "a frame is never delivered before its time");
            stamps.push(m.timestamp_ns);
        }
    }
    assert!(stamps[0] >= before && stamps[0] <= now());
    // Recorded intervals: 33 333 333 ns within a pass, one mean interval across passes.
    for w in stamps.windows(2) {
        assert_eq!(w[1] - w[0], 33_333_333, "{stamps:?}");
    }
    // A short timeout returns Timeout instead of sleeping past it.
    // (The next frame is 33 ms away unless this thread was descheduled that long; ten tries.)
    let timed_out = (0..10).any(|_| src.next_into(&mut buf, Duration::from_millis(1)).unwrap() == Next::Timeout);
    assert!(timed_out);
}
