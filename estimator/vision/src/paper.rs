//! The calibration paper's centreline detector (Wang et al., *Vision-based calibration of dual
//! RCM-based robot arms in human-robot collaborative minimally invasive surgery*, IEEE RA-L
//! 2017, section V-B "Automatic Centerline Detection"): an 11×11 low-pass, EDLines
//! ([`crate::edlines`]: gradient threshold 5.22, hill climbing from anchors, least-squares
//! line fitting, false-positive rejection with precision 0.125), the two edges of the shaft
//! paired among the segments ([`pair_shaft`]), and their **middle line** as the centreline
//! ([`crate::shaft::middle_line`], the paper's approximation of the projected axis).
//!
//! The paper does not state its pairing rule; [`pair_shaft`] is a simple one, documented
//! there, that works on any segments (so that EDLines', LSD's or OpenCV's can be compared
//! through the same pairing).
//!
//! Pixels: segments, `ends_px` and the pairing are in **measured** (distorted) pixels, as the
//! paper works on the raw image; `centreline` and `contours` are the same lines expressed in
//! **undistorted** pixels (through their end points, [`undistorted_line`]).

use estimator::calib::Intrinsics;

use crate::detect::{
    DetectError, RgbView, Segment, ShaftDetection, ShaftDetector, check_size, luma_into, undistorted_line,
};
use crate::edlines::{EdLine, EdLines, EdLinesError};
use crate::shaft::{ImageLine, middle_line};

/// Largest angle between the two edges of a pair, radians (10°). A shaft's two contours
/// converge under perspective (by twice the half-angle the shaft subtends, 9° for a 4 mm
/// radius at 50 mm); beyond that, two edges are not one shaft.
pub const MAX_PAIR_ANGLE_RAD: f64 = 10.0 * std::f64::consts::PI / 180.0;

/// Shortest segment taken as a shaft edge, pixels: a shaft seen over less is not measured.
pub const MIN_EDGE_LENGTH_PX: f64 = 20.0;

/// Narrowest shaft, pixels: below, the two edges are the two sides of one thin line or
/// ridge (about 2σ = 4 px apart behind the 11×11 low-pass).
pub const MIN_SHAFT_WIDTH_PX: f64 = 6.0;

/// Widest shaft, as a fraction of the smaller image side: a wider one is not an instrument
/// seen whole.
pub const MAX_SHAFT_WIDTH_FRACTION: f64 = 0.5;

/// Least overlap of the two edges along their common direction, as a fraction of the
/// shorter edge: the two contours of one shaft run side by side.
pub const MIN_OVERLAP_FRACTION: f64 = 0.5;

/// At most this many segments (the longest) enter the pairing, which is quadratic.
pub const MAX_PAIRING_CANDIDATES: usize = 128;

/// The calibration paper's centreline detector, with its working buffers (reused between
/// frames).
#[derive(Clone, Debug)]
pub struct PaperDetector {
    k: Intrinsics,
    edlines: EdLines,
    luma: Vec<f32>,
}

impl PaperDetector {
    /// A detector for images of the camera `k` (size and distortion).
    pub fn new(k: Intrinsics) -> Self {
        Self { k, edlines: EdLines::paper(), luma: Vec::new() }
    }

    /// EDLines' segments of `image` after the 11×11 low-pass, **measured** pixels (the
    /// pairing's input). The image must have the camera's size.
    pub fn segments(&mut self, image: &RgbView<'_>) -> Result<&[Segment], DetectError> {
        check_size(&self.k, image)?;
        luma_into(image, &mut self.luma);
        match self.edlines.detect(&self.luma, image.width(), image.height()) {
            Ok(s) => Ok(s),
            // luma_into gives width · height samples, so this does not happen.
            Err(EdLinesError::Size { .. } | EdLinesError::Params(_)) => Err(DetectError::SizeMismatch {
                width: image.width(),
                height: image.height(),
                camera_width: self.k.width,
                camera_height: self.k.height,
            }),
        }
    }

    /// The lines of the last [`segments`](Self::segments) (or `detect`) with their evidence
    /// (chain pixels, aligned pixels, NFA).
    pub fn lines(&self) -> &[EdLine] {
        self.edlines.lines()
    }
}

impl ShaftDetector for PaperDetector {
    fn name(&self) -> &'static str {
        "paper"
    }

    fn intrinsics(&self) -> &Intrinsics {
        &self.k
    }

    /// At most one shaft (the paper reports one centreline per image).
    fn detect(&mut self, image: &RgbView<'_>) -> Result<Vec<ShaftDetection>, DetectError> {
        let k = self.k;
        let segments = self.segments(image)?;
        Ok(pair_shaft(&k, segments).into_iter().collect())
    }
}

/// The shaft's two edges among `segments` (**measured** pixels) and their middle line, or
/// `None`.
///
/// The pairing rule (the paper gives none): among the [`MAX_PAIRING_CANDIDATES`] longest
/// segments with finite end points of at least [`MIN_EDGE_LENGTH_PX`], the pairs
/// - at most [`MAX_PAIR_ANGLE_RAD`] apart in direction,
/// - overlapping along their mean direction over at least [`MIN_OVERLAP_FRACTION`] of the
///   shorter one,
/// - not crossing over that overlap, and
/// - separated (perpendicular distance at the overlap's middle) by a plausible shaft width,
///   [`MIN_SHAFT_WIDTH_PX`] to [`MAX_SHAFT_WIDTH_FRACTION`] of the smaller image side,
///
/// and of those the one with the largest combined length (ties: the first found). The
/// gradient polarity is not used (segments do not carry it).
///
/// The result: `contours` the two edges' lines, `centreline` their middle line (the bisector,
/// [`middle_line`], computed in measured pixels as the paper does), each expressed in
/// undistorted pixels through two of its points; `ends_px` the middle line's points at the
/// two ends of the overlap (measured pixels); `confidence` the overlap over the longer
/// edge's length (1: both edges span the same stretch).
pub fn pair_shaft(k: &Intrinsics, segments: &[Segment]) -> Option<ShaftDetection> {
    let max_width = MAX_SHAFT_WIDTH_FRACTION * f64::from(k.width.min(k.height));
    let mut cand: Vec<(f64, usize)> = segments
        .iter()
        .enumerate()
        .filter(|(_, s)| s.a.iter().chain(&s.b).all(|v| v.is_finite()))
        .map(|(i, s)| (s.length_px(), i))
        .filter(|&(len, _)| len >= MIN_EDGE_LENGTH_PX)
        .collect();
    cand.sort_by(|p, q| q.0.total_cmp(&p.0).then(p.1.cmp(&q.1)));
    cand.truncate(MAX_PAIRING_CANDIDATES);

    let cos_max = MAX_PAIR_ANGLE_RAD.cos();
    let mut best: Option<(f64, Pair)> = None;
    for (n, &(li, i)) in cand.iter().enumerate() {
        for &(lj, j) in &cand[n + 1..] {
            let (s, t) = (&segments[i], &segments[j]);
            let Some(pair) = Pair::of(s, t, cos_max) else { continue };
            if pair.overlap < MIN_OVERLAP_FRACTION * li.min(lj)
                || !(MIN_SHAFT_WIDTH_PX..=max_width).contains(&pair.width)
                || pair.crossing
            {
                continue;
            }
            let score = li + lj;
            if best.as_ref().is_none_or(|(b, _)| score > *b) {
                best = Some((score, Pair { confidence: pair.overlap / li.max(lj), ..pair }));
            }
        }
    }
    let (_, pair) = best?;
    pair.detection(k)
}

/// Two segments in the frame of their mean direction.
#[derive(Clone, Copy, Debug)]
struct Pair {
    s: Segment,
    t: Segment,
    /// The four points `[s at o0, t at o0, s at o1, t at o1]` at the two ends of the overlap.
    ends: [[f64; 2]; 4],
    overlap: f64,
    width: f64,
    crossing: bool,
    confidence: f64,
}

impl Pair {
    fn of(s: &Segment, t: &Segment, cos_max: f64) -> Option<Self> {
        let unit = |g: &Segment| {
            let (dx, dy) = (g.b[0] - g.a[0], g.b[1] - g.a[1]);
            let l = dx.hypot(dy);
            [dx / l, dy / l]
        };
        let (u, mut v) = (unit(s), unit(t));
        let mut dot = u[0] * v[0] + u[1] * v[1];
        let t = if dot < 0.0 {
            v = [-v[0], -v[1]];
            dot = -dot;
            Segment { a: t.b, b: t.a }
        } else {
            *t
        };
        if dot < cos_max {
            return None;
        }
        // Mean direction d, normal m; origin at s.a.
        let (dx, dy) = (u[0] + v[0], u[1] + v[1]);
        let l = dx.hypot(dy);
        let d = [dx / l, dy / l];
        let m = [-d[1], d[0]];
        let o = s.a;
        let along = |p: [f64; 2]| (p[0] - o[0]) * d[0] + (p[1] - o[1]) * d[1];
        let (s0, s1, t0, t1) = (along(s.a), along(s.b), along(t.a), along(t.b));
        let (o0, o1) = (s0.max(t0), s1.min(t1));
        let overlap = o1 - o0;
        if overlap.is_nan() || overlap <= 0.0 {
            return None;
        }
        // The point of a segment at abscissa `x` along d.
        let at = |g: &Segment, g0: f64, g1: f64, x: f64| {
            let f = (x - g0) / (g1 - g0);
            [g.a[0] + f * (g.b[0] - g.a[0]), g.a[1] + f * (g.b[1] - g.a[1])]
        };
        let ends = [at(s, s0, s1, o0), at(&t, t0, t1, o0), at(s, s0, s1, o1), at(&t, t0, t1, o1)];
        let off = |p: [f64; 2], q: [f64; 2]| (q[0] - p[0]) * m[0] + (q[1] - p[1]) * m[1];
        let (w0, w1) = (off(ends[0], ends[1]), off(ends[2], ends[3]));
        let width = (0.5 * (w0 + w1)).abs();
        let crossing = w0 * w1 <= 0.0;
        Some(Self { s: *s, t, ends, overlap, width, crossing, confidence: 0.0 })
    }

    fn detection(&self, k: &Intrinsics) -> Option<ShaftDetection> {
        let join = |g: &Segment| {
            let (a, b) = (g.a, g.b);
            ImageLine::new([a[1] - b[1], b[0] - a[0], a[0] * b[1] - b[0] * a[1]]).ok()
        };
        let (cs, ct) = (join(&self.s)?, join(&self.t)?);
        let mid = |p: [f64; 2], q: [f64; 2]| [0.5 * (p[0] + q[0]), 0.5 * (p[1] + q[1])];
        let (m0, m1) = (mid(self.ends[0], self.ends[1]), mid(self.ends[2], self.ends[3]));
        let interior = mid(m0, m1);
        let centre = middle_line(&cs, &ct, interior).ok()?;
        // The two ends of the overlap, on the middle line (measured pixels).
        let onto = |p: [f64; 2]| {
            let d = centre.distance_px(p[0], p[1]);
            [p[0] - d * centre.abc[0], p[1] - d * centre.abc[1]]
        };
        let ends_px = [onto(m0), onto(m1)];
        Some(ShaftDetection {
            centreline: undistorted_line(k, ends_px[0], ends_px[1]).ok()?,
            contours: [undistorted_line(k, self.s.a, self.s.b).ok()?, undistorted_line(k, self.t.a, self.t.b).ok()?],
            ends_px,
            confidence: self.confidence.clamp(0.0, 1.0),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn k() -> Intrinsics {
        Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 319.5,
            cy: 239.5,
            skew: 0.0,
            width: 640,
            height: 480,
            distortion: [0.0; 5],
        }
    }

    fn seg(a: [f64; 2], b: [f64; 2]) -> Segment {
        Segment { a, b }
    }

    #[test]
    fn two_parallel_edges_give_their_middle_line() {
        let edges = [seg([100.0, 50.0], [100.0, 350.0]), seg([140.0, 400.0], [140.0, 80.0])];
        let d = pair_shaft(&k(), &edges).unwrap();
        assert!(d.centreline.distance_px(120.0, 0.0).abs() < 1e-9);
        assert!(d.centreline.distance_px(120.0, 300.0).abs() < 1e-9);
        for e in d.ends_px {
            assert!((e[0] - 120.0).abs() < 1e-9);
        }
        let mut ys = [d.ends_px[0][1], d.ends_px[1][1]];
        ys.sort_by(f64::total_cmp);
        assert!((ys[0] - 80.0).abs() < 1e-9 && (ys[1] - 350.0).abs() < 1e-9, "{ys:?}");
        assert!((d.confidence - 270.0 / 320.0).abs() < 1e-9);
        assert!(d.contours.iter().any(|c| c.distance_px(100.0, 7.0).abs() < 1e-9));
        assert!(d.contours.iter().any(|c| c.distance_px(140.0, 7.0).abs() < 1e-9));
    }

    #[test]
    fn converging_edges_give_the_bisector() {
        // Symmetric about u = 200.
        let edges = [seg([180.0, 50.0], [170.0, 400.0]), seg([220.0, 50.0], [230.0, 400.0])];
        let d = pair_shaft(&k(), &edges).unwrap();
        for v in [0.0, 100.0, 450.0] {
            assert!(d.centreline.distance_px(200.0, v).abs() < 1e-9);
        }
    }

    #[test]
    fn the_longest_plausible_pair_wins_and_implausible_ones_are_refused() {
        let shaft = [seg([300.0, 20.0], [300.0, 460.0]), seg([340.0, 20.0], [340.0, 460.0])];
        let clutter = [seg([50.0, 100.0], [50.0, 200.0]), seg([80.0, 100.0], [80.0, 200.0])];
        let all = [clutter[0], shaft[0], clutter[1], shaft[1]];
        let d = pair_shaft(&k(), &all).unwrap();
        assert!(d.centreline.distance_px(320.0, 100.0).abs() < 1e-9);
        // Too close (the two sides of a thin line).
        assert!(pair_shaft(&k(), &[seg([10.0, 0.0], [10.0, 300.0]), seg([13.0, 0.0], [13.0, 300.0])]).is_none());
        // Too far apart.
        assert!(pair_shaft(&k(), &[seg([10.0, 0.0], [10.0, 300.0]), seg([400.0, 0.0], [400.0, 300.0])]).is_none());
        // Not side by side.
        assert!(pair_shaft(&k(), &[seg([10.0, 0.0], [10.0, 100.0]), seg([40.0, 150.0], [40.0, 300.0])]).is_none());
        // Not parallel.
        assert!(pair_shaft(&k(), &[seg([100.0, 0.0], [100.0, 300.0]), seg([120.0, 0.0], [220.0, 300.0])]).is_none());
        // Crossing.
        assert!(pair_shaft(&k(), &[seg([100.0, 0.0], [120.0, 300.0]), seg([120.0, 0.0], [100.0, 300.0])]).is_none());
        // Too short, one edge, nothing, not finite.
        assert!(pair_shaft(&k(), &[seg([100.0, 0.0], [100.0, 15.0]), seg([130.0, 0.0], [130.0, 15.0])]).is_none());
        assert!(pair_shaft(&k(), &shaft[..1]).is_none());
        assert!(pair_shaft(&k(), &[]).is_none());
        assert!(pair_shaft(&k(), &[shaft[0], seg([f64::NAN, 0.0], [340.0, 460.0])]).is_none());
        assert!(pair_shaft(&k(), &[shaft[0], shaft[0]]).is_none());
    }
}
