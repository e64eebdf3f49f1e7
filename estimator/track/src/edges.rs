//! One image's edges and their distance field, computed once per frame and looked up by every
//! particle (ours), in buffers allocated at start-up.
//!
//! - [`EdgeField::compute_ours`]: grey levels, Sobel gradient, non-maximum suppression along the
//!   gradient, a threshold on the gradient's magnitude; each edge pixel keeps its gradient
//!   direction (for the oriented chamfer);
//! - [`EdgeField::set_edges`]: edges given by the caller (the paper mode's Canny edges);
//! - the exact Euclidean distance transform (Felzenszwalb and Huttenlocher's lower envelope of
//!   parabolas, two 1-D passes) with, at every pixel, the index of the nearest edge pixel.
//!
//! Pixels: the centre of the top-left pixel is `(0, 0)`; distances in pixels.

/// Why an image was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ImageError {
    /// The buffer's length is not `width · height · channels`.
    #[error("image buffer of {len} bytes is not {width}x{height}x{channels}")]
    Size {
        /// Bytes given.
        len: usize,
        /// Expected width, pixels.
        width: usize,
        /// Expected height, pixels.
        height: usize,
        /// Channels expected.
        channels: usize,
    },
}

/// Edges of one image and their distance field. See the module documentation.
#[derive(Clone, Debug)]
pub struct EdgeField {
    width: usize,
    height: usize,
    grey: Vec<f32>,
    mag: Vec<f32>,
    gx: Vec<f32>,
    /// The gradient's `y` component while computing, then its direction at edge pixels.
    gdir: Vec<f32>,
    edge: Vec<bool>,
    /// Distance to the nearest edge pixel, pixels (`f32::INFINITY` without any edge).
    dist: Vec<f32>,
    /// Index of the nearest edge pixel (`u32::MAX` without any edge).
    nearest: Vec<u32>,
    // Scratch of the transform.
    col_d: Vec<f32>,
    col_row: Vec<u32>,
    env_v: Vec<u32>,
    env_z: Vec<f32>,
    edge_count: usize,
    threshold_used: f32,
}

/// A contrast-adaptive threshold for [`EdgeField::compute_ours_adaptive`]: the Sobel magnitude
/// threshold `t` becomes `max(t · min(1, p / reference_px)², noise_factor · median)`, at most
/// `t`, where `p` is the frame's 99.9th percentile of the gradient magnitude (the strongest
/// contrasts: the instrument's contours on a clear frame) and `median` its median (the sensor
/// noise and texture floor). A hazy frame, whose contrasts smoke has scaled down, is judged
/// against its own contrast; a clear frame keeps `t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EdgeContrast {
    /// The 99.9th percentile of a clear frame's gradient magnitude, Sobel units (> 0).
    pub reference_px: f32,
    /// The threshold never goes below this many times the frame's median magnitude (≥ 0).
    pub noise_factor: f32,
}

const BIG: f32 = 1e12;

impl EdgeField {
    /// Buffers for `width × height` images (pixels, both ≥ 3).
    pub fn new(width: usize, height: usize) -> Self {
        let n = width * height;
        Self {
            width,
            height,
            grey: vec![0.0; n],
            mag: vec![0.0; n],
            gx: vec![0.0; n],
            gdir: vec![0.0; n],
            edge: vec![false; n],
            dist: vec![f32::INFINITY; n],
            nearest: vec![u32::MAX; n],
            col_d: vec![0.0; n],
            col_row: vec![0; n],
            env_v: vec![0; width.max(height) + 1],
            env_z: vec![0.0; width.max(height) + 2],
            edge_count: 0,
            threshold_used: 0.0,
        }
    }

    /// Width, pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height, pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Edge pixels found by the last computation.
    pub fn edge_count(&self) -> usize {
        self.edge_count
    }

    /// `true` at an edge pixel (row-major).
    pub fn edges(&self) -> &[bool] {
        &self.edge
    }

    /// Our edges of an sRGB image (`rgb`: row-major, 3 bytes a pixel): a Sobel gradient of the
    /// grey levels, non-maximum suppression, magnitude above `threshold` (grey levels per pixel,
    /// Sobel-scaled: a step of `s` grey levels gives `4·s`); then the distance field.
    /// Allocation-free.
    pub fn compute_ours(&mut self, rgb: &[u8], threshold: f32) -> Result<(), ImageError> {
        self.compute_ours_adaptive(rgb, threshold, None)
    }

    /// The Sobel threshold (magnitude units) the last [`EdgeField::compute_ours_adaptive`] used.
    pub fn threshold_used(&self) -> f32 {
        self.threshold_used
    }

    /// [`EdgeField::compute_ours`] with the threshold adapted to the frame's contrast
    /// ([`EdgeContrast`]; `None`: `threshold` as given). Allocation-free (a histogram of the
    /// magnitude on the stack).
    pub fn compute_ours_adaptive(
        &mut self,
        rgb: &[u8],
        threshold: f32,
        contrast: Option<EdgeContrast>,
    ) -> Result<(), ImageError> {
        let (w, h) = (self.width, self.height);
        if rgb.len() != w * h * 3 {
            return Err(ImageError::Size { len: rgb.len(), width: w, height: h, channels: 3 });
        }
        for (g, p) in self.grey.iter_mut().zip(rgb.chunks_exact(3)) {
            *g = 0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]) + 0.114 * f32::from(p[2]);
        }
        self.mag.fill(0.0);
        for y in 1..h - 1 {
            let (r0, r1, r2) = ((y - 1) * w, y * w, (y + 1) * w);
            for x in 1..w - 1 {
                let g = &self.grey;
                let gx = (g[r0 + x + 1] + 2.0 * g[r1 + x + 1] + g[r2 + x + 1])
                    - (g[r0 + x - 1] + 2.0 * g[r1 + x - 1] + g[r2 + x - 1]);
                let gy = (g[r2 + x - 1] + 2.0 * g[r2 + x] + g[r2 + x + 1])
                    - (g[r0 + x - 1] + 2.0 * g[r0 + x] + g[r0 + x + 1]);
                self.mag[r1 + x] = (gx * gx + gy * gy).sqrt();
                self.gx[r1 + x] = gx;
                self.gdir[r1 + x] = gy;
            }
        }
        let threshold = match contrast {
            None => threshold,
            Some(c) => {
                // Histogram of the magnitude, 1 unit per bin up to 1023.
                let mut hist = [0u32; 1024];
                let mut n = 0u64;
                for y in 1..h - 1 {
                    for &m in &self.mag[y * w + 1..y * w + w - 1] {
                        hist[(m as usize).min(1023)] += 1;
                        n += 1;
                    }
                }
                let at = |q: f64| {
                    let k = (q * n as f64).ceil() as u64;
                    let mut acc = 0u64;
                    for (b, &c) in hist.iter().enumerate() {
                        acc += u64::from(c);
                        if acc >= k {
                            return b as f32 + 0.5;
                        }
                    }
                    1023.5
                };
                let (median, top) = (at(0.5), at(0.999));
                let scale = (top / c.reference_px).min(1.0);
                (threshold * scale * scale).max(c.noise_factor * median).min(threshold)
            }
        };
        self.threshold_used = threshold;
        self.edge.fill(false);
        let mut count = 0;
        for y in 1..h - 1 {
            for x in 1..w - 1 {
                let i = y * w + x;
                let m = self.mag[i];
                if m <= threshold {
                    continue;
                }
                // Neighbours along the gradient, direction quantised to 45° (tan 22.5° = 0.4142).
                let (gx, gy) = (self.gx[i], self.gdir[i]);
                let (ax, ay) = (gx.abs(), gy.abs());
                let (dx, dy): (isize, isize) = if ay <= 0.4142 * ax {
                    (1, 0)
                } else if ax <= 0.4142 * ay {
                    (0, 1)
                } else if (gx > 0.0) == (gy > 0.0) {
                    (1, 1)
                } else {
                    (-1, 1)
                };
                let j1 = (i as isize + dy * w as isize + dx) as usize;
                let j2 = (i as isize - dy * w as isize - dx) as usize;
                if m >= self.mag[j1] && m > self.mag[j2] {
                    self.edge[i] = true;
                    count += 1;
                }
            }
        }
        // Gradient directions, at edge pixels only.
        for i in 0..w * h {
            if self.edge[i] {
                self.gdir[i] = self.gdir[i].atan2(self.gx[i]);
            }
        }
        self.edge_count = count;
        self.transform();
        Ok(())
    }

    /// Edges given by the caller (`edges[i]` nonzero at an edge pixel, row-major) with no
    /// direction (the paper's Canny output); then the distance field. Allocation-free.
    pub fn set_edges(&mut self, edges: &[u8]) -> Result<(), ImageError> {
        let (w, h) = (self.width, self.height);
        if edges.len() != w * h {
            return Err(ImageError::Size { len: edges.len(), width: w, height: h, channels: 1 });
        }
        let mut count = 0;
        for (e, &v) in self.edge.iter_mut().zip(edges) {
            *e = v != 0;
            count += usize::from(v != 0);
        }
        self.gdir.fill(0.0);
        self.edge_count = count;
        self.transform();
        Ok(())
    }

    /// Distance (pixels) to the nearest edge from pixel `(x, y)` and that edge's gradient
    /// direction (radians, image `x` right, `y` down); `None` outside the image or without
    /// edges.
    #[inline]
    pub fn lookup(&self, x: f64, y: f64) -> Option<(f32, f32)> {
        let (xi, yi) = (x.round(), y.round());
        if !(xi >= 0.0 && yi >= 0.0 && xi < self.width as f64 && yi < self.height as f64) {
            return None;
        }
        let i = yi as usize * self.width + xi as usize;
        let n = *self.nearest.get(i)?;
        let dir = *self.gdir.get(n as usize)?;
        Some((self.dist[i], dir))
    }

    /// Distance only (pixels), `None` outside the image.
    #[inline]
    pub fn distance(&self, xi: usize, yi: usize) -> Option<f32> {
        if xi >= self.width || yi >= self.height {
            return None;
        }
        self.dist.get(yi * self.width + xi).copied()
    }

    fn transform(&mut self) {
        let (w, h) = (self.width, self.height);
        // Pass 1, along columns, row by row (cache friendly): distance to the nearest edge in
        // the same column, and its row.
        for x in 0..w {
            let (d, r) = if self.edge[x] { (0.0, 0) } else { (BIG, u32::MAX) };
            self.col_d[x] = d;
            self.col_row[x] = r;
        }
        for y in 1..h {
            for x in 0..w {
                let i = y * w + x;
                if self.edge[i] {
                    self.col_d[i] = 0.0;
                    self.col_row[i] = y as u32;
                } else {
                    let p = i - w;
                    self.col_d[i] = if self.col_d[p] >= BIG { BIG } else { self.col_d[p] + 1.0 };
                    self.col_row[i] = self.col_row[p];
                }
            }
        }
        for y in (0..h - 1).rev() {
            for x in 0..w {
                let i = y * w + x;
                let n = i + w;
                if self.col_d[n] < BIG && self.col_d[n] + 1.0 < self.col_d[i] {
                    self.col_d[i] = self.col_d[n] + 1.0;
                    self.col_row[i] = self.col_row[n];
                }
            }
        }
        // Pass 2, along rows: lower envelope of the parabolas (q − x)² + g(q)².
        let (v, z) = (&mut self.env_v, &mut self.env_z);
        for y in 0..h {
            let row = y * w;
            let f = |q: usize| {
                let d = self.col_d[row + q];
                if d >= BIG { BIG } else { d * d }
            };
            let mut k = 0usize;
            v[0] = 0;
            z[0] = f32::NEG_INFINITY;
            z[1] = f32::INFINITY;
            for q in 1..w {
                let fq = f(q);
                loop {
                    let p = v[k] as usize;
                    let s = ((fq + (q * q) as f32) - (f(p) + (p * p) as f32)) / (2.0 * (q as f32 - p as f32));
                    if s <= z[k] && k > 0 {
                        k -= 1;
                        continue;
                    }
                    k += 1;
                    v[k] = q as u32;
                    z[k] = s;
                    z[k + 1] = f32::INFINITY;
                    break;
                }
            }
            let mut k = 0usize;
            for x in 0..w {
                while z[k + 1] < x as f32 {
                    k += 1;
                }
                let q = v[k] as usize;
                let fq = f(q);
                let i = row + x;
                if fq >= BIG {
                    self.dist[i] = f32::INFINITY;
                    self.nearest[i] = u32::MAX;
                } else {
                    let dx = x as f32 - q as f32;
                    self.dist[i] = (dx * dx + fq).sqrt();
                    self.nearest[i] = self.col_row[row + q] * w as u32 + q as u32;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brute(edges: &[bool], w: usize, h: usize, x: usize, y: usize) -> f32 {
        let mut best = f32::INFINITY;
        for j in 0..h {
            for i in 0..w {
                if edges[j * w + i] {
                    let d = ((i as f32 - x as f32).powi(2) + (j as f32 - y as f32).powi(2)).sqrt();
                    best = best.min(d);
                }
            }
        }
        best
    }

    /// A 64×64 frame: noise of ±`noise` grey levels and a vertical step of `step` levels at
    /// `x = 32`.
    fn step_frame(step: u8, noise: u8) -> Vec<u8> {
        let (w, h) = (64usize, 64usize);
        let mut s = 12_345u32;
        let mut rgb = vec![0u8; w * h * 3];
        for y in 0..h {
            for x in 0..w {
                s ^= s << 13;
                s ^= s >> 17;
                s ^= s << 5;
                let v = 100 + if x >= 32 { step } else { 0 } + (s % (2 * u32::from(noise) + 1)) as u8;
                rgb[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&[v, v, v]);
            }
        }
        rgb
    }

    #[test]
    fn the_contrast_adaptive_threshold_finds_a_faded_step_and_keeps_a_clear_frames() {
        let c = EdgeContrast { reference_px: 75.0, noise_factor: 2.5 };
        let on_step = |f: &EdgeField| (2..62).filter(|&y| (30..34).any(|x| f.edges()[y * 64 + x])).count();
        let off_step = |f: &EdgeField| {
            (2..62).map(|y| (2..28).chain(36..62).filter(|&x| f.edges()[y * 64 + x]).count()).sum::<usize>()
        };
        let mut f = EdgeField::new(64, 64);
        // Clear: a step of 40 levels (Sobel magnitude 160) keeps the fixed threshold.
        f.compute_ours_adaptive(&step_frame(40, 2), 60.0, Some(c)).unwrap();
        assert_eq!(f.threshold_used(), 60.0);
        assert!(on_step(&f) >= 58);
        // Faded to 8 levels (magnitude 32, under 60): the fixed threshold loses it, the
        // adaptive one finds it without taking the noise.
        f.compute_ours(&step_frame(8, 2), 60.0).unwrap();
        assert_eq!(on_step(&f), 0);
        f.compute_ours_adaptive(&step_frame(8, 2), 60.0, Some(c)).unwrap();
        assert!(f.threshold_used() < 32.0, "threshold {}", f.threshold_used());
        assert!(on_step(&f) >= 58, "{} rows with the step", on_step(&f));
        assert!(off_step(&f) < 20, "{} noise edges", off_step(&f));
        // A frame of noise alone: the floor (2.5 × the median) keeps the noise out.
        f.compute_ours_adaptive(&step_frame(0, 6), 60.0, Some(c)).unwrap();
        assert!(off_step(&f) < 40, "{} noise edges at threshold {}", off_step(&f), f.threshold_used());
    }

    #[test]
    fn distance_transform_matches_brute_force_and_points_at_an_edge() {
        let (w, h) = (23, 17);
        let mut e = vec![0u8; w * h];
        for &(x, y) in &[(3usize, 4usize), (20, 1), (11, 15), (12, 8), (0, 16)] {
            e[y * w + x] = 1;
        }
        let mut f = EdgeField::new(w, h);
        f.set_edges(&e).unwrap();
        for y in 0..h {
            for x in 0..w {
                let d = f.distance(x, y).unwrap();
                let b = brute(f.edges(), w, h, x, y);
                assert!((d - b).abs() < 1e-4, "({x},{y}) {d} vs {b}");
                let n = f.nearest[y * w + x] as usize;
                assert!(f.edges()[n]);
            }
        }
    }

    #[test]
    fn no_edges_means_infinite_distance_and_wrong_sizes_are_errors() {
        let mut f = EdgeField::new(8, 8);
        f.set_edges(&[0u8; 64]).unwrap();
        assert_eq!(f.distance(3, 3), Some(f32::INFINITY));
        assert!(matches!(f.set_edges(&[0u8; 63]), Err(ImageError::Size { .. })));
        assert!(matches!(f.compute_ours(&[0u8; 64], 10.0), Err(ImageError::Size { .. })));
        assert_eq!(f.lookup(-1.0, 2.0), None);
        assert_eq!(f.lookup(f64::NAN, 2.0), None);
    }

    #[test]
    fn a_vertical_step_gives_a_vertical_edge_with_horizontal_gradient() {
        let (w, h) = (32, 24);
        let mut rgb = vec![0u8; w * h * 3];
        for y in 0..h {
            for x in 16..w {
                rgb[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&[200, 200, 200]);
            }
        }
        let mut f = EdgeField::new(w, h);
        f.compute_ours(&rgb, 100.0).unwrap();
        assert!(f.edge_count() >= h - 2);
        let (d, dir) = f.lookup(5.0, 12.0).unwrap();
        assert!((9.0..=11.0).contains(&d), "{d}");
        assert!(dir.cos().abs() > 0.99, "{dir}");
    }
}
