//! The shaft benchmark end to end on a handful of rendered frames, with stand-in detectors:
//! an oracle that returns the true axis perturbed by a known offset, a detector that never
//! finds anything, and one that always returns the same wrong line (and, when OpenCV is
//! installed, the peers with a stand-in pairing).

use comanip_bench::shaft::scenes::{ClutterLevel, FAMILIES, SeedSet, frame_specs};
use comanip_bench::shaft::{self, PeerOptions, PeerStatus, ShaftOptions, endoscope_config, peers, render_frames};
use estimator::calib::Intrinsics;
use vision::shaft::ImageLine;
use vision::{DetectError, RgbView, Segment, ShaftDetection, ShaftDetector};

/// Returns, frame after frame (in the benchmark's order, cycling over the levels; each frame
/// is asked [`shaft::TIMING_REPEATS`] times), the
/// true axis of instrument 1 moved by `shift_px` along its normal, or nothing without one.
struct Oracle {
    k: Intrinsics,
    truths: Vec<Option<[f64; 3]>>,
    next: usize,
    shift_px: f64,
}

/// A detection along `abc` (normalised, `a² + b² = 1`).
fn detection(abc: [f64; 3]) -> ShaftDetection {
    let c = ImageLine { abc };
    ShaftDetection { centreline: c, contours: [c, c], ends_px: [[0.0; 2]; 2], confidence: 1.0 }
}

impl ShaftDetector for Oracle {
    fn name(&self) -> &'static str {
        "oracle"
    }
    fn intrinsics(&self) -> &Intrinsics {
        &self.k
    }
    fn detect(&mut self, image: &RgbView<'_>) -> Result<Vec<ShaftDetection>, DetectError> {
        vision::detect::check_size(&self.k, image)?;
        // The harness times each frame TIMING_REPEATS times in a row.
        let t = self.truths[(self.next / shaft::TIMING_REPEATS) % self.truths.len()];
        self.next += 1;
        Ok(t.map(|[a, b, c]| detection([a, b, c - self.shift_px])).into_iter().collect())
    }
}

struct Blind(Intrinsics);

impl ShaftDetector for Blind {
    fn name(&self) -> &'static str {
        "blind"
    }
    fn intrinsics(&self) -> &Intrinsics {
        &self.0
    }
    fn detect(&mut self, _: &RgbView<'_>) -> Result<Vec<ShaftDetection>, DetectError> {
        Ok(vec![])
    }
}

/// Always the line v = 5 (no instrument lies along the top border in these frames).
struct Stubborn(Intrinsics);

impl ShaftDetector for Stubborn {
    fn name(&self) -> &'static str {
        "stubborn"
    }
    fn intrinsics(&self) -> &Intrinsics {
        &self.0
    }
    fn detect(&mut self, _: &RgbView<'_>) -> Result<Vec<ShaftDetection>, DetectError> {
        Ok(vec![detection([0.0, 1.0, -5.0])])
    }
}

/// A stand-in for the paper's pairing: the middle line of the two longest segments.
fn longest_two(k: &Intrinsics, segs: &[Segment]) -> Option<ShaftDetection> {
    let mut s: Vec<&Segment> = segs.iter().collect();
    s.sort_by(|a, b| b.length_px().total_cmp(&a.length_px()));
    let (a, b) = (s.first()?, s.get(1)?);
    let la = vision::detect::undistorted_line(k, a.a, a.b).ok()?;
    let lb = vision::detect::undistorted_line(k, b.a, b.b).ok()?;
    let mid = [0.25 * (a.a[0] + a.b[0] + b.a[0] + b.b[0]), 0.25 * (a.a[1] + a.b[1] + b.a[1] + b.b[1])];
    let c = vision::shaft::middle_line(&la, &lb, mid).ok()?;
    Some(ShaftDetection { centreline: c, contours: [la, lb], ends_px: [a.a, a.b], confidence: 0.5 })
}

#[test]
fn the_benchmark_scores_stand_in_detectors_as_they_deserve() {
    let k = shaft::intrinsics();
    let set = SeedSet::Report;
    let specs = frame_specs(set, 1, &endoscope_config(set, ClutterLevel::Clean)).unwrap();
    // The report set's families: every one but the tuning-only blur and along families.
    let n_fam = set.families().len();
    assert_eq!(n_fam, FAMILIES.len() - 2);
    assert_eq!(specs.len(), n_fam);
    let frames = render_frames(set, ClutterLevel::Clean, &specs, &|| {}).unwrap();
    let truths: Vec<Option<[f64; 3]>> = frames.iter().map(|f| f.inst1.map(|t| t.line)).collect();
    // The instrument-free families have no instrument in view; the others mostly do.
    for f in &frames {
        let fam = &FAMILIES[f.spec.family];
        let in_view = !matches!(fam.key, "retracted" | "aside");
        if !in_view {
            assert!(!f.inst1_in_view, "{}: instrument in view", fam.key);
        }
    }
    let eligible = frames.iter().filter(|f| f.inst1.is_some_and(|t| t.eligible())).count();
    assert!(eligible >= 4, "only {eligible} eligible frames");

    let levels = vec![ClutterLevel::Clean, ClutterLevel::Second];
    let mut detectors: Vec<Box<dyn ShaftDetector>> =
        vec![Box::new(Oracle { k, truths, next: 0, shift_px: 0.7 }), Box::new(Blind(k)), Box::new(Stubborn(k))];
    let work = tempfile::tempdir().unwrap();
    let python = "python3".to_owned();
    let opts = ShaftOptions {
        set,
        frames_per_family: 1,
        levels: levels.clone(),
        peers: Some(PeerOptions {
            python: python.clone(),
            script: peers::default_script(),
            work_dir: work.path().into(),
        }),
    };
    let pairing = |s: &[Segment]| longest_two(&k, s);
    let calls = std::sync::atomic::AtomicU64::new(0);
    let report = shaft::run(&opts, &mut detectors, Some(&pairing), &|_, total| {
        calls.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        assert_eq!(total, (2 * 2 * n_fam) as u64);
    })
    .unwrap();
    assert_eq!(calls.into_inner(), (2 * 2 * n_fam) as u64);
    assert_eq!(report.records.len(), 2 * n_fam);
    let with_peers = peers::unavailable(&python).is_none();
    assert_eq!(report.detectors.len(), if with_peers { 5 } else { 3 });
    match &report.peers {
        PeerStatus::Ran { opencv_version, .. } => assert!(with_peers && !opencv_version.is_empty()),
        PeerStatus::Skipped(why) => assert!(!with_peers && !why.is_empty()),
        PeerStatus::NotRequested => panic!("peers were requested"),
    }

    for &level in &levels {
        let oracle = report.level_cell(level, 0);
        let blind = report.level_cell(level, 1);
        let stubborn = report.level_cell(level, 2);
        assert_eq!(oracle.frames, n_fam);
        // The same frames are eligible at both levels unless the second instrument hides
        // some of the first.
        assert!(oracle.eligible <= eligible && oracle.eligible + 2 >= eligible, "{level:?}");
        // The oracle finds every eligible instrument, 0.7 px off, at no angle.
        assert_eq!(oracle.detected, oracle.eligible);
        assert!((oracle.offset_px[0].unwrap() - 0.7).abs() < 1e-6);
        assert!((oracle.offset_max_px[1].unwrap() - 0.7).abs() < 1e-6);
        assert!(oracle.angle_deg[1].unwrap() < 1e-6);
        assert_eq!(oracle.false_detections, 0);
        assert_eq!(oracle.free_frames, 2);
        // Blind: nothing found, nothing false.
        assert_eq!((blind.detected, blind.false_detections), (0, 0));
        assert_eq!(blind.rate(), Some(0.0));
        // Stubborn: one false detection per frame, two on the instrument-free frames.
        assert_eq!(stubborn.detected, 0);
        assert_eq!(stubborn.false_detections, n_fam);
        assert_eq!(stubborn.false_on_free, 2);
        assert!(oracle.ms[0].unwrap() >= 0.0);
    }
    // At the second level, instrument 2 is in view in the crossing frames.
    assert!(report.records.iter().any(|r| r.level == ClutterLevel::Second && r.second_in_view));
    assert!(report.records.iter().all(|r| r.level != ClutterLevel::Clean || !r.second_in_view));

    let out = tempfile::tempdir().unwrap();
    let written = report.write(out.path(), &out.path().join("img")).unwrap();
    let md = std::fs::read_to_string(out.path().join("table.md")).unwrap();
    assert!(md.contains("| clean | oracle |") && md.contains("| second | stubborn |"));
    assert!(md.contains("mid (tuning)") && md.contains("border (held out)"));
    // Two overlays per level, the SVG, the table and the JSON.
    assert_eq!(written.len(), 2 + 1 + 2 * levels.len());
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("results.json")).unwrap()).unwrap();
    assert_eq!(json["records"].as_array().unwrap().len(), 2 * n_fam);
}
