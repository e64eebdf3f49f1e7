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
//!    undistortion per frame): there the contours are straight lines.
//! 2. **Line hypotheses** (`hough`): an orientation-guided Hough transform (each edgel votes
//!    once at its own normal, 1° × 2 px bins, peaks of a 5 × 3 box sum), then each peak's
//!    edgels are gathered and refitted (total least squares) and its supported span found.
//! 3. **Pairs with physics**: two lines are the contours of one cylinder of radius `r` only
//!    if they are nearly parallel, overlap along their length, and the angle `θ` between their
//!    planes through the optical centre (normals `Kᵀl`) gives a plausible distance of the
//!    axis, `d = r / sin(θ/2)`, inside `[min_depth_m, max_depth_m]` (this is what rejects
//!    vessels and creases: far too thin for a shaft at that distance). Then the **interior
//!    colour test**: the strip between the lines must be clearly less red than the tissue just
//!    outside on both sides (`C_out − C_in ≥ min_chroma_contrast` and `C_in ≤
//!    max_interior_chroma_ratio · C_out`); a vessel is redder inside, a pair of unrelated
//!    tissue edges has tissue inside, a fold's highlight stays pink.
//! 4. **Sub-pixel refinement** of each contour in the full-resolution measured image: profiles
//!    across the contour at every pixel along it, sampled at undistorted positions mapped
//!    through the lens (so each found edge is directly an undistorted point on the straight
//!    contour), the peak of `√(dC² + dL²)` located by a parabola, then a Tukey-biweight IRLS
//!    line fit (the wrist, the jaws, a crossing instrument and specular spots become
//!    outliers). Two rounds (gates ±3 px then ±1.5 px).
//! 5. **The exact axis** from the two refined contours, [`crate::shaft::axis_from_contours`]
//!    (the middle line is wrong by up to pixels under perspective), the distance gate and the
//!    colour test again on the refined lines, then the visible span: the overlap of both
//!    contours' inlier edges, projected on the axis and mapped back to measured pixels.
//!
//! A second instrument is a second valid pair (both are returned, best first); pairs sharing a
//! contour with a better one, or duplicating its axis, are dropped.
//!
//! ## Confidence
//!
//! `support × 1/(1 + (σ/0.5 px)²) × min(1, contrast / (3·min_chroma_contrast))`: `support` is
//! the smaller of the two contours' fractions of the visible span with an inlier edge, `σ` the
//! larger robust residual scale of the two fits (pixels), `contrast` the smaller interior/outside
//! chroma difference.
//!
//! Pixels: measured (distorted) images in, lines in undistorted pixels, `ends_px` measured.

mod edges;
mod geom;
mod hough;
mod lens;
mod profile;

use estimator::calib::Intrinsics;
use estimator::calib::camera::IntrinsicsError;
use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::detect::{DetectError, RgbView, ShaftDetection, ShaftDetector, check_size};
use crate::shaft::{ImageLine, axis_from_contours};
use edges::EdgeBuffers;
use geom::{Line, robust_fit};
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
    /// Shortest visible shaft (both contours), undistorted pixels (default 80).
    pub min_length_px: f64,
    /// Edgel threshold on the half-resolution Di Zenzo gradient magnitude (chroma units
    /// `2R − G − B` per half-resolution pixel, 8-bit values; default 6).
    pub edge_threshold: f64,
    /// Weight of luma against the chroma `2R − G − B` in the gradients (default 1).
    pub luma_weight: f64,
    /// Most line hypotheses kept (default 40).
    pub max_lines: usize,
    /// Most shafts returned (default 2).
    pub max_detections: usize,
    /// Least chroma drop from the tissue just outside to the shaft's interior, both sides
    /// (chroma units `2R − G − B`, default 12).
    pub min_chroma_contrast: f64,
    /// Largest interior chroma as a fraction of the chroma outside, both sides (default 0.5).
    pub max_interior_chroma_ratio: f64,
    /// Largest robust residual scale of a contour's fit, pixels (default 0.8).
    pub max_residual_px: f64,
    /// Least fraction of the visible span with an inlier edge on each contour (default 0.5).
    pub min_support: f64,
}

impl Default for OursConfig {
    fn default() -> Self {
        Self {
            shaft_diameter_m: 0.008,
            min_depth_m: 0.010,
            max_depth_m: 0.300,
            min_length_px: 80.0,
            edge_threshold: 6.0,
            luma_weight: 1.0,
            max_lines: 40,
            max_detections: 2,
            min_chroma_contrast: 12.0,
            max_interior_chroma_ratio: 0.5,
            max_residual_px: 0.8,
            min_support: 0.5,
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
    /// The undistorted image region is unbounded or far larger than the image: the distortion
    /// does not invert over the image (a polynomial that folds back before the corners).
    #[error("the distortion does not invert over the image: undistorted radius {radius_px} px (limit {limit_px} px)")]
    Undistortion {
        /// Largest distance of an undistorted half-resolution pixel from the principal point,
        /// undistorted pixels (infinite or NaN when the inversion diverged).
        radius_px: f32,
        /// [`MAX_UNDISTORTED_RADIUS_FACTOR`] × the image's diagonal, pixels.
        limit_px: f32,
    },
}

/// The undistorted image region may reach this many image diagonals from the principal point
/// (a wide-angle lens: about 1); beyond, [`OursDetector::new`] refuses the camera
/// ([`OursConfigError::Undistortion`]) instead of sizing its Hough accumulator on it.
pub const MAX_UNDISTORTED_RADIUS_FACTOR: f32 = 8.0;

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
        check((1..=10_000).contains(&self.max_lines), "max_lines", "1 ..= 10000")?;
        check(self.max_detections >= 1, "max_detections", "≥ 1")?;
        check(
            self.min_chroma_contrast.is_finite() && self.min_chroma_contrast >= 0.0,
            "min_chroma_contrast",
            "finite and ≥ 0",
        )?;
        check(
            self.max_interior_chroma_ratio.is_finite() && self.max_interior_chroma_ratio >= 0.0,
            "max_interior_chroma_ratio",
            "finite and ≥ 0",
        )?;
        check(pos(self.max_residual_px), "max_residual_px", "finite and > 0")?;
        check((0.0..=1.0).contains(&self.min_support), "min_support", "in [0, 1]")?;
        Ok(())
    }
}

/// A verified shaft before it becomes a [`ShaftDetection`].
#[derive(Clone, Copy, Debug)]
struct Found {
    det: ShaftDetection,
    /// The axis point at the span's middle, undistorted pixels.
    mid: [f64; 2],
    lines: [usize; 2],
    score: f64,
}

/// Our shaft detector (see the module docs). Keeps its working buffers between frames.
#[derive(Clone, Debug)]
pub struct OursDetector {
    k: Intrinsics,
    kmat: Matrix3<f64>,
    cfg: OursConfig,
    lens: Lens,
    table: HalfResTable,
    edges: EdgeBuffers,
    hough: Hough,
    pts: Vec<[f64; 2]>,
    ss: Vec<f64>,
    w: Vec<f64>,
    res: Vec<f64>,
    col: [Vec<f64>; 3],
    found: Vec<Found>,
}

/// A contour refined in the full-resolution image.
#[derive(Clone, Copy, Debug)]
struct Contour {
    line: Line,
    sigma: f64,
    /// Span of the inlier edges along the pair's direction, pixels from the pair's origin.
    span: [f64; 2],
    inliers: usize,
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
        let (mut rmax, c) = (1.0f32, [k.cx as f32, k.cy as f32]);
        for p in &table.uv {
            // NaN when an undistortion diverged: kept (f32::max would drop it).
            let r = (p[0] - c[0]).hypot(p[1] - c[1]);
            rmax = if r.is_nan() { r } else { rmax.max(r) };
        }
        let limit_px = MAX_UNDISTORTED_RADIUS_FACTOR * (k.width as f32).hypot(k.height as f32);
        if !(rmax <= limit_px) {
            return Err(OursConfigError::Undistortion { radius_px: rmax, limit_px });
        }
        let hough = Hough::new(c, rmax + 4.0);
        Ok(Self {
            kmat: k.k(),
            lens: Lens::new(&k),
            k,
            cfg,
            table,
            edges: EdgeBuffers::default(),
            hough,
            pts: Vec::new(),
            ss: Vec::new(),
            w: Vec::new(),
            res: Vec::new(),
            col: Default::default(),
            found: Vec::new(),
        })
    }

    /// The settings.
    pub fn config(&self) -> &OursConfig {
        &self.cfg
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

    /// The pair's frame: an origin on `a`'s span and a unit direction along `a`.
    fn pair_frame(a: &LineCand) -> ([f64; 2], [f64; 2]) {
        let o = a.ends[0];
        let d = [a.ends[1][0] - o[0], a.ends[1][1] - o[1]];
        let n = d[0].hypot(d[1]);
        let t = if n > 0.0 { [d[0] / n, d[1] / n] } else { a.line.direction() };
        (o, t)
    }

    /// Refines one contour along `s ∈ range` of the frame `(o, t)`.
    fn refine(
        &mut self,
        sampler: &Sampler<'_>,
        start: Line,
        o: [f64; 2],
        t: [f64; 2],
        range: [f64; 2],
    ) -> Option<Contour> {
        let mut line = start;
        let mut fit = None;
        for (gate, step) in [(3.0, 2.0), (1.5, 1.0)] {
            self.pts.clear();
            // Walk the line itself: the foot of o on it, along its own direction (aligned with t).
            let lt = line.direction();
            let lt = if lt[0] * t[0] + lt[1] * t[1] >= 0.0 { lt } else { [-lt[0], -lt[1]] };
            let dist = line.distance(o);
            let o_l = [o[0] - dist * line.n[0], o[1] - dist * line.n[1]];
            let n_steps = ((range[1] - range[0]) / step).floor().max(0.0) as usize;
            for k in 0..=n_steps {
                let s = range[0] + k as f64 * step;
                let p = [o_l[0] + s * lt[0], o_l[1] + s * lt[1]];
                if let Some((off, _)) = sampler.edge_offset(&line, p, gate, 0.75 * self.cfg.edge_threshold) {
                    self.pts.push([p[0] + off * line.n[0], p[1] + off * line.n[1]]);
                }
            }
            if self.pts.len() < 8 {
                return None;
            }
            let f = robust_fit(&self.pts, line, &mut self.w, &mut self.res)?;
            line = f.line;
            fit = Some(f);
        }
        let f = fit?;
        // Span of the inliers along t (isolated ends trimmed).
        self.ss.clear();
        for (p, w) in self.pts.iter().zip(&self.w) {
            if *w > 0.0 {
                self.ss.push((p[0] - o[0]) * t[0] + (p[1] - o[1]) * t[1]);
            }
        }
        self.ss.sort_by(f64::total_cmp);
        let span = trimmed_span(&self.ss, 16.0, 6)?;
        let inliers = self.ss.iter().filter(|s| **s >= span[0] && **s <= span[1]).count();
        Some(Contour { line, sigma: f.sigma, span, inliers })
    }

    /// Checks and refines the pair `(ia, ib)` of line hypotheses.
    fn verify(&mut self, image: &RgbView<'_>, ia: usize, ib: usize) -> Option<Found> {
        let (a, b) = (self.hough.lines[ia], self.hough.lines[ib]);
        let cfg = self.cfg;
        let lens = self.lens;
        let sampler = Sampler { image, lens: &lens, luma_weight: cfg.luma_weight };
        let (o, t) = Self::pair_frame(&a);
        let proj = |p: [f64; 2]| (p[0] - o[0]) * t[0] + (p[1] - o[1]) * t[1];
        let sa = [proj(a.ends[0]), proj(a.ends[1])];
        let sb = {
            let (x, y) = (proj(b.ends[0]), proj(b.ends[1]));
            [x.min(y), x.max(y)]
        };
        let ov = [sa[0].max(sb[0]), sa[1].min(sb[1])];
        if ov[1] - ov[0] < 0.6 * cfg.min_length_px {
            dbg_reject(1);
            return None;
        }
        // Refine both contours over the union of the spans, a little extended.
        let range = [sa[0].min(sb[0]) - 12.0, sa[1].max(sb[1]) + 12.0];
        let Some(ca) = self.refine(&sampler, a.line, o, t, range) else {
            dbg_reject(21);
            return None;
        };
        let Some(cb) = self.refine(&sampler, b.line, o, t, range) else {
            dbg_reject(22);
            return None;
        };
        if std::env::var_os("OURS_DEBUG").is_some() {
            eprintln!("  ca {ca:?}\n  cb {cb:?}");
        }
        let span = [ca.span[0].max(cb.span[0]), ca.span[1].min(cb.span[1])];
        let len = span[1] - span[0];
        if len < cfg.min_length_px {
            dbg_reject(3);
            return None;
        }
        let sigma = ca.sigma.max(cb.sigma);
        if sigma > cfg.max_residual_px {
            dbg_reject(4);
            return None;
        }
        let support = (ca.inliers.min(cb.inliers) as f64 / (len + 1.0)).min(1.0);
        if support < cfg.min_support {
            dbg_reject(5);
            return None;
        }
        // Interior point: middle of the two contours at the span's middle.
        let sm = 0.5 * (span[0] + span[1]);
        let q = [o[0] + sm * t[0], o[1] + sm * t[1]];
        let d = [-t[1], t[0]];
        let (la, lb) = (ca.line.hit(q, d)?, cb.line.hit(q, d)?);
        let mid = 0.5 * (la + lb);
        let inside = [q[0] + mid * d[0], q[1] + mid * d[1]];
        let dist = self.axis_distance(&ca.line, &cb.line, inside)?;
        if !(dist >= cfg.min_depth_m && dist <= cfg.max_depth_m) {
            dbg_reject(6);
            return None;
        }
        let fine = interior(&sampler, [&ca.line, &cb.line], o, t, span, &mut self.col)?;
        if !self.colour_ok(&fine) {
            dbg_reject(7);
            return None;
        }
        let c0 = ImageLine::new(ca.line.abc()).ok()?;
        let c1 = ImageLine::new(cb.line.abc()).ok()?;
        let axis = axis_from_contours(&self.kmat, &c0, &c1, inside).ok()?;
        let axis_l = Line::from_abc(axis.abc)?;
        // Ends: the span's ends projected on the axis, mapped to measured pixels.
        let mut ends_px = [[0.0; 2]; 2];
        for (e, s) in ends_px.iter_mut().zip(span) {
            let p = [o[0] + s * t[0], o[1] + s * t[1]];
            let dd = axis_l.distance(p);
            let f = [p[0] - dd * axis_l.n[0], p[1] - dd * axis_l.n[1]];
            let (x, y) = self.lens.distort_px(f[0], f[1]);
            *e = [x, y];
        }
        let contrast = (fine.outside[0] - fine.inside).min(fine.outside[1] - fine.inside);
        let confidence = support / (1.0 + (sigma / 0.5).powi(2))
            * (contrast / (3.0 * cfg.min_chroma_contrast.max(1e-9))).clamp(0.0, 1.0);
        Some(Found {
            det: ShaftDetection { centreline: axis, contours: [c0, c1], ends_px, confidence },
            mid: {
                let dd = axis_l.distance(q);
                [q[0] - dd * axis_l.n[0], q[1] - dd * axis_l.n[1]]
            },
            lines: [ia, ib],
            score: confidence * len.sqrt(),
        })
    }

    fn colour_ok(&self, c: &profile::Interior) -> bool {
        c.outside.iter().all(|&out| {
            out - c.inside >= self.cfg.min_chroma_contrast && c.inside <= self.cfg.max_interior_chroma_ratio * out
        })
    }

    /// The candidate pairs of line hypotheses, best first (cheap geometric tests only).
    fn pairs(&mut self, image: &RgbView<'_>) -> Vec<(f64, usize, usize)> {
        let lens = self.lens;
        let sampler = Sampler { image, lens: &lens, luma_weight: self.cfg.luma_weight };
        let mut col = std::mem::take(&mut self.col);
        let lines = &self.hough.lines;
        let cfg = self.cfg;
        let mut out = Vec::new();
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
                    continue;
                }
                let Some(dist) = self.axis_distance(&a.line, &b.line, inside) else { continue };
                if !(dist >= 0.6 * cfg.min_depth_m && dist <= 1.6 * cfg.max_depth_m) {
                    continue;
                }
                // Coarse colour test on the hypotheses.
                let Some(c) = interior(&sampler, [&a.line, &b.line], o, t, ov, &mut col) else { continue };
                if !self.colour_ok(&c) {
                    continue;
                }
                out.push((len * (a.count.min(b.count) as f64), i, j));
            }
        }
        self.col = col;
        out.sort_by(|a, b| b.0.total_cmp(&a.0));
        out
    }
}

/// The extent of the sorted `s` after trimming, at each end, points with fewer than
/// `min_count` points within `window` towards the bulk; `None` when nothing is left.
fn trimmed_span(s: &[f64], window: f64, min_count: usize) -> Option<[f64; 2]> {
    let n = s.len();
    let dense = |i: usize, fwd: bool| {
        if fwd {
            s[i..].iter().take_while(|&&x| x <= s[i] + window).count() >= min_count
        } else {
            s[..=i].iter().rev().take_while(|&&x| x >= s[i] - window).count() >= min_count
        }
    };
    let lo = (0..n).find(|&i| dense(i, true))?;
    let hi = (lo..n).rev().find(|&i| dense(i, false))?;
    (hi > lo).then(|| [s[lo], s[hi]])
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
        let cfg = self.cfg;
        self.edges.run(image, &self.table, cfg.edge_threshold as f32, cfg.luma_weight as f32);
        let min_votes = (0.3 * cfg.min_length_px).max(8.0) as u32;
        self.hough.run(&self.edges.edgels, min_votes, cfg.max_lines);
        let pairs = self.pairs(image);
        if std::env::var_os("OURS_DEBUG").is_some() {
            eprintln!("edgels {} lines {} pairs {}", self.edges.edgels.len(), self.hough.lines.len(), pairs.len());
            for l in &self.hough.lines {
                eprintln!("  line n={:?} c={:.1} ends={:?} count={}", l.line.n, l.line.c, l.ends, l.count);
            }
            for p in pairs.iter().take(10) {
                eprintln!("  pair {p:?}");
            }
        }
        self.found.clear();
        let mut tried = 0;
        for &(_, i, j) in &pairs {
            if self.found.len() >= cfg.max_detections || tried >= 4 * cfg.max_detections + 4 {
                break;
            }
            if self.found.iter().any(|f| f.lines.contains(&i) || f.lines.contains(&j)) {
                continue;
            }
            tried += 1;
            if let Some(f) = self.verify(image, i, j) {
                let dup = self.found.iter().any(|g| same_axis(g, &f));
                if !dup {
                    self.found.push(f);
                }
            }
        }
        self.found.sort_by(|a, b| b.score.total_cmp(&a.score));
        Ok(self.found.iter().map(|f| f.det).collect())
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

fn dbg_reject(why: u32) {
    if std::env::var_os("OURS_DEBUG").is_some() {
        eprintln!("  reject {why}");
    }
}
