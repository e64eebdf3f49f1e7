//! The stereo renderer: per eye, tissue and instruments are rasterised onto the undistorted
//! canvas with forward Blinn-Phong shading (light at the endoscope tip, inverse-square
//! falloff, optional smoke), the instruments once per motion-blur instant and averaged; the
//! canvas is then warped through the lens distortion onto the image grid, defocused by depth,
//! vignetted, given sensor noise and encoded to 8-bit sRGB.
//!
//! The two eyes are rendered in parallel (rayon), each on its own buffers: the result does
//! not depend on the scheduling. Noise is drawn from ChaCha8 streams keyed by the seed, the
//! frame's mid time, the eye and the row: the same seed and times give the same bytes.
//! Nothing is allocated per frame once the first frames have sized the buffers (the ground
//! truth's small vectors aside).
//!
//! **The tissue is kept between frames.** Each eye keeps its rasterised and shaded tissue
//! (colour and depth on the canvas) with the eye pose it was seen from; the light is rigid
//! with the endoscope, the configuration and the tissue with the renderer. While the
//! endoscope arm holds still (the same joints bit for bit, hence the same eye poses), a frame
//! only puts back the tissue where the last frame's instruments were and draws the
//! instruments again, and the image pixels whose distortion taps read no pixel the
//! instruments covered take the tissue already warped: the bytes are those of a fresh
//! renderer (tested). Defocus, vignetting, noise and sRGB run on the whole image every frame.

use estimator::calib::Intrinsics;
use estimator::calib::rcm_arms::camera_pose;
use nalgebra::{Isometry3, Point3, Translation3, Vector2, Vector3};
use rand::{RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::config::{ConfigError, EndoscopeConfig, Material};
use super::mesh::{InstrumentMesh, Part};
use super::raster::{Bounds, Canvas, Vtx, draw_triangle};
use super::scene::{InstrumentState, SceneState};
use super::tissue::Tissue;
use super::truth::{EyeProjection, InstrumentTruth, PoseTruth, instrument_truth};

/// Which eye.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Eye {
    /// The left eye: the endoscope camera frame `{c}`.
    Left,
    /// The right eye: `{c}` shifted by the baseline along its `x`.
    Right,
}

impl Eye {
    /// Both eyes, left first.
    pub const BOTH: [Eye; 2] = [Eye::Left, Eye::Right];

    /// Short name (`left` / `right`).
    pub fn name(self) -> &'static str {
        match self {
            Eye::Left => "left",
            Eye::Right => "right",
        }
    }
}

/// Mask labels (one byte per pixel).
pub mod label {
    /// Tissue or nothing.
    pub const BACKGROUND: u8 = 0;
    /// The instrument.
    pub const INSTRUMENT: u8 = 1;
    /// The second instrument.
    pub const SECOND: u8 = 2;
    /// The occluder plate ([`super::Occluder`]).
    pub const OCCLUDER: u8 = 3;
}

/// A flat opaque plate between the camera and the instrument (a retracted tissue flap, a
/// gauze, a suction cannula's guard): the rectangle `|x| ≤ half_size_m[0]`, `|y| ≤
/// half_size_m[1]` of its own `z = 0` plane, seen from both sides, still during an exposure,
/// label [`label::OCCLUDER`] in the mask. The occlusion experiments of `docs/tracking.md`
/// place it with [`crate::world::OcclusionWindow`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Occluder {
    /// `T_e_o`: the plate's frame in the world `{e}`, metres.
    pub pose_world: Isometry3<f64>,
    /// Half width and half height of the plate, metres.
    pub half_size_m: [f64; 2],
    /// Its material.
    pub material: Material,
}

impl Occluder {
    /// A matte off-white plate (gauze-like).
    pub const GAUZE: Material = Material { diffuse: [0.16, 0.14, 0.13], specular: [0.04, 0.04, 0.04], shininess: 8.0 };

    /// True when the pose is finite, the sizes finite and positive and the material in range.
    pub fn is_valid(&self) -> bool {
        let t = self.pose_world.translation.vector;
        let q = self.pose_world.rotation.quaternion();
        let unit = |c: &[f64; 3]| c.iter().all(|v| v.is_finite() && (0.0..=1.0).contains(v));
        t.iter().all(|v| v.is_finite())
            && q.coords.iter().all(|v| v.is_finite())
            && self.half_size_m.iter().all(|v| v.is_finite() && *v > 0.0)
            && unit(&self.material.diffuse)
            && unit(&self.material.specular)
            && self.material.shininess.is_finite()
            && self.material.shininess >= 1.0
    }
}

/// How much of the instrument (label 1) one eye sees at the exposure's mid time, counted on
/// the undistorted canvas (pixels): what the instrument would cover with nothing in front of
/// it (its own parts hiding each other still) and what stays visible with the second
/// instrument and the occluder drawn.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Visibility {
    /// Canvas pixels of the instrument alone (nothing else in front), pixels.
    pub unoccluded_px: u64,
    /// Canvas pixels of the instrument still visible, pixels.
    pub visible_px: u64,
}

impl Visibility {
    /// `visible_px / unoccluded_px`; `None` when the instrument is out of view.
    pub fn fraction(&self) -> Option<f64> {
        (self.unoccluded_px > 0).then(|| self.visible_px as f64 / self.unoccluded_px as f64)
    }
}

/// Ground truth of one eye at the exposure's mid time.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EyeTruth {
    /// Which eye.
    pub eye: Eye,
    /// `T_e_c`: this eye's camera frame in the world `{e}`, metres.
    pub camera_in_world: PoseTruth,
    /// The instruments drawn (label 1 first, then label 2 when the second is on).
    pub instruments: Vec<InstrumentTruth>,
    /// The instrument's visibility (occlusion by the second instrument and the occluder).
    #[serde(default)]
    pub visibility: Visibility,
}

/// One eye's image.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct EyeImage {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// 8-bit sRGB, row-major, 3 bytes per pixel.
    pub rgb: Vec<u8>,
    /// Visible instrument at the mid time per pixel ([`label`]), row-major.
    pub labels: Vec<u8>,
}

/// A stereo frame with its ground truth.
#[derive(Clone, Debug, PartialEq)]
pub struct StereoFrame {
    /// Mid time of the exposure, nanoseconds on the caller's clock.
    pub t_mid_ns: u64,
    /// Endoscope arm joints at the mid time `[yaw rad, pitch rad, insertion m, roll rad]`.
    pub ecm_joints: [f64; 4],
    /// Left and right images.
    pub images: [EyeImage; 2],
    /// Left and right ground truth.
    pub truth: [EyeTruth; 2],
}

impl Default for StereoFrame {
    fn default() -> Self {
        let empty = |eye| EyeTruth {
            eye,
            camera_in_world: PoseTruth::from(&Isometry3::identity()),
            instruments: vec![],
            visibility: Visibility::default(),
        };
        Self {
            t_mid_ns: 0,
            ecm_joints: [0.0; 4],
            images: [EyeImage::default(), EyeImage::default()],
            truth: [empty(Eye::Left), empty(Eye::Right)],
        }
    }
}

/// Mid time of frame `n`: `t0_ns + round(n · 10⁹ / fps)` nanoseconds.
pub fn frame_mid_time_ns(t0_ns: u64, fps: f64, n: u64) -> u64 {
    t0_ns.saturating_add((n as f64 * 1e9 / fps).round() as u64)
}

/// Why a renderer cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NewRendererError {
    /// The configuration is invalid.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The instrument mesh has no triangle or a non-finite vertex.
    #[error("the instrument mesh is empty or has a non-finite vertex")]
    Mesh,
}

/// Why a frame cannot be rendered.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RenderError {
    /// A pose or joint of the scene is NaN or infinite.
    #[error("the scene at t = {t_ns} ns has a non-finite {what}")]
    NotFinite {
        /// Time of the offending state, nanoseconds.
        t_ns: u64,
        /// What is not finite.
        what: &'static str,
    },
}

/// Per-eye work buffers (canvas-sized and image-sized) and the cached tissue.
#[derive(Default)]
struct EyeWork {
    /// The tissue's depth (metres, canvas-sized), valid for the eye pose and light of
    /// `tissue_key`.
    depth_t: Vec<f32>,
    /// What `depth_t` and the tissue in `colour` were rendered for (`None`: not yet).
    tissue_key: Option<[u64; 10]>,
    /// How many times the tissue was rasterised.
    tissue_draws: u64,
    /// The tissue alone warped onto the image (linear RGB) and its defocus radii (pixels),
    /// when `tissue_image` is true (made on the first frame that reuses the tissue).
    tissue_lin: Vec<[f32; 3]>,
    tissue_rad: Vec<f32>,
    tissue_image: bool,
    /// The composite (linear RGB, canvas-sized): the tissue, and the blurred instruments at
    /// the pixels of `dirty`.
    colour: Vec<[f32; 3]>,
    /// The pixels (canvas indices) the instruments covered at some instant of the last
    /// frame, with the tissue's colour there: `colour` and `lab_mid` are the tissue's again
    /// once these are put back.
    dirty: Vec<(u32, [f32; 3])>,
    depth_w: Vec<f32>,
    s_col: Vec<[f32; 3]>,
    s_lab: Vec<u8>,
    acc: Vec<[f32; 3]>,
    cnt: Vec<u8>,
    /// Label at the mid time (0 outside `dirty`).
    lab_mid: Vec<u8>,
    /// Instrument depth at the mid time, metres: meaningful where `lab_mid` is not 0 (the
    /// depth is `depth_t` elsewhere).
    depth_mid: Vec<f32>,
    out_lin: Vec<[f32; 3]>,
    /// Defocus radius per image pixel, pixels.
    out_rad: Vec<f32>,
    levels: [Vec<[f32; 3]>; 3],
    tmp: Vec<[f32; 3]>,
    /// Level sampling positions per image column and row (index, next index, weight).
    taps_x: [Vec<(u32, u32, f32)>; 3],
    taps_y: [Vec<(u32, u32, f32)>; 3],
    /// One image row's signal and noise draws, a float per channel (work buffers).
    row_val: Vec<f32>,
    row_noise: Vec<f32>,
    row_vig: Vec<f32>,
    row_idx: Vec<i32>,
    verts: Vec<Vtx<5>>,
    verts4: Vec<Vtx<4>>,
    ivert: Vec<Vtx<3>>,
    ranges: Vec<(usize, usize, Material, u8)>,
}

/// One image pixel's bilinear tap into the canvas: the top-left canvas index, the nearest
/// canvas index (labels, depth) and the weights along x and y.
#[derive(Clone, Copy, Debug)]
struct Tap {
    j: u32,
    nearest: u32,
    fx: f32,
    fy: f32,
    /// The top-left canvas pixel's column and row (`j` split).
    ix: u16,
    iy: u16,
}

impl Tap {
    /// True when one of the four canvas pixels read lies in `b`.
    #[inline]
    fn touches(&self, b: &Bounds) -> bool {
        let (ix, iy) = (self.ix as usize, self.iy as usize);
        ix + 1 >= b.x0 && ix <= b.x1 && iy + 1 >= b.y0 && iy <= b.y1
    }
}

/// What both eyes share (read-only during a frame).
struct Shared {
    cfg: EndoscopeConfig,
    mesh: InstrumentMesh,
    tissue: Tissue,
    hand_eye: Isometry3<f64>,
    canvas: Canvas,
    proj: EyeProjection,
    /// The bilinear tap of every image pixel into the canvas (`None`: no distortion, canvas =
    /// image).
    remap: Option<Vec<Tap>>,
    vignette: Vec<f32>,
    /// `y/z` of the ray of every canvas row, and `x/z` of every canvas column when the skew
    /// is zero (`None` otherwise): [`Canvas::ray`] tabulated.
    ray_y: Vec<f32>,
    ray_x: Option<Vec<f32>>,
    gauss: Box<[f32; GAUSS_LUT]>,
    srgb: Box<[u8; SRGB_LUT]>,
}

/// The simulated stereo endoscope.
pub struct StereoRenderer {
    shared: Shared,
    work: [EyeWork; 2],
    /// The scene at the motion-blur instants of the frame being rendered (reused).
    states: Vec<(u64, SceneState)>,
    /// The occluder drawn in the next frames (`None`: none).
    occluder: Option<Occluder>,
}

const SRGB_LUT: usize = 8192;
/// Blinn-Phong exponent of the wet tissue: a broad lobe, which per-vertex lighting renders
/// without visible grid artefacts.
const TISSUE_SHININESS: f32 = 6.0;
const GAUSS_LUT: usize = 4096;

fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Inverse standard normal CDF at the centres of `n` equal-probability bins (the CDF is
/// integrated numerically on a fine grid and inverted by interpolation).
fn gauss_table(n: usize) -> Vec<f32> {
    const STEPS: usize = 200_000;
    let (lo, hi) = (-8.0f64, 8.0f64);
    let h = (hi - lo) / STEPS as f64;
    let pdf = |x: f64| (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt();
    let mut cdf = Vec::with_capacity(STEPS + 1);
    let mut acc = 0.0;
    cdf.push(0.0);
    for i in 0..STEPS {
        let x = lo + i as f64 * h;
        acc += h * (pdf(x) + 4.0 * pdf(x + h / 2.0) + pdf(x + h)) / 6.0;
        cdf.push(acc);
    }
    let mut out = Vec::with_capacity(n);
    let mut j = 0;
    for i in 0..n {
        let p = (i as f64 + 0.5) / n as f64;
        while j + 1 < STEPS && cdf[j + 1] < p {
            j += 1;
        }
        let t = (p - cdf[j]) / (cdf[j + 1] - cdf[j]).max(1e-300);
        out.push((lo + (j as f64 + t) * h) as f32);
    }
    // Exact unit variance of the table (the binning trims the tails a little).
    let var: f64 = out.iter().map(|&v| (v as f64).powi(2)).sum::<f64>() / n as f64;
    let s = 1.0 / var.sqrt();
    out.into_iter().map(|v| (v as f64 * s) as f32).collect()
}

/// A table of `N` entries from `v` (padded with `fill`, or cut, to `N`).
fn lut<T: Copy, const N: usize>(v: Vec<T>, fill: T) -> Box<[T; N]> {
    let mut out = Box::new([fill; N]);
    for (o, x) in out.iter_mut().zip(v) {
        *o = x;
    }
    out
}

fn srgb_table(n: usize) -> Vec<u8> {
    (0..n)
        .map(|i| {
            let x = i as f64 / (n - 1) as f64;
            let y = if x <= 0.003_130_8 { 12.92 * x } else { 1.055 * x.powf(1.0 / 2.4) - 0.055 };
            (y * 255.0).round().clamp(0.0, 255.0) as u8
        })
        .collect()
}

/// Schlick's rational approximation of `x^n` for the specular lobe.
#[inline]
fn spec_pow(x: f32, n: f32) -> f32 {
    x / (n - n * x + x)
}

#[inline]
fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
fn normalize(a: [f32; 3]) -> [f32; 3] {
    let l = dot(a, a).sqrt();
    if l > 0.0 {
        let il = 1.0 / l;
        [a[0] * il, a[1] * il, a[2] * il]
    } else {
        a
    }
}

/// Per-eye shading constants.
#[derive(Clone, Copy)]
struct Lighting {
    light: [f32; 3],
    e_ref: f32,
    ambient: f32,
    smoke: Option<(f32, [f32; 3])>,
}

impl Lighting {
    /// Blinn-Phong factors at camera-frame point `p` with unit normal `n`: the diffuse
    /// factor (ambient plus irradiance × cos) and the specular factor (irradiance × lobe).
    #[inline(always)]
    fn terms(&self, p: [f32; 3], n: [f32; 3], shin: f32) -> (f32, f32) {
        let ip = 1.0 / dot(p, p).sqrt();
        let v = [-p[0] * ip, -p[1] * ip, -p[2] * ip];
        let mut n = n;
        if dot(n, v) < 0.0 {
            n = [-n[0], -n[1], -n[2]];
        }
        let l = [self.light[0] - p[0], self.light[1] - p[1], self.light[2] - p[2]];
        let d2 = dot(l, l);
        let il = 1.0 / d2.sqrt();
        let l = [l[0] * il, l[1] * il, l[2] * il];
        let e = self.e_ref / d2;
        let ndl = dot(n, l).max(0.0);
        let s = if ndl > 0.0 {
            // The half vector h = l + v, normalised in the dot product.
            let h = [l[0] + v[0], l[1] + v[1], l[2] + v[2]];
            let hl = dot(h, h).sqrt();
            let ndh = if hl > 0.0 { dot(n, h) / hl } else { dot(n, h) };
            spec_pow(ndh.max(0.0), shin) * e
        } else {
            0.0
        };
        (self.ambient + e * ndl, s)
    }

    /// Smoke transmittance at depth `z` (1 without smoke).
    #[inline]
    fn transmittance(&self, z: f32) -> f32 {
        match self.smoke {
            Some((density, _)) => (-density * z).exp(),
            None => 1.0,
        }
    }

    /// Adds the smoke's haze to a colour seen through transmittance `t`.
    #[inline]
    fn haze(&self, c: [f32; 3], t: f32) -> [f32; 3] {
        match self.smoke {
            Some((_, haze)) => {
                [c[0] * t + haze[0] * (1.0 - t), c[1] * t + haze[1] * (1.0 - t), c[2] * t + haze[2] * (1.0 - t)]
            }
            None => c,
        }
    }

    /// Blinn-Phong at camera-frame point `p` with unit normal `n`, through the smoke.
    #[inline(always)]
    fn shade(&self, p: [f32; 3], n: [f32; 3], albedo: [f32; 3], spec: [f32; 3], shin: f32) -> [f32; 3] {
        let (d, s) = self.terms(p, n, shin);
        let c = [albedo[0] * d + spec[0] * s, albedo[1] * d + spec[1] * s, albedo[2] * d + spec[2] * s];
        self.haze(c, self.transmittance(p[2]))
    }
}

fn mat_f32(m: &Material, specular_on: bool) -> ([f32; 3], [f32; 3], f32) {
    let spec = if specular_on { m.specular.map(|v| v as f32) } else { [0.0; 3] };
    (m.diffuse.map(|v| v as f32), spec, m.shininess as f32)
}

impl StereoRenderer {
    /// Builds the renderer: validates the configuration, precomputes the tissue (mesh and
    /// texture), the distortion warp, the vignetting and the lookup tables.
    pub fn new(cfg: EndoscopeConfig, mesh: InstrumentMesh) -> Result<Self, NewRendererError> {
        cfg.validate()?;
        if mesh.triangle_count() == 0
            || !mesh.parts.iter().all(|(_, m)| m.positions.iter().flatten().all(|v| v.is_finite()))
        {
            return Err(NewRendererError::Mesh);
        }
        let Some(hand_eye) = cfg.camera.hand_eye.isometry() else {
            return Err(ConfigError::Range { key: "camera.hand_eye", why: "finite, non-zero quaternion" }.into());
        };
        let k = cfg.camera.intrinsics;
        let (w, h) = (k.width as usize, k.height as usize);
        let (canvas, remap) = canvas_and_remap(&k)?;
        let proj = EyeProjection {
            k,
            ideal_bounds: [
                canvas.ox as f64,
                canvas.oy as f64,
                (canvas.ox + canvas.w as f32 - 1.0) as f64,
                (canvas.oy + canvas.h as f32 - 1.0) as f64,
            ],
        };
        let s = if cfg.realism.vignetting.enabled { cfg.realism.vignetting.strength as f32 } else { 0.0 };
        let mut vignette = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let ideal = k.undistort_px(&Vector2::new(x as f64, y as f64));
                let (xn, yn) = canvas.ray(ideal.x as f32 - canvas.ox, ideal.y as f32 - canvas.oy);
                let c2 = 1.0 / (1.0 + xn * xn + yn * yn);
                vignette.push(1.0 - s * (1.0 - c2 * c2));
            }
        }
        let tissue = Tissue::new(&cfg.tissue, cfg.seed, cfg.realism.tissue_texture);
        let shared = Shared {
            cfg,
            mesh,
            tissue,
            hand_eye,
            canvas,
            proj,
            remap,
            vignette,
            ray_y: (0..canvas.h).map(|y| canvas.ray(0.0, y as f32).1).collect(),
            ray_x: (canvas.skew == 0.0).then(|| (0..canvas.w).map(|x| canvas.ray(x as f32, 0.0).0).collect()),
            gauss: lut(gauss_table(GAUSS_LUT), 0.0),
            srgb: lut(srgb_table(SRGB_LUT), 0),
        };
        Ok(Self { shared, work: [EyeWork::default(), EyeWork::default()], states: Vec::new(), occluder: None })
    }

    /// How many times each eye's tissue was rasterised (the rest of the frames reused it).
    #[cfg(test)]
    pub(crate) fn tissue_draws(&self) -> [u64; 2] {
        [self.work[0].tissue_draws, self.work[1].tissue_draws]
    }

    /// The configuration in use.
    pub fn config(&self) -> &EndoscopeConfig {
        &self.shared.cfg
    }

    /// Puts `occluder` in the scene of the next frames (`None`: takes it away). Checked when a
    /// frame is rendered ([`RenderError::NotFinite`] when not [`Occluder::is_valid`]).
    pub fn set_occluder(&mut self, occluder: Option<Occluder>) {
        self.occluder = occluder;
    }

    /// The occluder in the scene.
    pub fn occluder(&self) -> Option<&Occluder> {
        self.occluder.as_ref()
    }

    /// Camera poses `T_e_c` of both eyes (metres) for endoscope arm joints `q`.
    pub fn eye_poses(&self, ecm_joints: &[f64; 4]) -> [Isometry3<f64>; 2] {
        eye_poses(&self.shared.hand_eye, self.shared.cfg.camera.baseline_m, ecm_joints)
    }

    /// Distorted pixel of world point `p_e` (metres, `{e}`) in one eye, `None` when behind the
    /// camera or outside the image.
    pub fn project_world(&self, eye_pose: &Isometry3<f64>, p_e: &Vector3<f64>) -> Option<Vector2<f64>> {
        let p_c = eye_pose.inverse() * Point3::from(*p_e);
        self.shared.proj.project_in_image(&p_c.coords)
    }

    /// Renders the stereo frame whose exposure is centred on `t_mid_ns`; `scene` gives the
    /// scene at any time (it is called at the motion-blur instants).
    pub fn render(&mut self, t_mid_ns: u64, scene: &dyn Fn(u64) -> SceneState) -> Result<StereoFrame, RenderError> {
        let mut f = StereoFrame::default();
        self.render_into(t_mid_ns, scene, &mut f)?;
        Ok(f)
    }

    /// As [`StereoRenderer::render`], into `out` (its buffers are reused).
    pub fn render_into(
        &mut self,
        t_mid_ns: u64,
        scene: &dyn Fn(u64) -> SceneState,
        out: &mut StereoFrame,
    ) -> Result<(), RenderError> {
        let sh = &self.shared;
        let r = &sh.cfg.realism;
        let k_samples = if r.motion_blur.enabled { r.motion_blur.samples } else { 1 };
        let exposure_ns = sh.cfg.timing.exposure_s * 1e9;
        let states = &mut self.states;
        states.clear();
        for s in 0..k_samples {
            let dt = exposure_ns * ((s as f64 + 0.5) / k_samples as f64 - 0.5);
            let t = if k_samples == 1 { t_mid_ns } else { (t_mid_ns as f64 + dt).round().max(0.0) as u64 };
            let st = scene(t);
            if !st.ecm_joints.iter().all(|v| v.is_finite()) {
                return Err(RenderError::NotFinite { t_ns: t, what: "endoscope joint" });
            }
            if !st.instrument.is_finite() {
                return Err(RenderError::NotFinite { t_ns: t, what: "instrument pose or joint" });
            }
            if r.second_instrument && st.second.is_some_and(|s| !s.is_finite()) {
                return Err(RenderError::NotFinite { t_ns: t, what: "second instrument pose or joint" });
            }
            states.push((t, st));
        }
        if self.occluder.is_some_and(|o| !o.is_valid()) {
            return Err(RenderError::NotFinite { t_ns: t_mid_ns, what: "occluder (pose, size or material)" });
        }
        let occ = self.occluder.as_ref();
        let states: &[(u64, SceneState)] = states;
        let mid = states[k_samples / 2].1;
        let poses = eye_poses(&sh.hand_eye, sh.cfg.camera.baseline_m, &mid.ecm_joints);
        let light_world = Point3::from((poses[0].translation.vector + poses[1].translation.vector) / 2.0);
        let [w0, w1] = &mut self.work;
        let [i0, i1] = &mut out.images;
        let [t0, t1] = &mut out.truth;
        let seed = sh.cfg.seed;
        rayon::join(
            || render_eye(sh, w0, Eye::Left, &poses[0], &light_world, states, occ, seed, t_mid_ns, i0, t0),
            || render_eye(sh, w1, Eye::Right, &poses[1], &light_world, states, occ, seed, t_mid_ns, i1, t1),
        );
        out.t_mid_ns = t_mid_ns;
        out.ecm_joints = mid.ecm_joints;
        Ok(())
    }
}

fn eye_poses(hand_eye: &Isometry3<f64>, baseline_m: f64, q: &[f64; 4]) -> [Isometry3<f64>; 2] {
    let left = camera_pose(q, hand_eye);
    [left, left * Translation3::new(baseline_m, 0.0, 0.0)]
}

/// The bilinear taps of every image pixel into the canvas, row-major (`None`: no distortion).
type Remap = Option<Vec<Tap>>;

/// The canvas (undistorted image covering every ideal pixel the image sees) and, with
/// distortion, the tap of every image pixel at its undistorted position.
fn canvas_and_remap(k: &Intrinsics) -> Result<(Canvas, Remap), ConfigError> {
    let (w, h) = (k.width as usize, k.height as usize);
    let base = |ox: f32, oy: f32, cw: usize, ch: usize| Canvas {
        w: cw,
        h: ch,
        ox,
        oy,
        fx: k.fx as f32,
        fy: k.fy as f32,
        skew: k.skew as f32,
        cx: k.cx as f32,
        cy: k.cy as f32,
    };
    if k.is_undistorted() {
        return Ok((base(0.0, 0.0, w, h), None));
    }
    // Undistort the border; check the round trip (a distortion that folds over fails it).
    let mut border = Vec::new();
    for x in 0..w {
        border.push((x as f64, 0.0));
        border.push((x as f64, (h - 1) as f64));
    }
    for y in 0..h {
        border.push((0.0, y as f64));
        border.push(((w - 1) as f64, y as f64));
    }
    let (mut u0, mut v0, mut u1, mut v1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for (x, y) in border {
        let px = Vector2::new(x, y);
        let ideal = k.undistort_px(&px);
        let p = k.k_inv() * Vector3::new(ideal.x, ideal.y, 1.0);
        let back = k.project(&p);
        if !(ideal.x.is_finite() && ideal.y.is_finite()) || (back - px).norm() > 0.01 {
            return Err(ConfigError::Distortion);
        }
        u0 = u0.min(ideal.x);
        v0 = v0.min(ideal.y);
        u1 = u1.max(ideal.x);
        v1 = v1.max(ideal.y);
    }
    let (ox, oy) = ((u0 - 2.0).floor(), (v0 - 2.0).floor());
    let (cw, ch) = ((u1 + 2.0).ceil() - ox + 1.0, (v1 + 2.0).ceil() - oy + 1.0);
    if !(cw > 1.0 && ch > 1.0 && cw <= 3.0 * w as f64 + 8.0 && ch <= 3.0 * h as f64 + 8.0) {
        return Err(ConfigError::Distortion);
    }
    let canvas = base(ox as f32, oy as f32, cw as usize, ch as usize);
    let (cw, ch) = (canvas.w, canvas.h);
    let mut remap = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let ideal = k.undistort_px(&Vector2::new(x as f64, y as f64));
            let m = [(ideal.x - ox) as f32, (ideal.y - oy) as f32];
            let (x, y) = (m[0].clamp(0.0, (cw - 1) as f32), m[1].clamp(0.0, (ch - 1) as f32));
            let (ix, iy) = ((x as usize).min(cw - 2), (y as usize).min(ch - 2));
            let nearest = ((y + 0.5) as usize * cw + (x + 0.5) as usize).min(cw * ch - 1);
            remap.push(Tap {
                j: (iy * cw + ix) as u32,
                nearest: nearest as u32,
                fx: x - ix as f32,
                fy: y - iy as f32,
                ix: ix as u16,
                iy: iy as u16,
            });
        }
    }
    Ok((canvas, Some(remap)))
}

fn resize<T: Clone>(v: &mut Vec<T>, n: usize, fill: T) {
    if v.len() != n {
        v.clear();
        v.resize(n, fill);
    }
}

#[allow(clippy::too_many_arguments)]
fn render_eye(
    sh: &Shared,
    wk: &mut EyeWork,
    eye: Eye,
    t_e_c: &Isometry3<f64>,
    light_world: &Point3<f64>,
    states: &[(u64, SceneState)],
    occluder: Option<&Occluder>,
    seed: u64,
    t_mid_ns: u64,
    img: &mut EyeImage,
    truth: &mut EyeTruth,
) {
    let cfg = &sh.cfg;
    let r = &cfg.realism;
    let c = sh.canvas;
    let nc = c.w * c.h;
    let (w, h) = (cfg.camera.intrinsics.width as usize, cfg.camera.intrinsics.height as usize);
    let no = w * h;
    if wk.depth_t.len() != nc {
        // First frame: size the buffers (nothing is cached yet).
        wk.tissue_key = None;
        wk.dirty.clear();
    }
    resize(&mut wk.depth_t, nc, f32::INFINITY);
    resize(&mut wk.colour, nc, [0.0; 3]);
    resize(&mut wk.depth_w, nc, f32::INFINITY);
    resize(&mut wk.s_col, nc, [0.0; 3]);
    resize(&mut wk.s_lab, nc, 0);
    resize(&mut wk.acc, nc, [0.0; 3]);
    resize(&mut wk.cnt, nc, 0);
    resize(&mut wk.lab_mid, nc, 0);
    resize(&mut wk.depth_mid, nc, f32::INFINITY);
    resize(&mut wk.out_lin, no, [0.0; 3]);
    resize(&mut wk.out_rad, no, 0.0);
    resize(&mut img.rgb, no * 3, 0);
    resize(&mut img.labels, no, 0);
    img.width = w as u32;
    img.height = h as u32;

    let t_c_e = t_e_c.inverse();
    let light_c = t_c_e * light_world;
    let lo = cfg.light;
    let smoke = r.smoke.enabled.then(|| {
        let e = lo.intensity as f32;
        (r.smoke.density_per_m as f32, r.smoke.colour.map(|v| v as f32 * e))
    });
    let lighting = Lighting {
        light: [light_c.x as f32, light_c.y as f32, light_c.z as f32],
        e_ref: (lo.intensity * lo.reference_distance_m * lo.reference_distance_m) as f32,
        ambient: lo.ambient as f32,
        smoke,
    };

    // 1. Tissue: rasterised and shaded only when the eye pose (and with it the light, rigid
    // with the endoscope) differs from the cached one, bit for bit; the configuration and
    // the tissue are fixed for the renderer's life. Either way `colour` and `depth_t` hold
    // the tissue alone afterwards, `lab_mid` is 0 and `depth_w` equals `depth_t`.
    let (tq, tt) = (t_c_e.rotation.quaternion().coords, t_c_e.translation.vector);
    let key = [tq.x, tq.y, tq.z, tq.w, tt.x, tt.y, tt.z, light_c.x, light_c.y, light_c.z].map(f64::to_bits);
    let hit = wk.tissue_key == Some(key);
    // The last frame's instruments are taken out again (their colour only matters when the
    // tissue is kept).
    for &(i, tissue) in &wk.dirty {
        let i = i as usize;
        if hit {
            wk.colour[i] = tissue;
        }
        wk.lab_mid[i] = 0;
    }
    wk.dirty.clear();
    if !hit {
        draw_tissue(sh, wk, &t_c_e, &lighting);
        wk.tissue_key = Some(key);
        wk.tissue_draws += 1;
        wk.depth_w.copy_from_slice(&wk.depth_t);
        wk.tissue_image = false;
    }
    let defocus_on = r.defocus.enabled && r.defocus.aperture_m > 0.0 && r.defocus.max_coc_px > 0.0;
    let d = &r.defocus;
    let k_rad = (d.aperture_m as f32) * (cfg.camera.intrinsics.fx as f32) * 0.5; // radius, px, per unit |1/z − 1/zf|
    let izf = 1.0 / d.focus_distance_m as f32;
    let rmax = 0.5 * d.max_coc_px as f32;
    let radius = |z: f32| if z.is_finite() { (k_rad * (1.0 / z - izf).abs()).min(rmax) } else { rmax };
    // The endoscope held still: the tissue alone is warped once, and the image pixels that
    // read no pixel the instruments covered take it from there (the same numbers).
    if let (true, false, Some(map)) = (hit, wk.tissue_image, &sh.remap) {
        resize(&mut wk.tissue_lin, no, [0.0; 3]);
        resize(&mut wk.tissue_rad, no, 0.0);
        for (i, m) in map.iter().enumerate() {
            wk.tissue_lin[i] = bilinear(&wk.colour, c.w, m);
            wk.tissue_rad[i] = if defocus_on { radius(wk.depth_t[m.nearest as usize]) } else { 0.0 };
        }
        wk.tissue_image = true;
    }

    // 2. Instruments, once per motion-blur instant.
    let k_samples = states.len();
    let mid = k_samples / 2;
    let mut union = Bounds::EMPTY;
    let mut visibility = Visibility::default();
    let geometry = &cfg.instrument;
    // The working depth `depth_w` equals the tissue's outside what the last instant drew.
    for (s, (_, st)) in states.iter().enumerate() {
        let mut instruments: [Option<(u8, &InstrumentState)>; 2] = [Some((label::INSTRUMENT, &st.instrument)), None];
        if r.second_instrument {
            instruments[1] = st.second.as_ref().map(|s| (label::SECOND, s));
        }
        // Posed vertices of every part of every instrument.
        wk.ivert.clear();
        wk.ranges.clear();
        for (lab, inst) in instruments.iter().flatten() {
            let poses = geometry.part_poses(inst.wrist_rad, inst.jaw_rad);
            for (pi, (part, m)) in sh.mesh.parts.iter().enumerate() {
                let jp = match part {
                    Part::Shaft => poses[0],
                    Part::Wrist => poses[1],
                    Part::Jaw1 => poses[2],
                    Part::Jaw2 => poses[3],
                };
                let t = t_c_e * inst.pose_world * jp;
                let (t32, r32) =
                    (t.translation.vector.cast::<f32>(), t.rotation.to_rotation_matrix().matrix().cast::<f32>());
                let start = wk.ivert.len();
                for (p, n) in m.positions.iter().zip(&m.normals) {
                    let pc = r32 * Vector3::from(*p) + t32;
                    let nn = r32 * Vector3::from(*n);
                    wk.ivert.push(Vtx { p: [pc.x, pc.y, pc.z], a: [nn.x, nn.y, nn.z] });
                }
                let mat = match (part, *lab) {
                    (Part::Shaft, label::SECOND) => cfg.materials.second_shaft,
                    (Part::Shaft, _) => cfg.materials.shaft,
                    _ => cfg.materials.tip,
                };
                wk.ranges.push((start, pi, mat, *lab));
            }
        }
        let mut drawn = Bounds::EMPTY;
        // The instrument (label 1) comes first: counted alone before the rest is drawn.
        let n_first = wk.ranges.iter().take_while(|r| r.3 == label::INSTRUMENT).count();
        for (ri, &(start, pi, mat, lab)) in wk.ranges.iter().enumerate() {
            if s == mid && ri == n_first {
                visibility.unoccluded_px = count_label(&wk.s_lab, c.w, &drawn, label::INSTRUMENT);
            }
            let m = &sh.mesh.parts[pi].1;
            let (albedo, spec, shin) = mat_f32(&mat, r.specular);
            let verts = &wk.ivert[start..start + m.positions.len()];
            let (s_col, s_lab) = (&mut wk.s_col, &mut wk.s_lab);
            let (ray_x, ray_y) = (sh.ray_x.as_deref(), &sh.ray_y);
            let mut frag = |idx: usize, x: usize, y: usize, z: f32, a: &[f32; 3]| {
                let (xn, yn) = match ray_x {
                    Some(rx) => (rx[x], ray_y[y]),
                    None => c.ray(x as f32, y as f32),
                };
                s_col[idx] = lighting.shade([xn * z, yn * z, z], normalize(*a), albedo, spec, shin);
                s_lab[idx] = lab;
            };
            for t in &m.triangles {
                let tri = [verts[t[0] as usize], verts[t[1] as usize], verts[t[2] as usize]];
                draw_triangle(&c, &mut wk.depth_w, &tri, true, &mut drawn, &mut frag);
            }
        }
        if s == mid && n_first == wk.ranges.len() {
            visibility.unoccluded_px = count_label(&wk.s_lab, c.w, &drawn, label::INSTRUMENT);
        }
        if let Some(o) = occluder {
            draw_occluder(sh, wk, o, &t_c_e, &lighting, &mut drawn);
        }
        if s == mid {
            visibility.visible_px = count_label(&wk.s_lab, c.w, &drawn, label::INSTRUMENT);
        }
        if drawn.is_empty() {
            continue;
        }
        union = union.union(&drawn);
        for y in drawn.y0..=drawn.y1 {
            let row = y * c.w;
            let span = row + drawn.x0..=row + drawn.x1;
            let labs = &mut wk.s_lab[span.clone()];
            let cols = &wk.s_col[span.clone()];
            let accs = &mut wk.acc[span.clone()];
            let cnts = &mut wk.cnt[span];
            for (o, l) in labs.iter_mut().enumerate() {
                if *l != 0 {
                    let sc = cols[o];
                    let a = &mut accs[o];
                    a[0] += sc[0];
                    a[1] += sc[1];
                    a[2] += sc[2];
                    cnts[o] += 1;
                    let i = row + drawn.x0 + o;
                    if s == mid {
                        wk.lab_mid[i] = *l;
                        wk.depth_mid[i] = wk.depth_w[i];
                    }
                    // Drawn: the working depth back to the tissue's.
                    wk.depth_w[i] = wk.depth_t[i];
                    *l = 0;
                }
            }
        }
    }
    // Composite: each instant covers a pixel with the instrument or leaves the tissue.
    if !union.is_empty() {
        let inv_k = 1.0 / k_samples as f32;
        for y in union.y0..=union.y1 {
            for i in y * c.w + union.x0..=y * c.w + union.x1 {
                let n = wk.cnt[i];
                if n != 0 {
                    let rest = (k_samples - n as usize) as f32;
                    let (t, a) = (wk.colour[i], wk.acc[i]);
                    wk.dirty.push((i as u32, t));
                    wk.colour[i] =
                        [(t[0] * rest + a[0]) * inv_k, (t[1] * rest + a[1]) * inv_k, (t[2] * rest + a[2]) * inv_k];
                    wk.acc[i] = [0.0; 3];
                    wk.cnt[i] = 0;
                }
            }
        }
    }

    // 3. Lens distortion: canvas → image (bilinear colour; nearest labels and depth, the
    // depth kept as the defocus radius).
    let mut blurred = false;
    match &sh.remap {
        None => {
            wk.out_lin.copy_from_slice(&wk.colour);
            img.labels.copy_from_slice(&wk.lab_mid);
            if defocus_on {
                for (i, o) in wk.out_rad.iter_mut().enumerate() {
                    let z = if wk.lab_mid[i] != 0 { wk.depth_mid[i] } else { wk.depth_t[i] };
                    *o = radius(z);
                    blurred |= *o > 0.35;
                }
            }
        }
        Some(map) => {
            let kept = hit && wk.tissue_image;
            let (colour, lab_mid, depth_mid, depth_t) = (&wk.colour, &wk.lab_mid, &wk.depth_mid, &wk.depth_t);
            let (tissue_lin, tissue_rad) = (&wk.tissue_lin, &wk.tissue_rad);
            let outs = wk.out_lin.iter_mut().zip(img.labels.iter_mut()).zip(wk.out_rad.iter_mut());
            for (i, (m, ((out, lab), rad))) in map.iter().zip(outs).enumerate() {
                if kept && !m.touches(&union) {
                    *out = tissue_lin[i];
                    *lab = label::BACKGROUND;
                    if defocus_on {
                        let rr = tissue_rad[i];
                        *rad = rr;
                        blurred |= rr > 0.35;
                    }
                    continue;
                }
                *out = bilinear(colour, c.w, m);
                let nearest = m.nearest as usize;
                let l = lab_mid[nearest];
                *lab = l;
                if defocus_on {
                    let rr = radius(if l != 0 { depth_mid[nearest] } else { depth_t[nearest] });
                    *rad = rr;
                    blurred |= rr > 0.35;
                }
            }
        }
    }

    // 4. Defocus: the pyramid of blurred levels, each blurred pixel interpolating between
    // the two levels around its circle.
    if defocus_on && blurred {
        let dims = defocus_levels(wk, w, h);
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let rr = wk.out_rad[i];
                if rr > 0.35 {
                    wk.out_lin[i] = defocus_gather(wk, &dims, wk.out_lin[i], rr, x, y);
                }
            }
        }
    }

    // 5. Vignetting, noise, sRGB, row by row.
    let noise =
        r.noise.enabled.then_some((r.noise.full_well_e as f32, (r.noise.read_noise_e * r.noise.read_noise_e) as f32));
    let eye_key = match eye {
        Eye::Left => 0x4C45_4654u64,
        Eye::Right => 0x5249_4748u64,
    };
    let lut_max = (SRGB_LUT - 1) as f32;
    // The signal of a row, one float per channel: vignetted, then noisy (the same operations
    // as per pixel, in loops the compiler vectorises), then to sRGB bytes.
    resize(&mut wk.row_val, 3 * w, 0.0);
    resize(&mut wk.row_noise, 3 * w, 0.0);
    resize(&mut wk.row_vig, 3 * w, 0.0);
    resize(&mut wk.row_idx, 3 * w, 0);
    for y in 0..h {
        let row = y * w;
        let rgb = &mut img.rgb[3 * row..3 * (row + w)];
        let lin = wk.out_lin[row..row + w].as_flattened();
        // The row's vignetting repeated per channel (a row buffer: less memory traffic than a
        // whole image of it).
        let vig = &mut wk.row_vig[..3 * w];
        for (o, &g) in vig.chunks_exact_mut(3).zip(&sh.vignette[row..row + w]) {
            o.fill(g);
        }
        let vig = &wk.row_vig[..3 * w];
        let val = &mut wk.row_val[..3 * w];
        match noise {
            Some((fw, read2)) => {
                let mut rng = ChaCha8Rng::seed_from_u64(splitmix(
                    seed ^ splitmix(t_mid_ns ^ splitmix(eye_key ^ ((y as u64) << 32))),
                ));
                let gauss = &sh.gauss;
                for nk in wk.row_noise[..3 * w].chunks_exact_mut(3) {
                    let bits = rng.next_u64();
                    nk[0] = gauss[((bits >> 4) & 0xFFF) as usize];
                    nk[1] = gauss[((bits >> 20) & 0xFFF) as usize];
                    nk[2] = gauss[((bits >> 36) & 0xFFF) as usize];
                }
                for (((o, &v), &g), &n) in val.iter_mut().zip(lin).zip(vig).zip(&wk.row_noise[..3 * w]) {
                    let c = v * g;
                    let e = c.max(0.0) * fw;
                    *o = c + (e + read2).sqrt() / fw * n;
                }
            }
            None => {
                for ((o, &v), &g) in val.iter_mut().zip(lin).zip(vig) {
                    *o = v * g;
                }
            }
        }
        // ⌊clamp(c, 0, 1)·lut_max + ½⌋ as ⌊c·lut_max + ½⌋ clamped to [0, lut_max] before
        // the truncation (the same index: lut_max is an integer, truncation sends (−1, ½) to
        // 0, and NaN goes to 0 either way, `f32::max` returning the number).
        let idx = &mut wk.row_idx[..3 * w];
        srgb_indices(val, idx, lut_max);
        for (o, &i) in rgb.iter_mut().zip(idx.iter()) {
            // In [0, SRGB_LUT − 1] already; the mask only spares the bounds check.
            *o = sh.srgb[(i as usize) & (SRGB_LUT - 1)];
        }
    }

    // Ground truth.
    truth.eye = eye;
    truth.camera_in_world = PoseTruth::from(t_e_c);
    truth.instruments.clear();
    truth.visibility = visibility;
    let st = &states[mid].1;
    truth.instruments.push(instrument_truth(label::INSTRUMENT, &st.instrument, geometry, &t_c_e, &sh.proj));
    if r.second_instrument
        && let Some(s2) = &st.second
    {
        truth.instruments.push(instrument_truth(label::SECOND, s2, geometry, &t_c_e, &sh.proj));
    }
}

/// Pixels labelled `lab` in `labels` (canvas, `w` wide) within `b`.
fn count_label(labels: &[u8], w: usize, b: &Bounds, lab: u8) -> u64 {
    if b.is_empty() {
        return 0;
    }
    let mut n = 0u64;
    for y in b.y0..=b.y1 {
        n += labels[y * w + b.x0..=y * w + b.x1].iter().filter(|&&l| l == lab).count() as u64;
    }
    n
}

/// Draws the occluder plate (two triangles, both faces, shaded with its normal turned to the
/// camera) into the instant's buffers with label [`label::OCCLUDER`].
fn draw_occluder(
    sh: &Shared,
    wk: &mut EyeWork,
    o: &Occluder,
    t_c_e: &Isometry3<f64>,
    lighting: &Lighting,
    drawn: &mut Bounds,
) {
    let c = sh.canvas;
    let t = t_c_e * o.pose_world;
    let [hx, hy] = o.half_size_m;
    let corners = [[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]].map(|[x, y]| t * Point3::new(x, y, 0.0));
    let mut n = t.rotation * Vector3::z();
    if n.dot(&corners[0].coords) > 0.0 {
        n = -n;
    }
    let a = [n.x as f32, n.y as f32, n.z as f32];
    let v = corners.map(|p| Vtx { p: [p.x as f32, p.y as f32, p.z as f32], a });
    let (albedo, spec, shin) = mat_f32(&o.material, sh.cfg.realism.specular);
    let (s_col, s_lab) = (&mut wk.s_col, &mut wk.s_lab);
    let (ray_x, ray_y) = (sh.ray_x.as_deref(), &sh.ray_y);
    let mut frag = |idx: usize, x: usize, y: usize, z: f32, a: &[f32; 3]| {
        let (xn, yn) = match ray_x {
            Some(rx) => (rx[x], ray_y[y]),
            None => c.ray(x as f32, y as f32),
        };
        s_col[idx] = lighting.shade([xn * z, yn * z, z], normalize(*a), albedo, spec, shin);
        s_lab[idx] = label::OCCLUDER;
    };
    for tri in [[v[0], v[1], v[2]], [v[0], v[2], v[3]]] {
        draw_triangle(&c, &mut wk.depth_w, &tri, false, drawn, &mut frag);
    }
}

/// `idx[i] = ⌊clamp(val[i]·lut_max + ½, 0, lut_max)⌋` (NaN to 0, `f32::max` returning the
/// number); on x86-64 four at a time with SSE2 (the same operations: `maxps` returns its
/// second operand, 0, for NaN; the truncation of a value in `[0, lut_max]` is exact).
#[inline]
fn srgb_indices(val: &[f32], idx: &mut [i32], lut_max: f32) {
    let scalar = |v: f32| (v * lut_max + 0.5).max(0.0).min(lut_max) as i32;
    #[cfg(target_arch = "x86_64")]
    let (val, idx) = {
        use std::arch::x86_64::{
            _mm_add_ps, _mm_cvttps_epi32, _mm_loadu_ps, _mm_max_ps, _mm_min_ps, _mm_mul_ps, _mm_set1_ps,
            _mm_setzero_ps, _mm_storeu_si128,
        };
        let n4 = val.len().min(idx.len()) / 4 * 4;
        for (v, o) in val[..n4].chunks_exact(4).zip(idx[..n4].chunks_exact_mut(4)) {
            // SAFETY: SSE2 is part of the x86-64 baseline; `v` and `o` are exactly four
            // elements long, so the unaligned 16-byte load and store stay inside them.
            unsafe {
                let x = _mm_add_ps(_mm_mul_ps(_mm_loadu_ps(v.as_ptr()), _mm_set1_ps(lut_max)), _mm_set1_ps(0.5));
                let x = _mm_min_ps(_mm_max_ps(x, _mm_setzero_ps()), _mm_set1_ps(lut_max));
                _mm_storeu_si128(o.as_mut_ptr().cast(), _mm_cvttps_epi32(x));
            }
        }
        (&val[n4..], &mut idx[n4..])
    };
    for (i, &v) in idx.iter_mut().zip(val) {
        *i = scalar(v);
    }
}

/// Bilinear sample of a canvas (`cw` pixels wide) at an image pixel's tap.
#[inline(always)]
fn bilinear(colour: &[[f32; 3]], cw: usize, m: &Tap) -> [f32; 3] {
    let j = m.j as usize;
    #[cfg(target_arch = "x86_64")]
    {
        // Four floats from each of the four pixels (the fourth lane, the next pixel's red, is
        // ignored): the same operations per channel. Needs one float past the bottom-right
        // pixel; the scalar code below takes the last tap of the canvas.
        use std::arch::x86_64::{_mm_add_ps, _mm_loadu_ps, _mm_mul_ps, _mm_set1_ps, _mm_storeu_ps, _mm_sub_ps};
        let flat = colour.as_flattened();
        if let Some(q) = flat.get(3 * j..3 * (j + cw) + 7) {
            let mut o = [0.0f32; 4];
            // SAFETY: SSE2 is part of the x86-64 baseline; `q` holds `3·cw + 7` floats, so the
            // 4-float loads at 0, 3, 3·cw and 3·cw + 3 stay inside it, and `o` holds 4.
            unsafe {
                let (fx, fy) = (_mm_set1_ps(m.fx), _mm_set1_ps(m.fy));
                let (a, b) = (_mm_loadu_ps(q.as_ptr()), _mm_loadu_ps(q.as_ptr().add(3)));
                let (cc, dd) = (_mm_loadu_ps(q.as_ptr().add(3 * cw)), _mm_loadu_ps(q.as_ptr().add(3 * cw + 3)));
                let top = _mm_add_ps(a, _mm_mul_ps(_mm_sub_ps(b, a), fx));
                let bot = _mm_add_ps(cc, _mm_mul_ps(_mm_sub_ps(dd, cc), fx));
                _mm_storeu_ps(o.as_mut_ptr(), _mm_add_ps(top, _mm_mul_ps(_mm_sub_ps(bot, top), fy)));
            }
            return [o[0], o[1], o[2]];
        }
    }
    let quad = &colour[j..j + cw + 2];
    let (a, b, cc, dd) = (quad[0], quad[1], quad[cw], quad[cw + 1]);
    let mut o = [0.0f32; 3];
    for k in 0..3 {
        let top = a[k] + (b[k] - a[k]) * m.fx;
        let bot = cc[k] + (dd[k] - cc[k]) * m.fx;
        o[k] = top + (bot - top) * m.fy;
    }
    o
}

/// Rasterises and shades the tissue seen from camera pose `t_c_e` into `wk.depth_t` and
/// `wk.colour` (canvas).
fn draw_tissue(sh: &Shared, wk: &mut EyeWork, t_c_e: &Isometry3<f64>, lighting: &Lighting) {
    let c = sh.canvas;
    wk.depth_t.fill(f32::INFINITY);
    let bg = lighting.smoke.map(|(_, haze)| haze).unwrap_or([0.0; 3]);
    wk.colour.fill(bg);
    // Tissue lighting per vertex (Gouraud: the grid is finer than the light's variation),
    // interpolated with the texture coordinates; the texture is sampled per pixel.
    let rot = t_c_e.rotation;
    let wet = sh.cfg.tissue.wet_specular as f32;
    wk.verts.clear();
    for ((p, n), uv) in sh.tissue.positions.iter().zip(&sh.tissue.normals).zip(&sh.tissue.uv) {
        let pc = t_c_e * Point3::from(*p);
        let nc3 = rot * n;
        let p32 = [pc.x as f32, pc.y as f32, pc.z as f32];
        let (d, s) = if pc.z > 0.0 {
            lighting.terms(p32, [nc3.x as f32, nc3.y as f32, nc3.z as f32], TISSUE_SHININESS)
        } else {
            (0.0, 0.0)
        };
        wk.verts.push(Vtx { p: p32, a: [uv[0], uv[1], d, s * wet, lighting.transmittance(p32[2].max(0.0))] });
    }
    let tissue = &sh.tissue;
    let colour = &mut wk.colour;
    let mut b = Bounds::EMPTY;
    if lighting.smoke.is_some() {
        let verts = &wk.verts;
        let mut frag = |idx: usize, _x: usize, _y: usize, _z: f32, a: &[f32; 5]| {
            let al = tissue.albedo(a[0], a[1]);
            let c = [al[0] * a[2] + a[3], al[1] * a[2] + a[3], al[2] * a[2] + a[3]];
            colour[idx] = lighting.haze(c, a[4]);
        };
        for t in &tissue.triangles {
            let tri = [verts[t[0] as usize], verts[t[1] as usize], verts[t[2] as usize]];
            draw_triangle(&c, &mut wk.depth_t, &tri, false, &mut b, &mut frag);
        }
    } else {
        // Without smoke the transmittance is 1 and the haze the identity: the other four
        // attributes alone (each is interpolated on its own: the same numbers).
        wk.verts4.clear();
        wk.verts4.extend(wk.verts.iter().map(|v| Vtx { p: v.p, a: [v.a[0], v.a[1], v.a[2], v.a[3]] }));
        let verts = &wk.verts4;
        let mut frag = |idx: usize, _x: usize, _y: usize, _z: f32, a: &[f32; 4]| {
            let al = tissue.albedo(a[0], a[1]);
            colour[idx] = [al[0] * a[2] + a[3], al[1] * a[2] + a[3], al[2] * a[2] + a[3]];
        };
        for t in &tissue.triangles {
            let tri = [verts[t[0] as usize], verts[t[1] as usize], verts[t[2] as usize]];
            draw_triangle(&c, &mut wk.depth_t, &tri, false, &mut b, &mut frag);
        }
    }
}

/// 2×2 box down-sampling then a [1 2 1]/4 blur in both directions.
fn down_blur(
    src: &[[f32; 3]],
    sw: usize,
    sh: usize,
    dst: &mut Vec<[f32; 3]>,
    tmp: &mut Vec<[f32; 3]>,
) -> (usize, usize) {
    let (dw, dh) = (sw.div_ceil(2), sh.div_ceil(2));
    resize(dst, dw * dh, [0.0; 3]);
    resize(tmp, dw * dh, [0.0; 3]);
    for y in 0..dh {
        let (y0, y1) = (2 * y, (2 * y + 1).min(sh - 1));
        let (r0, r1) = (&src[y0 * sw..(y0 + 1) * sw], &src[y1 * sw..(y1 + 1) * sw]);
        let out = &mut tmp[y * dw..(y + 1) * dw];
        for (x, o) in out.iter_mut().enumerate() {
            let (x0, x1) = (2 * x, (2 * x + 1).min(sw - 1));
            let (a, b, c, d) = (r0[x0], r0[x1], r1[x0], r1[x1]);
            *o = [
                0.25 * (a[0] + b[0] + c[0] + d[0]),
                0.25 * (a[1] + b[1] + c[1] + d[1]),
                0.25 * (a[2] + b[2] + c[2] + d[2]),
            ];
        }
    }
    // Horizontal [1 2 1] into dst, vertical back into tmp, swap.
    // On flat rows of floats (the three channels alike, in loops the compiler vectorises);
    // the edge pixels repeat themselves as their missing neighbour.
    let blur = |l: f32, m: f32, r: f32| 0.25 * (l + 2.0 * m + r);
    for y in 0..dh {
        let src_row = tmp[y * dw..(y + 1) * dw].as_flattened();
        let out = dst[y * dw..(y + 1) * dw].as_flattened_mut();
        let n = 3 * dw;
        let first_r = if dw > 1 { 3 } else { 0 };
        for k in 0..3 {
            out[k] = blur(src_row[k], src_row[k], src_row[k + first_r]);
        }
        if dw > 1 {
            for k in n - 3..n {
                out[k] = blur(src_row[k - 3], src_row[k], src_row[k]);
            }
        }
        if dw > 2 {
            let inner = out[3..n - 3].iter_mut().zip(&src_row[..n - 6]).zip(&src_row[3..n - 3]).zip(&src_row[6..]);
            for (((o, &l), &m), &r) in inner {
                *o = blur(l, m, r);
            }
        }
    }
    for y in 0..dh {
        let (up, dn) = (y.saturating_sub(1) * dw, (y + 1).min(dh - 1) * dw);
        let ru = dst[up..up + dw].as_flattened();
        let rm = dst[y * dw..(y + 1) * dw].as_flattened();
        let rd = dst[dn..dn + dw].as_flattened();
        let out = tmp[y * dw..(y + 1) * dw].as_flattened_mut();
        for (((o, &u), &m), &d) in out.iter_mut().zip(ru).zip(rm).zip(rd) {
            *o = blur(u, m, d);
        }
    }
    std::mem::swap(dst, tmp);
    (dw, dh)
}

/// Where image coordinate `x` (pixel centre) falls in a level `scale` times smaller with
/// `n` samples: the sample before, the one after and the weight of the latter.
fn level_taps(out: &mut Vec<(u32, u32, f32)>, len: usize, n: usize, scale: f32) {
    out.clear();
    for x in 0..len {
        let f = ((x as f32 + 0.5) / scale - 0.5).clamp(0.0, (n - 1) as f32);
        let i = f as usize;
        out.push((i as u32, (i + 1).min(n - 1) as u32, f - i as f32));
    }
}

/// The defocus pyramid: three levels (radius ≈ 1, 2, 4 px) of `wk.out_lin` in `wk.levels`
/// and their sampling positions; returns the levels' sizes.
fn defocus_levels(wk: &mut EyeWork, w: usize, h: usize) -> [(usize, usize); 3] {
    let [l1, l2, l3] = &mut wk.levels;
    let d1 = down_blur(&wk.out_lin, w, h, l1, &mut wk.tmp);
    let d2 = down_blur(l1, d1.0, d1.1, l2, &mut wk.tmp);
    let d3 = down_blur(l2, d2.0, d2.1, l3, &mut wk.tmp);
    let dims = [d1, d2, d3];
    for (n, &(lw, lh)) in dims.iter().enumerate() {
        let scale = (2u32 << n) as f32;
        level_taps(&mut wk.taps_x[n], w, lw, scale);
        level_taps(&mut wk.taps_y[n], h, lh, scale);
    }
    dims
}

/// Bilinear sample of pyramid level `n` (1, 2 or 3) at image pixel `(x, y)`.
#[inline]
fn sample_level(wk: &EyeWork, dims: &[(usize, usize); 3], n: usize, x: usize, y: usize) -> [f32; 3] {
    let l = &wk.levels[n - 1];
    let lw = dims[n - 1].0;
    let (ix, ix1, tx) = wk.taps_x[n - 1][x];
    let (iy, iy1, ty) = wk.taps_y[n - 1][y];
    let (ix, ix1, iy, iy1) = (ix as usize, ix1 as usize, iy as usize, iy1 as usize);
    let (a, b, c, d) = (l[iy * lw + ix], l[iy * lw + ix1], l[iy1 * lw + ix], l[iy1 * lw + ix1]);
    let mut o = [0.0; 3];
    for k in 0..3 {
        let top = a[k] + (b[k] - a[k]) * tx;
        let bot = c[k] + (d[k] - c[k]) * tx;
        o[k] = top + (bot - top) * ty;
    }
    o
}

/// Depth-dependent defocus of one pixel (linear colour `own`, circle radius `rr` pixels):
/// interpolation between the two pyramid levels around its circle of confusion (a gather
/// blur: a pixel's blur follows its own depth, so a blurred edge does not spread onto a
/// sharp background).
#[inline]
fn defocus_gather(wk: &EyeWork, dims: &[(usize, usize); 3], own: [f32; 3], rr: f32, x: usize, y: usize) -> [f32; 3] {
    const R: [f32; 4] = [0.0, 1.0, 2.0, 4.0];
    let lvl = |n: usize| if n == 0 { own } else { sample_level(wk, dims, n, x, y) };
    let n = if rr < R[1] {
        0
    } else if rr < R[2] {
        1
    } else if rr < R[3] {
        2
    } else {
        3
    };
    if n == 3 {
        lvl(3)
    } else {
        let t = (rr - R[n]) / (R[n + 1] - R[n]);
        let (a, b) = (lvl(n), lvl(n + 1));
        [a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, a[2] + (b[2] - a[2]) * t]
    }
}

#[cfg(test)]
mod simd_tests {
    use super::*;

    #[test]
    fn srgb_indices_match_the_scalar_clamp() {
        let lut_max = (SRGB_LUT - 1) as f32;
        let mut val = vec![f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -1.0, -1e-5, -0.0, 0.0, 1.0, 1.5, 1e30];
        val.extend((0..5000).map(|i| i as f32 * 2.7e-4 - 0.2));
        let mut idx = vec![0; val.len()];
        srgb_indices(&val, &mut idx, lut_max);
        for (&v, &i) in val.iter().zip(&idx) {
            // The former per-channel formula.
            let want = ((v * lut_max + 0.5) as i32).clamp(0, SRGB_LUT as i32 - 1);
            assert_eq!(i, want, "{v}");
        }
    }
}
