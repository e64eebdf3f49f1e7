//! Why ours misses a shaft (`comanip-bench shaft --diagnose`): each eligible frame where
//! ours returns no detection matching instrument 1 (the benchmark's match rule, unchanged) is
//! put in the first stage of the detector that lost the shaft, from its trace
//! ([`vision::ours::OursDetector::detect_traced`]) and the renderer's true contours:
//!
//! - `few edgels`: on one of the two true contours (its visible part), fewer than 30 % of
//!   the half-resolution edgels a clean edge gives (one per 2 px, within 1.5 px and 10° of it);
//! - `no line`: the edgels are there but no line hypothesis lies on that contour (within 2°,
//!   and its span's middle within 3 px of the contour);
//! - `pair: <test>`: lines on both contours, but every pair of them was turned down by a
//!   cheap test (overlap, crossing, distance, coarse colour);
//! - `not verified`: a pair passed the cheap tests but ranked beyond the verification budget;
//! - `verify: <test>`: verified and turned down by a named test;
//! - `dropped`: verified, then dropped in the final selection;
//! - `returned, no match`: returned, but outside the match rule.
//!
//! Separately it counts the missed frames whose top detection matches the second instrument,
//! and those with a false detection (matching no instrument).
//!
//! With `SHAFT_DIAG_FRAMES` set in the environment, each missed frame (`MISS level family
//! seed class cov=[c0, c1] ...`, `c0`, `c1` the edgel coverage of the two true contours in %
//! as `few edgels` counts it, with every ranked pair's outcome, `*` on the pairs of the true contours,
//! `=1`/`=2` on those matching an instrument) and each frame without instrument 1 that has a
//! false detection (`FALSE ...`) is printed to stderr: a debugging aid, not part of the tables.
//!
//! Each `MISS` line is preceded by a `NEAR` line: per true contour (its line and visible
//! segment), the line hypotheses within 10° and 15 px of it (angle, distance of the
//! hypothesis's span middle, its position along the contour, its votes).
//!
//! With `SHAFT_DIAG_WRONG` set, each returned detection matching no instrument prints `WRONG
//! level family seed rank class=…`: which true contour each of its two contours lies on (`1a`,
//! `1b`, `2a`, `2b`, `-`: within 2° and 3 px at the true contour's visible middle), its
//! errors against both instruments' axes, its ends and confidence.
//!
//! With `SHAFT_DIAG_ACC` set, each matched eligible frame prints `ACC level family seed` and a
//! JSON object to stderr: the returned contours' signed angle errors and offsets against the
//! true contours, the span against the visible length, the middle line's error (an accuracy
//! aid).
//!
//! With `SHAFT_DIAG_ONLY=family:seed,...` only those frames are run.
//!
//! With `SHAFT_DIAG_PNG_EVERY` set (and `SHAFT_DIAG_PNG=DIR`), every frame's overlay is written,
//! not only those printed.
//!
//! With `SHAFT_DIAG_SHARP` set, each frame prints `SHARP level family seed silhouette=N
//! blurred=F`: its silhouette edgels (grey on one side, tissue on the other) and the fraction
//! of them whose step is blurred, the motion-blur measure that gates the Hough window
//! (`OursConfig::hough_window_max_blurred`).
//!
//! A diagnostic only: it runs on whatever set it is given, and is meant for the tuning set.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use estimator::calib::Intrinsics;
use sim::endoscope::label;
use vision::ShaftDetector as _;
use vision::ours::{OursConfig, OursDetector, OursTrace, PairOutcome, PairReject};

use super::metrics::{MATCH_ANGLE_DEG, angle_deg, distance_px, score_frame};
use super::scenes::{ClutterLevel, FAMILIES, SeedSet, frame_specs};
use super::{RenderedFrame, ShaftBenchError, endoscope_config, render_frames};

/// A true contour: line `[a, b, c]` (undistorted pixels) and its visible segment.
type TrueContour = ([f64; 3], [[f64; 2]; 2]);

/// Least fraction of a contour's expected edgels for it to count as seen.
const MIN_EDGEL_COVERAGE: f64 = 0.3;

/// The reason's key of a test.
fn reject_key(r: PairReject) -> &'static str {
    match r {
        PairReject::Overlap => "overlap",
        PairReject::Crossing => "crossing",
        PairReject::Distance => "distance",
        PairReject::CoarseColour => "coarse colour",
        PairReject::ContourA | PairReject::ContourB => "contour refinement",
        PairReject::NoSpan => "no span",
        PairReject::ShortSpan => "short span",
        PairReject::Support => "support",
        PairReject::Refit => "refit",
        PairReject::Trimmed => "trimmed short",
        PairReject::Residual => "residual",
        PairReject::Geometry => "geometry",
        PairReject::AxisDistance => "axis distance",
        PairReject::EndDepth => "end depth",
        PairReject::FineColour => "fine colour",
        PairReject::Axis => "axis",
        PairReject::Border => "border",
        PairReject::Diverging => "diverging",
    }
}

/// Fraction of the expected edgels (one per 2 px of the visible part) found on contour `c`.
fn edgel_coverage(trace: &OursTrace, c: &TrueContour, visible_fraction: f64) -> f64 {
    let ([a, b, cc], [p, q]) = *c;
    let len = (q[0] - p[0]).hypot(q[1] - p[1]);
    if len < 1.0 {
        return 0.0;
    }
    let t = [(q[0] - p[0]) / len, (q[1] - p[1]) / len];
    let cos_tol = 10f64.to_radians().cos();
    let n = trace
        .edgels
        .iter()
        .filter(|e| {
            let (x, y) = (f64::from(e.p[0]), f64::from(e.p[1]));
            let s = (x - p[0]) * t[0] + (y - p[1]) * t[1];
            (a * x + b * y + cc).abs() <= 1.5
                && (0.0..=len).contains(&s)
                && (f64::from(e.n[0]) * a + f64::from(e.n[1]) * b).abs() >= cos_tol
        })
        .count();
    n as f64 * 2.0 / (len * visible_fraction.clamp(0.05, 1.0))
}

/// The line hypotheses lying on contour `c`.
fn lines_on(trace: &OursTrace, c: &TrueContour) -> Vec<usize> {
    let (l, [p, q]) = *c;
    let len = (q[0] - p[0]).hypot(q[1] - p[1]).max(1e-9);
    let t = [(q[0] - p[0]) / len, (q[1] - p[1]) / len];
    trace
        .lines
        .iter()
        .enumerate()
        .filter(|(_, h)| {
            let m = [0.5 * (h.ends[0][0] + h.ends[1][0]), 0.5 * (h.ends[0][1] + h.ends[1][1])];
            let s = (m[0] - p[0]) * t[0] + (m[1] - p[1]) * t[1];
            angle_deg(&h.abc, &l).is_some_and(|a| a <= MATCH_ANGLE_DEG)
                && distance_px(&l, m).is_some_and(|d| d <= 3.0)
                && (-20.0..=len + 20.0).contains(&s)
        })
        .map(|(i, _)| i)
        .collect()
}

/// How far a pair got (larger: later stage).
fn progress(o: &TracePairOutcome) -> u32 {
    match o.0 {
        PairOutcome::Rejected(_) if o.1.is_none() => 0,
        PairOutcome::NotVerified | PairOutcome::Redundant => 1,
        PairOutcome::Rejected(_) => 2,
        PairOutcome::Dropped => 3,
        PairOutcome::Returned(_) => 4,
    }
}

/// A verified pair's figures for the per-frame lines of `SHAFT_DIAG_FRAMES` (empty when not
/// verified).
fn verified_detail(p: &vision::ours::TracePair) -> String {
    p.verified.map_or_else(String::new, |v| {
        format!(
            "{{s={:.2} c={:.2} sup={:.2} sig={:.2} con={:.2} len={:.0} w={:.1} ends=[{:.0},{:.0}]-[{:.0},{:.0}]{}}}",
            v.score,
            v.confidence,
            v.support,
            v.sigma_px,
            v.contrast,
            v.length_px,
            v.width_px,
            v.ends[0][0],
            v.ends[0][1],
            v.ends[1][0],
            v.ends[1][1],
            v.clash.map_or_else(String::new, |(r, rule)| format!(" by {r}:{rule:?}"))
        )
    })
}

/// With `SHAFT_DIAG_ALL` in the environment: one line per frame on stderr, `VER` and a JSON
/// object with every verified pair (its figures, and which instrument it matches: 1, 2 or
/// 0). A debugging aid for the final selection.
fn print_verified(frame: &RenderedFrame, level: ClutterLevel, fam: &str, trace: &OursTrace) {
    let inst2 = if frame.inst2_in_view { frame.inst2.as_ref() } else { None };
    let i1 = frame.inst1.as_ref();
    let pairs: Vec<serde_json::Value> = trace
        .pairs
        .iter()
        .filter_map(|p| {
            let v = p.verified?;
            let abc = p.centreline?;
            let m1 = i1.and_then(|t| super::metrics::line_errors(&abc, t)).is_some_and(|e| e.matches());
            let m2 = inst2.and_then(|t| super::metrics::line_errors(&abc, t)).is_some_and(|e| e.matches());
            Some(serde_json::json!({
                "rank": p.rank, "outcome": p.outcome, "lines": p.lines, "m": if m1 { 1 } else if m2 { 2 } else { 0 },
                "v": v,
            }))
        })
        .collect();
    let eligible = i1.is_some_and(|t| t.eligible());
    let v = serde_json::json!({
        "level": level.key(), "fam": fam, "seed": frame.spec.seed, "eligible": eligible,
        "in_view": frame.inst1_in_view, "pairs": pairs, "clashes": trace.clashes,
    });
    eprintln!("VER {v}");
    if pairs.iter().any(|p| p["m"] == 0 && p["outcome"].get("returned").is_some()) {
        write_diag_png(frame, level, fam, trace);
    }
}

/// With `SHAFT_DIAG_PNG=DIR` in the environment (and `SHAFT_DIAG_FRAMES`), writes the frame
/// printed as `DIR/{level}_{family}_{seed}.png`: the true axes green, the returned
/// detections red, the verified pairs dropped in the final selection yellow. A debugging aid.
fn write_diag_png(frame: &RenderedFrame, level: ClutterLevel, fam: &str, trace: &OursTrace) {
    let Some(dir) = std::env::var_os("SHAFT_DIAG_PNG") else { return };
    let dir = std::path::PathBuf::from(dir);
    let k = super::intrinsics();
    let mut img = frame.image.clone();
    for inst in &frame.truth.instruments {
        if let Some(a) = &inst.axis {
            super::figures::draw_polyline(&mut img, &a.polyline_px, 1, super::figures::TRUTH_RGB);
        }
    }
    for p in &trace.pairs {
        let (Some(abc), true) = (p.centreline, p.rank.is_some()) else { continue };
        let c = match p.outcome {
            PairOutcome::Returned(_) => super::figures::DETECTOR_RGB[0],
            _ => super::figures::DETECTOR_RGB[1],
        };
        super::figures::draw_ideal_line(&mut img, &k, &abc, 0, c, 0, 1);
        if let PairOutcome::Returned(_) = p.outcome {
            for &l in &p.lines {
                super::figures::draw_ideal_line(
                    &mut img,
                    &k,
                    &trace.lines[l].abc,
                    0,
                    super::figures::DETECTOR_RGB[3],
                    0,
                    2,
                );
            }
        }
    }
    let _ = std::fs::create_dir_all(&dir);
    let path = dir.join(format!("{}_{}_{}.png", level.key(), fam, frame.spec.seed));
    if let Err(e) = sim::endoscope::output::write_png(&path, &img) {
        eprintln!("{}: {e}", path.display());
    }
}

/// With `SHAFT_DIAG_ACC` in the environment: one line per matched eligible frame on stderr,
/// `ACC level family seed` and a JSON object: the axis's errors, and per returned contour
/// (matched to the nearer true one) its signed angle error (degrees) and its signed offset
/// at the true contour's visible midpoint (pixels, positive outwards, away from the axis);
/// the returned span's length against the true visible length; the angle errors of the
/// middle line of the returned contours and of the exact axis built from the true contours.
/// A debugging aid for the accuracy.
fn print_accuracy(
    frame: &RenderedFrame,
    level: ClutterLevel,
    fam: &str,
    i1: &super::metrics::TruthAxis,
    det: &vision::ShaftDetection,
    tc: &[TrueContour; 2],
    k: &Intrinsics,
) {
    let unit = |l: [f64; 3]| {
        let n = l[0].hypot(l[1]);
        l.map(|v| v / n)
    };
    let mid = i1.midpoint();
    let axis = unit(i1.line);
    // Signed angle of line `l` from line `r`, degrees (directions taken along r's).
    let signed = |l: [f64; 3], r: [f64; 3]| {
        let (l, r) = (unit(l), unit(r));
        let (dl, dr) = ([-l[1], l[0]], [-r[1], r[0]]);
        let (c, s) = (dl[0] * dr[0] + dl[1] * dr[1], dl[0] * dr[1] - dl[1] * dr[0]);
        let a = s.atan2(c).to_degrees();
        if a > 90.0 {
            a - 180.0
        } else if a < -90.0 {
            a + 180.0
        } else {
            a
        }
    };
    let mut per = Vec::new();
    for (tl, seg) in tc {
        let tm = [0.5 * (seg[0][0] + seg[1][0]), 0.5 * (seg[0][1] + seg[1][1])];
        let Some(c) = det.contours.iter().map(|c| unit(c.abc)).min_by(|a, b| {
            (a[0] * tm[0] + a[1] * tm[1] + a[2]).abs().total_cmp(&(b[0] * tm[0] + b[1] * tm[1] + b[2]).abs())
        }) else {
            continue;
        };
        // Outwards: from the axis towards the true contour.
        let side = (axis[0] * tm[0] + axis[1] * tm[1] + axis[2]).signum();
        let cd = c[0] * tm[0] + c[1] * tm[1] + c[2];
        // The detected contour's point nearest tm is tm - cd·n; outwards distance.
        let foot = [tm[0] - cd * c[0], tm[1] - cd * c[1]];
        let out = side * (axis[0] * foot[0] + axis[1] * foot[1] + axis[2])
            - side * (axis[0] * tm[0] + axis[1] * tm[1] + axis[2]);
        let seg_len = (seg[1][0] - seg[0][0]).hypot(seg[1][1] - seg[0][1]);
        // Normals along the axis's, so that the signs compare between the two contours.
        let along = |l: [f64; 3]| if l[0] * axis[0] + l[1] * axis[1] < 0.0 { l.map(|v| -v) } else { l };
        per.push(serde_json::json!({"ang": signed(along(c), along(unit(*tl))), "out": out, "seg": seg_len}));
    }
    let c0 = unit(det.contours[0].abc);
    let c1 = {
        let c = unit(det.contours[1].abc);
        // Orient alike (normals along the same direction) for the middle line.
        if c[0] * c0[0] + c[1] * c0[1] < 0.0 { c.map(|v| -v) } else { c }
    };
    let middle = [0.5 * (c0[0] + c1[0]), 0.5 * (c0[1] + c1[1]), 0.5 * (c0[2] + c1[2])];
    let true_axis = (|| {
        let a = vision::shaft::ImageLine::new(tc[0].0).ok()?;
        let b = vision::shaft::ImageLine::new(tc[1].0).ok()?;
        vision::shaft::axis_from_contours(&k.k(), &a, &b, mid).ok()
    })();
    let e = super::metrics::line_errors(&det.centreline.abc, i1);
    let omega = {
        let w = frame.spec.scene.instrument.omega_rad_s;
        (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt()
    };
    let len = (det.ends_px[1][0] - det.ends_px[0][0]).hypot(det.ends_px[1][1] - det.ends_px[0][1]);
    let v = serde_json::json!({
        "ang": e.map(|e| e.angle_deg), "sang": signed(
            if det.centreline.abc[0] * axis[0] + det.centreline.abc[1] * axis[1] < 0.0 {
                det.centreline.abc.map(|v| -v)
            } else {
                det.centreline.abc
            },
            axis,
        ), "off": e.map(|e| e.offset_mid_px),
        "len": len, "vis": i1.visible_px, "seg": i1.segment_px(), "conf": det.confidence, "contours": per, "axis_det": det.centreline.abc,
        "tc": [tc[0].0, tc[1].0], "tseg": [tc[0].1, tc[1].1],
        "omega": omega,
        "middle_ang": super::metrics::angle_deg(&middle, &i1.line),
        "true_contours_axis_ang": true_axis.and_then(|a| super::metrics::angle_deg(&a.abc, &i1.line)),
    });
    eprintln!("ACC {} {} {} {v}", level.key(), fam, frame.spec.seed);
}

/// With `SHAFT_DIAG_WRONG` in the environment: one line per returned detection matching no
/// instrument, `WRONG level family seed rank class` and its figures: which true contour each
/// of its two contours lies on (`1`/`2`: instrument, `-`: none; within 2° and 3 px at the true
/// visible contour's middle), its angle and offset against both instruments' axes, its ends.
/// A debugging aid for the wrong detections.
fn print_wrong(frame: &RenderedFrame, level: ClutterLevel, fam: &str, dets: &[vision::ShaftDetection]) {
    let inst2 = if frame.inst2_in_view { frame.inst2.as_ref() } else { None };
    let i1 = frame.inst1.as_ref();
    let contours_of = |lab: u8| -> Option<[TrueContour; 2]> {
        let inst = frame.truth.instruments.iter().find(|i| i.label == lab)?;
        let [c0, c1] = inst.contours.as_ref()?;
        Some([(c0.line_ideal, c0.segment_ideal_px?), (c1.line_ideal, c1.segment_ideal_px?)])
    };
    let tcs = [contours_of(label::INSTRUMENT), if inst2.is_some() { contours_of(label::SECOND) } else { None }];
    let on = |abc: &[f64; 3]| -> String {
        for (k, tc) in tcs.iter().enumerate() {
            for (ci, (l, seg)) in tc.iter().flatten().enumerate() {
                let m = [0.5 * (seg[0][0] + seg[1][0]), 0.5 * (seg[0][1] + seg[1][1])];
                if angle_deg(abc, l).is_some_and(|a| a <= 2.0) && distance_px(abc, m).is_some_and(|d| d <= 3.0) {
                    return format!("{}{}", k + 1, if ci == 0 { "a" } else { "b" });
                }
            }
        }
        "-".into()
    };
    for (r, det) in dets.iter().enumerate() {
        let e1 = i1.and_then(|t| super::metrics::line_errors(&det.centreline.abc, t));
        let e2 = inst2.and_then(|t| super::metrics::line_errors(&det.centreline.abc, t));
        if e1.is_some_and(|e| e.matches()) || e2.is_some_and(|e| e.matches()) {
            continue;
        }
        let sides = det.contours.map(|c| on(&c.abc));
        let mut k: Vec<String> = sides.iter().map(|s| s.chars().next().unwrap_or('-').to_string()).collect();
        k.sort();
        eprintln!(
            "WRONG {} {} {} r{} class={} sides={:?} e1={:?} e2={:?} ends={:?} conf={:.3} eligible={} crossed={:.2}",
            level.key(),
            fam,
            frame.spec.seed,
            r,
            k.join("+"),
            sides,
            e1.map(|e| (e.angle_deg, e.offset_mid_px)),
            e2.map(|e| (e.angle_deg, e.offset_mid_px)),
            det.ends_px,
            det.confidence,
            i1.is_some_and(|t| t.eligible()),
            i1.map_or(0.0, |t| t.crossed_fraction),
        );
    }
}

/// A pair's outcome and its rank.
type TracePairOutcome = (PairOutcome, Option<usize>);

/// The class of a missed frame (see the module docs).
pub fn classify(trace: &OursTrace, contours: &[TrueContour; 2], visible_fraction: f64) -> String {
    let cov = contours.map(|c| edgel_coverage(trace, &c, visible_fraction));
    if cov.iter().any(|&c| c < MIN_EDGEL_COVERAGE) {
        return "few edgels".into();
    }
    let on = contours.map(|c| lines_on(trace, &c));
    if on.iter().any(Vec::is_empty) {
        return "no line".into();
    }
    let best = trace
        .pairs
        .iter()
        .filter(|p| {
            (on[0].contains(&p.lines[0]) && on[1].contains(&p.lines[1]))
                || (on[1].contains(&p.lines[0]) && on[0].contains(&p.lines[1]))
        })
        .max_by_key(|p| progress(&(p.outcome, p.rank)));
    match best.map(|p| (p.outcome, p.rank)) {
        None => "pair: not parallel".into(),
        Some((PairOutcome::Rejected(r), None)) => format!("pair: {}", reject_key(r)),
        Some((PairOutcome::NotVerified, _)) => "not verified".into(),
        Some((PairOutcome::Redundant, _)) => "skipped as a duplicate".into(),
        Some((PairOutcome::Rejected(r), Some(_))) => format!("verify: {}", reject_key(r)),
        Some((PairOutcome::Dropped, _)) => "dropped".into(),
        Some((PairOutcome::Returned(_), _)) => "returned, no match".into(),
    }
}

/// Counts per class, per level and per family.
#[derive(Clone, Debug, Default)]
pub struct Diagnosis {
    /// `(level, family) → (eligible, detected, class → count, second on top, with a false one)`.
    pub cells: BTreeMap<(String, String), DiagCell>,
}

/// One cell of the diagnosis.
#[derive(Clone, Debug, Default)]
pub struct DiagCell {
    /// Eligible frames.
    pub eligible: usize,
    /// Detected (matched) frames.
    pub detected: usize,
    /// Missed frames per class.
    pub classes: BTreeMap<String, usize>,
    /// Missed frames whose top detection is the second instrument.
    pub second_on_top: usize,
    /// Missed frames with a false detection.
    pub with_false: usize,
    /// Frames without instrument 1 in view.
    pub free_frames: usize,
    /// False detections on those.
    pub false_on_free: usize,
    /// Frames (all of them).
    pub frames: usize,
    /// False detections over all frames (matching no instrument in the frame).
    pub false_all: usize,
    /// Angle errors of the matched eligible frames, degrees.
    pub angles_deg: Vec<f64>,
}

/// The true contours of instrument 1 with a visible segment.
fn true_contours(frame: &RenderedFrame) -> Option<[TrueContour; 2]> {
    let inst = frame.truth.instruments.iter().find(|i| i.label == label::INSTRUMENT)?;
    let [c0, c1] = inst.contours.as_ref()?;
    Some([(c0.line_ideal, c0.segment_ideal_px?), (c1.line_ideal, c1.segment_ideal_px?)])
}

/// Runs ours (default settings, or `SHAFT_DIAG_OURS`'s) traced on the frames of `set` at `levels` and classifies the
/// misses. `progress` is called once per frame rendered and once per frame diagnosed.
pub fn run(
    k: &Intrinsics,
    set: SeedSet,
    frames_per_family: usize,
    levels: &[ClutterLevel],
    progress: &(dyn Fn() + Sync),
) -> Result<Diagnosis, ShaftBenchError> {
    let mut specs = frame_specs(set, frames_per_family, &endoscope_config(set, ClutterLevel::Clean))?;
    // `SHAFT_DIAG_ONLY=family:seed,...`: only those frames (a debugging aid).
    if let Ok(only) = std::env::var("SHAFT_DIAG_ONLY") {
        let keep: Vec<String> = only.split(',').map(|s| s.trim().to_owned()).collect();
        specs.retain(|s| keep.contains(&format!("{}:{}", FAMILIES[s.family].key, s.seed)));
    }
    // `SHAFT_DIAG_OURS`: settings of ours as JSON (the fields to change; the others keep
    // their defaults), to measure a setting against the default on the same frames.
    let cfg = match std::env::var("SHAFT_DIAG_OURS") {
        Ok(json) => serde_json::from_str::<OursConfig>(&json)
            .map_err(|e| ShaftBenchError::Io { path: "SHAFT_DIAG_OURS".into(), message: e.to_string() })?,
        Err(_) => OursConfig::default(),
    };
    let mut det =
        OursDetector::new(*k, cfg).map_err(|e| ShaftBenchError::Io { path: "ours".into(), message: e.to_string() })?;
    let mut d = Diagnosis::default();
    for &level in levels {
        let frames = render_frames(set, level, &specs, progress)?;
        for frame in &frames {
            let view = frame.view()?;
            let (dets, trace) = det
                .detect_traced(&view)
                .map_err(|source| ShaftBenchError::Detect { detector: det.name().to_owned(), source })?;
            progress();
            let fam = FAMILIES[frame.spec.family].key;
            {
                let inst2 = if frame.inst2_in_view { frame.inst2.as_ref() } else { None };
                let s = score_frame(&dets, frame.inst1.as_ref(), inst2);
                let cell = d.cells.entry((level.key().to_owned(), fam.to_owned())).or_default();
                cell.frames += 1;
                cell.false_all += s.false_detections;
            }
            if std::env::var_os("SHAFT_DIAG_ALL").is_some() {
                print_verified(frame, level, fam, &trace);
            }
            if std::env::var_os("SHAFT_DIAG_WRONG").is_some() {
                print_wrong(frame, level, fam, &dets);
            }
            if std::env::var_os("SHAFT_DIAG_PNG_EVERY").is_some() {
                write_diag_png(frame, level, fam, &trace);
            }
            if std::env::var_os("SHAFT_DIAG_SHARP").is_some() {
                eprintln!(
                    "SHARP {} {} {} silhouette={} blurred={:.3} eligible={}",
                    level.key(),
                    fam,
                    frame.spec.seed,
                    trace.silhouette.0,
                    trace.silhouette.1,
                    frame.inst1.as_ref().is_some_and(|t| t.eligible())
                );
            }
            if !frame.inst1_in_view {
                let inst2 = if frame.inst2_in_view { frame.inst2.as_ref() } else { None };
                let s = score_frame(&dets, None, inst2);
                let cell = d.cells.entry((level.key().to_owned(), fam.to_owned())).or_default();
                cell.free_frames += 1;
                cell.false_on_free += s.false_detections;
                if s.false_detections > 0 && std::env::var_os("SHAFT_DIAG_FRAMES").is_some() {
                    let outs: Vec<String> = trace
                        .pairs
                        .iter()
                        .filter(|p| p.rank.is_some())
                        .map(|p| {
                            let e2 =
                                p.centreline.and_then(|abc| inst2.and_then(|t| super::metrics::line_errors(&abc, t)));
                            format!(
                                "{:?}:{:?}{}{}",
                                p.rank,
                                p.outcome,
                                if e2.is_some_and(|e| e.matches()) { "=2" } else { "" },
                                verified_detail(p)
                            )
                        })
                        .collect();
                    write_diag_png(frame, level, fam, &trace);
                    eprintln!(
                        "FALSE {} {} {} dets={:?} pairs=[{}]",
                        level.key(),
                        fam,
                        frame.spec.seed,
                        dets.iter().map(|d| (d.centreline.abc, d.confidence, d.ends_px)).collect::<Vec<_>>(),
                        outs.join(" ")
                    );
                }
            }
            let Some(i1) = frame.inst1.as_ref().filter(|t| t.eligible()) else { continue };
            let inst2 = if frame.inst2_in_view { frame.inst2.as_ref() } else { None };
            let s = score_frame(&dets, Some(i1), inst2);
            let cell = d.cells.entry((level.key().to_owned(), fam.to_owned())).or_default();
            cell.eligible += 1;
            if let Some(e) = s.matched {
                cell.detected += 1;
                cell.angles_deg.push(e.angle_deg);
                if std::env::var_os("SHAFT_DIAG_ACC").is_some()
                    && let (Some(r), Some(tc)) = (s.matched_rank, true_contours(frame))
                {
                    print_accuracy(frame, level, fam, i1, &dets[r], &tc, k);
                }
                continue;
            }
            let class = match true_contours(frame) {
                Some(c) => classify(&trace, &c, i1.visible_px / i1.segment_px().max(1e-9)),
                None => "no true contours".into(),
            };
            if std::env::var_os("SHAFT_DIAG_FRAMES").is_some() {
                let on = true_contours(frame).map(|c| c.map(|c| lines_on(&trace, &c)));
                let mut pairs: Vec<String> = Vec::new();
                for p in &trace.pairs {
                    let mark = on.as_ref().is_some_and(|on| {
                        (on[0].contains(&p.lines[0]) && on[1].contains(&p.lines[1]))
                            || (on[1].contains(&p.lines[0]) && on[0].contains(&p.lines[1]))
                    });
                    let e2 = p.centreline.and_then(|abc| inst2.and_then(|t| super::metrics::line_errors(&abc, t)));
                    let e1 = p.centreline.and_then(|abc| super::metrics::line_errors(&abc, i1));
                    if p.rank.is_some() || mark {
                        pairs.push(format!(
                            "{}{:?}:{:?}{}{}{}",
                            if mark { "*" } else { "" },
                            p.rank,
                            p.outcome,
                            if e1.is_some_and(|e| e.matches()) { "=1" } else { "" },
                            if e2.is_some_and(|e| e.matches()) { "=2" } else { "" },
                            verified_detail(p)
                        ));
                    }
                }
                write_diag_png(frame, level, fam, &trace);
                let on_lines: Vec<String> = on
                    .iter()
                    .flatten()
                    .flatten()
                    .map(|&l| {
                        let h = &trace.lines[l];
                        format!(
                            "{l}:[{:.0},{:.0}]-[{:.0},{:.0}]v{}",
                            h.ends[0][0], h.ends[0][1], h.ends[1][0], h.ends[1][1], h.votes
                        )
                    })
                    .collect();
                // Per true contour, the nearest line hypotheses: (line, angle °, distance of its
                // span's middle from the contour px, s of the middle along the contour, votes).
                let near: Vec<String> = true_contours(frame)
                    .iter()
                    .flatten()
                    .map(|(l, [p, q])| {
                        let len = (q[0] - p[0]).hypot(q[1] - p[1]).max(1e-9);
                        let t = [(q[0] - p[0]) / len, (q[1] - p[1]) / len];
                        let mut v: Vec<(usize, f64, f64, f64, usize)> = trace
                            .lines
                            .iter()
                            .enumerate()
                            .filter_map(|(i, h)| {
                                let m = [0.5 * (h.ends[0][0] + h.ends[1][0]), 0.5 * (h.ends[0][1] + h.ends[1][1])];
                                let s = (m[0] - p[0]) * t[0] + (m[1] - p[1]) * t[1];
                                Some((i, angle_deg(&h.abc, l)?, distance_px(l, m)?, s, h.votes))
                            })
                            .filter(|x| x.1 < 10.0 && x.2 < 15.0)
                            .collect();
                        v.sort_by(|a, b| a.2.total_cmp(&b.2));
                        format!(
                            "[len {len:.0} abc {l:?} seg {p:?} {q:?}: {}]",
                            v.iter()
                                .map(|x| format!("{}:{:.1}°/{:.1}px/s{:.0}/v{}", x.0, x.1, x.2, x.3, x.4))
                                .collect::<Vec<_>>()
                                .join(" ")
                        )
                    })
                    .collect();
                eprintln!("NEAR {} {} {} {}", level.key(), fam, frame.spec.seed, near.join(" "));
                eprintln!(
                    "MISS {} {} {} class={} cov={:?} lines={} on={:?} {} vis={:.0} pairs=[{}]",
                    level.key(),
                    fam,
                    frame.spec.seed,
                    class,
                    true_contours(frame).map(|c| c.map(|c| (edgel_coverage(
                        &trace,
                        &c,
                        i1.visible_px / i1.segment_px().max(1e-9)
                    ) * 100.0)
                        .round() as i32)),
                    trace.lines.len(),
                    on,
                    on_lines.join(" "),
                    i1.visible_px,
                    pairs.join(" ")
                );
            }
            *cell.classes.entry(class).or_default() += 1;
            cell.second_on_top += usize::from(
                s.second_matches > 0 && s.matched_rank.is_none() && {
                    let e2 = inst2.and_then(|t| super::metrics::line_errors(&dets[0].centreline.abc, t));
                    e2.is_some_and(|e| e.matches())
                },
            );
            cell.with_false += usize::from(s.false_detections > 0);
        }
    }
    Ok(d)
}

impl Diagnosis {
    /// The Markdown tables: per level, then per family (every level).
    pub fn markdown(&self) -> String {
        let mut classes: Vec<String> = self.cells.values().flat_map(|c| c.classes.keys().cloned()).collect();
        classes.sort();
        classes.dedup();
        let mut m = String::new();
        for (title, by_level) in [("level", true), ("family", false)] {
            let mut groups: BTreeMap<String, DiagCell> = BTreeMap::new();
            for ((level, fam), c) in &self.cells {
                let g = groups.entry(if by_level { level.clone() } else { fam.clone() }).or_default();
                g.eligible += c.eligible;
                g.detected += c.detected;
                g.second_on_top += c.second_on_top;
                g.with_false += c.with_false;
                g.free_frames += c.free_frames;
                g.false_on_free += c.false_on_free;
                g.frames += c.frames;
                g.false_all += c.false_all;
                g.angles_deg.extend_from_slice(&c.angles_deg);
                for (k, v) in &c.classes {
                    *g.classes.entry(k.clone()).or_default() += v;
                }
            }
            let _ = writeln!(
                m,
                "\n| {title} | eligible | detected | missed | {} | second on top | with a false one | false on instrument-free frames (n) | false over all frames (n) | angle ° median |",
                classes.join(" | ")
            );
            let _ = writeln!(m, "|---|---|---|---|{}---|---|---|---|---|", "---|".repeat(classes.len()));
            let order: Vec<String> = if by_level {
                ClutterLevel::ALL.iter().map(|l| l.key().to_owned()).filter(|k| groups.contains_key(k)).collect()
            } else {
                groups.keys().cloned().collect()
            };
            for key in order {
                let g = &groups[&key];
                let _ = writeln!(
                    m,
                    "| {key} | {} | {} | {} | {} | {} | {} | {} ({}) | {} ({}) | {} |",
                    g.eligible,
                    g.detected,
                    g.eligible - g.detected,
                    classes
                        .iter()
                        .map(|c| g.classes.get(c).copied().unwrap_or(0).to_string())
                        .collect::<Vec<_>>()
                        .join(" | "),
                    g.second_on_top,
                    g.with_false,
                    g.false_on_free,
                    g.free_frames,
                    g.false_all,
                    g.frames,
                    super::metrics::quantile(&g.angles_deg, 0.5).map_or_else(|| "–".to_owned(), |q| format!("{q:.3}"))
                );
            }
        }
        m
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use vision::ours::{TraceEdgel, TraceLine, TracePair};

    /// Two true contours `v = 100` and `v = 130` from `u = 0` to `u = 200`.
    fn contours() -> [TrueContour; 2] {
        [([0.0, 1.0, -100.0], [[0.0, 100.0], [200.0, 100.0]]), ([0.0, 1.0, -130.0], [[0.0, 130.0], [200.0, 130.0]])]
    }

    /// Edgels every 2 px along both contours (normals along v) and one line on each.
    fn trace_with_lines() -> OursTrace {
        let mut t = OursTrace::default();
        for v in [100.0f32, 130.0] {
            t.edgels.extend((0..100).map(|i| TraceEdgel { p: [2.0 * i as f32, v], n: [0.0, 1.0] }));
            t.lines.push(TraceLine {
                abc: [0.0, 1.0, -f64::from(v) - 0.5],
                ends: [[0.0, f64::from(v) + 0.5], [198.0, f64::from(v) + 0.5]],
                votes: 100,
            });
        }
        t
    }

    fn pair(outcome: PairOutcome, rank: Option<usize>) -> TracePair {
        TracePair { lines: [1, 0], rank, outcome, centreline: None, verified: None }
    }

    #[test]
    fn a_miss_is_put_in_the_first_stage_that_lost_the_shaft() {
        let c = contours();
        // No edgels on the second contour.
        let mut t = trace_with_lines();
        t.edgels.retain(|e| e.p[1] < 120.0);
        assert_eq!(classify(&t, &c, 1.0), "few edgels");
        // Only 40 px of the second contour with edgels: few on a fully visible shaft, but all
        // there is when only a fifth of it is visible (then both lines are there, no pair).
        let mut t = trace_with_lines();
        t.edgels.retain(|e| e.p[1] < 120.0 || e.p[0] < 40.0);
        assert_eq!(classify(&t, &c, 1.0), "few edgels");
        assert_eq!(classify(&t, &c, 0.2), "pair: not parallel");
        // Edgels but the second line 3° off.
        let mut t = trace_with_lines();
        let a = 3f64.to_radians();
        t.lines[1].abc = [-a.sin(), a.cos(), -130.0];
        assert_eq!(classify(&t, &c, 1.0), "no line");
        // Lines, pairs at each stage: the furthest stage wins.
        let mut t = trace_with_lines();
        assert_eq!(classify(&t, &c, 1.0), "pair: not parallel");
        t.pairs.push(pair(PairOutcome::Rejected(PairReject::CoarseColour), None));
        assert_eq!(classify(&t, &c, 1.0), "pair: coarse colour");
        t.pairs.push(pair(PairOutcome::NotVerified, Some(9)));
        assert_eq!(classify(&t, &c, 1.0), "not verified");
        t.pairs.push(pair(PairOutcome::Rejected(PairReject::Border), Some(2)));
        assert_eq!(classify(&t, &c, 1.0), "verify: border");
        t.pairs.push(pair(PairOutcome::Dropped, Some(3)));
        assert_eq!(classify(&t, &c, 1.0), "dropped");
        t.pairs.push(pair(PairOutcome::Returned(1), Some(4)));
        assert_eq!(classify(&t, &c, 1.0), "returned, no match");
        // A pair of other lines does not count.
        let mut t = trace_with_lines();
        t.lines.push(t.lines[0]);
        t.lines[2].abc[2] -= 40.0;
        t.pairs.push(TracePair {
            lines: [0, 2],
            rank: Some(0),
            outcome: PairOutcome::Returned(0),
            centreline: None,
            verified: None,
        });
        assert_eq!(classify(&t, &c, 1.0), "pair: not parallel");
    }
}
