//! Ours' two changes under haze (session 25) on rendered tuning frames under smoke: the
//! coarse-scale fallback (`OursConfig::coarse_edgels_under_haze`, opt-in: four shafts the
//! default misses, no shaft returned, are found on the coarse scale's
//! silhouette edgels, and frames without the instrument still give nothing) and the contour
//! walk's floor scaled by the haze (`OursConfig::haze_walk_floor`, opt-in), and the checks
//! on what that walk's fainter edges may prove (`OursConfig::haze_walk_checked`, session 26,
//! opt-in).

mod support;

use comanip_bench::shaft::scenes::{ClutterLevel, FrameSpec, SeedSet, frame_spec};
use comanip_bench::shaft::{endoscope_config, intrinsics, render_frames};
use support::score_both;
use vision::ShaftDetector as _;
use vision::ours::{OursConfig, OursDetector};

#[test]
fn the_coarse_fallback_finds_hazy_shafts_and_nothing_on_empty_frames() {
    let level = ClutterLevel::Smoke;
    let spec = |family: &str, seed: u64| frame_spec(family, seed, &endoscope_config(SeedSet::Tuning, level)).unwrap();
    let found = [spec("mid", 1046), spec("mid", 1052), spec("mid", 1054), spec("along", 1042)];
    let empty: Vec<FrameSpec> = (1000..1006).map(|s| spec("retracted", s)).collect();
    let rule = OursConfig { coarse_edgels_under_haze: true, ..OursConfig::default() };
    let mut old = OursDetector::new(intrinsics(), OursConfig::default()).unwrap();
    let mut new = OursDetector::new(intrinsics(), rule).unwrap();
    let frames = render_frames(SeedSet::Tuning, level, &found, &|| {}).unwrap();
    for (i, f) in frames.iter().enumerate() {
        let (a, b) = score_both(&mut old, &mut new, f);
        assert_eq!(a.detections, 0, "frame {i}: the default returns a shaft ({a:?})");
        assert!(b.matched.is_some(), "frame {i}: the shaft not found on the coarse scale ({b:?})");
        assert_eq!(b.false_detections, 0, "frame {i}: a false detection on the coarse scale");
    }
    for f in &render_frames(SeedSet::Tuning, level, &empty, &|| {}).unwrap() {
        assert!(new.detect(&f.view().unwrap()).unwrap().is_empty(), "a detection without the instrument");
    }
}

/// Ours' contour walk with the floor scaled by the haze (`OursConfig::haze_walk_floor`,
/// session 25) on the tuning frame whose miss it was traced from (`smoke` mid 1034: the
/// shaft's span stopped short of the border, `verify: border`) and two more it finds under
/// smoke; the default misses all three.
#[test]
fn the_hazy_walk_reaches_the_border() {
    let level = ClutterLevel::Smoke;
    let spec = |seed: u64| frame_spec("mid", seed, &endoscope_config(SeedSet::Tuning, level)).unwrap();
    let specs = [spec(1034), spec(1000), spec(1046)];
    // The coarse fallback off on both sides (it finds mid 1046 too).
    let base = OursConfig { coarse_edgels_under_haze: false, ..OursConfig::default() };
    let rule = OursConfig { haze_walk_floor: true, ..base };
    let mut old = OursDetector::new(intrinsics(), base).unwrap();
    let mut new = OursDetector::new(intrinsics(), rule).unwrap();
    for (i, f) in render_frames(SeedSet::Tuning, level, &specs, &|| {}).unwrap().iter().enumerate() {
        // No second instrument at this level.
        assert!(!f.inst2_in_view);
        let (a, b) = score_both(&mut old, &mut new, f);
        assert!(a.matched.is_none(), "frame {i}: the default finds the shaft ({a:?})");
        assert!(b.matched.is_some(), "frame {i}: the shaft not found with the hazy walk ({b:?})");
        assert_eq!(b.false_detections, 0, "frame {i}: a false detection with the hazy walk");
    }
}

/// The hazy walk's checks (`OursConfig::haze_walk_checked`, session 26): under smoke with the
/// crossing instrument, the walk alone returns a pair of lines on neither instrument's
/// contours (walked on over the tissue, a soft shadow or past the point where they meet) on
/// three tuning frames; with the checks it returns none there. Under smoke alone the walk with
/// the checks still finds the shafts the default misses (the walk's own test frames).
#[test]
fn the_hazy_walk_checks_drop_walked_pairs_and_keep_the_shafts() {
    let walk = OursConfig { coarse_edgels_under_haze: false, haze_walk_floor: true, ..OursConfig::default() };
    let checked = OursConfig { haze_walk_checked: true, ..walk };
    let mut old = OursDetector::new(intrinsics(), walk).unwrap();
    let mut new = OursDetector::new(intrinsics(), checked).unwrap();
    let level = ClutterLevel::All;
    let spec = |family: &str, seed: u64| frame_spec(family, seed, &endoscope_config(SeedSet::Tuning, level)).unwrap();
    let wrong = [spec("mid", 1016), spec("far", 1021), spec("along", 1054)];
    for (i, f) in render_frames(SeedSet::Tuning, level, &wrong, &|| {}).unwrap().iter().enumerate() {
        let (a, b) = score_both(&mut old, &mut new, f);
        assert!(a.false_detections > 0, "frame {i}: the walk alone returns no wrong pair ({a:?})");
        assert_eq!(b.false_detections, 0, "frame {i}: a wrong pair with the checks ({b:?})");
    }
    let base = OursConfig { coarse_edgels_under_haze: false, ..OursConfig::default() };
    let mut plain = OursDetector::new(intrinsics(), base).unwrap();
    let level = ClutterLevel::Smoke;
    let spec = |family: &str, seed: u64| frame_spec(family, seed, &endoscope_config(SeedSet::Tuning, level)).unwrap();
    let found = [spec("mid", 1034), spec("mid", 1000), spec("along", 1042)];
    for (i, f) in render_frames(SeedSet::Tuning, level, &found, &|| {}).unwrap().iter().enumerate() {
        let (a, b) = score_both(&mut plain, &mut new, f);
        assert!(a.matched.is_none(), "frame {i}: the default finds the shaft ({a:?})");
        assert!(b.matched.is_some(), "frame {i}: the shaft not found with the checked walk ({b:?})");
        assert_eq!(b.false_detections, 0, "frame {i}: a false detection with the checked walk");
    }
}
