//! Ours' gap bridging (`OursConfig::bridge_min_both`, session 24) on rendered tuning frames:
//! a wrong pair (two edges of the wrist and jaws, its visible span bridged over the shaft
//! between them and an edge near the border) that the default returns is no longer
//! returned with the rule, and the true shafts of those frames (two of them of the `along`
//! family: a shaft close to the lens along an image border) still are.

mod support;

use comanip_bench::shaft::scenes::{ClutterLevel, SeedSet, frame_spec};
use comanip_bench::shaft::{endoscope_config, intrinsics, render_frames};
use support::score_both;
use vision::ours::{OursConfig, OursDetector};

#[test]
fn the_bridging_rule_drops_the_jaws_pair_and_keeps_the_shafts() {
    // The tuning frames of a family and seed at `clean` (no noise: the same pixels on every
    // machine).
    let spec = |family: &str, seed: u64| {
        frame_spec(family, seed, &endoscope_config(SeedSet::Tuning, ClutterLevel::Clean)).unwrap()
    };
    let specs = [spec("blur", 1057), spec("along", 1001), spec("along", 1002)];
    let frames = render_frames(SeedSet::Tuning, ClutterLevel::Clean, &specs, &|| {}).unwrap();
    let rule = OursConfig { bridge_min_both: 5, ..OursConfig::default() };
    let mut old = OursDetector::new(intrinsics(), OursConfig::default()).unwrap();
    let mut new = OursDetector::new(intrinsics(), rule).unwrap();
    for (i, f) in frames.iter().enumerate() {
        let (a, b) = score_both(&mut old, &mut new, f);
        // The shaft is found with and without the rule.
        assert!(a.matched.is_some() && b.matched.is_some(), "frame {i}: the shaft lost ({a:?} -> {b:?})");
        assert_eq!(b.false_detections, 0, "frame {i}: a false detection with the rule");
        if i == 0 {
            // The default returns the wrong pair as a second detection (19° off).
            assert_eq!(a.false_detections, 1, "frame 0: the default's wrong pair is gone ({a:?})");
        }
    }
}
