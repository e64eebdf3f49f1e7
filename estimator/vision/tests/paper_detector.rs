//! The calibration paper's detector on synthetic images whose lines are known: EDLines'
//! segments on the true edges, none on noise (the NFA control), the middle line of a band on
//! its centre line, no shaft without two edges, typed errors, no panic on any small image.

use estimator::calib::Intrinsics;
use proptest::prelude::*;
use vision::detect::{DetectError, RgbView, Segment, ShaftDetector, undistorted_line};
use vision::edlines::EdLines;
use vision::paper::{PaperDetector, pair_shaft};

fn camera(w: usize, h: usize, distortion: [f64; 5]) -> Intrinsics {
    Intrinsics {
        fx: 400.0,
        fy: 400.0,
        cx: (w as f64 - 1.0) / 2.0,
        cy: (h as f64 - 1.0) / 2.0,
        skew: 0.0,
        width: w as u32,
        height: h as u32,
        distortion,
    }
}

/// A region (`inside(u, v)`) and its grey level.
type Shape<'a> = (&'a dyn Fn(f64, f64) -> bool, f64);

/// A signed distance to a line, pixels.
type Distance = dyn Fn(f64, f64) -> f64;

/// xorshift64: uniform in [-0.5, 0.5).
struct Noise(u64);
impl Noise {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 40) as f64 / (1u64 << 24) as f64 - 0.5
    }
}

/// A grey image as RGB bytes: `background(u, v)` with the shapes (`inside(u, v)`, grey level)
/// drawn over it, 4×4 supersampled (anti-aliased), plus uniform noise of `noise` grey levels
/// peak to peak.
fn render(
    w: usize,
    h: usize,
    background: impl Fn(f64, f64) -> f64,
    shapes: &[Shape<'_>],
    noise: f64,
    seed: u64,
) -> Vec<u8> {
    let mut rng = Noise(seed.max(1));
    let mut out = Vec::with_capacity(3 * w * h);
    for y in 0..h {
        for x in 0..w {
            let mut acc = 0.0;
            for sy in 0..4 {
                for sx in 0..4 {
                    let (u, v) = (x as f64 + (sx as f64 - 1.5) / 4.0, y as f64 + (sy as f64 - 1.5) / 4.0);
                    let mut g = background(u, v);
                    for (inside, level) in shapes {
                        if inside(u, v) {
                            g = *level;
                        }
                    }
                    acc += g / 16.0;
                }
            }
            let g = (acc + noise * rng.next()).round().clamp(0.0, 255.0) as u8;
            out.extend_from_slice(&[g, g, g]);
        }
    }
    out
}

fn texture(u: f64, v: f64) -> f64 {
    100.0 + 15.0 * (u / 9.0).sin() * (v / 13.0).cos()
}

/// A line through `p` with direction `d`: signed distance function.
fn line_through(p: [f64; 2], d: [f64; 2]) -> impl Fn(f64, f64) -> f64 {
    let l = d[0].hypot(d[1]);
    let n = [-d[1] / l, d[0] / l];
    move |u, v| (u - p[0]) * n[0] + (v - p[1]) * n[1]
}

fn near(seg: &Segment, dist: &dyn Fn(f64, f64) -> f64, tol: f64) -> bool {
    dist(seg.a[0], seg.a[1]).abs() <= tol && dist(seg.b[0], seg.b[1]).abs() <= tol
}

#[test]
fn edlines_finds_the_four_sides_of_a_rectangle_within_a_pixel() {
    let (w, h) = (200, 160);
    let (x0, y0, x1, y1) = (40.3, 30.7, 150.6, 120.2);
    let rect = move |u: f64, v: f64| (x0..=x1).contains(&u) && (y0..=y1).contains(&v);
    let bytes = render(w, h, texture, &[(&rect, 190.0)], 6.0, 7);
    let image = RgbView::new(w, h, &bytes).unwrap();
    let mut det = PaperDetector::new(camera(w, h, [0.0; 5]));
    let segs = det.segments(&image).unwrap().to_vec();
    let sides: [(Box<Distance>, f64); 4] = [
        (Box::new(move |u, _| u - x0), y1 - y0),
        (Box::new(move |u, _| u - x1), y1 - y0),
        (Box::new(move |_, v| v - y0), x1 - x0),
        (Box::new(move |_, v| v - y1), x1 - x0),
    ];
    for s in &segs {
        assert!(sides.iter().any(|(d, _)| near(s, d.as_ref(), 1.0)), "segment off every side: {s:?} in {segs:?}");
    }
    for (d, len) in &sides {
        let covered: f64 = segs.iter().filter(|s| near(s, d.as_ref(), 1.0)).map(Segment::length_px).sum();
        assert!(covered >= 0.6 * len, "side covered over {covered} of {len}: {segs:?}");
    }
    // Every kept line passed the Helmholtz test.
    assert!(det.lines().iter().all(|l| l.log10_nfa <= 0.0 && l.fit_rms_px <= 1.0 && l.aligned <= l.pixels));
}

#[test]
fn edlines_finds_a_slanted_line_at_any_angle() {
    let (w, h) = (160, 160);
    for deg in [7.0f64, 30.0, 45.0, 63.0, 100.0, 152.0] {
        let d = [deg.to_radians().cos(), deg.to_radians().sin()];
        let dist = line_through([80.3, 79.6], d);
        let half = |u: f64, v: f64| dist(u, v) > 0.0;
        let bytes = render(w, h, |_, _| 70.0, &[(&half, 170.0)], 4.0, 11);
        let image = RgbView::new(w, h, &bytes).unwrap();
        let mut det = PaperDetector::new(camera(w, h, [0.0; 5]));
        let segs = det.segments(&image).unwrap();
        let on: Vec<&Segment> = segs.iter().filter(|s| near(s, &dist, 1.0)).collect();
        let total: f64 = on.iter().map(|s| s.length_px()).sum();
        assert!(total >= 100.0, "{deg}°: {total} px on the line: {segs:?}");
        assert_eq!(on.len(), segs.len(), "{deg}°: segments off the line: {segs:?}");
    }
}

#[test]
fn no_segments_on_pure_noise() {
    let (w, h) = (160, 120);
    for seed in [1u64, 2, 3, 4] {
        let bytes = render(w, h, |_, _| 128.0, &[], 255.0, seed);
        let image = RgbView::new(w, h, &bytes).unwrap();
        let mut det = PaperDetector::new(camera(w, h, [0.0; 5]));
        assert!(det.segments(&image).unwrap().is_empty(), "seed {seed}: {:?}", det.lines());
        assert!(det.detect(&image).unwrap().is_empty());
    }
}

#[test]
fn noise_makes_candidate_lines_that_the_nfa_removes() {
    // The smoothed noise crosses the gradient threshold and its chains give lines within the
    // fitting error: only the validation removes them.
    let (w, h) = (160, 120);
    for seed in [1u64, 2] {
        let bytes = render(w, h, |_, _| 128.0, &[], 255.0, seed);
        let image = RgbView::new(w, h, &bytes).unwrap();
        let mut luma = Vec::new();
        vision::detect::luma_into(&image, &mut luma);
        let mut ed = EdLines::paper();
        assert!(ed.detect(&luma, w, h).unwrap().is_empty());
        assert!(ed.candidates() > 0, "seed {seed}");
    }
}

fn band_image(w: usize, h: usize, centre: &dyn Fn(f64, f64) -> f64, half_width: f64, level: f64, seed: u64) -> Vec<u8> {
    let inside = |u: f64, v: f64| centre(u, v).abs() <= half_width;
    render(w, h, texture, &[(&inside, level)], 6.0, seed)
}

#[test]
fn the_middle_line_of_a_band_is_its_centre_line() {
    let (w, h) = (320, 240);
    // (direction, band level, half width, a point of the centre line); the last two have
    // their edges half-way between pixel centres, where ED's chain hesitates between two
    // rows or columns.
    let bands = [
        (80.0f64, 220.0, 18.0, [161.2, 118.7]),
        (65.0, 20.0, 25.0, [161.2, 118.7]),
        (100.0, 200.0, 12.0, [161.2, 118.7]),
        (20.0, 30.0, 20.0, [161.2, 118.7]),
        (90.0, 210.0, 20.0, [119.5, 0.0]),
        (0.0, 40.0, 15.0, [0.0, 100.0]),
    ];
    for (deg, level, half, point) in bands {
        let d = [deg.to_radians().cos(), deg.to_radians().sin()];
        let centre = line_through(point, d);
        let bytes = band_image(w, h, &centre, half, level, 5);
        let image = RgbView::new(w, h, &bytes).unwrap();
        let mut det = PaperDetector::new(camera(w, h, [0.0; 5]));
        let found = det.detect(&image).unwrap();
        assert_eq!(found.len(), 1, "{deg}°");
        let s = found[0];
        for e in s.ends_px {
            assert!(centre(e[0], e[1]).abs() < 0.5, "{deg}°: end {e:?} is {} px off", centre(e[0], e[1]));
            assert!(s.centreline.distance_px(e[0], e[1]).abs() < 1e-6);
        }
        let span = (s.ends_px[0][0] - s.ends_px[1][0]).hypot(s.ends_px[0][1] - s.ends_px[1][1]);
        assert!(span > 100.0, "{deg}°: span {span}");
        for c in s.contours {
            let e = s.ends_px[0];
            assert!((c.distance_px(e[0], e[1]).abs() - half).abs() < 1.0, "{deg}°: contour {c:?}");
        }
        assert!(s.confidence > 0.5 && s.confidence <= 1.0);
        // The same pairing on the same segments gives the same answer.
        let segs = det.segments(&image).unwrap().to_vec();
        assert_eq!(pair_shaft(det.intrinsics(), &segs), Some(s));
    }
}

#[test]
fn with_distortion_the_centreline_is_the_undistorted_middle_line() {
    let (w, h) = (320, 240);
    let k = camera(w, h, [-0.2, 0.05, 0.001, -0.001, 0.0]);
    let centre = line_through([70.0, 120.0], [0.3, 1.0]);
    let bytes = band_image(w, h, &centre, 16.0, 210.0, 9);
    let image = RgbView::new(w, h, &bytes).unwrap();
    let mut det = PaperDetector::new(k);
    let found = det.detect(&image).unwrap();
    assert_eq!(found.len(), 1);
    let s = found[0];
    for e in s.ends_px {
        assert!(centre(e[0], e[1]).abs() < 0.5);
    }
    let expected = undistorted_line(&k, s.ends_px[0], s.ends_px[1]).unwrap();
    assert_eq!(s.centreline, expected);
    // Undistorting moved it: the measured line is not the undistorted one.
    let e = s.ends_px[0];
    assert!(s.centreline.distance_px(e[0], e[1]).abs() > 0.1);
}

#[test]
fn no_shaft_with_one_edge_or_nothing() {
    let (w, h) = (160, 120);
    let k = camera(w, h, [0.0; 5]);
    let mut det = PaperDetector::new(k);
    let step = line_through([70.5, 60.0], [0.2, 1.0]);
    let half = |u: f64, v: f64| step(u, v) > 0.0;
    let bytes = render(w, h, texture, &[(&half, 200.0)], 6.0, 3);
    let image = RgbView::new(w, h, &bytes).unwrap();
    assert!(!det.segments(&image).unwrap().is_empty(), "the edge itself is found");
    assert!(det.detect(&image).unwrap().is_empty());
    for g in [0u8, 97, 255] {
        let bytes = vec![g; 3 * w * h];
        let image = RgbView::new(w, h, &bytes).unwrap();
        assert!(det.segments(&image).unwrap().is_empty());
        assert!(det.detect(&image).unwrap().is_empty());
    }
    let mut ed = EdLines::paper();
    let flat = vec![42.0f32; w * h];
    assert!(ed.detect(&flat, w, h).unwrap().is_empty());
    assert!(ed.gradient_magnitude().iter().all(|g| g.is_finite() && *g == 0.0));
}

#[test]
fn a_wrong_image_size_is_a_typed_error() {
    let mut det = PaperDetector::new(camera(64, 48, [0.0; 5]));
    let bytes = vec![0u8; 3 * 48 * 64];
    let image = RgbView::new(48, 64, &bytes).unwrap();
    let want = DetectError::SizeMismatch { width: 48, height: 64, camera_width: 64, camera_height: 48 };
    assert_eq!(det.detect(&image), Err(want));
    assert_eq!(det.segments(&image).map(<[Segment]>::len), Err(want));
    assert_eq!(det.name(), "paper");
}

#[test]
fn buffers_are_reset_between_frames() {
    let (w, h) = (200, 160);
    let centre = line_through([100.0, 80.0], [0.1, 1.0]);
    let band = band_image(w, h, &centre, 15.0, 220.0, 21);
    let noise = render(w, h, |_, _| 128.0, &[], 255.0, 8);
    let mut det = PaperDetector::new(camera(w, h, [0.0; 5]));
    let band_image = RgbView::new(w, h, &band).unwrap();
    let noise_image = RgbView::new(w, h, &noise).unwrap();
    let first = det.detect(&band_image).unwrap();
    let first_segments = det.segments(&band_image).unwrap().to_vec();
    assert!(det.detect(&noise_image).unwrap().is_empty());
    assert_eq!(det.detect(&band_image).unwrap(), first);
    assert_eq!(det.segments(&band_image).unwrap(), &first_segments[..]);
    assert_eq!(first.len(), 1);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(200))]

    #[test]
    fn any_small_image_gives_finite_answers(w in 1usize..28, h in 1usize..28, seed in any::<u64>(), pattern in 0u8..3) {
        let mut rng = Noise(seed | 1);
        let bytes: Vec<u8> = (0..3 * w * h)
            .map(|i| match pattern {
                0 => (rng.next() * 255.0 + 128.0) as u8,
                1 => if (i / 3) % w < w / 2 { 30 } else { 220 },
                _ => if ((i / 3) % w).abs_diff(w / 2) < 3 { 250 } else { (rng.next() * 20.0 + 60.0) as u8 },
            })
            .collect();
        let image = RgbView::new(w, h, &bytes).unwrap();
        let mut det = PaperDetector::new(camera(w, h, [-0.1, 0.01, 0.0, 0.0, 0.0]));
        for s in det.segments(&image).unwrap() {
            prop_assert!(s.a.iter().chain(&s.b).all(|v| v.is_finite()));
        }
        for d in det.detect(&image).unwrap() {
            prop_assert!(d.centreline.abc.iter().all(|v| v.is_finite()));
            prop_assert!(d.ends_px.iter().flatten().all(|v| v.is_finite()));
            prop_assert!((0.0..=1.0).contains(&d.confidence));
        }
    }

    #[test]
    fn any_samples_never_panic(w in 1usize..20, h in 1usize..20, samples in proptest::collection::vec(prop_oneof![
        Just(f32::NAN), Just(f32::INFINITY), Just(f32::NEG_INFINITY), -1e6f32..1e6f32, 0.0f32..255.0
    ], 1..400)) {
        let mut ed = EdLines::paper();
        match ed.detect(&samples, w, h) {
            Ok(segs) => prop_assert!(segs.iter().all(|s| s.a.iter().chain(&s.b).all(|v| v.is_finite()))),
            Err(_) => prop_assert_ne!(samples.len(), w * h),
        }
    }

    #[test]
    fn any_segments_pair_to_at_most_one_finite_shaft(raw in proptest::collection::vec(
        (prop_oneof![Just(f64::NAN), -100.0f64..800.0], -100.0f64..600.0, -100.0f64..800.0, -100.0f64..600.0), 0..30)) {
        let k = camera(640, 480, [-0.1, 0.01, 0.0, 0.0, 0.0]);
        let segs: Vec<Segment> = raw.iter().map(|&(a, b, c, d)| Segment { a: [a, b], b: [c, d] }).collect();
        if let Some(d) = pair_shaft(&k, &segs) {
            prop_assert!(d.centreline.abc.iter().all(|v| v.is_finite()));
            prop_assert!(d.ends_px.iter().flatten().all(|v| v.is_finite()));
        }
    }
}
