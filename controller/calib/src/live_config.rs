//! The configuration of `comanip-calib live` on the bus (`configs/comanip-calib.toml`): TOML,
//! every key optional (the defaults match `simrobot live --camera`'s default endoscope and
//! fulcrumd's default services), unknown keys refused, checked at load with errors that name
//! the file and the key.

use std::path::{Path, PathBuf};

use estimator::calib::{Intrinsics, KinematicNoise, Setup};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use serde::Deserialize;
use sim::endoscope_arm::EndoscopeArmConfig;

/// `[bus]`: the encoder bus and how its frames are cut (fulcrumd's configuration).
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct BusSection {
    /// SocketCAN interface the passive listener opens (`can0`, `vcan0`).
    pub iface: String,
    /// fulcrumd's configuration file (its `[bus.encoder]`, `[loop] frame_deadline_us`,
    /// `[health]` and `[output]` are used); absent: fulcrumd's built-in defaults.
    pub fulcrumd_config: Option<PathBuf>,
    /// The endoscope-holder arm's nodes and encoder resolutions (`[endoscope_arm]` of
    /// `configs/simrobot.toml`; only `node_ids`, `counts_per_rev` and `insertion_counts_per_m`
    /// matter here).
    pub endoscope_arm: EndoscopeArmConfig,
}

impl Default for BusSection {
    fn default() -> Self {
        Self { iface: "can0".into(), fulcrumd_config: None, endoscope_arm: EndoscopeArmConfig::default() }
    }
}

/// `[services]`: iceoryx2 service names.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct ServicesSection {
    /// The stereo frame service (`docs/frames.md`).
    pub frames: String,
    /// fulcrumd's output; absent: the `[output] service` of `bus.fulcrumd_config`.
    pub fulcrum: Option<String>,
    /// The calibration this process publishes (`hw_io::ipc::CalibrationSample`).
    pub calibration: String,
}

impl Default for ServicesSection {
    fn default() -> Self {
        Self {
            frames: hw_io::ipc::DEFAULT_FRAME_SERVICE.into(),
            fulcrum: None,
            calibration: hw_io::ipc::DEFAULT_CALIBRATION_SERVICE.into(),
        }
    }
}

/// A pose as written in the file: metres and a unit quaternion `[w, x, y, z]`.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PoseToml {
    /// Translation, metres.
    pub translation_m: [f64; 3],
    /// Rotation, unit quaternion `[w, x, y, z]`.
    pub quaternion_wxyz: [f64; 4],
}

/// `[camera]`: the stereo endoscope (the left eye's intrinsics, the right eye a parallel copy
/// `baseline_m` along the left eye's `x`).
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct CameraSection {
    /// The left eye's intrinsics inline (pixels, plumb-bob distortion, image size)…
    pub intrinsics: Option<Intrinsics>,
    /// … or a camera YAML file (ROS/OpenCV `camera_info`, `docs/calibration.md`); not both.
    pub intrinsics_yaml: Option<PathBuf>,
    /// Distance between the two eyes' optical centres, metres.
    pub baseline_m: f64,
    /// Hand-eye `T_f_c`: the left eye in the endoscope arm's end-effector frame.
    pub hand_eye: PoseToml,
}

impl Default for CameraSection {
    /// simrobot's default stereo endoscope (`sim::endoscope::config::CameraConfig`).
    fn default() -> Self {
        let c = sim::endoscope::config::CameraConfig::default();
        Self {
            intrinsics: None,
            intrinsics_yaml: None,
            baseline_m: c.baseline_m,
            hand_eye: PoseToml { translation_m: c.hand_eye.translation_m, quaternion_wxyz: c.hand_eye.quaternion_wxyz },
        }
    }
}

/// `[tool]`.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct ToolSection {
    /// Wrist centre `P` to the instrument's tip along its axis, metres.
    pub wrist_to_tip_m: f64,
    /// How far past the tip (along the axis) the shaft detector may report the instrument:
    /// the jaws beyond a tip point at their pivot, metres (`estimator::calib::ShaftExtent`).
    /// Default: simrobot's rendered instrument, 18 mm jaws.
    pub beyond_tip_m: f64,
    /// How far back from the fulcrum (out of the patient) the endoscope can see the shaft,
    /// metres: 0 inside a patient (the abdominal wall hides it; the most information); up to
    /// the wrist for a bench or a phantom with no wall. Default: simrobot's twin, which has no
    /// wall (0.36 m, the rendered instrument's whole shaft and wrist link). Too small a value makes the calibration refuse good
    /// data; too large only gives up some information.
    pub before_fulcrum_m: f64,
    /// The shaft detector's precision of a line's end along the line, pixels (standard
    /// deviation): how far past the instrument's image a detected end may lie. Default: our
    /// detector on simrobot's frames (`comanip_calib::pixels::DETECTOR_END_SD_PX`).
    pub line_end_sd_px: f64,
}

impl Default for ToolSection {
    fn default() -> Self {
        // simrobot's rendered instrument and our detector on its frames.
        let e = crate::pixels::rendered_shaft_extent(&sim::endoscope::InstrumentGeometry::default());
        Self {
            wrist_to_tip_m: 0.3,
            beyond_tip_m: e.beyond_tip_m,
            before_fulcrum_m: e.before_point_m,
            line_end_sd_px: e.end_sd_px,
        }
    }
}

/// `[target]`: when the calibration is published.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct TargetSection {
    /// Predicted RMS translation at the mean fulcrum, millimetres.
    pub translation_mm: f64,
    /// Predicted RMS rotation, degrees.
    pub rotation_deg: f64,
}

impl Default for TargetSection {
    fn default() -> Self {
        Self { translation_mm: 1.0, rotation_deg: 0.2 }
    }
}

/// `[noise]`: the observation noise model (docs/calibration.md, "Live").
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct NoiseSection {
    /// σ of each line point, pixels.
    pub pixel_px: f64,
    /// σ per axis of the camera's and the tool line's frame rotation, milliradians.
    pub rotation_mrad: f64,
    /// σ per axis of their translation, millimetres.
    pub translation_mm: f64,
}

impl Default for NoiseSection {
    fn default() -> Self {
        Self { pixel_px: 1.2, rotation_mrad: 4.0, translation_mm: 1.2 }
    }
}

/// `[output]`.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct OutputSection {
    /// The versioned result file written at each publication (`comanip-calib-result`).
    pub result_file: PathBuf,
    /// The current state is published again this often, seconds (a subscriber started later
    /// gets it).
    pub republish_s: f64,
    /// A progress log line this often, seconds (under systemd; a terminal gets a live line).
    pub progress_every_s: f64,
    /// Arm data older than this at a frame's time are stale, milliseconds.
    pub max_age_ms: f64,
}

impl Default for OutputSection {
    fn default() -> Self {
        Self {
            result_file: PathBuf::from("calibration-live.json"),
            republish_s: 1.0,
            progress_every_s: 10.0,
            max_age_ms: 100.0,
        }
    }
}

/// `[pairing]`: how far apart the bus samples around a frame's time may be.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct PairingSection {
    /// The endoscope arm's two samples around a frame's time (it answers every 10th SYNC)
    /// are interpolated when at most this far apart, and its newest sample is held at most
    /// this long, milliseconds.
    pub endoscope_max_gap_ms: f64,
}

impl Default for PairingSection {
    fn default() -> Self {
        Self { endoscope_max_gap_ms: 25.0 }
    }
}

/// The whole file.
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct LiveConfig {
    /// `[bus]`.
    pub bus: BusSection,
    /// `[services]`.
    pub services: ServicesSection,
    /// `[camera]`.
    pub camera: CameraSection,
    /// `[tool]`.
    pub tool: ToolSection,
    /// `[target]`.
    pub target: TargetSection,
    /// `[noise]`.
    pub noise: NoiseSection,
    /// `[output]`.
    pub output: OutputSection,
    /// `[pairing]`.
    pub pairing: PairingSection,
    /// `[collection]`.
    pub collection: CollectionSection,
}

/// `[collection]`: bounds of one collection.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct CollectionSection {
    /// The most observations (eye lines) one collection keeps, 40 to 100 000: a bound on memory
    /// and on each solve's time (about 0.1 s at 729 observations); beyond, new lines are
    /// refused as `collection full` and the drift watch goes on.
    pub max_observations: usize,
}

impl Default for CollectionSection {
    fn default() -> Self {
        Self { max_observations: 2000 }
    }
}

/// Why a configuration was refused.
#[derive(Debug, thiserror::Error)]
pub enum LiveConfigError {
    /// A file cannot be read.
    #[error("{path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// Not TOML, a wrong type or an unknown key (toml's message: line, column, key).
    #[error("{path}: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// What and where.
        message: String,
    },
    /// A value out of its range.
    #[error("{path}: {key}: {problem}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// The key.
        key: &'static str,
        /// What is wrong.
        problem: String,
    },
    /// fulcrumd's configuration (`bus.fulcrumd_config`) is refused.
    #[error("bus.fulcrumd_config: {0}")]
    Fulcrumd(String),
}

/// Everything the live process needs, checked.
#[derive(Clone, Debug)]
pub struct Resolved {
    /// The file as read.
    pub file: LiveConfig,
    /// fulcrumd's configuration (encoders, deadline, health, output).
    pub fulcrumd: controller::config::Config,
    /// Camera, hand-eye, right eye and the detector's selection rule.
    pub setup: Setup,
    /// The noise model (radians, metres, pixels).
    pub noise: KinematicNoise,
    /// fulcrumd's output service.
    pub fulcrum_service: String,
}

impl LiveConfig {
    /// Parses TOML text (`path` for messages only).
    pub fn from_toml(text: &str, path: &Path) -> Result<Self, LiveConfigError> {
        toml::from_str(text).map_err(|e| LiveConfigError::Parse { path: path.to_owned(), message: e.to_string() })
    }

    /// Reads and parses a file.
    pub fn load(path: &Path) -> Result<Self, LiveConfigError> {
        let text =
            std::fs::read_to_string(path).map_err(|source| LiveConfigError::Read { path: path.to_owned(), source })?;
        Self::from_toml(&text, path)
    }

    /// Checks every value and reads the files it names (`path`: this file, for messages and
    /// relative paths).
    pub fn resolve(&self, path: &Path) -> Result<Resolved, LiveConfigError> {
        let bad = |key: &'static str, problem: String| LiveConfigError::Invalid { path: path.to_owned(), key, problem };
        if self.bus.iface.is_empty() {
            return Err(bad("bus.iface", "empty".into()));
        }
        let fulcrumd = match &self.bus.fulcrumd_config {
            Some(p) => controller::config::Config::load(&relative(path, p))
                .map_err(|e| LiveConfigError::Fulcrumd(e.to_string()))?,
            None => controller::config::Config::default(),
        };
        self.bus
            .endoscope_arm
            .validate(&fulcrumd.bus.encoder.node_ids)
            .map_err(|e| bad("bus.endoscope_arm", e.to_string()))?;
        for (key, name) in
            [("services.frames", &self.services.frames), ("services.calibration", &self.services.calibration)]
        {
            if name.is_empty() {
                return Err(bad(key, "empty".into()));
            }
        }
        let intrinsics = match (&self.camera.intrinsics, &self.camera.intrinsics_yaml) {
            (Some(_), Some(_)) => {
                return Err(bad("camera", "give either intrinsics or intrinsics_yaml, not both".into()));
            }
            (Some(k), None) => *k,
            (None, Some(p)) => {
                let p = relative(path, p);
                let text =
                    std::fs::read_to_string(&p).map_err(|source| LiveConfigError::Read { path: p.clone(), source })?;
                hw_io::calib_files::parse_intrinsics_yaml(&text)
                    .map_err(|e| bad("camera.intrinsics_yaml", format!("{}: {e}", p.display())))?
            }
            (None, None) => sim::endoscope::config::CameraConfig::default().intrinsics,
        };
        intrinsics.validate().map_err(|e| bad("camera.intrinsics", e.to_string()))?;
        let b = self.camera.baseline_m;
        if !(b.is_finite() && b > 0.0 && b < 1.0) {
            return Err(bad("camera.baseline_m", format!("{b}: must be in (0, 1) metres")));
        }
        let hand_eye = pose(&self.camera.hand_eye).ok_or_else(|| {
            bad("camera.hand_eye", "not a finite translation and a unit quaternion (|q| within 1e-6 of 1)".into())
        })?;
        let tip = self.tool.wrist_to_tip_m;
        if !(tip.is_finite() && tip > 0.0 && tip < 2.0) {
            return Err(bad("tool.wrist_to_tip_m", format!("{tip}: must be in (0, 2) metres")));
        }
        for (key, v) in
            [("tool.beyond_tip_m", self.tool.beyond_tip_m), ("tool.before_fulcrum_m", self.tool.before_fulcrum_m)]
        {
            if !(v.is_finite() && (0.0..2.0).contains(&v)) {
                return Err(bad(key, format!("{v}: must be in [0, 2) metres")));
            }
        }
        let e = self.tool.line_end_sd_px;
        if !(e.is_finite() && (0.0..1000.0).contains(&e)) {
            return Err(bad("tool.line_end_sd_px", format!("{e}: must be in [0, 1000) pixels")));
        }
        for (key, v) in
            [("target.translation_mm", self.target.translation_mm), ("target.rotation_deg", self.target.rotation_deg)]
        {
            if !(v.is_finite() && v > 0.0) {
                return Err(bad(key, format!("{v}: must be finite and > 0")));
            }
        }
        let noise = KinematicNoise {
            rot_rad: self.noise.rotation_mrad * 1e-3,
            trans_m: self.noise.translation_mm * 1e-3,
            pixel_px: self.noise.pixel_px,
        };
        if !noise.is_valid() {
            return Err(bad("noise", "each σ finite and ≥ 0, not all 0".into()));
        }
        let o = &self.output;
        for (key, v, min) in [
            ("output.republish_s", o.republish_s, 0.01),
            ("output.progress_every_s", o.progress_every_s, 0.1),
            ("output.max_age_ms", o.max_age_ms, 1.0),
            ("pairing.endoscope_max_gap_ms", self.pairing.endoscope_max_gap_ms, 1.0),
        ] {
            if !(v.is_finite() && v >= min && v <= 3600.0) {
                return Err(bad(key, format!("{v}: must be in [{min}, 3600]")));
            }
        }
        if !(40..=100_000).contains(&self.collection.max_observations) {
            return Err(bad(
                "collection.max_observations",
                format!("{}: must be in [40, 100000]", self.collection.max_observations),
            ));
        }
        if o.result_file.as_os_str().is_empty() {
            return Err(bad("output.result_file", "empty".into()));
        }
        let setup = Setup {
            intrinsics,
            hand_eye,
            right_eye: Some(Isometry3::from_parts(Translation3::new(b, 0.0, 0.0), UnitQuaternion::identity())),
            selection: crate::pixels::selection_rule(),
            shaft_extent: estimator::calib::ShaftExtent {
                beyond_tip_m: self.tool.beyond_tip_m,
                before_point_m: self.tool.before_fulcrum_m,
                end_sd_px: self.tool.line_end_sd_px,
            },
        };
        let fulcrum_service = self.services.fulcrum.clone().unwrap_or_else(|| fulcrumd.output.service.clone());
        Ok(Resolved { file: self.clone(), fulcrumd, setup, noise, fulcrum_service })
    }
}

fn relative(config: &Path, p: &Path) -> PathBuf {
    match config.parent() {
        Some(dir) if p.is_relative() => dir.join(p),
        _ => p.to_owned(),
    }
}

fn pose(p: &PoseToml) -> Option<Isometry3<f64>> {
    let [w, x, y, z] = p.quaternion_wxyz;
    let q = Quaternion::new(w, x, y, z);
    let all = p.translation_m.iter().chain(&p.quaternion_wxyz);
    if !all.clone().all(|v| v.is_finite()) || (q.norm() - 1.0).abs() > 1e-6 {
        return None;
    }
    Some(Isometry3::from_parts(Translation3::from(Vector3::from(p.translation_m)), UnitQuaternion::from_quaternion(q)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn resolve(text: &str) -> Result<Resolved, LiveConfigError> {
        let p = Path::new("t.toml");
        LiveConfig::from_toml(text, p)?.resolve(p)
    }

    #[test]
    fn the_shipped_file_and_the_defaults_resolve_alike() {
        let shipped =
            std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/comanip-calib.toml")).unwrap();
        let cfg = LiveConfig::from_toml(&shipped, Path::new("comanip-calib.toml")).unwrap();
        let r = cfg.resolve(Path::new("comanip-calib.toml")).unwrap();
        let d = resolve("").unwrap();
        assert_eq!(r.setup.intrinsics, d.setup.intrinsics);
        assert_eq!(r.setup.hand_eye, d.setup.hand_eye);
        assert_eq!(r.noise, d.noise);
        assert_eq!(r.fulcrum_service, "comanip/fulcrum");
        assert_eq!(cfg.bus.iface, "can0");
    }

    #[test]
    fn bad_values_name_their_key() {
        for (text, key) in [
            ("[bus]\niface = \"\"\n", "bus.iface"),
            ("[camera]\nbaseline_m = -1.0\n", "camera.baseline_m"),
            (
                "[camera.hand_eye]\ntranslation_m = [0.0, 0.0, 0.0]\nquaternion_wxyz = [2.0, 0.0, 0.0, 0.0]\n",
                "camera.hand_eye",
            ),
            ("[tool]\nwrist_to_tip_m = nan\n", "tool.wrist_to_tip_m"),
            ("[tool]\nbeyond_tip_m = -0.001\n", "tool.beyond_tip_m"),
            ("[tool]\nbefore_fulcrum_m = inf\n", "tool.before_fulcrum_m"),
            ("[tool]\nline_end_sd_px = -1.0\n", "tool.line_end_sd_px"),
            ("[target]\ntranslation_mm = 0.0\n", "target.translation_mm"),
            ("[noise]\npixel_px = 0.0\nrotation_mrad = 0.0\ntranslation_mm = 0.0\n", "noise"),
            ("[output]\nrepublish_s = 0.0\n", "output.republish_s"),
            ("[pairing]\nendoscope_max_gap_ms = 0.5\n", "pairing.endoscope_max_gap_ms"),
            ("[collection]\nmax_observations = 10\n", "collection.max_observations"),
            (
                "[camera]\nintrinsics_yaml = \"x.yaml\"\n[camera.intrinsics]\nfx = 1.0\nfy = 1.0\ncx = 1.0\ncy = 1.0\nwidth = 4\nheight = 4\n",
                "camera",
            ),
            (
                "[camera.intrinsics]\nfx = -1.0\nfy = 1.0\ncx = 1.0\ncy = 1.0\nwidth = 4\nheight = 4\n",
                "camera.intrinsics",
            ),
            ("[bus.endoscope_arm]\nnode_ids = [1, 5]\n", "bus.endoscope_arm"),
        ] {
            match resolve(text) {
                Err(LiveConfigError::Invalid { key: k, .. }) => assert_eq!(k, key, "{text}"),
                other => panic!("{text}: {other:?}"),
            }
        }
    }

    #[test]
    fn unknown_keys_and_wrong_types_are_parse_errors_with_the_key() {
        for (text, needle) in
            [("[target]\nprecision = 1.0\n", "precision"), ("[tool]\nwrist_to_tip_m = \"a\"\n", "wrist_to_tip_m")]
        {
            match resolve(text) {
                Err(LiveConfigError::Parse { message, .. }) => assert!(message.contains(needle), "{message}"),
                other => panic!("{text}: {other:?}"),
            }
        }
        assert!(matches!(
            LiveConfig::load(Path::new("/nonexistent/comanip-calib.toml")),
            Err(LiveConfigError::Read { .. })
        ));
        assert!(matches!(
            resolve("[bus]\nfulcrumd_config = \"/nonexistent/fulcrumd.toml\"\n"),
            Err(LiveConfigError::Fulcrumd(_))
        ));
    }
}
