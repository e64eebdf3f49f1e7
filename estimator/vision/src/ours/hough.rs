//! Stage 2: straight-line hypotheses from the edgels (undistorted pixels, where the contours
//! are straight): an orientation-guided Hough transform (each edgel votes once at its own
//! normal direction, peaks on a 9 × 3 box sum as edgel normals at half resolution scatter by
//! a few degrees; or, with a normal window, at every angle within the window of its normal,
//! peaks on a 1 × 3 box sum: [`Hough::run`]; either way the cost is linear in the edgels),
//! then each peak's edgels are gathered and refitted by total least squares, and the
//! supported span is found along the line.

use super::edges::Edgel;
use super::geom::{Line, fit_line};

/// Angle bins over `[0, π)`.
const N_THETA: usize = 180;
/// Width of a distance bin, pixels.
const RHO_STEP: f32 = 2.0;

/// A line hypothesis with the edgels that support it.
#[derive(Clone, Copy, Debug)]
pub(crate) struct LineCand {
    /// The line, undistorted pixels.
    pub(crate) line: Line,
    /// The two ends of the supported span, undistorted pixels.
    pub(crate) ends: [[f64; 2]; 2],
    /// Number of supporting edgels (half-resolution).
    pub(crate) count: usize,
}

/// The working buffers of stage 2.
#[derive(Clone, Debug, Default)]
pub(crate) struct Hough {
    acc: Vec<u16>,
    n_rho: usize,
    rho0: usize,
    centre: [f32; 2],
    peaks: Vec<(u32, usize, usize)>,
    kept: Vec<(usize, usize)>,
    members: Vec<[f64; 2]>,
    /// The edgel index of each of `members`.
    member_idx: Vec<u32>,
    /// With the window: per edgel, whether its votes were taken back (a line gathered it).
    unvoted: Vec<bool>,
    /// Per edgel, its angle bin.
    tbs: Vec<u16>,
    /// Start of each angle bin in `order` (prefix sums, `N_THETA + 1` entries).
    bins: Vec<u32>,
    /// Edgel indices sorted by angle bin.
    order: Vec<u32>,
    /// Scratch: next free slot per angle bin.
    next: Vec<u32>,
    s_buf: Vec<f64>,
    /// Per angle bin, the unit normal at its centre `[cos θ, sin θ]`.
    trig: Vec<[f32; 2]>,
    pub(crate) lines: Vec<LineCand>,
}

impl Hough {
    /// An accumulator for an undistorted image region of radius `radius_px` around `centre`.
    pub(crate) fn new(centre: [f32; 2], radius_px: f32) -> Self {
        let rho0 = (radius_px / RHO_STEP).ceil().max(1.0) as usize + 2;
        let n_rho = 2 * rho0 + 1;
        let trig = (0..N_THETA)
            .map(|b| {
                let theta = (b as f32 + 0.5) * (std::f32::consts::PI / N_THETA as f32);
                [theta.cos(), theta.sin()]
            })
            .collect();
        Self { acc: vec![0; N_THETA * n_rho], n_rho, rho0, centre, trig, ..Default::default() }
    }

    fn cell(&self, tb: isize, rb: isize) -> u32 {
        let (mut t, mut r) = (tb, rb);
        if t < 0 {
            t += N_THETA as isize;
            r = 2 * self.rho0 as isize - r;
        } else if t >= N_THETA as isize {
            t -= N_THETA as isize;
            r = 2 * self.rho0 as isize - r;
        }
        if r < 0 || r >= self.n_rho as isize {
            return 0;
        }
        u32::from(self.acc[t as usize * self.n_rho + r as usize])
    }

    /// Fills `self.lines` (best supported first, at most `max_lines`) from `edgels`;
    /// `min_votes` is the number of edgels a peak needs.
    ///
    /// `window` (angle bins, 0: off) spreads each edgel's vote over the angles within
    /// `±window` bins of its normal, each at its own distance `ρ(θ) = (p − c)·n(θ)`: the
    /// edgel's position is exact to a pixel while its normal, from a 2×2 gradient at half
    /// resolution, scatters by degrees (noise, haze), and one vote at the measured normal
    /// lands `s·δθ` away in distance, `s` the edgel's distance along the line from the foot of
    /// the perpendicular from the centre (a 3° error 300 px along is 16 px, eight
    /// bins). With the window, the edgels of a straight contour all vote into the same cell at
    /// the contour's true angle whatever their normals' errors within the window, and a peak
    /// is the 1 (angle) × 3 (distance) box sum; once a peak's line is gathered, its edgels'
    /// votes are taken back, so that one contour leaves one peak and `max_lines` counts
    /// distinct lines. Without it (`window` 0) each edgel votes once at its own normal and a
    /// peak is the 9 × 3 box sum. Either against `min_votes`.
    pub(crate) fn run(&mut self, edgels: &[Edgel], min_votes: u32, max_lines: usize, window: usize) {
        self.lines.clear();
        self.peaks.clear();
        self.acc.iter_mut().for_each(|a| *a = 0);
        let [cx, cy] = self.centre;
        self.bins.clear();
        self.bins.resize(N_THETA + 1, 0);
        self.tbs.clear();
        for e in edgels {
            let theta = e.n[1].atan2(e.n[0]);
            let tb = ((theta * (N_THETA as f32 / std::f32::consts::PI)) as usize).min(N_THETA - 1);
            self.tbs.push(tb as u16);
            self.bins[tb + 1] += 1;
            if window == 0 {
                let rho = (e.p[0] - cx) * e.n[0] + (e.p[1] - cy) * e.n[1];
                self.vote(tb, rho);
                continue;
            }
            self.vote_window(e, tb, window, true);
        }
        // Edgel indices sorted by angle bin (counting sort): a peak gathers from its bins only.
        for i in 0..N_THETA {
            self.bins[i + 1] += self.bins[i];
        }
        self.order.clear();
        self.order.resize(edgels.len(), 0);
        {
            self.next.clear();
            self.next.extend_from_slice(&self.bins);
            for (i, &tb) in self.tbs.iter().enumerate() {
                let slot = &mut self.next[tb as usize];
                self.order[*slot as usize] = i as u32;
                *slot += 1;
            }
        }
        // Peaks of the 9 (angle) × 3 (distance) box sum; with the window, of the 1 × 3 one
        // (every edgel within the window votes at the true angle: the edgels within ±3 px of
        // the line at that angle, the line's support; at a neighbouring angle the votes of a
        // long contour spread over the distance bins by `s·sin 1°` along it).
        let half_t = if window == 0 { 4isize } else { 0 };
        let seed = (min_votes / 8).max(2);
        for tb in 0..N_THETA {
            for rb in 0..self.n_rho {
                if u32::from(self.acc[tb * self.n_rho + rb]) < seed {
                    continue;
                }
                let mut s = 0;
                for dt in -half_t..=half_t {
                    for dr in -1..=1isize {
                        s += self.cell(tb as isize + dt, rb as isize + dr);
                    }
                }
                if s >= min_votes {
                    self.peaks.push((s, tb, rb));
                }
            }
        }
        self.peaks.sort_unstable_by_key(|p| std::cmp::Reverse(p.0));
        let mut kept = std::mem::take(&mut self.kept);
        kept.clear();
        let peaks = std::mem::take(&mut self.peaks);
        // Suppression around a kept peak: ±4 angle bins (the 9 × 3 box's reach) and ±3
        // distance bins; with the window, ±(window + 4) angle bins, and every vote of a
        // gathered line's edgels is taken back before the next peak is judged (over the
        // window, a contour's edgels also make cells at the neighbouring angles, a short
        // contour's nearly as full as its own: without this one line left two or three
        // peaks). Without the window `max_lines` counts the peaks taken; with it the distinct
        // lines, at most `4·max_lines` peaks tried.
        let reach = 4 + window.min(N_THETA / 2 - 5);
        if window > 0 {
            self.unvoted.clear();
            self.unvoted.resize(edgels.len(), false);
        }
        for &(_, tb, rb) in &peaks {
            if window == 0 && kept.len() >= max_lines {
                break;
            }
            if window > 0 && (self.lines.len() >= max_lines || kept.len() >= 4 * max_lines) {
                break;
            }
            let near = kept.iter().any(|&(t2, r2)| {
                let dt = tb.abs_diff(t2);
                if dt <= reach {
                    return rb.abs_diff(r2) <= 3;
                }
                if N_THETA - dt <= reach {
                    return (2 * self.rho0).abs_diff(rb).abs_diff(r2) <= 3;
                }
                false
            });
            if near {
                continue;
            }
            if window > 0 {
                // The peak's 1 × 3 box sum with the votes of the lines gathered so far taken back.
                let left: u32 = (-1..=1isize).map(|dr| self.cell(tb as isize, rb as isize + dr)).sum();
                if left < min_votes {
                    continue;
                }
            }
            kept.push((tb, rb));
            let theta = (tb as f64 + 0.5) * std::f64::consts::PI / N_THETA as f64;
            let rho = (rb as f64 - self.rho0 as f64) * f64::from(RHO_STEP);
            let (n0, n1) = (theta.cos(), theta.sin());
            let line = Line { n: [n0, n1], c: -(rho + n0 * f64::from(cx) + n1 * f64::from(cy)) };
            if let Some(cand) = self.gather(edgels, tb, line) {
                if window > 0 {
                    for k in 0..self.member_idx.len() {
                        let i = self.member_idx[k] as usize;
                        if !self.unvoted[i] {
                            self.unvoted[i] = true;
                            self.vote_window(&edgels[i], usize::from(self.tbs[i]), window, false);
                        }
                    }
                }
                // Two peaks may refit to the same line: keep the better supported.
                let mid = [0.5 * (cand.ends[0][0] + cand.ends[1][0]), 0.5 * (cand.ends[0][1] + cand.ends[1][1])];
                let same = |l: &LineCand| {
                    (l.line.n[0] * cand.line.n[0] + l.line.n[1] * cand.line.n[1]).abs() > 0.99985
                        && l.line.distance(mid).abs() < 2.0
                };
                match self.lines.iter().position(same) {
                    Some(i) if self.lines[i].count < cand.count => self.lines[i] = cand,
                    Some(_) => {}
                    None => self.lines.push(cand),
                }
            }
        }
        self.peaks = peaks;
        self.kept = kept;
        self.lines.sort_by_key(|l| std::cmp::Reverse(l.count));
    }

    /// One vote at angle bin `tb` and distance `rho` (pixels from the centre), if inside.
    fn vote(&mut self, tb: usize, rho: f32) {
        self.vote_signed(tb, rho, true);
    }

    /// A vote at angle bin `tb` and distance `rho` (pixels from the centre), if inside: cast
    /// (`add`) or taken back.
    fn vote_signed(&mut self, tb: usize, rho: f32, add: bool) {
        if !rho.is_finite() || rho.abs() > RHO_STEP * self.rho0 as f32 {
            return;
        }
        let rb = (rho / RHO_STEP).round() as isize + self.rho0 as isize;
        if rb < 0 || rb >= self.n_rho as isize {
            return;
        }
        let a = &mut self.acc[tb * self.n_rho + rb as usize];
        *a = if add { a.saturating_add(1) } else { a.saturating_sub(1) };
    }

    /// The votes of edgel `e` (angle bin `tb`) at every angle bin within `±window` of its
    /// normal, each at the distance its position gives there: cast (`add`) or taken back.
    fn vote_window(&mut self, e: &Edgel, tb: usize, window: usize, add: bool) {
        let [cx, cy] = self.centre;
        let w = window.min(N_THETA / 2 - 1) as isize;
        for b in tb as isize - w..=tb as isize + w {
            // Past either end of [0, π) the bin wraps: the wrapped bin's own normal (the
            // table's) is the unwrapped one's negated, and so is the distance.
            let bw = b.rem_euclid(N_THETA as isize) as usize;
            let [c, s] = self.trig[bw];
            self.vote_signed(bw, (e.p[0] - cx) * c + (e.p[1] - cy) * s, add);
        }
    }

    /// The edgels near `line` (twice: wide, then around the refit), the refit line and its
    /// supported span.
    fn gather(&mut self, edgels: &[Edgel], tb: usize, mut line: Line) -> Option<LineCand> {
        for (tol_px, cos_tol) in [(3.5f64, 0.990f64), (2.0, 0.995)] {
            self.members.clear();
            self.member_idx.clear();
            // The angle bins within ±9° (cos 0.990 is 8.1°), wrapping around π.
            let candidates = (tb as isize - 9..=tb as isize + 9).flat_map(|b| {
                let b = b.rem_euclid(N_THETA as isize) as usize;
                self.order[self.bins[b] as usize..self.bins[b + 1] as usize].iter()
            });
            for &i in candidates {
                let e = &edgels[i as usize];
                let p = [f64::from(e.p[0]), f64::from(e.p[1])];
                let cosang = (f64::from(e.n[0]) * line.n[0] + f64::from(e.n[1]) * line.n[1]).abs();
                if cosang >= cos_tol && line.distance(p).abs() <= tol_px {
                    self.members.push(p);
                    self.member_idx.push(i);
                }
            }
            if self.members.len() < 6 {
                return None;
            }
            line = fit_line(&self.members, None)?;
        }
        // Span along the line, isolated members trimmed off the ends.
        let t = line.direction();
        let o = line.foot();
        self.s_buf.clear();
        self.s_buf.extend(self.members.iter().map(|p| (p[0] - o[0]) * t[0] + (p[1] - o[1]) * t[1]));
        self.s_buf.sort_by(f64::total_cmp);
        let max_gap = 24.0;
        let s = &self.s_buf;
        let (mut lo, mut hi) = (0, s.len() - 1);
        // Trim ends with a gap to the next of more than max_gap, keeping at least the bulk.
        while lo + 1 < hi && s[lo + 1] - s[lo] > max_gap {
            lo += 1;
        }
        while hi > lo + 1 && s[hi] - s[hi - 1] > max_gap {
            hi -= 1;
        }
        let ends = [[o[0] + s[lo] * t[0], o[1] + s[lo] * t[1]], [o[0] + s[hi] * t[0], o[1] + s[hi] * t[1]]];
        Some(LineCand { line, ends, count: hi + 1 - lo })
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;

    /// 30 edgels every 2 px along a straight contour 60 px long, its foot 250 px from the
    /// centre and the span 170-230 px along from the foot, their positions exact but their
    /// normals off by +3°, 0°, −3° in turn (a 2×2 gradient's scatter): one vote at the
    /// measured normal lands about `200·sin 3°` = 10 px away in distance, so the edgels split
    /// into three cells 10 px apart, 10 votes each, and no 9 × 3 box reaches 12; with a window
    /// of 3° every edgel also votes at the true angle, into one cell.
    fn contour(theta_deg: f32) -> (Vec<Edgel>, Line) {
        contour_at(theta_deg, 250.0, 200.0, 30, 3.0)
    }

    /// `n` edgels every 2 px along a straight contour at normal angle `theta_deg`, its foot
    /// `foot_px` from the centre, the span's middle `shift_px` along from the foot, their
    /// normals off by `+err_deg`, 0, `−err_deg` in turn.
    fn contour_at(theta_deg: f32, foot_px: f32, shift_px: f32, n_edgels: usize, err_deg: f32) -> (Vec<Edgel>, Line) {
        let centre = [320.0f32, 240.0];
        let th = theta_deg.to_radians();
        let n = [th.cos(), th.sin()];
        let t = [-n[1], n[0]];
        let foot = [centre[0] + foot_px * n[0], centre[1] + foot_px * n[1]];
        let mut edgels = Vec::new();
        for k in 0..n_edgels {
            let s = -(n_edgels as f32) + 2.0 * k as f32 + 0.5;
            let p = [foot[0] + s * t[0], foot[1] + s * t[1]];
            // Far from the line's foot, so that the error in distance is large: shift the span.
            let p = [p[0] + shift_px * t[0], p[1] + shift_px * t[1]];
            let err = [err_deg, 0.0, -err_deg][k % 3].to_radians();
            let mut m = [(th + err).cos(), (th + err).sin()];
            if m[1] < 0.0 || (m[1] == 0.0 && m[0] < 0.0) {
                m = [-m[0], -m[1]];
            }
            edgels.push(Edgel { p, n: m });
        }
        let line = Line { n: [f64::from(n[0]), f64::from(n[1])], c: -(f64::from(n[0] * foot[0] + n[1] * foot[1])) };
        (edgels, line)
    }

    fn found(h: &Hough, truth: &Line) -> bool {
        h.lines.iter().any(|l| {
            (l.line.n[0] * truth.n[0] + l.line.n[1] * truth.n[1]).abs() > 1f64.to_radians().cos()
                && l.line.distance([l.ends[0][0], l.ends[0][1]]).abs() < 1e-6
                && truth.distance(l.ends[0]).abs() < 2.0
                && truth.distance(l.ends[1]).abs() < 2.0
        })
    }

    #[test]
    fn a_contour_far_from_the_centre_with_scattered_normals_is_found_only_with_the_window() {
        for theta in [20.0f32, 75.0, 130.0, 178.0] {
            let (edgels, truth) = contour(theta);
            let mut h = Hough::new([320.0, 240.0], 800.0);
            h.run(&edgels, 12, 40, 0);
            assert!(!found(&h, &truth), "θ = {theta}°: found with one vote per edgel: {:?}", h.lines);
            h.run(&edgels, 12, 40, 3);
            assert!(found(&h, &truth), "θ = {theta}°: not found with the window: {:?}", h.lines);
        }
    }

    #[test]
    fn with_exact_normals_the_window_finds_the_same_line() {
        let (mut edgels, truth) = contour(40.0);
        let th = 40f32.to_radians();
        for e in &mut edgels {
            e.n = [th.cos(), th.sin()];
        }
        let mut h = Hough::new([320.0, 240.0], 800.0);
        h.run(&edgels, 12, 40, 0);
        assert!(found(&h, &truth));
        let one = h.lines[0];
        h.run(&edgels, 12, 40, 3);
        assert!(found(&h, &truth));
        assert_eq!(h.lines.len(), 1);
        assert_eq!(h.lines[0].count, one.count);
    }

    #[test]
    fn with_the_window_one_contour_leaves_one_peak() {
        // A short contour far out votes nearly as fully at the angles around its own (its
        // span's distance moves by `s·sin δ` there, a few bins): each of those cells was a
        // peak of its own, refitted to the same line, and took a place in `max_lines`.
        for theta in [20.0f32, 75.0, 130.0, 178.0] {
            let (edgels, truth) = contour(theta);
            let mut h = Hough::new([320.0, 240.0], 800.0);
            for window in 3..=5 {
                h.run(&edgels, 12, 40, window);
                assert!(found(&h, &truth), "θ = {theta}°, window {window}: not found: {:?}", h.lines);
                assert_eq!(h.lines.len(), 1, "θ = {theta}°, window {window}: {:?}", h.lines);
                assert_eq!(h.kept.len(), 1, "θ = {theta}°, window {window}: peaks {:?}", h.kept);
            }
        }
    }

    #[test]
    fn with_the_window_a_weaker_second_line_still_makes_the_list() {
        // Two contours: the first of 30 edgels with scattered normals (cells of 20-30 votes at
        // every angle within the window), the second of 16 with exact normals. With
        // `max_lines` 2 both are lines: the first's neighbouring cells are not peaks once its
        // edgels' votes are taken back.
        for (ta, tb) in [(40.0f32, 120.0f32), (100.0, 10.0), (170.0, 60.0)] {
            let (mut edgels, first) = contour_at(ta, 250.0, 200.0, 30, 3.0);
            let (more, second) = contour_at(tb, 120.0, -60.0, 16, 0.0);
            edgels.extend(more);
            let mut h = Hough::new([320.0, 240.0], 800.0);
            h.run(&edgels, 12, 2, 5);
            assert!(found(&h, &first), "{ta}°/{tb}°: the first not found: {:?}", h.lines);
            assert!(found(&h, &second), "{ta}°/{tb}°: the second not found: {:?}", h.lines);
        }
    }
}
