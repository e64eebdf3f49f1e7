//! Stage 3's measurements in the full-resolution image: colour samples at undistorted
//! positions (mapped to measured pixels through the lens, then bilinear), sub-pixel edge
//! positions on profiles across a contour, and the interior/outside colour test.

use super::geom::Line;
use super::lens::Lens;
use crate::detect::RgbView;

/// Bilinear samples of the measured image at undistorted positions.
#[derive(Clone, Copy)]
pub(crate) struct Sampler<'a> {
    pub(crate) image: &'a RgbView<'a>,
    pub(crate) lens: &'a Lens,
    pub(crate) luma_weight: f64,
}

impl Sampler<'_> {
    /// `(chroma 2R − G − B, luma)` (8-bit units) at the undistorted pixel `(u, v)`; `None` outside
    /// the measured image.
    #[inline]
    pub(crate) fn sample(&self, u: f64, v: f64) -> Option<(f64, f64)> {
        let (x, y) = self.lens.distort_px(u, v);
        self.measured(x, y)
    }

    /// `(chroma, luma)` at the measured pixel `(x, y)` (bilinear); `None` outside the image.
    #[inline]
    fn measured(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        let (w, h) = (self.image.width(), self.image.height());
        if !(x >= 0.0 && y >= 0.0 && x < (w - 1) as f64 && y < (h - 1) as f64) {
            return None;
        }
        // In range (checked above): truncation is the floor.
        let (x0, y0) = (x as u32 as usize, y as u32 as usize);
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let d = self.image.data();
        let i = 3 * (y0 * w + x0);
        let j = i + 3 * w;
        let (Some(top), Some(bot)) = (d.get(i..i + 6), d.get(j..j + 6)) else { return None };
        // Chroma `2R − G − B` and luma ×1000 (BT.601 weights) of a pixel, exact in integers;
        // bilinear weights applied once per channel.
        let px = |s: &[u8], k: usize| {
            let (r, g, b) = (i32::from(s[k]), i32::from(s[k + 1]), i32::from(s[k + 2]));
            (f64::from(2 * r - g - b), f64::from(299 * r + 587 * g + 114 * b))
        };
        let (a, b, c, e) = (px(top, 0), px(top, 3), px(bot, 0), px(bot, 3));
        let top = (a.0 + fx * (b.0 - a.0), a.1 + fx * (b.1 - a.1));
        let bot = (c.0 + fx * (e.0 - c.0), c.1 + fx * (e.1 - c.1));
        Some((top.0 + fy * (bot.0 - top.0), 0.001 * (top.1 + fy * (bot.1 - top.1))))
    }

    /// The edge across `line` at `p` (a point of the line, undistorted pixels): the sub-pixel
    /// offset along the line's normal (pixels, within `±gate_px`) of the strongest combined
    /// gradient `√(dC² + dL²)` (1-px samples, central differences, parabola through the peak),
    /// and that strength; `None` when the profile leaves the image or the peak is on the
    /// gate's border or below `min_strength`.
    pub(crate) fn edge_offset(&self, line: &Line, p: [f64; 2], gate_px: f64, min_strength: f64) -> Option<(f64, f64)> {
        const MAX_K: usize = 8;
        let k_gate = (gate_px.ceil() as usize).clamp(1, MAX_K - 3);
        let kk = k_gate + 2;
        let mut vals = [(0.0f64, 0.0f64); 2 * MAX_K + 1];
        let dir = line.direction();
        // Two samples 1.5 px apart along the contour (each bilinear) per position: averages
        // the noise along the edge over about three pixels. The measured positions along each
        // of the two rows across the contour: the lens mapping at both ends and the middle of
        // the row, quadratic in between (the mapping is smooth: its third-order term over
        // the few pixels of a profile is under 10⁻⁴ px).
        let kf = kk as f64;
        let rows = [-0.75, 0.75].map(|side| {
            let q = [p[0] + side * dir[0], p[1] + side * dir[1]];
            ProfileRow::new(self.lens, q, line.n, kf)
        });
        for (idx, k) in (-(kk as isize)..=kk as isize).enumerate() {
            let sk = k as f64 / kf;
            let (xa, ya) = rows[0].at(sk);
            let (xb, yb) = rows[1].at(sk);
            let a = self.measured(xa, ya)?;
            let b = self.measured(xb, yb)?;
            vals[idx] = (0.5 * (a.0 + b.0), 0.5 * (a.1 + b.1));
        }
        let mut strength = [0.0f64; 2 * MAX_K + 1];
        // Derivative kernel [−1, −2, 0, 2, 1] / 8 (smooths blurred, noisy edges).
        for idx in 2..2 * kk - 1 {
            let d = |ch: fn(&(f64, f64)) -> f64| {
                (2.0 * (ch(&vals[idx + 1]) - ch(&vals[idx - 1])) + ch(&vals[idx + 2]) - ch(&vals[idx - 2])) / 8.0
            };
            let (dc, dl) = (d(|v| v.0), self.luma_weight * d(|v| v.1));
            strength[idx] = (dc * dc + dl * dl).sqrt();
        }
        let mut best = 2;
        for idx in 2..2 * kk - 1 {
            if strength[idx] > strength[best] {
                best = idx;
            }
        }
        if best == 2 || best == 2 * kk - 2 || strength[best] < min_strength {
            return None;
        }
        // Sub-pixel: the centroid of the peak's upper half (a motion-blurred edge is a
        // staircase of a few steps: its centroid is the middle instant's edge, where a
        // parabola would lock onto the strongest step).
        let peak = strength[best];
        let half = 0.5 * peak;
        let (mut sw, mut swx) = (0.0, 0.0);
        let mut i = best;
        while i >= 2 && strength[i] > half {
            sw += strength[i] - half;
            swx += (strength[i] - half) * i as f64;
            i -= 1;
        }
        let mut i = best + 1;
        while i <= 2 * kk - 2 && strength[i] > half {
            sw += strength[i] - half;
            swx += (strength[i] - half) * i as f64;
            i += 1;
        }
        if sw <= 0.0 || sw.is_nan() {
            return None;
        }
        let off = swx / sw - kk as f64;
        let b = peak;
        (off.abs() <= gate_px).then_some((off, b))
    }
}

/// The measured positions along one row of a profile, `q + t·n` for `t ∈ [−half, half]`
/// (undistorted pixels in): the lens mapping at both ends and the middle, quadratic in
/// between, `x(s) = mid + s·b + s²·c` with `s = t / half`.
#[derive(Clone, Copy, Debug)]
struct ProfileRow {
    mid: [f64; 2],
    b: [f64; 2],
    c: [f64; 2],
}

impl ProfileRow {
    #[inline]
    fn new(lens: &Lens, q: [f64; 2], n: [f64; 2], half: f64) -> Self {
        let at = |t: f64| lens.distort_px(q[0] + t * n[0], q[1] + t * n[1]);
        let (lo, mid, hi) = (at(-half), at(0.0), at(half));
        Self {
            mid: [mid.0, mid.1],
            b: [0.5 * (hi.0 - lo.0), 0.5 * (hi.1 - lo.1)],
            c: [0.5 * (hi.0 + lo.0) - mid.0, 0.5 * (hi.1 + lo.1) - mid.1],
        }
    }

    /// The measured position at `s = t / half`, `s ∈ [−1, 1]`.
    #[inline]
    fn at(&self, s: f64) -> (f64, f64) {
        (self.mid[0] + s * (self.b[0] + s * self.c[0]), self.mid[1] + s * (self.b[1] + s * self.c[1]))
    }
}

/// The chroma inside the strip between two contours (upper quartile) and just outside each
/// (medians).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Interior {
    pub(crate) inside: f64,
    pub(crate) outside: [f64; 2],
    /// Just inside each contour (medians).
    pub(crate) near: [f64; 2],
    /// Luma: median inside, medians just outside each contour.
    pub(crate) luma_inside: f64,
    pub(crate) luma_outside: [f64; 2],
}

/// Samples the strip between `c0` and `c1` at 16 stations of `o + s·t`, `s ∈ [s0, s1]`
/// (undistorted pixels). `None` when too few samples fall in the image or the stations are not
/// between the lines.
pub(crate) fn interior(
    sampler: &Sampler<'_>,
    c: [&Line; 2],
    o: [f64; 2],
    t: [f64; 2],
    s: [f64; 2],
    buf: &mut [Vec<f64>; 8],
) -> Option<Interior> {
    buf.iter_mut().for_each(Vec::clear);
    let d = [-t[1], t[0]];
    let n_st = 16;
    for k in 0..n_st {
        let sk = s[0] + (s[1] - s[0]) * (k as f64 + 0.5) / n_st as f64;
        let q = [o[0] + sk * t[0], o[1] + sk * t[1]];
        let (Some(l0), Some(l1)) = (c[0].hit(q, d), c[1].hit(q, d)) else { continue };
        let m = 0.5 * (l0 + l1);
        let (h0, h1) = (l0 - m, l1 - m);
        if h0 * h1 >= 0.0 {
            return None;
        }
        let at = |lam: f64| sampler.sample(q[0] + (m + lam) * d[0], q[1] + (m + lam) * d[1]);
        for f in [-0.7, -0.35, 0.0, 0.35, 0.7] {
            if let Some((cv, lv)) = at(f * h0.abs()) {
                buf[0].push(cv);
                buf[5].push(lv);
            }
        }
        for (side, h) in [h0, h1].into_iter().enumerate() {
            // Just outside: beyond a blurred edge, not as far as another structure; and just
            // inside (the contour must bound the grey strip itself).
            let margin = 4.0;
            if let Some((cv, lv)) = at(h + h.signum() * margin) {
                buf[1 + side].push(cv);
                buf[6 + side].push(lv);
            }
            let inner = margin.min(0.4 * h.abs());
            if let Some((cv, _)) = at(h - h.signum() * inner) {
                buf[3 + side].push(cv);
            }
        }
    }
    if buf.iter().any(|b| b.len() < 4) {
        return None;
    }
    // Inside: the upper quartile (nearly all of the strip must be grey, not just half of it);
    // outside: the medians.
    let mut med = [0.0; 8];
    for (i, (m, b)) in med.iter_mut().zip(buf.iter_mut()).enumerate() {
        let q = if i == 0 { (3 * b.len()) / 4 } else { b.len() / 2 };
        b.select_nth_unstable_by(q, f64::total_cmp);
        *m = b[q];
    }
    Some(Interior {
        inside: med[0],
        outside: [med[1], med[2]],
        near: [med[3], med[4]],
        luma_inside: med[5],
        luma_outside: [med[6], med[7]],
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use estimator::calib::Intrinsics;

    /// The detectors' test camera (640×480, mild barrel distortion).
    fn camera() -> Intrinsics {
        crate::synth::endoscope_camera()
    }

    #[test]
    fn the_profile_rows_follow_the_lens_within_a_thousandth_of_a_pixel() {
        let lens = Lens::new(&camera());
        let mut worst = 0.0f64;
        // Profiles across the whole image, corners included, at every orientation.
        for (qx, qy) in [(5.0, 5.0), (320.0, 240.0), (630.0, 470.0), (100.0, 400.0), (600.0, 30.0), (-10.0, 250.0)] {
            for deg in (0..180).step_by(15) {
                let a = f64::from(deg).to_radians();
                let n = [a.cos(), a.sin()];
                for half in [4.0, 5.0, 8.0] {
                    let row = ProfileRow::new(&lens, [qx, qy], n, half);
                    for k in -8..=8 {
                        let t = f64::from(k) * half / 8.0;
                        let exact = lens.distort_px(qx + t * n[0], qy + t * n[1]);
                        let got = row.at(t / half);
                        worst = worst.max((got.0 - exact.0).hypot(got.1 - exact.1));
                    }
                }
            }
        }
        assert!(worst < 1e-3, "worst {worst} px");
    }

    #[test]
    fn a_sample_is_the_bilinear_chroma_and_luma_of_the_four_pixels() {
        let k = camera();
        let lens = Lens::new(&k);
        let (w, h) = (k.width as usize, k.height as usize);
        let data: Vec<u8> = (0..w * h * 3).map(|i| ((i * 7919 + (i / 3) * 31) % 256) as u8).collect();
        let image = RgbView::new(w, h, &data).unwrap();
        let s = Sampler { image: &image, lens: &lens, luma_weight: 1.0 };
        let px = |x: usize, y: usize| {
            let p = image.pixel(x, y).map(f64::from);
            (2.0 * p[0] - p[1] - p[2], 0.299 * p[0] + 0.587 * p[1] + 0.114 * p[2])
        };
        let mut n = 0;
        for i in 0..400 {
            let (u, v) = (f64::from(i) * 1.61 % 660.0 - 10.0, f64::from(i) * 2.37 % 500.0 - 10.0);
            let (x, y) = lens.distort_px(u, v);
            let got = s.sample(u, v);
            if !(x >= 0.0 && y >= 0.0 && x < (w - 1) as f64 && y < (h - 1) as f64) {
                assert!(got.is_none(), "({u}, {v}) → ({x}, {y}) is outside");
                continue;
            }
            let (x0, y0) = (x.floor() as usize, y.floor() as usize);
            let (fx, fy) = (x - x0 as f64, y - y0 as f64);
            let lerp = |a: f64, b: f64, f: f64| a + f * (b - a);
            let (a, b, c, d) = (px(x0, y0), px(x0 + 1, y0), px(x0, y0 + 1), px(x0 + 1, y0 + 1));
            let want =
                (lerp(lerp(a.0, b.0, fx), lerp(c.0, d.0, fx), fy), lerp(lerp(a.1, b.1, fx), lerp(c.1, d.1, fx), fy));
            let got = got.unwrap();
            assert!((got.0 - want.0).abs() < 1e-9 && (got.1 - want.1).abs() < 1e-9, "{got:?} vs {want:?}");
            n += 1;
        }
        assert!(n > 300);
    }
}
