//! # Tool tracking: a particle filter over the tool arm's joints (issue 18)
//!
//! The method of *Vision-Based Surgical Tool Pose Estimation for the da Vinci® Robotic
//! Surgical System* (Hao, Özgüner and Çavuşoğlu, IROS 2018) on our set-up, and ours. Pure
//! maths: images come in as bytes, the estimate goes out as numbers; no I/O, no clock.
//!
//! ## The state and the models (`docs/tracking.md` maps every paper quantity)
//! - **State** ([`Particle`]): the tool arm's six joints (the Achilles-type arm: three
//!   motorised, the passive wrist's three; radians), the jaw angle (each jaw, radians: the
//!   instrument's jaws are not encoded, so they are state, not input), and optionally the
//!   correction of the camera-to-base transform `g_CB` (Eq. 17-18; a rotation vector and a
//!   translation applied on the left of the left eye's `g_CB`).
//! - **Motion** (Eq. 13): each joint moves by the encoders' increment since the previous
//!   frame plus Gaussian noise of its own standard deviation; the jaw and `g_CB` by Gaussian
//!   noise alone (a Brownian motion, the paper's footnote 1). Ours by default estimates the
//!   kinematic error instead ([`OffsetMotion`]): the offset `joints − encoders`,
//!   mean-reverting towards the kinematics with a time constant.
//! - **Measurement**: [`Mode::Paper`]: Canny edges of both images, the virtual image of each
//!   particle's silhouette (Algorithms 1-2), chamfer distance, `s = exp(−d/τ)`, `π =
//!   sqrt(s_l² + s_r²)` (Eq. 14-16), resampling every frame (Algorithm 3). [`Mode::Ours`]:
//!   the shaft's two contour lines in closed form plus the tip parts' precomputed candidate
//!   edges, sampled and looked up in each eye's distance field (computed once per frame),
//!   oriented (edge direction) and truncated (clutter, occlusion), annealed over a few layers,
//!   the best hypothesis refined locally; all particles in parallel on the tracker's own worker
//!   threads ([`workers`]: started at the first frame, loops handed over without a queue); no
//!   allocation per frame after start-up, in any thread.
//! - **Status** ([`Status`]): `Tracking`, `Uncertain` (the particles' tip spread too wide),
//!   `Lost` (the best hypothesis's cost above a threshold; ours: its inlier share below one,
//!   unless the prior holds it, [`OffsetMotion::prior_lost`]); after a few lost frames the
//!   particles are re-initialised from the kinematics (the encoders' joints).
//!
//! A live process calls [`Tracker::step`] once per stereo frame.

pub mod edges;
pub mod measure;
pub mod model;
pub mod proposal;
pub mod resample;
pub mod workers;

use estimator::kinematics::JOINTS;
use nalgebra::{Isometry3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
pub use workers::Workers;

pub use edges::{EdgeContrast, EdgeField, ImageError};
pub use measure::OursCost;
pub use model::{ModelError, Part, PartMesh, StereoCameras, ToolGeometry, ToolModel};
pub use proposal::{AxisError, ProposalConfig, ShaftAxis};

/// One hypothesis of the state.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Particle {
    /// The tool arm's joints 1-6, radians (`docs/kinematics.md`).
    pub joints: [f64; JOINTS],
    /// Each jaw's opening, radians (≥ 0 open).
    pub jaw_rad: f64,
    /// Correction of `g_CB` (Eq. 17): rotation vector (radians) then translation (metres),
    /// applied on the left of the left eye's `T_c_b`; zeros unless the augmentation is on.
    pub camera_delta: [f64; 6],
}

/// Which measurement and filter.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// The paper's method, faithful (Algorithms 1-3, Eq. 6-16).
    Paper,
    /// Ours: analytic silhouettes, distance field once per frame, oriented truncated chamfer,
    /// annealing, local refinement.
    Ours,
}

/// The tracker's verdict on a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum Status {
    /// The best hypothesis fits and the particles agree.
    Tracking,
    /// The best hypothesis fits but the particles' tip spread exceeds
    /// [`TrackerConfig::uncertain_spread_m`].
    Uncertain,
    /// The best hypothesis does not fit (likelihood collapse): no pose is published.
    Lost,
}

/// Where [`OffsetMotion`]'s mean-reverting offset returns to without image evidence.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RevertTo {
    /// The kinematics: the offset `b = joints − encoders` returns to zero.
    Kinematics,
    /// The offset the particles were (re-)initialised with ([`Tracker::initialise`]'s
    /// `centre − encoder_rad`): a start off the kinematics is kept as the prior's mean, so only
    /// the images can move it (the paper's convergence protocol: vision alone).
    Start,
}

/// Ours: the motion model of the kinematic error ("lumped error"). Each particle's state is
/// the offset `b = joints − encoders` (per joint, radians; the jaw stays a random walk, it is
/// not encoded), propagated between frames as a mean-reverting (Ornstein-Uhlenbeck, AR(1))
/// process `b_k = m + ρ (b_{k−1} − m) + σ √(1 − ρ²) ε`, `ρ = exp(−Δt / time_constant_s)`, `m`
/// the mean ([`RevertTo`]), `σ` the stationary standard deviation: without image evidence the
/// estimate returns to the kinematics with the time constant, and what the images constrain
/// is corrected by them. The random walk on absolute joints (Eq. 13) lets the estimate wander
/// without bound along the directions the contours do not fix (along the shaft, its roll).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OffsetMotion {
    /// Time constant of the reversion, seconds (> 0).
    pub time_constant_s: f64,
    /// Stationary standard deviation of the offset per joint, radians: the expected encoder
    /// and calibration error; also the particles' spread at (re-)initialisation.
    pub stationary_rad: [f64; JOINTS],
    /// What the offset returns to.
    pub revert_to: RevertTo,
    /// Frame period assumed when a frame has no time ([`FrameInput::time_ns`]) or its time does
    /// not advance, seconds.
    pub nominal_period_s: f64,
    /// LOST with the prior: a frame whose inlier share is below
    /// [`TrackerConfig::lost_inlier_share`] is not LOST when the best hypothesis's offset is
    /// within `max_sigma` stationary standard deviations of the mean on every joint and each of
    /// the shaft's two contour lines fits (its share of in-image samples on a matching edge, the
    /// worse line, mean of both eyes, at least `line_share`): the visible part fits where the
    /// prior says the instrument is (half of it hidden from the tip end). `None`: the inlier
    /// share alone.
    pub prior_lost: Option<PriorLost>,
}

/// See [`OffsetMotion::prior_lost`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PriorLost {
    /// Largest `|b_j − m_j| / σ_j` over the joints of a plausible offset.
    pub max_sigma: f64,
    /// Smallest inlier share of the worse shaft contour line (mean of both eyes), 0..1.
    pub line_share: f64,
}

impl OffsetMotion {
    /// Defaults (tuned on seeds 2 and 3 of `docs/tracking.md`).
    pub fn default_ours() -> Self {
        Self {
            time_constant_s: 1.0,
            stationary_rad: [0.002, 0.002, 0.002, 0.004, 0.004, 0.01],
            revert_to: RevertTo::Kinematics,
            nominal_period_s: 0.1,
            prior_lost: Some(PriorLost { max_sigma: 3.0, line_share: 0.1 }),
        }
    }

    /// `ρ` for a step of `dt_s` seconds.
    pub fn rho(&self, dt_s: f64) -> f64 {
        (-dt_s / self.time_constant_s).exp()
    }
}

/// The tracker's parameters (units in each field).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackerConfig {
    /// Measurement and filter.
    pub mode: Mode,
    /// Particles.
    pub particles: usize,
    /// Image width and height, pixels (both eyes).
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Eq. 13's standard deviation of each joint's process noise per frame, radians.
    pub joint_noise_rad: [f64; JOINTS],
    /// Spread of the particles about the kinematics at (re-)initialisation, radians per joint.
    pub init_spread_rad: [f64; JOINTS],
    /// Jaw angle at (re-)initialisation, radians.
    pub jaw_init_rad: f64,
    /// The jaw's process noise per frame, radians.
    pub jaw_noise_rad: f64,
    /// `g_CB` augmentation (Eq. 17): process noise per frame `[rotation rad, translation m]`;
    /// `None`: `g_CB` is taken as calibrated.
    pub camera_noise: Option<[f64; 2]>,
    /// The paper's sensitivity τ (Eq. 15), pixels; ours: the temperature of the last layer,
    /// pixels of summed mean cost.
    pub tau_px: f64,
    /// Our measurement's parameters.
    pub ours: OursCost,
    /// Our edge threshold (Sobel magnitude, grey levels per pixel ×4).
    pub edge_threshold: f32,
    /// The paper's Canny thresholds (low, high), grey-level gradient.
    pub canny_px: [f32; 2],
    /// Ours: annealing layers after the first evaluation (0: none).
    pub anneal_layers: usize,
    /// Ours: coordinate-descent sweeps refining the best hypothesis (0: none).
    pub refine_sweeps: usize,
    /// Tip spread (weighted standard deviation of the particles' tip, metres) above which a
    /// frame is `Uncertain`.
    pub uncertain_spread_m: f64,
    /// Best hypothesis's cost above which a frame is `Lost`, pixels (ours: mean sample cost per
    /// eye; paper: mean chamfer distance per eye).
    pub lost_cost_px: f64,
    /// Consecutive lost frames after which the particles are re-initialised from the
    /// kinematics.
    pub reinit_after_lost: u32,
    /// Ours: LOST by the inlier share instead of the mean cost: a frame is LOST when the best
    /// hypothesis's share of samples on a matching edge (within `measure::INLIER_PX`),
    /// averaged over both eyes, is below this; `None`: by [`TrackerConfig::lost_cost_px`]
    /// (the paper's mode always). The mean cost counts a hidden sample at the truncation, so
    /// half the instrument hidden reads as lost; the inlier share halves instead.
    pub lost_inlier_share: Option<f64>,
    /// Ours: once re-initialised after [`TrackerConfig::reinit_after_lost`] lost frames, keep
    /// the particles on the kinematics (re-initialise at every further lost frame) until the
    /// instrument is found again, instead of letting them drift on clutter; and no adaptive
    /// noise growth after a lost frame (there was nothing to fit).
    pub hold_while_lost: bool,
    /// Ours: adaptive process noise `(good_px, max_scale)`: the motion noise is scaled by
    /// `clamp(c / good_px, 1, √max_scale)²` where `c` is the previous frame's best cost per
    /// eye (pixels): a poor fit explores more. `None`: fixed noise (the paper). Not applied
    /// with [`TrackerConfig::offset_motion`] (its innovation is fixed by the prior).
    pub adaptive_noise: Option<(f64, f64)>,
    /// Ours: the motion model of the kinematic error ([`OffsetMotion`]) instead of Eq. 13's
    /// random walk on the joints; `None`: Eq. 13 (the paper's mode always).
    pub offset_motion: Option<OffsetMotion>,
    /// Ours: re-seeding from the detected shaft's axis ([`ProposalConfig`],
    /// [`Tracker::set_shaft_axis`]); `None`: off.
    pub proposal: Option<ProposalConfig>,
    /// Ours: the edge threshold adapted to each frame's contrast ([`EdgeContrast`]: smoke);
    /// `None`: [`TrackerConfig::edge_threshold`] as given.
    pub edge_contrast: Option<EdgeContrast>,
    /// Seed of the noise (runs are reproducible).
    pub seed: u64,
    /// Threads of the particle loops, the stepping thread included (its [`Workers`], started by
    /// the first [`Tracker::step`] from the thread that calls it, whose priority they inherit);
    /// 0: the processors available to the process ([`workers::available_threads`]). The
    /// results do not depend on it.
    pub threads: usize,
}

impl TrackerConfig {
    /// Defaults for `mode` on `width × height` images (tuned on seeds 2 and 3 of
    /// `docs/tracking.md`).
    pub fn new(mode: Mode, width: usize, height: usize) -> Self {
        let (particles, anneal, refine, tau) = match mode {
            Mode::Paper => (500, 0, 0, 3.0),
            Mode::Ours => (1000, 2, 4, 1.0),
        };
        Self {
            mode,
            particles,
            width,
            height,
            joint_noise_rad: [0.0005, 0.0005, 0.0005, 0.001, 0.001, 0.005],
            init_spread_rad: [0.01, 0.01, 0.01, 0.02, 0.02, 0.05],
            jaw_init_rad: 0.2,
            jaw_noise_rad: 0.01,
            camera_noise: None,
            tau_px: tau,
            ours: OursCost { truncate_px: 12.0, orientation_px: 3.0, shaft_samples: 24 },
            edge_threshold: 60.0,
            canny_px: [20.0, 50.0],
            anneal_layers: anneal,
            refine_sweeps: refine,
            uncertain_spread_m: 0.004,
            lost_cost_px: 7.0,
            reinit_after_lost: 3,
            lost_inlier_share: match mode {
                Mode::Paper => None,
                Mode::Ours => Some(0.2),
            },
            hold_while_lost: mode == Mode::Ours,
            adaptive_noise: match mode {
                Mode::Paper => None,
                Mode::Ours => Some((3.5, 16.0)),
            },
            offset_motion: match mode {
                Mode::Paper => None,
                Mode::Ours => Some(OffsetMotion::default_ours()),
            },
            proposal: None,
            edge_contrast: match mode {
                Mode::Paper => None,
                Mode::Ours => Some(EdgeContrast { reference_px: 75.0, noise_factor: 2.5 }),
            },
            seed: 1,
            threads: 0,
        }
    }

    /// Checks every value; the error names the field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let pos = |v: f64| v.is_finite() && v > 0.0;
        let nonneg = |v: f64| v.is_finite() && v >= 0.0;
        if self.particles == 0 || self.particles > 1_000_000 {
            return Err(ConfigError("particles (1..=1000000)"));
        }
        if self.threads > 1024 {
            return Err(ConfigError("threads (0..=1024, 0: the machine's processors)"));
        }
        if self.width < 3 || self.height < 3 || self.width > 8192 || self.height > 8192 {
            return Err(ConfigError("width/height (3..=8192 pixels)"));
        }
        if !self.joint_noise_rad.iter().all(|&v| nonneg(v)) {
            return Err(ConfigError("joint_noise_rad"));
        }
        if !self.init_spread_rad.iter().all(|&v| nonneg(v)) {
            return Err(ConfigError("init_spread_rad"));
        }
        if !nonneg(self.jaw_init_rad) || !nonneg(self.jaw_noise_rad) {
            return Err(ConfigError("jaw_init_rad/jaw_noise_rad"));
        }
        if let Some(c) = self.camera_noise
            && !c.iter().all(|&v| nonneg(v))
        {
            return Err(ConfigError("camera_noise"));
        }
        if !pos(self.tau_px) {
            return Err(ConfigError("tau_px"));
        }
        let o = &self.ours;
        if !pos(o.truncate_px) || !nonneg(o.orientation_px) || o.shaft_samples < 2 {
            return Err(ConfigError("ours (truncate_px > 0, orientation_px >= 0, shaft_samples >= 2)"));
        }
        if !(self.edge_threshold.is_finite() && self.edge_threshold >= 0.0) {
            return Err(ConfigError("edge_threshold"));
        }
        if !(self.canny_px[0].is_finite() && self.canny_px[1].is_finite() && self.canny_px[0] <= self.canny_px[1]) {
            return Err(ConfigError("canny_px (low <= high)"));
        }
        if self.anneal_layers > 8 || self.refine_sweeps > 32 {
            return Err(ConfigError("anneal_layers (<= 8) / refine_sweeps (<= 32)"));
        }
        if !pos(self.uncertain_spread_m) {
            return Err(ConfigError("uncertain_spread_m"));
        }
        if !pos(self.lost_cost_px) {
            return Err(ConfigError("lost_cost_px"));
        }
        if let Some(v) = self.lost_inlier_share
            && !(v.is_finite() && (0.0..=1.0).contains(&v))
        {
            return Err(ConfigError("lost_inlier_share (0..=1)"));
        }
        if let Some((g, m)) = self.adaptive_noise
            && !(pos(g) && m.is_finite() && m >= 1.0)
        {
            return Err(ConfigError("adaptive_noise (good_px > 0, max_scale >= 1)"));
        }
        if let Some(m) = &self.offset_motion {
            if self.mode == Mode::Paper {
                return Err(ConfigError("offset_motion (ours only)"));
            }
            if !pos(m.time_constant_s) {
                return Err(ConfigError("offset_motion.time_constant_s"));
            }
            if !m.stationary_rad.iter().all(|&v| nonneg(v)) {
                return Err(ConfigError("offset_motion.stationary_rad"));
            }
            if !(pos(m.nominal_period_s) && m.nominal_period_s <= 10.0) {
                return Err(ConfigError("offset_motion.nominal_period_s (0 < period <= 10 s)"));
            }
            if let Some(p) = m.prior_lost
                && !(pos(p.max_sigma) && p.line_share.is_finite() && (0.0..=1.0).contains(&p.line_share))
            {
                return Err(ConfigError("offset_motion.prior_lost (max_sigma > 0, line_share 0..=1)"));
            }
        }
        if let Some(c) = &self.edge_contrast
            && !(c.reference_px.is_finite()
                && c.reference_px > 0.0
                && c.noise_factor.is_finite()
                && c.noise_factor >= 0.0)
        {
            return Err(ConfigError("edge_contrast (reference_px > 0, noise_factor >= 0)"));
        }
        if let Some(p) = &self.proposal {
            if self.mode == Mode::Paper {
                return Err(ConfigError("proposal (ours only)"));
            }
            if let Some(f) = p.invalid_field() {
                return Err(ConfigError(f));
            }
        }
        Ok(())
    }
}

/// A configuration value out of range (the field named).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("tracker configuration: {0} out of range")]
pub struct ConfigError(pub &'static str);

/// One stereo frame's input.
#[derive(Clone, Copy, Debug)]
pub struct FrameInput<'a> {
    /// The tool arm's joints from its encoders at the frame's mid-exposure time, radians.
    pub encoder_rad: [f64; JOINTS],
    /// The cameras at that time (`g_CB` from the endoscope arm's kinematics and the calibration).
    pub cameras: StereoCameras,
    /// Left and right sRGB images, row-major, 3 bytes a pixel, `width × height`.
    pub rgb: [&'a [u8]; 2],
    /// The frame's mid-exposure time, nanoseconds (any epoch, the same for every frame): the
    /// time step of [`OffsetMotion`]; `None`: its nominal period.
    pub time_ns: Option<u64>,
}

/// Why a frame was refused (the tracker's state is unchanged).
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum StepError {
    /// An encoder joint is not finite.
    #[error("encoder joint {0} is not finite")]
    Encoder(usize),
    /// The cameras are not finite or their intrinsics invalid.
    #[error("cameras not finite or intrinsics invalid")]
    Cameras,
    /// An image has the wrong size.
    #[error("{eye} image: {source}")]
    Image {
        /// `left` or `right`.
        eye: &'static str,
        /// The reason.
        source: ImageError,
    },
    /// The encoders' joints are off the arm (its forward kinematics fails).
    #[error("the encoders' joints are not a pose of the arm")]
    Kinematics,
}

/// The tracked pose (every number finite).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackedPose {
    /// `T_b_tip`: the tip (jaw pivot; axes of the arm's frame 6, `z` along the instrument) in
    /// the tool arm's base frame, metres.
    pub tip_in_base: Isometry3<f64>,
    /// `T_c_tip`: the tip in the left camera frame (with the estimated `g_CB`), metres.
    pub tip_in_camera: Isometry3<f64>,
    /// Each jaw's opening, radians.
    pub jaw_rad: f64,
    /// The estimated joints, radians.
    pub joints_rad: [f64; JOINTS],
    /// The estimated `g_CB` correction (zeros without augmentation).
    pub camera_delta: [f64; 6],
}

/// The result of one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Estimate {
    /// The verdict.
    pub status: Status,
    /// The best hypothesis's pose; `None` when `Lost`.
    pub pose: Option<TrackedPose>,
    /// Weighted standard deviation of the particles' tips, metres.
    pub spread_m: f64,
    /// The best hypothesis's cost, pixels (ours: mean sample cost per eye; paper: mean chamfer
    /// distance per eye).
    pub best_cost_px: f64,
    /// Effective number of particles `1/Σw²` of the final weights.
    pub effective_particles: f64,
    /// `true` when the particles were re-initialised from the kinematics at this frame.
    pub reinitialised: bool,
    /// `true` when the inlier share alone would have made the frame LOST but the prior kept
    /// it ([`OffsetMotion::prior_lost`]).
    pub held_by_prior: bool,
    /// Ours with [`TrackerConfig::proposal`]: the particles were re-initialised this frame
    /// about a hypothesis on the detected shaft's axis (a re-initialisation from vision, not
    /// from the kinematics).
    pub reseeded_from_vision: bool,
}

fn mix(a: u64, b: u64) -> u64 {
    let mut z = a ^ b.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The particle filter. Buffers are allocated by [`Tracker::new`]; [`Tracker::step`] in
/// [`Mode::Ours`] allocates nothing.
#[derive(Debug)]
pub struct Tracker {
    cfg: TrackerConfig,
    model: ToolModel,
    particles: Vec<Particle>,
    next: Vec<Particle>,
    costs: Vec<f64>,
    weights: Vec<f64>,
    tips: Vec<Vector3<f64>>,
    idx: Vec<usize>,
    fields: [EdgeField; 2],
    last_encoder: Option<[f64; JOINTS]>,
    last_time_ns: Option<u64>,
    offset_mean: [f64; JOINTS],
    last_cost_px: f64,
    last_inlier_share: f64,
    last_line_share: f64,
    frame: u64,
    lost_run: u32,
    rng: ChaCha8Rng,
    /// The detected shaft's axis for the next step ([`Tracker::set_shaft_axis`]).
    axis: Option<ShaftAxis>,
    /// The previous frame's best hypothesis (refined), or the initial centre.
    last_best: Option<Particle>,
    /// Hypotheses on the detected axis and their costs (preallocated).
    proposals: Vec<Particle>,
    prop_costs: Vec<f64>,
    last_reseed_share: f64,
    /// The particle loops' threads: [`Workers::serial`] until the first step starts them.
    workers: Workers,
    workers_started: bool,
}

impl Tracker {
    /// A tracker for `model` with `cfg` (validated).
    pub fn new(cfg: TrackerConfig, model: ToolModel) -> Result<Self, ConfigError> {
        cfg.validate()?;
        let n = cfg.particles;
        let p0 = Particle { joints: [0.0; JOINTS], jaw_rad: cfg.jaw_init_rad, camera_delta: [0.0; 6] };
        Ok(Self {
            model,
            particles: vec![p0; n],
            next: vec![p0; n],
            costs: vec![0.0; n],
            weights: vec![0.0; n],
            tips: vec![Vector3::zeros(); n],
            idx: vec![0; n],
            fields: [EdgeField::new(cfg.width, cfg.height), EdgeField::new(cfg.width, cfg.height)],
            last_encoder: None,
            last_time_ns: None,
            offset_mean: [0.0; JOINTS],
            last_cost_px: 0.0,
            last_inlier_share: f64::NAN,
            last_line_share: f64::NAN,
            frame: 0,
            lost_run: 0,
            rng: ChaCha8Rng::seed_from_u64(cfg.seed),
            axis: None,
            last_best: None,
            proposals: vec![p0; cfg.proposal.map_or(0, |p| p.count)],
            prop_costs: vec![f64::INFINITY; cfg.proposal.map_or(0, |p| p.count)],
            last_reseed_share: f64::NAN,
            workers: Workers::serial(),
            workers_started: false,
            cfg,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &TrackerConfig {
        &self.cfg
    }

    /// The model.
    pub fn model(&self) -> &ToolModel {
        &self.model
    }

    /// The current particles (after the last resampling).
    pub fn particles(&self) -> &[Particle] {
        &self.particles
    }

    /// Each eye's edge field of the last frame.
    pub fn edge_fields(&self) -> &[EdgeField; 2] {
        &self.fields
    }

    /// Ours with [`TrackerConfig::lost_inlier_share`]: the best hypothesis's inlier share
    /// (mean of both eyes, 0..1) of the last frame; NaN otherwise.
    pub fn last_inlier_share(&self) -> f64 {
        self.last_inlier_share
    }

    /// Ours with [`OffsetMotion::prior_lost`]: the best hypothesis's inlier share of its worse
    /// shaft contour line (mean of both eyes, 0..1) on the last frame it was needed (a frame
    /// whose inlier share was below the threshold); NaN otherwise.
    pub fn last_line_share(&self) -> f64 {
        self.last_line_share
    }

    /// Gives the next [`Tracker::step`] the shaft's axis detected in this frame's images (base
    /// frame; [`proposal::triangulate_axis`]), used when [`TrackerConfig::proposal`] is set;
    /// `None`: no detection. Taken by that step (the next one has none unless set again).
    pub fn set_shaft_axis(&mut self, axis: Option<ShaftAxis>) {
        self.axis = axis;
    }

    /// Ours with [`TrackerConfig::proposal`]: the inlier share (0..1) of the best hypothesis
    /// on the detected axis on the last frame re-seeding was tried; NaN when it was not.
    pub fn last_reseed_share(&self) -> f64 {
        self.last_reseed_share
    }

    /// Ours with [`OffsetMotion`]: the offset's mean `m` (radians per joint; zeros when it
    /// returns to the kinematics).
    pub fn offset_mean(&self) -> [f64; JOINTS] {
        self.offset_mean
    }

    /// Puts the particles about `centre` (joints, radians) with the configured initial spread
    /// (the first particle exactly at `centre`), the encoders reading `encoder_rad` now (the
    /// next frame's increment is taken from it). Used at start-up from the kinematics, and by
    /// the experiments from a perturbed start.
    /// With [`OffsetMotion`] the spread is its stationary one and the next frame's time step is
    /// zero (the particles are put at that frame), the offset's mean is zero or, reverting to
    /// the start, `centre − encoder_rad`.
    pub fn initialise(&mut self, centre: &[f64; JOINTS], encoder_rad: &[f64; JOINTS]) {
        self.init_particles(centre, encoder_rad);
        self.last_time_ns = None;
    }

    fn init_particles(&mut self, centre: &[f64; JOINTS], encoder_rad: &[f64; JOINTS]) {
        let seed = mix(self.cfg.seed, 0xA11C_E000 + self.frame);
        let spread = self.cfg.offset_motion.map_or(self.cfg.init_spread_rad, |m| m.stationary_rad);
        self.offset_mean = match self.cfg.offset_motion {
            Some(OffsetMotion { revert_to: RevertTo::Start, .. }) => {
                core::array::from_fn(|j| centre[j] - encoder_rad[j])
            }
            _ => [0.0; JOINTS],
        };
        let jaw = self.cfg.jaw_init_rad;
        self.workers.for_each_mut(&mut self.particles, |i, p| {
            let mut r = ChaCha8Rng::seed_from_u64(mix(seed, i as u64));
            p.joints = *centre;
            if i > 0 {
                for (j, q) in p.joints.iter_mut().enumerate() {
                    *q += spread[j] * r.sample::<f64, _>(StandardNormal);
                }
            }
            p.jaw_rad = jaw;
            p.camera_delta = [0.0; 6];
        });
        self.last_encoder = Some(*encoder_rad);
        self.last_cost_px = 0.0;
        self.lost_run = 0;
        self.last_best = Some(Particle { joints: *centre, jaw_rad: jaw, camera_delta: [0.0; 6] });
    }

    /// [`OffsetMotion`]'s step: each particle's offset from the previous encoders `prev`
    /// reverts towards the mean by `rho` plus noise (`scale` × its innovation standard
    /// deviation), and is put back on the current encoders `enc`; the jaw and `g_CB` as in
    /// [`Tracker::diffuse`].
    fn diffuse_offset(&mut self, m: &OffsetMotion, enc: &[f64; JOINTS], prev: &[f64; JOINTS], rho: f64, scale: f64) {
        let seed = mix(mix(self.cfg.seed, self.frame), 1);
        let innov = (1.0 - rho * rho).max(0.0).sqrt();
        let sig: [f64; JOINTS] = core::array::from_fn(|j| m.stationary_rad[j] * innov);
        let mean = self.offset_mean;
        let (jsig, cam) = (self.cfg.jaw_noise_rad, self.cfg.camera_noise);
        self.workers.for_each_mut(&mut self.particles, |i, p| {
            let mut r = ChaCha8Rng::seed_from_u64(mix(seed, i as u64));
            for j in 0..JOINTS {
                let b = p.joints[j] - prev[j];
                let b = mean[j] + rho * (b - mean[j]) + scale * sig[j] * r.sample::<f64, _>(StandardNormal);
                p.joints[j] = enc[j] + b;
            }
            p.jaw_rad = (p.jaw_rad + scale * jsig * r.sample::<f64, _>(StandardNormal)).clamp(0.0, 1.2);
            if let Some([sr, st]) = cam {
                for k in 0..6 {
                    let s = if k < 3 { sr } else { st };
                    p.camera_delta[k] += scale * s * r.sample::<f64, _>(StandardNormal);
                }
            }
        });
    }

    /// Ours with [`OffsetMotion`]: `½ Σ ((b_j − m_j) / σ_j)²` of `p` against the encoders
    /// `enc` (the prior's negative log density up to a constant), and the largest
    /// `|b_j − m_j| / σ_j`; zeros without it (or for a joint with `σ_j = 0`).
    fn prior_of(&self, p: &Particle, enc: &[f64; JOINTS]) -> (f64, f64) {
        let Some(m) = &self.cfg.offset_motion else { return (0.0, 0.0) };
        let (mut e, mut mx) = (0.0, 0.0f64);
        for (((q, y), mean), sig) in p.joints.iter().zip(enc).zip(&self.offset_mean).zip(&m.stationary_rad) {
            if *sig > 0.0 {
                let z = (q - y - mean) / sig;
                e += 0.5 * z * z;
                mx = mx.max(z.abs());
            }
        }
        (e, mx)
    }

    fn diffuse(&mut self, increment: &[f64; JOINTS], scale: f64, layer: u64) {
        let seed = mix(mix(self.cfg.seed, self.frame), layer + 1);
        let sig = self.cfg.joint_noise_rad;
        let (jsig, cam) = (self.cfg.jaw_noise_rad, self.cfg.camera_noise);
        self.workers.for_each_mut(&mut self.particles, |i, p| {
            let mut r = ChaCha8Rng::seed_from_u64(mix(seed, i as u64));
            for j in 0..JOINTS {
                p.joints[j] += increment[j] + scale * sig[j] * r.sample::<f64, _>(StandardNormal);
            }
            p.jaw_rad = (p.jaw_rad + scale * jsig * r.sample::<f64, _>(StandardNormal)).clamp(0.0, 1.2);
            if let Some([sr, st]) = cam {
                for k in 0..6 {
                    let s = if k < 3 { sr } else { st };
                    p.camera_delta[k] += scale * s * r.sample::<f64, _>(StandardNormal);
                }
            }
        });
    }

    fn evaluate(&mut self, cams: &StereoCameras) {
        let model = &self.model;
        let fields = &self.fields;
        let oc = self.cfg.ours;
        let tau = self.cfg.tau_px;
        match self.cfg.mode {
            Mode::Ours => {
                let particles = &self.particles;
                self.workers.for_each_mut2(&mut self.costs, &mut self.tips, |i, c, t| {
                    let p = &particles[i];
                    *c = measure::cost_ours(model, cams, fields, p, &oc);
                    *t = model.tip_in_base(&p.joints).map_or(Vector3::zeros(), |x| x.translation.vector);
                });
            }
            Mode::Paper => {
                let (w, h) = (self.cfg.width, self.cfg.height);
                let particles = &self.particles;
                self.workers.for_each_mut3(&mut self.costs, &mut self.weights, &mut self.tips, |i, c, wt, t| {
                    let p = &particles[i];
                    VIRTUAL.with(|img| {
                        let mut img = img.borrow_mut();
                        img.resize(w * h, 0);
                        let (pi, d) = measure::paper_score(model, cams, fields, p, tau, &mut img);
                        *wt = pi;
                        *c = d;
                    });
                    *t = model.tip_in_base(&p.joints).map_or(Vector3::zeros(), |x| x.translation.vector);
                });
            }
        }
    }

    /// Ours: weights `exp(−(c − c_min)/τ)`; non-finite costs weigh zero.
    fn weights_from_costs(&mut self, tau: f64) -> bool {
        let cmin = self.costs.iter().copied().filter(|c| c.is_finite()).fold(f64::INFINITY, f64::min);
        if !cmin.is_finite() {
            return false;
        }
        for (w, &c) in self.weights.iter_mut().zip(&self.costs) {
            *w = if c.is_finite() { (-(c - cmin) / tau).exp() } else { 0.0 };
        }
        true
    }

    fn resample(&mut self) -> bool {
        let u0: f64 = self.rng.random::<f64>();
        if resample::low_variance(&self.weights, u0, &mut self.idx).is_err() {
            return false;
        }
        for (k, &i) in self.idx.iter().enumerate() {
            self.next[k] = self.particles[i];
        }
        std::mem::swap(&mut self.particles, &mut self.next);
        true
    }

    /// Coordinate descent on the best hypothesis; the objective is the cost plus, with
    /// [`OffsetMotion`], τ × the prior's negative log density (the posterior's, as the weights
    /// `exp(−c/τ)` are the likelihood): along what the images do not fix the prior decides.
    /// Returns the refined hypothesis and its cost (without the prior term).
    fn refine(
        &self,
        start: &Particle,
        start_cost: f64,
        cams: &StereoCameras,
        enc: &[f64; JOINTS],
        with_prior: bool,
    ) -> (Particle, f64) {
        let tau = self.cfg.tau_px;
        let objective = |p: &Particle, c: f64| if with_prior { c + tau * self.prior_of(p, enc).0 } else { c };
        let mut best = *start;
        let mut cost = start_cost;
        let mut best_obj = objective(&best, cost);
        let mut steps = [0.0; JOINTS + 1];
        for (s, n) in steps.iter_mut().zip(&self.cfg.joint_noise_rad) {
            *s = 2.0 * n;
        }
        steps[JOINTS] = 2.0 * self.cfg.jaw_noise_rad;
        for _ in 0..self.cfg.refine_sweeps {
            for (j, step) in steps.iter().enumerate() {
                for sign in [1.0, -1.0] {
                    let mut c = best;
                    if j < JOINTS {
                        c.joints[j] += sign * step;
                    } else {
                        c.jaw_rad = (c.jaw_rad + sign * step).clamp(0.0, 1.2);
                    }
                    let k = measure::cost_ours(&self.model, cams, &self.fields, &c, &self.cfg.ours);
                    let o = objective(&c, k);
                    if o < best_obj {
                        best = c;
                        cost = k;
                        best_obj = o;
                        break;
                    }
                }
            }
            for s in &mut steps {
                *s *= 0.5;
            }
        }
        (best, cost)
    }

    /// Processes one stereo frame: motion (the encoders' increment since the previous frame
    /// plus noise; with [`OffsetMotion`] the offset from the encoders reverting over the time
    /// since the previous frame), measurement, resampling, status. On error the state is unchanged.
    /// Allocation-free in [`Mode::Ours`].
    pub fn step(&mut self, input: &FrameInput<'_>) -> Result<Estimate, StepError> {
        if let Some(j) = input.encoder_rad.iter().position(|v| !v.is_finite()) {
            return Err(StepError::Encoder(j));
        }
        if !input.cameras.is_valid() {
            return Err(StepError::Cameras);
        }
        let n_px = self.cfg.width * self.cfg.height * 3;
        for (e, eye) in ["left", "right"].into_iter().enumerate() {
            if input.rgb[e].len() != n_px {
                return Err(StepError::Image {
                    eye,
                    source: ImageError::Size {
                        len: input.rgb[e].len(),
                        width: self.cfg.width,
                        height: self.cfg.height,
                        channels: 3,
                    },
                });
            }
        }
        if self.model.instrument_in_base(&input.encoder_rad).is_none() {
            return Err(StepError::Kinematics);
        }
        let cams = input.cameras;
        if !self.workers_started {
            // Start-up: the worker threads, from the stepping thread (they inherit its priority).
            self.workers = Workers::new(self.cfg.threads);
            self.workers_started = true;
        }
        // Edges, once per frame.
        match self.cfg.mode {
            Mode::Ours => {
                let (th, ec) = (self.cfg.edge_threshold, self.cfg.edge_contrast);
                let mut done = [Ok(()), Ok(())];
                self.workers.for_each_mut2(&mut self.fields, &mut done, |e, f, r| {
                    *r = f.compute_ours_adaptive(input.rgb[e], th, ec);
                });
                let [a, b] = done;
                a.and(b).map_err(|source| StepError::Image { eye: "left", source })?;
            }
            Mode::Paper => {
                let (w, h) = (self.cfg.width as u32, self.cfg.height as u32);
                let [lo, hi] = self.cfg.canny_px;
                for (e, f) in self.fields.iter_mut().enumerate() {
                    let grey: Vec<u8> = input.rgb[e]
                        .chunks_exact(3)
                        .map(|p| (0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]) + 0.114 * f32::from(p[2])) as u8)
                        .collect();
                    let img = image::GrayImage::from_raw(w, h, grey).ok_or(StepError::Image {
                        eye: "left",
                        source: ImageError::Size { len: 0, width: w as usize, height: h as usize, channels: 1 },
                    })?;
                    let edges = imageproc::edges::canny(&img, lo, hi);
                    f.set_edges(edges.as_raw()).map_err(|source| StepError::Image { eye: "left", source })?;
                }
            }
        }
        // Time step (the offset model's ρ).
        let dt_s = match (input.time_ns, self.last_time_ns) {
            (Some(t), Some(t0)) if t >= t0 => Some((t - t0) as f64 * 1e-9),
            // The first timed frame after `initialise`: the particles were put at it.
            (Some(_), None) => Some(0.0),
            _ => None,
        };
        // Motion (Eq. 13 or the offset model), or initialisation from the kinematics.
        let mut reinitialised = false;
        match self.last_encoder {
            None => {
                self.init_particles(&input.encoder_rad, &input.encoder_rad);
                reinitialised = true;
            }
            Some(prev) => {
                let inc: [f64; JOINTS] = core::array::from_fn(|j| input.encoder_rad[j] - prev[j]);
                let scale = match self.cfg.adaptive_noise {
                    // The offset model's innovation is not scaled: after a poor fit the prior
                    // decides (exploring beyond it is how the filter drifted onto clutter).
                    _ if self.cfg.offset_motion.is_some() => 1.0,
                    // After a lost frame there was nothing to fit: no extra exploration while
                    // held on the kinematics (it finds the occluder's edges).
                    Some(_) if self.cfg.hold_while_lost && self.lost_run > 0 => 1.0,
                    Some((good, max)) if self.last_cost_px.is_finite() => {
                        (self.last_cost_px / good).clamp(1.0, max.sqrt()).powi(2)
                    }
                    Some((_, max)) => max,
                    None => 1.0,
                };
                match self.cfg.offset_motion {
                    Some(m) => {
                        let dt = dt_s.filter(|d| d.is_finite() && *d <= 10.0).unwrap_or(m.nominal_period_s);
                        self.diffuse_offset(&m, &input.encoder_rad, &prev, m.rho(dt), scale);
                    }
                    None => self.diffuse(&inc, scale, 0),
                }
            }
        }
        // Re-seeding from the detected shaft (ours), before the cloud is measured.
        let axis = self.axis.take();
        let mut reseeded_from_vision = false;
        self.last_reseed_share = f64::NAN;
        if let (Mode::Ours, Some(pc), Some(axis), Some(prev)) =
            (self.cfg.mode, self.cfg.proposal, axis, self.last_encoder)
        {
            reseeded_from_vision = self.reseed_from_axis(&pc, &axis, &cams, &input.encoder_rad, &prev);
        }
        self.last_encoder = Some(input.encoder_rad);
        if input.time_ns.is_some() {
            self.last_time_ns = input.time_ns;
        }
        self.evaluate(&cams);
        let (best_i, best_cost) = match self.cfg.mode {
            Mode::Ours => {
                let layers = self.cfg.anneal_layers;
                for l in 0..layers {
                    let tau = self.cfg.tau_px * 2f64.powi((layers - l) as i32);
                    if !self.weights_from_costs(tau) || !self.resample() {
                        break;
                    }
                    self.diffuse(&[0.0; JOINTS], 0.5f64.powi(l as i32 + 1), l as u64 + 1);
                    self.evaluate(&cams);
                }
                let ok = self.weights_from_costs(self.cfg.tau_px);
                let bi = if self.cfg.offset_motion.is_some() {
                    // The posterior's best: the cost plus τ × the prior's term.
                    let tau = self.cfg.tau_px;
                    let enc = input.encoder_rad;
                    let mut bi = argmin(&self.costs);
                    let mut bo = self.costs[bi] + tau * self.prior_of(&self.particles[bi], &enc).0;
                    for (i, (p, &c)) in self.particles.iter().zip(&self.costs).enumerate() {
                        if c.is_finite() {
                            let o = c + tau * self.prior_of(p, &enc).0;
                            if o < bo {
                                (bi, bo) = (i, o);
                            }
                        }
                    }
                    bi
                } else {
                    argmin(&self.costs)
                };
                if !ok { (bi, f64::INFINITY) } else { (bi, self.costs[bi]) }
            }
            Mode::Paper => {
                let bi = argmax(&self.weights);
                (bi, self.costs[bi])
            }
        };
        // Spread and effective particles of the final weights.
        let total: f64 = self.weights.iter().sum();
        let (spread, ess) = if total > 0.0 && total.is_finite() {
            let mut mean = Vector3::zeros();
            for (w, t) in self.weights.iter().zip(&self.tips) {
                mean += t * (w / total);
            }
            let mut var = 0.0;
            let mut s2 = 0.0;
            for (w, t) in self.weights.iter().zip(&self.tips) {
                let wn = w / total;
                var += wn * (t - mean).norm_squared();
                s2 += wn * wn;
            }
            (var.sqrt(), 1.0 / s2)
        } else {
            (f64::INFINITY, 0.0)
        };
        // The best hypothesis, refined (ours).
        let mut best = self.particles[best_i];
        let mut best_cost = best_cost;
        if self.cfg.mode == Mode::Ours && self.cfg.refine_sweeps > 0 && best_cost.is_finite() {
            let (p, c) = self.refine(&best, best_cost, &cams, &input.encoder_rad, true);
            best = p;
            best_cost = c;
            // The refined hypothesis replaces the worst particle.
            let wi = argmax_cost(&self.costs);
            self.particles[wi] = best;
            self.costs[wi] = best_cost;
            self.weights[wi] = self.weights[best_i].max(self.weights[wi]);
        }
        self.last_best = Some(best);
        let per_eye = match self.cfg.mode {
            Mode::Ours => best_cost / 2.0,
            Mode::Paper => best_cost,
        };
        self.last_cost_px = per_eye;
        let mut held_by_prior = false;
        self.last_line_share = f64::NAN;
        let lost = match (self.cfg.mode, self.cfg.lost_inlier_share) {
            (Mode::Ours, Some(min)) => {
                let (c, inl) = measure::fit_ours(&self.model, &cams, &self.fields, &best, &self.cfg.ours);
                self.last_inlier_share = 0.5 * (inl[0] + inl[1]);
                let lost = !(c.is_finite() && self.last_inlier_share >= min);
                match self.cfg.offset_motion.and_then(|m| m.prior_lost) {
                    Some(pl) if lost && c.is_finite() => {
                        // The visible part fits where the prior says the instrument is.
                        let lines = measure::shaft_line_shares(&self.model, &cams, &self.fields, &best, &self.cfg.ours);
                        self.last_line_share = 0.5 * (lines[0] + lines[1]);
                        let plausible = self.prior_of(&best, &input.encoder_rad).1 <= pl.max_sigma;
                        held_by_prior = plausible && self.last_line_share >= pl.line_share;
                        !held_by_prior
                    }
                    _ => lost,
                }
            }
            _ => !(per_eye.is_finite() && per_eye <= self.cfg.lost_cost_px),
        };
        let mut status = if lost {
            Status::Lost
        } else if spread > self.cfg.uncertain_spread_m {
            Status::Uncertain
        } else {
            Status::Tracking
        };
        let pose = if lost { None } else { self.pose_of(&best, &cams) };
        if pose.is_none() {
            status = Status::Lost;
        }
        // Resample for the next frame.
        if !self.resample() {
            status = Status::Lost;
        }
        self.frame += 1;
        if status == Status::Lost {
            self.lost_run += 1;
            if self.lost_run >= self.cfg.reinit_after_lost {
                let run = self.lost_run;
                // Back to the kinematics (plus the offset's mean: zero unless it reverts to
                // the start), with the initial (offset model: the stationary) spread.
                let centre: [f64; JOINTS] = core::array::from_fn(|j| input.encoder_rad[j] + self.offset_mean[j]);
                self.init_particles(&centre, &input.encoder_rad);
                reinitialised = true;
                if self.cfg.hold_while_lost {
                    // Stay on the kinematics while the instrument is not found.
                    self.lost_run = run;
                }
            }
        } else {
            self.lost_run = 0;
        }
        Ok(Estimate {
            status,
            pose: if status == Status::Lost { None } else { pose },
            spread_m: spread,
            best_cost_px: per_eye,
            effective_particles: ess,
            reinitialised,
            held_by_prior: held_by_prior && status != Status::Lost,
            reseeded_from_vision,
        })
    }

    /// [`ProposalConfig`]'s rule on this frame (the edge fields computed, the particles moved
    /// to it): `true` when the particles were re-initialised about a hypothesis on `axis`.
    /// `prev`: the previous frame's encoders. Allocation-free.
    fn reseed_from_axis(
        &mut self,
        pc: &ProposalConfig,
        axis: &ShaftAxis,
        cams: &StereoCameras,
        enc: &[f64; JOINTS],
        prev: &[f64; JOINTS],
    ) -> bool {
        let Some(last) = self.last_best else { return false };
        // The reference: the previous best moved with the encoders (same offset).
        let mut reference = last;
        for j in 0..JOINTS {
            reference.joints[j] = enc[j] + (last.joints[j] - prev[j]);
        }
        let (_, inl) = measure::fit_ours(&self.model, cams, &self.fields, &reference, &self.cfg.ours);
        let ref_share = 0.5 * (inl[0] + inl[1]);
        if ref_share >= pc.trigger_share || !proposal::axis_consistent(&self.model, &reference.joints, axis, pc) {
            return false;
        }
        // The reference put on the axis once; every hypothesis is solved from there.
        let Some(q_axis) = proposal::joints_for_axis(&self.model, &reference.joints, axis, 0.0, 0.0) else {
            return false;
        };
        let distal = proposal::slide_to_distal_end(&self.model, &q_axis, axis);
        let seed = mix(mix(self.cfg.seed, self.frame), 0x5EED_A715);
        let model = &self.model;
        let (fields, oc) = (&self.fields, self.cfg.ours);
        let n = self.proposals.len();
        self.workers.for_each_mut2(&mut self.proposals, &mut self.prop_costs, |i, p, c| {
            let mut r = ChaCha8Rng::seed_from_u64(mix(seed, i as u64));
            // Half about the detected distal end (when there is one), half about the reference.
            let centre = if i < n / 2 { distal.unwrap_or(0.0) } else { 0.0 };
            let first = i == 0 || i == n / 2;
            let slide = if first { centre } else { centre + pc.slide_sigma_m * r.sample::<f64, _>(StandardNormal) };
            let roll = if first { 0.0 } else { pc.roll_sigma_rad * r.sample::<f64, _>(StandardNormal) };
            *p = reference;
            // Every other hypothesis with a jaw angle drawn over the jaws' range.
            if i % 2 == 1 {
                p.jaw_rad = r.random_range(0.0..0.8);
            }
            let target = proposal::instrument_on_axis(model, &q_axis, axis, slide, roll);
            match target.and_then(|t| proposal::solve_instrument_pose(model, &q_axis, &t, 8)) {
                Some(q) => {
                    p.joints = q;
                    *c = measure::cost_ours(model, cams, fields, p, &oc);
                }
                None => *c = f64::INFINITY,
            }
        });
        let bi = argmin(&self.prop_costs);
        let c0 = self.prop_costs[bi];
        if !c0.is_finite() {
            return false;
        }
        let (best, _) = self.refine(&self.proposals[bi], c0, cams, enc, false);
        let (c, inl) = measure::fit_ours(&self.model, cams, &self.fields, &best, &self.cfg.ours);
        let share = 0.5 * (inl[0] + inl[1]);
        self.last_reseed_share = share;
        if !(c.is_finite() && share >= pc.accept_share && share >= ref_share + pc.margin) {
            return false;
        }
        let jaw = best.jaw_rad;
        self.init_particles(&best.joints, enc);
        for p in &mut self.particles {
            p.jaw_rad = jaw;
        }
        true
    }

    fn pose_of(&self, p: &Particle, cams: &StereoCameras) -> Option<TrackedPose> {
        let tip = self.model.tip_in_base(&p.joints)?;
        let eyes = cams.eyes_from_base(&p.camera_delta);
        let cam = eyes[0] * tip;
        let finite = |t: &Isometry3<f64>| {
            t.translation.vector.iter().all(|v| v.is_finite()) && t.rotation.coords.iter().all(|v| v.is_finite())
        };
        (finite(&tip) && finite(&cam) && p.jaw_rad.is_finite()).then_some(TrackedPose {
            tip_in_base: tip,
            tip_in_camera: cam,
            jaw_rad: p.jaw_rad,
            joints_rad: p.joints,
            camera_delta: p.camera_delta,
        })
    }

    /// The cost (ours, pixels summed over both eyes) of one hypothesis on the last frame's edges.
    pub fn cost_of(&self, p: &Particle, cams: &StereoCameras) -> f64 {
        measure::cost_ours(&self.model, cams, &self.fields, p, &self.cfg.ours)
    }
}

thread_local! {
    static VIRTUAL: std::cell::RefCell<Vec<u8>> = const { std::cell::RefCell::new(Vec::new()) };
}

fn argmin(v: &[f64]) -> usize {
    let mut bi = 0;
    for (i, &c) in v.iter().enumerate() {
        if c < v[bi] || !v[bi].is_finite() && c.is_finite() {
            bi = i;
        }
    }
    bi
}

fn argmax(v: &[f64]) -> usize {
    let mut bi = 0;
    for (i, &c) in v.iter().enumerate() {
        if c > v[bi] {
            bi = i;
        }
    }
    bi
}

fn argmax_cost(v: &[f64]) -> usize {
    let mut bi = 0;
    for (i, &c) in v.iter().enumerate() {
        if !c.is_finite() || c > v[bi] {
            bi = i;
            if !c.is_finite() {
                break;
            }
        }
    }
    bi
}
