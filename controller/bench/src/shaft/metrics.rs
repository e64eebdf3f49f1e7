//! The shaft benchmark's per-frame scoring: pure functions on lines in undistorted pixels.
//!
//! - **Eligible**: the instrument's truth axis has at least [`ELIGIBLE_PX`] of *visible*
//!   length: the true visible segment (`segment_ideal_px`, undistorted pixels) times the
//!   fraction of points along it (its distorted polyline, sampled every pixel) that the
//!   renderer's mask labels as this instrument: the parts hidden by the second instrument, by
//!   the tissue or by the image border do not count.
//! - **Match**: a detected centreline matches an instrument when the angle between the two
//!   lines is at most [`MATCH_ANGLE_DEG`] and the detected line passes within
//!   [`MATCH_OFFSET_PX`] of the midpoint of the instrument's true visible segment.
//! - **Errors** of a matched detection: the angle (degrees) between the lines; the offset
//!   (pixels): the distance of the detected centreline from the midpoint of the true visible
//!   segment (which lies on the true axis); and the largest distance over the visible
//!   segment (at one of its ends: the distance to a line is linear along a segment).
//! - **False detection**: a returned detection that matches no instrument in the frame.

use serde::Serialize;
use vision::ShaftDetection;

/// Visible shaft length from which a frame is eligible, pixels.
pub const ELIGIBLE_PX: f64 = 100.0;

/// Largest angle between a detected centreline and the true axis for a match, degrees.
pub const MATCH_ANGLE_DEG: f64 = 2.0;

/// Largest distance of a detected centreline from the true segment's midpoint for a match,
/// pixels.
pub const MATCH_OFFSET_PX: f64 = 5.0;

/// One instrument's true axis in one image.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct TruthAxis {
    /// `[a, b, c]`, `a·u + b·v + c = 0`, undistorted pixels, `a² + b² = 1`.
    pub line: [f64; 3],
    /// The visible part's end points (image border and lens plane; not occlusion),
    /// undistorted pixels.
    pub segment: [[f64; 2]; 2],
    /// Visible length after occlusion (mask), pixels (see the module documentation).
    pub visible_px: f64,
    /// Fraction of the segment's samples labelled as the *other* instrument (crossed).
    pub crossed_fraction: f64,
}

impl TruthAxis {
    /// Length of the visible segment before occlusion, pixels.
    pub fn segment_px(&self) -> f64 {
        let [a, b] = self.segment;
        (b[0] - a[0]).hypot(b[1] - a[1])
    }

    /// Midpoint of the visible segment, undistorted pixels.
    pub fn midpoint(&self) -> [f64; 2] {
        let [a, b] = self.segment;
        [0.5 * (a[0] + b[0]), 0.5 * (a[1] + b[1])]
    }

    /// At least [`ELIGIBLE_PX`] visible.
    pub fn eligible(&self) -> bool {
        self.visible_px >= ELIGIBLE_PX
    }
}

/// The errors of a detected line against a true axis.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct LineErrors {
    /// Angle between the lines, degrees, in `[0, 90]`.
    pub angle_deg: f64,
    /// Distance of the detected line from the true segment's midpoint, pixels.
    pub offset_mid_px: f64,
    /// Largest distance of the detected line from the true visible segment, pixels.
    pub offset_max_px: f64,
}

impl LineErrors {
    /// The match rule: angle ≤ [`MATCH_ANGLE_DEG`] and midpoint offset ≤ [`MATCH_OFFSET_PX`]
    /// (false for NaN errors).
    pub fn matches(&self) -> bool {
        self.angle_deg <= MATCH_ANGLE_DEG && self.offset_mid_px <= MATCH_OFFSET_PX
    }
}

/// `[a, b, c]` scaled to `a² + b² = 1`; `None` when not finite or degenerate.
fn normalised(l: &[f64; 3]) -> Option<[f64; 3]> {
    let n = l[0].hypot(l[1]);
    (l.iter().all(|v| v.is_finite()) && n > 1e-12).then(|| l.map(|v| v / n))
}

/// Angle between two image lines (homogeneous `[a, b, c]`, any scale), degrees in
/// `[0, 90]`; `None` when either is not a line.
pub fn angle_deg(l1: &[f64; 3], l2: &[f64; 3]) -> Option<f64> {
    let (a, b) = (normalised(l1)?, normalised(l2)?);
    let cross = (a[0] * b[1] - a[1] * b[0]).abs();
    let dot = (a[0] * b[0] + a[1] * b[1]).abs();
    Some(cross.atan2(dot).to_degrees())
}

/// Distance of pixel `p` from line `l` (any scale), pixels; `None` when `l` is not a line.
pub fn distance_px(l: &[f64; 3], p: [f64; 2]) -> Option<f64> {
    let a = normalised(l)?;
    Some((a[0] * p[0] + a[1] * p[1] + a[2]).abs())
}

/// The errors of detected line `det` against `truth`; `None` when `det` is not a line.
pub fn line_errors(det: &[f64; 3], truth: &TruthAxis) -> Option<LineErrors> {
    let [a, b] = truth.segment;
    Some(LineErrors {
        angle_deg: angle_deg(det, &truth.line)?,
        offset_mid_px: distance_px(det, truth.midpoint())?,
        offset_max_px: distance_px(det, a)?.max(distance_px(det, b)?),
    })
}

/// Visible length of a true segment from the mask: `segment_len_px` times the fraction of
/// the points along the distorted `polyline` (sampled about every pixel) whose label is
/// `label`, and the fraction whose label is `other`. Points outside the image count as not
/// visible. `labels` is row-major, `width × height`. An empty polyline or a mask of the
/// wrong size gives `(0, 0)`.
pub fn visible_length_px(
    segment_len_px: f64,
    polyline: &[[f64; 2]],
    labels: &[u8],
    width: usize,
    height: usize,
    label: u8,
    other: u8,
) -> (f64, f64) {
    if polyline.len() < 2 || labels.len() != width * height || !segment_len_px.is_finite() {
        return (0.0, 0.0);
    }
    let (mut total, mut own, mut crossed) = (0usize, 0usize, 0usize);
    for pair in polyline.windows(2) {
        let (a, b) = (pair[0], pair[1]);
        let n = ((b[0] - a[0]).hypot(b[1] - a[1]).ceil() as usize).clamp(1, 100_000);
        for k in 0..n {
            let t = k as f64 / n as f64;
            let (x, y) = ((a[0] + (b[0] - a[0]) * t).round(), (a[1] + (b[1] - a[1]) * t).round());
            total += 1;
            if x >= 0.0 && y >= 0.0 && (x as usize) < width && (y as usize) < height {
                let l = labels[y as usize * width + x as usize];
                own += usize::from(l == label);
                crossed += usize::from(l == other);
            }
        }
    }
    let f = |c: usize| c as f64 / total.max(1) as f64;
    (segment_len_px * f(own), f(crossed))
}

/// One detector's score on one frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct FrameScore {
    /// Detections returned.
    pub detections: usize,
    /// The errors of the best-ranked detection matching instrument 1, if any.
    pub matched: Option<LineErrors>,
    /// Rank (0 = best) of that detection.
    pub matched_rank: Option<usize>,
    /// The errors of the best-ranked detection against instrument 1, matching or not (when
    /// instrument 1 has a visible segment and a detection was returned).
    pub top: Option<LineErrors>,
    /// Detections matching instrument 2.
    pub second_matches: usize,
    /// Further detections matching instrument 1 (after the first).
    pub duplicates: usize,
    /// Detections matching no instrument.
    pub false_detections: usize,
}

/// Scores the detections of one frame (best first) against the true axes of instrument 1
/// and 2 (`None`: not in the image). A detection matching both counts for instrument 1.
pub fn score_frame(dets: &[ShaftDetection], inst1: Option<&TruthAxis>, inst2: Option<&TruthAxis>) -> FrameScore {
    let mut s = FrameScore { detections: dets.len(), ..Default::default() };
    for (rank, d) in dets.iter().enumerate() {
        let e1 = inst1.and_then(|t| line_errors(&d.centreline.abc, t));
        if rank == 0 {
            s.top = e1;
        }
        if e1.is_some_and(|e| e.matches()) {
            if s.matched.is_none() {
                s.matched = e1;
                s.matched_rank = Some(rank);
            } else {
                s.duplicates += 1;
            }
        } else if inst2.and_then(|t| line_errors(&d.centreline.abc, t)).is_some_and(|e| e.matches()) {
            s.second_matches += 1;
        } else {
            s.false_detections += 1;
        }
    }
    s
}

/// The `q`-quantile (`0 ≤ q ≤ 1`) of `values` with linear interpolation between order
/// statistics (the "type 7" rule of R and numpy's default); NaNs are ignored; `None` when
/// nothing is left.
pub fn quantile(values: &[f64], q: f64) -> Option<f64> {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| !x.is_nan()).collect();
    if v.is_empty() || !(0.0..=1.0).contains(&q) {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let h = q * (v.len() - 1) as f64;
    let (lo, hi) = (h.floor() as usize, h.ceil() as usize);
    Some(v[lo] + (h - lo as f64) * (v[hi] - v[lo]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use vision::shaft::ImageLine;

    /// The line through two points, normalised.
    fn through(p: [f64; 2], q: [f64; 2]) -> [f64; 3] {
        let l = [p[1] - q[1], q[0] - p[0], p[0] * q[1] - q[0] * p[1]];
        normalised(&l).unwrap()
    }

    fn truth(p: [f64; 2], q: [f64; 2]) -> TruthAxis {
        TruthAxis { line: through(p, q), segment: [p, q], visible_px: 200.0, crossed_fraction: 0.0 }
    }

    fn det(l: [f64; 3]) -> ShaftDetection {
        let c = ImageLine::new(l).unwrap();
        ShaftDetection { centreline: c, contours: [c, c], ends_px: [[0.0; 2]; 2], confidence: 1.0 }
    }

    #[test]
    fn angle_between_constructed_lines() {
        let h = through([0.0, 100.0], [640.0, 100.0]);
        for deg in [0.0f64, 0.05, 1.0, 30.0, 89.0, 90.0, 135.0, 179.5] {
            let r = deg.to_radians();
            let l = through([320.0, 240.0], [320.0 + 100.0 * r.cos(), 240.0 + 100.0 * r.sin()]);
            let want = if deg > 90.0 { 180.0 - deg } else { deg };
            assert!((angle_deg(&h, &l).unwrap() - want).abs() < 1e-9, "{deg}");
            // Scale and sign of the coefficients do not matter.
            let scaled = l.map(|v| -3.5 * v);
            assert!((angle_deg(&h, &scaled).unwrap() - want).abs() < 1e-9, "{deg}");
        }
        assert_eq!(angle_deg(&[0.0, 0.0, 1.0], &h), None);
        assert_eq!(angle_deg(&[f64::NAN, 1.0, 0.0], &h), None);
    }

    #[test]
    fn offsets_at_the_midpoint_and_over_the_segment() {
        let t = truth([100.0, 100.0], [300.0, 100.0]);
        // A parallel line 2 px away.
        let e = line_errors(&through([0.0, 102.0], [10.0, 102.0]), &t).unwrap();
        assert!(e.angle_deg.abs() < 1e-12);
        assert!((e.offset_mid_px - 2.0).abs() < 1e-12 && (e.offset_max_px - 2.0).abs() < 1e-12);
        // Through the midpoint, tilted: no midpoint offset, the ends 100·sin(1°) away.
        let r = 1f64.to_radians();
        let e = line_errors(&through([200.0, 100.0], [200.0 + r.cos(), 100.0 + r.sin()]), &t).unwrap();
        assert!(e.offset_mid_px < 1e-9);
        assert!((e.offset_max_px - 100.0 * r.sin()).abs() < 1e-9);
        assert!((e.angle_deg - 1.0).abs() < 1e-9);
        assert_eq!(line_errors(&[0.0, 0.0, 5.0], &t), None);
    }

    #[test]
    fn the_match_rule_bounds_angle_and_midpoint_offset() {
        let ok = LineErrors { angle_deg: 1.99, offset_mid_px: 4.99, offset_max_px: 9.0 };
        assert!(ok.matches());
        assert!(!LineErrors { angle_deg: 2.01, ..ok }.matches());
        assert!(!LineErrors { offset_mid_px: 5.01, ..ok }.matches());
        assert!(!LineErrors { angle_deg: f64::NAN, ..ok }.matches());
    }

    #[test]
    fn frames_are_scored_by_instrument() {
        let t1 = truth([100.0, 100.0], [500.0, 100.0]);
        let t2 = truth([300.0, 0.0], [300.0, 400.0]);
        let near1 = det(through([0.0, 101.0], [640.0, 101.5]));
        let on2 = det(through([301.0, 0.0], [301.0, 480.0]));
        let wrong = det(through([0.0, 0.0], [640.0, 480.0]));
        let s = score_frame(&[on2, near1, wrong, near1], Some(&t1), Some(&t2));
        assert_eq!(s.detections, 4);
        assert_eq!(s.matched_rank, Some(1));
        assert!(s.matched.unwrap().offset_mid_px > 1.0 && s.matched.unwrap().offset_mid_px < 1.5);
        assert_eq!((s.second_matches, s.duplicates, s.false_detections), (1, 1, 1));
        // The top detection (instrument 2) against instrument 1: far off.
        assert!(s.top.unwrap().angle_deg > 80.0);
        // Without instrument 2 drawn, its detection is false; without instrument 1, so is the
        // one that would match it.
        let s = score_frame(&[on2, near1], Some(&t1), None);
        assert_eq!(s.false_detections, 1);
        let s = score_frame(&[near1], None, None);
        assert_eq!((s.false_detections, s.matched), (1, None));
        assert_eq!(score_frame(&[], Some(&t1), None), FrameScore::default());
    }

    #[test]
    fn eligibility_counts_only_the_pixels_labelled_as_the_instrument() {
        let (w, h) = (64usize, 48usize);
        let mut labels = vec![0u8; w * h];
        // Instrument 1 along row 20 from x = 0 to 59; instrument 2 covers x = 30..40.
        for x in 0..60 {
            labels[20 * w + x] = 1;
        }
        for x in 30..40 {
            labels[20 * w + x] = 2;
        }
        let poly = [[0.0, 20.0], [30.0, 20.0], [60.0, 20.0]];
        let (vis, crossed) = visible_length_px(120.0, &poly, &labels, w, h, 1, 2);
        // 50 of the 60 samples are instrument 1, 10 are instrument 2.
        assert!((vis - 100.0).abs() < 1e-9, "{vis}");
        assert!((crossed - 10.0 / 60.0).abs() < 1e-9);
        let t = TruthAxis { visible_px: vis, ..truth([0.0, 20.0], [120.0, 20.0]) };
        assert!(t.eligible());
        assert!(!TruthAxis { visible_px: 99.9, ..t }.eligible());
        assert!((t.segment_px() - 120.0).abs() < 1e-12);
        // Outside the image, the wrong mask size, no polyline: nothing visible.
        assert_eq!(visible_length_px(50.0, &[[-50.0, -5.0], [-10.0, -5.0]], &labels, w, h, 1, 2).0, 0.0);
        assert_eq!(visible_length_px(50.0, &poly, &labels[1..], w, h, 1, 2), (0.0, 0.0));
        assert_eq!(visible_length_px(50.0, &poly[..1], &labels, w, h, 1, 2), (0.0, 0.0));
    }

    #[test]
    fn quantiles_interpolate_and_ignore_nan() {
        let v = [4.0, 1.0, f64::NAN, 3.0, 2.0];
        assert_eq!(quantile(&v, 0.5), Some(2.5));
        assert_eq!(quantile(&v, 0.0), Some(1.0));
        assert_eq!(quantile(&v, 1.0), Some(4.0));
        assert!((quantile(&v, 0.95).unwrap() - 3.85).abs() < 1e-12);
        assert_eq!(quantile(&[], 0.5), None);
        assert_eq!(quantile(&[1.0], 1.5), None);
    }
}
