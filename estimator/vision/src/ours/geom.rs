//! Plane geometry of the detector: lines in undistorted pixels and their (robust) fits.

/// A line `n·p + c = 0`, `|n| = 1`, undistorted pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Line {
    pub(crate) n: [f64; 2],
    pub(crate) c: f64,
}

impl Line {
    /// Signed distance of `p`, pixels.
    #[inline]
    pub(crate) fn distance(&self, p: [f64; 2]) -> f64 {
        self.n[0] * p[0] + self.n[1] * p[1] + self.c
    }

    /// A unit direction along the line.
    pub(crate) fn direction(&self) -> [f64; 2] {
        [-self.n[1], self.n[0]]
    }

    /// The point of the line nearest the origin.
    pub(crate) fn foot(&self) -> [f64; 2] {
        [-self.c * self.n[0], -self.c * self.n[1]]
    }

    /// `[a, b, c]`.
    pub(crate) fn abc(&self) -> [f64; 3] {
        [self.n[0], self.n[1], self.c]
    }

    /// From `[a, b, c]` (any scale); `None` when degenerate.
    pub(crate) fn from_abc(abc: [f64; 3]) -> Option<Self> {
        let s = abc[0].hypot(abc[1]);
        (s.is_finite() && s > 1e-300 && abc[2].is_finite()).then(|| Self { n: [abc[0] / s, abc[1] / s], c: abc[2] / s })
    }

    /// The intersection of `p + λ·d` with the line: `λ`, `None` when parallel.
    pub(crate) fn hit(&self, p: [f64; 2], d: [f64; 2]) -> Option<f64> {
        let den = self.n[0] * d[0] + self.n[1] * d[1];
        (den.abs() > 1e-12).then(|| -self.distance(p) / den)
    }
}

/// Weighted total-least-squares line through `pts` (weights `w`, all 1 when `None`);
/// `None` when fewer than two weighted points or all coincide.
pub(crate) fn fit_line(pts: &[[f64; 2]], w: Option<&[f64]>) -> Option<Line> {
    let (mut sw, mut mx, mut my) = (0.0, 0.0, 0.0);
    for (i, p) in pts.iter().enumerate() {
        let wi = w.map_or(1.0, |w| w[i]);
        sw += wi;
        mx += wi * p[0];
        my += wi * p[1];
    }
    if sw <= 0.0 || sw.is_nan() {
        return None;
    }
    let (mx, my) = (mx / sw, my / sw);
    let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
    for (i, p) in pts.iter().enumerate() {
        let wi = w.map_or(1.0, |w| w[i]);
        let (dx, dy) = (p[0] - mx, p[1] - my);
        sxx += wi * dx * dx;
        syy += wi * dy * dy;
        sxy += wi * dx * dy;
    }
    // Direction: the major eigenvector of the scatter matrix.
    let theta = 0.5 * (2.0 * sxy).atan2(sxx - syy);
    let (dx, dy) = (theta.cos(), theta.sin());
    if sxx + syy <= 0.0 || (sxx + syy).is_nan() {
        return None;
    }
    let n = [-dy, dx];
    let c = -(n[0] * mx + n[1] * my);
    (c.is_finite()).then_some(Line { n, c })
}

/// The result of a robust fit.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RobustFit {
    pub(crate) line: Line,
    /// Robust scale of the residuals (1.4826·MAD), pixels.
    pub(crate) sigma: f64,
}

/// Tukey-biweight IRLS line fit, starting from `start`; `w` is a scratch buffer and holds the
/// final weights (0 for outliers). `res` is scratch too.
pub(crate) fn robust_fit(pts: &[[f64; 2]], start: Line, w: &mut Vec<f64>, res: &mut Vec<f64>) -> Option<RobustFit> {
    let mut line = start;
    let mut sigma = 1.0;
    w.clear();
    w.resize(pts.len(), 1.0);
    for _ in 0..6 {
        res.clear();
        res.extend(pts.iter().map(|p| line.distance(*p).abs()));
        let mid = res.len() / 2;
        if res.is_empty() {
            return None;
        }
        res.select_nth_unstable_by(mid, f64::total_cmp);
        sigma = (1.4826 * res[mid]).max(0.08);
        let c = 4.685 * sigma;
        for (wi, p) in w.iter_mut().zip(pts) {
            let u = line.distance(*p) / c;
            *wi = if u.abs() < 1.0 { (1.0 - u * u).powi(2) } else { 0.0 };
        }
        line = fit_line(pts, Some(w))?;
    }
    Some(RobustFit { line, sigma })
}

/// A running least-squares slope of `y` against `x` (sums of 1, x, x², y, x·y), for the
/// drift of edge offsets (pixels) along a contour (stations, pixels).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct SlopeFit {
    n: f64,
    sx: f64,
    sxx: f64,
    sy: f64,
    sxy: f64,
}

impl SlopeFit {
    /// Adds the point `(x, y)`.
    pub(crate) fn add(&mut self, x: f64, y: f64) {
        self.n += 1.0;
        self.sx += x;
        self.sxx += x * x;
        self.sy += y;
        self.sxy += x * y;
    }

    /// The fitted `dy/dx`; `None` with fewer than `min_n` points or all at one `x`.
    pub(crate) fn slope(&self, min_n: f64) -> Option<f64> {
        let den = self.n * self.sxx - self.sx * self.sx;
        (self.n >= min_n && den > 0.0).then(|| (self.n * self.sxy - self.sx * self.sy) / den)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn robust_fit_ignores_outliers() {
        let mut pts: Vec<[f64; 2]> = (0..100).map(|i| [i as f64, 0.5 * i as f64 + 3.0]).collect();
        pts.extend((0..20).map(|i| [i as f64 * 5.0, 200.0 - i as f64]));
        // A start near the truth (y = 0.5x + 3), 1.5 px off and 1° turned, as the Hough stage gives.
        let a = 0.5f64.atan() + 1f64.to_radians();
        let start = Line::from_abc([a.sin(), -a.cos(), 3.0 * a.cos() + 1.5]).unwrap();
        let (mut w, mut r) = (Vec::new(), Vec::new());
        let f = robust_fit(&pts, start, &mut w, &mut r).unwrap();
        for x in [0.0, 50.0, 99.0] {
            assert!(f.line.distance([x, 0.5 * x + 3.0]).abs() < 1e-6);
        }
        assert!(w[110] == 0.0 && w[10] > 0.99);
        assert!(fit_line(&[[1.0, 1.0], [1.0, 1.0]], None).is_none());
    }

    #[test]
    fn slope_fit_is_least_squares() {
        let mut f = SlopeFit::default();
        for (x, y) in [(0.0, 1.0), (2.0, 2.1), (4.0, 2.9), (6.0, 4.0)] {
            f.add(x, y);
        }
        // Centred: Σ(x−3)(y−2.5) = 9.8, Σ(x−3)² = 20: slope 0.49.
        assert!((f.slope(4.0).unwrap() - 0.49).abs() < 1e-12);
        assert!(f.slope(5.0).is_none());
        let mut same_x = SlopeFit::default();
        same_x.add(3.0, 1.0);
        same_x.add(3.0, 2.0);
        assert!(same_x.slope(1.0).is_none());
    }
}
