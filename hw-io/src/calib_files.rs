//! Files of the dual RCM-arm calibration (`docs/calibration.md`): camera intrinsics from
//! OpenCV FileStorage YAML or ROS `camera_info` YAML, the dataset file, the ground-truth file
//! of a simulated dataset and the result file (all three JSON, versioned).
//!
//! Units: metres, radians, pixels. Quaternions are `[w, x, y, z]`. Transforms are `T_e_t`
//! (robot 2's RCM frame in robot 1's RCM frame) unless named otherwise.

use serde::{Deserialize, Serialize};

/// Pinhole intrinsics (pixels) with plumb-bob distortion, as read from a file: the
/// estimator's own type, so that no field is copied across.
pub use estimator::calib::Eye;
pub use estimator::calib::Intrinsics as CameraIntrinsics;
/// The line detector's acceptance rule in a dataset: the estimator's own type.
pub use estimator::calib::{SelectionRule, ShaftExtent};

/// Why an intrinsics YAML file was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum IntrinsicsFileError {
    /// Not YAML.
    #[error("intrinsics YAML, line {line}, column {column}: {message}")]
    Yaml {
        /// 1-based line.
        line: usize,
        /// 1-based column.
        column: usize,
        /// The parser's message.
        message: String,
    },
    /// A required field is missing (named as in the file).
    #[error(
        "intrinsics YAML: missing field `{0}` (OpenCV: camera_matrix / image_width / image_height; ROS: camera_matrix or K, image_width or width, ...)"
    )]
    Missing(&'static str),
    /// A field has the wrong type, size or value.
    #[error("intrinsics YAML: field `{field}`: {problem}")]
    Field {
        /// The field's name.
        field: &'static str,
        /// What is wrong.
        problem: String,
    },
}

fn first<'a>(map: &'a serde_yaml_ng::Value, keys: &[&'static str]) -> Option<(&'static str, &'a serde_yaml_ng::Value)> {
    keys.iter().find_map(|k| map.get(*k).map(|v| (*k, v)))
}

fn numbers(field: &'static str, v: &serde_yaml_ng::Value) -> Result<Vec<f64>, IntrinsicsFileError> {
    // Either a plain sequence (ROS CameraInfo `K: [..]`) or a matrix mapping with `data`
    // (OpenCV `!!opencv-matrix`, ROS camera_calibration `{rows, cols, data}`).
    let seq = match v {
        serde_yaml_ng::Value::Sequence(s) => s,
        serde_yaml_ng::Value::Mapping(_) => match v.get("data") {
            Some(serde_yaml_ng::Value::Sequence(s)) => s,
            _ => return Err(IntrinsicsFileError::Field { field, problem: "matrix without a `data` list".into() }),
        },
        _ => return Err(IntrinsicsFileError::Field { field, problem: "expected a list or a matrix".into() }),
    };
    seq.iter()
        .enumerate()
        .map(|(i, x)| match x.as_f64() {
            Some(f) if f.is_finite() => Ok(f),
            _ => Err(IntrinsicsFileError::Field { field, problem: format!("element {i} is not a finite number") }),
        })
        .collect()
}

fn size(map: &serde_yaml_ng::Value, keys: &[&'static str]) -> Result<u32, IntrinsicsFileError> {
    let (k, v) = first(map, keys).ok_or(IntrinsicsFileError::Missing(keys[0]))?;
    v.as_u64()
        .filter(|n| *n > 0 && *n <= u32::MAX as u64)
        .map(|n| n as u32)
        .ok_or(IntrinsicsFileError::Field { field: k, problem: "expected a positive integer".into() })
}

/// Parses camera intrinsics from OpenCV FileStorage YAML (`%YAML:1.0` header,
/// `!!opencv-matrix` tags; keys `camera_matrix`/`cameraMatrix`/`K`,
/// `distortion_coefficients`/`dist_coeffs`/`distCoeffs`/`D`), ROS camera_calibration YAML
/// (`camera_matrix: {rows, cols, data}`, `distortion_model`) or a ROS `CameraInfo` message
/// (`width`, `height`, `K`/`k`, `D`/`d`).
pub fn parse_intrinsics_yaml(text: &str) -> Result<CameraIntrinsics, IntrinsicsFileError> {
    // OpenCV writes a non-standard directive (`%YAML:1.0`) and a custom tag: drop both,
    // keeping line numbers (the directive line becomes a comment).
    let cleaned: String = text
        .lines()
        .map(|l| if l.trim_start().starts_with("%YAML") { "#".to_string() } else { l.replace("!!opencv-matrix", "") })
        .collect::<Vec<_>>()
        .join("\n");
    let doc: serde_yaml_ng::Value = serde_yaml_ng::from_str(&cleaned).map_err(|e| {
        let (line, column) = e.location().map(|l| (l.line(), l.column())).unwrap_or((0, 0));
        IntrinsicsFileError::Yaml { line, column, message: e.to_string() }
    })?;
    if !doc.is_mapping() {
        return Err(IntrinsicsFileError::Yaml {
            line: 1,
            column: 1,
            message: "expected a mapping at the top level".into(),
        });
    }
    let (kf, kv) = first(&doc, &["camera_matrix", "cameraMatrix", "K", "k"])
        .ok_or(IntrinsicsFileError::Missing("camera_matrix"))?;
    let k = numbers(kf, kv)?;
    if k.len() != 9 {
        return Err(IntrinsicsFileError::Field {
            field: kf,
            problem: format!("expected 9 numbers (3x3, row-major), got {}", k.len()),
        });
    }
    if k[3] != 0.0 || k[6] != 0.0 || k[7] != 0.0 || k[8] != 1.0 {
        return Err(IntrinsicsFileError::Field {
            field: kf,
            problem: "not a camera matrix (last row must be 0 0 1, K[1][0] = 0)".into(),
        });
    }
    if !(k[0] > 0.0 && k[4] > 0.0) {
        return Err(IntrinsicsFileError::Field { field: kf, problem: "focal lengths must be positive".into() });
    }
    if let Some((f, m)) = first(&doc, &["distortion_model"]) {
        match m.as_str() {
            Some("plumb_bob") | Some("rational_polynomial") | Some("") | None => {}
            Some(other) => {
                return Err(IntrinsicsFileError::Field {
                    field: f,
                    problem: format!("unsupported distortion model `{other}` (plumb_bob only)"),
                });
            }
        }
    }
    let mut distortion = [0.0; 5];
    if let Some((df, dv)) = first(&doc, &["distortion_coefficients", "dist_coeffs", "distCoeffs", "D", "d"]) {
        let d = numbers(df, dv)?;
        if d.len() > 5 && d[5..].iter().any(|x| *x != 0.0) {
            return Err(IntrinsicsFileError::Field {
                field: df,
                problem: format!(
                    "{} coefficients with non-zero rational terms; only plumb-bob k1 k2 p1 p2 k3 is supported",
                    d.len()
                ),
            });
        }
        if !d.is_empty() && d.len() < 4 {
            return Err(IntrinsicsFileError::Field {
                field: df,
                problem: format!("expected 4 or 5 coefficients, got {}", d.len()),
            });
        }
        for (o, v) in distortion.iter_mut().zip(d.iter()) {
            *o = *v;
        }
    }
    Ok(CameraIntrinsics {
        fx: k[0],
        skew: k[1],
        cx: k[2],
        fy: k[4],
        cy: k[5],
        width: size(&doc, &["image_width", "width"])?,
        height: size(&doc, &["image_height", "height"])?,
        distortion,
    })
}

/// A rigid transform in a file: translation (metres) and unit quaternion `[w, x, y, z]`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransformJson {
    /// Translation, metres.
    pub translation_m: [f64; 3],
    /// Rotation as a unit quaternion `[w, x, y, z]`.
    pub quaternion_wxyz: [f64; 4],
}

/// The kinematic noise model in a dataset (see `estimator::calib::KinematicNoise`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoiseJson {
    /// σ of each rotation component of a frame perturbation, radians.
    pub rot_rad: f64,
    /// σ of each translation component of a frame perturbation, metres.
    pub trans_m: f64,
    /// σ of each line-point coordinate, pixels.
    pub pixel_px: f64,
}

/// One observation in a dataset file.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObservationJson {
    /// Robot 1 (ECM-like): `[yaw rad, pitch rad, insertion m, roll rad]`.
    pub ecm_joints: [f64; 4],
    /// Robot 2 (PSM-like): `[yaw rad, pitch rad, insertion m]`; for an arm without a
    /// mechanical RCM, the tool line's direction written as those joints about
    /// `tool_point_m` (the tip `insertion` metres from it).
    pub psm_joints: [f64; 3],
    /// The known point of the tool's line in `{t}`, metres: omitted (the origin, robot 2's
    /// RCM) for an RCM arm; the fulcrum for an arm without a mechanical RCM (issue 19).
    #[serde(default, skip_serializing_if = "is_origin")]
    pub tool_point_m: [f64; 3],
    /// Two distinct points of the tool centreline in the image, pixels `[[u, v], [u, v]]`.
    pub line_px: [[f64; 2]; 2],
    /// The eye that saw the line, `"left"` (default, omitted) or `"right"` (needs the
    /// dataset's `right_eye`).
    #[serde(default, skip_serializing_if = "is_left")]
    pub eye: Eye,
}

fn is_origin(p: &[f64; 3]) -> bool {
    *p == [0.0; 3]
}

fn is_left(e: &Eye) -> bool {
    *e == Eye::Left
}

/// The dataset file's `format` value.
pub const DATASET_FORMAT: &str = "comanip-calib-dataset";
/// The truth file's `format` value.
pub const TRUTH_FORMAT: &str = "comanip-calib-truth";
/// The result file's `format` value.
pub const RESULT_FORMAT: &str = "comanip-calib-result";
/// The version written and the only one read, for all three files.
pub const CALIB_FILE_VERSION: u32 = 1;

/// The dataset file (JSON): everything the calibration needs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetFile {
    /// Always [`DATASET_FORMAT`].
    pub format: String,
    /// Always [`CALIB_FILE_VERSION`].
    pub version: u32,
    /// Camera intrinsics, pixels.
    pub intrinsics: CameraIntrinsics,
    /// Hand-eye `T_f_c`: camera frame in robot 1's end-effector frame.
    pub hand_eye: TransformJson,
    /// `T_c_r`: a stereo endoscope's right eye in the left eye's camera frame `{c}` (metres;
    /// same intrinsics); absent for a single camera.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub right_eye: Option<TransformJson>,
    /// Optional kinematic noise model (weights our pipeline).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_model: Option<NoiseJson>,
    /// Legacy (version-1 files before `selection`): the tip in the image and at least this much
    /// shaft (pixels) visible from it, i.e. `selection` with `require_tip_in_view: true`. Read,
    /// never written; refused together with `selection`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub min_shaft_px: Option<f64>,
    /// The line detector's acceptance rule, which our pipeline models (see
    /// `estimator::calib::SelectionRule`); absent: `min_shaft_px`'s rule if given, else the
    /// default rule (visible shaft only, tip not required).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub selection: Option<SelectionRule>,
    /// Where along the instrument the camera can see it (`estimator::calib::ShaftExtent`,
    /// metres); absent: the default (from robot 2's RCM to the tool tip, as inside a patient).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shaft_extent: Option<ShaftExtent>,
    /// The observations.
    pub observations: Vec<ObservationJson>,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// Ground truth of a simulated dataset (JSON).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TruthFile {
    /// Always [`TRUTH_FORMAT`].
    pub format: String,
    /// Always [`CALIB_FILE_VERSION`].
    pub version: u32,
    /// The true `T_e_t`.
    pub truth: TransformJson,
    /// Protocol: values per ECM joint.
    pub n_e: usize,
    /// Protocol: values per PSM joint.
    pub n_t: usize,
    /// Protocol: noise σ (dimensionless).
    pub sigma: f64,
    /// Protocol: unit of the noise's translation part, `"mm"` or `"m"`.
    pub units: String,
    /// Protocol: pixel noise σ, pixels.
    pub pixel_sigma_px: f64,
    /// Protocol: seed.
    pub seed: u64,
    /// Joint combinations tried.
    pub generated: usize,
    /// Combinations dropped because the tool was not in view.
    pub dropped: usize,
    /// Combinations not generated because the tool would pass through the endoscope (the
    /// scene's instrument bodies); absent when none was.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub collided: usize,
    /// Observations (0-based, dataset order) whose line was replaced by a wrong one (a
    /// simulated detector error); absent when none was.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub wrong_lines: Vec<usize>,
}

/// Residual statistics in a result file (pixels).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ResidualJson {
    /// Observations used.
    pub count: usize,
    /// RMS point-to-line distance, pixels.
    pub rms_px: f64,
    /// Median point-to-line distance, pixels.
    pub median_px: f64,
    /// Largest point-to-line distance, pixels.
    pub max_px: f64,
    /// Observations with full weight (inside the Huber threshold).
    pub inliers: usize,
}

/// One pipeline's result in a result file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PipelineResultJson {
    /// `"paper"` or `"ours"`.
    pub pipeline: String,
    /// `T_e_t` as a row-major 4×4 homogeneous matrix (metres).
    pub transform: [[f64; 4]; 4],
    /// Rotation of `T_e_t`, `[w, x, y, z]`.
    pub quaternion_wxyz: [f64; 4],
    /// Translation of `T_e_t` (robot 2's RCM in robot 1's RCM frame), metres.
    pub translation_m: [f64; 3],
    /// Point-to-line residuals, pixels.
    pub residuals: ResidualJson,
    /// Covariance of `(tx, ty, tz m, φx, φy, φz rad)` (left rotation increment in robot 1's
    /// RCM frame), row-major 6×6; `null` for the paper pipeline.
    pub covariance: Option<[[f64; 6]; 6]>,
    /// Legacy (before `log_likelihood_ratio`): cost ratio of the mirrored candidate. Read,
    /// never written.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ambiguity_ratio: Option<f64>,
    /// Ours: negative log-likelihood of the runner-up (typically the mirror) minus the
    /// result's (natural log, finite, ≥ 0; large = unambiguous).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub log_likelihood_ratio: Option<f64>,
    /// Solve time, milliseconds.
    pub solve_ms: f64,
    /// Ours with a noise model: what its selection-aware stage did (absent otherwise).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub selection_stage: Option<SelectionStageJson>,
    /// Ours when asked to estimate the noise model's scale: the factor its standard
    /// deviations were multiplied by (dimensionless; absent when taken as stated).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_scale: Option<f64>,
    /// Ours: how many observations its candidates were searched on (all of them, or a
    /// subsample when the dataset is large; the result itself is refined and judged on all).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub searched_on: Option<usize>,
    /// Ours: `true` when the answer comes from a search from a cover of rotation space: under
    /// the default, every solve with a noise model and a linear start; with a poor-fit
    /// trigger, when the first search's answer fitted the data worse than the noise model
    /// predicts (`docs/calibration.md`, "Our pipeline").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cover_searched: Option<bool>,
}

/// Our pipeline's selection-aware stage in a result file (`docs/calibration.md`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SelectionStageJson {
    /// True when its pose is the result; false when it was refused (see `refused`) and the
    /// result is the border-guarded robust fit.
    pub applied: bool,
    /// Observations fitted with their selection.
    pub selected: usize,
    /// Observations fitted as plain lines.
    pub plain: usize,
    /// Observations left out.
    pub left_out: usize,
    /// How far the stage moved from the robust fit, standard deviations.
    pub shift_sigmas: f64,
    /// Why it was refused, when it was.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refused: Option<String>,
    /// The move test's statistic (dimensionless, χ² when the stage and the robust fit are
    /// consistent); absent when it was not computed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub move_statistic: Option<f64>,
    /// The move test's refusal limit (the χ² quantile at one minus the false-refusal
    /// probability); absent with `move_statistic`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub move_limit: Option<f64>,
    /// The move failed the test (`move_statistic` above `move_limit`) and the stage was
    /// applied because its pose is far more likely than the guarded fit's on all
    /// observations (the likelihood override, `docs/calibration.md`); absent when false.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub accepted_on_likelihood: bool,
}

/// The result file (JSON).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ResultFile {
    /// Always [`RESULT_FORMAT`].
    pub format: String,
    /// Always [`CALIB_FILE_VERSION`].
    pub version: u32,
    /// One entry per pipeline that produced a pose (a pipeline listed in `failures` too
    /// produced only an unrefined estimate the user did not accept).
    pub results: Vec<PipelineResultJson>,
    /// One entry per requested pipeline that failed (absent when none did).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub failures: Vec<PipelineFailureJson>,
}

/// A pipeline's failure in a result file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PipelineFailureJson {
    /// `"paper"` or `"ours"`.
    pub pipeline: String,
    /// A stable name of the failure (e.g. `ambiguous`, `degenerate`, `selection_refused`).
    pub kind: String,
    /// The error message.
    pub error: String,
}

/// Why a calibration JSON file (dataset, truth, result) was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibFileError {
    /// Not valid JSON, or a field of the wrong type / unknown / missing.
    #[error("line {line}, column {column}: {message}")]
    Json {
        /// 1-based line.
        line: usize,
        /// 1-based column.
        column: usize,
        /// serde_json's message (names the field).
        message: String,
    },
    /// The `format` field is not the expected one.
    #[error("field `format`: expected \"{expected}\", found \"{found}\"")]
    Format {
        /// Expected value.
        expected: &'static str,
        /// Found value.
        found: String,
    },
    /// Unsupported `version`.
    #[error("field `version`: version {found} is not supported (this build reads {supported})")]
    Version {
        /// Found.
        found: u32,
        /// Supported.
        supported: u32,
    },
    /// A value is out of range (field path and problem).
    #[error("field `{field}`: {problem}")]
    Field {
        /// Field path, e.g. `observations[3].line_px`.
        field: String,
        /// What is wrong.
        problem: String,
    },
}

fn json<T: for<'de> Deserialize<'de>>(text: &str) -> Result<T, CalibFileError> {
    serde_json::from_str(text).map_err(|e| CalibFileError::Json {
        line: e.line(),
        column: e.column(),
        message: e.to_string(),
    })
}

fn check_header(format: &str, version: u32, expected: &'static str) -> Result<(), CalibFileError> {
    if format != expected {
        return Err(CalibFileError::Format { expected, found: format.into() });
    }
    if version != CALIB_FILE_VERSION {
        return Err(CalibFileError::Version { found: version, supported: CALIB_FILE_VERSION });
    }
    Ok(())
}

fn finite(field: impl Fn() -> String, v: &[f64]) -> Result<(), CalibFileError> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(CalibFileError::Field { field: field(), problem: "values must be finite numbers".into() })
    }
}

fn check_transform(name: &str, t: &TransformJson) -> Result<(), CalibFileError> {
    finite(|| format!("{name}.translation_m"), &t.translation_m)?;
    finite(|| format!("{name}.quaternion_wxyz"), &t.quaternion_wxyz)?;
    let n = t.quaternion_wxyz.iter().map(|x| x * x).sum::<f64>().sqrt();
    if (n - 1.0).abs() > 1e-6 {
        return Err(CalibFileError::Field {
            field: format!("{name}.quaternion_wxyz"),
            problem: format!("not a unit quaternion (norm {n})"),
        });
    }
    Ok(())
}

/// Parses and validates a dataset file: header, intrinsics, hand-eye, noise model, and
/// every observation (finite values, distinct line points); errors name the field path.
pub fn parse_dataset(text: &str) -> Result<DatasetFile, CalibFileError> {
    let d: DatasetFile = json(text)?;
    check_header(&d.format, d.version, DATASET_FORMAT)?;
    let k = &d.intrinsics;
    finite(|| "intrinsics".into(), &[k.fx, k.fy, k.cx, k.cy, k.skew])?;
    finite(|| "intrinsics.distortion".into(), &k.distortion)?;
    if !(k.fx > 0.0 && k.fy > 0.0) {
        return Err(CalibFileError::Field {
            field: "intrinsics.fx/fy".into(),
            problem: "focal lengths must be positive".into(),
        });
    }
    if k.width == 0 || k.height == 0 {
        return Err(CalibFileError::Field {
            field: "intrinsics.width/height".into(),
            problem: "image size must be positive".into(),
        });
    }
    check_transform("hand_eye", &d.hand_eye)?;
    if let Some(r) = &d.right_eye {
        check_transform("right_eye", r)?;
    } else if let Some(i) = d.observations.iter().position(|o| o.eye == Eye::Right) {
        return Err(CalibFileError::Field {
            field: format!("observations[{i}].eye"),
            problem: "\"right\" needs the dataset's right_eye transform".into(),
        });
    }
    d.selection_rule()?;
    if let Some(e) = d.shaft_extent.filter(|e| !e.is_valid()) {
        return Err(CalibFileError::Field {
            field: "shaft_extent".into(),
            problem: format!(
                "beyond_tip_m, before_point_m (metres) and end_sd_px (pixels) must be finite and ≥ 0 (got {}, {}, {})",
                e.beyond_tip_m, e.before_point_m, e.end_sd_px
            ),
        });
    }
    if let Some(n) = &d.noise_model {
        let v = [n.rot_rad, n.trans_m, n.pixel_px];
        if !v.iter().all(|x| x.is_finite() && *x >= 0.0) || v.iter().all(|x| *x == 0.0) {
            return Err(CalibFileError::Field {
                field: "noise_model".into(),
                problem: "standard deviations must be finite, ≥ 0 and not all zero".into(),
            });
        }
    }
    if d.observations.is_empty() {
        return Err(CalibFileError::Field { field: "observations".into(), problem: "no observations".into() });
    }
    for (i, o) in d.observations.iter().enumerate() {
        finite(|| format!("observations[{i}].ecm_joints"), &o.ecm_joints)?;
        finite(|| format!("observations[{i}].psm_joints"), &o.psm_joints)?;
        finite(|| format!("observations[{i}].tool_point_m"), &o.tool_point_m)?;
        let p = [o.line_px[0][0], o.line_px[0][1], o.line_px[1][0], o.line_px[1][1]];
        finite(|| format!("observations[{i}].line_px"), &p)?;
        if (p[0] - p[2]).hypot(p[1] - p[3]) < 1e-6 {
            return Err(CalibFileError::Field {
                field: format!("observations[{i}].line_px"),
                problem: "the two line points coincide".into(),
            });
        }
    }
    Ok(d)
}

/// The shaft-lines file's `format` value (`comanip-calib detect`).
pub const LINES_FORMAT: &str = "comanip-shaft-lines";
/// The shaft-lines file's version (the calibration files' [`CALIB_FILE_VERSION`]).
pub const LINES_VERSION: u32 = CALIB_FILE_VERSION;

/// One detected shaft in a lines file. Lines `[a, b, c]` (`a·u + b·v + c = 0`, `a² + b² = 1`)
/// are in **undistorted** pixels of the file's camera; `ends_px` are measured (distorted)
/// pixels.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ShaftJson {
    /// The centreline (the projected axis, or the middle line for the paper's detector).
    pub centreline: [f64; 3],
    /// The two contour lines.
    pub contours: [[f64; 3]; 2],
    /// Two points on the centreline spanning the visible shaft, measured pixels
    /// (a calibration observation's `line_px`).
    pub ends_px: [[f64; 2]; 2],
    /// The detector's confidence, 0..=1.
    pub confidence: f64,
}

/// One image of a lines file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageLinesJson {
    /// The image file's name (relative to the images directory).
    pub file: String,
    /// The shafts found, best first (empty: none).
    pub shafts: Vec<ShaftJson>,
    /// Why the image was not examined (unreadable, wrong size), when it was not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Detection time, milliseconds (0 when not examined).
    pub detect_ms: f64,
}

/// The lines file of `comanip-calib detect` (JSON).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LinesFile {
    /// Always [`LINES_FORMAT`].
    pub format: String,
    /// Always [`LINES_VERSION`].
    pub version: u32,
    /// The detector (`ours`, `paper`).
    pub detector: String,
    /// The camera the lines are expressed in, pixels.
    pub intrinsics: CameraIntrinsics,
    /// Every image, in order.
    pub images: Vec<ImageLinesJson>,
}

/// Parses a lines file (header checked).
pub fn parse_lines(text: &str) -> Result<LinesFile, CalibFileError> {
    let l: LinesFile = json(text)?;
    check_header(&l.format, l.version, LINES_FORMAT)?;
    Ok(l)
}

impl DatasetFile {
    /// The dataset's selection rule: `selection`, else the legacy `min_shaft_px` (tip in view),
    /// else the default; refused when both are given or a length is negative or not finite.
    pub fn selection_rule(&self) -> Result<SelectionRule, CalibFileError> {
        let rule = match (self.selection, self.min_shaft_px) {
            (Some(_), Some(_)) => {
                return Err(CalibFileError::Field {
                    field: "min_shaft_px".into(),
                    problem: "give either `selection` or the legacy `min_shaft_px`, not both".into(),
                });
            }
            (Some(r), None) => r,
            (None, Some(px)) => SelectionRule::tip_in_view(px),
            (None, None) => SelectionRule::default(),
        };
        if !rule.is_valid() {
            return Err(CalibFileError::Field {
                field: if self.selection.is_some() { "selection".into() } else { "min_shaft_px".into() },
                problem: "lengths must be finite and ≥ 0".into(),
            });
        }
        Ok(rule)
    }
}

/// Parses a truth file.
pub fn parse_truth(text: &str) -> Result<TruthFile, CalibFileError> {
    let t: TruthFile = json(text)?;
    check_header(&t.format, t.version, TRUTH_FORMAT)?;
    check_transform("truth", &t.truth)?;
    Ok(t)
}

/// Parses a result file.
pub fn parse_result(text: &str) -> Result<ResultFile, CalibFileError> {
    let r: ResultFile = json(text)?;
    check_header(&r.format, r.version, RESULT_FORMAT)?;
    Ok(r)
}

/// Serialises any of the three files as pretty JSON (bit-exact round trip of every f64).
pub fn to_json<T: Serialize>(value: &T) -> String {
    // Serialising these plain structs cannot fail (no maps with non-string keys).
    serde_json::to_string_pretty(value).unwrap_or_default()
}

/// A calibrated stereo rig: each eye's intrinsics and the right eye's pose relative to the left.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StereoCalibration {
    /// The left eye (pixels).
    pub left: CameraIntrinsics,
    /// The right eye (pixels).
    pub right: CameraIntrinsics,
    /// Rotation taking a vector from the left eye's camera frame to the right eye's, row-major.
    pub rotation_right_left: [[f64; 3]; 3],
    /// The left eye's optical centre in the right eye's camera frame, metres: a point `X_l` (left
    /// camera frame) is `R·X_l + t` in the right camera frame.
    pub translation_right_left_m: [f64; 3],
}

impl StereoCalibration {
    /// The baseline (distance between the optical centres), metres.
    pub fn baseline_m(&self) -> f64 {
        let t = self.translation_right_left_m;
        (t[0] * t[0] + t[1] * t[1] + t[2] * t[2]).sqrt()
    }
}

/// Why a pair of ROS `camera_info` files was refused as a stereo calibration.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StereoFileError {
    /// One eye's intrinsics.
    #[error("{eye} camera_info: {source}")]
    Intrinsics {
        /// `left` or `right`.
        eye: &'static str,
        /// The reason.
        source: IntrinsicsFileError,
    },
    /// A matrix (R, P) missing or malformed.
    #[error("{eye} camera_info: field `{field}`: {problem}")]
    Field {
        /// `left` or `right`.
        eye: &'static str,
        /// The field.
        field: &'static str,
        /// What is wrong.
        problem: String,
    },
}

/// Parses a stereo calibration from the left and right eyes' ROS `camera_info` YAML (as written
/// by ROS `camera_calibration` or a `CameraInfo` message): `K`/`D` of each eye, and the
/// rectification `R` and projection `P` that tie them together (ROS convention: the right
/// eye's `P[0][3] = Tx = −fx'·B` with `B` the baseline in metres, the rectified frames share
/// their orientation). The right-from-left transform is `R_r^T·R_l` and `−R_r^T·(B, 0, 0)`.
pub fn parse_stereo_camera_info(left: &str, right: &str) -> Result<StereoCalibration, StereoFileError> {
    let parse = |eye: &'static str, text: &str| -> Result<(CameraIntrinsics, [f64; 9], [f64; 12]), StereoFileError> {
        let intrinsics = parse_intrinsics_yaml(text).map_err(|source| StereoFileError::Intrinsics { eye, source })?;
        let cleaned: String =
            text.lines()
                .map(|l| {
                    if l.trim_start().starts_with("%YAML") { "#".to_string() } else { l.replace("!!opencv-matrix", "") }
                })
                .collect::<Vec<_>>()
                .join("\n");
        let doc: serde_yaml_ng::Value = serde_yaml_ng::from_str(&cleaned).map_err(|e| StereoFileError::Intrinsics {
            eye,
            source: IntrinsicsFileError::Yaml { line: 0, column: 0, message: e.to_string() },
        })?;
        let matrix = |keys: &[&'static str], n: usize| -> Result<Vec<f64>, StereoFileError> {
            let (field, v) = first(&doc, keys).ok_or(StereoFileError::Field {
                eye,
                field: keys[0],
                problem: "missing (a stereo camera_info carries R and P)".into(),
            })?;
            let x = numbers(field, v).map_err(|source| StereoFileError::Intrinsics { eye, source })?;
            if x.len() != n {
                return Err(StereoFileError::Field {
                    eye,
                    field,
                    problem: format!("expected {n} numbers, got {}", x.len()),
                });
            }
            Ok(x)
        };
        let r = matrix(&["rectification_matrix", "R", "r"], 9)?;
        let p = matrix(&["projection_matrix", "P", "p"], 12)?;
        let mut r9 = [0.0; 9];
        r9.copy_from_slice(&r);
        let mut p12 = [0.0; 12];
        p12.copy_from_slice(&p);
        // R must be a rotation (orthonormal, det +1) to 1e-6.
        let rt_r_err = (0..3)
            .flat_map(|i| (0..3).map(move |j| (i, j)))
            .map(|(i, j)| {
                let dot: f64 = (0..3).map(|k| r9[3 * k + i] * r9[3 * k + j]).sum();
                (dot - if i == j { 1.0 } else { 0.0 }).abs()
            })
            .fold(0.0, f64::max);
        let det = r9[0] * (r9[4] * r9[8] - r9[5] * r9[7]) - r9[1] * (r9[3] * r9[8] - r9[5] * r9[6])
            + r9[2] * (r9[3] * r9[7] - r9[4] * r9[6]);
        if rt_r_err > 1e-6 || (det - 1.0).abs() > 1e-6 {
            return Err(StereoFileError::Field { eye, field: "R", problem: "not a rotation matrix".into() });
        }
        if p12[0] <= 0.0 {
            return Err(StereoFileError::Field { eye, field: "P", problem: "P[0][0] (fx') must be positive".into() });
        }
        Ok((intrinsics, r9, p12))
    };
    let (left_k, r_l, p_l) = parse("left", left)?;
    let (right_k, r_r, p_r) = parse("right", right)?;
    if p_l[3] != 0.0 {
        return Err(StereoFileError::Field {
            eye: "left",
            field: "P",
            problem: "the left eye's P[0][3] must be 0 (it is the reference)".into(),
        });
    }
    let baseline_m = -p_r[3] / p_r[0];
    if !(baseline_m.is_finite() && baseline_m > 0.0) {
        return Err(StereoFileError::Field {
            eye: "right",
            field: "P",
            problem: format!("P[0][3] = {} gives no positive baseline (expected −fx'·B < 0)", p_r[3]),
        });
    }
    // R_r^T · R_l and −R_r^T · (B, 0, 0).
    let mut rotation = [[0.0; 3]; 3];
    for (i, row) in rotation.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|k| r_r[3 * k + i] * r_l[3 * k + j]).sum();
        }
    }
    let translation = [-r_r[0] * baseline_m, -r_r[1] * baseline_m, -r_r[2] * baseline_m];
    Ok(StereoCalibration {
        left: left_k,
        right: right_k,
        rotation_right_left: rotation,
        translation_right_left_m: translation,
    })
}

/// A ROS `camera_info` YAML (`camera_calibration`'s format) of one eye of an ideal stereo rig
/// whose eyes share their orientation and are `baseline_m` metres apart along x: `R` is the
/// identity and the right eye's `P[0][3] = −fx·B`. What `simrobot` writes for its simulated
/// endoscope; [`parse_stereo_camera_info`] reads it back.
pub fn write_camera_info_yaml(name: &str, k: &CameraIntrinsics, right_eye_baseline_m: Option<f64>) -> String {
    let tx = right_eye_baseline_m.map_or(0.0, |b| -k.fx * b);
    let d = k.distortion;
    format!(
        "image_width: {w}\nimage_height: {h}\ncamera_name: {name}\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: [{fx:?}, {s:?}, {cx:?}, 0.0, {fy:?}, {cy:?}, 0.0, 0.0, 1.0]\ndistortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [{:?}, {:?}, {:?}, {:?}, {:?}]\nrectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]\nprojection_matrix:\n  rows: 3\n  cols: 4\n  data: [{fx:?}, {s:?}, {cx:?}, {tx:?}, 0.0, {fy:?}, {cy:?}, 0.0, 0.0, 0.0, 1.0, 0.0]\n",
        d[0],
        d[1],
        d[2],
        d[3],
        d[4],
        w = k.width,
        h = k.height,
        fx = k.fx,
        fy = k.fy,
        cx = k.cx,
        cy = k.cy,
        s = k.skew,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    const OPENCV: &str = "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 320., 0., 319.5, 0., 321., 239.5, 0., 0., 1. ]\ndistortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ -0.1, 0.01, 0., 0., 0. ]\n";
    const ROS: &str = "image_width: 640\nimage_height: 480\ncamera_name: endoscope_left\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: [320, 0, 319.5, 0, 321, 239.5, 0, 0, 1]\ndistortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [-0.1, 0.01, 0, 0, 0]\nrectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n";
    const ROS_MSG: &str = "header:\n  seq: 0\nheight: 480\nwidth: 640\ndistortion_model: plumb_bob\nD: [-0.1, 0.01, 0.0, 0.0, 0.0]\nK: [320.0, 0.0, 319.5, 0.0, 321.0, 239.5, 0.0, 0.0, 1.0]\n";

    #[test]
    fn reads_opencv_ros_and_camera_info() {
        for text in [OPENCV, ROS, ROS_MSG] {
            let k = parse_intrinsics_yaml(text).unwrap();
            assert_eq!((k.fx, k.fy, k.cx, k.cy, k.width, k.height), (320.0, 321.0, 319.5, 239.5, 640, 480));
            assert_eq!(k.distortion, [-0.1, 0.01, 0.0, 0.0, 0.0]);
        }
    }

    #[test]
    fn intrinsics_errors_name_the_problem() {
        let bad = OPENCV.replace("data: [ 320., 0., 319.5, 0., 321., 239.5, 0., 0., 1. ]", "data: [ 320., 0., 319.5 ]");
        assert!(matches!(parse_intrinsics_yaml(&bad), Err(IntrinsicsFileError::Field { field: "camera_matrix", .. })));
        let missing = ROS.replace("image_height: 480\n", "");
        assert_eq!(parse_intrinsics_yaml(&missing), Err(IntrinsicsFileError::Missing("image_height")));
        let fisheye = ROS.replace("plumb_bob", "equidistant");
        assert!(matches!(
            parse_intrinsics_yaml(&fisheye),
            Err(IntrinsicsFileError::Field { field: "distortion_model", .. })
        ));
        match parse_intrinsics_yaml("image_width: 640\ncamera_matrix: [1, 2\n") {
            Err(IntrinsicsFileError::Yaml { line, .. }) => assert!(line >= 2, "line {line}"),
            other => panic!("{other:?}"),
        }
        assert_eq!(parse_intrinsics_yaml("width: 3\n"), Err(IntrinsicsFileError::Missing("camera_matrix")));
    }

    fn dataset() -> DatasetFile {
        DatasetFile {
            format: DATASET_FORMAT.into(),
            version: 1,
            intrinsics: parse_intrinsics_yaml(ROS).unwrap(),
            hand_eye: TransformJson { translation_m: [0.0, 0.0, 0.001], quaternion_wxyz: [1.0, 0.0, 0.0, 0.0] },
            right_eye: None,
            noise_model: None,
            min_shaft_px: None,
            selection: Some(SelectionRule {
                min_visible_shaft_px: 40.0,
                border_margin_px: 2.0,
                require_tip_in_view: false,
                ends_are_shaft_ends: true,
            }),
            shaft_extent: Some(ShaftExtent { beyond_tip_m: 0.018, before_point_m: 0.0, end_sd_px: 8.0 }),
            observations: vec![ObservationJson {
                ecm_joints: [0.1, 0.0, 0.05, 0.0],
                psm_joints: [0.0, 0.1, 0.1],
                tool_point_m: [0.0; 3],
                line_px: [[10.0, 20.0], [200.0, 220.0]],
                eye: Eye::Left,
            }],
        }
    }

    #[test]
    fn dataset_round_trips_and_errors_name_fields() {
        let d = dataset();
        let text = to_json(&d);
        assert_eq!(parse_dataset(&text).unwrap(), d);
        let bad_version = text.replace("\"version\": 1", "\"version\": 7");
        assert_eq!(parse_dataset(&bad_version), Err(CalibFileError::Version { found: 7, supported: 1 }));
        let bad_format = text.replace(DATASET_FORMAT, "something-else");
        assert!(matches!(parse_dataset(&bad_format), Err(CalibFileError::Format { .. })));
        let mut same = d.clone();
        same.observations[0].line_px = [[5.0, 5.0], [5.0, 5.0]];
        assert_eq!(
            parse_dataset(&to_json(&same)),
            Err(CalibFileError::Field {
                field: "observations[0].line_px".into(),
                problem: "the two line points coincide".into()
            })
        );
        // Wrong arity: serde names the field and the line.
        let short = text.replacen("\"ecm_joints\": [", "\"ecm_joints\": [9.0, ", 1);
        match parse_dataset(&short) {
            Err(CalibFileError::Json { line, message, .. }) => {
                assert!(line > 1 && !message.is_empty(), "{line} {message}");
            }
            other => panic!("{other:?}"),
        }
        let mut q = d.clone();
        q.hand_eye.quaternion_wxyz = [1.0, 1.0, 0.0, 0.0];
        assert!(
            matches!(parse_dataset(&to_json(&q)), Err(CalibFileError::Field { field, .. }) if field == "hand_eye.quaternion_wxyz")
        );
        let unknown = text.replacen("\"version\"", "\"colour\": 1, \"version\"", 1);
        assert!(
            matches!(parse_dataset(&unknown), Err(CalibFileError::Json { message, .. }) if message.contains("colour"))
        );
        assert!(matches!(parse_dataset("{\"format\": "), Err(CalibFileError::Json { line: 1, .. })));
    }

    #[test]
    fn the_truth_files_wrong_lines_are_optional_and_round_trip() {
        let mut t = TruthFile {
            format: TRUTH_FORMAT.into(),
            version: CALIB_FILE_VERSION,
            truth: TransformJson { quaternion_wxyz: [1.0, 0.0, 0.0, 0.0], translation_m: [0.1, 0.02, 0.09] },
            n_e: 3,
            n_t: 3,
            sigma: 0.01,
            units: "mm".into(),
            pixel_sigma_px: 0.0,
            seed: 1,
            generated: 729,
            dropped: 223,
            collided: 0,
            wrong_lines: Vec::new(),
        };
        // None: the key is not written, and a file without it (as before) parses.
        let text = to_json(&t);
        assert!(!text.contains("wrong_lines"), "{text}");
        assert_eq!(parse_truth(&text).unwrap(), t);
        t.wrong_lines = vec![3, 17, 40];
        let text = to_json(&t);
        assert!(text.contains("\"wrong_lines\""), "{text}");
        assert_eq!(parse_truth(&text).unwrap().wrong_lines, [3, 17, 40]);
    }

    #[test]
    fn the_selection_rule_round_trips_and_old_files_keep_their_meaning() {
        let d = dataset();
        let text = to_json(&d);
        assert!(text.contains("\"require_tip_in_view\": false"), "{text}");
        assert!(!text.contains("min_shaft_px"), "{text}");
        let back = parse_dataset(&text).unwrap();
        assert_eq!(back.selection_rule().unwrap(), d.selection.unwrap());
        // A version-1 file with the legacy key: the tip-in-view rule it meant.
        let mut old = d.clone();
        old.selection = None;
        old.min_shaft_px = Some(25.0);
        let old_text = to_json(&old);
        assert!(old_text.contains("\"min_shaft_px\": 25.0") && !old_text.contains("\"selection\""));
        assert_eq!(parse_dataset(&old_text).unwrap().selection_rule().unwrap(), SelectionRule::tip_in_view(25.0));
        // Neither: the default rule (visible shaft only).
        old.min_shaft_px = None;
        let none = parse_dataset(&to_json(&old)).unwrap();
        assert_eq!(none.selection_rule().unwrap(), SelectionRule::default());
        assert!(!SelectionRule::default().require_tip_in_view);
        // Both, a negative length, an unknown rule key: named errors.
        let mut both = d.clone();
        both.min_shaft_px = Some(1.0);
        assert!(
            matches!(parse_dataset(&to_json(&both)), Err(CalibFileError::Field { field, .. }) if field == "min_shaft_px")
        );
        let mut neg = d.clone();
        neg.selection = Some(SelectionRule { min_visible_shaft_px: -1.0, ..SelectionRule::default() });
        assert!(
            matches!(parse_dataset(&to_json(&neg)), Err(CalibFileError::Field { field, .. }) if field == "selection")
        );
        let unknown = text.replacen("\"require_tip_in_view\"", "\"tip_colour\": 1, \"require_tip_in_view\"", 1);
        assert!(
            matches!(parse_dataset(&unknown), Err(CalibFileError::Json { message, .. }) if message.contains("tip_colour"))
        );
    }

    #[test]
    fn the_shaft_extent_round_trips_is_optional_and_is_checked() {
        let d = dataset();
        let text = to_json(&d);
        assert!(text.contains("\"beyond_tip_m\": 0.018"), "{text}");
        assert_eq!(parse_dataset(&text).unwrap().shaft_extent, d.shaft_extent);
        // Older files: absent, the default (RCM to tip).
        let mut old = d.clone();
        old.shaft_extent = None;
        let old_text = to_json(&old);
        assert!(!old_text.contains("shaft_extent"));
        assert_eq!(parse_dataset(&old_text).unwrap().shaft_extent, None);
        for bad in [-0.001, f64::NAN] {
            let mut neg = d.clone();
            neg.shaft_extent = Some(ShaftExtent { beyond_tip_m: 0.0, before_point_m: bad, end_sd_px: 0.0 });
            // NaN is written as null, which JSON refuses as a number; a negative length is named.
            match parse_dataset(&to_json(&neg)) {
                Err(CalibFileError::Field { field, .. }) => assert_eq!(field, "shaft_extent"),
                Err(CalibFileError::Json { .. }) => assert!(bad.is_nan()),
                other => panic!("{bad}: {other:?}"),
            }
        }
    }

    #[test]
    fn result_files_record_failures_and_read_old_ambiguity_ratios() {
        let r = ResultFile {
            format: RESULT_FORMAT.into(),
            version: CALIB_FILE_VERSION,
            results: vec![],
            failures: vec![PipelineFailureJson {
                pipeline: "ours".into(),
                kind: "ambiguous".into(),
                error: "x".into(),
            }],
        };
        let text = to_json(&r);
        assert!(text.contains("\"failures\""), "{text}");
        assert_eq!(parse_result(&text).unwrap(), r);
        let none = ResultFile { failures: vec![], ..r };
        assert!(!to_json(&none).contains("failures"));
        assert_eq!(parse_result(&to_json(&none)).unwrap(), none);
    }

    #[test]
    fn stereo_camera_info_round_trips_and_gives_the_right_from_left_transform() {
        let k = CameraIntrinsics {
            fx: 400.0,
            fy: 401.0,
            cx: 320.5,
            cy: 240.0,
            skew: 0.0,
            width: 640,
            height: 480,
            distortion: [-0.08, 0.01, 0.0, 0.0, 0.0],
        };
        let left = write_camera_info_yaml("left", &k, None);
        let right = write_camera_info_yaml("right", &k, Some(0.005));
        let s = parse_stereo_camera_info(&left, &right).unwrap();
        assert_eq!(s.left, k);
        assert_eq!(s.right, k);
        assert!((s.baseline_m() - 0.005).abs() < 1e-15);
        // Left optical centre seen from the right eye: 5 mm to its left.
        assert!((s.translation_right_left_m[0] + 0.005).abs() < 1e-15);
        assert_eq!(s.rotation_right_left, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);
        // A rotated rectification: R_l = Rz(90°) gives R_r^T R_l = Rz(90°) with R_r = I.
        let rotated = left.replace(
            "data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]",
            "data: [0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]",
        );
        let s = parse_stereo_camera_info(&rotated, &right).unwrap();
        assert_eq!(s.rotation_right_left[0], [0.0, -1.0, 0.0]);
        // Swapped eyes (positive Tx), a non-rotation R, a missing P: typed errors.
        assert!(matches!(parse_stereo_camera_info(&right, &left), Err(StereoFileError::Field { .. })));
        let skewed = left.replace(
            "data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]",
            "data: [2.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]",
        );
        assert!(matches!(parse_stereo_camera_info(&skewed, &right), Err(StereoFileError::Field { field: "R", .. })));
        let no_p: String =
            right.lines().take_while(|l| !l.starts_with("projection_matrix")).collect::<Vec<_>>().join("\n");
        assert!(matches!(
            parse_stereo_camera_info(&left, &no_p),
            Err(StereoFileError::Field { eye: "right", field: "projection_matrix", .. })
        ));
    }
}
