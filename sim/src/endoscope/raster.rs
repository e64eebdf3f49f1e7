//! Z-buffered triangle rasterisation (ours): near-plane clipping in the camera frame,
//! pinhole projection onto the *canvas* (the undistorted image, possibly larger than the
//! output so that distortion can be applied afterwards), edge functions over the triangle's
//! bounding box, perspective-correct depth and attributes.
//!
//! Conventions: pixel centres at integer canvas coordinates (OpenCV: the centre of the
//! top-left pixel is `(0, 0)`); a pixel is covered when its centre is inside or on the edge
//! of the triangle; the depth buffer holds the camera-frame `z` (metres), nearer wins
//! (strictly).

/// The canvas: a pinhole image in ideal (undistorted) pixels, offset by `(ox, oy)`: canvas
/// pixel `(x, y)` is ideal pixel `(x + ox, y + oy)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Canvas {
    /// Width, pixels.
    pub w: usize,
    /// Height, pixels.
    pub h: usize,
    /// Offset of the canvas origin in ideal pixels (≤ 0 when the canvas is larger than the
    /// image).
    pub ox: f32,
    /// Offset along v, ideal pixels.
    pub oy: f32,
    /// Focal length u, pixels.
    pub fx: f32,
    /// Focal length v, pixels.
    pub fy: f32,
    /// Skew, pixels.
    pub skew: f32,
    /// Principal point u, ideal pixels.
    pub cx: f32,
    /// Principal point v, ideal pixels.
    pub cy: f32,
}

/// Nearest depth drawn, metres: triangles are clipped at `z = NEAR_M`.
pub const NEAR_M: f32 = 1e-3;

/// A vertex in the camera frame (metres) with `N` attributes.
#[derive(Clone, Copy, Debug)]
pub struct Vtx<const N: usize> {
    /// Position in the camera frame, metres.
    pub p: [f32; 3],
    /// Attributes (interpolated perspective-correctly).
    pub a: [f32; N],
}

impl Canvas {
    /// Camera-frame ray `(x/z, y/z)` of the centre of canvas pixel `(x, y)`.
    #[inline]
    pub fn ray(&self, x: f32, y: f32) -> (f32, f32) {
        let yn = (y + self.oy - self.cy) / self.fy;
        let xn = (x + self.ox - self.cx - self.skew * yn) / self.fx;
        (xn, yn)
    }

    #[inline]
    fn project(&self, p: &[f32; 3]) -> (f64, f64, f64) {
        let iz = 1.0 / p[2] as f64;
        let (xn, yn) = (p[0] as f64 * iz, p[1] as f64 * iz);
        let (fx, fy, s) = (self.fx as f64, self.fy as f64, self.skew as f64);
        (fx * xn + s * yn + self.cx as f64 - self.ox as f64, fy * yn + self.cy as f64 - self.oy as f64, iz)
    }
}

fn lerp_vtx<const N: usize>(a: &Vtx<N>, b: &Vtx<N>, t: f32) -> Vtx<N> {
    let mut out = *a;
    for k in 0..3 {
        out.p[k] = a.p[k] + (b.p[k] - a.p[k]) * t;
    }
    for k in 0..N {
        out.a[k] = a.a[k] + (b.a[k] - a.a[k]) * t;
    }
    out
}

/// Touched region (inclusive pixel bounds) of what was drawn, to limit later passes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Bounds {
    /// First column.
    pub x0: usize,
    /// First row.
    pub y0: usize,
    /// Last column.
    pub x1: usize,
    /// Last row.
    pub y1: usize,
}

impl Default for Bounds {
    /// Nothing drawn ([`Bounds::EMPTY`]).
    fn default() -> Self {
        Bounds::EMPTY
    }
}

impl Bounds {
    /// Nothing drawn.
    pub const EMPTY: Bounds = Bounds { x0: usize::MAX, y0: usize::MAX, x1: 0, y1: 0 };

    /// True when nothing was drawn.
    pub fn is_empty(&self) -> bool {
        self.x0 > self.x1 || self.y0 > self.y1
    }

    fn add(&mut self, x0: usize, y0: usize, x1: usize, y1: usize) {
        self.x0 = self.x0.min(x0);
        self.y0 = self.y0.min(y0);
        self.x1 = self.x1.max(x1);
        self.y1 = self.y1.max(y1);
    }

    /// Union.
    pub fn union(&self, o: &Bounds) -> Bounds {
        let mut b = *self;
        if !o.is_empty() {
            b.add(o.x0, o.y0, o.x1, o.y1);
        }
        b
    }
}

/// Draws one triangle: clips it at [`NEAR_M`], culls it when `cull_back` and it faces away
/// (counter-clockwise faces seen from outside are front faces), and calls
/// `frag(index, x, y, z, attributes)` for every covered pixel that passes (and updates) the depth
/// test. `bounds` grows by the bounding box of what was rasterised.
pub fn draw_triangle<const N: usize>(
    c: &Canvas,
    depth: &mut [f32],
    tri: &[Vtx<N>; 3],
    cull_back: bool,
    bounds: &mut Bounds,
    frag: &mut impl FnMut(usize, usize, usize, f32, &[f32; N]),
) {
    if cull_back {
        let [a, b, d] = [tri[0].p, tri[1].p, tri[2].p];
        let e1 = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let e2 = [d[0] - a[0], d[1] - a[1], d[2] - a[2]];
        let n = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]];
        if n[0] * a[0] + n[1] * a[1] + n[2] * a[2] >= 0.0 {
            return;
        }
    }
    let inside = tri.map(|v| v.p[2] >= NEAR_M);
    if inside.iter().all(|&i| i) {
        raster(c, depth, tri, bounds, frag);
        return;
    }
    if !inside.iter().any(|&i| i) {
        return;
    }
    // Sutherland-Hodgman against z = NEAR_M: at most 4 vertices.
    let mut poly: [Vtx<N>; 4] = [tri[0]; 4];
    let mut n = 0;
    for i in 0..3 {
        let (a, b) = (&tri[i], &tri[(i + 1) % 3]);
        let (ia, ib) = (inside[i], inside[(i + 1) % 3]);
        if ia {
            poly[n] = *a;
            n += 1;
        }
        if ia != ib {
            let t = (NEAR_M - a.p[2]) / (b.p[2] - a.p[2]);
            poly[n] = lerp_vtx(a, b, t);
            n += 1;
        }
    }
    for k in 1..n.saturating_sub(1) {
        raster(c, depth, &[poly[0], poly[k], poly[k + 1]], bounds, frag);
    }
}

fn raster<const N: usize>(
    c: &Canvas,
    depth: &mut [f32],
    tri: &[Vtx<N>; 3],
    bounds: &mut Bounds,
    frag: &mut impl FnMut(usize, usize, usize, f32, &[f32; N]),
) {
    // Screen coordinates in f64: a triangle clipped at the near plane can project thousands
    // of pixels away, where f32 edge functions would lose the pixel.
    let (x0, y0, w0) = c.project(&tri[0].p);
    let (mut x1, mut y1, mut w1) = c.project(&tri[1].p);
    let (mut x2, mut y2, mut w2) = c.project(&tri[2].p);
    let mut a1 = tri[1].a;
    let mut a2 = tri[2].a;
    let mut area = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0);
    if area.is_nan() || area.abs() <= 1e-12 {
        return; // degenerate or not finite
    }
    if area < 0.0 {
        std::mem::swap(&mut x1, &mut x2);
        std::mem::swap(&mut y1, &mut y2);
        std::mem::swap(&mut w1, &mut w2);
        std::mem::swap(&mut a1, &mut a2);
        area = -area;
    }
    let (minx, maxx) = (x0.min(x1).min(x2), x0.max(x1).max(x2));
    let (miny, maxy) = (y0.min(y1).min(y2), y0.max(y1).max(y2));
    let (wmax, hmax) = ((c.w - 1) as f64, (c.h - 1) as f64);
    if maxx < 0.0 || maxy < 0.0 || minx > wmax || miny > hmax {
        return;
    }
    let bx0 = minx.max(0.0).ceil() as usize;
    let by0 = miny.max(0.0).ceil() as usize;
    let bx1 = maxx.min(wmax).floor() as usize;
    let by1 = maxy.min(hmax).floor() as usize;
    if bx0 > bx1 || by0 > by1 {
        return;
    }
    let inv_area = 1.0 / area;
    // Edge function of the edge opposite vertex i, e_i = A_i x + B_i y + C_i, ≥ 0 inside.
    let coef = |ax: f64, ay: f64, bx: f64, by: f64| (-(by - ay), bx - ax, (by - ay) * ax - (bx - ax) * ay);
    let e = [coef(x1, y1, x2, y2), coef(x2, y2, x0, y0), coef(x0, y0, x1, y1)];
    // 1/z and the attributes pre-multiplied by 1/z are affine in the pixel: with the
    // barycentrics b_i = e_i / area, q(x, y) = Σ b_i q_i. Their x gradients, per pixel:
    let ws = [w0, w1, w2];
    let a0 = tri[0].a;
    let mut pa = [[0.0f64; N]; 3];
    for k in 0..N {
        pa[0][k] = a0[k] as f64 * w0;
        pa[1][k] = a1[k] as f64 * w1;
        pa[2][k] = a2[k] as f64 * w2;
    }
    let g = [e[0].0 * inv_area, e[1].0 * inv_area, e[2].0 * inv_area];
    let giz = g[0] * w0 + g[1] * w1 + g[2] * w2;
    let mut ga = [0.0f32; N];
    for k in 0..N {
        ga[k] = (g[0] * pa[0][k] + g[1] * pa[1][k] + g[2] * pa[2][k]) as f32;
    }
    let inside =
        |px: f64, r: &[f64; 3]| e[0].0 * px + r[0] >= 0.0 && e[1].0 * px + r[1] >= 0.0 && e[2].0 * px + r[2] >= 0.0;
    let mut touched = false;
    for y in by0..=by1 {
        let py = y as f64;
        // The row's span where all three edge functions are ≥ 0.
        let (mut lo, mut hi) = (bx0 as f64, bx1 as f64);
        let mut r = [0.0f64; 3];
        for i in 0..3 {
            let (a, b, cc) = e[i];
            r[i] = b * py + cc;
            if a > 0.0 {
                lo = lo.max(-r[i] / a);
            } else if a < 0.0 {
                hi = hi.min(-r[i] / a);
            } else if r[i] < 0.0 {
                hi = -1.0;
            }
        }
        if lo.is_nan() || hi.is_nan() || lo > hi {
            continue;
        }
        // bx0 ≤ lo ≤ hi ≤ bx1 here (neither is NaN): ⌈lo⌉ and ⌊hi⌋ of non-negative numbers
        // by truncation (baseline x86-64 has no rounding instruction; `ceil` is a call).
        let (lt, ht) = (lo as usize, hi as usize);
        let (mut xs, mut xe) = ((lt + ((lt as f64) < lo) as usize).max(bx0), ht.min(bx1));
        // The computed edge functions are monotone in x (rounding is monotone), so the covered
        // pixels of the row are an interval: trim its ends with the exact per-pixel test.
        while xs <= xe && !inside(xs as f64, &r) {
            xs += 1;
        }
        while xe > xs && !inside(xe as f64, &r) {
            xe -= 1;
        }
        if xs > xe {
            continue;
        }
        // 1/z and the pre-multiplied attributes at the span's first pixel.
        let px = xs as f64;
        let b = [(e[0].0 * px + r[0]) * inv_area, (e[1].0 * px + r[1]) * inv_area, (e[2].0 * px + r[2]) * inv_area];
        let iz0 = b[0] * ws[0] + b[1] * ws[1] + b[2] * ws[2];
        let mut q0 = [0.0f32; N];
        for k in 0..N {
            q0[k] = (b[0] * pa[0][k] + b[1] * pa[1][k] + b[2] * pa[2][k]) as f32;
        }
        let row = y * c.w;
        // By chunks of the span: the depths first (independent divisions, off the per-pixel
        // path), then the depth test and the fragments. Pixel offsets from the span's start
        // are exact integers in f64 and f32.
        const CHUNK: usize = 32;
        let mut zs = [0.0f32; CHUNK];
        for (ci, chunk) in depth[row + xs..=row + xe].chunks_mut(CHUNK).enumerate() {
            let base = ci * CHUNK;
            for (k, zo) in zs.iter_mut().enumerate().take(chunk.len()) {
                *zo = (1.0 / (iz0 + giz * (base + k) as f64)) as f32;
            }
            for (k, (d, &z)) in chunk.iter_mut().zip(&zs).enumerate() {
                if z < *d && z >= NEAR_M * 0.999 {
                    touched = true;
                    *d = z;
                    let dxf = (base + k) as f32;
                    let mut at = [0.0f32; N];
                    for j in 0..N {
                        at[j] = (q0[j] + ga[j] * dxf) * z;
                    }
                    let x = xs + base + k;
                    frag(row + x, x, y, z, &at);
                }
            }
        }
    }
    if touched {
        bounds.add(bx0, by0, bx1, by1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn canvas() -> Canvas {
        Canvas { w: 64, h: 48, ox: 0.0, oy: 0.0, fx: 50.0, fy: 50.0, skew: 0.0, cx: 31.5, cy: 23.5 }
    }

    #[test]
    fn depth_is_perspective_correct_and_nearer_wins() {
        let c = canvas();
        let mut depth = vec![f32::INFINITY; c.w * c.h];
        let mut got = vec![0.0f32; c.w * c.h];
        // A slanted plane z = 1 + x: depth at every covered pixel must be the plane's depth
        // along that pixel's ray, and the attribute (= x) the ray's x.
        let v = |x: f32, y: f32| Vtx { p: [x, y, 1.0 + x], a: [x] };
        let tri = [v(-0.5, -0.5), v(0.5, -0.5), v(0.0, 0.5)];
        let mut b = Bounds::EMPTY;
        draw_triangle(&c, &mut depth, &tri, false, &mut b, &mut |i, _, _, _z, a| got[i] = a[0]);
        let mut n = 0;
        for y in 0..c.h {
            for x in 0..c.w {
                let i = y * c.w + x;
                if depth[i].is_finite() {
                    n += 1;
                    let (xn, _) = c.ray(x as f32, y as f32);
                    // z = 1 + X, X = xn z  =>  z = 1 / (1 - xn)
                    let z = 1.0 / (1.0 - xn);
                    assert!((depth[i] - z).abs() < 1e-4 * z, "{} vs {z}", depth[i]);
                    assert!((got[i] - xn * z).abs() < 1e-4);
                }
            }
        }
        assert!(n > 100);
        // A nearer triangle replaces, a farther one does not.
        let before = depth.clone();
        let far = [
            Vtx { p: [-5.0, -5.0, 9.0], a: [0.0] },
            Vtx { p: [5.0, -5.0, 9.0], a: [0.0] },
            Vtx { p: [0.0, 5.0, 9.0], a: [0.0] },
        ];
        draw_triangle(&c, &mut depth, &far, false, &mut b, &mut |_, _, _, _, _| {});
        for (a, b) in before.iter().zip(&depth) {
            if a.is_finite() {
                assert_eq!(a, b);
            }
        }
    }

    #[test]
    fn near_plane_clipping_and_culling() {
        let c = canvas();
        let mut depth = vec![f32::INFINITY; c.w * c.h];
        let mut b = Bounds::EMPTY;
        // A triangle crossing the camera plane: no NaN, only depths ≥ NEAR_M.
        let tri =
            [Vtx { p: [-0.2, 0.0, -0.5], a: [] }, Vtx { p: [0.2, 0.0, 0.5], a: [] }, Vtx { p: [0.0, 0.2, 0.5], a: [] }];
        draw_triangle(&c, &mut depth, &tri, false, &mut b, &mut |_, _, _, _, _| {});
        assert!(depth.iter().all(|d| d.is_infinite() || (*d >= NEAR_M * 0.99 && d.is_finite())));
        // Back face: seen from the camera the vertices go clockwise.
        let mut d2 = vec![f32::INFINITY; c.w * c.h];
        let front = [
            Vtx { p: [-0.1, -0.1, 1.0], a: [] },
            Vtx { p: [0.0, 0.1, 1.0], a: [] },
            Vtx { p: [0.1, -0.1, 1.0], a: [] },
        ];
        let back = [front[0], front[2], front[1]];
        let mut hits = [0usize; 2];
        draw_triangle(&c, &mut d2, &front, true, &mut b, &mut |_, _, _, _, _| hits[0] += 1);
        let mut d3 = vec![f32::INFINITY; c.w * c.h];
        draw_triangle(&c, &mut d3, &back, true, &mut b, &mut |_, _, _, _, _| hits[1] += 1);
        assert!(hits[0] > 0 && hits[1] == 0, "{hits:?}");
    }
}
