//! The renderer's configuration (serde: every key optional in a TOML file, unknown keys
//! refused) and its validation.
//!
//! Units are in the key names: `_m` metres, `_rad` radians, `_s` seconds, `_px` pixels,
//! `_per_m` per metre; colours are linear RGB in `[0, 1]`.

use estimator::calib::Intrinsics;
use estimator::calib::camera::IntrinsicsError;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use serde::{Deserialize, Serialize};

use super::mesh::{GeometryError, InstrumentGeometry};

/// Largest image side accepted, pixels.
pub const MAX_SIDE_PX: u32 = 8192;

/// Everything the renderer needs besides the instrument mesh and the scene's motion.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EndoscopeConfig {
    /// Seed of the tissue texture and of the sensor noise.
    pub seed: u64,
    /// The stereo endoscope.
    pub camera: CameraConfig,
    /// Frame rate and exposure.
    pub timing: TimingConfig,
    /// The light at the endoscope tip.
    pub light: LightConfig,
    /// The parametric instrument (used when no OBJ is given).
    pub instrument: InstrumentGeometry,
    /// Materials of the instrument.
    pub materials: MaterialsConfig,
    /// The tissue surface.
    pub tissue: TissueConfig,
    /// The realism options, each on or off.
    pub realism: RealismConfig,
}

/// Pose as written in files: translation (metres) and unit quaternion `[w, x, y, z]`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseConfig {
    /// Translation, metres.
    pub translation_m: [f64; 3],
    /// Rotation as a unit quaternion `[w, x, y, z]` (normalised on use; must not be zero).
    pub quaternion_wxyz: [f64; 4],
}

impl PoseConfig {
    /// The identity pose.
    pub const IDENTITY: PoseConfig = PoseConfig { translation_m: [0.0; 3], quaternion_wxyz: [1.0, 0.0, 0.0, 0.0] };

    /// From an isometry.
    pub fn from_isometry(t: &Isometry3<f64>) -> Self {
        let q = t.rotation.quaternion();
        let v = t.translation.vector;
        Self { translation_m: [v.x, v.y, v.z], quaternion_wxyz: [q.w, q.i, q.j, q.k] }
    }

    /// The isometry, `None` when not finite or the quaternion is (nearly) zero.
    pub fn isometry(&self) -> Option<Isometry3<f64>> {
        let [w, x, y, z] = self.quaternion_wxyz;
        let q = Quaternion::new(w, x, y, z);
        let n = q.norm();
        if !(n.is_finite() && n > 1e-9 && self.translation_m.iter().all(|v| v.is_finite())) {
            return None;
        }
        let [tx, ty, tz] = self.translation_m;
        Some(Isometry3::from_parts(Translation3::new(tx, ty, tz), UnitQuaternion::from_quaternion(q)))
    }
}

/// The stereo endoscope: two identical, parallel pinhole cameras with distortion.
///
/// The left eye's frame is the endoscope camera frame `{c}` of `docs/calibration.md`
/// (`T_e_c = F4(q)·X`, z forward, x right, y down); the right eye sits at `+baseline_m` along
/// the left eye's `x` (so a point at depth `z` has disparity `u_left − u_right = fx·b/z > 0`
/// before distortion).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraConfig {
    /// Intrinsics of each eye (pixels, plumb-bob distortion), also the image size.
    pub intrinsics: Intrinsics,
    /// Distance between the optical centres, metres.
    pub baseline_m: f64,
    /// Hand-eye `X = T_f_c`: the left eye in the ECM end-effector frame `{f}`.
    pub hand_eye: PoseConfig,
}

impl Default for CameraConfig {
    /// 640×480, f = 400 px (77° × 62° field of view), mild barrel distortion, 5 mm baseline,
    /// the left eye 2.5 mm off the endoscope axis.
    fn default() -> Self {
        Self {
            intrinsics: Intrinsics {
                fx: 400.0,
                fy: 400.0,
                cx: 319.5,
                cy: 239.5,
                skew: 0.0,
                width: 640,
                height: 480,
                distortion: [-0.08, 0.01, 0.0, 0.0, 0.0],
            },
            baseline_m: 0.005,
            hand_eye: PoseConfig { translation_m: [-0.0025, 0.0, 0.0], quaternion_wxyz: [1.0, 0.0, 0.0, 0.0] },
        }
    }
}

/// Frame timing: the caller's clock stamps each frame with its exposure's mid time.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TimingConfig {
    /// Frames per second (the period of [`super::frame_mid_time_ns`]).
    pub fps: f64,
    /// Exposure time, seconds (at most one frame period); the span of the motion blur.
    pub exposure_s: f64,
}

impl Default for TimingConfig {
    fn default() -> Self {
        Self { fps: 30.0, exposure_s: 0.016 }
    }
}

/// The light at the endoscope tip (the midpoint of the two optical centres).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LightConfig {
    /// Irradiance scale: a surface facing the light at `reference_distance_m` receives
    /// `intensity`; it falls off with the inverse square of the distance.
    pub intensity: f64,
    /// Reference distance, metres.
    pub reference_distance_m: f64,
    /// Ambient light (fraction of the albedo), for the parts the tip light does not reach.
    pub ambient: f64,
}

impl Default for LightConfig {
    fn default() -> Self {
        Self { intensity: 1.0, reference_distance_m: 0.09, ambient: 0.04 }
    }
}

/// A Blinn-Phong material: diffuse albedo plus a specular lobe.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Material {
    /// Diffuse albedo, linear RGB.
    pub diffuse: [f64; 3],
    /// Specular colour, linear RGB (metals: tinted like the metal).
    pub specular: [f64; 3],
    /// Blinn-Phong exponent (higher: smaller, sharper highlights).
    pub shininess: f64,
}

/// Materials of the instrument parts.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MaterialsConfig {
    /// The shaft (brushed stainless steel by default).
    pub shaft: Material,
    /// The wrist link and the jaws (polished steel).
    pub tip: Material,
    /// The second instrument's shaft (dark, insulated), to tell the two apart.
    pub second_shaft: Material,
}

impl Default for MaterialsConfig {
    fn default() -> Self {
        Self {
            shaft: Material { diffuse: [0.13, 0.13, 0.14], specular: [0.45, 0.45, 0.47], shininess: 24.0 },
            tip: Material { diffuse: [0.12, 0.12, 0.125], specular: [0.7, 0.7, 0.72], shininess: 64.0 },
            second_shaft: Material { diffuse: [0.05, 0.05, 0.055], specular: [0.35, 0.35, 0.35], shininess: 32.0 },
        }
    }
}

/// The tissue: a height field facing the endoscope, in the world frame `{e}` (the ECM's
/// remote centre of motion), with a procedural texture.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TissueConfig {
    /// Mean plane `z = plane_z_m` in `{e}` (metres along the ECM axis at zero joints).
    pub plane_z_m: f64,
    /// Side of the square patch, metres, centred on the `{e}` z axis.
    pub extent_m: f64,
    /// Grid cells per side of the height-field mesh.
    pub grid: usize,
    /// Texture side, texels (precomputed once per seed).
    pub texture_px: usize,
    /// Peak-to-peak height of the folds, metres (toward the endoscope).
    pub fold_amplitude_m: f64,
    /// Specular strength of the wet surface (0: matte).
    pub wet_specular: f64,
}

impl Default for TissueConfig {
    fn default() -> Self {
        Self {
            plane_z_m: 0.16,
            extent_m: 0.34,
            grid: 72,
            texture_px: 1024,
            fold_amplitude_m: 0.012,
            wet_specular: 0.12,
        }
    }
}

/// The realism options; each can be switched off.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RealismConfig {
    /// Specular highlights on the instrument (Blinn-Phong); off: diffuse only.
    pub specular: bool,
    /// The procedural tissue texture (noise, red-pink tones, vessels, folds); off: a flat
    /// pink albedo on the same geometry.
    pub tissue_texture: bool,
    /// Vignetting.
    pub vignetting: VignettingConfig,
    /// Depth-dependent defocus blur.
    pub defocus: DefocusConfig,
    /// Motion blur over the exposure.
    pub motion_blur: MotionBlurConfig,
    /// Sensor noise.
    pub noise: NoiseConfig,
    /// A second instrument that crosses and occludes (when the scene has one).
    pub second_instrument: bool,
    /// Surgical smoke (haze growing with depth).
    pub smoke: SmokeConfig,
}

impl Default for RealismConfig {
    /// The default set: everything but the second instrument and smoke.
    fn default() -> Self {
        Self {
            specular: true,
            tissue_texture: true,
            vignetting: VignettingConfig::default(),
            defocus: DefocusConfig::default(),
            motion_blur: MotionBlurConfig::default(),
            noise: NoiseConfig::default(),
            second_instrument: false,
            smoke: SmokeConfig::default(),
        }
    }
}

impl RealismConfig {
    /// Every option off: the ideal image (flat tissue albedo, diffuse metal, no blur, no noise).
    pub fn none() -> Self {
        Self {
            specular: false,
            tissue_texture: false,
            vignetting: VignettingConfig { enabled: false, ..Default::default() },
            defocus: DefocusConfig { enabled: false, ..Default::default() },
            motion_blur: MotionBlurConfig { enabled: false, ..Default::default() },
            noise: NoiseConfig { enabled: false, ..Default::default() },
            second_instrument: false,
            smoke: SmokeConfig { enabled: false, ..Default::default() },
        }
    }
}

/// Vignetting: gain `1 − strength·(1 − cos⁴θ)` at the angle θ of the pixel's ray to the
/// optical axis (on top of the light's own inverse-square falloff).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VignettingConfig {
    /// On/off.
    pub enabled: bool,
    /// 0: none, 1: the full cos⁴ law.
    pub strength: f64,
}

impl Default for VignettingConfig {
    fn default() -> Self {
        Self { enabled: true, strength: 0.8 }
    }
}

/// Thin-lens defocus: circle of confusion (diameter, pixels)
/// `c = aperture_m · fx · |1/z − 1/focus_distance_m|`, clamped to `max_coc_px`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DefocusConfig {
    /// On/off.
    pub enabled: bool,
    /// Distance in focus, metres (along the optical axis).
    pub focus_distance_m: f64,
    /// Aperture diameter, metres.
    pub aperture_m: f64,
    /// Largest circle of confusion, pixels (diameter).
    pub max_coc_px: f64,
}

impl Default for DefocusConfig {
    fn default() -> Self {
        Self { enabled: true, focus_distance_m: 0.09, aperture_m: 0.0008, max_coc_px: 8.0 }
    }
}

/// Motion blur: the instruments are rendered at `samples` instants spread evenly over the
/// exposure and averaged (the endoscope is taken as still during one exposure).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MotionBlurConfig {
    /// On/off (off: one instant, the exposure's mid time).
    pub enabled: bool,
    /// Instants per exposure, odd (the middle one is the mid time, the ground truth's).
    pub samples: usize,
}

impl Default for MotionBlurConfig {
    fn default() -> Self {
        Self { enabled: true, samples: 3 }
    }
}

/// Poisson-Gaussian sensor noise on the linear signal `x ∈ [0, 1]` (1 = full well):
/// `x + N(0, (x·full_well_e + read_noise_e²)) / full_well_e`, the shot noise's Poisson law
/// approximated by its Gaussian (exact in mean and variance).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NoiseConfig {
    /// On/off.
    pub enabled: bool,
    /// Electrons at full scale.
    pub full_well_e: f64,
    /// Read noise, electrons (standard deviation).
    pub read_noise_e: f64,
}

impl Default for NoiseConfig {
    fn default() -> Self {
        Self { enabled: true, full_well_e: 2500.0, read_noise_e: 4.0 }
    }
}

/// Smoke: transmittance `exp(−density_per_m · z)` over the depth `z`, the rest is the haze
/// colour lit by the tip light.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SmokeConfig {
    /// On/off.
    pub enabled: bool,
    /// Extinction per metre of depth.
    pub density_per_m: f64,
    /// Haze colour, linear RGB.
    pub colour: [f64; 3],
}

impl Default for SmokeConfig {
    fn default() -> Self {
        Self { enabled: false, density_per_m: 9.0, colour: [0.62, 0.58, 0.56] }
    }
}

/// Why a configuration is unusable (the key is named).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ConfigError {
    /// Bad intrinsics.
    #[error("camera.intrinsics: {0}")]
    Intrinsics(#[from] IntrinsicsError),
    /// Image larger than [`MAX_SIDE_PX`].
    #[error("camera.intrinsics: image {width}x{height} larger than {MAX_SIDE_PX} px a side")]
    TooLarge {
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
    },
    /// Distortion so strong that the image border does not undistort.
    #[error("camera.intrinsics.distortion: the image border does not undistort (distortion too strong)")]
    Distortion,
    /// A key out of range or not finite.
    #[error("{key}: {why}")]
    Range {
        /// The key.
        key: &'static str,
        /// What is wrong.
        why: &'static str,
    },
    /// Bad instrument dimensions.
    #[error("instrument: {0}")]
    Geometry(#[from] GeometryError),
}

fn check(ok: bool, key: &'static str, why: &'static str) -> Result<(), ConfigError> {
    if ok { Ok(()) } else { Err(ConfigError::Range { key, why }) }
}

fn finite_pos(v: f64) -> bool {
    v.is_finite() && v > 0.0
}

fn unit_colour(c: &[f64; 3]) -> bool {
    c.iter().all(|v| v.is_finite() && (0.0..=1.0).contains(v))
}

impl EndoscopeConfig {
    /// Checks every key; the renderer refuses a configuration that does not pass.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let k = &self.camera.intrinsics;
        k.validate()?;
        if k.width > MAX_SIDE_PX || k.height > MAX_SIDE_PX {
            return Err(ConfigError::TooLarge { width: k.width, height: k.height });
        }
        check(finite_pos(self.camera.baseline_m) && self.camera.baseline_m < 0.1, "camera.baseline_m", "in (0, 0.1)")?;
        check(self.camera.hand_eye.isometry().is_some(), "camera.hand_eye", "finite, non-zero quaternion")?;
        let t = &self.timing;
        check(finite_pos(t.fps) && t.fps <= 10_000.0, "timing.fps", "in (0, 10000]")?;
        check(t.exposure_s.is_finite() && t.exposure_s >= 0.0, "timing.exposure_s", "finite, ≥ 0")?;
        check(t.exposure_s <= 1.0 / t.fps, "timing.exposure_s", "at most one frame period")?;
        let l = &self.light;
        check(l.intensity.is_finite() && l.intensity >= 0.0, "light.intensity", "finite, ≥ 0")?;
        check(finite_pos(l.reference_distance_m), "light.reference_distance_m", "finite, > 0")?;
        check(l.ambient.is_finite() && (0.0..=1.0).contains(&l.ambient), "light.ambient", "in [0, 1]")?;
        self.instrument.validate()?;
        for (m, key) in [
            (&self.materials.shaft, "materials.shaft"),
            (&self.materials.tip, "materials.tip"),
            (&self.materials.second_shaft, "materials.second_shaft"),
        ] {
            check(
                unit_colour(&m.diffuse) && unit_colour(&m.specular) && m.shininess.is_finite() && m.shininess >= 1.0,
                key,
                "colours in [0, 1], shininess ≥ 1",
            )?;
        }
        let s = &self.tissue;
        check(s.plane_z_m.is_finite(), "tissue.plane_z_m", "finite")?;
        check(finite_pos(s.extent_m) && s.extent_m <= 10.0, "tissue.extent_m", "in (0, 10]")?;
        check((2..=512).contains(&s.grid), "tissue.grid", "in 2..=512")?;
        check((16..=4096).contains(&s.texture_px), "tissue.texture_px", "in 16..=4096")?;
        check(s.fold_amplitude_m.is_finite() && s.fold_amplitude_m >= 0.0, "tissue.fold_amplitude_m", "finite, ≥ 0")?;
        check(s.wet_specular.is_finite() && (0.0..=1.0).contains(&s.wet_specular), "tissue.wet_specular", "in [0, 1]")?;
        let r = &self.realism;
        check(
            r.vignetting.strength.is_finite() && (0.0..=1.0).contains(&r.vignetting.strength),
            "realism.vignetting.strength",
            "in [0, 1]",
        )?;
        let d = &r.defocus;
        check(finite_pos(d.focus_distance_m), "realism.defocus.focus_distance_m", "finite, > 0")?;
        check(d.aperture_m.is_finite() && d.aperture_m >= 0.0, "realism.defocus.aperture_m", "finite, ≥ 0")?;
        check(
            d.max_coc_px.is_finite() && (0.0..=64.0).contains(&d.max_coc_px),
            "realism.defocus.max_coc_px",
            "in [0, 64]",
        )?;
        let m = &r.motion_blur;
        check(m.samples % 2 == 1 && m.samples <= 31, "realism.motion_blur.samples", "odd, 1..=31")?;
        let n = &r.noise;
        check(finite_pos(n.full_well_e), "realism.noise.full_well_e", "finite, > 0")?;
        check(n.read_noise_e.is_finite() && n.read_noise_e >= 0.0, "realism.noise.read_noise_e", "finite, ≥ 0")?;
        let sm = &r.smoke;
        check(sm.density_per_m.is_finite() && sm.density_per_m >= 0.0, "realism.smoke.density_per_m", "finite, ≥ 0")?;
        check(unit_colour(&sm.colour), "realism.smoke.colour", "in [0, 1]")?;
        Ok(())
    }
}

impl Default for EndoscopeConfig {
    fn default() -> Self {
        Self {
            seed: 1,
            camera: CameraConfig::default(),
            timing: TimingConfig::default(),
            light: LightConfig::default(),
            instrument: InstrumentGeometry::default(),
            materials: MaterialsConfig::default(),
            tissue: TissueConfig::default(),
            realism: RealismConfig::default(),
        }
    }
}
