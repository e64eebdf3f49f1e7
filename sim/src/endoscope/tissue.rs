//! The tissue: a procedural height field (folds) in the world frame `{e}` with a procedural
//! texture (value-noise tones from pink to red, fat patches, speckle, darker creases and a
//! branching vessel network), both computed once per seed.
//!
//! The surface faces the endoscope: `z(x, y) = plane_z − amplitude·(h(x, y) − ½)` in `{e}`
//! (metres), `h ∈ [0, 1]` a ridged multi-octave value noise, so folds rise toward the camera.
//! Texture coordinates are `((x − x0)/extent, (y − y0)/extent)` over the square patch, so
//! both eyes see the same texel at the same world point.

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::config::TissueConfig;

/// Flat albedo when the texture is off (linear RGB).
pub const FLAT_ALBEDO: [f32; 3] = [0.55, 0.16, 0.13];

/// Deterministic lattice value noise (our own; a hash of the seed and the lattice point).
#[derive(Clone, Copy, Debug)]
struct ValueNoise {
    seed: u64,
}

fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

impl ValueNoise {
    fn lattice(&self, ix: i64, iy: i64) -> f64 {
        let h = splitmix(self.seed ^ splitmix((ix as u64).wrapping_mul(0x1_0000_01B3) ^ (iy as u64) << 32));
        (h >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Smoothly interpolated noise in `[0, 1]`, one lattice cell per unit.
    fn value(&self, x: f64, y: f64) -> f64 {
        let (fx, fy) = (x.floor(), y.floor());
        let (ix, iy) = (fx as i64, fy as i64);
        let (tx, ty) = (x - fx, y - fy);
        let s = |t: f64| t * t * (3.0 - 2.0 * t);
        let (sx, sy) = (s(tx), s(ty));
        let a = self.lattice(ix, iy) + (self.lattice(ix + 1, iy) - self.lattice(ix, iy)) * sx;
        let b = self.lattice(ix, iy + 1) + (self.lattice(ix + 1, iy + 1) - self.lattice(ix, iy + 1)) * sx;
        a + (b - a) * sy
    }

    /// Fractal sum of `octaves` octaves (gain ½, lacunarity 2), normalised to `[0, 1]`.
    fn fbm(&self, x: f64, y: f64, octaves: u32) -> f64 {
        let (mut sum, mut amp, mut norm, mut f) = (0.0, 1.0, 0.0, 1.0);
        for o in 0..octaves {
            let n = ValueNoise { seed: self.seed.wrapping_add(o as u64 * 7919) };
            sum += amp * n.value(x * f, y * f);
            norm += amp;
            amp *= 0.5;
            f *= 2.0;
        }
        sum / norm
    }
}

/// The fold height field `h ∈ [0, 1]` at patch coordinates `(s, t) ∈ [0, 1]²`.
#[derive(Clone, Copy, Debug)]
struct Folds {
    ridge: ValueNoise,
    soft: ValueNoise,
}

impl Folds {
    fn new(seed: u64) -> Self {
        Self { ridge: ValueNoise { seed: splitmix(seed ^ 0xF01D) }, soft: ValueNoise { seed: splitmix(seed ^ 0x50F7) } }
    }

    fn height(&self, s: f64, t: f64) -> f64 {
        let r = 1.0 - (2.0 * self.ridge.fbm(s * 3.0, t * 3.0, 3) - 1.0).abs();
        (0.65 * r * r + 0.35 * self.soft.fbm(s * 5.0 + 11.0, t * 5.0, 3)).clamp(0.0, 1.0)
    }
}

/// The tissue, ready to render: mesh in `{e}` and texture.
#[derive(Clone, Debug)]
pub struct Tissue {
    /// Vertex positions in `{e}`, metres.
    pub positions: Vec<Vector3<f64>>,
    /// Unit normals in `{e}` (toward the endoscope side, `−z`).
    pub normals: Vec<Vector3<f64>>,
    /// Texture coordinates in `[0, 1]²`.
    pub uv: Vec<[f32; 2]>,
    /// Triangles.
    pub triangles: Vec<[u32; 3]>,
    /// Texture side, texels.
    pub texture_px: usize,
    /// Linear albedo per texel (RGB ×255, A unused), row-major, `v` down the rows.
    pub texture: Vec<[u8; 4]>,
    /// The same texels as little-endian `u32` (R in the low byte; half the memory of one
    /// 16-bit lane per channel: the lookup widens them), for bilinear lookups four channels
    /// at a time; one more column and row repeat the last ones, so that the four texels of
    /// a lookup are always there (`(texture_px + 1)²` entries).
    packed: Vec<u32>,
    /// `texture_px` and `(texture_px − 1)·256` as floats (the lookup's constants).
    n_f32: f32,
    max_f32: f32,
}

impl Tissue {
    /// Builds mesh and texture from the configuration and seed (deterministic; a 1024² texture
    /// takes some 0.1-0.3 s, once).
    pub fn new(cfg: &TissueConfig, seed: u64, textured: bool) -> Self {
        let folds = Folds::new(seed);
        let n = cfg.grid;
        let x0 = -cfg.extent_m / 2.0;
        let step = cfg.extent_m / n as f64;
        let z_at = |s: f64, t: f64| cfg.plane_z_m - cfg.fold_amplitude_m * (folds.height(s, t) - 0.5);
        let mut positions = Vec::with_capacity((n + 1) * (n + 1));
        let mut normals = Vec::with_capacity((n + 1) * (n + 1));
        let mut uv = Vec::with_capacity((n + 1) * (n + 1));
        let ds = 0.5 / n as f64;
        for j in 0..=n {
            for i in 0..=n {
                let (s, t) = (i as f64 / n as f64, j as f64 / n as f64);
                positions.push(Vector3::new(x0 + i as f64 * step, x0 + j as f64 * step, z_at(s, t)));
                // Normal of z = f(x, y) toward −z: (∂f/∂x, ∂f/∂y, −1), central differences.
                let dzdx = (z_at(s + ds, t) - z_at(s - ds, t)) / (2.0 * ds * cfg.extent_m);
                let dzdy = (z_at(s, t + ds) - z_at(s, t - ds)) / (2.0 * ds * cfg.extent_m);
                normals.push(Vector3::new(dzdx, dzdy, -1.0).normalize());
                uv.push([s as f32, t as f32]);
            }
        }
        let mut triangles = Vec::with_capacity(2 * n * n);
        let w = (n + 1) as u32;
        for j in 0..n as u32 {
            for i in 0..n as u32 {
                let a = j * w + i;
                triangles.push([a, a + 1, a + w + 1]);
                triangles.push([a, a + w + 1, a + w]);
            }
        }
        let texture_px = if textured { cfg.texture_px } else { 1 };
        let texture = if textured {
            texture(cfg.texture_px, seed, &folds)
        } else {
            let c = FLAT_ALBEDO.map(|c| (c * 255.0).round() as u8);
            vec![[c[0], c[1], c[2], 255]]
        };
        let mut packed = Vec::with_capacity((texture_px + 1) * (texture_px + 1));
        for j in 0..=texture_px {
            let row = &texture[j.min(texture_px - 1) * texture_px..][..texture_px];
            packed.extend(row.iter().map(|t| u32::from_le_bytes(*t)));
            packed.push(u32::from_le_bytes(row[texture_px - 1]));
        }
        let (n_f32, max_f32) = (texture_px as f32, ((texture_px - 1) * 256) as f32);
        Self { positions, normals, uv, triangles, texture_px, texture, packed, n_f32, max_f32 }
    }

    /// Bilinear albedo (linear RGB) at texture coordinates `(s, t)` (clamped to the edge);
    /// 8-bit weights, the four channels in one integer operation (on x86-64, the two
    /// texture coordinates and the four texels in SSE2 registers: the same numbers).
    #[inline(always)]
    pub fn albedo(&self, s: f32, t: f32) -> [f32; 3] {
        let n = self.texture_px;
        // In 1/256 texel, clamped to the edge texels' centres: the integer part is the texel,
        // the low byte the weight. The same numbers as clamping x = s·n − ½ to [0, n − 1]
        // first (x·256 is exact in f32, truncation sends (−1, 0) to 0, NaN goes to 0).
        let (fx, fy) = fixed_coords(s, t, n, self.n_f32, self.max_f32);
        let (ix, iy) = ((fx >> 8) as usize, (fy >> 8) as usize);
        let (wx, wy) = (fx & 0xFF, fy & 0xFF);
        // The four texels (the padding column and row stand in at the edges, with weight 0).
        let stride = n + 1;
        let i = iy * stride + ix;
        let (top, bot) = self.packed[i..i + stride + 2].split_at(stride);
        // Two neighbouring texels in one 64-bit word (the left one in the low half).
        let pair = |p: &[u32]| p[0] as u64 | (p[1] as u64) << 32;
        bilerp(pair(top), pair(bot), wx, wy)
    }
}

const K_BYTE: f32 = 1.0 / 255.0;

/// `(s·n − ½)·256` and `(t·n − ½)·256` truncated toward zero, clamped to `[0, (n − 1)·256]`
/// (NaN to 0).
#[cfg(not(target_arch = "x86_64"))]
#[inline(always)]
fn fixed_coords(s: f32, t: f32, n: usize, _n_f32: f32, _max_f32: f32) -> (u32, u32) {
    let fix = |s: f32| ((s * n as f32 - 0.5) * 256.0) as i32;
    let max = (n as i32 - 1) * 256;
    (fix(s).clamp(0, max) as u32, fix(t).clamp(0, max) as u32)
}

/// [`fixed_coords`] on x86-64: both coordinates in one SSE2 register, clamped as floats
/// before the truncation (`maxps` sends NaN to 0; `(n − 1)·256` is an integer, so clamping
/// before or after truncating gives the same integer).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn fixed_coords(s: f32, t: f32, _n: usize, n_f32: f32, max_f32: f32) -> (u32, u32) {
    use std::arch::x86_64::{
        _mm_cvtsi128_si32, _mm_cvttps_epi32, _mm_max_ps, _mm_min_ps, _mm_mul_ps, _mm_set_ps, _mm_set1_ps,
        _mm_setzero_ps, _mm_shuffle_epi32, _mm_sub_ps,
    };
    // SAFETY: SSE2 is part of the x86-64 baseline (every x86_64 target enables it), and these
    // intrinsics only read and write registers.
    unsafe {
        let x = _mm_mul_ps(
            _mm_sub_ps(_mm_mul_ps(_mm_set_ps(0.0, 0.0, t, s), _mm_set1_ps(n_f32)), _mm_set1_ps(0.5)),
            _mm_set1_ps(256.0),
        );
        // `_mm_max_ps(x, 0)` returns 0 where x is NaN.
        let x = _mm_min_ps(_mm_max_ps(x, _mm_setzero_ps()), _mm_set1_ps(max_f32));
        let i = _mm_cvttps_epi32(x);
        (_mm_cvtsi128_si32(i) as u32, _mm_cvtsi128_si32(_mm_shuffle_epi32::<1>(i)) as u32)
    }
}

/// Bilinear blend of four texels with 8-bit weights, to linear RGB: `top` holds the top left
/// texel's RGBA bytes then the top right one's, `bot` the bottom ones.
#[cfg(not(target_arch = "x86_64"))]
#[inline(always)]
fn bilerp(top: u64, bot: u64, wx: u32, wy: u32) -> [f32; 3] {
    let texel = |pair: u64, k: u32| spread(((pair >> (32 * k)) as u32).to_le_bytes());
    let (a, b, c, d) = (texel(top, 0), texel(top, 1), texel(bot, 0), texel(bot, 1));
    let top = lerp_packed(a, b, wx);
    let bot = lerp_packed(c, d, wx);
    let c = lerp_packed(top, bot, wy);
    // Each lane holds a byte value: the low byte of the shifted lane is all of it.
    [c as u8 as f32 * K_BYTE, (c >> 16) as u8 as f32 * K_BYTE, (c >> 32) as u8 as f32 * K_BYTE]
}

/// [`bilerp`] on x86-64 with SSE2: the same per-lane integer operations as [`lerp_packed`]
/// (16-bit products and sums never exceed 255·256), two texels per register.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn bilerp(top: u64, bot: u64, wx: u32, wy: u32) -> [f32; 3] {
    use std::arch::x86_64::{
        _mm_add_epi16, _mm_cvtepi32_ps, _mm_cvtss_f32, _mm_mul_ps, _mm_mullo_epi16, _mm_set_epi64x, _mm_set1_epi16,
        _mm_set1_ps, _mm_setzero_si128, _mm_shuffle_ps, _mm_srli_epi16, _mm_unpackhi_epi8, _mm_unpackhi_epi64,
        _mm_unpacklo_epi8, _mm_unpacklo_epi16, _mm_unpacklo_epi64, _mm_xor_si128,
    };
    // SAFETY: SSE2 is part of the x86-64 baseline (every x86_64 target enables it), and these
    // intrinsics only read and write registers.
    unsafe {
        // [256 − w (4 lanes) | w (4 lanes)] = (w ^ [!0 | 0]) + [257 | 0] (two's complement:
        // !w + 257 = 256 − w).
        let flip = _mm_set_epi64x(0, -1);
        let base = _mm_set_epi64x(0, 0x0101_0101_0101_0101);
        let weights = |w: u32| _mm_add_epi16(_mm_xor_si128(_mm_set1_epi16(w as i16), flip), base);
        let wxv = weights(wx);
        // [a·(256 − wx) | b·wx] and [c·(256 − wx) | d·wx], lane by lane.
        // The four texels' bytes widened to 16-bit lanes: [a | b] and [c | d].
        let bytes = _mm_set_epi64x(bot as i64, top as i64);
        let (ab, cd) = (_mm_unpacklo_epi8(bytes, _mm_setzero_si128()), _mm_unpackhi_epi8(bytes, _mm_setzero_si128()));
        let pt = _mm_mullo_epi16(ab, wxv);
        let pb = _mm_mullo_epi16(cd, wxv);
        // [top | bottom] = (sums) >> 8.
        let tb = _mm_srli_epi16::<8>(_mm_add_epi16(_mm_unpacklo_epi64(pt, pb), _mm_unpackhi_epi64(pt, pb)));
        let p = _mm_mullo_epi16(tb, weights(wy));
        let v = _mm_srli_epi16::<8>(_mm_add_epi16(p, _mm_unpackhi_epi64(p, p)));
        let f = _mm_mul_ps(_mm_cvtepi32_ps(_mm_unpacklo_epi16(v, _mm_setzero_si128())), _mm_set1_ps(K_BYTE));
        [_mm_cvtss_f32(f), _mm_cvtss_f32(_mm_shuffle_ps::<1>(f, f)), _mm_cvtss_f32(_mm_shuffle_ps::<2>(f, f))]
    }
}

/// An RGBA texel with each 8-bit channel in its own 16-bit lane of a `u64` (R lowest).
#[cfg_attr(target_arch = "x86_64", allow(dead_code, reason = "the scalar fallback, and the tests' reference"))]
fn spread(t: [u8; 4]) -> u64 {
    t.iter().enumerate().fold(0u64, |acc, (k, &v)| acc | (v as u64) << (16 * k))
}

/// `⌊(a·(256 − w) + b·w) / 256⌋` on each lane of spread texels (`w ≤ 256`): the sums stay
/// below 2¹⁶, so the lanes never carry into each other.
#[cfg_attr(target_arch = "x86_64", allow(dead_code, reason = "the scalar fallback, and the tests' reference"))]
#[inline]
fn lerp_packed(a: u64, b: u64, w: u32) -> u64 {
    const LANES: u64 = 0x00FF_00FF_00FF_00FF;
    let (w, iw) = (w as u64, 256 - w as u64);
    ((a * iw + b * w) >> 8) & LANES
}

fn lerp3(a: [f64; 3], b: [f64; 3], t: f64) -> [f64; 3] {
    [a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, a[2] + (b[2] - a[2]) * t]
}

fn texture(n: usize, seed: u64, folds: &Folds) -> Vec<[u8; 4]> {
    let tone = ValueNoise { seed: splitmix(seed ^ 0x70E) };
    let fat = ValueNoise { seed: splitmix(seed ^ 0xFA7) };
    let speckle = ValueNoise { seed: splitmix(seed ^ 0x5BEC) };
    let pink = [0.62, 0.21, 0.18];
    let red = [0.42, 0.065, 0.055];
    let yellow = [0.72, 0.48, 0.20];
    let mut rgb = vec![[0.0f64; 3]; n * n];
    for j in 0..n {
        for i in 0..n {
            let (s, t) = ((i as f64 + 0.5) / n as f64, (j as f64 + 0.5) / n as f64);
            let mut c = lerp3(pink, red, tone.fbm(s * 9.0, t * 9.0, 4).powf(1.3) * 1.2);
            let f = fat.fbm(s * 5.0 + 3.0, t * 5.0, 3);
            if f > 0.68 {
                c = lerp3(c, yellow, ((f - 0.68) / 0.1).min(1.0) * 0.55);
            }
            let sp = 0.9 + 0.2 * speckle.fbm(s * 180.0, t * 180.0, 2);
            let crease = 0.55 + 0.45 * folds.height(s, t).sqrt();
            rgb[j * n + i] = c.map(|v| (v * sp * crease).clamp(0.0, 1.0));
        }
    }
    // Vessels: branching random walks, stamped as soft discs into an opacity map.
    let mut alpha = vec![0.0f64; n * n];
    let mut rng = ChaCha8Rng::seed_from_u64(splitmix(seed ^ 0x7E55E1));
    let scale = n as f64 / 1024.0;
    let mut stack: Vec<(f64, f64, f64, f64, u32)> = (0..14)
        .map(|_| {
            (
                rng.random_range(0.0..n as f64),
                rng.random_range(0.0..n as f64),
                rng.random_range(0.0..std::f64::consts::TAU),
                rng.random_range(2.2..4.2) * scale,
                0,
            )
        })
        .collect();
    let mut walks = 0;
    while let Some((mut x, mut y, mut heading, mut width, depth)) = stack.pop() {
        walks += 1;
        if walks > 400 {
            break;
        }
        for _ in 0..(900.0 * scale) as usize {
            if width < 0.5 * scale.max(0.6) || x < 0.0 || y < 0.0 || x >= n as f64 || y >= n as f64 {
                break;
            }
            let rr = width + 1.0;
            let (x0, x1) = ((x - rr).floor().max(0.0) as usize, ((x + rr).ceil() as usize).min(n - 1));
            let (y0, y1) = ((y - rr).floor().max(0.0) as usize, ((y + rr).ceil() as usize).min(n - 1));
            for py in y0..=y1 {
                for px in x0..=x1 {
                    let d = ((px as f64 + 0.5 - x).powi(2) + (py as f64 + 0.5 - y).powi(2)).sqrt();
                    let a = (width * 0.5 - d + 0.7).clamp(0.0, 1.0) * (0.55 + 0.1 * width.min(4.0));
                    let cell = &mut alpha[py * n + px];
                    *cell = cell.max(a);
                }
            }
            heading += rng.random_range(-0.18..0.18);
            x += heading.cos() * 1.5 * scale.max(0.5);
            y += heading.sin() * 1.5 * scale.max(0.5);
            width *= 0.9985;
            if depth < 4 && rng.random::<f64>() < 0.012 {
                let side = if rng.random::<bool>() { 1.0 } else { -1.0 };
                stack.push((x, y, heading + side * rng.random_range(0.4..1.1), width * 0.65, depth + 1));
                width *= 0.9;
            }
        }
    }
    let vessel = [0.22, 0.018, 0.03];
    rgb.iter()
        .zip(&alpha)
        .map(|(c, &a)| {
            let v = lerp3(*c, vessel, a.min(0.9));
            [(v[0] * 255.0).round() as u8, (v[1] * 255.0).round() as u8, (v[2] * 255.0).round() as u8, 255]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tissue_is_deterministic_and_seed_dependent() {
        let cfg = TissueConfig { texture_px: 128, grid: 8, ..TissueConfig::default() };
        let a = Tissue::new(&cfg, 3, true);
        let b = Tissue::new(&cfg, 3, true);
        let c = Tissue::new(&cfg, 4, true);
        assert_eq!(a.texture, b.texture);
        assert_ne!(a.texture, c.texture);
        assert_eq!(a.triangles.len(), 2 * 8 * 8);
        // Normals face the endoscope (−z) and the folds stay within the amplitude.
        for (p, nrm) in a.positions.iter().zip(&a.normals) {
            assert!(nrm.z < 0.0);
            assert!((p.z - cfg.plane_z_m).abs() <= cfg.fold_amplitude_m / 2.0 + 1e-12);
        }
        // Reddish on average: red channel dominates.
        let mean =
            a.texture.iter().fold([0u64; 3], |m, t| [m[0] + t[0] as u64, m[1] + t[1] as u64, m[2] + t[2] as u64]);
        assert!(mean[0] > 2 * mean[1] && mean[0] > 2 * mean[2], "{mean:?}");
        // The packed bilinear lookup reproduces the texels at their centres and blends between.
        let n = cfg.texture_px;
        for (i, j) in [(0usize, 0usize), (5, 9), (127, 64)] {
            let got = a.albedo((i as f32 + 0.5) / n as f32, (j as f32 + 0.5) / n as f32);
            let want = a.texture[j * n + i];
            for k in 0..3 {
                assert!((got[k] * 255.0 - want[k] as f32).abs() < 1.01, "{got:?} vs {want:?}");
            }
        }
        let mid = a.albedo(6.0 / n as f32, 9.5 / n as f32);
        let (l, r) = (a.texture[9 * n + 5], a.texture[9 * n + 6]);
        assert!((mid[0] * 255.0 - (l[0] as f32 + r[0] as f32) / 2.0).abs() < 1.01);
    }
}

#[cfg(test)]
mod lookup_tests {
    use super::*;

    /// The scalar reference of [`fixed_coords`].
    fn fixed_ref(s: f32, n: usize) -> u32 {
        let max = (n as i32 - 1) * 256;
        (((s * n as f32 - 0.5) * 256.0) as i32).clamp(0, max) as u32
    }

    #[test]
    fn the_lookup_matches_the_scalar_reference_bit_for_bit() {
        let n = 1024;
        let specials =
            [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -1e9, 1e9, -0.0, 0.0, 1.0, 0.5 / n as f32, 1.3, -0.2];
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let coords: Vec<f32> =
            specials.iter().copied().chain((0..2000).map(|_| rng.random_range(-0.1f32..1.1))).collect();
        for &s in &coords {
            let (nf, maxf) = (n as f32, ((n - 1) * 256) as f32);
            assert_eq!(fixed_coords(s, 0.25, n, nf, maxf).0, fixed_ref(s, n), "s = {s}");
            assert_eq!(fixed_coords(0.25, s, n, nf, maxf).1, fixed_ref(s, n), "t = {s}");
        }
        for _ in 0..20_000 {
            let t: [[u8; 4]; 4] = std::array::from_fn(|_| rng.random::<[u8; 4]>());
            let q = t.map(spread);
            let pair = |l: [u8; 4], r: [u8; 4]| u32::from_le_bytes(l) as u64 | (u32::from_le_bytes(r) as u64) << 32;
            let (wx, wy) = (rng.random_range(0..256u32), rng.random_range(0..256u32));
            let c = lerp_packed(lerp_packed(q[0], q[1], wx), lerp_packed(q[2], q[3], wx), wy);
            let want = [c as u8 as f32 * K_BYTE, (c >> 16) as u8 as f32 * K_BYTE, (c >> 32) as u8 as f32 * K_BYTE];
            let got = bilerp(pair(t[0], t[1]), pair(t[2], t[3]), wx, wy);
            assert_eq!(got.map(f32::to_bits), want.map(f32::to_bits));
        }
    }
}
