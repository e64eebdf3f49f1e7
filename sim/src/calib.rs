//! The calibration paper's simulation protocol (Wang et al. 2017, Sec. IV) with ground truth.
//!
//! An ECM-like robot 1 holds the camera, a PSM-like robot 2 the tool
//! ([`estimator::calib::rcm_arms`]). Joint grids: `n_e` values of each of the ECM's four
//! joints (`n_e⁴` poses) × `n_t` values of the PSM's yaw and pitch (`n_t²` poses) at a fixed
//! insertion; every combination is one observation. The camera and tool are placed with the
//! *actual* (perturbed) kinematics, the dataset records the *nominal* joints: each of the ECM
//! end-effector frame and PSM frames 2 and 3 is `T·exp(δ^)` (chained: the perturbed frame 2
//! carries frame 3), `δ = (ρ, φ) ~ N(0, σ² I6)` drawn independently per observation and frame.
//! `φ` is in radians; `ρ` in millimetres or metres ([`NoiseUnits`]) — the paper does not say.
//!
//! The observed line: the actual shaft from the tool tip back toward the RCM, clipped to the
//! part in front of the camera and inside the image (shrunk by the rule's margin); its two end
//! points (pixels) are the observation. The detector's acceptance rule
//! ([`CalibGeometry::selection`], [`SelectionRule`]) decides which lines are recorded: enough
//! visible shaft, and the tip in view when the rule requires it; the others are dropped and
//! counted.
//!
//! The instruments are solid ([`Bodies`], session 22): a combination whose actual tool shaft
//! (tip to RCM) would pass through the endoscope (its RCM to the lens), closer than the sum of
//! their radii, is not generated and is counted apart ([`CalibDataset::collided`]); one whose
//! camera sits inside the shaft's cylinder extended past the tip sees the shaft end-on, has no
//! silhouette lines, and is dropped with the lines out of view. Before session 22 the
//! generator let the instrument pass through the lens, which put singular line images in the
//! data (docs/calibration.md, "Session 21: a millimetre refusal traced...").
//!
//! [`random_geometry`] draws valid scenes for the generalisation protocol (RCM-to-RCM distance,
//! tool-to-scope angle, twist, joint ranges that keep the tool in view, lens distortion).
//!
//! Deterministic: the same protocol and seed give the same dataset (ChaCha8).

use estimator::calib::rcm_arms::{ecm_frames, psm_frames, se3_exp};
use estimator::calib::{Eye, Intrinsics, KinematicNoise, Observation, SelectionRule, Setup, ShaftExtent};
use nalgebra::{Isometry3, Rotation3, Translation3, UnitQuaternion, Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

/// In which unit the translation part `ρ` of the noise `δ` is read.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NoiseUnits {
    /// `ρ` in millimetres: σ = 0.01 is 10 µm per frame, the noise is almost purely rotational
    /// (the reading that reproduces the paper's figures).
    Millimetre,
    /// `ρ` in metres: σ = 0.01 is 10 mm per frame (the hard case).
    Metre,
}

impl NoiseUnits {
    /// Metres per unit of `ρ`.
    pub fn metres(self) -> f64 {
        match self {
            NoiseUnits::Millimetre => 1e-3,
            NoiseUnits::Metre => 1.0,
        }
    }
    /// Short name (`mm` / `m`).
    pub fn name(self) -> &'static str {
        match self {
            NoiseUnits::Millimetre => "mm",
            NoiseUnits::Metre => "m",
        }
    }
}

/// The simulated scene: camera, hand-eye, ground truth and the joint ranges of the grids.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CalibGeometry {
    /// Camera intrinsics (pixels).
    pub intrinsics: Intrinsics,
    /// Hand-eye `T_f_c` (metres).
    pub hand_eye: Isometry3<f64>,
    /// Ground truth `T_e_t` (metres).
    pub truth: Isometry3<f64>,
    /// ECM yaw range, radians (grid from min to max).
    pub ecm_yaw_rad: [f64; 2],
    /// ECM pitch range, radians.
    pub ecm_pitch_rad: [f64; 2],
    /// ECM insertion range, metres.
    pub ecm_insertion_m: [f64; 2],
    /// ECM roll range, radians.
    pub ecm_roll_rad: [f64; 2],
    /// PSM yaw range, radians.
    pub psm_yaw_rad: [f64; 2],
    /// PSM pitch range, radians.
    pub psm_pitch_rad: [f64; 2],
    /// PSM insertion (fixed), metres.
    pub psm_insertion_m: f64,
    /// The line detector's acceptance rule (pixels as measured).
    pub selection: SelectionRule,
    /// The instruments' bodies: a combination that puts the tool shaft through the endoscope
    /// is physically impossible and is not generated ([`Bodies`]).
    pub bodies: Bodies,
}

/// The two instruments as cylinders, for the rule that no generated pose puts one through the
/// other: the tool's shaft (tip to its RCM) and the endoscope (its RCM to the lens, closed by
/// a hemisphere at the lens) must stay at least `tool_radius_m + scope_radius_m` apart,
/// measured between their axes' segments in robot 1's RCM frame `{e}` (metres).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bodies {
    /// Radius of the tool's shaft, metres (an 8 mm instrument: 0.004).
    pub tool_radius_m: f64,
    /// Radius of the endoscope, metres (a 10 mm laparoscope: 0.005).
    pub scope_radius_m: f64,
}

impl Default for Bodies {
    /// An 8 mm instrument beside a 10 mm endoscope.
    fn default() -> Self {
        Self { tool_radius_m: 0.004, scope_radius_m: 0.005 }
    }
}

impl Bodies {
    /// No bodies: every combination is generated, the tool may pass through the lens (the
    /// protocol as sessions 15-21 ran it; kept for comparison).
    pub const NONE: Self = Self { tool_radius_m: 0.0, scope_radius_m: 0.0 };

    /// Whether the tool shaft (segment `tip_e` → `rcm_e`) collides with the endoscope
    /// (segment `scope_rcm_e` → `lens_e`), all in `{e}`, metres.
    pub fn collide(
        &self,
        tip_e: &Vector3<f64>,
        rcm_e: &Vector3<f64>,
        scope_rcm_e: &Vector3<f64>,
        lens_e: &Vector3<f64>,
    ) -> bool {
        let clearance = self.tool_radius_m + self.scope_radius_m;
        clearance > 0.0 && segment_distance(tip_e, rcm_e, scope_rcm_e, lens_e) < clearance
    }

    /// Whether the camera (optical centre `lens_e`) lies inside the tool shaft's cylinder
    /// extended along its axis (through `tip_e`, unit direction `back_e`), all in `{e}`,
    /// metres: it then sees the shaft end-on, with no silhouette lines (the tangent planes
    /// from the optical centre to the cylinder do not exist), and no line can be detected.
    pub fn end_on(&self, tip_e: &Vector3<f64>, back_e: &Vector3<f64>, lens_e: &Vector3<f64>) -> bool {
        let v = lens_e - tip_e;
        (v - back_e * v.dot(back_e)).norm() < self.tool_radius_m
    }
}

/// The shortest distance between segments `p0 p1` and `q0 q1` (same unit as the points).
/// The closest points are found by minimising over the two segment parameters in `[0, 1]²`
/// (Ericson, "Real-Time Collision Detection", 2005, Sec. 5.1.9); degenerate segments (points)
/// and parallel segments are handled.
pub fn segment_distance(p0: &Vector3<f64>, p1: &Vector3<f64>, q0: &Vector3<f64>, q1: &Vector3<f64>) -> f64 {
    let d1 = p1 - p0;
    let d2 = q1 - q0;
    let r = p0 - q0;
    let (a, e, f) = (d1.norm_squared(), d2.norm_squared(), d2.dot(&r));
    let tiny = 1e-18;
    let (s, t) = if a <= tiny && e <= tiny {
        (0.0, 0.0)
    } else if a <= tiny {
        (0.0, (f / e).clamp(0.0, 1.0))
    } else {
        let c = d1.dot(&r);
        if e <= tiny {
            ((-c / a).clamp(0.0, 1.0), 0.0)
        } else {
            let b = d1.dot(&d2);
            let denom = a * e - b * b;
            let mut s = if denom > tiny * a * e { ((b * f - c * e) / denom).clamp(0.0, 1.0) } else { 0.0 };
            let mut t = (b * s + f) / e;
            if t < 0.0 {
                t = 0.0;
                s = (-c / a).clamp(0.0, 1.0);
            } else if t > 1.0 {
                t = 1.0;
                s = ((b - c) / a).clamp(0.0, 1.0);
            }
            (s, t)
        }
    };
    ((p0 + d1 * s) - (q0 + d2 * t)).norm()
}

impl Default for CalibGeometry {
    /// The documented default scene (`docs/calibration.md`): 640×480 camera, f = 320 px
    /// (90° × 74° field of view, a wide-angle laparoscope);
    /// robot 2's RCM 136 mm from robot 1's; ±15° arm motions, ECM insertion 40-120 mm,
    /// PSM insertion 120 mm; the original protocol's rule: the tip in view and 40 px of shaft.
    fn default() -> Self {
        let deg = core::f64::consts::PI / 180.0;
        let t = Vector3::new(0.100, 0.020, 0.090);
        // Tool pointing from its RCM toward a point on robot 1's shaft axis, 240 mm deep,
        // with a 40° twist about the shaft so the rotation is generic.
        let aim = (Vector3::new(0.0, 0.0, 0.24) - t).normalize();
        let r = UnitQuaternion::rotation_between(&Vector3::z(), &aim).unwrap_or_else(UnitQuaternion::identity)
            * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 40.0 * deg);
        Self {
            intrinsics: Intrinsics {
                fx: 320.0,
                fy: 320.0,
                cx: 319.5,
                cy: 239.5,
                skew: 0.0,
                width: 640,
                height: 480,
                distortion: [0.0; 5],
            },
            hand_eye: Isometry3::from_parts(
                Translation3::new(0.0025, -0.001, 0.0005),
                UnitQuaternion::from_euler_angles(-2.0 * deg, 3.0 * deg, 0.0),
            ),
            truth: Isometry3::from_parts(Translation3::from(t), r),
            ecm_yaw_rad: [-15.0 * deg, 15.0 * deg],
            ecm_pitch_rad: [-15.0 * deg, 15.0 * deg],
            ecm_insertion_m: [0.040, 0.120],
            ecm_roll_rad: [-15.0 * deg, 15.0 * deg],
            psm_yaw_rad: [-15.0 * deg, 15.0 * deg],
            psm_pitch_rad: [-15.0 * deg, 15.0 * deg],
            psm_insertion_m: 0.120,
            selection: SelectionRule { ends_are_shaft_ends: true, ..SelectionRule::tip_in_view(40.0) },
            bodies: Bodies::default(),
        }
    }
}

/// One run of the protocol.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CalibProtocol {
    /// The scene.
    pub geometry: CalibGeometry,
    /// Values per ECM joint (`n_e⁴` ECM poses), 1..=8.
    pub n_e: usize,
    /// Values per PSM joint (`n_t²` PSM poses), 1..=16.
    pub n_t: usize,
    /// σ of every component of δ (dimensionless; see [`NoiseUnits`]).
    pub sigma: f64,
    /// Unit of δ's translation part.
    pub units: NoiseUnits,
    /// σ of each coordinate of the observed line points, pixels (0 in the paper's protocol).
    pub pixel_sigma_px: f64,
    /// Seed of the noise.
    pub seed: u64,
}

impl CalibProtocol {
    /// The noiseless 3⁴×3² grid of `geometry` (σ = 0, no pixel noise, seed 0): what a scene
    /// records without noise, for validity checks and tests.
    pub fn noiseless(geometry: CalibGeometry) -> Self {
        Self { geometry, n_e: 3, n_t: 3, sigma: 0.0, units: NoiseUnits::Millimetre, pixel_sigma_px: 0.0, seed: 0 }
    }
}

/// A simulated dataset with its ground truth.
#[derive(Clone, Debug)]
pub struct CalibDataset {
    /// Intrinsics and hand-eye.
    pub setup: Setup,
    /// Ground truth `T_e_t` (metres).
    pub truth: Isometry3<f64>,
    /// The kept observations (nominal joints, observed line).
    pub observations: Vec<Observation>,
    /// Joint combinations tried (`n_e⁴ n_t²`).
    pub generated: usize,
    /// Combinations dropped because the tool was not (enough) in view, or seen end-on
    /// ([`Bodies::end_on`]).
    pub dropped: usize,
    /// Combinations not generated because the tool shaft would pass through the endoscope
    /// ([`Bodies`]); `generated = observations + dropped + collided`.
    pub collided: usize,
    /// The injected noise as a model for the estimator and the CRB (`None` when noiseless).
    pub noise: Option<KinematicNoise>,
}

/// Why a protocol cannot be run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibProtocolError {
    /// Grid sizes out of range.
    #[error("grid sizes out of range: n_e = {n_e} (1..=8), n_t = {n_t} (1..=16)")]
    Grid {
        /// Values per ECM joint.
        n_e: usize,
        /// Values per PSM joint.
        n_t: usize,
    },
    /// σ negative or not finite.
    #[error("noise σ must be finite and ≥ 0 (sigma = {sigma}, pixel_sigma_px = {pixel})")]
    Sigma {
        /// Kinematic σ.
        sigma: f64,
        /// Pixel σ.
        pixel: f64,
    },
    /// No combination had the tool in view.
    #[error("no observation has the tool in view ({generated} combinations tried)")]
    NothingInView {
        /// Combinations tried.
        generated: usize,
    },
}

fn grid(range: [f64; 2], n: usize) -> Vec<f64> {
    if n == 1 {
        return vec![0.5 * (range[0] + range[1])];
    }
    (0..n).map(|i| range[0] + (range[1] - range[0]) * i as f64 / (n - 1) as f64).collect()
}

/// The ECM poses of the grid (`n_e⁴`), `[yaw, pitch, insertion, roll]`.
pub fn ecm_grid(g: &CalibGeometry, n_e: usize) -> Vec<[f64; 4]> {
    let (a, b, c, d) =
        (grid(g.ecm_yaw_rad, n_e), grid(g.ecm_pitch_rad, n_e), grid(g.ecm_insertion_m, n_e), grid(g.ecm_roll_rad, n_e));
    let mut out = Vec::with_capacity(n_e.pow(4));
    for &q1 in &a {
        for &q2 in &b {
            for &q3 in &c {
                for &q4 in &d {
                    out.push([q1, q2, q3, q4]);
                }
            }
        }
    }
    out
}

/// The PSM poses of the grid (`n_t²`), `[yaw, pitch, insertion]`.
pub fn psm_grid(g: &CalibGeometry, n_t: usize) -> Vec<[f64; 3]> {
    let (a, b) = (grid(g.psm_yaw_rad, n_t), grid(g.psm_pitch_rad, n_t));
    let mut out = Vec::with_capacity(n_t * n_t);
    for &q1 in &a {
        for &q2 in &b {
            out.push([q1, q2, g.psm_insertion_m]);
        }
    }
    out
}

fn draw(rng: &mut ChaCha8Rng, sigma: f64, rho_m: f64) -> Isometry3<f64> {
    if sigma == 0.0 {
        return Isometry3::identity();
    }
    let mut v = [0.0; 6];
    for x in &mut v {
        let z: f64 = rng.sample(StandardNormal);
        *x = z * sigma;
    }
    se3_exp(&(Vector3::new(v[0], v[1], v[2]) * rho_m), &Vector3::new(v[3], v[4], v[5]))
}

/// The observed line of the actual shaft (tip `tip_e`, unit direction `back_e` toward the
/// RCM, both in `{e}`) seen by camera `cam` (`T_e_c`): the end points (pixels) of its part in
/// front of the camera and inside the image shrunk by the rule's margin, or `None` when the
/// rule rejects it (too little visible shaft, or the tip out of view when required).
pub fn observe_shaft(
    g: &CalibGeometry,
    cam: &Isometry3<f64>,
    tip_e: &Vector3<f64>,
    back_e: &Vector3<f64>,
    length_m: f64,
) -> Option<[Vector2<f64>; 2]> {
    let inv = cam.inverse();
    let k = &g.intrinsics;
    let rule = &g.selection;
    let m = rule.border_margin_px;
    let see = |s: f64| -> Option<Vector2<f64>> {
        let p = inv * nalgebra::Point3::from(tip_e + back_e * s);
        if p.z < 0.005 {
            return None;
        }
        let px = k.project(&p.coords);
        let inside = px.x >= m && px.y >= m && px.x <= k.width as f64 - 1.0 - m && px.y <= k.height as f64 - 1.0 - m;
        inside.then_some(px)
    };
    // The visible part is one interval of the shaft (a segment in front of the camera projects
    // to a segment, the image is convex): find it on a fine grid, then sharpen its ends.
    let steps = 400;
    let at = |i: usize| length_m * i as f64 / steps as f64;
    let first = (0..=steps).find(|&i| see(at(i)).is_some())?;
    if rule.require_tip_in_view && first != 0 {
        return None;
    }
    let last = (first..=steps).take_while(|&i| see(at(i)).is_some()).last().unwrap_or(first);
    // Bisection between an outside and an inside sample.
    let sharpen = |inside: f64, outside: f64| -> f64 {
        let (mut a, mut b) = (inside, outside);
        for _ in 0..30 {
            let c = 0.5 * (a + b);
            if see(c).is_some() { a = c } else { b = c }
        }
        a
    };
    let s0 = if first == 0 { 0.0 } else { sharpen(at(first), at(first - 1)) };
    let s1 = if last == steps { length_m } else { sharpen(at(last), at(last + 1)) };
    let (a, b) = (see(s0)?, see(s1)?);
    ((b - a).norm() >= rule.min_visible_shaft_px.max(1e-6)).then_some([a, b])
}

/// Runs the protocol: every grid combination, perturbed, projected, kept when in view.
pub fn generate_calibration(p: &CalibProtocol) -> Result<CalibDataset, CalibProtocolError> {
    if !(1..=8).contains(&p.n_e) || !(1..=16).contains(&p.n_t) {
        return Err(CalibProtocolError::Grid { n_e: p.n_e, n_t: p.n_t });
    }
    if !(p.sigma.is_finite() && p.sigma >= 0.0 && p.pixel_sigma_px.is_finite() && p.pixel_sigma_px >= 0.0) {
        return Err(CalibProtocolError::Sigma { sigma: p.sigma, pixel: p.pixel_sigma_px });
    }
    let g = &p.geometry;
    let rho = p.units.metres();
    let mut rng = ChaCha8Rng::seed_from_u64(p.seed);
    let ecm = ecm_grid(g, p.n_e);
    let psm = psm_grid(g, p.n_t);
    let mut observations = Vec::with_capacity(ecm.len() * psm.len());
    let mut dropped = 0;
    let mut collided = 0;
    for qe in &ecm {
        let f4 = ecm_frames(qe)[3];
        for qt in &psm {
            // Always draw all three perturbations so the stream does not depend on drops.
            let de = draw(&mut rng, p.sigma, rho);
            let da = draw(&mut rng, p.sigma, rho);
            let db = draw(&mut rng, p.sigma, rho);
            let (n0, n1, n2, n3): (f64, f64, f64, f64) = (
                rng.sample(StandardNormal),
                rng.sample(StandardNormal),
                rng.sample(StandardNormal),
                rng.sample(StandardNormal),
            );
            let cam = f4 * de * g.hand_eye;
            let fr = psm_frames(qt);
            let f2 = fr[1] * da;
            let f3 = f2 * Isometry3::translation(0.0, 0.0, qt[2]) * db;
            let tip_e = g.truth * nalgebra::Point3::from(f3.translation.vector);
            let back_e = g.truth.rotation * (f3.rotation * -Vector3::z());
            let rcm_e = tip_e.coords + back_e * qt[2];
            let lens_e = cam.translation.vector;
            if g.bodies.collide(&tip_e.coords, &rcm_e, &Vector3::zeros(), &lens_e) {
                collided += 1;
                continue;
            }
            if g.bodies.end_on(&tip_e.coords, &back_e, &lens_e) {
                dropped += 1;
                continue;
            }
            match observe_shaft(g, &cam, &tip_e.coords, &back_e, qt[2]) {
                Some([a, b]) => {
                    let s = p.pixel_sigma_px;
                    observations.push(Observation {
                        ecm_joints: *qe,
                        psm_joints: *qt,
                        tool_point_m: [0.0; 3],
                        line_px: [[a.x + s * n0, a.y + s * n1], [b.x + s * n2, b.y + s * n3]],
                        eye: Eye::Left,
                    });
                }
                None => dropped += 1,
            }
        }
    }
    let generated = ecm.len() * psm.len();
    if observations.is_empty() {
        return Err(CalibProtocolError::NothingInView { generated });
    }
    let noise = KinematicNoise { rot_rad: p.sigma, trans_m: p.sigma * rho, pixel_px: p.pixel_sigma_px };
    Ok(CalibDataset {
        setup: Setup {
            intrinsics: g.intrinsics,
            hand_eye: g.hand_eye,
            right_eye: None,
            selection: g.selection,
            shaft_extent: ShaftExtent::default(),
        },
        truth: g.truth,
        observations,
        generated,
        dropped,
        collided,
        noise: noise.is_valid().then_some(noise),
    })
}

/// What [`random_geometry`] drew, for grouping results by geometry class.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GeometryDraw {
    /// The scene.
    pub geometry: CalibGeometry,
    /// Distance between the two RCMs, metres.
    pub rcm_distance_m: f64,
    /// Angle between the tool axis (at zero joints) and the scope axis, radians.
    pub tool_scope_angle_rad: f64,
    /// Whether the lens has distortion.
    pub distorted: bool,
}

/// Why no valid scene was drawn.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[error("no valid scene geometry after {attempts} draws (seed {seed})")]
pub struct RandomGeometryError {
    /// Draws tried.
    pub attempts: usize,
    /// The seed.
    pub seed: u64,
}

/// Draws a valid random scene (ChaCha8 from `seed`), for the generalisation protocol:
/// - robot 2's RCM 80-250 mm from robot 1's, the tool axis (zero joints) 20-70° from the
///   scope axis at a random azimuth, aimed at a working point 80-260 mm deep on the scope
///   axis, with a random twist about the tool axis;
/// - a 640×480 camera with a 60-90° horizontal field of view, radial/tangential distortion
///   when `distortion` (k1 −0.3..−0.05, k2 0..0.1, p1, p2 ±0.002; redrawn unless the
///   undistortion converges over the whole image), a random small hand-eye;
/// - joint ranges: ECM yaw/pitch ±4° up to ±30 % of the half field of view, roll ±10-30°,
///   insertion putting the camera 40-120 mm from the working point; PSM yaw/pitch ±5-12°;
///   kept only when the tool stays in view (below);
/// - the detector's rule: 40 px of visible shaft, tip not required, no margin;
/// - an 8 mm instrument and a 10 mm endoscope ([`Bodies::default`]).
///
/// Valid: at least 50 % of the noiseless 3⁴×3² grid's lines recorded (combinations with the
/// tool through the endoscope count against it) and all nine tool
/// orientations among them; otherwise redrawn (at most 200 times).
pub fn random_geometry(seed: u64, distortion: bool) -> Result<GeometryDraw, RandomGeometryError> {
    let deg = core::f64::consts::PI / 180.0;
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x4745_4f4d_4554_5259); // "GEOMETRY"
    const ATTEMPTS: usize = 200;
    for _ in 0..ATTEMPTS {
        let dist = rng.random_range(0.080..=0.250);
        let theta = rng.random_range(20.0 * deg..=70.0 * deg);
        let azimuth = rng.random_range(0.0..core::f64::consts::TAU);
        let d_max = (dist / theta.sin() * 0.999).min(0.26);
        if d_max < 0.08 {
            continue;
        }
        let depth = rng.random_range(0.08..=d_max);
        let reach = depth * theta.cos() + (dist * dist - (depth * theta.sin()).powi(2)).max(0.0).sqrt();
        let axis = Vector3::new(theta.sin() * azimuth.cos(), theta.sin() * azimuth.sin(), theta.cos());
        let t = Vector3::new(0.0, 0.0, depth) - axis * reach;
        let twist = rng.random_range(0.0..core::f64::consts::TAU);
        let r = UnitQuaternion::rotation_between(&Vector3::z(), &axis).unwrap_or_else(UnitQuaternion::identity)
            * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), twist);
        let fov = rng.random_range(60.0 * deg..=90.0 * deg);
        let f = 320.0 / (0.5 * fov).tan();
        let dist_coeffs = if distortion {
            [
                rng.random_range(-0.3..=-0.05),
                rng.random_range(0.0..=0.1),
                rng.random_range(-0.002..=0.002),
                rng.random_range(-0.002..=0.002),
                0.0,
            ]
        } else {
            [0.0; 5]
        };
        // The camera 40-120 mm from the working point.
        let ins_hi = depth - 0.04;
        let ins_lo = (depth - 0.12).max(0.0);
        if ins_hi <= ins_lo + 0.02 {
            continue;
        }
        let half = 0.5 * fov;
        let ecm_angle = rng.random_range(4.0 * deg..=(0.3 * half).max(4.5 * deg));
        let roll = rng.random_range(10.0 * deg..=30.0 * deg);
        let psm_angle = rng.random_range(5.0 * deg..=12.0 * deg);
        let he = Isometry3::from_parts(
            Translation3::new(
                rng.random_range(-0.003..=0.003),
                rng.random_range(-0.003..=0.003),
                rng.random_range(0.0..=0.002),
            ),
            UnitQuaternion::from_euler_angles(
                rng.random_range(-3.0 * deg..=3.0 * deg),
                rng.random_range(-3.0 * deg..=3.0 * deg),
                rng.random_range(-3.0 * deg..=3.0 * deg),
            ),
        );
        let geometry = CalibGeometry {
            intrinsics: Intrinsics {
                fx: f,
                fy: f,
                cx: 319.5,
                cy: 239.5,
                skew: 0.0,
                width: 640,
                height: 480,
                distortion: dist_coeffs,
            },
            hand_eye: he,
            truth: Isometry3::from_parts(Translation3::from(t), r),
            ecm_yaw_rad: [-ecm_angle, ecm_angle],
            ecm_pitch_rad: [-ecm_angle, ecm_angle],
            ecm_insertion_m: [ins_lo, ins_hi],
            ecm_roll_rad: [-roll, roll],
            psm_yaw_rad: [-psm_angle, psm_angle],
            psm_pitch_rad: [-psm_angle, psm_angle],
            psm_insertion_m: reach,
            selection: SelectionRule {
                min_visible_shaft_px: 40.0,
                border_margin_px: 0.0,
                require_tip_in_view: false,
                ends_are_shaft_ends: true,
            },
            bodies: Bodies::default(),
        };
        // The lens model must be invertible over the whole image (undistortion converges).
        let k = &geometry.intrinsics;
        let invertible = [(0.0, 0.0), (639.0, 0.0), (0.0, 479.0), (639.0, 479.0), (319.5, 0.0), (0.0, 239.5)]
            .iter()
            .all(|&(u, v)| {
                let p = Vector2::new(u, v);
                let back = k.distort_px(&k.undistort_px(&p));
                (back - p).norm() < 1e-3
            });
        if !invertible {
            continue;
        }
        let clean = generate_calibration(&CalibProtocol::noiseless(geometry));
        let Ok(clean) = clean else { continue };
        let mut orientations: Vec<[f64; 3]> = Vec::new();
        for o in &clean.observations {
            if !orientations.iter().any(|q| q[0] == o.psm_joints[0] && q[1] == o.psm_joints[1]) {
                orientations.push(o.psm_joints);
            }
        }
        if clean.observations.len() * 2 >= clean.generated && orientations.len() == 9 {
            return Ok(GeometryDraw {
                geometry,
                rcm_distance_m: dist,
                tool_scope_angle_rad: theta,
                distorted: distortion,
            });
        }
    }
    Err(RandomGeometryError { attempts: ATTEMPTS, seed })
}

/// A uniformly distributed random unit quaternion `[w, x, y, z]` (Shoemake), for the
/// initial-guess robustness sweep.
pub fn random_unit_quaternion(rng: &mut impl Rng) -> [f64; 4] {
    let (u1, u2, u3): (f64, f64, f64) = (rng.random(), rng.random(), rng.random());
    let tau = 2.0 * core::f64::consts::PI;
    let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
    [b * (tau * u3).cos(), a * (tau * u2).sin(), a * (tau * u2).cos(), b * (tau * u3).sin()]
}

/// Rotation helper for tests and docs: the angle (radians) between two rotations.
pub fn rotation_distance(a: &Rotation3<f64>, b: &Rotation3<f64>) -> f64 {
    (a.inverse() * b).angle()
}

/// Replaces the lines of `round(fraction × n)` observations (chosen with `seed`, ChaCha8) by
/// wrong ones, as a line detector gets wrong when it takes another instrument's edge or a
/// reflection for the tool: a segment between two uniform points of the `intrinsics` image,
/// at least 80 px long (ideal pixels). Returns the replaced observations' indices, ascending.
/// `fraction` outside `0..=1` (or NaN) replaces none.
pub fn corrupt_lines(
    observations: &mut [Observation],
    intrinsics: &Intrinsics,
    fraction: f64,
    seed: u64,
) -> Vec<usize> {
    if !(0.0..=1.0).contains(&fraction) {
        return Vec::new();
    }
    let n = observations.len();
    let count = ((fraction * n as f64).round() as usize).min(n);
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5752_4f4e_474c_494e); // "WRONGLIN"
    let mut idx: Vec<usize> = (0..n).collect();
    // Partial Fisher-Yates: the first `count` entries are a uniform sample.
    for i in 0..count {
        let j = rng.random_range(i..n);
        idx.swap(i, j);
    }
    let mut chosen = idx[..count].to_vec();
    chosen.sort_unstable();
    let (w, h) = (f64::from(intrinsics.width) - 1.0, f64::from(intrinsics.height) - 1.0);
    for &i in &chosen {
        let (a, b) = loop {
            let a = Vector2::new(rng.random_range(0.0..=w), rng.random_range(0.0..=h));
            let b = Vector2::new(rng.random_range(0.0..=w), rng.random_range(0.0..=h));
            if (b - a).norm() >= 80.0 {
                break (a, b);
            }
        };
        observations[i].line_px = [[a.x, a.y], [b.x, b.y]];
    }
    chosen
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dataset() -> CalibDataset {
        generate_calibration(&CalibProtocol {
            geometry: CalibGeometry::default(),
            n_e: 2,
            n_t: 3,
            sigma: 0.0,
            units: NoiseUnits::Millimetre,
            pixel_sigma_px: 0.0,
            seed: 3,
        })
        .unwrap()
    }

    #[test]
    fn segment_distance_handles_crossing_parallel_and_degenerate_segments() {
        let v = Vector3::new;
        // Skew segments crossing at right angles 2 apart.
        let d = segment_distance(&v(-1.0, 0.0, 0.0), &v(1.0, 0.0, 0.0), &v(0.0, -1.0, 2.0), &v(0.0, 1.0, 2.0));
        assert!((d - 2.0).abs() < 1e-12, "{d}");
        // The lines cross, the segments do not: the closest points are end points.
        let d = segment_distance(&v(1.0, 0.0, 0.0), &v(2.0, 0.0, 0.0), &v(0.0, 1.0, 0.0), &v(0.0, 3.0, 0.0));
        assert!((d - 2f64.sqrt()).abs() < 1e-12, "{d}");
        // Parallel, overlapping, 0.5 apart; parallel, disjoint.
        let d = segment_distance(&v(0.0, 0.0, 0.0), &v(4.0, 0.0, 0.0), &v(1.0, 0.5, 0.0), &v(6.0, 0.5, 0.0));
        assert!((d - 0.5).abs() < 1e-12, "{d}");
        let d = segment_distance(&v(0.0, 0.0, 0.0), &v(1.0, 0.0, 0.0), &v(4.0, 0.0, 0.0), &v(6.0, 0.0, 0.0));
        assert!((d - 3.0).abs() < 1e-12, "{d}");
        // A point against a segment, and two points.
        let p = v(0.5, 3.0, 0.0);
        assert!((segment_distance(&p, &p, &v(0.0, 0.0, 0.0), &v(1.0, 0.0, 0.0)) - 3.0).abs() < 1e-12);
        assert!((segment_distance(&p, &p, &v(0.5, 0.0, 4.0), &v(0.5, 0.0, 4.0)) - 5.0).abs() < 1e-12);
        // Symmetric in its two segments.
        let (a, b, c, e) = (v(0.1, 0.2, 0.3), v(1.0, -2.0, 0.5), v(-1.0, 0.0, 1.0), v(2.0, 1.0, -1.0));
        assert!((segment_distance(&a, &b, &c, &e) - segment_distance(&c, &e, &a, &b)).abs() < 1e-12);
    }

    #[test]
    fn bodies_collide_and_end_on_follow_the_radii() {
        let b = Bodies::default();
        let v = Vector3::new;
        let (scope_rcm, lens) = (v(0.0, 0.0, 0.0), v(0.0, 0.0, 0.08));
        // A tool crossing the scope axis 8 mm in front of the lens: 8 mm < 9 mm clearance.
        let (tip, rcm) = (v(-0.05, 0.0, 0.088), v(0.1, 0.0, 0.088));
        assert!(b.collide(&tip, &rcm, &scope_rcm, &lens));
        // 10 mm in front: clear. Without bodies, nothing collides.
        let (tip, rcm) = (v(-0.05, 0.0, 0.09), v(0.1, 0.0, 0.09));
        assert!(!b.collide(&tip, &rcm, &scope_rcm, &lens));
        assert!(!Bodies::NONE.collide(&lens, &lens, &scope_rcm, &lens));
        // Pointing at the lens from 30 mm, 3 mm off its axis: end-on for an 8 mm shaft
        // (radius 4 mm), not for a 5 mm one.
        let tip = v(0.003, 0.0, 0.11);
        let back = v(0.0, 0.0, 1.0);
        assert!(b.end_on(&tip, &back, &lens));
        assert!(!Bodies { tool_radius_m: 0.0025, ..b }.end_on(&tip, &back, &lens));
    }

    #[test]
    fn no_generated_observation_puts_the_tool_through_the_endoscope() {
        use estimator::calib::rcm_arms::{ecm_frames, psm_frames};
        // Tuning geometry 9013 (distorted) has combinations with the tool through the lens.
        let geometry = random_geometry(9013, true).unwrap().geometry;
        let run = |geometry| generate_calibration(&CalibProtocol::noiseless(geometry)).unwrap();
        let clearance = |d: &CalibDataset, b: &Bodies| -> Vec<f64> {
            d.observations
                .iter()
                .map(|o| {
                    let lens = (ecm_frames(&o.ecm_joints)[3] * geometry.hand_eye).translation.vector;
                    let f3 = psm_frames(&o.psm_joints)[2];
                    let tip = geometry.truth * nalgebra::Point3::from(f3.translation.vector);
                    let back = geometry.truth.rotation * (f3.rotation * -Vector3::z());
                    let rcm = tip.coords + back * o.psm_joints[2];
                    let gap = segment_distance(&tip.coords, &rcm, &Vector3::zeros(), &lens)
                        - (b.tool_radius_m + b.scope_radius_m);
                    if b.end_on(&tip.coords, &back, &lens) { -1.0 } else { gap }
                })
                .collect()
        };
        let with = run(geometry);
        let without = run(CalibGeometry { bodies: Bodies::NONE, ..geometry });
        assert_eq!(with.generated, with.observations.len() + with.dropped + with.collided);
        assert!(with.collided > 0);
        assert_eq!(without.collided, 0);
        assert!(clearance(&with, &geometry.bodies).iter().all(|&g| g >= 0.0));
        assert!(
            clearance(&without, &geometry.bodies).iter().any(|&g| g < 0.0),
            "the old protocol let the tool through"
        );
        assert!(with.observations.len() < without.observations.len());
    }

    #[test]
    fn corrupt_lines_replaces_the_requested_share_repeatably_inside_the_image() {
        let d = dataset();
        let k = d.setup.intrinsics;
        let mut a = d.observations.clone();
        let chosen = corrupt_lines(&mut a, &k, 0.25, 9);
        assert_eq!(chosen.len(), (0.25 * a.len() as f64).round() as usize);
        assert!(chosen.windows(2).all(|w| w[0] < w[1]));
        for (i, (new, old)) in a.iter().zip(&d.observations).enumerate() {
            if chosen.contains(&i) {
                let [p, q] = new.line_px.map(|p| Vector2::new(p[0], p[1]));
                assert!((q - p).norm() >= 80.0);
                assert!(
                    [p, q]
                        .iter()
                        .all(|x| (0.0..k.width as f64).contains(&x.x) && (0.0..k.height as f64).contains(&x.y))
                );
                assert_ne!(new.line_px, old.line_px);
            } else {
                assert_eq!(new, old, "observation {i} changed");
            }
        }
        // Same seed, same corruption; another seed, another choice.
        let mut b = d.observations.clone();
        assert_eq!(corrupt_lines(&mut b, &k, 0.25, 9), chosen);
        assert_eq!(a, b);
        let mut c = d.observations.clone();
        assert_ne!(corrupt_lines(&mut c, &k, 0.25, 10), chosen);
        // Nothing for 0, everything for 1, nothing for a fraction outside 0..=1.
        for (f, n) in [(0.0, 0), (1.0, d.observations.len()), (1.5, 0), (-0.1, 0), (f64::NAN, 0)] {
            let mut o = d.observations.clone();
            assert_eq!(corrupt_lines(&mut o, &k, f, 1).len(), n, "fraction {f}");
        }
    }
}
