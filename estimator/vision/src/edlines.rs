//! EDLines, the real-time line-segment detector with a false detection control (C. Akinlar and
//! C. Topal, *EDLines: A real-time line segment detector with a false detection control*,
//! Pattern Recognition Letters 32(13), 2011), on top of Edge Drawing (C. Topal and C. Akinlar,
//! *Edge Drawing: a combined real-time edge and segment detector*, Journal of Visual
//! Communication and Image Representation 23(6), 2012).
//!
//! The stages, each in the papers' terms:
//!
//! 1. **Smoothing**: a Gaussian low-pass of `smoothing_size × smoothing_size` taps (separable,
//!    OpenCV's default border: reflect-101). ED uses 5×5, σ = 1; the calibration paper
//!    replaces it by an 11×11 low-pass ([`EdLinesParams::paper`]).
//! 2. **Gradient**: the Sobel operator on the smoothed image (ED's operator for EDLines),
//!    scaled by 1/8 so that the magnitude is in grey levels per pixel (a ramp of slope `s`
//!    gives `s`), the unit of the threshold's quantisation argument; the magnitude is the
//!    Euclidean norm `√(gx² + gy²)`. Each pixel at or above the gradient threshold is an
//!    *edge area* pixel with an **edge direction**: *vertical* when `|gx| ≥ |gy|` (the edge
//!    runs up–down), *horizontal* otherwise (ED's rule). The one-pixel image frame has no
//!    gradient.
//! 3. **Anchors**: edge-area pixels that are a peak of the gradient across their edge
//!    direction (left/right neighbours for a vertical edge, up/down for a horizontal one) by
//!    at least the anchor threshold, on every `scan_interval`-th row and column (ED), at least
//!    two pixels from the image border.
//! 4. **Smart routing**: from each anchor, strongest first, ED walks along its edge direction
//!    both ways, each step to the one of the three pixels ahead with the largest gradient
//!    (preferring one already drawn, to join chains), turning when it meets a pixel of the
//!    other edge direction (both ways along the new direction), stopping at a pixel below the
//!    gradient threshold or already drawn. The walks of one anchor form a tree; its longest
//!    path through the anchor is one **edge segment** (a chain of pixels), each leftover
//!    branch long enough another one (ED's tree of chains).
//! 5. **Line fitting** (EDLines' Algorithm 1): along each chain, fit a line by least squares
//!    (total least squares, RMS perpendicular error) to the first `min_line_length` pixels;
//!    while the fitting error exceeds `max_fit_error_px` (1 px), drop the first pixel and
//!    retry; then extend the line over the next pixels while they lie within
//!    `max_fit_error_px` of it, output it (end points: its first and last pixel projected onto
//!    it), continue after it. The extension is the authors' implementation's (ED_Lib,
//!    `EDLines::SplitSegment2Lines`): it steps over up to 4 consecutive farther pixels and
//!    refits the line on all its pixels each time a run of close pixels ends, then goes on
//!    with the refitted line. Algorithm 1 as printed compares every pixel with the initial
//!    fit of `min_line_length` pixels, whose slope is only as good as a dozen pixels of a
//!    digital staircase give: a long line of shallow slope came out in pieces of about twice
//!    the minimum length.
//! 6. **Validation** by the Helmholtz principle: a line of `n` chain pixels of which `k` have
//!    their level-line angle within τ = 22.5° of the line's (undirected; gradient by Prewitt
//!    on the **unsmoothed** image, so that the pixels' angles are independent under the
//!    noise model) is kept when its number of false alarms
//!    `NFA = N⁴ · Σ_{i=k..n} C(n, i) pᶦ (1 − p)ⁿ⁻ᶦ ≤ ε = 1`, with `p = τ / 180° = 0.125` and
//!    `N⁴ = (width · height)²` the number of possible segments.
//!
//! Constants and where they come from:
//!
//! - gradient threshold `ρ = q / sin τ = 2 / sin 22.5° ≈ 5.22` grey levels per pixel: the
//!   quantisation argument of LSD that EDLines takes over (R. Grompone von Gioi et al., *LSD: a
//!   fast line segment detector with a false detection control*, IEEE TPAMI 2010): with
//!   pixel values quantised to integers (error `q = 2` on a gradient), a gradient weaker than
//!   `ρ` has an angle error above τ. The calibration paper states the same 5.22.
//! - anchor threshold 0 and scan interval 1: the parameter-free setting of ED (C. Akinlar and
//!   C. Topal, *EDPF: a parameter-free edge segment detector with a false detection control*,
//!   IJPRAI 26(1), 2012), which goes with the quantisation threshold above: every gradient
//!   peak may start a chain, validation removes the false ones. (ED's own 36 and 8 are for
//!   `|gx| + |gy|` of the unscaled Sobel after a 5×5 low-pass; behind an 11×11 low-pass the
//!   gradient ridge is so flat that a fixed positive anchor threshold drops every edge lying
//!   half-way between two pixel centres.)
//! - `max_fit_error_px = 1`: EDLines' fitting error and extension distance.
//! - minimum line length `n_min = round(−4 · log N / log p)` with `N = √(width · height)`:
//!   EDLines' Helmholtz bound, the shortest line whose pixels all aligned give `NFA ≤ 1`
//!   (12 pixels for 640×480). (The authors' later code halves it and validates short lines on
//!   a two-pixel-wide rectangle; the paper's bound is kept here.)
//! - τ = 22.5°, `p = 0.125`, `ε = 1`: EDLines' (and LSD's) validation; `p` is the
//!   calibration paper's "0.125".
//!
//! Not done here: the collinear-line joining of the authors' later code (not in the paper).
//!
//! Coordinates: pixel centres, `(0, 0)` the top-left pixel, x right, y down, in the image as
//! given (the **measured**, distorted pixels for a camera image).

use crate::detect::Segment;

/// `2 / sin(22.5°)`: the gradient threshold of EDLines' quantisation argument, grey levels per
/// pixel (see the module documentation).
pub const GRADIENT_THRESHOLD: f32 = 5.226_251_7;

/// EDLines' angle tolerance τ, radians (22.5°).
pub const ANGLE_TOLERANCE_RAD: f64 = std::f64::consts::PI / 8.0;

/// Parameters of [`EdLines`]. Units: pixels, grey levels (0..=255) per pixel, radians.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EdLinesParams {
    /// Width and height of the Gaussian low-pass, pixels (odd; 1 = no smoothing).
    pub smoothing_size: usize,
    /// The Gaussian's standard deviation, pixels.
    pub smoothing_sigma: f64,
    /// Gradient magnitude below which a pixel is no edge, grey levels per pixel.
    pub gradient_threshold: f32,
    /// How much an anchor's gradient must exceed its two neighbours' across the edge, grey
    /// levels per pixel.
    pub anchor_threshold: f32,
    /// Anchors are looked for on every `scan_interval`-th row and column (≥ 1).
    pub scan_interval: usize,
    /// RMS fitting error of a line and distance of a pixel added to it, pixels.
    pub max_fit_error_px: f64,
    /// Angle tolerance τ of the validation, radians; the precision is `p = τ / π`.
    pub angle_tolerance_rad: f64,
    /// Shortest line, pixels of chain; `None`: the Helmholtz bound of the image size.
    pub min_line_length: Option<usize>,
}

impl EdLinesParams {
    /// EDLines as published: 5×5 Gaussian with σ = 1, the 5.22 gradient threshold, anchor
    /// threshold 0, scan interval 1, 1 px fitting error, τ = 22.5°, Helmholtz minimum length.
    pub const fn edlines() -> Self {
        Self {
            smoothing_size: 5,
            smoothing_sigma: 1.0,
            gradient_threshold: GRADIENT_THRESHOLD,
            anchor_threshold: 0.0,
            scan_interval: 1,
            max_fit_error_px: 1.0,
            angle_tolerance_rad: ANGLE_TOLERANCE_RAD,
            min_line_length: None,
        }
    }

    /// The calibration paper's setting (Wang et al., *Vision-based calibration of dual
    /// RCM-based robot arms in human-robot collaborative minimally invasive surgery*, IEEE
    /// RA-L 2017): EDLines behind an 11×11 low-pass. The paper gives the kernel size only;
    /// σ = 2 px is OpenCV's `GaussianBlur` default for that size
    /// (`0.3 · ((11 − 1) / 2 − 1) + 0.8`).
    pub const fn paper() -> Self {
        Self { smoothing_size: 11, smoothing_sigma: 2.0, ..Self::edlines() }
    }

    fn check(&self) -> Result<(), EdLinesError> {
        let bad = |what| Err(EdLinesError::Params(what));
        if self.smoothing_size == 0 || self.smoothing_size.is_multiple_of(2) || self.smoothing_size > 255 {
            return bad("smoothing_size must be odd, 1..=255");
        }
        if !(self.smoothing_sigma.is_finite() && self.smoothing_sigma > 0.0) {
            return bad("smoothing_sigma must be positive");
        }
        if !(self.gradient_threshold.is_finite() && self.gradient_threshold > 0.0) {
            return bad("gradient_threshold must be positive");
        }
        if !(self.anchor_threshold.is_finite() && self.anchor_threshold >= 0.0) {
            return bad("anchor_threshold must be non-negative");
        }
        if self.scan_interval == 0 {
            return bad("scan_interval must be at least 1");
        }
        if !(self.max_fit_error_px.is_finite() && self.max_fit_error_px > 0.0) {
            return bad("max_fit_error_px must be positive");
        }
        if !(self.angle_tolerance_rad > 0.0 && self.angle_tolerance_rad < std::f64::consts::FRAC_PI_2) {
            return bad("angle_tolerance_rad must be in (0, π/2)");
        }
        if self.min_line_length.is_some_and(|n| n < 2) {
            return bad("min_line_length must be at least 2");
        }
        Ok(())
    }
}

impl Default for EdLinesParams {
    fn default() -> Self {
        Self::edlines()
    }
}

/// Why EDLines refused its input.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum EdLinesError {
    /// The sample count is not `width · height`.
    #[error("{got} samples for a {width}x{height} image")]
    Size {
        /// Width, pixels.
        width: usize,
        /// Height, pixels.
        height: usize,
        /// Samples given.
        got: usize,
    },
    /// A parameter is out of its range.
    #[error("invalid EDLines parameter: {0}")]
    Params(&'static str),
}

/// One validated line with its evidence.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EdLine {
    /// End points: the first and last chain pixel projected onto the fitted line, pixels of
    /// the image as given.
    pub segment: Segment,
    /// Chain pixels the line was fitted to (`n` of the validation).
    pub pixels: usize,
    /// Of those (inside the image frame), how many have their level-line angle within τ of
    /// the line's (`k` of the validation).
    pub aligned: usize,
    /// `log₁₀ NFA` (≤ 0 for a kept line).
    pub log10_nfa: f64,
    /// RMS perpendicular distance of the chain pixels from the line, pixels.
    pub fit_rms_px: f64,
}

/// Consecutive pixels farther than the fitting error that the extension of a line steps
/// over (the authors' implementation stops at the fifth).
const MAX_OUTLIER_RUN: usize = 4;

const DIR_NONE: u8 = 0;
const DIR_HORIZONTAL: u8 = 1;
const DIR_VERTICAL: u8 = 2;
const MARK_ANCHOR: u8 = 1;
const MARK_EDGE: u8 = 2;
const NO_WALK: u32 = u32::MAX;

#[derive(Clone, Copy, PartialEq, Eq)]
enum Step {
    Left,
    Right,
    Up,
    Down,
}

/// The EDLines detector with its working buffers (reused between images: no allocation once
/// warm for images of the same size and similar content).
#[derive(Clone, Debug)]
pub struct EdLines {
    params: EdLinesParams,
    kernel: Vec<f32>,
    buffers: Buffers,
}

#[derive(Clone, Debug, Default)]
struct Buffers {
    tmp: Vec<f32>,
    row: Vec<f32>,
    smooth: Vec<f32>,
    grad: Vec<f32>,
    dir: Vec<u8>,
    mark: Vec<u8>,
    anchors: Vec<u32>,
    walks: Vec<WalkRec>,
    walk_px: Vec<u32>,
    stack: Vec<(u32, u8, u32)>,
    path: Vec<u32>,
    chain_px: Vec<u32>,
    chains: Vec<(u32, u32)>,
    xs: Vec<f64>,
    ys: Vec<f64>,
    ln_fact: Vec<f64>,
    lines: Vec<EdLine>,
    segments: Vec<Segment>,
    candidates: usize,
}

/// One walk of the smart routing: a run of pixels (`walk_px[start..end]`) in one direction,
/// a node of the anchor's tree.
#[derive(Clone, Copy, Debug)]
struct WalkRec {
    start: u32,
    end: u32,
    children: [u32; 2],
    /// Pixels on the longest path down from this walk (itself included).
    best: u32,
    /// Already part of an emitted chain.
    used: bool,
}

impl EdLines {
    /// A detector with `params` (checked).
    pub fn new(params: EdLinesParams) -> Result<Self, EdLinesError> {
        params.check()?;
        Ok(Self::unchecked(params))
    }

    /// The calibration paper's EDLines ([`EdLinesParams::paper`]).
    pub fn paper() -> Self {
        Self::unchecked(EdLinesParams::paper())
    }

    fn unchecked(params: EdLinesParams) -> Self {
        let n = params.smoothing_size;
        let r = (n / 2) as f64;
        let s2 = 2.0 * params.smoothing_sigma * params.smoothing_sigma;
        let raw: Vec<f64> = (0..n).map(|i| (-((i as f64 - r).powi(2)) / s2).exp()).collect();
        let sum: f64 = raw.iter().sum();
        let kernel = raw.iter().map(|w| (w / sum) as f32).collect();
        Self { params, kernel, buffers: Buffers::default() }
    }

    /// The parameters.
    pub fn params(&self) -> &EdLinesParams {
        &self.params
    }

    /// The low-pass kernel (one dimension of the separable Gaussian), summing to 1.
    pub fn kernel(&self) -> &[f32] {
        &self.kernel
    }

    /// The minimum line length for a `width × height` image, chain pixels: the parameter if
    /// set, else EDLines' Helmholtz bound `round(−4 · log N / log p)`, `N² = width · height`,
    /// at least 2.
    pub fn min_line_length(&self, width: usize, height: usize) -> usize {
        if let Some(n) = self.params.min_line_length {
            return n;
        }
        let p = self.params.angle_tolerance_rad / std::f64::consts::PI;
        let log_nt = log10_tests(width, height);
        ((-log_nt / p.log10()).round() as usize).max(2)
    }

    /// `log₁₀ NFA` of a line of `n` pixels with `k` aligned, in a `width × height` image.
    pub fn log10_nfa(&mut self, n: usize, k: usize, width: usize, height: usize) -> f64 {
        let p = self.params.angle_tolerance_rad / std::f64::consts::PI;
        log10_tests(width, height) + log10_binomial_tail(&mut self.buffers.ln_fact, n, k, p)
    }

    /// The line segments of a grey image (`luma`, row-major, `width · height` samples, any
    /// scale; 0..=255 for the thresholds to mean what they say), **pixels of the image as
    /// given**. Non-finite samples make no edge. Images smaller than 5×5 have no lines.
    pub fn detect(&mut self, luma: &[f32], width: usize, height: usize) -> Result<&[Segment], EdLinesError> {
        if width.checked_mul(height) != Some(luma.len()) {
            return Err(EdLinesError::Size { width, height, got: luma.len() });
        }
        self.buffers.lines.clear();
        self.buffers.segments.clear();
        self.buffers.candidates = 0;
        if width < 5 || height < 5 || u32::try_from(luma.len()).is_err() {
            return Ok(&self.buffers.segments);
        }
        self.smooth(luma, width, height);
        self.gradient(width, height);
        self.anchors(width, height);
        let min_len = self.min_line_length(width, height);
        self.route(width, min_len);
        self.fit_and_validate(luma, width, height, min_len);
        let b = &mut self.buffers;
        b.segments.extend(b.lines.iter().map(|l| l.segment));
        Ok(&self.buffers.segments)
    }

    /// The lines of the last [`detect`](Self::detect), with their evidence, in the same order
    /// as its segments.
    pub fn lines(&self) -> &[EdLine] {
        &self.buffers.lines
    }

    /// How many lines the fitting of the last [`detect`](Self::detect) proposed to the
    /// validation (kept or not).
    pub fn candidates(&self) -> usize {
        self.buffers.candidates
    }

    /// The gradient magnitude of the last image, grey levels per pixel, row-major.
    pub fn gradient_magnitude(&self) -> &[f32] {
        &self.buffers.grad
    }

    /// Separable Gaussian, reflect-101 border, into `smooth`.
    fn smooth(&mut self, luma: &[f32], w: usize, h: usize) {
        let b = &mut self.buffers;
        let k = &self.kernel;
        let r = k.len() / 2;
        b.tmp.clear();
        b.tmp.resize(w * h, 0.0);
        b.smooth.clear();
        b.smooth.resize(w * h, 0.0);
        if k.len() == 1 {
            b.smooth.copy_from_slice(luma);
            return;
        }
        // Horizontal pass through a padded row.
        b.row.clear();
        b.row.resize(w + 2 * r, 0.0);
        for y in 0..h {
            let src = &luma[y * w..(y + 1) * w];
            for (i, v) in b.row.iter_mut().enumerate() {
                *v = src[reflect101(i as isize - r as isize, w)];
            }
            let dst = &mut b.tmp[y * w..(y + 1) * w];
            dst.fill(0.0);
            for (t, &kt) in k.iter().enumerate() {
                for (d, s) in dst.iter_mut().zip(&b.row[t..t + w]) {
                    *d += kt * s;
                }
            }
        }
        // Vertical pass.
        for y in 0..h {
            let (dst_all, tmp) = (&mut b.smooth, &b.tmp);
            let dst = &mut dst_all[y * w..(y + 1) * w];
            for (t, &kt) in k.iter().enumerate() {
                let sy = reflect101(y as isize + t as isize - r as isize, h);
                for (d, s) in dst.iter_mut().zip(&tmp[sy * w..(sy + 1) * w]) {
                    *d += kt * s;
                }
            }
        }
    }

    /// Sobel / 8, magnitude and edge direction.
    fn gradient(&mut self, w: usize, h: usize) {
        let b = &mut self.buffers;
        let thr = self.params.gradient_threshold;
        b.grad.clear();
        b.grad.resize(w * h, 0.0);
        b.dir.clear();
        b.dir.resize(w * h, DIR_NONE);
        let s = &b.smooth;
        for y in 1..h - 1 {
            let (up, mid, dn) = (&s[(y - 1) * w..y * w], &s[y * w..(y + 1) * w], &s[(y + 1) * w..(y + 2) * w]);
            let grow = &mut b.grad[y * w..(y + 1) * w];
            let drow = &mut b.dir[y * w..(y + 1) * w];
            for x in 1..w - 1 {
                let gx = (up[x + 1] + 2.0 * mid[x + 1] + dn[x + 1]) - (up[x - 1] + 2.0 * mid[x - 1] + dn[x - 1]);
                let gy = (dn[x - 1] + 2.0 * dn[x] + dn[x + 1]) - (up[x - 1] + 2.0 * up[x] + up[x + 1]);
                let (gx, gy) = (gx * 0.125, gy * 0.125);
                let g = (gx * gx + gy * gy).sqrt();
                grow[x] = g;
                if g >= thr {
                    drow[x] = if gx.abs() >= gy.abs() { DIR_VERTICAL } else { DIR_HORIZONTAL };
                }
            }
        }
    }

    /// ED's anchors, sorted by gradient, strongest first.
    fn anchors(&mut self, w: usize, h: usize) {
        let b = &mut self.buffers;
        let (at, si) = (self.params.anchor_threshold, self.params.scan_interval);
        b.mark.clear();
        b.mark.resize(w * h, 0);
        b.anchors.clear();
        for y in 2..h - 2 {
            let (start, step) = if y % si == 0 { (2, 1) } else { (si, si) };
            for x in (start..w - 2).step_by(step) {
                let i = y * w + x;
                let g = b.grad[i];
                let (n0, n1) = match b.dir[i] {
                    DIR_VERTICAL => (b.grad[i - 1], b.grad[i + 1]),
                    DIR_HORIZONTAL => (b.grad[i - w], b.grad[i + w]),
                    _ => continue,
                };
                if g - n0 >= at && g - n1 >= at {
                    b.mark[i] = MARK_ANCHOR;
                    b.anchors.push(i as u32);
                }
            }
        }
        let grad = &b.grad;
        b.anchors.sort_unstable_by(|&p, &q| grad[q as usize].total_cmp(&grad[p as usize]).then(p.cmp(&q)));
    }

    /// Smart routing from every anchor; edge segments (chains) into `chain_px` / `chains`.
    fn route(&mut self, w: usize, min_len: usize) {
        let b = &mut self.buffers;
        b.chain_px.clear();
        b.chains.clear();
        for ai in 0..b.anchors.len() {
            let a = b.anchors[ai] as usize;
            if b.mark[a] != MARK_ANCHOR {
                continue;
            }
            b.walks.clear();
            b.walk_px.clear();
            b.stack.clear();
            let (s1, s2) = steps_of(b.dir[a]);
            // Popped in reverse: s1's walk (and its subtree) first.
            b.stack.push((a as u32, s2 as u8, NO_WALK));
            b.stack.push((a as u32, s1 as u8, NO_WALK));
            let mut roots = [NO_WALK; 2];
            while let Some((p, s, parent)) = b.stack.pop() {
                let id = b.walks.len() as u32;
                let start = b.walk_px.len() as u32;
                // A turn's second walk starts on the pixel its first drew: its chain keeps that
                // pixel; the anchor's second walk does not repeat the anchor.
                let keep_start = parent != NO_WALK || roots[0] == NO_WALK;
                let turn =
                    walk(&mut b.mark, &b.grad, &b.dir, &mut b.walk_px, w, (p as usize, step_from(s)), keep_start);
                b.walks.push(WalkRec {
                    start,
                    end: b.walk_px.len() as u32,
                    children: [NO_WALK; 2],
                    best: 0,
                    used: false,
                });
                if parent == NO_WALK {
                    if roots[0] == NO_WALK {
                        roots[0] = id;
                    } else {
                        roots[1] = id;
                    }
                } else {
                    let ch = &mut b.walks[parent as usize].children;
                    if ch[0] == NO_WALK {
                        ch[0] = id;
                    } else {
                        ch[1] = id;
                    }
                }
                if let Some(q) = turn {
                    let (t1, t2) = steps_of(b.dir[q]);
                    b.stack.push((q as u32, t2 as u8, id));
                    b.stack.push((q as u32, t1 as u8, id));
                }
            }
            // Longest path below each walk (children have larger ids).
            for id in (0..b.walks.len()).rev() {
                let wk = b.walks[id];
                let below = wk.children.iter().filter(|&&c| c != NO_WALK).map(|&c| b.walks[c as usize].best).max();
                b.walks[id].best = (wk.end - wk.start) + below.unwrap_or(0);
            }
            // The main chain: root 0's path reversed, then root 1's.
            b.path.clear();
            take_path(&mut b.walks, &b.walk_px, roots[0], &mut b.path);
            b.path.reverse();
            take_path(&mut b.walks, &b.walk_px, roots[1], &mut b.path);
            push_chain(&mut b.chain_px, &mut b.chains, &b.path, min_len);
            // Leftover branches.
            for id in 0..b.walks.len() {
                if !b.walks[id].used {
                    b.path.clear();
                    take_path(&mut b.walks, &b.walk_px, id as u32, &mut b.path);
                    push_chain(&mut b.chain_px, &mut b.chains, &b.path, min_len);
                }
            }
        }
    }

    /// EDLines' line fitting along each chain, then the NFA validation.
    fn fit_and_validate(&mut self, luma: &[f32], w: usize, h: usize, min_len: usize) {
        let max_err = self.params.max_fit_error_px;
        let p = self.params.angle_tolerance_rad / std::f64::consts::PI;
        let sin_tol = self.params.angle_tolerance_rad.sin();
        let log_nt = log10_tests(w, h);
        let b = &mut self.buffers;
        for ci in 0..b.chains.len() {
            let (c0, c1) = b.chains[ci];
            b.xs.clear();
            b.ys.clear();
            for &i in &b.chain_px[c0 as usize..c1 as usize] {
                b.xs.push((i as usize % w) as f64);
                b.ys.push((i as usize / w) as f64);
            }
            let n = b.xs.len();
            let mut start = 0;
            while n - start >= min_len {
                // An initial line of min_len pixels.
                let mut fit = None;
                while n - start >= min_len {
                    let f = LineFit::of(&b.xs[start..start + min_len], &b.ys[start..start + min_len]);
                    if f.rms <= max_err {
                        fit = Some(f);
                        break;
                    }
                    start += 1;
                }
                let Some(f) = fit else { break };
                // Extend while the next pixels are close to it, refitting as it grows.
                let mut f = f;
                let mut end = start + min_len;
                loop {
                    let (mut idx, mut last_good, mut good, mut bad) = (end, end, 0usize, 0usize);
                    while idx < n {
                        if f.distance(b.xs[idx], b.ys[idx]) <= max_err {
                            last_good = idx + 1;
                            good += 1;
                            bad = 0;
                        } else {
                            bad += 1;
                            if bad > MAX_OUTLIER_RUN {
                                break;
                            }
                        }
                        idx += 1;
                    }
                    if good < 2 {
                        break;
                    }
                    end = last_good;
                    f = LineFit::of(&b.xs[start..end], &b.ys[start..end]);
                    if end >= n {
                        break;
                    }
                }
                let f = LineFit::of(&b.xs[start..end], &b.ys[start..end]);
                let a = f.project(b.xs[start], b.ys[start]);
                let e = f.project(b.xs[end - 1], b.ys[end - 1]);
                // Validation on the unsmoothed image.
                let (mut count, mut aligned) = (0usize, 0usize);
                for j in start..end {
                    let (x, y) = (b.xs[j] as usize, b.ys[j] as usize);
                    if x == 0 || y == 0 || x + 1 >= w || y + 1 >= h {
                        continue;
                    }
                    count += 1;
                    let at = |dx: isize, dy: isize| luma[(y as isize + dy) as usize * w + (x as isize + dx) as usize];
                    let gx = (at(1, -1) - at(-1, -1)) + (at(1, 0) - at(-1, 0)) + (at(1, 1) - at(-1, 1));
                    let gy = (at(-1, 1) - at(-1, -1)) + (at(0, 1) - at(0, -1)) + (at(1, 1) - at(1, -1));
                    let (gx, gy) = (f64::from(gx), f64::from(gy));
                    let g = gx.hypot(gy);
                    // Level line within τ of the line ⇔ gradient within τ of its normal.
                    if g > 0.0 && (gx * f.dx + gy * f.dy).abs() <= g * sin_tol {
                        aligned += 1;
                    }
                }
                b.candidates += 1;
                let log_nfa = log_nt + log10_binomial_tail(&mut b.ln_fact, count, aligned, p);
                if log_nfa <= 0.0 && a.iter().chain(&e).all(|v| v.is_finite()) {
                    b.lines.push(EdLine {
                        segment: Segment { a, b: e },
                        pixels: end - start,
                        aligned,
                        log10_nfa: log_nfa,
                        fit_rms_px: f.rms,
                    });
                }
                start = end;
            }
        }
    }
}

/// `log₁₀ N⁴ = 2 · log₁₀(width · height)`: the number of segments of the image.
fn log10_tests(width: usize, height: usize) -> f64 {
    2.0 * ((width.max(1) as f64).log10() + (height.max(1) as f64).log10())
}

/// `log₁₀ Σ_{i=k..n} C(n, i) pᶦ (1 − p)ⁿ⁻ᶦ`, with `ln i!` cached in `ln_fact`.
fn log10_binomial_tail(ln_fact: &mut Vec<f64>, n: usize, k: usize, p: f64) -> f64 {
    if k == 0 {
        return 0.0;
    }
    if k > n {
        return f64::NEG_INFINITY;
    }
    while ln_fact.len() <= n {
        let i = ln_fact.len();
        let prev = ln_fact.last().copied().unwrap_or(0.0);
        ln_fact.push(if i == 0 { 0.0 } else { prev + (i as f64).ln() });
    }
    let (lp, lq) = (p.ln(), (1.0 - p).ln());
    let ln_term = |i: usize| ln_fact[n] - ln_fact[i] - ln_fact[n - i] + i as f64 * lp + (n - i) as f64 * lq;
    // Sum relative to the first term (the largest once i > (n + 1)p, which the terms pass).
    let first = ln_term(k);
    let mut peak = first;
    let mut sum = 0.0f64;
    for i in k..=n {
        let t = ln_term(i);
        if t > peak {
            sum *= (peak - t).exp();
            peak = t;
        }
        let r = (t - peak).exp();
        sum += r;
        if i as f64 > (n as f64 + 1.0) * p && r < 1e-12 * sum {
            break;
        }
    }
    (peak + sum.ln()) / std::f64::consts::LN_10
}

fn reflect101(i: isize, n: usize) -> usize {
    if n == 1 {
        return 0;
    }
    let period = 2 * (n as isize - 1);
    let m = i.rem_euclid(period);
    (if m < n as isize { m } else { period - m }) as usize
}

fn steps_of(dir: u8) -> (Step, Step) {
    if dir == DIR_HORIZONTAL { (Step::Left, Step::Right) } else { (Step::Up, Step::Down) }
}

fn step_from(s: u8) -> Step {
    match s {
        0 => Step::Left,
        1 => Step::Right,
        2 => Step::Up,
        _ => Step::Down,
    }
}

/// One walk of the smart routing from pixel `p` in direction `s`; pixels drawn are appended
/// to `px` (the start pixel too if it was drawn already and `keep_start`). Returns the pixel where the edge turns to the other direction, if it does.
///
/// Every pixel walked on has an edge direction, so it lies inside the one-pixel frame and
/// its eight neighbours exist.
fn walk(
    mark: &mut [u8],
    grad: &[f32],
    dir: &[u8],
    px: &mut Vec<u32>,
    w: usize,
    (p, s): (usize, Step),
    keep_start: bool,
) -> Option<usize> {
    let along = if matches!(s, Step::Left | Step::Right) { DIR_HORIZONTAL } else { DIR_VERTICAL };
    let mut p = p;
    if mark[p] != MARK_EDGE {
        mark[p] = MARK_EDGE;
        px.push(p as u32);
    } else if keep_start {
        px.push(p as u32);
    }
    loop {
        // Anchors beside the chain are the same edge: no new chain from them.
        let (side0, side1) = if along == DIR_HORIZONTAL { (p - w, p + w) } else { (p - 1, p + 1) };
        for q in [side0, side1] {
            if mark[q] == MARK_ANCHOR {
                mark[q] = 0;
            }
        }
        // Ahead: straight, and the two diagonals (a = up/left one, c = down/right one).
        let (straight, a, c) = match s {
            Step::Left => (p - 1, p - 1 - w, p - 1 + w),
            Step::Right => (p + 1, p + 1 - w, p + 1 + w),
            Step::Up => (p - w, p - w - 1, p - w + 1),
            Step::Down => (p + w, p + w - 1, p + w + 1),
        };
        let next = if mark[straight] >= MARK_ANCHOR {
            straight
        } else if mark[a] >= MARK_ANCHOR {
            a
        } else if mark[c] >= MARK_ANCHOR {
            c
        } else if grad[a] > grad[straight] {
            if grad[a] > grad[c] { a } else { c }
        } else if grad[c] > grad[straight] {
            c
        } else {
            straight
        };
        if dir[next] == DIR_NONE || mark[next] == MARK_EDGE {
            return None;
        }
        if dir[next] != along {
            return Some(next);
        }
        p = next;
        mark[p] = MARK_EDGE;
        px.push(p as u32);
    }
}

/// Appends the pixels of the longest path from walk `id` down its tree to `out`, marking
/// the walks used.
fn take_path(walks: &mut [WalkRec], walk_px: &[u32], id: u32, out: &mut Vec<u32>) {
    let mut id = id;
    while id != NO_WALK && !walks[id as usize].used {
        let wk = &mut walks[id as usize];
        wk.used = true;
        out.extend_from_slice(&walk_px[wk.start as usize..wk.end as usize]);
        let ch = wk.children;
        id = ch
            .iter()
            .filter(|&&c| c != NO_WALK && !walks[c as usize].used)
            .max_by_key(|&&c| walks[c as usize].best)
            .copied()
            .unwrap_or(NO_WALK);
    }
}

fn push_chain(chain_px: &mut Vec<u32>, chains: &mut Vec<(u32, u32)>, path: &[u32], min_len: usize) {
    if path.len() >= min_len {
        let s = chain_px.len() as u32;
        chain_px.extend_from_slice(path);
        chains.push((s, chain_px.len() as u32));
    }
}

/// A total-least-squares line: through the centroid `(cx, cy)` with unit direction
/// `(dx, dy)`; `rms` the RMS perpendicular distance, pixels.
#[derive(Clone, Copy, Debug)]
struct LineFit {
    cx: f64,
    cy: f64,
    dx: f64,
    dy: f64,
    rms: f64,
}

impl LineFit {
    fn of(xs: &[f64], ys: &[f64]) -> Self {
        let n = xs.len().max(1) as f64;
        let (x0, y0) = (xs.first().copied().unwrap_or(0.0), ys.first().copied().unwrap_or(0.0));
        let (mut sx, mut sy) = (0.0, 0.0);
        for (x, y) in xs.iter().zip(ys) {
            sx += x - x0;
            sy += y - y0;
        }
        let (mx, my) = (sx / n, sy / n);
        let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
        for (x, y) in xs.iter().zip(ys) {
            let (u, v) = (x - x0 - mx, y - y0 - my);
            sxx += u * u;
            syy += v * v;
            sxy += u * v;
        }
        let theta = 0.5 * (2.0 * sxy).atan2(sxx - syy);
        let half = 0.5 * (sxx - syy);
        let lmin = 0.5 * (sxx + syy) - half.hypot(sxy);
        Self { cx: x0 + mx, cy: y0 + my, dx: theta.cos(), dy: theta.sin(), rms: (lmin.max(0.0) / n).sqrt() }
    }

    fn distance(&self, x: f64, y: f64) -> f64 {
        ((x - self.cx) * self.dy - (y - self.cy) * self.dx).abs()
    }

    fn project(&self, x: f64, y: f64) -> [f64; 2] {
        let t = (x - self.cx) * self.dx + (y - self.cy) * self.dy;
        [self.cx + t * self.dx, self.cy + t * self.dy]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_paper_parameters_are_valid_and_the_kernel_is_normalised() {
        assert!(EdLinesParams::paper().check().is_ok());
        assert!(EdLinesParams::edlines().check().is_ok());
        let ed = EdLines::paper();
        assert_eq!(ed.kernel().len(), 11);
        let sum: f32 = ed.kernel().iter().sum();
        assert!((sum - 1.0).abs() < 1e-6);
        assert!(ed.kernel()[5] > ed.kernel()[4] && (ed.kernel()[0] - ed.kernel()[10]).abs() < 1e-9);
        assert!((f64::from(GRADIENT_THRESHOLD) - 2.0 / (std::f64::consts::PI / 8.0).sin()).abs() < 1e-6);
        for bad in [
            EdLinesParams { smoothing_size: 4, ..EdLinesParams::paper() },
            EdLinesParams { smoothing_sigma: f64::NAN, ..EdLinesParams::paper() },
            EdLinesParams { scan_interval: 0, ..EdLinesParams::paper() },
            EdLinesParams { angle_tolerance_rad: 2.0, ..EdLinesParams::paper() },
            EdLinesParams { min_line_length: Some(1), ..EdLinesParams::paper() },
        ] {
            assert!(matches!(EdLines::new(bad), Err(EdLinesError::Params(_))));
        }
    }

    #[test]
    fn the_minimum_length_is_the_shortest_meaningful_fully_aligned_line() {
        let mut ed = EdLines::paper();
        for (w, h) in [(640, 480), (1920, 1080), (64, 48)] {
            let n = ed.min_line_length(w, h);
            // All n aligned: NFA = N⁴ pⁿ; the bound rounds −log N⁴ / log p.
            let exact = -log10_tests(w, h) / 0.125f64.log10();
            assert!((n as f64 - exact).abs() <= 0.5, "{w}x{h}: {n} vs {exact}");
            assert!(ed.log10_nfa(n + 1, n + 1, w, h) < 0.0);
            assert!(ed.log10_nfa(n - 1, n - 1, w, h) > 0.0);
        }
    }

    #[test]
    fn the_binomial_tail_matches_a_direct_sum() {
        let mut cache = Vec::new();
        let p = 0.125f64;
        for n in [1usize, 5, 12, 40, 90] {
            for k in 0..=n {
                let direct: f64 = (k..=n)
                    .map(|i| {
                        let c: f64 = (0..i).map(|j| (n - j) as f64 / (j + 1) as f64).product();
                        c * p.powi(i as i32) * (1.0 - p).powi((n - i) as i32)
                    })
                    .sum();
                let got = log10_binomial_tail(&mut cache, n, k, p);
                assert!((got - direct.log10()).abs() < 1e-9 * direct.log10().abs().max(1.0), "n={n} k={k}");
            }
        }
        assert_eq!(log10_binomial_tail(&mut cache, 3, 4, p), f64::NEG_INFINITY);
    }

    #[test]
    fn reflect101_is_opencvs_default_border() {
        let got: Vec<usize> = (-3..8).map(|i| reflect101(i, 5)).collect();
        assert_eq!(got, vec![3, 2, 1, 0, 1, 2, 3, 4, 3, 2, 1]);
        assert_eq!(reflect101(-7, 1), 0);
        assert_eq!(reflect101(9, 2), 1);
    }

    #[test]
    fn a_total_least_squares_fit_of_a_slanted_run() {
        let xs: Vec<f64> = (0..20).map(f64::from).collect();
        let ys: Vec<f64> = xs.iter().map(|x| 3.0 + 0.5 * x).collect();
        let f = LineFit::of(&xs, &ys);
        assert!(f.rms < 1e-9);
        assert!(f.distance(4.0, 5.0) < 1e-9);
        assert!((f.distance(4.0, 6.0) - 1.0 / 1.25f64.sqrt()).abs() < 1e-9);
        let [u, v] = f.project(0.0, 4.0);
        assert!((v - (3.0 + 0.5 * u)).abs() < 1e-9);
    }

    #[test]
    fn the_routing_draws_connected_chains_around_a_disc() {
        let (w, h) = (120usize, 100usize);
        let (cx, cy, r) = (60.3, 48.8, 30.0);
        let luma: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                // 4×4 supersampled disc: 200 inside, 60 outside.
                let mut cover = 0.0;
                for s in 0..16 {
                    let (u, v) = (x + ((s % 4) as f64 - 1.5) / 4.0, y + ((s / 4) as f64 - 1.5) / 4.0);
                    if (u - cx).hypot(v - cy) <= r {
                        cover += 1.0 / 16.0;
                    }
                }
                (60.0 + 140.0 * cover) as f32
            })
            .collect();
        let mut ed = EdLines::paper();
        ed.detect(&luma, w, h).unwrap();
        let b = &ed.buffers;
        let mut drawn = 0;
        for &(s, e) in &b.chains {
            let px = &b.chain_px[s as usize..e as usize];
            for pair in px.windows(2) {
                let (p, q) = (pair[0] as usize, pair[1] as usize);
                let (dx, dy) = ((p % w).abs_diff(q % w), (p / w).abs_diff(q / w));
                assert!(dx.max(dy) == 1, "chain jumps from {p} to {q}");
            }
            let mut sorted = px.to_vec();
            sorted.sort_unstable();
            sorted.dedup();
            assert_eq!(sorted.len(), px.len(), "a pixel twice in one chain");
            for &p in px {
                let d = ((p as usize % w) as f64 - cx).hypot((p as usize / w) as f64 - cy);
                assert!((d - r).abs() < 1.5, "chain pixel {d} px from the centre");
            }
            drawn += px.len();
        }
        // The circumference (≈ 2πr / 1.1 pixels of an 8-connected digital circle) is drawn.
        assert!(drawn as f64 > 0.8 * 2.0 * std::f64::consts::PI * r / 1.2, "{drawn}");
        // A circle is no line: whatever lines were kept are short chords within a pixel.
        for l in ed.lines() {
            for p in [l.segment.a, l.segment.b] {
                assert!(((p[0] - cx).hypot(p[1] - cy) - r).abs() < 1.5);
            }
        }
    }

    #[test]
    fn wrong_sample_counts_are_refused() {
        let mut ed = EdLines::paper();
        assert_eq!(ed.detect(&[0.0; 11], 3, 4), Err(EdLinesError::Size { width: 3, height: 4, got: 11 }));
        assert!(ed.detect(&[0.0; 12], 3, 4).unwrap().is_empty());
    }
}
