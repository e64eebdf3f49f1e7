//! # Our instrument-shaft detector ("ours")
//!
//! Finds the shaft of a laparoscopic instrument (a metal cylinder of known diameter) in an
//! endoscope image and returns its exact projected axis. It competes with the detector of the
//! dual RCM-arm calibration paper (Wang et al., *Vision-based calibration of dual RCM-based
//! robot arms in human-robot collaborative minimally invasive surgery*, IEEE RA-L 2017,
//! Sec. V-B: line segments, then the middle line of the two shaft edges) on three counts:
//! precision (sub-pixel edges, straight lines only after undistortion, the exact perspective
//! axis instead of the middle line), robustness (colour and cylinder physics reject tissue
//! clutter), and speed (a few milliseconds per 640×480 frame on one core).
//!
//! ## Pipeline and why
//!
//! 1. **Edgels at half resolution** (`edges`). Each 2×2 block is averaged (halves the noise,
//!    quarters the work) into two channels: luma, and the red opponent `C = 2R − G − B`.
//!    Colour is the strongest cue in the abdomen: grey metal has `C ≈ 0`, pink/red tissue
//!    `C ≫ 0`, whatever the lighting (vignetting and the tip light scale both). The gradient
//!    is Di Zenzo's (largest eigenvalue of the two channels' structure tensor), so a contour
//!    seen in either channel counts (under smoke the colour fades and luma carries the edge).
//!    Non-maximum suppression along the gradient, a threshold, then each edgel's position and
//!    normal are mapped to **undistorted** pixels by a table built once (no per-pixel
//!    undistortion per frame): there the contours are straight lines. Opt-in
//!    ([`OursConfig::coarse_edgels_under_haze`]): on a hazy frame where no shaft was found,
//!    stages 2-7 run once more on the silhouette edgels of the image averaged over 2×2 blocks
//!    (a faint, spread step is clearer on wider blocks).
//! 2. **Line hypotheses** (`hough`): an orientation-guided Hough transform, 1° × 2 px bins:
//!    on a clear frame each edgel votes at every angle within `hough_normal_window_deg` of
//!    its normal (an option, 0 by default: once at its own normal, peaks of a 9 × 3 box sum), at the
//!    distance its position gives there, and the peaks are 1 × 3 box sums (a contour's
//!    edgels are exactly on one line while their normals scatter by degrees: one vote at the
//!    measured normal lands `s·δθ` off in distance, `s` along the line from the foot of the perpendicular from the
//!    centre, so a short contour far out makes no peak), and once a peak's line is gathered
//!    its edgels' votes are taken back, so that one contour leaves one peak; on a hazy frame,
//!    or on one whose instrument silhouettes are motion-blurred (more than
//!    `hough_window_max_blurred` of the edgels with grey on one side and tissue on the other
//!    have a step spread over more than a few pixels: each instant of the exposure leaves a
//!    step of its own, which the window would turn into lines), each edgel votes once at its
//!    own normal, peaks of a 9 × 3 box sum. Then each peak's edgels are gathered and refitted
//!    (total least squares) and its supported span found.
//! 3. **Pairs with physics** (cheap tests on the hypotheses): two lines are the contours of
//!    one cylinder of radius `r` only if they are within 25° of parallel, overlap along their
//!    length, and the angle `θ` between their planes through the optical centre (normals
//!    `Kᵀl`) gives a plausible distance of the axis, `d = r / sin(θ/2)`, inside
//!    `[min_depth_m, max_depth_m]` (this rejects vessels and creases: far too thin for a shaft
//!    at that distance). Then the **interior colour test**: the strip between the lines must
//!    be clearly less red than the tissue just outside on both sides, `C_out − C_in ≥
//!    min_chroma_contrast` and `C_in ≤ max_interior_chroma_ratio · C_out`, with `C_in` the
//!    upper quartile across the strip and also the median just inside each line (a vessel is
//!    redder inside; a contour paired with an unrelated tissue edge or fold has tissue in part
//!    of the strip; a fold's highlight stays pink). Under haze half the colour contrast is
//!    enough on a side with a clear luma step (`min_luma_contrast`); where the haze has washed
//!    the colour out of the tissue on both sides, a luma step of the same sign on both sides
//!    (1.5 × `min_luma_contrast`) stands in for the colour, all the way through (the span's
//!    stations and the final test use the same evidence). Haze also scales every contrast
//!    down: the thresholds are **normalised by the frame's colour contrast** (its median
//!    chroma against a clear frame's, `clear_chroma`, at least `min_contrast_scale`; the
//!    required relative drop `1 − max_interior_chroma_ratio` scales alike), so a hazy frame
//!    is judged against its own contrast, not a clear frame's. Pairs are ranked by length ×
//!    support × greyness of the interior. The colour test samples the image across the strip
//!    (scattered reads: with a crossing second instrument a frame has hundreds of pairs), so
//!    the ranking is **lazy**: the pairs are taken in the order of their score bound (length ×
//!    support, the greyness being at most 1) and each is scored only when it could rank before
//!    the best one scored so far, and not at all once it duplicates a verified shaft (it
//!    would be passed over anyway); the verification sees the same pairs in the same order as
//!    a full ranking would give (`next_in_rank`, tested against a full sort).
//! 4. **Sub-pixel contours** in the full-resolution measured image, each Hough line once per
//!    frame: profiles across the contour, sampled at undistorted positions mapped through the
//!    lens (so each edge found is directly an undistorted point on the straight contour), two
//!    samples 1.5 px apart along the edge averaged, the combined gradient
//!    `√(dC² + (w·dL)²)` (kernel `[1 2 0 −2 −1]/8`, `w = profile_luma_weight`: the silhouette is
//!    where the colour changes, the dark rim and highlights of the metal are luma edges just
//!    inside), its peak placed by the centroid of its upper half (a motion-blurred edge is a
//!    staircase: its centroid is the middle instant). Two rounds over the Hough support
//!    (gates ±3 px then ±1.5 px), each with a Tukey-biweight IRLS line fit; then the contour is
//!    followed outwards along the line while edges keep coming, and refitted; from the second
//!    round on, an edge must be at least a third of the contour's median strength. A contour
//!    that yields too few edges is retried with luma at full weight (a hazy luma-only edge).
//! 5. **The visible span**: stations every 2 px where both contours have an inlier edge and
//!    the interior is grey against both outsides (or one edge and a clearly grey interior);
//!    the run with the most good stations is the shaft. Gaps of any length are bridged (the
//!    stations on both sides lie on the same two contour lines with a grey interior: one
//!    cylinder, a second instrument crossing in front); a gap over 64 px is an occlusion and
//!    does not count against the support (opt-in, `bridge_min_both`: only where both contours
//!    run on on each side of it). Its ends are trimmed while either contour leaves its line systematically (the
//!    wrist, a bent link, the tapered jaws), and both contours are refitted on the span.
//! 6. **The exact axis** from the two contours, [`crate::shaft::axis_from_contours`] (the
//!    middle line is wrong by up to pixels under perspective); the distance gate again, the
//!    axis's depth at both ends of the span (a tapered tip seen as a cylinder would reach far
//!    beyond the range towards its apex), the colour test on the span; a span shorter than
//!    `long_span_px` must reach the image border (a shaft runs out of the view, a pair of jaws
//!    does not): either contour's edges followed past the span (gaps up to 32 px), or a run
//!    of 32 px of edges on a contour line past a gap of any length (the part behind a crossing
//!    instrument); or be slender, at least `slender_span_widths` shaft widths long (a pair of
//!    jaws is a few widths long at most; a shaft cut short by a crossing instrument, or whose
//!    contours fade in a vignetted, defocused, hazy border region, keeps a slender part); or,
//!    opt-in (`occluded_end_waiver`), end where a verified shaft crossing in front hides it.
//!    `ends_px` are the span's ends on the axis, mapped back to measured pixels.
//! 7. **Under haze, the returned shafts re-measured** ([`OursConfig::haze_refit`]): haze
//!    fades the silhouette's colour step with the tissue's transmittance while its luma step
//!    stays (the shaft, nearer the lens, is less hazy than the tissue behind it), so each
//!    returned shaft's contours are profiled again every pixel of the verified span where
//!    they had edges, with the luma weight divided by the haze scale, refitted, and the axis
//!    rebuilt. Only the returned lines change, never which shafts are returned.
//!
//! The best-ranked pairs (`3 · max_detections + 2`) are verified, not counting the pairs
//! whose two lines both lie in the strip of a shaft already verified and nearly parallel to
//! it (its duplicates: a near second instrument has several lines per contour, rim and
//! highlights, whose pairs would otherwise fill the budget before the first instrument's
//! pair is reached); the best consistent set is returned, by **merit**: the product of the
//! pair's ranking score (the whole lines' evidence) and its verification score (confidence ×
//! √length of the verified span). The verification score alone is not comparable between a
//! pair verified first and one reached far down the ranking past many duplicates: under haze a
//! wrong pairing on the same shaft (a contour with a shadow's or a highlight's edge) can score
//! a little higher on its span than the right pair, while its weaker line has far fewer votes.
//! So a second instrument is a second valid pair, and a pair sharing a Hough line,
//! a contour or the axis with a better one, or nearly parallel to it (within 10°) and lying
//! in its strip, or of the size of its wrist and jaws (narrower, `jaw_width_ratio`, and no
//! longer than the instrument's end beyond the shaft, `tip_length_diameters` of its widths)
//! and either continuing it past an end of its span nearly in line (within 30°, from within
//! half a width of that end) or starting within a width of the distal end of its span (an end
//! inside the image) at any angle (an articulated wrist), is dropped (two shafts do not lie
//! over each other in the image; a crossing one does not start where another ends, and is
//! not narrower by more than its depth makes it).
//!
//! [`OursDetector::detect_traced`] records what each stage did ([`OursTrace`]: edgels, line
//! hypotheses, every candidate pair with the test that turned it down), for diagnostics.
//!
//! Cost (640×480, one core): about 1 ms for the half-resolution edgels, under 1 ms for the
//! Hough stage, the rest in the profiles; no allocation per frame once warm, except the
//! returned vector. A profile sample is a bilinear read of the chroma and luma (integer
//! channels, one interpolation per channel); along each of a profile's two rows the lens
//! mapping is computed at both ends and the middle and is quadratic in between (under
//! 10⁻³ px from the exact mapping, tested; the profiles are most of the time).
//!
//! ## Confidence
//!
//! `support × 1/(1 + (σ/0.5 px)²) × min(1, contrast / (3·min_chroma_contrast))`: `support` is
//! the fraction of good stations in the visible span, `σ` the larger robust residual scale of
//! the two contour fits (pixels), `contrast` the smaller interior/outside chroma difference.
//! Low under smoke (the colour contrast fades) even when the axis is right.
//!
//! Pixels: measured (distorted) images in, lines in undistorted pixels, `ends_px` measured.

mod edges;
mod geom;
mod hough;
mod lens;
mod profile;
mod trace;

pub use trace::{ClashRule, OursTrace, PairOutcome, PairReject, TraceEdgel, TraceLine, TracePair, TraceVerified};

use estimator::calib::Intrinsics;
use estimator::calib::camera::IntrinsicsError;
use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::detect::{DetectError, RgbView, ShaftDetection, ShaftDetector, check_size};
use crate::shaft::{ImageLine, axis_from_contours};
use edges::EdgeBuffers;
use geom::{Line, SlopeFit, robust_fit};
use hough::{Hough, LineCand};
use lens::{HalfResTable, Lens};
use profile::{Sampler, interior};

/// The detector's settings. Every field has a default ([`OursConfig::default`]); the
/// defaults suit the simulated 640×480, f = 400 px endoscope with an 8 mm shaft.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OursConfig {
    /// Shaft diameter, metres (default 0.008).
    pub shaft_diameter_m: f64,
    /// Nearest plausible distance from the optical centre to the shaft's axis, metres
    /// (default 0.010).
    pub min_depth_m: f64,
    /// Farthest plausible distance from the optical centre to the shaft's axis, metres
    /// (default 0.300).
    pub max_depth_m: f64,
    /// Shortest visible shaft (both contours), undistorted pixels (default 40: in the twin's
    /// recorded runs the tool arm's shaft is often only 50–100 px visible from the image
    /// border; a span shorter than `long_span_px` must reach the border anyway).
    pub min_length_px: f64,
    /// Edgel threshold on the half-resolution Di Zenzo gradient magnitude (chroma units
    /// `2R − G − B` per half-resolution pixel, 8-bit values; default 6).
    pub edge_threshold: f64,
    /// Weight of luma against the chroma `2R − G − B` in the half-resolution gradients that
    /// find the lines (default 1).
    pub luma_weight: f64,
    /// Weight of luma against the chroma in the full-resolution profiles that place the
    /// contours (default 0.3: the silhouette is where the colour changes; a metal shaft's dark
    /// rim and highlights are luma edges just inside it).
    pub profile_luma_weight: f64,
    /// Most line hypotheses kept (default 40; a shaft only 40–80 px long has fewer votes than
    /// the long edges of bright folds and may miss the list on heavily folded tissue: 100
    /// finds it there, at 2–3× the time).
    pub max_lines: usize,
    /// Most shafts returned (default 2).
    pub max_detections: usize,
    /// Least chroma drop from the tissue just outside to the shaft's interior, both sides
    /// (chroma units `2R − G − B`, default 12).
    pub min_chroma_contrast: f64,
    /// Luma difference (8-bit) between the interior and the outside of a side from which half
    /// of `min_chroma_contrast` is enough there (default 25: haze fades the colour, not the
    /// brightness step of the metal).
    pub min_luma_contrast: f64,
    /// Largest interior chroma as a fraction of the chroma outside, both sides (default 0.5).
    pub max_interior_chroma_ratio: f64,
    /// Largest robust residual scale of a contour's fit, pixels (default 2; defocus and
    /// motion blur on a noisy image scatter single edge points by about a pixel).
    pub max_residual_px: f64,
    /// Least fraction of the visible span with an inlier edge on each contour (default 0.5).
    pub min_support: f64,
    /// A visible shaft shorter than `long_span_px` must reach this close to the image border,
    /// measured pixels (default 24): a shaft comes through a trocar and runs out of the view,
    /// while a tapered tip or a pair of jaws (which can pass for a farther cylinder) lies
    /// inside it. Infinite to switch the test off.
    pub border_margin_px: f64,
    /// Visible length from which the border test is waived, undistorted pixels (default 200;
    /// a long span with straight parallel edges and a grey interior is a shaft, and its end
    /// at the border may be lost in a vignetted, hazy corner).
    pub long_span_px: f64,
    /// The frame's median chroma (`2R − G − B`, 8-bit) from which it counts as clear (default
    /// 60: tissue under the simulated endoscope's light reads 70–120 without haze, 15–30
    /// under smoke). Below it the colour tests' contrast thresholds scale down in proportion
    /// (haze: the contrast normalisation of the module docs). 0 switches it off.
    pub clear_chroma: f64,
    /// The least scale of the contrast thresholds under haze (default 0.25: the thickest haze
    /// of the range `clear_chroma` is set for, a median chroma of 15 against 60, so that the
    /// normalisation follows the haze over all of that range; with 0.4 the thresholds stopped
    /// following it at a median of 24, and thick smoke with a crossing instrument lost the
    /// shafts whose interior was only 2-4 chroma units greyer than the tissue).
    pub min_contrast_scale: f64,
    /// A visible span at least this many shaft widths long (the width between the contours
    /// at the span's middle, undistorted pixels) is waived from the border test, as a span
    /// of `long_span_px` is (default 4; infinite: off). A pair of jaws or a tapered tip is
    /// at most a few widths long; a shaft cut short by a crossing instrument, or whose
    /// contours fade before the border, keeps a slender straight part.
    pub slender_span_widths: f64,
    /// Length of the instrument's articulated end beyond the shaft (wrist and jaws), in shaft
    /// diameters (default 3.5: a 10 mm wrist and 18 mm jaws on an 8 mm shaft). A narrower
    /// detection (`jaw_width_ratio`) starting at the distal end of a shaft's span and no longer
    /// than this many of that shaft's widths is taken for its wrist and jaws and dropped in
    /// the final selection: at any angle (an articulated wrist), or nearly in line with it. 0:
    /// both rules off.
    pub tip_length_diameters: f64,
    /// The width of a detection on an instrument's wrist and jaws as a fraction of its shaft's
    /// width, at most (default 0.85: the wrist is 0.94 of the 8 mm shaft, the jaws at most
    /// 0.75; a pair over both measures up to about 0.8 at its middle). Only a detection at most
    /// this fraction of a shaft's width can be its jaws; a shaft crossing behind is narrower
    /// only by its depth (0.7-0.95 for a few millimetres farther at 50-150 mm), so a crossing
    /// shaft under this ratio starting where another's span ends is still taken for jaws.
    pub jaw_width_ratio: f64,
    /// On a hazy frame (median chroma under `clear_chroma`), take each edgel's normal from
    /// the structure tensor summed over its 3×3 half-resolution neighbourhood instead of the
    /// pixel's own (default false: main's behaviour). On the tuning set (session 18) it found
    /// 6 more shafts of 120 under smoke and 3 fewer false detections over all frames, but on
    /// the report set 2 more false detections under smoke (4 → 6) with 3 more shafts
    /// (`docs/detection.md`, sixth round): opt-in until that is understood.
    pub haze_normal_integration: bool,
    /// Waive the border test for a visible span shorter than `long_span_px` when an end of it
    /// lies where a verified shaft crossing it (at least 15° apart) and nearer the lens hides
    /// it: within half the span's width outside that shaft's strip, the span's middle outside
    /// it, and not within half a width of that shaft's distal end (default false: main's
    /// behaviour). The end of a shaft seen behind a crossing instrument is where the instrument
    /// in front covers it, not a tip. On the tuning set (session 19) it found 3 more shafts of
    /// 103 with the crossing instrument and 1 more with smoke and the crossing instrument, with
    /// one wrong detection fewer; on the report set none more at `second` and one fewer at `all`, with 1 and 5 more
    /// wrong detections (`docs/detection.md`, seventh round): opt-in until that is understood.
    pub occluded_end_waiver: bool,
    /// On a hazy frame (median chroma under `clear_chroma`), re-measure each returned shaft's
    /// contours over its verified span with the profiles' luma weight divided by the haze
    /// scale (default true). Changes only the returned lines (centreline, contours, ends),
    /// never which shafts are returned. On the extended tuning set (session 20) the angle
    /// median under smoke fell from 0.062° to 0.041°, with smoke and the crossing instrument
    /// from 0.084° to 0.040° (`docs/detection.md`, eighth round).
    pub haze_refit: bool,
    /// On a clear frame without motion blur (`hough_window_under_haze`,
    /// `hough_window_max_blurred`), each edgel votes in the Hough transform at every angle
    /// within this many degrees of its normal (1° bins), at the distance its position gives at
    /// that angle, instead of once at its own normal (default 0: one vote). A contour is
    /// straight in undistorted pixels, while its edgels' normals (a 2×2 gradient at half
    /// resolution) scatter by degrees: one vote at the measured normal lands
    /// `s·δθ` from the line's distance bin (`s` the edgel's distance along the line from the
    /// foot of the perpendicular from the image centre: 10 px for 3° at 200 px), so a short
    /// or faint contour far out in the image spreads its votes over several cells and makes
    /// no line hypothesis. With the window every edgel votes at the true angle, where a
    /// contour's edgels all share one distance. On the extended tuning set (session 21) it
    /// found 1 more shaft of 120 at `default` and 3 more of 103 with the crossing instrument,
    /// with 1 and 2 fewer wrong detections; on the report set 9 more shafts with the crossing
    /// instrument but 7 more wrong detections, mostly motion-blurred frames, and it was left
    /// off (`docs/detection.md`, ninth round). With one peak per line and the motion-blur gate
    /// (`hough_window_max_blurred`; session 22, tenth round), on the tuning set with a
    /// motion-blur family 4 more shafts and 4 fewer wrong detections over the levels, and on
    /// the report set 10 more shafts (`default` +2, `second` +8) with no level's wrong
    /// detections up; but with it on, the calibration from the rendered grid's detected lines
    /// (`comanip-calib pixels`, both eyes) was refused by the selection stage's move test
    /// (statistic 58.1), where it had been applied (0.216 mm / 0.370°): off by default until
    /// that is understood (`docs/detection.md`, tenth round). At most 5: the gather takes an edgel only within
    /// 5.7-8.1° of the line's normal, so a wider window would vote edgels it never gathers.
    pub hough_normal_window_deg: u32,
    /// Apply `hough_normal_window_deg` on hazy frames too (median chroma under
    /// `clear_chroma`; default false). On the tuning set (session 21) it found 5 more shafts of
    /// 120 under smoke and 4 more of 103 under smoke with the crossing instrument, but under
    /// smoke 3 more wrong detections (the shaft with one contour on a shadow's or a
    /// highlight's edge, 2-5° off): opt-in.
    pub hough_window_under_haze: bool,
    /// Apply `hough_normal_window_deg` only on a frame where at most this fraction of the
    /// silhouette edgels (grey on one side, tissue on the other) is blurred (default 0.1;
    /// 1: always). A silhouette edgel is blurred when the chroma slope at it (half-resolution
    /// pixels) is under a quarter of the whole chroma step across it (±3 pixels): a moving
    /// instrument, rendered as the mean of the exposure's instants, has a staircase of weaker
    /// parallel steps for each contour, which the window turns into line hypotheses of their
    /// own, and a pair of one true contour and one step of another instant passes as a shaft
    /// a few pixels off. On the tuning set's motion-blur family (session 22) the window raised
    /// the wrong detections 12 → 27 without this gate and 12 → 11 with it (0.2: 18;
    /// `docs/detection.md`, tenth round).
    pub hough_window_max_blurred: f64,
    /// A gap of over 64 px in a pair's visible span (no edge on either contour, or an interior
    /// not grey) is bridged only when, on each side of it, at least this many stations (every
    /// 2 px) have both contours' edges, or the other contour's edges near its line there do not
    /// turn away from it (`bridge_max_divergence_deg`) (default 0: every gap is bridged, main's
    /// behaviour; 5 the setting measured). Such a gap is taken for a second instrument crossing
    /// in front of the shaft, which hides both contours; on both sides of it the same two
    /// silhouettes run on. Where the shaft runs along an image border close to the lens and
    /// one of its silhouettes is outside the image, the two outer edges of its jaws extended
    /// over the shaft have a long gap between the jaws and the border, with one of them on
    /// the shaft's corner on the far side, and the gap, bridged, made them a shaft converging
    /// on the jaws' tip. On the tuning set with the `along` family (session 24) 5 found 2
    /// shafts fewer with the crossing instrument and 1 false detection fewer at three levels;
    /// on the calibration's pixels grid it removed one wrong line of about 20
    /// (`docs/detection.md`, twelfth round): opt-in.
    pub bridge_min_both: usize,
    /// Where a segment of a pair's visible span next to a gap of over 64 px has fewer than
    /// `bridge_min_both` stations with both contours' edges, the gap is bridged only when the
    /// edges found within 3.5 px of each contour's line there (where it has no inlier edge, at
    /// least 4 of them) turn away from it by at most this angle, degrees (default 3; 90: off).
    pub bridge_max_divergence_deg: f64,
    /// The visible span's stations sample the interior also this far inside each contour
    /// (undistorted pixels, at most half the width; default 0: off; 4 the setting measured): a
    /// station is good only where the interior is grey against the outside right up to both
    /// contours. On the tuning set (session 24) 4 removed a third of the `along` family's false
    /// detections but added 4 at `default` and cost 3-4 shafts: opt-in.
    pub interior_near_px: f64,
    /// Over the verified span, where a contour has no inlier edge, the edges found within
    /// 3.5 px of its line may turn away from it by at most this angle, degrees
    /// ([`PairReject::Diverging`]; default 90: off). With 3 (session 24) the tuning set lost
    /// 19 shafts of 240 on clear frames: opt-in.
    pub span_max_divergence_deg: f64,
    /// The border test's reach past the span (a contour's edges followed past it, or a run
    /// of 32 px of edges on a contour line) counts only where both contours have edges
    /// (default false: either contour, main's behaviour). A shaft runs out of the view with
    /// both silhouettes; a pair of jaws one of whose lines runs on along the shaft's end to
    /// the border does not; but with it a third of the tuning set's shafts on clear frames
    /// were lost (session 24; a shaft whose other silhouette fades before the border): opt-in.
    pub border_reach_both: bool,
    /// On a hazy frame (median chroma under `clear_chroma`) where no shaft was found, run the
    /// line, pairing and verification stages once more on edgels at a coarser scale (default
    /// false): the edgel stage on the image averaged over 2×2 blocks (its half-resolution
    /// pass works on 4×4 blocks of the original), keeping only its silhouette edgels (grey
    /// on one side, tissue-coloured on the other, ±3 coarse pixels along the normal), mapped
    /// to the original's undistorted pixels. Haze scales a silhouette's step down by its
    /// transmittance while the noise of the 2×2 block means stays, so a faint contour's
    /// gradient per pixel falls under `edge_threshold`; over blocks twice as wide the
    /// gradient of a step spread over a few pixels doubles and the noise halves. The contours
    /// are still placed by the full-resolution profiles. On the tuning set (session 25) it
    /// found 4 more shafts of 240 under smoke (none elsewhere), with no more wrong detections
    /// at any level; adding every coarse edgel to the first pass instead found 10 more under
    /// smoke but added 4-11 wrong detections per hazy level (soft tissue edges, shadows), and
    /// the fallback on both scales' silhouette edgels 9 more with 2 more wrong
    /// (`docs/detection.md`, thirteenth round). Opt-in: turned on by default once, the live
    /// tracker's hardware-in-loop test then fell behind the camera (its cost on frames without
    /// a shaft, under emulation, not yet measured there).
    pub coarse_edgels_under_haze: bool,
    /// On a hazy frame, the walk that follows a refined contour outwards past its Hough
    /// support takes edges down to `0.75 · edge_threshold` times the frame's contrast scale
    /// (and at least a third of the contour's median strength), as the hazy refit does,
    /// instead of `0.75 · edge_threshold` (default false). Haze fades a contour with the
    /// tissue's transmittance, most towards a vignetted border. On the tuning set (session
    /// 25) it found 14 more shafts of 240 under smoke with 5 fewer wrong detections, but
    /// under smoke with the crossing instrument 2 more of 209 with 11 more wrong detections
    /// (pairs of lines on neither instrument's contours, confidence 0.02-0.3;
    /// `docs/detection.md`, thirteenth round): opt-in. [`OursConfig::haze_walk_checked`]
    /// (session 26) checks what the fainter edges may prove.
    pub haze_walk_floor: bool,
    /// With `haze_walk_floor`, check what the lower floor's edges may prove (default
    /// false; no effect without `haze_walk_floor` or on a clear frame): (1) a station of the
    /// visible span where neither contour has an edge at the clear frame's floor (only the
    /// hazy walk's fainter ones) is good only where the interior's margin over the outsides
    /// is at least half the pair's own (its median over the stations with such an edge): a
    /// shaft under even haze keeps its contrast along its length, while a pair of lines
    /// walked on over tissue or a soft shadow has the haze's bare minimum there; (2) the
    /// border test's waivers (a long or slender span) are judged on the extent of the
    /// stations with an edge at the clear floor; (3) the border test's reach counts only
    /// where the pair's axis is at a plausible depth (`min_depth_m / 2` to `max_depth_m`, as
    /// at the span's ends): past the point where two converging lines meet there is no
    /// cylinder. On the tuning set (session 26) the hazy walk with these checks found 17
    /// more shafts of 240 under smoke than the default with 9 fewer wrong detections (152 →
    /// 169, 10 → 1), and under smoke with the crossing instrument 2 more of 209 with 4 more
    /// wrong (20 → 24; without the checks 11 more; `docs/detection.md`, fourteenth round):
    /// opt-in.
    pub haze_walk_checked: bool,
}

impl Default for OursConfig {
    fn default() -> Self {
        Self {
            shaft_diameter_m: 0.008,
            min_depth_m: 0.010,
            max_depth_m: 0.300,
            min_length_px: 40.0,
            edge_threshold: 6.0,
            luma_weight: 1.0,
            profile_luma_weight: 0.3,
            max_lines: 40,
            max_detections: 2,
            min_chroma_contrast: 12.0,
            min_luma_contrast: 25.0,
            max_interior_chroma_ratio: 0.5,
            max_residual_px: 2.0,
            min_support: 0.5,
            border_margin_px: 24.0,
            long_span_px: 200.0,
            clear_chroma: 60.0,
            min_contrast_scale: 0.25,
            slender_span_widths: 4.0,
            tip_length_diameters: 3.5,
            jaw_width_ratio: 0.85,
            haze_normal_integration: false,
            occluded_end_waiver: false,
            haze_refit: true,
            hough_normal_window_deg: 0,
            hough_window_under_haze: false,
            hough_window_max_blurred: 0.1,
            bridge_min_both: 0,
            bridge_max_divergence_deg: 3.0,
            interior_near_px: 0.0,
            span_max_divergence_deg: 90.0,
            border_reach_both: false,
            coarse_edgels_under_haze: false,
            haze_walk_floor: false,
            haze_walk_checked: false,
        }
    }
}

/// Why an [`OursDetector`] could not be built.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum OursConfigError {
    /// The camera's intrinsics are unusable.
    #[error("camera intrinsics: {0}")]
    Intrinsics(#[from] IntrinsicsError),
    /// A setting is out of its range.
    #[error("ours.{field}: {why}")]
    Invalid {
        /// The setting's name.
        field: &'static str,
        /// What it must be.
        why: &'static str,
    },
}

impl OursConfig {
    /// Checks every setting's range.
    pub fn validate(&self) -> Result<(), OursConfigError> {
        let check = |ok: bool, field: &'static str, why: &'static str| {
            if ok { Ok(()) } else { Err(OursConfigError::Invalid { field, why }) }
        };
        let pos = |v: f64| v.is_finite() && v > 0.0;
        check(pos(self.shaft_diameter_m), "shaft_diameter_m", "finite and > 0")?;
        check(pos(self.min_depth_m), "min_depth_m", "finite and > 0")?;
        check(
            self.max_depth_m.is_finite() && self.max_depth_m > self.min_depth_m,
            "max_depth_m",
            "finite and > min_depth_m",
        )?;
        check(
            self.min_depth_m > 0.5 * self.shaft_diameter_m,
            "min_depth_m",
            "larger than the shaft's radius (the camera outside the shaft)",
        )?;
        check(pos(self.min_length_px), "min_length_px", "finite and > 0")?;
        check(pos(self.edge_threshold), "edge_threshold", "finite and > 0")?;
        check(self.luma_weight.is_finite() && self.luma_weight >= 0.0, "luma_weight", "finite and ≥ 0")?;
        check(
            self.profile_luma_weight.is_finite() && self.profile_luma_weight >= 0.0,
            "profile_luma_weight",
            "finite and ≥ 0",
        )?;
        check((1..=10_000).contains(&self.max_lines), "max_lines", "1 ..= 10000")?;
        check(self.max_detections >= 1, "max_detections", "≥ 1")?;
        check(
            self.min_chroma_contrast.is_finite() && self.min_chroma_contrast >= 0.0,
            "min_chroma_contrast",
            "finite and ≥ 0",
        )?;
        check(
            self.min_luma_contrast.is_finite() && self.min_luma_contrast >= 0.0,
            "min_luma_contrast",
            "finite and ≥ 0",
        )?;
        check(
            self.max_interior_chroma_ratio.is_finite() && self.max_interior_chroma_ratio >= 0.0,
            "max_interior_chroma_ratio",
            "finite and ≥ 0",
        )?;
        check(pos(self.max_residual_px), "max_residual_px", "finite and > 0")?;
        check((0.0..=1.0).contains(&self.min_support), "min_support", "in [0, 1]")?;
        check(
            !self.border_margin_px.is_nan() && self.border_margin_px >= 0.0,
            "border_margin_px",
            "≥ 0 (infinite: off)",
        )?;
        check(!self.long_span_px.is_nan() && self.long_span_px >= 0.0, "long_span_px", "≥ 0")?;
        check(self.clear_chroma.is_finite() && self.clear_chroma >= 0.0, "clear_chroma", "finite and ≥ 0")?;
        check(
            !self.slender_span_widths.is_nan() && self.slender_span_widths > 0.0,
            "slender_span_widths",
            "> 0 (infinite: off)",
        )?;
        check(
            self.tip_length_diameters.is_finite() && self.tip_length_diameters >= 0.0,
            "tip_length_diameters",
            "finite and ≥ 0",
        )?;
        check((0.0..=1.0).contains(&self.jaw_width_ratio), "jaw_width_ratio", "in [0, 1]")?;
        check(self.hough_normal_window_deg <= 5, "hough_normal_window_deg", "at most 5")?;
        check((0.0..=1.0).contains(&self.hough_window_max_blurred), "hough_window_max_blurred", "in [0, 1]")?;
        check(self.interior_near_px.is_finite() && self.interior_near_px >= 0.0, "interior_near_px", "finite and ≥ 0")?;
        check((0.0..=90.0).contains(&self.bridge_max_divergence_deg), "bridge_max_divergence_deg", "in [0, 90]")?;
        check(self.min_contrast_scale > 0.0 && self.min_contrast_scale <= 1.0, "min_contrast_scale", "in (0, 1]")?;
        Ok(())
    }
}

/// What makes a strip between two lines a shaft's interior.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Evidence {
    /// Grey against redder tissue.
    Colour,
    /// Haze washed the colour out: a luma step of this sign (+1 brighter inside) on both sides.
    Luma(f64),
}

/// The frame's contrast normalisation of the colour tests (haze).
///
/// Smoke adds the haze's own colour to every pixel and scales the scene's contrasts by its
/// transmittance (Koschmieder's model: `I = J·T + A·(1 − T)`), so fixed contrast thresholds
/// chosen on clear frames reject every shaft under thick haze. The frame's median chroma
/// (`2R − G − B`, mostly tissue) against the tissue's on a clear frame
/// ([`OursConfig::clear_chroma`]) estimates how much colour contrast the frame has left,
/// `scale`; the contrast thresholds (chroma and luma) and the interior's relative drop in
/// chroma are scaled by it. `scale` is 1 on a clear frame and at least
/// [`OursConfig::min_contrast_scale`] (below that, the tissue's own texture would pass).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Haze {
    /// The contrast scale, in `[min_contrast_scale, 1]`.
    scale: f64,
}

impl Haze {
    const CLEAR: Self = Self { scale: 1.0 };

    /// From the frame's median chroma and the settings.
    fn new(median: f64, cfg: &OursConfig) -> Self {
        if !(median.is_finite() && cfg.clear_chroma > 0.0) {
            return Self::CLEAR;
        }
        Self { scale: (median / cfg.clear_chroma).clamp(cfg.min_contrast_scale.min(1.0), 1.0) }
    }
}

/// The camera `k` with half its resolution: each pixel the mean of a 2×2 block of `k`'s
/// (the block `(2j, 2i)…(2j+1, 2i+1)`, centre `(2j + 0.5, 2i + 0.5)` of `k`), the same
/// rays and distortion.
fn half_camera(k: &Intrinsics) -> Intrinsics {
    Intrinsics {
        fx: 0.5 * k.fx,
        fy: 0.5 * k.fy,
        cx: 0.5 * (k.cx - 0.5),
        cy: 0.5 * (k.cy - 0.5),
        skew: 0.5 * k.skew,
        width: k.width / 2,
        height: k.height / 2,
        distortion: k.distortion,
    }
}

/// A verified shaft before it becomes a [`ShaftDetection`].
#[derive(Clone, Copy, Debug)]
struct Found {
    det: ShaftDetection,
    /// The axis point at the span's middle, undistorted pixels.
    mid: [f64; 2],
    /// The span's ends on the axis, undistorted pixels.
    ends: [[f64; 2]; 2],
    /// The width between the contours at the span's middle, undistorted pixels.
    width: f64,
    lines: [usize; 2],
    score: f64,
    /// The fraction of good stations in the span, the larger contour residual scale (pixels),
    /// the interior's contrast (fraction of three thresholds, unclamped), the span's length
    /// (undistorted pixels).
    support: f64,
    sigma: f64,
    contrast: f64,
    len: f64,
    /// The fraction of the span's stations where each contour has an edge.
    coverage: [f64; 2],
    /// The pair's rank in the verification order.
    rank: usize,
    /// The pair's ranking score before verification ([`OursDetector::pair_score`]).
    rank_score: f64,
}

impl Found {
    /// The final selection's merit: the product of the two stages' scores, the ranking's
    /// (the whole lines' evidence: overlap × the weaker line's votes × the interior's
    /// greyness) and the verification's (confidence × √length of the verified span).
    fn merit(&self) -> f64 {
        self.score * self.rank_score
    }
}

/// Our shaft detector (see the module docs). Keeps its working buffers between frames.
#[derive(Clone, Debug)]
pub struct OursDetector {
    k: Intrinsics,
    kmat: Matrix3<f64>,
    cfg: OursConfig,
    lens: Lens,
    table: HalfResTable,
    /// The coarse scale's edgel stage (`coarse_edgels_under_haze`): the table of the camera
    /// with half the resolution, its buffers and the 2×2-averaged image.
    coarse_table: HalfResTable,
    coarse_edges: EdgeBuffers,
    coarse_image: Vec<u8>,
    edges: EdgeBuffers,
    hough: Hough,
    pts: Vec<[f64; 2]>,
    w: Vec<f64>,
    res: Vec<f64>,
    col: [Vec<f64>; 8],
    samp: [Vec<(f64, [f64; 2])>; 2],
    /// Bounding box of the undistorted image, pixels: `(min, max)`.
    bounds: ([f64; 2], [f64; 2]),
    has: Vec<u8>,
    margin: Vec<f64>,
    /// The visible span's segments of good stations: (start, last, good, with both edges).
    segs: Vec<(usize, usize, usize, usize)>,
    /// The visible span's good stations.
    good: Vec<bool>,
    cands: Vec<Found>,
    found: Vec<Found>,
    pair_buf: Vec<(f64, usize, usize)>,
    /// The geometric candidate pairs of the frame: `(score bound, i, j, overlap)`.
    geo_buf: Vec<(f64, usize, usize, [f64; 2])>,
    /// Their order by score bound (indices into `geo_buf`), and the scored ones waiting:
    /// `(score, index into geo_buf)`.
    geo_order: Vec<usize>,
    scored: Vec<(f64, usize)>,
    /// Per Hough line of the frame: its refined contour (`None`: not yet refined).
    cache: Vec<Option<Option<Contour>>>,
    /// Per Hough line: its refined contour's inlier points, undistorted pixels.
    cache_pts: Vec<Vec<[f64; 2]>>,
    /// Per Hough line: the inlier points of `cache_pts` found at the clear frame's floor
    /// (not only by the hazy walk's lower one).
    cache_strong: Vec<Vec<[f64; 2]>>,
    /// The refinement's inlier points found at the clear frame's floor (its scratch).
    strong_pts: Vec<[f64; 2]>,
    /// Which of the refinement's walked points were found only under the hazy walk's lower
    /// floor (its scratch).
    walk_weak: Vec<bool>,
    /// Per station of the visible span: the contours with an edge at the clear floor (bits;
    /// filled only while [`Self::walk_checked`]).
    strong: Vec<u8>,
    /// The visible span's margins at the stations with an edge at the clear floor (scratch).
    strong_margins: Vec<f64>,
    /// Record a trace of this frame ([`OursDetector::detect_traced`]).
    tracing: bool,
    /// The stations of a returned contour's span where its edges were found (the hazy
    /// refit's scratch).
    cover: Vec<bool>,
    /// The pairs the cheap tests turned down (traced frames only).
    trace_rejects: Vec<(usize, usize, PairReject)>,
    /// The trace of the last traced frame.
    trace: OursTrace,
    /// The frame's haze estimate.
    haze: Haze,
    /// The ranks of the pairs skipped as duplicates of a verified shaft (traced frames only).
    redundant: Vec<usize>,
    /// The verified pairs dropped in the final selection (traced frames only): their rank,
    /// the rank of the detection they clashed with and the rule.
    clashes: Vec<(usize, (usize, ClashRule))>,
}

/// A contour refined in the full-resolution image.
#[derive(Clone, Copy, Debug)]
struct Contour {
    line: Line,
    sigma: f64,
}

impl OursDetector {
    /// A detector for camera `k` (image size, pinhole, distortion) with settings `cfg`.
    ///
    /// **Not for the real-time loop:** builds the undistortion table (one `undistort_px` per
    /// half-resolution pixel) and the buffers.
    pub fn new(k: Intrinsics, cfg: OursConfig) -> Result<Self, OursConfigError> {
        k.validate()?;
        cfg.validate()?;
        let table = HalfResTable::new(&k);
        let coarse_table = HalfResTable::new(&half_camera(&k));
        let (mut rmax, c) = (1.0f32, [k.cx as f32, k.cy as f32]);
        let mut bounds = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        // A strong distortion may not invert everywhere (the table then holds far or
        // non-finite positions): those pixels are ignored, and the accumulator is capped.
        let cap = 4.0 * (k.width as f32 + k.height as f32);
        for p in table.uv.iter().filter(|p| p.iter().all(|v| v.is_finite() && v.abs() < cap)) {
            rmax = rmax.max((p[0] - c[0]).hypot(p[1] - c[1]));
            for (i, pi) in p.iter().enumerate() {
                bounds.0[i] = bounds.0[i].min(f64::from(*pi) - 2.0);
                bounds.1[i] = bounds.1[i].max(f64::from(*pi) + 2.0);
            }
        }
        if !bounds.0.iter().chain(&bounds.1).all(|v| v.is_finite()) {
            bounds = ([0.0; 2], [0.0; 2]);
        }
        let hough = Hough::new(c, rmax + 4.0);
        Ok(Self {
            kmat: k.k(),
            lens: Lens::new(&k),
            k,
            cfg,
            table,
            coarse_table,
            coarse_edges: EdgeBuffers::silhouettes_only(),
            coarse_image: Vec::new(),
            edges: EdgeBuffers::default(),
            hough,
            pts: Vec::new(),
            w: Vec::new(),
            res: Vec::new(),
            col: Default::default(),
            samp: Default::default(),
            bounds,
            has: Vec::new(),
            margin: Vec::new(),
            segs: Vec::new(),
            good: Vec::new(),
            cands: Vec::new(),
            found: Vec::new(),
            pair_buf: Vec::new(),
            geo_buf: Vec::new(),
            geo_order: Vec::new(),
            scored: Vec::new(),
            cache: Vec::new(),
            cache_pts: Vec::new(),
            cache_strong: Vec::new(),
            strong_pts: Vec::new(),
            walk_weak: Vec::new(),
            strong: Vec::new(),
            strong_margins: Vec::new(),
            tracing: false,
            cover: Vec::new(),
            trace_rejects: Vec::new(),
            trace: OursTrace::default(),
            haze: Haze::CLEAR,
            redundant: Vec::new(),
            clashes: Vec::new(),
        })
    }

    /// The settings.
    pub fn config(&self) -> &OursConfig {
        &self.cfg
    }

    /// The final selection's jaws rule from the settings.
    fn jaws_rule(&self) -> JawsRule {
        JawsRule {
            tip_diameters: self.cfg.tip_length_diameters,
            width_ratio: self.cfg.jaw_width_ratio,
            size: [f64::from(self.k.width) - 1.0, f64::from(self.k.height) - 1.0],
            margin: if self.cfg.border_margin_px.is_finite() { self.cfg.border_margin_px } else { 24.0 },
        }
    }

    /// Distance from the optical centre to the axis of the cylinder (radius from the
    /// settings) whose contours are `a` and `b` (undistorted pixels), `interior` a pixel
    /// between them; metres.
    fn axis_distance(&self, a: &Line, b: &Line, interior: [f64; 2]) -> Option<f64> {
        let plane = |l: &Line| {
            let s = if l.distance(interior) >= 0.0 { 1.0 } else { -1.0 };
            let n = self.kmat.transpose() * Vector3::new(s * l.n[0], s * l.n[1], s * l.c);
            let norm = n.norm();
            (norm > 0.0).then(|| n / norm)
        };
        let (na, nb) = (plane(a)?, plane(b)?);
        let half = (0.5 * (1.0 + na.dot(&nb))).max(0.0).sqrt();
        let r = 0.5 * self.cfg.shaft_diameter_m;
        (half > 0.0).then(|| r / half)
    }

    /// The depth (camera z, metres) at which the ray of the undistorted pixel `px` meets the
    /// axis of the cylinder (radius from the settings) whose contours are `a` and `b`
    /// (`interior` a pixel between them): the axis is along `n₀ × n₁`, at distance
    /// `d = r / sin(θ/2)` from the optical centre towards `n₀ + n₁` (the plane normals
    /// oriented with the inside positive). `None` when degenerate.
    fn axis_depth_at(&self, a: &Line, b: &Line, interior: [f64; 2], px: [f64; 2]) -> Option<f64> {
        let plane = |l: &Line| {
            let s = if l.distance(interior) >= 0.0 { 1.0 } else { -1.0 };
            let n = self.kmat.transpose() * Vector3::new(s * l.n[0], s * l.n[1], s * l.c);
            let norm = n.norm();
            (norm > 0.0).then(|| n / norm)
        };
        let (na, nb) = (plane(a)?, plane(b)?);
        let dist = self.axis_distance(a, b, interior)?;
        let d = na.cross(&nb);
        let m = na + nb;
        let (dn, mn) = (d.norm(), m.norm());
        if !(dn > 1e-12 && mn > 1e-12) {
            return None;
        }
        let (d, p0) = (d / dn, m * (dist / mn));
        let r = self.k.k_inv() * Vector3::new(px[0], px[1], 1.0);
        // Closest points of t·r and p0 + λ·d.
        let (rr, rd) = (r.dot(&r), r.dot(&d));
        let (rp, dp) = (r.dot(&p0), d.dot(&p0));
        let den = rr - rd * rd;
        if den.abs() < 1e-15 {
            return None;
        }
        let lam = (rd * rp - rr * dp) / den;
        let z = (p0 + lam * d).z;
        z.is_finite().then_some(z)
    }

    /// The depth (camera z, metres) of verified shaft `f`'s axis on the ray of the undistorted
    /// pixel `px` ([`Self::axis_depth_at`] with its contours).
    fn depth_of(&self, f: &Found, px: [f64; 2]) -> Option<f64> {
        let [c0, c1] = f.det.contours;
        let (a, b) = (Line::from_abc(c0.abc)?, Line::from_abc(c1.abc)?);
        self.axis_depth_at(&a, &b, f.mid, px)
    }

    /// True when an end of the visible span `span` (along `t` from `o`) of the pair with
    /// contours `c` (`inside` a pixel between them) is hidden by a verified shaft crossing in
    /// front of it ([`hides_end`], and nearer the lens than the pair's axis on that end's ray).
    fn end_hidden(&self, c: [&Line; 2], inside: [f64; 2], o: [f64; 2], t: [f64; 2], span: [f64; 2]) -> bool {
        let d = [-t[1], t[0]];
        let jaws = self.jaws_rule();
        let sm = 0.5 * (span[0] + span[1]);
        let middle = [o[0] + sm * t[0], o[1] + sm * t[1]];
        span.iter().any(|&e| {
            let p = [o[0] + e * t[0], o[1] + e * t[1]];
            let width = match (c[0].hit(p, d), c[1].hit(p, d)) {
                (Some(l0), Some(l1)) => (l1 - l0).abs(),
                _ => return false,
            };
            let slack = 4.0f64.max(0.5 * width);
            let own = self.axis_depth_at(c[0], c[1], inside, p);
            self.cands.iter().any(|f| {
                hides_end(f, p, middle, t, slack, |e| jaws.inside(e))
                    && own.zip(self.depth_of(f, p)).is_some_and(|(z, zf)| zf < z)
            })
        })
    }

    /// Whether the hazy walk's checks apply to this frame ([`OursConfig::haze_walk_checked`]
    /// with [`OursConfig::haze_walk_floor`], on a hazy frame).
    fn walk_checked(&self) -> bool {
        self.cfg.haze_walk_floor && self.cfg.haze_walk_checked && self.haze.scale < 1.0
    }

    /// The pair's frame: an origin on `a`'s span and a unit direction along `a`.
    fn pair_frame(a: &LineCand) -> ([f64; 2], [f64; 2]) {
        let o = a.ends[0];
        let d = [a.ends[1][0] - o[0], a.ends[1][1] - o[1]];
        let n = d[0].hypot(d[1]);
        let t = if n > 0.0 { [d[0] / n, d[1] / n] } else { a.line.direction() };
        (o, t)
    }

    /// Refines one contour: two rounds of profiles (gates ±3 px every 3 px, then ±1.5 px
    /// every pixel) over `core` (the Hough support, `s` along the frame `(o, t)`), each
    /// followed by a robust fit; then the contour is followed outwards to `full` (the line
    /// inside the image, every 2 px) as long as edges keep coming within 1.5 px of the line, and refitted.
    /// Its inlier edge points (with their `s`, sorted) are left in `self.samp[which]`.
    #[allow(clippy::too_many_arguments)]
    fn refine(
        &mut self,
        sampler: &Sampler<'_>,
        start: Line,
        o: [f64; 2],
        t: [f64; 2],
        core: [f64; 2],
        full: [f64; 2],
        which: usize,
    ) -> Option<Contour> {
        let mut line = start;
        let mut min_strength = 0.75 * self.cfg.edge_threshold;
        // A third of the contour's median edge strength (set by the rounds below).
        let mut third = 0.0f64;
        // The walk along the line: the foot of o on it, its own direction aligned with t.
        let frame = |line: &Line| {
            let lt = line.direction();
            let lt = if lt[0] * t[0] + lt[1] * t[1] >= 0.0 { lt } else { [-lt[0], -lt[1]] };
            let dist = line.distance(o);
            ([o[0] - dist * line.n[0], o[1] - dist * line.n[1]], lt)
        };
        for (gate, step) in [(3.0, 3.0), (1.5, 1.0)] {
            self.pts.clear();
            self.res.clear();
            let (o_l, lt) = frame(&line);
            let n_steps = ((core[1] - core[0]) / step).floor().max(0.0) as usize;
            for k in 0..=n_steps {
                let s = core[0] + k as f64 * step;
                let p = [o_l[0] + s * lt[0], o_l[1] + s * lt[1]];
                if let Some((off, st)) = sampler.edge_offset(&line, p, gate, min_strength) {
                    self.pts.push([p[0] + off * line.n[0], p[1] + off * line.n[1]]);
                    self.res.push(st);
                }
            }
            if self.pts.len() < 8 {
                return None;
            }
            // From now on, an edge must be at least a third of this contour's typical one
            // (weak tissue texture along the line is not the contour).
            let mid = self.res.len() / 2;
            self.res.select_nth_unstable_by(mid, f64::total_cmp);
            third = third.max(self.res[mid] / 3.0);
            min_strength = min_strength.max(third);
            let f = robust_fit(&self.pts, line, &mut self.w, &mut self.res)?;
            line = f.line;
        }
        // Follow the contour outwards from both ends of the core. Under haze
        // (`haze_walk_floor`) the absolute floor is scaled by the frame's contrast scale, as
        // the hazy refit's is: the contour fades towards a vignetted, hazy border with the
        // tissue's transmittance; a third of its own median strength still holds.
        let walk_floor = if self.cfg.haze_walk_floor {
            (0.75 * self.cfg.edge_threshold * self.haze.scale).max(third)
        } else {
            min_strength
        };
        let (o_l, lt) = frame(&line);
        let n_core = self.pts.len();
        self.walk_weak.clear();
        for dir in [-1.0f64, 1.0] {
            let (from, to) = if dir < 0.0 { (core[0], full[0]) } else { (core[1], full[1]) };
            let mut misses = 0u32;
            let mut s = from + 2.0 * dir;
            while (to - s) * dir > 0.0 && misses < 24 {
                let p = [o_l[0] + s * lt[0], o_l[1] + s * lt[1]];
                match sampler.edge_offset(&line, p, 2.0, walk_floor) {
                    Some((off, st)) if off.abs() <= 1.5 => {
                        self.pts.push([p[0] + off * line.n[0], p[1] + off * line.n[1]]);
                        self.walk_weak.push(st < min_strength);
                        misses = misses.saturating_sub(1);
                    }
                    _ => misses += 2,
                }
                s += 2.0 * dir;
            }
        }
        let f = robust_fit(&self.pts, line, &mut self.w, &mut self.res)?;
        let line = f.line;
        let samp = &mut self.samp[which];
        samp.clear();
        self.strong_pts.clear();
        for (k, (p, w)) in self.pts.iter().zip(&self.w).enumerate() {
            if *w > 0.0 {
                samp.push(((p[0] - o[0]) * t[0] + (p[1] - o[1]) * t[1], *p));
                if k < n_core || !self.walk_weak.get(k - n_core).copied().unwrap_or(false) {
                    self.strong_pts.push(*p);
                }
            }
        }
        samp.sort_by(|x, y| x.0.total_cmp(&y.0));
        Some(Contour { line, sigma: f.sigma })
    }

    /// The refined contour of Hough line `idx` (computed once per frame, in the line's own
    /// frame), its inlier edge points left in `self.cache_pts[idx]`.
    fn contour_of(&mut self, sampler: &Sampler<'_>, idx: usize) -> Option<Contour> {
        if let Some(c) = self.cache[idx] {
            return c;
        }
        let cand = self.hough.lines[idx];
        let (o, t) = Self::pair_frame(&cand);
        let len = (cand.ends[1][0] - o[0]) * t[0] + (cand.ends[1][1] - o[1]) * t[1];
        let full = self.line_range(o, t);
        let core = [0.0f64.max(full[0]), len.min(full[1])];
        // Where haze has washed the colour out, the contour is a luma edge: retry with luma
        // at full weight.
        let c = self.refine(sampler, cand.line, o, t, core, full, 0).or_else(|| {
            let luma = Sampler { luma_weight: 1.0, ..*sampler };
            self.refine(&luma, cand.line, o, t, core, full, 0)
        });
        let pts = &mut self.cache_pts[idx];
        pts.clear();
        pts.extend(self.samp[0].iter().map(|(_, p)| *p));
        let strong = &mut self.cache_strong[idx];
        strong.clear();
        strong.extend_from_slice(&self.strong_pts);
        self.cache[idx] = Some(c);
        c
    }

    /// The extent along `t` (from `o`) of the undistorted image's bounding box.
    fn line_range(&self, o: [f64; 2], t: [f64; 2]) -> [f64; 2] {
        let (lo, hi) = self.bounds;
        let mut r = [f64::INFINITY, f64::NEG_INFINITY];
        for c in [[lo[0], lo[1]], [hi[0], lo[1]], [lo[0], hi[1]], [hi[0], hi[1]]] {
            let sc = (c[0] - o[0]) * t[0] + (c[1] - o[1]) * t[1];
            r = [r[0].min(sc), r[1].max(sc)];
        }
        r
    }

    /// The visible span of the pair: stations every 2 px along `t` over `range` are good where
    /// both contours have an inlier edge within 2 px and the interior (mean of three samples)
    /// is less red than both outsides by half the colour contrast (smoothed over 5 stations),
    /// or one contour has one and the contrast is full; the span is the run of good stations
    /// (gaps up to 64 px: a crossing instrument) with
    /// the most good stations. Returns the span and the fraction of good stations in it.
    /// With [`OursConfig::haze_walk_checked`] on a hazy frame, a station where neither of the
    /// pair's Hough lines `lines` has an edge found at the clear floor needs half the pair's
    /// median margin as well.
    #[allow(clippy::too_many_arguments)]
    fn visible_span(
        &mut self,
        sampler: &Sampler<'_>,
        c: [&Line; 2],
        o: [f64; 2],
        t: [f64; 2],
        range: [f64; 2],
        mode: Evidence,
        lines: [usize; 2],
    ) -> Option<([f64; 2], f64)> {
        const STEP: f64 = 2.0;
        let n = ((range[1] - range[0]) / STEP).floor().max(0.0) as usize + 1;
        self.has.clear();
        self.has.resize(n, 0);
        for (bit, samp) in self.samp.iter().enumerate() {
            for (s, _) in samp {
                let i = ((s - range[0]) / STEP).round();
                if i >= 0.0 && (i as usize) < n {
                    let i = i as usize;
                    for j in i.saturating_sub(1)..=(i + 1).min(n - 1) {
                        self.has[j] |= 1 << bit;
                    }
                }
            }
        }
        // The stations with an edge found at the clear frame's floor (`haze_walk_checked`).
        let checked = self.walk_checked();
        self.strong.clear();
        self.strong.resize(n, 0);
        for (bit, idx) in lines.iter().enumerate().filter(|_| checked) {
            for p in &self.cache_strong[*idx] {
                let i = (((p[0] - o[0]) * t[0] + (p[1] - o[1]) * t[1] - range[0]) / STEP).round();
                if i >= 0.0 && (i as usize) < n {
                    let i = i as usize;
                    for j in i.saturating_sub(1)..=(i + 1).min(n - 1) {
                        self.strong[j] |= 1 << bit;
                    }
                }
            }
        }
        self.margin.clear();
        self.margin.resize(n, f64::NAN);
        let d = [-t[1], t[0]];
        for i in 0..n {
            if self.has[i] == 0 {
                continue;
            }
            let s = range[0] + i as f64 * STEP;
            let q = [o[0] + s * t[0], o[1] + s * t[1]];
            let (Some(l0), Some(l1)) = (c[0].hit(q, d), c[1].hit(q, d)) else { continue };
            let m = 0.5 * (l0 + l1);
            let h = 0.5 * (l1 - l0);
            // The margin of the interior over the outsides: less red (colour), or the luma step
            // in the pair's sign (luma).
            let at = |lam: f64| {
                sampler.sample(q[0] + lam * d[0], q[1] + lam * d[1]).map(|v| match mode {
                    Evidence::Colour => v.0,
                    Evidence::Luma(sign) => -sign * v.1,
                })
            };
            let (Some(i0), Some(i1), Some(i2)) = (at(m - 0.3 * h), at(m), at(m + 0.3 * h)) else { continue };
            let margin = 4.0 * h.signum();
            let (Some(out0), Some(out1)) = (at(l0 - margin), at(l1 + margin)) else { continue };
            let inside = (i0 + i1 + i2) / 3.0;
            // The interior just inside each contour too (`interior_near_px`): a line that
            // runs on outside the shaft's silhouette has tissue just inside it.
            let near = self.cfg.interior_near_px.min(0.5 * h.abs()) * h.signum();
            let (in0, in1) = if near != 0.0 {
                match (at(l0 + near), at(l1 - near)) {
                    (Some(n0), Some(n1)) => (inside.max(n0), inside.max(n1)),
                    _ => continue,
                }
            } else {
                (inside, inside)
            };
            self.margin[i] = (out0 - in0).min(out1 - in1);
        }
        let need = self.haze.scale
            * match mode {
                Evidence::Colour => 0.5 * self.cfg.min_chroma_contrast,
                Evidence::Luma(_) => 0.5 * self.cfg.min_luma_contrast,
            };
        // Segments of good stations whose gaps are all shorter than `short_gap`: (start, last,
        // good stations, good stations with both edges).
        let short_gap = (64.0 / STEP) as usize;
        // A station with only the hazy walk's fainter edges needs half the pair's own margin
        // (its median over the stations with an edge at the clear floor).
        let walked_need = if checked {
            self.strong_margins.clear();
            self.strong_margins.extend(
                self.strong.iter().zip(&self.margin).filter(|(s, m)| **s != 0 && m.is_finite()).map(|(_, m)| *m),
            );
            let mid = self.strong_margins.len() / 2;
            if self.strong_margins.is_empty() {
                f64::INFINITY
            } else {
                0.5 * *self.strong_margins.select_nth_unstable_by(mid, f64::total_cmp).1
            }
        } else {
            f64::NEG_INFINITY
        };
        self.segs.clear();
        self.good.clear();
        self.good.resize(n, false);
        for i in 0..n {
            let (lo, hi) = (i.saturating_sub(2), (i + 2).min(n - 1));
            let (mut sum, mut cnt) = (0.0, 0);
            for m in &self.margin[lo..=hi] {
                if m.is_finite() {
                    sum += m;
                    cnt += 1;
                }
            }
            // Both edges and a grey interior; or one edge (the other may fade against bright
            // fat or in a hazy corner) and a clearly grey interior.
            let mean = if cnt >= 2 { sum / cnt as f64 } else { f64::NEG_INFINITY };
            let faint = checked && self.strong[i] == 0 && mean < walked_need;
            let both = self.has[i] == 3 && mean >= need && !faint;
            let good = both || (self.has[i] != 0 && mean >= 2.0 * need && !faint);
            if !good {
                continue;
            }
            self.good[i] = true;
            match self.segs.last_mut() {
                Some(seg) if i - seg.1 - 1 < short_gap => {
                    seg.1 = i;
                    seg.2 += 1;
                    seg.3 += usize::from(both);
                }
                _ => self.segs.push((i, i, 1, usize::from(both))),
            }
        }
        // Runs: segments joined across a long gap, which is taken for an occlusion (a second
        // instrument crossing in front hides both contours; the gap does not count against the
        // support), when both contours run on on each side of it (`two_sided`): the same two
        // contour lines with a grey interior on both sides, one cylinder. Gaps shorter than
        // `short_gap` count against the support. Best: the run with the most good stations;
        // (start, last, good stations, stations in long gaps).
        let mut best: Option<(usize, usize, usize, usize)> = None;
        let mut k = 0;
        while k < self.segs.len() {
            let (start, mut last, mut count, _) = self.segs[k];
            let mut hidden = 0;
            let mut j = k;
            while j + 1 < self.segs.len()
                && self.two_sided(sampler, c, o, t, range, self.segs[j])
                && self.two_sided(sampler, c, o, t, range, self.segs[j + 1])
            {
                hidden += self.segs[j + 1].0 - self.segs[j].1 - 1;
                last = self.segs[j + 1].1;
                count += self.segs[j + 1].2;
                j += 1;
            }
            if best.is_none_or(|b| count > b.2) {
                best = Some((start, last, count, hidden));
            }
            k = j + 1;
        }
        let (start, last, count, hidden) = best?;
        let span = [range[0] + start as f64 * STEP, range[0] + last as f64 * STEP];
        Some((span, count as f64 / (last - start + 1 - hidden).max(1) as f64))
    }

    /// Whether the segment `seg` (`(start, last, good stations, good stations with both
    /// edges)`, stations of [`Self::visible_span`] every 2 px over `range` along `t` from `o`)
    /// may be joined to the next across a long gap: at least [`OursConfig::bridge_min_both`] of
    /// its good stations have both contours' edges; or, where a contour has no inlier edge,
    /// the edges found near its line (a profile within 3.5 px of it) do not diverge from it:
    /// over at least 4 of them, their offsets from the line change by less than
    /// [`OursConfig::bridge_max_divergence_deg`] along it. The part of a shaft seen past a
    /// crossing instrument may have the inlier edges of one contour only (the contour's
    /// refinement stops at a gap of 24 px), while the other is there, parallel to its line
    /// (a few pixels off where it was extrapolated across the gap); an edge of a wrist or jaws
    /// extended over a shaft whose other silhouette is out of the image meets that
    /// silhouette at the pair's error in angle.
    #[allow(clippy::too_many_arguments)]
    fn two_sided(
        &self,
        sampler: &Sampler<'_>,
        c: [&Line; 2],
        o: [f64; 2],
        t: [f64; 2],
        range: [f64; 2],
        seg: (usize, usize, usize, usize),
    ) -> bool {
        const STEP: f64 = 2.0;
        let (start, last, _, both) = seg;
        if both >= self.cfg.bridge_min_both {
            return true;
        }
        let max_slope = self.cfg.bridge_max_divergence_deg.to_radians().tan();
        (0..2).all(|k| {
            let mut fit = SlopeFit::default();
            for i in start..=last {
                if !self.good[i] || self.has[i] & (1 << k) != 0 {
                    continue;
                }
                let s = range[0] + i as f64 * STEP;
                if let Some(off) = self.near_edge(sampler, c[k], o, t, s) {
                    fit.add(s - range[0] - start as f64 * STEP, off);
                }
            }
            fit.slope(4.0).is_none_or(|slope| slope.abs() <= max_slope)
        })
    }

    /// Whether, over the span `span` (along `t` from `o`; the stations of
    /// [`Self::visible_span`] every 2 px over `range`), one of the contours `c`, along a run of
    /// stations where it has no inlier edge, has edges near its line (a profile within 3.5 px
    /// of it, at least 5) that turn away from it by more than
    /// [`OursConfig::bridge_max_divergence_deg`]: the visible span's stations with one edge
    /// are good, and a line that is an edge of a wrist or jaws extended over the shaft meets
    /// the shaft's silhouette at the pair's error in angle there.
    #[allow(clippy::too_many_arguments)]
    fn diverges(
        &self,
        sampler: &Sampler<'_>,
        c: [&Line; 2],
        o: [f64; 2],
        t: [f64; 2],
        range: [f64; 2],
        span: [f64; 2],
    ) -> bool {
        const STEP: f64 = 2.0;
        let max_slope = self.cfg.span_max_divergence_deg.to_radians().tan();
        let first = ((span[0] - range[0]) / STEP).ceil().max(0.0) as usize;
        let last = (((span[1] - range[0]) / STEP).floor().max(0.0) as usize).min(self.has.len().saturating_sub(1));
        let steep = |fit: &SlopeFit| fit.slope(5.0).is_some_and(|slope| slope.abs() > max_slope);
        (0..2).any(|k| {
            let mut fit = SlopeFit::default();
            for i in first..=last {
                if self.has[i] & (1 << k) != 0 {
                    if steep(&fit) {
                        return true;
                    }
                    fit = SlopeFit::default();
                    continue;
                }
                let s = range[0] + i as f64 * STEP;
                if let Some(off) = self.near_edge(sampler, c[k], o, t, s) {
                    fit.add(s - span[0], off);
                }
            }
            steep(&fit)
        })
    }

    /// The offset (pixels along `line`'s normal, within ±3.5 px) of the edge found near the
    /// contour line `line` on the profile across it where the normal to `t` at the station
    /// `s` (pixels along `t` from `o`) meets it, at least 0.75 of
    /// [`OursConfig::edge_threshold`] strong; `None` when there is none or the normal does
    /// not meet the line.
    fn near_edge(&self, sampler: &Sampler<'_>, line: &Line, o: [f64; 2], t: [f64; 2], s: f64) -> Option<f64> {
        let d = [-t[1], t[0]];
        let q = [o[0] + s * t[0], o[1] + s * t[1]];
        let l = line.hit(q, d)?;
        let p = [q[0] + l * d[0], q[1] + l * d[1]];
        let floor = 0.75 * self.cfg.edge_threshold;
        sampler.edge_offset(line, p, 4.0, floor).map(|(off, _)| off).filter(|off| off.abs() <= 3.5)
    }

    /// Refits contour `which` with its inlier points inside `span`.
    fn refit_in_span(&mut self, which: usize, start: Line, span: [f64; 2]) -> Option<Contour> {
        self.pts.clear();
        self.pts.extend(self.samp[which].iter().filter(|(s, _)| *s >= span[0] && *s <= span[1]).map(|(_, p)| *p));
        if self.pts.len() < 8 {
            return None;
        }
        let f = robust_fit(&self.pts, start, &mut self.w, &mut self.res)?;
        Some(Contour { line: f.line, sigma: f.sigma })
    }

    /// Checks and refines the pair `(ia, ib)` of line hypotheses.
    fn verify(&mut self, image: &RgbView<'_>, ia: usize, ib: usize) -> Result<Found, PairReject> {
        use PairReject as R;
        let (a, b) = (self.hough.lines[ia], self.hough.lines[ib]);
        let cfg = self.cfg;
        let lens = self.lens;
        let sampler = Sampler { image, lens: &lens, luma_weight: cfg.profile_luma_weight };
        let (o, t) = Self::pair_frame(&a);
        let proj = |p: [f64; 2]| (p[0] - o[0]) * t[0] + (p[1] - o[1]) * t[1];
        let sa = [proj(a.ends[0]), proj(a.ends[1])];
        let sb = {
            let (x, y) = (proj(b.ends[0]), proj(b.ends[1]));
            [x.min(y), x.max(y)]
        };
        let ov = [sa[0].max(sb[0]), sa[1].min(sb[1])];
        if ov[1] - ov[0] < 0.6 * cfg.min_length_px {
            return Err(R::Overlap);
        }
        let coarse = interior(&sampler, [&a.line, &b.line], o, t, ov, &mut self.col).ok_or(R::CoarseColour)?;
        let mode = self.colour_mode(&coarse).ok_or(R::CoarseColour)?;
        // Both contours, refined once per frame each; their inlier points in the pair's frame.
        let range = self.line_range(o, t);
        let ca = self.contour_of(&sampler, ia).ok_or(R::ContourA)?;
        let cb = self.contour_of(&sampler, ib).ok_or(R::ContourB)?;
        for (which, idx) in [(0, ia), (1, ib)] {
            let samp = &mut self.samp[which];
            samp.clear();
            samp.extend(self.cache_pts[idx].iter().map(|p| ((p[0] - o[0]) * t[0] + (p[1] - o[1]) * t[1], *p)));
            samp.sort_by(|x, y| x.0.total_cmp(&y.0));
        }
        let (span, support) =
            self.visible_span(&sampler, [&ca.line, &cb.line], o, t, range, mode, [ia, ib]).ok_or(R::NoSpan)?;
        let len = span[1] - span[0];
        if len < cfg.min_length_px {
            return Err(R::ShortSpan);
        }
        if support < cfg.min_support {
            return Err(R::Support);
        }
        let mut ca = self.refit_in_span(0, ca.line, span).ok_or(R::Refit)?;
        let mut cb = self.refit_in_span(1, cb.line, span).ok_or(R::Refit)?;
        // Trim ends where either contour leaves its line systematically (the wrist, a bent or
        // thinner link, a tapered tip), then refit.
        let mut span = span;
        for _ in 0..24 {
            const WIN: f64 = 16.0;
            let off = |samp: &[(f64, [f64; 2])], line: &Line, lo: f64, hi: f64| {
                let (mut sum, mut n) = (0.0, 0);
                for (s, p) in samp {
                    if *s >= lo && *s <= hi {
                        sum += line.distance(*p);
                        n += 1;
                    }
                }
                if n >= 4 { (sum / n as f64).abs() } else { 0.0 }
            };
            let thr = 0.35;
            let head = off(&self.samp[0], &ca.line, span[0], span[0] + WIN).max(off(
                &self.samp[1],
                &cb.line,
                span[0],
                span[0] + WIN,
            ));
            let tail = off(&self.samp[0], &ca.line, span[1] - WIN, span[1]).max(off(
                &self.samp[1],
                &cb.line,
                span[1] - WIN,
                span[1],
            ));
            if head <= thr && tail <= thr {
                break;
            }
            if head > thr {
                span[0] += 0.5 * WIN;
            }
            if tail > thr {
                span[1] -= 0.5 * WIN;
            }
            if span[1] - span[0] < cfg.min_length_px {
                return Err(R::Trimmed);
            }
            let (Some(na), Some(nb)) = (self.refit_in_span(0, ca.line, span), self.refit_in_span(1, cb.line, span))
            else {
                return Err(R::Refit);
            };
            (ca, cb) = (na, nb);
        }
        let len = span[1] - span[0];
        if self.cfg.span_max_divergence_deg < 90.0 && self.diverges(&sampler, [&ca.line, &cb.line], o, t, range, span) {
            return Err(R::Diverging);
        }
        let sigma = ca.sigma.max(cb.sigma);
        if sigma > cfg.max_residual_px {
            return Err(R::Residual);
        }
        // Interior point: middle of the two contours at the span's middle.
        let sm = 0.5 * (span[0] + span[1]);
        let q = [o[0] + sm * t[0], o[1] + sm * t[1]];
        let d = [-t[1], t[0]];
        let (la, lb) = (ca.line.hit(q, d).ok_or(R::Geometry)?, cb.line.hit(q, d).ok_or(R::Geometry)?);
        let mid = 0.5 * (la + lb);
        let inside = [q[0] + mid * d[0], q[1] + mid * d[1]];
        let dist = self.axis_distance(&ca.line, &cb.line, inside).ok_or(R::Geometry)?;
        if !(dist >= cfg.min_depth_m && dist <= cfg.max_depth_m) {
            return Err(R::AxisDistance);
        }
        // The axis's depth at both ends of the visible span must be plausible too (a tapered
        // tip seen as a cylinder would reach far beyond the range towards its apex).
        for e in span {
            let p = [o[0] + e * t[0], o[1] + e * t[1]];
            let z = self.axis_depth_at(&ca.line, &cb.line, inside, p).unwrap_or(f64::NAN);
            if !(z >= 0.5 * cfg.min_depth_m && z <= cfg.max_depth_m) {
                return Err(R::EndDepth);
            }
        }
        let fine = interior(&sampler, [&ca.line, &cb.line], o, t, span, &mut self.col).ok_or(R::FineColour)?;
        if self.colour_mode(&fine) != Some(mode) {
            return Err(R::FineColour);
        }
        let c0 = ImageLine::new(ca.line.abc()).map_err(|_| R::Axis)?;
        let c1 = ImageLine::new(cb.line.abc()).map_err(|_| R::Axis)?;
        let axis = axis_from_contours(&self.kmat, &c0, &c1, inside).map_err(|_| R::Axis)?;
        let axis_l = Line::from_abc(axis.abc).ok_or(R::Axis)?;
        // Ends: the span's ends projected on the axis, mapped to measured pixels.
        let mut ends_px = [[0.0; 2]; 2];
        let mut ends = [[0.0; 2]; 2];
        for ((e, u), s) in ends_px.iter_mut().zip(&mut ends).zip(span) {
            let p = [o[0] + s * t[0], o[1] + s * t[1]];
            let dd = axis_l.distance(p);
            let f = [p[0] - dd * axis_l.n[0], p[1] - dd * axis_l.n[1]];
            *u = f;
            let (x, y) = self.lens.distort_px(f[0], f[1]);
            *e = [x, y];
        }
        // A slender span (many widths long) is waived too: a pair of jaws is at most a few
        // shaft widths long, while a shaft cut short by a crossing instrument or faded into
        // a vignetted, hazy border region keeps its slender straight part.
        // With `haze_walk_checked`, the waivers are judged on the stations with an edge at the
        // clear frame's floor.
        let wlen = if self.walk_checked() {
            let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
            for (i, h) in self.strong.iter().enumerate() {
                let sv = range[0] + i as f64 * 2.0;
                if *h != 0 && sv >= span[0] && sv <= span[1] {
                    lo = lo.min(sv);
                    hi = hi.max(sv);
                }
            }
            (hi - lo).max(0.0)
        } else {
            len
        };
        let slender = wlen >= cfg.slender_span_widths * (la - lb).abs();
        if cfg.border_margin_px.is_finite()
            && wlen < cfg.long_span_px
            && !slender
            && !(cfg.occluded_end_waiver && self.end_hidden([&ca.line, &cb.line], inside, o, t, span))
        {
            let (w, h) = (f64::from(self.k.width) - 1.0, f64::from(self.k.height) - 1.0);
            let near = |p: &[f64; 2]| p[0].min(p[1]).min(w - p[0]).min(h - p[1]) <= cfg.border_margin_px;
            // The contours' edges may run on past the span's colour evidence (haze, vignetting):
            // follow either contour's inlier edges from each end (gaps up to 32 px).
            let mut reach = span;
            for samp in &self.samp {
                let (mut lo, mut hi) = (span[0], span[1]);
                for (sv, _) in samp.iter().rev().filter(|(sv, _)| *sv < span[0]) {
                    if lo - sv > 32.0 {
                        break;
                    }
                    lo = *sv;
                }
                for (sv, _) in samp.iter().filter(|(sv, _)| *sv > span[1]) {
                    if sv - hi > 32.0 {
                        break;
                    }
                    hi = *sv;
                }
                reach = if cfg.border_reach_both {
                    [
                        if reach[0] < span[0] { reach[0].max(lo) } else { lo },
                        if reach[1] > span[1] { reach[1].min(hi) } else { hi },
                    ]
                } else {
                    [reach[0].min(lo), reach[1].max(hi)]
                };
            }
            // A contour running on past a gap of any length (a second instrument crossing in
            // front hides the part between): a run of at least 32 px where a contour has an
            // edge at every station (those of `visible_span`, every 2 px over `range`) extends
            // the reach; the lines of a pair of jaws run on over tissue.
            let mut run = 0usize;
            for (i, &h) in self.has.iter().enumerate() {
                let on = if cfg.border_reach_both { h == 3 } else { h != 0 };
                run = if on { run + 1 } else { 0 };
                if run >= 16 {
                    let (first, last) = (range[0] + (i + 1 - run) as f64 * 2.0, range[0] + i as f64 * 2.0);
                    reach = [reach[0].min(first), reach[1].max(last)];
                }
            }
            let reach_px = reach.map(|sv| {
                let p = [o[0] + sv * t[0], o[1] + sv * t[1]];
                let (x, y) = self.lens.distort_px(p[0], p[1]);
                [x, y]
            });
            // With `haze_walk_checked`, a reach past the point where the contours meet (no
            // cylinder there) or to an implausible depth does not count.
            let checked = self.walk_checked();
            let plausible = |sv: f64| {
                !checked
                    || self
                        .axis_depth_at(&ca.line, &cb.line, inside, [o[0] + sv * t[0], o[1] + sv * t[1]])
                        .is_some_and(|z| z >= 0.5 * cfg.min_depth_m && z <= cfg.max_depth_m)
            };
            if !reach_px.iter().zip(reach).any(|(p, sv)| near(p) && plausible(sv)) {
                return Err(R::Border);
            }
        }
        // The fraction of the span's stations with an edge of each contour (the trace's).
        let coverage = {
            let (mut n, mut c) = (0usize, [0usize; 2]);
            for (i, h) in self.has.iter().enumerate() {
                let sv = range[0] + i as f64 * 2.0;
                if sv >= span[0] && sv <= span[1] {
                    n += 1;
                    c[0] += usize::from(h & 1 != 0);
                    c[1] += usize::from(h & 2 != 0);
                }
            }
            c.map(|v| v as f64 / n.max(1) as f64)
        };
        let contrast = match mode {
            Evidence::Colour => {
                (fine.outside[0] - fine.inside).min(fine.outside[1] - fine.inside)
                    / (3.0 * cfg.min_chroma_contrast.max(1e-9))
            }
            Evidence::Luma(sign) => {
                fine.luma_outside.iter().map(|o| sign * (fine.luma_inside - o)).fold(f64::INFINITY, f64::min)
                    / (3.0 * cfg.min_luma_contrast.max(1e-9))
            }
        };
        let confidence = support / (1.0 + (sigma / 0.5).powi(2)) * contrast.clamp(0.0, 1.0);
        Ok(Found {
            det: ShaftDetection { centreline: axis, contours: [c0, c1], ends_px, confidence },
            mid: {
                let dd = axis_l.distance(q);
                [q[0] - dd * axis_l.n[0], q[1] - dd * axis_l.n[1]]
            },
            ends,
            width: (la - lb).abs(),
            lines: [ia, ib],
            score: confidence * len.sqrt(),
            support,
            sigma,
            contrast,
            len,
            coverage,
            rank: 0,
            rank_score: 0.0,
        })
    }

    /// Re-measures a returned shaft's two contours under haze ([`OursConfig::haze_refit`]):
    /// a profile every pixel along its verified span, only where the verified contour had
    /// an edge (within 2 px: not across a crossing instrument), the luma weighted by
    /// `profile_luma_weight / haze scale` and the strength floor scaled by the haze alike,
    /// then the same robust fit; the axis and its ends follow. Kept only within 0.5° and
    /// 1 px (at the span's middle) of the verified contour: a refinement, not a new
    /// detection.
    ///
    /// Why: haze fades the silhouette's colour step with the tissue's transmittance (the
    /// haze scale measures it), while its luma step stays (the shaft, nearer, is less hazy
    /// than the tissue behind it); with the clear frame's luma weight the contour is placed
    /// by a chroma step a few times weaker against the same sensor noise (the chroma
    /// `2R − G − B` has √6 times the noise of one channel, the luma about 0.67 times).
    fn refit_under_haze(&mut self, image: &RgbView<'_>, f: &mut Found) {
        let lens = self.lens;
        let scale = self.haze.scale;
        let sampler = Sampler { image, lens: &lens, luma_weight: self.cfg.profile_luma_weight / scale };
        let floor = 0.75 * self.cfg.edge_threshold * scale;
        let (e0, e1) = (f.ends[0], f.ends[1]);
        let len = (e1[0] - e0[0]).hypot(e1[1] - e0[1]);
        if len.is_nan() || len < 1.0 {
            return;
        }
        let t = [(e1[0] - e0[0]) / len, (e1[1] - e0[1]) / len];
        let n_st = len.floor() as usize + 1;
        let mut lines = [None, None];
        for (k, c) in f.det.contours.iter().enumerate() {
            let Some(line) = Line::from_abc(c.abc) else { return };
            // The stations (every pixel along the span) with a verified edge within 2 px.
            self.cover.clear();
            self.cover.resize(n_st, false);
            for p in &self.cache_pts[f.lines[k]] {
                let i = ((p[0] - e0[0]) * t[0] + (p[1] - e0[1]) * t[1]).round();
                if i >= -2.0 && i <= n_st as f64 + 1.0 {
                    let i = i as isize;
                    for j in (i - 2).max(0)..=(i + 2).min(n_st as isize - 1) {
                        self.cover[j as usize] = true;
                    }
                }
            }
            self.pts.clear();
            for i in 0..n_st {
                if !self.cover[i] {
                    continue;
                }
                let q = [e0[0] + i as f64 * t[0], e0[1] + i as f64 * t[1]];
                let dd = line.distance(q);
                let p = [q[0] - dd * line.n[0], q[1] - dd * line.n[1]];
                if let Some((off, _)) = sampler.edge_offset(&line, p, 1.5, floor) {
                    self.pts.push([p[0] + off * line.n[0], p[1] + off * line.n[1]]);
                }
            }
            if self.pts.len() < 8 {
                return;
            }
            let Some(fit) = robust_fit(&self.pts, line, &mut self.w, &mut self.res) else { return };
            let (n0, n1) = (line.n, fit.line.n);
            let angle = (n0[0] * n1[1] - n0[1] * n1[0]).abs().min(1.0).asin().to_degrees();
            let mq = [0.5 * (e0[0] + e1[0]), 0.5 * (e0[1] + e1[1])];
            let dm = line.distance(mq);
            let pm = [mq[0] - dm * line.n[0], mq[1] - dm * line.n[1]];
            if !(angle <= 0.5 && fit.line.distance(pm).abs() <= 1.0) {
                return;
            }
            lines[k] = Some(fit.line);
        }
        let (Some(a), Some(b)) = (lines[0], lines[1]) else { return };
        let (Ok(c0), Ok(c1)) = (ImageLine::new(a.abc()), ImageLine::new(b.abc())) else { return };
        let Ok(axis) = axis_from_contours(&self.kmat, &c0, &c1, f.mid) else { return };
        let Some(axis_l) = Line::from_abc(axis.abc) else { return };
        let mut ends_px = [[0.0; 2]; 2];
        for (e, p) in ends_px.iter_mut().zip(f.ends) {
            let dd = axis_l.distance(p);
            let q = [p[0] - dd * axis_l.n[0], p[1] - dd * axis_l.n[1]];
            let (x, y) = self.lens.distort_px(q[0], q[1]);
            *e = [x, y];
        }
        f.det.centreline = axis;
        f.det.contours = [c0, c1];
        f.det.ends_px = ends_px;
    }

    /// How the strip between two contours passes as a shaft's interior: by colour (grey
    /// against redder tissue on both sides; under haze half the colour contrast is enough where
    /// the luma step is clear), or, when haze has washed the colour out of the tissue on both
    /// sides, by a clear luma step of the same sign on both sides (the interior no redder than
    /// the outside); `None` when neither.
    fn colour_mode(&self, c: &profile::Interior) -> Option<Evidence> {
        let cfg = &self.cfg;
        // Thresholds scaled by the frame's contrast ([`Haze`]).
        let scale = self.haze.scale;
        let ratio = 1.0 - (1.0 - cfg.max_interior_chroma_ratio) * scale;
        let colour = c.outside.iter().zip(c.near).zip(c.luma_outside).all(|((&out, near), luma_out)| {
            let inside = c.inside.max(near);
            let luma = (c.luma_inside - luma_out).abs() >= scale * cfg.min_luma_contrast;
            let need = scale * if luma { 0.5 * cfg.min_chroma_contrast } else { cfg.min_chroma_contrast };
            out - inside >= need && inside <= ratio * out
        });
        if colour {
            return Some(Evidence::Colour);
        }
        let washed_out = c.outside.iter().all(|&out| out < scale * cfg.min_chroma_contrast);
        let steps = c.luma_outside.map(|out| c.luma_inside - out);
        let sign = steps[0].signum();
        let luma = steps.iter().all(|d| d * sign >= 1.5 * scale * cfg.min_luma_contrast)
            && c.inside.max(c.near[0]).max(c.near[1]) <= c.outside[0].max(c.outside[1]) + 3.0;
        (washed_out && luma).then_some(Evidence::Luma(sign))
    }

    /// [`ShaftDetector::detect`] with a record of what each stage did (for diagnostics: the
    /// benchmark's miss classification). Slower than `detect` (the trace is allocated).
    pub fn detect_traced(&mut self, image: &RgbView<'_>) -> Result<(Vec<ShaftDetection>, OursTrace), DetectError> {
        check_size(&self.k, image)?;
        self.tracing = true;
        let out = self.run(image);
        self.tracing = false;
        Ok((out, std::mem::take(&mut self.trace)))
    }

    /// The detection proper (the image's size checked).
    fn run(&mut self, image: &RgbView<'_>) -> Vec<ShaftDetection> {
        let cfg = self.cfg;
        // The 3×3 normal integration under haze, when asked for (`clear_chroma` 0: never).
        let normal_clear = if cfg.haze_normal_integration { cfg.clear_chroma as f32 } else { 0.0 };
        self.edges.run(image, &self.table, cfg.edge_threshold as f32, cfg.luma_weight as f32, normal_clear);
        self.haze = Haze::new(f64::from(self.edges.chroma_median), &cfg);
        let out = self.shafts(image);
        // On a hazy frame where the edgels gave no shaft, once more on the coarse scale's
        // silhouette edgels (`coarse_edgels_under_haze`).
        if out.is_empty() && cfg.coarse_edgels_under_haze && self.haze.scale < 1.0 {
            self.coarse_silhouettes(image, normal_clear);
            return self.shafts(image);
        }
        out
    }

    /// Stages 2-7 on the frame's edgels (`self.edges`, the haze estimate set).
    fn shafts(&mut self, image: &RgbView<'_>) -> Vec<ShaftDetection> {
        let cfg = self.cfg;
        let min_votes = (0.3 * cfg.min_length_px).max(8.0) as u32;
        let hazy = self.haze.scale < 1.0 && !cfg.hough_window_under_haze;
        let blurred = f64::from(self.edges.silhouette_blurred) > cfg.hough_window_max_blurred;
        let window = if hazy || blurred { 0 } else { cfg.hough_normal_window_deg };
        self.hough.run(&self.edges.edgels, min_votes, cfg.max_lines, window as usize);
        self.trace_rejects.clear();
        let buf = std::mem::take(&mut self.pair_buf);
        // Traced frames rank every pair (the trace records them all); otherwise the pairs are
        // scored lazily, in the order of their score bounds, only as far as the verification
        // reaches (the same pairs verified in the same order).
        let pairs = if self.tracing {
            self.pairs(image, buf)
        } else {
            self.geometric_pairs();
            buf
        };
        let n_lines = self.hough.lines.len();
        self.cache.clear();
        self.cache.resize(n_lines, None);
        if self.cache_pts.len() < n_lines {
            self.cache_pts.resize_with(n_lines, Vec::new);
        }
        if self.cache_strong.len() < n_lines {
            self.cache_strong.resize_with(n_lines, Vec::new);
        }
        // Verify the best-ranked pairs, then keep the best-scoring consistent set (a pair
        // sharing a line, a contour or the axis with a better one is dropped).
        self.cands.clear();
        let budget = 3 * cfg.max_detections + 2;
        let mut outcomes: Vec<(usize, Result<(), PairReject>)> = Vec::new();
        let mut verified = 0usize;
        self.redundant.clear();
        let mut lazy = LazyRanking::new(self, image);
        let mut rank = 0usize;
        while verified < budget {
            let Some((i, j, rank_score)) =
                (if self.tracing { pairs.get(rank).map(|p| (p.1, p.2, p.0)) } else { lazy.next(self) })
            else {
                break;
            };
            // A duplicate of a shaft already verified (both lines in its strip, nearly
            // parallel) does not take a place in the budget: a near second instrument has
            // several lines per contour (rim, highlights) whose pairs would fill it.
            if self.is_duplicate(i, j) {
                if self.tracing {
                    self.redundant.push(rank);
                }
                rank += 1;
                continue;
            }
            verified += 1;
            match self.verify(image, i, j) {
                Ok(f) => {
                    if self.tracing {
                        outcomes.push((rank, Ok(())));
                    }
                    self.cands.push(Found { rank, rank_score, ..f });
                }
                Err(r) => {
                    if self.tracing {
                        outcomes.push((rank, Err(r)));
                    }
                }
            }
            rank += 1;
        }
        self.pair_buf = pairs;
        self.clashes.clear();
        let jaws = self.jaws_rule();
        select(&mut self.cands, &mut self.found, cfg.max_detections, &jaws, &mut self.clashes);
        // Under haze, the returned shafts' contours re-measured over their spans with the
        // luma weighted up as the colour contrast fades.
        if cfg.haze_refit && self.haze.scale < 1.0 {
            let mut found = std::mem::take(&mut self.found);
            for f in &mut found {
                self.refit_under_haze(image, f);
            }
            self.found = found;
        }
        if !self.tracing {
            self.clashes.clear();
        }
        if self.tracing {
            self.record_trace(&outcomes);
        }
        self.found.iter().map(|f| f.det).collect()
    }

    /// Replaces `self.edges.edgels` by the silhouette edgels of the image averaged over 2×2
    /// blocks ([`OursConfig::coarse_edgels_under_haze`]), mapped to undistorted pixels of the
    /// original: a pixel `u'` of the half-resolution camera ([`half_camera`]) is `2u' + 0.5`
    /// of the original, the normals unchanged.
    fn coarse_silhouettes(&mut self, image: &RgbView<'_>, normal_clear: f32) {
        self.edges.edgels.clear();
        let (w, h) = (image.width(), image.height());
        let (wc, hc) = (w / 2, h / 2);
        if wc < 6 || hc < 6 {
            return;
        }
        let data = image.data();
        self.coarse_image.clear();
        self.coarse_image.reserve(3 * wc * hc);
        for i in 0..hc {
            let (r0, r1) = (3 * (2 * i) * w, 3 * (2 * i + 1) * w);
            for j in 0..wc {
                for ch in 0..3 {
                    let at = |r: usize, x: usize| u32::from(data[r + 3 * x + ch]);
                    let sum = at(r0, 2 * j) + at(r0, 2 * j + 1) + at(r1, 2 * j) + at(r1, 2 * j + 1);
                    self.coarse_image.push(((sum + 2) / 4) as u8);
                }
            }
        }
        let Ok(view) = RgbView::new(wc, hc, &self.coarse_image) else { return };
        let cfg = self.cfg;
        self.coarse_edges.run(
            &view,
            &self.coarse_table,
            cfg.edge_threshold as f32,
            cfg.luma_weight as f32,
            normal_clear,
        );
        self.edges.edgels.extend(
            self.coarse_edges
                .edgels
                .iter()
                .map(|e| edges::Edgel { p: [2.0 * e.p[0] + 0.5, 2.0 * e.p[1] + 0.5], n: e.n }),
        );
    }

    /// Fills `self.trace` from the frame's stages (`outcomes`: per verified rank, the
    /// centreline or the reason).
    fn record_trace(&mut self, outcomes: &[(usize, Result<(), PairReject>)]) {
        let jaws = self.jaws_rule();
        let tr = &mut self.trace;
        tr.edgels.clear();
        tr.edgels.extend(self.edges.edgels.iter().map(|e| TraceEdgel { p: e.p, n: e.n }));
        tr.lines.clear();
        tr.lines.extend(self.hough.lines.iter().map(|l| TraceLine { abc: l.line.abc(), ends: l.ends, votes: l.count }));
        tr.pairs.clear();
        tr.clashes.clear();
        tr.silhouette = (self.edges.silhouette_edgels, self.edges.silhouette_blurred);
        for g in &self.cands {
            for f in &self.cands {
                if let (true, Some(r)) = (g.rank != f.rank, clash(g, f, &jaws)) {
                    tr.clashes.push((g.rank, f.rank, r));
                }
            }
        }
        for &(i, j, r) in &self.trace_rejects {
            tr.pairs.push(TracePair {
                lines: [i, j],
                rank: None,
                outcome: PairOutcome::Rejected(r),
                centreline: None,
                verified: None,
            });
        }
        for (rank, &(_, i, j)) in self.pair_buf.iter().enumerate() {
            let verified = outcomes.iter().find(|o| o.0 == rank).map(|o| o.1);
            let (outcome, found) = match verified {
                None if self.redundant.contains(&rank) => (PairOutcome::Redundant, None),
                None => (PairOutcome::NotVerified, None),
                Some(Err(r)) => (PairOutcome::Rejected(r), None),
                Some(Ok(())) => {
                    let pos = self.found.iter().position(|f| f.rank == rank);
                    (
                        pos.map_or(PairOutcome::Dropped, PairOutcome::Returned),
                        self.cands.iter().find(|f| f.rank == rank),
                    )
                }
            };
            let rank_score = found.map_or(self.pair_buf[rank].0, |f| f.rank_score);
            let verified = found.map(|f| TraceVerified {
                score: f.score,
                rank_score,
                confidence: f.det.confidence,
                support: f.support,
                sigma_px: f.sigma,
                contrast: f.contrast,
                length_px: f.len,
                width_px: f.width,
                coverage: f.coverage,
                ends: f.ends,
                clash: self.clashes.iter().find(|c| c.0 == rank).map(|c| c.1),
            });
            let centreline = found.map(|f| f.det.centreline.abc);
            tr.pairs.push(TracePair { lines: [i, j], rank: Some(rank), outcome, centreline, verified });
        }
    }

    /// The candidate pairs of line hypotheses that pass the cheap geometric tests (nearly
    /// parallel, overlapping, not crossing, a plausible axis distance), in generation order:
    /// `(upper bound of the ranking score, i, j, overlap along i's frame)`. The ranking score
    /// ([`Self::pair_score`]) is the bound times the interior's greyness, in `[0, 1]`.
    fn geometric_pairs(&mut self) {
        let tracing = self.tracing;
        let mut out = std::mem::take(&mut self.geo_buf);
        out.clear();
        let lines = &self.hough.lines;
        let cfg = self.cfg;
        let cos_max = (25.0f64).to_radians().cos();
        for i in 0..lines.len() {
            for j in i + 1..lines.len() {
                let (a, b) = (&lines[i], &lines[j]);
                if (a.line.n[0] * b.line.n[0] + a.line.n[1] * b.line.n[1]).abs() < cos_max {
                    continue;
                }
                let (o, t) = Self::pair_frame(a);
                let proj = |p: [f64; 2]| (p[0] - o[0]) * t[0] + (p[1] - o[1]) * t[1];
                let sa = [proj(a.ends[0]), proj(a.ends[1])];
                let (x, y) = (proj(b.ends[0]), proj(b.ends[1]));
                let ov = [sa[0].max(x.min(y)), sa[1].min(x.max(y))];
                let len = ov[1] - ov[0];
                if len < 0.6 * cfg.min_length_px {
                    if tracing {
                        self.trace_rejects.push((i, j, PairReject::Overlap));
                    }
                    continue;
                }
                // Widths at both ends of the overlap: the lines must not cross there.
                let d = [-t[1], t[0]];
                let mut ok = true;
                let mut inside = [0.0; 2];
                for s in [ov[0], 0.5 * (ov[0] + ov[1]), ov[1]] {
                    let q = [o[0] + s * t[0], o[1] + s * t[1]];
                    match (a.line.hit(q, d), b.line.hit(q, d)) {
                        (Some(la), Some(lb)) if (la - lb).abs() >= 2.0 => {
                            let m = 0.5 * (la + lb);
                            inside = [q[0] + m * d[0], q[1] + m * d[1]];
                        }
                        _ => ok = false,
                    }
                }
                if !ok {
                    if tracing {
                        self.trace_rejects.push((i, j, PairReject::Crossing));
                    }
                    continue;
                }
                let dist = self.axis_distance(&a.line, &b.line, inside);
                if !dist.is_some_and(|dist| dist >= 0.6 * cfg.min_depth_m && dist <= 1.6 * cfg.max_depth_m) {
                    if tracing {
                        self.trace_rejects.push((i, j, PairReject::Distance));
                    }
                    continue;
                }
                out.push((len * (a.count.min(b.count) as f64), i, j, ov));
            }
        }
        self.geo_buf = out;
    }

    /// The ranking score of a geometric candidate pair (`bound`, lines `i`, `j`, overlap `ov`
    /// along `i`'s frame): `bound` × how grey the interior is against the outsides, after the
    /// coarse colour test on the hypotheses (`None`: turned down).
    fn pair_score(&mut self, sampler: &Sampler<'_>, bound: f64, i: usize, j: usize, ov: [f64; 2]) -> Option<f64> {
        let (a, b) = (&self.hough.lines[i], &self.hough.lines[j]);
        let (o, t) = Self::pair_frame(a);
        let c = interior(sampler, [&a.line, &b.line], o, t, ov, &mut self.col)?;
        let mode = self.colour_mode(&c)?;
        // Rank by support and by how grey the interior is against the outsides.
        let grey = match mode {
            Evidence::Colour => (1.0 - c.inside.max(0.0) / c.outside[0].min(c.outside[1]).max(1e-9)).clamp(0.0, 1.0),
            Evidence::Luma(_) => 0.5,
        };
        Some(bound * grey)
    }

    /// True when both lines of the pair lie in the strip of a shaft already verified and
    /// nearly parallel to it ([`within_strip`]): a duplicate of that shaft.
    fn is_duplicate(&self, i: usize, j: usize) -> bool {
        let (a, b) = (&self.hough.lines[i], &self.hough.lines[j]);
        self.cands.iter().any(|f| within_strip(f, a) && within_strip(f, b))
    }

    /// Every candidate pair of line hypotheses, best first (cheap tests only: the geometric
    /// ones and the coarse colour test), as `(score, i, j)`; for the trace, which records
    /// every pair.
    fn pairs(&mut self, image: &RgbView<'_>, mut out: Vec<(f64, usize, usize)>) -> Vec<(f64, usize, usize)> {
        let lens = self.lens;
        let sampler = Sampler { image, lens: &lens, luma_weight: self.cfg.profile_luma_weight };
        out.clear();
        self.geometric_pairs();
        let geo = std::mem::take(&mut self.geo_buf);
        for &(bound, i, j, ov) in &geo {
            match self.pair_score(&sampler, bound, i, j, ov) {
                Some(score) => out.push((score, i, j)),
                None => {
                    if self.tracing {
                        self.trace_rejects.push((i, j, PairReject::CoarseColour));
                    }
                }
            }
        }
        self.geo_buf = geo;
        out.sort_by(|a, b| b.0.total_cmp(&a.0));
        out
    }
}

impl ShaftDetector for OursDetector {
    fn name(&self) -> &'static str {
        "ours"
    }

    fn intrinsics(&self) -> &Intrinsics {
        &self.k
    }

    fn detect(&mut self, image: &RgbView<'_>) -> Result<Vec<ShaftDetection>, DetectError> {
        check_size(&self.k, image)?;
        self.tracing = false;
        Ok(self.run(image))
    }
}

/// The candidate pairs in ranking order (score descending, generation order on ties, as a
/// stable sort of every scored pair would give), scored lazily: a pair's coarse colour test
/// (the costly part of the ranking) is run only when its score bound could place it before
/// the best pair scored so far, and not at all once it is a duplicate of a verified shaft (it
/// would be skipped when reached: the verified shafts only grow).
struct LazyRanking<'a> {
    image: RgbView<'a>,
    /// Next position in `geo_order`.
    next: usize,
}

impl<'a> LazyRanking<'a> {
    /// Orders the frame's geometric candidates (`det.geo_buf`) by score bound.
    fn new(det: &mut OursDetector, image: &RgbView<'a>) -> Self {
        let geo = &det.geo_buf;
        det.geo_order.clear();
        det.scored.clear();
        if !det.tracing {
            det.geo_order.extend(0..geo.len());
            det.geo_order.sort_by(|&x, &y| geo[y].0.total_cmp(&geo[x].0).then(x.cmp(&y)));
        }
        Self { image: *image, next: 0 }
    }

    /// The next pair `(i, j, ranking score)` in ranking order, `None` when none is left.
    fn next(&mut self, det: &mut OursDetector) -> Option<(usize, usize, f64)> {
        let lens = det.lens;
        let sampler = Sampler { image: &self.image, lens: &lens, luma_weight: det.cfg.profile_luma_weight };
        let order = std::mem::take(&mut det.geo_order);
        let mut scored = std::mem::take(&mut det.scored);
        let geo = std::mem::take(&mut det.geo_buf);
        let bounds = &geo;
        let g = next_in_rank(
            &order,
            &mut self.next,
            &mut scored,
            |g| bounds[g].0,
            |g| {
                let (bound, i, j, ov) = bounds[g];
                if det.is_duplicate(i, j) { None } else { det.pair_score(&sampler, bound, i, j, ov) }
            },
        );
        det.geo_buf = geo;
        det.geo_order = order;
        det.scored = scored;
        g.map(|(g, score)| (det.geo_buf[g].1, det.geo_buf[g].2, score))
    }
}

/// The next item in ranking order (score descending, index ascending on ties), with its score, of the items
/// `order` (sorted by `bound` descending, index ascending on ties; `bound(g) ≥ score(g)`),
/// scoring them lazily: from `order[*next]` on, each is scored (`None`: not ranked) only while
/// it could rank before the best one scored so far; `scored` holds the scored ones waiting.
fn next_in_rank(
    order: &[usize],
    next: &mut usize,
    scored: &mut Vec<(f64, usize)>,
    bound: impl Fn(usize) -> f64,
    mut score: impl FnMut(usize) -> Option<f64>,
) -> Option<(usize, f64)> {
    // The best scored item: highest score, lowest index on ties.
    fn best(scored: &[(f64, usize)]) -> Option<(usize, (f64, usize))> {
        scored.iter().copied().enumerate().reduce(|b, c| match c.1.0.total_cmp(&b.1.0) {
            std::cmp::Ordering::Greater => c,
            std::cmp::Ordering::Equal if c.1.1 < b.1.1 => c,
            _ => b,
        })
    }
    while let Some(&g) = order.get(*next) {
        // An item not scored yet ranks after the best scored one when its bound is lower
        // (or equal and its index higher): the best one is next.
        if let Some((_, (s, bg))) = best(scored) {
            match bound(g).total_cmp(&s) {
                std::cmp::Ordering::Less => break,
                std::cmp::Ordering::Equal if g > bg => break,
                _ => {}
            }
        }
        *next += 1;
        if let Some(sc) = score(g) {
            scored.push((sc, g));
        }
    }
    let (k, (sc, g)) = best(scored)?;
    scored.swap_remove(k);
    Some((g, sc))
}

/// The final selection: the verified shafts `cands` by merit ([`Found::merit`], the earlier
/// verified first on ties), each kept in `found` (cleared first; at most `max`) unless it
/// clashes with one kept before it ([`clash`]); the ones dropped are recorded in `clashes`
/// (their rank, the rank of the detection kept and the rule; `usize::MAX` with
/// [`ClashRule::Full`]). `cands` is left sorted, `found` by merit.
fn select(
    cands: &mut [Found],
    found: &mut Vec<Found>,
    max: usize,
    jaws: &JawsRule,
    clashes: &mut Vec<(usize, (usize, ClashRule))>,
) {
    cands.sort_by(|a, b| b.merit().total_cmp(&a.merit()).then(a.rank.cmp(&b.rank)));
    found.clear();
    for f in cands.iter() {
        let c = if found.len() >= max {
            Some((usize::MAX, ClashRule::Full))
        } else {
            found.iter().find_map(|g| clash(g, f, jaws).map(|r| (g.rank, r)))
        };
        match c {
            None => found.push(*f),
            Some(c) => clashes.push((f.rank, c)),
        }
    }
}

/// The rule by which detection `f` clashes with the better one `g` (they cannot both be
/// shafts), `None` when they are compatible.
fn clash(g: &Found, f: &Found, jaws: &JawsRule) -> Option<ClashRule> {
    if g.lines.iter().any(|l| f.lines.contains(l)) {
        Some(ClashRule::SharedLine)
    } else if same_axis(g, f) {
        Some(ClashRule::SameAxis)
    } else if shares_contour(g, f) {
        Some(ClashRule::SharedContour)
    } else if overlap(g, f) {
        Some(ClashRule::Overlap)
    } else if continues(g, f) && jaws.jaw_like(g, f) {
        Some(ClashRule::Continues)
    } else if jaws.applies(g, f) {
        Some(ClashRule::Jaws)
    } else {
        None
    }
}

/// The jaws rule of the final selection ([`JawsRule::applies`]).
#[derive(Clone, Copy, Debug, PartialEq)]
struct JawsRule {
    /// [`OursConfig::tip_length_diameters`].
    tip_diameters: f64,
    /// [`OursConfig::jaw_width_ratio`].
    width_ratio: f64,
    /// The image's last column and row, measured pixels.
    size: [f64; 2],
    /// How far inside the image an end of a span must lie to be the shaft's distal end,
    /// measured pixels: [`OursConfig::border_margin_px`], or its default 24 when the border
    /// test is off (infinite).
    margin: f64,
}

impl JawsRule {
    /// True when the measured pixel `p` lies more than `margin` inside the image.
    fn inside(&self, p: [f64; 2]) -> bool {
        p[0].min(p[1]).min(self.size[0] - p[0]).min(self.size[1] - p[1]) > self.margin
    }

    /// True when detection `f` could be the wrist and jaws of the shaft `g` by its size:
    /// narrower than `g` by `width_ratio`, and no longer than `tip_diameters` of `g`'s widths.
    fn jaw_like(&self, g: &Found, f: &Found) -> bool {
        f.width <= self.width_ratio * g.width && f.len <= self.tip_diameters * g.width
    }

    /// True when detection `f` is the wrist and jaws of the better one `g`, at any angle (an
    /// articulated wrist): `f` is narrower than `g` by `width_ratio` (jaws are narrower than
    /// the shaft; a shaft crossing behind is narrower only by its depth), no longer than
    /// `tip_diameters` of `g`'s widths (the instrument's end beyond the shaft, at the shaft's
    /// depth; foreshortening only shortens it), its nearer end within one of `g`'s widths of
    /// an end of `g`'s span that lies inside the image (the shaft's distal end: an end at the
    /// border is where the view stops), and it runs away from that end (not back along `g`).
    fn applies(&self, g: &Found, f: &Found) -> bool {
        if !self.jaw_like(g, f) {
            return false;
        }
        let [a, b] = g.ends;
        let len = (b[0] - a[0]).hypot(b[1] - a[1]);
        if len <= 0.0 {
            return false;
        }
        let w = g.width.max(20.0);
        [(1, 0), (0, 1)].iter().any(|&(e, o)| {
            let (end, other) = (g.ends[e], g.ends[o]);
            if !self.inside(g.det.ends_px[e]) {
                return false;
            }
            let t = [(end[0] - other[0]) / len, (end[1] - other[1]) / len];
            let d = f.ends.map(|p| (p[0] - end[0]).hypot(p[1] - end[1]));
            let (near, far) = if d[0] <= d[1] { (0, 1) } else { (1, 0) };
            let p = f.ends[far];
            let s_far = (p[0] - end[0]) * t[0] + (p[1] - end[1]) * t[1];
            d[near] <= w && s_far >= -0.5 * g.width
        })
    }
}

/// True when two detections have nearly the same axis (within 3°, and each one's span middle
/// within 5 px of the other's axis).
fn same_axis(a: &Found, b: &Found) -> bool {
    let (la, lb) = (a.det.centreline, b.det.centreline);
    let cos = (la.abc[0] * lb.abc[0] + la.abc[1] * lb.abc[1]).abs();
    if cos < 3f64.to_radians().cos() {
        return false;
    }
    lb.distance_px(a.mid[0], a.mid[1]).abs() < 5.0 || la.distance_px(b.mid[0], b.mid[1]).abs() < 5.0
}

/// True when two nearly parallel detections (within 10°) overlap: either one's span middle
/// lies inside the other's strip. Two shafts cannot lie over each other in the image (a second
/// instrument crosses in front at an angle); the worse one is a contour of the better paired
/// with something beside it.
fn overlap(a: &Found, b: &Found) -> bool {
    let (la, lb) = (a.det.centreline, b.det.centreline);
    if (la.abc[0] * lb.abc[0] + la.abc[1] * lb.abc[1]).abs() < 10f64.to_radians().cos() {
        return false;
    }
    let inside = |f: &Found, p: [f64; 2]| {
        let [c0, c1] = f.det.contours;
        let (d0, d1) = (c0.distance_px(p[0], p[1]), c1.distance_px(p[0], p[1]));
        let (m0, m1) = (c0.distance_px(f.mid[0], f.mid[1]), c1.distance_px(f.mid[0], f.mid[1]));
        // Same side of each contour as the strip's own middle.
        d0 * m0 > 0.0 && d1 * m1 > 0.0
    };
    inside(a, b.mid) || inside(b, a.mid)
}

/// True when detection `f` continues the better one `g` past an end of its span, nearly in
/// line (within 30°), starting within half a shaft width of the end: the wrist and jaws of the
/// instrument whose shaft `g` is (a second instrument crosses a shaft, it does not start
/// where the shaft's span ends).
fn continues(g: &Found, f: &Found) -> bool {
    let (lg, lf) = (g.det.centreline, f.det.centreline);
    if (lg.abc[0] * lf.abc[0] + lg.abc[1] * lf.abc[1]).abs() < 30f64.to_radians().cos() {
        return false;
    }
    let [a, b] = g.ends;
    let len = (b[0] - a[0]).hypot(b[1] - a[1]);
    if len <= 0.0 {
        return false;
    }
    let t = [(b[0] - a[0]) / len, (b[1] - a[1]) / len];
    let w = 0.5 * g.width.max(20.0);
    let s = f.ends.map(|p| (p[0] - a[0]) * t[0] + (p[1] - a[1]) * t[1]);
    let lat = f.ends.map(|p| ((p[0] - a[0]) * t[1] - (p[1] - a[1]) * t[0]).abs());
    let (near, far) = if s[0] <= s[1] { (0, 1) } else { (1, 0) };
    // Past the end at `len`: its nearer end within half a width of that end, along and across.
    let beyond_end = s[near] >= len - w && lat[near] <= w;
    // Past the start at 0: its farther-out end (the larger `s`) within half a width of it.
    let beyond_start = s[far] <= w && lat[far] <= w;
    beyond_end || beyond_start
}

/// True when Hough line `l` lies in the strip of the verified shaft `f`: within 10° of its
/// axis, and its span's middle between its two contours (or within 1.5 px outside one).
fn within_strip(f: &Found, l: &LineCand) -> bool {
    let axis = f.det.centreline.abc;
    if (axis[0] * l.line.n[0] + axis[1] * l.line.n[1]).abs() < 10f64.to_radians().cos() {
        return false;
    }
    let p = [0.5 * (l.ends[0][0] + l.ends[1][0]), 0.5 * (l.ends[0][1] + l.ends[1][1])];
    f.det.contours.iter().all(|c| {
        let (d, m) = (c.distance_px(p[0], p[1]), c.distance_px(f.mid[0], f.mid[1]));
        d * m.signum() >= -1.5
    })
}

/// True when the verified shaft `f` can hide the end `p` (undistorted pixels) of a visible
/// span running along `t` (unit) with its middle at `middle`: `f`'s axis at least 15° from `t`
/// (a crossing instrument, not the same shaft), `p` inside `f`'s strip or at most `slack`
/// pixels outside a contour while `middle` is outside it (the span runs out from under `f`), and
/// along `f`'s span: up to half a width past an end at the image border, at least a width
/// short of an end inside the image (`inside`, on measured pixels: the distal end).
fn hides_end(
    f: &Found,
    p: [f64; 2],
    middle: [f64; 2],
    t: [f64; 2],
    slack: f64,
    inside: impl Fn([f64; 2]) -> bool,
) -> bool {
    let [a, b] = f.ends;
    let len = (b[0] - a[0]).hypot(b[1] - a[1]);
    if len.is_nan() || len <= 0.0 {
        return false;
    }
    let u = [(b[0] - a[0]) / len, (b[1] - a[1]) / len];
    if (u[0] * t[1] - u[1] * t[0]).abs() < 15f64.to_radians().sin() {
        return false;
    }
    // Along `f`'s span: up to half a width past an end at the image border (where the view
    // stops), but at least a width short of an end inside it (`f`'s distal end: its own wrist
    // and jaws start there, and a pair on them ends where the shaft does).
    let s = (p[0] - a[0]) * u[0] + (p[1] - a[1]) * u[1];
    let reach = f.det.ends_px.map(|e| if inside(e) { -0.5 * f.width } else { 0.5 * f.width });
    if s < -reach[0] || s > len + reach[1] {
        return false;
    }
    // `p` in the strip (within `slack`), the span's middle outside it: the span runs out
    // from under `f`, it does not lie along it.
    let side = |q: [f64; 2], slack: f64| {
        f.det.contours.iter().all(|c| c.distance_px(q[0], q[1]) * c.distance_px(f.mid[0], f.mid[1]).signum() >= -slack)
    };
    side(p, slack) && !side(middle, 0.0)
}

/// True when two detections share a contour (within 1° and 2 px at the other's span middle).
fn shares_contour(a: &Found, b: &Found) -> bool {
    a.det.contours.iter().any(|ca| {
        b.det.contours.iter().any(|cb| {
            let cos = (ca.abc[0] * cb.abc[0] + ca.abc[1] * cb.abc[1]).abs();
            cos > 1f64.to_radians().cos()
                && (ca.distance_px(b.mid[0], b.mid[1]).abs() - cb.distance_px(b.mid[0], b.mid[1]).abs()).abs() < 2.0
                && (ca.distance_px(a.mid[0], a.mid[1]).abs() - cb.distance_px(a.mid[0], a.mid[1]).abs()).abs() < 2.0
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A verified shaft along the horizontal `v = y`, contours `y ± half`, span from `u = u0`
    /// to `u = u1` (undistorted pixels), or along a line through `(u0, y)` at `angle_deg`.
    fn found(u0: f64, u1: f64, y: f64, half: f64, angle_deg: f64) -> Found {
        let (c, s) = (angle_deg.to_radians().cos(), angle_deg.to_radians().sin());
        // Normal (-s, c); the line through (u0, y).
        let line = |off: f64| ImageLine::new([-s, c, -(-s * u0 + c * y) - off]).unwrap();
        let at = |u: f64| [u0 + (u - u0) * c, y + (u - u0) * s];
        Found {
            det: ShaftDetection {
                centreline: line(0.0),
                contours: [line(-half), line(half)],
                ends_px: [at(u0), at(u1)],
                confidence: 1.0,
            },
            mid: at(0.5 * (u0 + u1)),
            ends: [at(u0), at(u1)],
            width: 2.0 * half,
            lines: [0, 1],
            score: 1.0,
            support: 1.0,
            sigma: 0.1,
            contrast: 1.0,
            len: u1 - u0,
            coverage: [1.0; 2],
            rank: 0,
            rank_score: 1.0,
        }
    }

    /// A pixel `x'` of the half-resolution camera (the mean of the 2×2 block whose centre is
    /// `2x' + 0.5` of the original) sees the ray of that centre: its undistorted position
    /// `u'` maps to the original's as `2u' + 0.5`.
    #[test]
    fn the_half_camera_sees_the_block_centres_rays() {
        let k = Intrinsics { skew: 0.7, cx: 321.0, ..crate::synth::endoscope_camera() };
        let h = half_camera(&k);
        assert_eq!((h.width, h.height), (320, 240));
        for (x, y) in [(0.0, 0.0), (10.0, 200.0), (159.5, 119.5), (319.0, 239.0), (250.25, 17.75)] {
            let full = k.undistort_px(&nalgebra::Vector2::new(2.0 * x + 0.5, 2.0 * y + 0.5));
            let half = h.undistort_px(&nalgebra::Vector2::new(x, y));
            assert!(
                (2.0 * half.x + 0.5 - full.x).abs() < 1e-6 && (2.0 * half.y + 0.5 - full.y).abs() < 1e-6,
                "{x}, {y}"
            );
        }
    }

    /// The jaws rule with the default settings on a 640×480 image.
    const RULE: JawsRule = JawsRule { tip_diameters: 3.5, width_ratio: 0.85, size: [639.0, 479.0], margin: 24.0 };

    /// A crossing instrument in front: horizontal at `v = 100`, 60 px wide, from beyond the
    /// left border (`u = -10`) to its distal end inside the image (`u = 400`).
    fn occluder() -> Found {
        found(-10.0, 400.0, 100.0, 30.0, 0.0)
    }

    #[test]
    fn a_span_ending_at_a_crossing_shaft_is_hidden_there_not_beyond_its_slack() {
        let f = occluder();
        let inside = |e: [f64; 2]| RULE.inside(e);
        let down = [0.0, 1.0];
        // A vertical span below it, from just under its lower contour (v = 130).
        let middle = [200.0, 200.0];
        assert!(hides_end(&f, [200.0, 135.0], middle, down, 10.0, inside));
        assert!(hides_end(&f, [200.0, 120.0], middle, down, 10.0, inside));
        // 20 px short of the contour with 10 px of slack: a span that stops on open tissue.
        assert!(!hides_end(&f, [200.0, 150.0], middle, down, 10.0, inside));
        assert!(hides_end(&f, [200.0, 150.0], middle, down, 25.0, inside));
    }

    #[test]
    fn a_span_along_the_shaft_or_inside_its_strip_is_not_hidden_by_it() {
        let f = occluder();
        let inside = |e: [f64; 2]| RULE.inside(e);
        // Within 15° of the shaft's axis: the same shaft (or a pairing along it), not a crossing.
        let (c, s) = (10f64.to_radians().cos(), 10f64.to_radians().sin());
        assert!(!hides_end(&f, [200.0, 132.0], [200.0 + 60.0 * c, 132.0 + 60.0 * s], [c, s], 10.0, inside));
        // At 20° it is a crossing.
        let (c, s) = (20f64.to_radians().cos(), 20f64.to_radians().sin());
        assert!(hides_end(&f, [200.0, 132.0], [200.0 + 80.0 * c, 132.0 + 80.0 * s], [c, s], 10.0, inside));
        // The span's middle inside the strip: it lies under the shaft, it does not run out from it.
        assert!(!hides_end(&f, [200.0, 135.0], [200.0, 110.0], [0.0, 1.0], 10.0, inside));
    }

    #[test]
    fn near_the_distal_end_of_the_crossing_shaft_its_own_jaws_are_not_taken_for_hidden() {
        let f = occluder();
        let inside = |e: [f64; 2]| RULE.inside(e);
        let down = [0.0, 1.0];
        let at = |u: f64| ([u, 131.0], [u, 200.0]);
        // Half a width (30 px) short of the distal end at u = 400: still a crossing.
        let (p, m) = at(365.0);
        assert!(hides_end(&f, p, m, down, 10.0, inside));
        // Within half a width of it, or past it: where its wrist and jaws start.
        for u in [380.0, 399.0, 420.0] {
            let (p, m) = at(u);
            assert!(!hides_end(&f, p, m, down, 10.0, inside), "u = {u}");
        }
        // Past its end at the border (u = -10, left of the margin) by under half a width: the
        // view stops there, the shaft goes on.
        let (p, m) = at(-30.0);
        assert!(hides_end(&f, p, m, down, 10.0, inside));
        let (p, m) = at(-50.0);
        assert!(!hides_end(&f, p, m, down, 10.0, inside));
    }

    #[test]
    fn a_narrow_short_detection_at_a_shafts_distal_end_is_its_jaws_at_any_angle() {
        // A shaft 60 px wide from the left border to u = 350 (its distal end inside the image).
        let shaft = found(-10.0, 350.0, 228.0, 30.0, 0.0);
        // Jaws 30 px wide, 124 px long, from the end at 40° and 70° (an articulated wrist).
        let jaws = |angle: f64| found(355.0, 479.0, 233.0, 15.0, angle);
        assert!(RULE.applies(&shaft, &jaws(40.0)));
        assert!(RULE.applies(&shaft, &jaws(-70.0)));
        assert_eq!(clash(&shaft, &Found { lines: [2, 3], ..jaws(40.0) }, &RULE), Some(ClashRule::Jaws));
        // A shaft crossing behind, 0.9 of the width (farther only by a few millimetres),
        // whose span starts at the end: not jaws.
        assert!(!RULE.applies(&shaft, &found(355.0, 479.0, 233.0, 27.0, 40.0)));
        // Longer than 3.5 of the shaft's widths (210 px): not.
        assert!(!RULE.applies(&shaft, &found(355.0, 600.0, 233.0, 15.0, 40.0)));
        // Starting more than a width from the end: not.
        assert!(!RULE.applies(&shaft, &found(430.0, 530.0, 233.0, 15.0, 40.0)));
        // Running back along the shaft: not (that is the overlap rule's).
        assert!(!RULE.applies(&shaft, &found(355.0, 470.0, 240.0, 15.0, 175.0)));
        // The shaft's span ending at the image border is not its distal end: a narrower
        // shaft there is another instrument.
        let at_border = found(300.0, 630.0, 228.0, 30.0, 0.0);
        assert!(!RULE.applies(&at_border, &found(633.0, 660.0, 233.0, 15.0, 60.0)));
        // Off: a zero tip length.
        assert!(!JawsRule { tip_diameters: 0.0, ..RULE }.applies(&shaft, &jaws(40.0)));
    }

    #[test]
    fn a_detection_continuing_past_a_shafts_end_is_its_jaws() {
        let shaft = found(100.0, 300.0, 200.0, 15.0, 0.0);
        // In line past the end, and tilted 20° (an articulated wrist) from the end.
        assert!(continues(&shaft, &found(305.0, 380.0, 200.0, 8.0, 0.0)));
        assert!(continues(&shaft, &found(302.0, 380.0, 203.0, 8.0, 20.0)));
        // Past the start (the span's other end), too.
        assert!(continues(&shaft, &found(20.0, 95.0, 200.0, 8.0, 0.0)));
        // A second shaft crossing this one at 25°, its span through the middle: not jaws.
        assert!(!continues(&shaft, &found(150.0, 350.0, 180.0, 15.0, 25.0)));
        // The final selection's rule also wants the jaws' size: narrower, and short.
        let right_size = Found { lines: [2, 3], ..found(302.0, 380.0, 203.0, 8.0, 20.0) };
        assert_eq!(clash(&shaft, &right_size, &RULE), Some(ClashRule::Continues));
        // A shaft crossing behind (0.9 of the width) whose span starts at the end, 24° off: kept.
        let crossing = Found { lines: [2, 3], ..found(302.0, 380.0, 203.0, 13.5, 24.0) };
        assert!(continues(&shaft, &crossing));
        assert_eq!(clash(&shaft, &crossing, &RULE), None);
        // Narrow but longer than the wrist and jaws (3.5 widths, 105 px): kept.
        let long = Found { lines: [2, 3], ..found(302.0, 420.0, 203.0, 8.0, 20.0) };
        assert_eq!(clash(&shaft, &long, &RULE), None);
        // Starting past the end but far off the axis (another instrument beside it): not.
        assert!(!continues(&shaft, &found(305.0, 380.0, 240.0, 8.0, 0.0)));
        // Perpendicular at the end: not.
        assert!(!continues(&shaft, &found(300.0, 380.0, 200.0, 8.0, 90.0)));
    }

    #[test]
    fn a_wrong_pair_verified_late_does_not_displace_the_right_one_by_a_slightly_higher_score() {
        // The right pair, first in the ranking (long lines, many votes), and a wrong pairing
        // on nearly the same axis verified far down the ranking (reached past the duplicates
        // of a verified shaft) with a slightly higher verification score under haze: the
        // figures of a hazy frame of the tuning set.
        let right = Found { score: 3.34, rank_score: 17681.0, rank: 0, ..found(100.0, 500.0, 200.0, 45.0, 0.0) };
        let wrong =
            Found { score: 3.46, rank_score: 2893.0, rank: 13, lines: [2, 3], ..found(200.0, 500.0, 202.0, 58.0, 0.5) };
        assert_eq!(clash(&wrong, &right, &RULE), Some(ClashRule::SameAxis));
        let (mut found_v, mut clashes) = (Vec::new(), Vec::new());
        select(&mut [wrong, right], &mut found_v, 2, &RULE, &mut clashes);
        assert_eq!(found_v.iter().map(|f| f.rank).collect::<Vec<_>>(), vec![0]);
        assert_eq!(clashes, vec![(13, (0, ClashRule::SameAxis))]);
        // A later pair that is much better in the verification still wins (a right pair
        // ranked below a wrong one: verification is not a formality).
        let better = Found { score: 3.46 * 10.0, ..wrong };
        select(&mut [right, better], &mut found_v, 2, &RULE, &mut clashes);
        assert_eq!(found_v.iter().map(|f| f.rank).collect::<Vec<_>>(), vec![13]);
        // Two compatible shafts (crossing at 40°) are both kept, the better merit first, up
        // to the most detections asked for.
        let crossing =
            Found { score: 1.0, rank_score: 100.0, rank: 5, lines: [6, 7], ..found(150.0, 450.0, 100.0, 20.0, 40.0) };
        clashes.clear();
        select(&mut [crossing, right, wrong], &mut found_v, 2, &RULE, &mut clashes);
        assert_eq!(found_v.iter().map(|f| f.rank).collect::<Vec<_>>(), vec![0, 5]);
        select(&mut [crossing, right], &mut found_v, 1, &RULE, &mut clashes);
        assert_eq!(found_v.iter().map(|f| f.rank).collect::<Vec<_>>(), vec![0]);
    }

    #[test]
    fn the_lazy_ranking_gives_the_pairs_in_the_order_of_the_full_ranking() {
        use crate::synth::{Cylinder, Scene, endoscope_camera, render};
        let k = endoscope_camera();
        let cyl = |point_m: [f64; 3], direction: [f64; 3], albedo: f64| Cylinder {
            point_m,
            direction,
            radius_m: 0.004,
            extent_m: [0.0, 0.4],
            albedo,
        };
        // Two crossing shafts over folded, veined tissue: many line hypotheses and pairs.
        let scene = Scene {
            shafts: vec![
                cyl([0.01, 0.005, 0.08], [-1.0, 0.2, 0.15], 0.8),
                cyl([0.01, 0.03, 0.09], [-1.0, 0.25, 0.1], 0.6),
                cyl([-0.01, 0.02, 0.05], [0.3, -1.0, 0.1], 0.4),
            ],
            seed: 5,
            vessels: true,
            folds: true,
            noise: 4.0,
        };
        let img = render(&k, &scene);
        let view = RgbView::new(k.width as usize, k.height as usize, &img).unwrap();
        let mut det = OursDetector::new(k, OursConfig { max_lines: 100, ..OursConfig::default() }).unwrap();
        let cfg = det.cfg;
        det.edges.run(&view, &det.table, cfg.edge_threshold as f32, cfg.luma_weight as f32, cfg.clear_chroma as f32);
        det.haze = Haze::new(f64::from(det.edges.chroma_median), &cfg);
        det.hough.run(&det.edges.edgels, 12, cfg.max_lines, cfg.hough_normal_window_deg as usize);
        let full = det.pairs(&view, Vec::new());
        assert!(full.len() >= 4, "only {} pairs of {} lines", full.len(), det.hough.lines.len());
        det.geometric_pairs();
        assert!(det.geo_buf.len() > full.len(), "some pairs fail the coarse colour test");
        let mut lazy = LazyRanking::new(&mut det, &view);
        let mut order = Vec::new();
        while let Some(p) = lazy.next(&mut det) {
            order.push(p);
        }
        let want: Vec<(usize, usize, f64)> = full.iter().map(|p| (p.1, p.2, p.0)).collect();
        assert_eq!(order, want);
    }

    #[test]
    fn lazy_ranking_matches_a_full_sort_and_scores_only_what_it_needs() {
        // Pseudo-random bounds and scores (score ≤ bound, some not ranked, ties included).
        let mut x = 12345u64;
        let mut rnd = || {
            x = x.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
            (x >> 33) as f64 / (1u64 << 31) as f64
        };
        for trial in 0..50 {
            let n = 5 + trial * 3;
            let bounds: Vec<f64> = (0..n).map(|_| (rnd() * 10.0).round()).collect();
            let scores: Vec<Option<f64>> = bounds
                .iter()
                .map(|&b| (rnd() > 0.2).then(|| if rnd() < 0.2 { b } else { (b * rnd() * 4.0).round() / 4.0 }))
                .collect();
            let mut full: Vec<usize> = (0..n).filter(|&g| scores[g].is_some()).collect();
            full.sort_by(|&a, &b| scores[b].unwrap().total_cmp(&scores[a].unwrap()).then(a.cmp(&b)));
            let mut order: Vec<usize> = (0..n).collect();
            order.sort_by(|&a, &b| bounds[b].total_cmp(&bounds[a]).then(a.cmp(&b)));
            let (mut next, mut scored, mut calls) = (0, Vec::new(), 0);
            let mut got = Vec::new();
            // Only the first three in ranking order: fewer items are scored than exist.
            for _ in 0..3.min(full.len()) {
                let g = next_in_rank(
                    &order,
                    &mut next,
                    &mut scored,
                    |g| bounds[g],
                    |g| {
                        calls += 1;
                        scores[g]
                    },
                );
                got.push(g.unwrap().0);
            }
            assert_eq!(got, full[..got.len()], "trial {trial}");
            assert!(calls <= n);
            // Then the rest.
            while let Some((g, sc)) = next_in_rank(&order, &mut next, &mut scored, |g| bounds[g], |g| scores[g]) {
                assert_eq!(Some(sc), scores[g]);
                got.push(g);
            }
            assert_eq!(got, full, "trial {trial}");
        }
    }

    fn hough_line(p: [f64; 2], q: [f64; 2]) -> LineCand {
        let l = Line::from_abc([q[1] - p[1], p[0] - q[0], q[0] * p[1] - p[0] * q[1]]).unwrap();
        LineCand { line: l, ends: [p, q], count: 50 }
    }

    #[test]
    fn only_lines_inside_a_verified_shafts_strip_and_along_it_are_its_duplicates() {
        let shaft = found(100.0, 300.0, 200.0, 15.0, 0.0);
        // A rim line 5 px inside a contour, and the contour itself (within 1.5 px): inside.
        assert!(within_strip(&shaft, &hough_line([120.0, 190.0], [280.0, 190.0])));
        assert!(within_strip(&shaft, &hough_line([120.0, 214.0], [280.0, 216.0])));
        // A tissue edge 10 px outside: not.
        assert!(!within_strip(&shaft, &hough_line([120.0, 225.0], [280.0, 225.0])));
        // A contour of a crossing instrument through the strip at 30°: not.
        let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
        assert!(!within_strip(
            &shaft,
            &hough_line([200.0 - 80.0 * c, 200.0 - 80.0 * s], [200.0 + 80.0 * c, 200.0 + 80.0 * s])
        ));
    }
}
