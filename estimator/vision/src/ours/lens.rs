//! The lens model on the fast path: undistorted pixel → measured pixel (the plumb-bob model of
//! `estimator::calib::Intrinsics::project`, restated on plain `f64`s so that the profiles'
//! thousands of samples cost a few multiplications each), and the half-resolution table of
//! undistorted positions of measured pixels (built once, with `Intrinsics::undistort_px`).

use estimator::calib::Intrinsics;
use nalgebra::Vector2;

/// The camera's pinhole and distortion coefficients, copied.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Lens {
    fx: f64,
    fy: f64,
    inv_fx: f64,
    inv_fy: f64,
    cx: f64,
    cy: f64,
    skew: f64,
    d: [f64; 5],
    distorted: bool,
}

impl Lens {
    pub(crate) fn new(k: &Intrinsics) -> Self {
        Self {
            fx: k.fx,
            fy: k.fy,
            inv_fx: 1.0 / k.fx,
            inv_fy: 1.0 / k.fy,
            cx: k.cx,
            cy: k.cy,
            skew: k.skew,
            d: k.distortion,
            distorted: !k.is_undistorted(),
        }
    }

    /// Measured (distorted) pixel of the undistorted pixel `(u, v)`; the same arithmetic as
    /// `Intrinsics::project` of the normalised ray.
    #[inline]
    pub(crate) fn distort_px(&self, u: f64, v: f64) -> (f64, f64) {
        if !self.distorted {
            return (u, v);
        }
        let y = (v - self.cy) * self.inv_fy;
        let x = (u - self.cx - self.skew * y) * self.inv_fx;
        let [k1, k2, p1, p2, k3] = self.d;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
        (self.fx * xd + self.skew * yd + self.cx, self.fy * yd + self.cy)
    }
}

/// Undistorted full-resolution position of every half-resolution pixel centre (the 2×2 block
/// `(2j, 2i)…(2j+1, 2i+1)` has its centre at `(2j + 0.5, 2i + 0.5)` measured), row-major.
#[derive(Clone, Debug, Default)]
pub(crate) struct HalfResTable {
    pub(crate) w2: usize,
    pub(crate) h2: usize,
    /// `[u, v]` undistorted pixels per half-resolution pixel.
    pub(crate) uv: Vec<[f32; 2]>,
}

impl HalfResTable {
    pub(crate) fn new(k: &Intrinsics) -> Self {
        let (w2, h2) = (k.width as usize / 2, k.height as usize / 2);
        let mut uv = Vec::with_capacity(w2 * h2);
        for i in 0..h2 {
            for j in 0..w2 {
                let p = k.undistort_px(&Vector2::new(2.0 * j as f64 + 0.5, 2.0 * i as f64 + 0.5));
                uv.push([p.x as f32, p.y as f32]);
            }
        }
        Self { w2, h2, uv }
    }

    /// The undistorted position (full-resolution pixels) of half-resolution pixel `(j, i)`
    /// and the undistorted direction of the measured unit vector `(ex, ey)` there (finite
    /// differences of the table; not normalised).
    #[inline]
    pub(crate) fn map(&self, j: usize, i: usize, ex: f32, ey: f32) -> ([f32; 2], [f32; 2]) {
        let w = self.w2;
        let at = |jj: usize, ii: usize| self.uv[ii * w + jj];
        let p = at(j, i);
        let (jl, jr) = (j.saturating_sub(1), (j + 1).min(self.w2 - 1));
        let (iu, id) = (i.saturating_sub(1), (i + 1).min(self.h2 - 1));
        let (l, r, u, d) = (at(jl, i), at(jr, i), at(j, iu), at(j, id));
        let dx = ((jr - jl) as f32).max(1.0);
        let dy = ((id - iu) as f32).max(1.0);
        let jx = [(r[0] - l[0]) / dx, (r[1] - l[1]) / dx];
        let jy = [(d[0] - u[0]) / dy, (d[1] - u[1]) / dy];
        (p, [jx[0] * ex + jy[0] * ey, jx[1] * ex + jy[1] * ey])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    #[test]
    fn distort_px_matches_project_and_inverts_undistort() {
        let k = Intrinsics {
            fx: 400.0,
            fy: 410.0,
            cx: 321.0,
            cy: 238.0,
            skew: 0.5,
            width: 640,
            height: 480,
            distortion: [-0.08, 0.01, 0.001, -0.0005, 0.0],
        };
        let lens = Lens::new(&k);
        for &(u, v) in &[(10.0, 20.0), (320.0, 240.0), (600.0, 470.0), (-20.0, 500.0)] {
            let y = (v - k.cy) / k.fy;
            let x = (u - k.cx - k.skew * y) / k.fx;
            let p = k.project(&Vector3::new(x, y, 1.0));
            let (du, dv) = lens.distort_px(u, v);
            assert!((p.x - du).abs() < 1e-9 && (p.y - dv).abs() < 1e-9);
            let back = k.undistort_px(&Vector2::new(du, dv));
            assert!((back.x - u).abs() < 1e-6 && (back.y - v).abs() < 1e-6, "{back:?} vs {u},{v}");
        }
    }
}
