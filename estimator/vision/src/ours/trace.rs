//! Diagnostics: what each stage of [`super::OursDetector`] did on one frame
//! ([`super::OursDetector::detect_traced`]), so a benchmark can tell *why* a shaft was missed
//! (no edgels on its contours, no line hypothesis, no candidate pair, a pair rejected by a
//! named test, a verified pair dropped in the final selection).
//!
//! Pixels: undistorted (ideal pinhole) pixels throughout.

use serde::Serialize;

/// One half-resolution edgel: position and unit normal (modulo π), undistorted pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct TraceEdgel {
    /// Position `[u, v]`, undistorted pixels.
    pub p: [f32; 2],
    /// Unit normal of the edge (gradient direction modulo π).
    pub n: [f32; 2],
}

/// One straight-line hypothesis of the Hough stage.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct TraceLine {
    /// `[a, b, c]`, `a·u + b·v + c = 0`, `a² + b² = 1`, undistorted pixels.
    pub abc: [f64; 3],
    /// The ends of its supported span, undistorted pixels.
    pub ends: [[f64; 2]; 2],
    /// Supporting half-resolution edgels.
    pub votes: usize,
}

/// The test that turned a candidate pair of lines down (see the module docs of
/// [`super`] for what each test is).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PairReject {
    /// The two lines' spans overlap too little (`0.6 · min_length_px`).
    Overlap,
    /// The lines cross (or are closer than 2 px) over their overlap.
    Crossing,
    /// The cylinder's axis distance `r / sin(θ/2)` is out of range (cheap test).
    Distance,
    /// The strip between the lines is not a shaft's interior (coarse colour/luma test).
    CoarseColour,
    /// The first line's contour could not be refined in the full-resolution image.
    ContourA,
    /// The second line's contour could not be refined.
    ContourB,
    /// No run of good stations (both edges and a grey interior) along the pair.
    NoSpan,
    /// The visible span is shorter than `min_length_px`.
    ShortSpan,
    /// Too few good stations in the span (`min_support`).
    Support,
    /// A contour has too few edges inside the span to refit.
    Refit,
    /// The span fell under `min_length_px` while its ends were trimmed.
    Trimmed,
    /// A contour's robust residual scale exceeds `max_residual_px`.
    Residual,
    /// A degenerate geometry (parallel probes, no interior point).
    Geometry,
    /// The axis distance of the refined contours is out of range.
    AxisDistance,
    /// The axis's depth at an end of the span is out of range.
    EndDepth,
    /// The fine colour test on the span failed (or changed evidence).
    FineColour,
    /// The exact axis could not be computed.
    Axis,
    /// A short span that does not reach the image border.
    Border,
    /// Where a contour has no inlier edge in the span, the edges near its line turn away from
    /// it (`bridge_max_divergence_deg`): an edge of a wrist or jaws paired with a silhouette.
    Diverging,
}

/// What became of a candidate pair.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PairOutcome {
    /// Turned down by a test.
    Rejected(PairReject),
    /// Passed the cheap tests but ranked beyond the verification budget.
    NotVerified,
    /// Passed the cheap tests but not verified: both its lines lie in the strip of a shaft
    /// already verified and nearly parallel to it (a duplicate of that shaft: a rim or
    /// highlight line inside it), so it does not take a place in the verification budget.
    Redundant,
    /// Verified, then dropped in the final selection (it shares a line, a contour or the axis
    /// with a better one, or `max_detections` were already taken).
    Dropped,
    /// Returned, at this rank (0 = best).
    Returned(usize),
}

/// One candidate pair of lines (indices into [`OursTrace::lines`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct TracePair {
    /// The two lines.
    pub lines: [usize; 2],
    /// Its rank among the pairs that passed the cheap tests (0 = best), `None` when a cheap
    /// test turned it down.
    pub rank: Option<usize>,
    /// What became of it.
    pub outcome: PairOutcome,
    /// The verified detection's centreline `[a, b, c]` (undistorted pixels), when verified.
    pub centreline: Option<[f64; 3]>,
    /// The verified detection's figures, when verified.
    pub verified: Option<TraceVerified>,
}

/// What the verification measured on a pair it accepted.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct TraceVerified {
    /// The final selection's score (confidence × √length).
    pub score: f64,
    /// The pair's ranking score before verification (overlap length × the lines' least
    /// vote count × the interior's greyness).
    pub rank_score: f64,
    /// The detection's confidence, in `[0, 1]`.
    pub confidence: f64,
    /// The fraction of good stations in the visible span.
    pub support: f64,
    /// The larger robust residual scale of the two contours' fits, pixels.
    pub sigma_px: f64,
    /// The interior's contrast against the outsides, as a fraction of three times the
    /// threshold (chroma or luma), before clamping.
    pub contrast: f64,
    /// The visible span's length, undistorted pixels.
    pub length_px: f64,
    /// The width between the contours at the span's middle, undistorted pixels.
    pub width_px: f64,
    /// The fraction of the span's stations (every 2 px) where each contour has an inlier edge.
    pub coverage: [f64; 2],
    /// The span's ends on the axis, undistorted pixels.
    pub ends: [[f64; 2]; 2],
    /// For a pair dropped in the final selection: the rank of the returned detection it
    /// clashed with and the rule (`usize::MAX` with [`ClashRule::Full`]; `None`: returned).
    pub clash: Option<(usize, ClashRule)>,
}

/// Why the final selection dropped a verified pair for a better one.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ClashRule {
    /// It shares a line hypothesis with the better one.
    SharedLine,
    /// Nearly the same axis.
    SameAxis,
    /// It shares a contour.
    SharedContour,
    /// Nearly parallel, one lying in the other's strip.
    Overlap,
    /// It continues the better one past an end of its span (its wrist and jaws).
    Continues,
    /// A narrower, short detection starting at the better one's distal end at any angle: its
    /// jaws behind an articulated wrist.
    Jaws,
    /// `max_detections` were already taken.
    Full,
}

/// Everything [`super::OursDetector::detect_traced`] records about one frame.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct OursTrace {
    /// Every edgel, undistorted pixels.
    pub edgels: Vec<TraceEdgel>,
    /// The line hypotheses, best supported first.
    pub lines: Vec<TraceLine>,
    /// Every pair of lines within 25° of parallel.
    pub pairs: Vec<TracePair>,
    /// Every clash between two verified pairs, by rank: `(g, f, rule)`, `f` would be dropped
    /// for `g` were `g` the better one.
    pub clashes: Vec<(usize, usize, ClashRule)>,
    /// The frame's silhouette edgels (grey on one side, tissue on the other) and the fraction
    /// of them whose step is blurred (the motion-blur measure that gates
    /// `OursConfig::hough_normal_window_deg`; 0 with fewer than 20 of them).
    pub silhouette: (usize, f32),
}
