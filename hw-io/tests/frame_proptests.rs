//! The new input boundaries of the image half never panic on arbitrary input: a frame header
//! with any field values (a corrupt or newer writer), an image-sequence index of any text,
//! a stereo camera_info pair of any text. Each gives a typed error or a value whose invariants
//! hold.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a panic is a failed test")]

use hw_io::camera::image_sequence::{ImageSequence, ImageSequenceConfig};
use hw_io::frame::MAX_DIMENSION;
use hw_io::ipc::FrameHeader;
use proptest::prelude::*;

fn header() -> impl Strategy<Value = FrameHeader> {
    (
        (0u32..3, any::<u32>(), any::<u64>(), any::<u64>(), any::<u64>()),
        (prop_oneof![0u32..4, any::<u32>()], prop_oneof![0u32..5000, any::<u32>()]),
        (prop_oneof![0u32..5000, any::<u32>()], prop_oneof![0u32..20000, any::<u32>()], 0u32..6),
        (any::<u64>(), any::<u64>(), any::<u32>()),
    )
        .prop_map(
            |(
                (version, camera_id, sequence, run_id, timestamp_ns),
                (eyes, width),
                (height, stride, fmt),
                (pb, dropped, exp),
            )| {
                FrameHeader {
                    version,
                    camera_id,
                    sequence,
                    run_id,
                    timestamp_ns,
                    exposure_ns: exp,
                    eyes,
                    width,
                    height,
                    stride,
                    pixel_format: fmt,
                    payload_bytes: pb,
                    source_dropped: dropped,
                }
            },
        )
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]

    #[test]
    fn any_frame_header_is_refused_or_consistent(h in header(), len in prop_oneof![0usize..10_000_000, any::<usize>()]) {
        // A header that describes exactly `len` bytes sometimes: make the length agree.
        for payload_len in [len, h.payload_bytes.min(usize::MAX as u64) as usize] {
            if let Ok(m) = h.meta(payload_len) {
                prop_assert!((1..=2).contains(&m.eyes));
                prop_assert!(m.layout.width >= 1 && m.layout.width <= MAX_DIMENSION);
                prop_assert!(m.layout.height >= 1 && m.layout.height <= MAX_DIMENSION);
                prop_assert!(m.layout.stride as usize >= m.layout.row_bytes());
                prop_assert_eq!(m.payload_bytes(), payload_len);
                prop_assert_eq!(m.payload_bytes() as u64, h.payload_bytes);
            }
        }
    }

    #[test]
    fn any_stereo_camera_info_text_is_refused_or_read(left in ".{0,300}", right in ".{0,300}") {
        if let Ok(s) = hw_io::calib_files::parse_stereo_camera_info(&left, &right) {
            prop_assert!(s.baseline_m() > 0.0 && s.baseline_m().is_finite());
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

    #[test]
    fn any_frame_index_is_refused_or_read(text in "([0-9 ]{0,30}[a-z.]{0,8}\n|#.{0,10}\n|.{0,20}\n){0,6}") {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("frames.txt"), &text).unwrap();
        image::GrayImage::new(2, 2).save(dir.path().join("a.png")).unwrap();
        // Either a typed error (malformed index, missing or undecodable image) or a sequence.
        if let Ok(s) = ImageSequence::open(ImageSequenceConfig::new(dir.path())) {
            prop_assert!(!s.is_empty());
        }
    }
}
