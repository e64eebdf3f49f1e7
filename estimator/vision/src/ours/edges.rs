//! Stage 1: edgels on a half-resolution image, located in undistorted pixels.
//!
//! Two channels per 2×2 block (its mean): luma (BT.601) and the red opponent
//! `C = 2R − G − B` (grey metal ≈ 0, pink/red tissue ≫ 0). The gradient of the pair is
//! Di Zenzo's: the largest eigenvalue of the 2×2 structure tensor summed over both channels
//! (Sobel on each), so an edge seen in either channel counts, whatever its polarity in each.
//! Non-maximum suppression along the gradient, a threshold, then each edgel's position and
//! normal direction are mapped to undistorted pixels through the precomputed table.
//!
//! On a hazy frame (median chroma under `clear_chroma`) the normal is the eigenvector of the
//! tensor summed over the 3×3 neighbourhood (the structure tensor's integration scale, as in
//! Förstner's operator), not the pixel's own: haze scales the contrasts by its transmittance
//! and leaves the sensor noise, so a faint contour's single-pixel gradient directions scatter
//! by several degrees, and the orientation-guided Hough transform votes at each edgel's own
//! normal, its distance from the reference point wrong by `s · δθ` (hundreds of pixels along
//! the line times the angle error): the votes of a straight, well covered contour spread over
//! tens of distance bins and make no peak.

use super::lens::HalfResTable;
use crate::detect::RgbView;

/// One edgel, undistorted full-resolution pixels.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Edgel {
    /// Position `[u, v]`, undistorted pixels.
    pub(crate) p: [f32; 2],
    /// Unit normal (gradient direction modulo π: `ny ≥ 0`, or `nx > 0` when `ny = 0`).
    pub(crate) n: [f32; 2],
}

/// The working buffers of stage 1 (kept between frames).
#[derive(Clone, Debug, Default)]
pub(crate) struct EdgeBuffers {
    chroma: Vec<f32>,
    luma: Vec<f32>,
    mag2: Vec<f32>,
    dir: Vec<u8>,
    eig: Vec<[f32; 2]>,
    hist: Vec<u32>,
    /// The structure tensor `(gx², gy², gx·gy)` summed over both channels, per pixel.
    tensor: [Vec<f32>; 3],
    pub(crate) edgels: Vec<Edgel>,
    /// The frame's median half-resolution chroma `2R − G − B` (8-bit units): the haze
    /// estimate of `super::Haze`.
    pub(crate) chroma_median: f32,
    /// The frame's silhouette edgels (grey on one side, tissue-coloured on the other: an
    /// instrument's outline against the tissue).
    pub(crate) silhouette_edgels: usize,
    /// The fraction of the silhouette edgels whose step is blurred, its sharpness under
    /// `BLURRED_SHARPNESS`, 0 with fewer than `MIN_SILHOUETTE_EDGELS` of them. The sharpness
    /// is the chroma slope at the edgel (half-resolution central difference along its normal,
    /// per pixel) over the whole chroma step across it (±3 half-resolution pixels): about 0.5
    /// for a step within a pixel, lower for a blurred one (a motion-blurred silhouette is a
    /// staircase of the exposure's instants: about 1/6 for three steps 2 px apart).
    pub(crate) silhouette_blurred: f32,
    /// Keep only the silhouette edgels (grey on one side, tissue-coloured on the other, as
    /// `silhouette_edgels` counts them; none when the frame's median chroma is 8 or less):
    /// the coarse scale's edgels (`super::OursConfig::coarse_edgels_under_haze`), where soft
    /// tissue edges (a shadow's, the haze's gradient) also pass the threshold.
    pub(crate) silhouette_only: bool,
}

/// The fewest silhouette edgels for `EdgeBuffers::silhouette_blurred` (fewer: 0).
const MIN_SILHOUETTE_EDGELS: usize = 20;

/// The sharpness under which a silhouette edgel counts as blurred (see
/// `EdgeBuffers::silhouette_blurred`; on the tuning set's `default` frames, session 22, the
/// slow families' silhouette edgels had a median fraction under it of 0.01-0.02, the
/// motion-blurred `blur` family's 0.37).
const BLURRED_SHARPNESS: f32 = 0.25;

impl EdgeBuffers {
    /// Buffers that keep only the silhouette edgels (`silhouette_only`).
    pub(crate) fn silhouettes_only() -> Self {
        Self { silhouette_only: true, ..Self::default() }
    }

    /// Sets `chroma_median` from the histogram of the half-resolution chroma filled by
    /// `run` (1-unit bins over `[−256, 512)`).
    fn chroma_median(&mut self) {
        const LO: f32 = -256.0;
        let total: u32 = self.hist.iter().sum();
        let want = total.div_ceil(2).max(1);
        let mut acc = 0;
        self.chroma_median = 0.0;
        for (i, h) in self.hist.iter().enumerate() {
            acc += h;
            if acc >= want {
                self.chroma_median = i as f32 + LO + 0.5;
                break;
            }
        }
    }

    /// Fills `self.edgels`. `image` has the table's camera size (checked by the caller);
    /// `threshold` is on the gradient magnitude (channel units per half-resolution pixel);
    /// `luma_weight` scales the luma channel against the chroma channel. On a hazy frame, its
    /// median chroma under `clear_chroma` (`2R − G − B`, 8-bit; 0: never), each edgel's
    /// normal is the structure tensor's summed over its 3×3 neighbourhood (its position and
    /// magnitude stay the pixel's own).
    pub(crate) fn run(
        &mut self,
        image: &RgbView<'_>,
        table: &HalfResTable,
        threshold: f32,
        luma_weight: f32,
        clear_chroma: f32,
    ) {
        self.edgels.clear();
        let (w2, h2) = (table.w2, table.h2);
        if w2 < 3 || h2 < 3 {
            return;
        }
        let n = w2 * h2;
        self.chroma.resize(n, 0.0);
        self.luma.resize(n, 0.0);
        self.mag2.clear();
        self.mag2.resize(n, 0.0);
        self.dir.clear();
        self.dir.resize(n, 0);
        self.eig.resize(n, [0.0; 2]);
        let w = image.width();
        let data = image.data();
        // Histogram of the chroma (1-unit bins over [−256, 512)), for the frame's median.
        const HIST_BINS: usize = 768;
        self.hist.clear();
        self.hist.resize(HIST_BINS, 0);
        // Half-resolution means.
        for i in 0..h2 {
            let r0 = &data[3 * (2 * i) * w..3 * (2 * i + 1) * w];
            let r1 = &data[3 * (2 * i + 1) * w..3 * (2 * i + 2) * w];
            let crow = &mut self.chroma[i * w2..(i + 1) * w2];
            let lrow = &mut self.luma[i * w2..(i + 1) * w2];
            for j in 0..w2 {
                let a = &r0[6 * j..6 * j + 6];
                let b = &r1[6 * j..6 * j + 6];
                let r = u32::from(a[0]) + u32::from(a[3]) + u32::from(b[0]) + u32::from(b[3]);
                let g = u32::from(a[1]) + u32::from(a[4]) + u32::from(b[1]) + u32::from(b[4]);
                let bl = u32::from(a[2]) + u32::from(a[5]) + u32::from(b[2]) + u32::from(b[5]);
                // The chroma's bin: ⌊(2R − G − B)/4⌋ + 256, clamped (exactly the bin of the
                // mean below, computed in integers).
                let c4 = 2 * r as i32 - g as i32 - bl as i32;
                let bin = ((c4 >> 2) + 256).clamp(0, HIST_BINS as i32 - 1) as usize;
                self.hist[bin] += 1;
                let (r, g, bl) = (r as f32, g as f32, bl as f32);
                crow[j] = 0.25 * (2.0 * r - g - bl);
                lrow[j] = 0.25 * luma_weight * (0.299 * r + 0.587 * g + 0.114 * bl);
            }
        }
        self.chroma_median();
        // Under haze (the frame's median chroma under `clear_chroma`) the contrasts are scaled
        // down and the noise is not: a weak edge's single-pixel orientation scatters by degrees.
        let integrate = self.chroma_median < clear_chroma;
        // The structure tensor `(gx², gy², gx·gy)` summed over both channels, per pixel
        // (Sobel / 8 on both channels; zero on the border).
        for t in &mut self.tensor {
            t.clear();
            t.resize(n, 0.0);
        }
        for i in 1..h2 - 1 {
            fn rows(ch: &[f32], i: usize, w2: usize) -> (&[f32], &[f32], &[f32]) {
                (&ch[(i - 1) * w2..i * w2], &ch[i * w2..(i + 1) * w2], &ch[(i + 1) * w2..(i + 2) * w2])
            }
            // Branch-free (vectorised).
            let m = w2 - 2;
            let (c0, c1, c2) = rows(&self.chroma, i, w2);
            let (l0, l1, l2) = rows(&self.luma, i, w2);
            let [ta, tc, tb] = &mut self.tensor;
            let at = i * w2 + 1;
            let (ta, tc, tb) = (&mut ta[at..at + m], &mut tc[at..at + m], &mut tb[at..at + m]);
            let sobel = |u: &[f32], m: &[f32], d: &[f32], k: usize| {
                let (u, m, d) = (&u[k..k + 3], &m[k..k + 3], &d[k..k + 3]);
                let gx = (u[2] + 2.0 * m[2] + d[2]) - (u[0] + 2.0 * m[0] + d[0]);
                let gy = (d[0] + 2.0 * d[1] + d[2]) - (u[0] + 2.0 * u[1] + u[2]);
                (gx * 0.125, gy * 0.125)
            };
            for k in 0..m {
                let (gxc, gyc) = sobel(c0, c1, c2, k);
                let (gxl, gyl) = sobel(l0, l1, l2, k);
                ta[k] = (0.0 + gxc * gxc) + gxl * gxl;
                tc[k] = (0.0 + gyc * gyc) + gyl * gyl;
                tb[k] = (0.0 + gxc * gyc) + gxl * gyl;
            }
        }
        // Di Zenzo magnitude per pixel; the direction from the tensor integrated over the 3×3
        // neighbourhood (a weak edge's single-pixel orientation scatters by degrees under
        // noise, and the Hough votes at it); quantised direction for the NMS.
        let t2 = threshold * threshold;
        let tan22 = 0.414_213_56_f32;
        for i in 1..h2 - 1 {
            for j in 1..w2 - 1 {
                let idx = i * w2 + j;
                let (a, c, b) = (self.tensor[0][idx], self.tensor[1][idx], self.tensor[2][idx]);
                let tr = a + c;
                if tr < t2 {
                    continue;
                }
                let disc = ((a - c) * (a - c) + 4.0 * b * b).sqrt();
                let lam = 0.5 * (tr + disc);
                self.mag2[idx] = lam;
                if lam < t2 {
                    continue;
                }
                let (a, c, b) = if integrate {
                    let mut s = [0.0f32; 3];
                    for r in [idx - w2, idx, idx + w2] {
                        for q in r - 1..=r + 1 {
                            s[0] += self.tensor[0][q];
                            s[1] += self.tensor[1][q];
                            s[2] += self.tensor[2][q];
                        }
                    }
                    (s[0], s[1], s[2])
                } else {
                    (a, c, b)
                };
                let disc = ((a - c) * (a - c) + 4.0 * b * b).sqrt();
                let lam = 0.5 * (a + c + disc);
                // Eigenvector of the largest eigenvalue.
                let (ex, ey) = if a >= c { (lam - c, b) } else { (b, lam - a) };
                let norm = (ex * ex + ey * ey).sqrt();
                if norm <= 0.0 || norm.is_nan() {
                    continue;
                }
                let (ex, ey) = (ex / norm, ey / norm);
                self.eig[idx] = [ex, ey];
                let (ax, ay) = (ex.abs(), ey.abs());
                // 1: horizontal neighbours, 2: vertical, 3: diagonal (+,+), 4: diagonal (+,−).
                self.dir[idx] = if ay <= tan22 * ax {
                    1
                } else if ax <= tan22 * ay {
                    2
                } else if (ex > 0.0) == (ey > 0.0) {
                    3
                } else {
                    4
                };
            }
        }
        // Non-maximum suppression and mapping to undistorted pixels.
        let (mut n_sil, mut n_blurred) = (0usize, 0usize);
        let grey = 0.25 * self.chroma_median;
        let tissue = 0.6 * self.chroma_median;
        for i in 1..h2 - 1 {
            for j in 1..w2 - 1 {
                let idx = i * w2 + j;
                let d = self.dir[idx];
                if d == 0 {
                    continue;
                }
                let m = self.mag2[idx];
                let (p, q) = match d {
                    1 => (idx - 1, idx + 1),
                    2 => (idx - w2, idx + w2),
                    3 => (idx - w2 - 1, idx + w2 + 1),
                    _ => (idx - w2 + 1, idx + w2 - 1),
                };
                if !(m > self.mag2[p] && m >= self.mag2[q]) {
                    continue;
                }
                let [ex, ey] = self.eig[idx];
                let mut silhouette = false;
                if self.chroma_median > 8.0 {
                    // The chroma at ±k half-resolution pixels along the normal (nearest pixel).
                    let at = |k: f32| -> Option<f32> {
                        let (x, y) = (j as f32 + k * ex, i as f32 + k * ey);
                        let (x, y) = (x.round(), y.round());
                        (x >= 0.0 && y >= 0.0 && (x as usize) < w2 && (y as usize) < h2)
                            .then(|| self.chroma[y as usize * w2 + x as usize])
                    };
                    if let (Some(a3), Some(a1), Some(b1), Some(b3)) = (at(-3.0), at(-1.0), at(1.0), at(3.0)) {
                        let (lo, hi) = (a3.min(b3), a3.max(b3));
                        if lo < grey && hi > tissue {
                            silhouette = true;
                            n_sil += 1;
                            n_blurred += usize::from(0.5 * (b1 - a1).abs() < BLURRED_SHARPNESS * (hi - lo));
                        }
                    }
                }
                if self.silhouette_only && !silhouette {
                    continue;
                }
                // The edge's tangent, mapped; the undistorted normal is its perpendicular.
                let (pos, tan) = table.map(j, i, -ey, ex);
                if !pos.iter().all(|v| v.is_finite()) {
                    continue;
                }
                let (mut nx, mut ny) = (tan[1], -tan[0]);
                let nn = (nx * nx + ny * ny).sqrt();
                if nn <= 0.0 || nn.is_nan() {
                    continue;
                }
                nx /= nn;
                ny /= nn;
                if ny < 0.0 || (ny == 0.0 && nx < 0.0) {
                    nx = -nx;
                    ny = -ny;
                }
                self.edgels.push(Edgel { p: pos, n: [nx, ny] });
            }
        }
        self.silhouette_edgels = n_sil;
        self.silhouette_blurred = if n_sil >= MIN_SILHOUETTE_EDGELS { n_blurred as f32 / n_sil as f32 } else { 0.0 };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A hazy frame (chroma about 20): a faint straight colour step of 14 chroma units over
    /// 3 px with uniform noise of ±3 on red (±6 in chroma), its normal at 20° from the x axis.
    /// The edgels on it have their normals within 5° RMS with the 3×3 integration (4.2°
    /// measured), and scattered by at least 1.5 times that without it (`clear_chroma` 0: 8.8°).
    #[test]
    fn a_faint_edges_normals_are_integrated_under_haze() {
        let k = crate::synth::endoscope_camera();
        let table = HalfResTable::new(&k);
        let (w, h) = (k.width as usize, k.height as usize);
        // The edge: undistorted points with n·(u − p0) = 0, n at 20° from the x axis.
        let a = 20f64.to_radians();
        let n = [a.cos(), a.sin()];
        let p0 = [320.0, 240.0];
        let mut data = vec![0u8; w * h * 3];
        let mut state = 12345u64;
        for y in 0..h {
            for x in 0..w {
                let u = k.undistort_px(&nalgebra::Vector2::new(x as f64, y as f64));
                let d = (u.x - p0[0]) * n[0] + (u.y - p0[1]) * n[1];
                let s = (d / 3.0 + 0.5).clamp(0.0, 1.0);
                state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
                let noise = ((state >> 33) % 7) as f64 - 3.0;
                let r = 160.0 - 7.0 * s + noise;
                let px = &mut data[3 * (y * w + x)..3 * (y * w + x) + 3];
                px.copy_from_slice(&[r.round() as u8, 150, 150]);
            }
        }
        let image = RgbView::new(w, h, &data).unwrap();
        let rms = |clear_chroma: f32| {
            let mut e = EdgeBuffers::default();
            e.run(&image, &table, 5.0, 1.0, clear_chroma);
            let errs: Vec<f64> = e
                .edgels
                .iter()
                .filter(|g| {
                    let d = (f64::from(g.p[0]) - p0[0]) * n[0] + (f64::from(g.p[1]) - p0[1]) * n[1];
                    d.abs() < 2.0
                })
                .map(|g| (f64::from(g.n[0]) * n[0] + f64::from(g.n[1]) * n[1]).abs().min(1.0).acos().to_degrees())
                .collect();
            assert!(errs.len() > 100, "{} edgels on the edge", errs.len());
            (errs.iter().map(|e| e * e).sum::<f64>() / errs.len() as f64).sqrt()
        };
        let (with, without) = (rms(60.0), rms(0.0));
        println!("normal RMS error: {with:.2}° integrated, {without:.2}° per pixel");
        assert!(with < 5.0, "{with}°");
        assert!(without > 1.5 * with, "{without}° against {with}°");
    }

    #[test]
    fn the_chroma_median_is_the_median_bin_of_the_half_resolution_chroma() {
        let k = crate::synth::endoscope_camera();
        let table = HalfResTable::new(&k);
        let (w, h) = (k.width as usize, k.height as usize);
        // A left half of strong red (chroma ≈ 300), a right half of grey, and a ramp of
        // greenish rows (negative chroma), so that bins on both sides of zero are used.
        let mut data = vec![0u8; w * h * 3];
        for y in 0..h {
            for x in 0..w {
                let p = &mut data[3 * (y * w + x)..3 * (y * w + x) + 3];
                let v = ((x * 13 + y * 7) % 50) as u8;
                p.copy_from_slice(&if y < 60 {
                    [40, 120 + v, 90]
                } else if x < 300 {
                    [200 + v, 60, 50]
                } else {
                    [120 + v, 118, 121]
                });
            }
        }
        let image = RgbView::new(w, h, &data).unwrap();
        let mut e = EdgeBuffers::default();
        e.run(&image, &table, 6.0, 1.0, 60.0);
        // The median bin of ⌊chroma + 256⌋ (chroma of each 2×2 block's mean), by sorting.
        let mut bins: Vec<i64> = e.chroma.iter().map(|c| ((c + 256.0).floor() as i64).clamp(0, 767)).collect();
        bins.sort_unstable();
        let want = bins[bins.len().div_ceil(2) - 1] as f32 - 256.0 + 0.5;
        assert_eq!(e.chroma_median, want);
        assert!(e.chroma.iter().any(|&c| c < 0.0) && e.chroma.iter().any(|&c| c > 200.0));
    }
}
