//! `comanip-track`'s configuration (TOML, `configs/comanip-track.toml`): every key optional,
//! unknown keys refused, errors naming the file, the line and the key.

use std::path::{Path, PathBuf};

use hw_io::calib_files::TransformJson;
use serde::Deserialize;
use track::{Mode, OffsetMotion, PriorLost, RevertTo, TrackerConfig};

/// The file's schema. Units are in the key names.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackFile {
    /// `paper` or `ours`.
    pub mode: Mode,
    /// Particles (`--particles` overrides).
    pub particles: Option<usize>,
    /// Threads of the particle loops, the tracking thread included (`--threads` overrides); 0
    /// or absent: the processors available to the process (`TrackerConfig::threads`).
    pub threads: Option<usize>,
    /// The instrument on the tool arm.
    pub tool: ToolSection,
    /// Process noise.
    pub noise: NoiseSection,
    /// Measurement.
    pub measurement: MeasurementSection,
    /// Filter and status.
    pub filter: FilterSection,
    /// Ours: the motion model.
    pub motion: MotionSection,
    /// The camera rig and the starting camera-to-base transform (the live process).
    pub rig: RigSection,
    /// How sparse and how old the arms' joint readings may be (the live process).
    pub joints: JointsSection,
    /// Ours: re-seeding from the detected shaft (offline commands).
    pub proposal: ProposalSection,
}

/// `[proposal]` (ours): re-seeding the particles from the shaft detected by `vision::ours`
/// in both eyes (`track::ProposalConfig`; docs/tracking.md "Re-seeding from the detected
/// shaft"). Off unless `enabled = true`; an absent key takes `ProposalConfig::default`. Used by
/// the offline commands (`run`, `converge`, `scenes`, `noise`, `calib-error`), not by `live`.
#[derive(Clone, Copy, Debug, PartialEq, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ProposalSection {
    /// On/off (default off).
    pub enabled: Option<bool>,
    /// Hypotheses on the axis per triggered frame.
    pub count: Option<usize>,
    /// Tried when the previous best's inlier share (0..1) is below this.
    pub trigger_share: Option<f64>,
    /// The best hypothesis on the axis must reach this inlier share (0..1).
    pub accept_share: Option<f64>,
    /// ... and beat the previous best's by this (0..1).
    pub margin: Option<f64>,
    /// Slide along the axis, standard deviation, metres.
    pub slide_sigma_m: Option<f64>,
    /// Roll about the axis, standard deviation, radians.
    pub roll_sigma_rad: Option<f64>,
    /// The detection is ignored beyond this angle from the previous best's axis, radians.
    pub max_angle_rad: Option<f64>,
    /// ... or this distance from its instrument origin, metres.
    pub max_distance_m: Option<f64>,
}

/// `[joints]` (the live process): how far apart and how old the arms' joint readings around a
/// frame's time may be before the frame is refused (`tool-joints-stale`,
/// `endoscope-joints-stale`), and how long a frame waits for the bus listener to pass its time;
/// milliseconds. An absent limit is scaled from fulcrumd's control period `T`
/// (`cycle.period_us`): the tool arm answers every SYNC (gap 5 T, age 20 T: 5 and 20 ms at
/// 1 kHz), the endoscope arm every 10th (gap 25 T, age 50 T).
#[derive(Clone, Copy, Debug, PartialEq, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct JointsSection {
    /// Largest gap between the two tool-arm samples around a frame's time, ms.
    pub tool_max_gap_ms: Option<f64>,
    /// Largest age of the newest tool-arm sample when the frame is newer than it, ms.
    pub tool_max_age_ms: Option<f64>,
    /// As `tool_max_gap_ms`, for the endoscope arm.
    pub endoscope_max_gap_ms: Option<f64>,
    /// As `tool_max_age_ms`, for the endoscope arm.
    pub endoscope_max_age_ms: Option<f64>,
    /// How long a frame newer than the bus waits for the listener to catch up, ms (default 30).
    pub wait_ms: Option<f64>,
}

/// What [`JointsSection::resolve`] gives: the staleness rules of both arms and the wait.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct JointsRules {
    /// The tool arm's rule.
    pub tool: controller::bus_listen::Staleness,
    /// The endoscope arm's rule.
    pub endoscope: controller::bus_listen::Staleness,
    /// The catch-up wait.
    pub wait: std::time::Duration,
}

impl JointsSection {
    /// The rules for fulcrumd's control period `period_us` (microseconds).
    pub fn resolve(&self, period_us: u32) -> JointsRules {
        use controller::bus_listen::Staleness;
        let t_ms = f64::from(period_us) / 1e3;
        let ns = |v: Option<f64>, periods: f64| ((v.unwrap_or(periods * t_ms)) * 1e6).round() as u64;
        JointsRules {
            tool: Staleness { max_gap_ns: ns(self.tool_max_gap_ms, 5.0), max_age_ns: ns(self.tool_max_age_ms, 20.0) },
            endoscope: Staleness {
                max_gap_ns: ns(self.endoscope_max_gap_ms, 25.0),
                max_age_ns: ns(self.endoscope_max_age_ms, 50.0),
            },
            wait: std::time::Duration::from_secs_f64(self.wait_ms.unwrap_or(30.0) / 1e3),
        }
    }
}

/// `[rig]`: what `comanip-track live` needs besides the frames and the bus: the stereo cameras,
/// the hand-eye transform, the transform it starts from until a live calibration arrives, and
/// the instrument's dimensions.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RigSection {
    /// The left and right eyes' `camera_info` YAML files (`--cameras` overrides).
    pub cameras: Option<[PathBuf; 2]>,
    /// `T_f_c`: the left camera in the endoscope arm's flange frame, metres and unit quaternion
    /// `[w, x, y, z]` (default: the simulated endoscope's).
    pub hand_eye: TransformJson,
    /// `T_b_e`: the endoscope arm's RCM frame in the tool arm's base frame, metres and unit
    /// quaternion (the calibration), used until `comanip-calib live` publishes a valid one
    /// (default: the simulated set-up's `rcm_in_tool_base`).
    pub endoscope_in_tool_base: TransformJson,
    /// The instrument's dimensions, metres (default: the simulated instrument's).
    pub instrument: sim::endoscope::InstrumentGeometry,
}

impl Default for RigSection {
    fn default() -> Self {
        let h = std::f64::consts::FRAC_1_SQRT_2;
        Self {
            cameras: None,
            hand_eye: TransformJson { translation_m: [-0.0025, 0.0, 0.0], quaternion_wxyz: [1.0, 0.0, 0.0, 0.0] },
            endoscope_in_tool_base: TransformJson {
                translation_m: [0.29, 0.0, 0.16],
                quaternion_wxyz: [0.0, h, h, 0.0],
            },
            instrument: sim::endoscope::InstrumentGeometry::default(),
        }
    }
}

/// `[tool]`.
#[derive(Clone, Copy, Debug, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ToolSection {
    /// Wrist centre to tip (jaw pivot), metres.
    pub instrument_length_m: f64,
    /// Shaft modelled back from its distal end, metres.
    pub shaft_modelled_m: f64,
    /// Sides of the model's cylinders.
    pub segments: usize,
}

impl Default for ToolSection {
    fn default() -> Self {
        Self { instrument_length_m: 0.3, shaft_modelled_m: 0.10, segments: 16 }
    }
}

/// `[noise]`. `None`: the mode's default.
#[derive(Clone, Copy, Debug, PartialEq, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NoiseSection {
    /// Eq. 13's σ per joint per frame, radians.
    pub joint_rad: Option<[f64; 6]>,
    /// Particles' spread about the kinematics at (re-)initialisation, radians per joint.
    pub init_spread_rad: Option<[f64; 6]>,
    /// Jaw noise per frame, radians.
    pub jaw_rad: Option<f64>,
    /// Initial jaw angle, radians.
    pub jaw_init_rad: Option<f64>,
    /// `g_CB` augmentation noise per frame `[rotation rad, translation m]` (absent: off).
    pub camera: Option<[f64; 2]>,
}

/// `[measurement]`.
#[derive(Clone, Copy, Debug, PartialEq, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MeasurementSection {
    /// τ, pixels.
    pub tau_px: Option<f64>,
    /// Ours: truncation, pixels.
    pub truncate_px: Option<f64>,
    /// Ours: orientation weight, pixels.
    pub orientation_px: Option<f64>,
    /// Ours: samples per shaft contour line.
    pub shaft_samples: Option<usize>,
    /// Ours: Sobel magnitude threshold.
    pub edge_threshold: Option<f32>,
    /// Paper: Canny thresholds `[low, high]`.
    pub canny: Option<[f32; 2]>,
    /// Ours: the edge threshold adapted to the frame's contrast `[reference, noise_factor]`
    /// (`track::EdgeContrast`: the clear frame's 99.9th percentile of the Sobel magnitude, and
    /// the floor in multiples of the frame's median); absent: the default (`[75, 2.5]` in
    /// ours); a reference at or below 0: the fixed threshold.
    pub edge_contrast: Option<[f32; 2]>,
}

/// `[motion]`'s `model`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MotionModel {
    /// The kinematic error as state, mean-reverting (`track::OffsetMotion`; ours' default).
    Offset,
    /// Eq. 13's random walk on the joints (the paper's; `[noise] joint_rad`).
    Joints,
}

/// `[motion]` (ours). `None`: the default of `track::OffsetMotion::default_ours`.
#[derive(Clone, Copy, Debug, PartialEq, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MotionSection {
    /// `offset` (default in ours) or `joints`; the paper's mode accepts `joints` only.
    pub model: Option<MotionModel>,
    /// The offset's reversion time constant, seconds (> 0).
    pub time_constant_s: Option<f64>,
    /// The offset's stationary standard deviation per joint, radians (≥ 0): the expected
    /// encoder and calibration error; the spread at (re-)initialisation.
    pub stationary_rad: Option<[f64; 6]>,
    /// `kinematics` (default) or `start`: what the offset returns to.
    pub revert_to: Option<RevertTo>,
    /// Frame period when frames carry no time, seconds (0 < period ≤ 10).
    pub nominal_period_s: Option<f64>,
    /// LOST with the prior: the most standard deviations a plausible offset is off its mean
    /// (> 0).
    pub prior_lost_max_sigma: Option<f64>,
    /// LOST with the prior: the worse shaft contour line's smallest inlier share (0..1);
    /// negative: the rule off (the inlier share alone decides).
    pub prior_lost_line_share: Option<f64>,
}

/// `[filter]`.
#[derive(Clone, Copy, Debug, PartialEq, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FilterSection {
    /// Ours: annealing layers.
    pub anneal_layers: Option<usize>,
    /// Ours: refinement sweeps.
    pub refine_sweeps: Option<usize>,
    /// Spread above which a frame is UNCERTAIN, metres.
    pub uncertain_spread_m: Option<f64>,
    /// Cost above which a frame is LOST, pixels.
    pub lost_cost_px: Option<f64>,
    /// Lost frames before re-initialisation from the kinematics.
    pub reinit_after_lost: Option<u32>,
    /// Ours: LOST below this inlier share (0..1); a negative value: by `lost_cost_px`.
    pub lost_inlier_share: Option<f64>,
    /// Ours: keep the particles on the kinematics while lost.
    pub hold_while_lost: Option<bool>,
    /// Ours: adaptive process noise `[good_px, max_scale]`.
    pub adaptive_noise: Option<[f64; 2]>,
    /// Noise seed.
    pub seed: Option<u64>,
}

impl Default for TrackFile {
    fn default() -> Self {
        Self {
            mode: Mode::Ours,
            particles: None,
            threads: None,
            tool: ToolSection::default(),
            noise: NoiseSection::default(),
            measurement: MeasurementSection::default(),
            filter: FilterSection::default(),
            motion: MotionSection::default(),
            rig: RigSection::default(),
            joints: JointsSection::default(),
            proposal: ProposalSection::default(),
        }
    }
}

/// Why the configuration was refused.
#[derive(Debug, thiserror::Error)]
pub enum ConfigFileError {
    /// Unreadable file.
    #[error("cannot read config file {path}: {source}")]
    Read {
        /// File.
        path: PathBuf,
        /// OS error.
        source: std::io::Error,
    },
    /// Not TOML of this schema (the message names the line, column and key).
    #[error("config file {path}: {message}")]
    Parse {
        /// File.
        path: PathBuf,
        /// Parser message.
        message: String,
    },
    /// A value out of range.
    #[error("config file {path}: {key}: {message}")]
    Value {
        /// File.
        path: PathBuf,
        /// The key.
        key: &'static str,
        /// Why.
        message: String,
    },
}

impl TrackFile {
    /// Parses `text` (`path` for the messages) and checks the values.
    pub fn from_toml(text: &str, path: &Path) -> Result<Self, ConfigFileError> {
        let f: TrackFile = toml::from_str(text)
            .map_err(|e| ConfigFileError::Parse { path: path.to_owned(), message: e.to_string() })?;
        let t = &f.tool;
        let bad = |key: &'static str, message: &str| ConfigFileError::Value {
            path: path.to_owned(),
            key,
            message: message.to_string(),
        };
        if !(t.instrument_length_m.is_finite() && t.instrument_length_m > 0.02) {
            return Err(bad("tool.instrument_length_m", "must be finite and above 0.02 m"));
        }
        if !(t.shaft_modelled_m.is_finite() && t.shaft_modelled_m > 0.0) {
            return Err(bad("tool.shaft_modelled_m", "must be finite and positive"));
        }
        if !(3..=128).contains(&t.segments) {
            return Err(bad("tool.segments", "must be in 3..=128"));
        }
        for (key, x) in
            [("rig.hand_eye", &f.rig.hand_eye), ("rig.endoscope_in_tool_base", &f.rig.endoscope_in_tool_base)]
        {
            let n2: f64 = x.quaternion_wxyz.iter().map(|v| v * v).sum();
            if !(x.translation_m.iter().chain(&x.quaternion_wxyz).all(|v| v.is_finite()) && n2 > 1e-12) {
                return Err(bad(key, "must be finite with a non-zero quaternion"));
            }
        }
        if f.rig.instrument.mesh().is_err() {
            return Err(bad(
                "rig.instrument",
                "not a valid instrument (positive dimensions, wrist no wider than the shaft)",
            ));
        }
        let j = &f.joints;
        for (key, v) in [
            ("joints.tool_max_gap_ms", j.tool_max_gap_ms),
            ("joints.tool_max_age_ms", j.tool_max_age_ms),
            ("joints.endoscope_max_gap_ms", j.endoscope_max_gap_ms),
            ("joints.endoscope_max_age_ms", j.endoscope_max_age_ms),
        ] {
            if v.is_some_and(|v| !(v.is_finite() && v > 0.0 && v <= 10_000.0)) {
                return Err(bad(key, "must be a number of milliseconds in (0, 10000]"));
            }
        }
        if j.wait_ms.is_some_and(|v| !(v.is_finite() && (0.0..=10_000.0).contains(&v))) {
            return Err(bad("joints.wait_ms", "must be a number of milliseconds in [0, 10000]"));
        }
        let m = &f.motion;
        if f.mode == Mode::Paper && m.model == Some(MotionModel::Offset) {
            return Err(bad("motion.model", "offset is ours only (the paper's mode: joints)"));
        }
        if let Some(v) = m.time_constant_s
            && !(v.is_finite() && v > 0.0)
        {
            return Err(bad("motion.time_constant_s", "must be finite and positive"));
        }
        if let Some(v) = m.stationary_rad
            && let Some(j) = v.iter().position(|x| !(x.is_finite() && *x >= 0.0))
        {
            return Err(ConfigFileError::Value {
                path: path.to_owned(),
                key: "motion.stationary_rad",
                message: format!("element {j} must be finite and non-negative"),
            });
        }
        if let Some(v) = m.nominal_period_s
            && !(v.is_finite() && v > 0.0 && v <= 10.0)
        {
            return Err(bad("motion.nominal_period_s", "must be in (0, 10] seconds"));
        }
        if let Some(v) = m.prior_lost_max_sigma
            && !(v.is_finite() && v > 0.0)
        {
            return Err(bad("motion.prior_lost_max_sigma", "must be finite and positive"));
        }
        if let Some(v) = m.prior_lost_line_share
            && !(v.is_finite() && v <= 1.0)
        {
            return Err(bad("motion.prior_lost_line_share", "must be finite and at most 1 (negative: off)"));
        }
        f.tracker(640, 480).validate().map_err(|e| ConfigFileError::Value {
            path: path.to_owned(),
            key: e.0,
            message: "out of range".into(),
        })?;
        Ok(f)
    }

    /// Reads and checks a file.
    pub fn load(path: &Path) -> Result<Self, ConfigFileError> {
        let text =
            std::fs::read_to_string(path).map_err(|source| ConfigFileError::Read { path: path.to_owned(), source })?;
        Self::from_toml(&text, path)
    }

    /// The tracker's configuration for `width × height` images.
    pub fn tracker(&self, width: usize, height: usize) -> TrackerConfig {
        let mut c = TrackerConfig::new(self.mode, width, height);
        if let Some(n) = self.particles {
            c.particles = n;
        }
        if let Some(n) = self.threads {
            c.threads = n;
        }
        let n = &self.noise;
        if let Some(v) = n.joint_rad {
            c.joint_noise_rad = v;
        }
        if let Some(v) = n.init_spread_rad {
            c.init_spread_rad = v;
        }
        if let Some(v) = n.jaw_rad {
            c.jaw_noise_rad = v;
        }
        if let Some(v) = n.jaw_init_rad {
            c.jaw_init_rad = v;
        }
        c.camera_noise = n.camera;
        let m = &self.measurement;
        if let Some(v) = m.tau_px {
            c.tau_px = v;
        }
        if let Some(v) = m.truncate_px {
            c.ours.truncate_px = v;
        }
        if let Some(v) = m.orientation_px {
            c.ours.orientation_px = v;
        }
        if let Some(v) = m.shaft_samples {
            c.ours.shaft_samples = v;
        }
        if let Some(v) = m.edge_threshold {
            c.edge_threshold = v;
        }
        if let Some(v) = m.canny {
            c.canny_px = v;
        }
        if let Some([r, k]) = m.edge_contrast {
            // A reference at or below 0: the fixed threshold.
            c.edge_contrast =
                (r > 0.0 || r.is_nan()).then_some(track::EdgeContrast { reference_px: r, noise_factor: k });
        }
        let f = &self.filter;
        if let Some(v) = f.anneal_layers {
            c.anneal_layers = v;
        }
        if let Some(v) = f.refine_sweeps {
            c.refine_sweeps = v;
        }
        if let Some(v) = f.uncertain_spread_m {
            c.uncertain_spread_m = v;
        }
        if let Some(v) = f.lost_cost_px {
            c.lost_cost_px = v;
        }
        if let Some(v) = f.reinit_after_lost {
            c.reinit_after_lost = v;
        }
        if let Some(v) = f.lost_inlier_share {
            c.lost_inlier_share = (v >= 0.0 || v.is_nan()).then_some(v);
        }
        if let Some(v) = f.hold_while_lost {
            c.hold_while_lost = v;
        }
        if let Some([g, m]) = f.adaptive_noise {
            c.adaptive_noise = Some((g, m));
        }
        if let Some(v) = f.seed {
            c.seed = v;
        }
        let m = &self.motion;
        c.offset_motion = match (self.mode, m.model) {
            (Mode::Paper, _) | (_, Some(MotionModel::Joints)) => None,
            (Mode::Ours, _) => {
                let mut o = c.offset_motion.unwrap_or_else(OffsetMotion::default_ours);
                if let Some(v) = m.time_constant_s {
                    o.time_constant_s = v;
                }
                if let Some(v) = m.stationary_rad {
                    o.stationary_rad = v;
                }
                if let Some(v) = m.revert_to {
                    o.revert_to = v;
                }
                if let Some(v) = m.nominal_period_s {
                    o.nominal_period_s = v;
                }
                let d =
                    OffsetMotion::default_ours().prior_lost.unwrap_or(PriorLost { max_sigma: 3.0, line_share: 0.1 });
                let mut pl = o.prior_lost.unwrap_or(d);
                if let Some(v) = m.prior_lost_max_sigma {
                    pl.max_sigma = v;
                }
                if let Some(v) = m.prior_lost_line_share {
                    pl.line_share = v;
                }
                o.prior_lost = (pl.line_share >= 0.0).then_some(pl);
                Some(o)
            }
        };
        let p = &self.proposal;
        c.proposal = p.enabled.unwrap_or(false).then(|| {
            let mut o = track::ProposalConfig::default();
            let set = |dst: &mut f64, v: Option<f64>| {
                if let Some(v) = v {
                    *dst = v;
                }
            };
            if let Some(v) = p.count {
                o.count = v;
            }
            set(&mut o.trigger_share, p.trigger_share);
            set(&mut o.accept_share, p.accept_share);
            set(&mut o.margin, p.margin);
            set(&mut o.slide_sigma_m, p.slide_sigma_m);
            set(&mut o.roll_sigma_rad, p.roll_sigma_rad);
            set(&mut o.max_angle_rad, p.max_angle_rad);
            set(&mut o.max_distance_m, p.max_distance_m);
            o
        });
        c
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_file_parses() {
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/comanip-track.toml");
        let f = TrackFile::load(&p).unwrap();
        assert_eq!(f.tool, ToolSection::default());
    }

    #[test]
    fn errors_name_the_key() {
        let e = TrackFile::from_toml("[filter]\nlost_cost_px = -1.0\n", Path::new("x.toml")).unwrap_err();
        assert!(e.to_string().contains("lost_cost_px"), "{e}");
        let e = TrackFile::from_toml("[tool]\nbogus = 1\n", Path::new("x.toml")).unwrap_err();
        assert!(e.to_string().contains("bogus"), "{e}");
        let e = TrackFile::from_toml(
            "[rig]\nhand_eye = { translation_m = [0.0, 0.0, nan], quaternion_wxyz = [1.0, 0.0, 0.0, 0.0] }\n",
            Path::new("x.toml"),
        )
        .unwrap_err();
        assert!(e.to_string().contains("rig.hand_eye"), "{e}");
        let e = TrackFile::from_toml("particles = 0\n", Path::new("x.toml")).unwrap_err();
        assert!(e.to_string().contains("particles"), "{e}");
        let e = TrackFile::from_toml("threads = 5000\n", Path::new("x.toml")).unwrap_err();
        assert!(e.to_string().contains("threads"), "{e}");
        let f = TrackFile::from_toml("threads = 3\n", Path::new("x.toml")).unwrap();
        assert_eq!(f.tracker(640, 480).threads, 3);
        assert_eq!(TrackFile::default().tracker(640, 480).threads, 0, "default: the machine's processors");
        let e = TrackFile::from_toml("[joints]\ntool_max_age_ms = nan\n", Path::new("x.toml")).unwrap_err();
        assert!(e.to_string().contains("joints.tool_max_age_ms"), "{e}");
        let e = TrackFile::from_toml("[joints]\nendoscope_max_gap_ms = 0.0\n", Path::new("x.toml")).unwrap_err();
        assert!(e.to_string().contains("joints.endoscope_max_gap_ms"), "{e}");
        let e = TrackFile::from_toml("[joints]\nwait_ms = -1.0\n", Path::new("x.toml")).unwrap_err();
        assert!(e.to_string().contains("joints.wait_ms"), "{e}");
    }

    #[test]
    fn joint_staleness_scales_with_the_control_period_unless_given() {
        use controller::bus_listen::Staleness;
        let f = TrackFile::default();
        let r = f.joints.resolve(1000);
        assert_eq!((r.tool, r.endoscope), (Staleness::TOOL, Staleness::ENDOSCOPE), "the 1 kHz rules");
        assert_eq!(r.wait, std::time::Duration::from_millis(30));
        let r = f.joints.resolve(2000);
        assert_eq!(r.tool, Staleness { max_gap_ns: 10_000_000, max_age_ns: 40_000_000 });
        assert_eq!(r.endoscope, Staleness { max_gap_ns: 50_000_000, max_age_ns: 100_000_000 });
        let f = TrackFile::from_toml("[joints]\ntool_max_gap_ms = 50.0\nwait_ms = 200\n", Path::new("x.toml")).unwrap();
        let r = f.joints.resolve(2000);
        assert_eq!(r.tool, Staleness { max_gap_ns: 50_000_000, max_age_ns: 40_000_000 });
        assert_eq!(r.wait, std::time::Duration::from_millis(200));
    }

    #[test]
    fn proposal_and_edge_contrast_keys_are_checked_and_applied() {
        let x = Path::new("x.toml");
        for (text, key) in [
            (
                "[proposal]
enabled = true
count = 0
",
                "proposal.count",
            ),
            (
                "[proposal]
enabled = true
accept_share = 1.5
",
                "proposal.trigger_share",
            ),
            (
                "[proposal]
enabled = true
slide_sigma_m = -0.1
",
                "proposal.slide_sigma_m",
            ),
            (
                "[proposal]
enabled = true
max_distance_m = 0.0
",
                "proposal.max_angle_rad",
            ),
            ("mode = \"paper\"\n[proposal]\nenabled = true\n", "proposal (ours only)"),
            ("[proposal]\nbogus = 1\n", "bogus"),
            ("[measurement]\nedge_contrast = [nan, 1.0]\n", "edge_contrast"),
            ("[measurement]\nedge_contrast = [75.0, -1.0]\n", "edge_contrast"),
        ] {
            let e = TrackFile::from_toml(text, x).unwrap_err().to_string();
            assert!(e.contains(key), "{text:?}: {e}");
        }
        // Off by default; the keys reach the tracker's configuration.
        let d = TrackFile::from_toml("", x).unwrap().tracker(640, 480);
        assert_eq!(d.proposal, None);
        assert_eq!(d.edge_contrast, Some(track::EdgeContrast { reference_px: 75.0, noise_factor: 2.5 }));
        let t =
            "[proposal]\nenabled = true\ncount = 32\nroll_sigma_rad = 0.1\n[measurement]\nedge_contrast = [0.0, 0.0]\n";
        let c = TrackFile::from_toml(t, x).unwrap().tracker(640, 480);
        let p = c.proposal.unwrap();
        assert_eq!((p.count, p.roll_sigma_rad), (32, 0.1));
        assert_eq!(p.accept_share, track::ProposalConfig::default().accept_share);
        assert_eq!(c.edge_contrast, None);
    }

    #[test]
    fn motion_keys_are_checked_and_applied() {
        let x = Path::new("x.toml");
        for (text, key) in [
            ("[motion]\ntime_constant_s = 0.0\n", "motion.time_constant_s"),
            ("[motion]\ntime_constant_s = nan\n", "motion.time_constant_s"),
            ("[motion]\nstationary_rad = [0.0, 0.0, -1.0, 0.0, 0.0, 0.0]\n", "motion.stationary_rad"),
            ("[motion]\nnominal_period_s = 11.0\n", "motion.nominal_period_s"),
            ("[motion]\nprior_lost_max_sigma = -1.0\n", "motion.prior_lost_max_sigma"),
            ("[motion]\nprior_lost_line_share = 1.5\n", "motion.prior_lost_line_share"),
            ("mode = \"paper\"\n[motion]\nmodel = \"offset\"\n", "motion.model"),
            ("[motion]\nrevert_to = \"nowhere\"\n", "revert_to"),
            ("[motion]\nbogus = 1\n", "bogus"),
        ] {
            let e = TrackFile::from_toml(text, x).unwrap_err().to_string();
            assert!(e.contains(key), "{text:?}: {e}");
        }
        // Defaults: ours has the offset model, the paper's mode not.
        let d = TrackFile::from_toml("", x).unwrap().tracker(640, 480);
        assert_eq!(d.offset_motion, Some(OffsetMotion::default_ours()));
        let p = TrackFile::from_toml("mode = \"paper\"\n", x).unwrap().tracker(640, 480);
        assert_eq!(p.offset_motion, None);
        let f = TrackFile::from_toml(
            "[motion]\ntime_constant_s = 2.5\nrevert_to = \"start\"\nprior_lost_line_share = -1.0\n",
            x,
        )
        .unwrap()
        .tracker(640, 480);
        let o = f.offset_motion.unwrap();
        assert_eq!((o.time_constant_s, o.revert_to, o.prior_lost), (2.5, RevertTo::Start, None));
        let j = TrackFile::from_toml("[motion]\nmodel = \"joints\"\n", x).unwrap().tracker(640, 480);
        assert_eq!(j.offset_motion, None);
    }
}
