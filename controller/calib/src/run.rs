//! `generate` and `calibrate`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use estimator::calib::ours::observation_residuals;
use estimator::calib::ours::{
    MAX_UNEXPLAINED_SHARE, OursConfig, OursError, SHAFT_MARGIN, shaft_explanation, solve_ours_prepared,
};
use estimator::calib::paper::{PaperConfig, PaperError, solve_paper_prepared};
use estimator::calib::prepare::{PrepareError, prepare};
use estimator::calib::{PoseErrors, pose_errors};
use hw_io::calib_files::{
    CALIB_FILE_VERSION, CalibFileError, IntrinsicsFileError, PipelineFailureJson, RESULT_FORMAT, ResultFile,
    TRUTH_FORMAT, TruthFile, parse_dataset, parse_intrinsics_yaml, parse_truth, to_json,
};
use sim::calib::{CalibGeometry, CalibProtocol, CalibProtocolError, NoiseUnits, corrupt_lines, generate_calibration};

use super::convert;
use super::residual_plot::{PipelineResiduals, residual_figure};

/// Which pipeline(s) `calibrate` runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Pipeline {
    /// The paper's, faithful.
    Paper,
    /// Ours.
    Ours,
    /// Both, paper first.
    Both,
}

/// Why `generate` failed.
#[derive(Debug, thiserror::Error)]
pub enum GenerateError {
    /// The protocol is invalid.
    #[error(transparent)]
    Protocol(#[from] CalibProtocolError),
    /// The fraction of wrong lines is outside 0..=1.
    #[error("--wrong-lines {0}: must be a fraction in 0..=1")]
    WrongLines(f64),
    /// A file could not be written.
    #[error("cannot write {path}: {source}")]
    Write {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
}

/// What `generate` wrote.
#[derive(Clone, Copy, Debug)]
pub struct Generated {
    /// Observations kept.
    pub kept: usize,
    /// Combinations dropped (tool not in view).
    pub dropped: usize,
    /// Combinations not generated (the tool through the endoscope).
    pub collided: usize,
    /// Combinations tried.
    pub generated: usize,
    /// Observations whose line was replaced by a wrong one.
    pub wrong: usize,
}

/// Runs the simulation protocol, replaces a fraction `wrong_lines` (0..=1) of the lines by
/// wrong ones ([`corrupt_lines`]), and writes the dataset and its ground truth (which lists
/// the wrong lines).
pub fn generate(
    protocol: &CalibProtocol,
    wrong_lines: f64,
    dataset: &Path,
    truth: &Path,
) -> Result<Generated, GenerateError> {
    if !(0.0..=1.0).contains(&wrong_lines) {
        return Err(GenerateError::WrongLines(wrong_lines));
    }
    let mut d = generate_calibration(protocol)?;
    let wrong = corrupt_lines(&mut d.observations, &d.setup.intrinsics, wrong_lines, protocol.seed);
    let file = convert::dataset_json(&d.setup, &d.observations, d.noise);
    write(dataset, &to_json(&file))?;
    let t = TruthFile {
        format: TRUTH_FORMAT.into(),
        version: CALIB_FILE_VERSION,
        truth: convert::transform_json(&d.truth),
        n_e: protocol.n_e,
        n_t: protocol.n_t,
        sigma: protocol.sigma,
        units: protocol.units.name().into(),
        pixel_sigma_px: protocol.pixel_sigma_px,
        seed: protocol.seed,
        generated: d.generated,
        dropped: d.dropped,
        collided: d.collided,
        wrong_lines: wrong.clone(),
    };
    write(truth, &to_json(&t))?;
    Ok(Generated {
        kept: d.observations.len(),
        dropped: d.dropped,
        collided: d.collided,
        generated: d.generated,
        wrong: wrong.len(),
    })
}

fn write(path: &Path, text: &str) -> Result<(), GenerateError> {
    std::fs::write(path, text).map_err(|source| GenerateError::Write { path: path.to_owned(), source })
}

/// The default protocol of `generate` (the paper's condition, millimetre reading).
pub fn default_protocol() -> CalibProtocol {
    CalibProtocol {
        geometry: CalibGeometry::default(),
        n_e: 3,
        n_t: 3,
        sigma: 0.01,
        units: NoiseUnits::Millimetre,
        pixel_sigma_px: 0.0,
        seed: 1,
    }
}

/// Why `calibrate` failed.
#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    /// A file could not be read.
    #[error("cannot read {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The dataset (or truth) file is malformed.
    #[error("{path}: {source}")]
    File {
        /// The file.
        path: PathBuf,
        /// What is wrong, with line/column or field.
        source: CalibFileError,
    },
    /// The intrinsics YAML is malformed.
    #[error("{path}: {source}")]
    Intrinsics {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        source: IntrinsicsFileError,
    },
    /// The data are unusable or degenerate.
    #[error("{0}")]
    Prepare(#[from] PrepareError),
    /// The paper's pipeline failed.
    #[error("paper pipeline: {0}")]
    Paper(#[from] PaperError),
    /// Our pipeline failed.
    #[error("our pipeline: {0}")]
    Ours(#[from] OursError),
    /// The result could not be written.
    #[error("cannot write {path}: {source}")]
    Write {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The residual figure could not be written.
    #[error(transparent)]
    Plot(#[from] super::residual_plot::ResidualPlotError),
}

/// Summary of one pipeline, for the terminal.
#[derive(Clone, Debug)]
pub struct CalibrateSummary {
    /// `"paper"` / `"ours"`.
    pub pipeline: &'static str,
    /// Errors against the truth file, when one was given and the pipeline produced a pose.
    pub errors: Option<PoseErrors>,
    /// Solve time, milliseconds.
    pub solve_ms: f64,
    /// Why our selection-aware stage was refused when the user accepted the unrefined
    /// (border-guarded) estimate (`--accept-unrefined`).
    pub warning: Option<String>,
    /// Why the pipeline failed (also in the result file's `failures`).
    pub failure: Option<String>,
}

/// The stable name of a failure in the result file.
fn paper_kind(e: &PaperError) -> &'static str {
    match e {
        PaperError::Prepare(p) => prepare_kind(p),
        _ => "degenerate",
    }
}

fn prepare_kind(e: &PrepareError) -> &'static str {
    match e {
        PrepareError::TooFewViews { .. } | PrepareError::TooFewToolOrientations { .. } => "degenerate",
        _ => "input",
    }
}

fn ours_kind(e: &OursError) -> &'static str {
    match e {
        OursError::Prepare(p) => prepare_kind(p),
        OursError::Ambiguous { .. } => "ambiguous",
        OursError::NoConvergence => "no_convergence",
        OursError::ShaftsNotExplained { .. } => "shafts_not_explained",
        OursError::NoiseModel => "input",
        _ => "degenerate",
    }
}

/// True when every requested pipeline failed: `calibrate`'s exit rule (non-zero then only).
pub fn all_failed(summaries: &[CalibrateSummary]) -> bool {
    summaries.iter().all(|s| s.failure.is_some())
}

fn read(path: &Path) -> Result<String, CalibrateError> {
    std::fs::read_to_string(path).map_err(|source| CalibrateError::Read { path: path.to_owned(), source })
}

/// How `calibrate` runs our pipeline.
#[derive(Clone, Copy, Debug, Default)]
pub struct OursOptions {
    /// Accept the unrefined (border-guarded) estimate when the selection-aware stage cannot
    /// model the data (otherwise a failure of our pipeline).
    pub accept_unrefined: bool,
    /// Take the dataset's noise model as known up to a scale, estimated from the data
    /// (`estimator::calib::ours::OursConfig::estimate_noise_scale`).
    pub estimate_noise_scale: bool,
    /// The probability (in `(0, 1)`) that the stage's move test refuses a stage consistent
    /// with the guarded fit (`estimator::calib::selection::SelectionConfig::false_refusal_probability`);
    /// `None`: the default, 1e-3.
    pub false_refusal_probability: Option<f64>,
    /// Search the candidates on every observation
    /// (`estimator::calib::ours::OursConfig::search_observations` `None`); `false`: the
    /// library's default subsample for large datasets.
    pub search_on_all: bool,
}

/// Reads a dataset (optionally overriding its intrinsics from a YAML file), runs the
/// requested pipeline(s), writes the result file (each pipeline's result or its failure; and
/// the residual figure to `plot`, SVG, when given), and compares with a truth file if given.
///
/// A pipeline fails when it returns an error (degenerate data, ambiguity, ...) and, for ours,
/// when its selection-aware stage cannot model the data unless `ours.accept_unrefined` (the
/// unrefined estimate is then written, with the refusal in its `selection_stage`). `Err` only
/// for unreadable or malformed inputs and unwritable outputs; the caller decides the exit code
/// from the summaries ([`all_failed`]).
pub fn calibrate(
    dataset: &Path,
    intrinsics: Option<&Path>,
    truth: Option<&Path>,
    out: &Path,
    plot: Option<&Path>,
    pipeline: Pipeline,
    ours: OursOptions,
) -> Result<Vec<CalibrateSummary>, CalibrateError> {
    let OursOptions { accept_unrefined, estimate_noise_scale, false_refusal_probability, search_on_all } = ours;
    let text = read(dataset)?;
    let file = parse_dataset(&text).map_err(|source| CalibrateError::File { path: dataset.to_owned(), source })?;
    let (mut setup, obs, noise) = convert::dataset(&file);
    if let Some(p) = intrinsics {
        let k = parse_intrinsics_yaml(&read(p)?)
            .map_err(|source| CalibrateError::Intrinsics { path: p.to_owned(), source })?;
        setup.intrinsics = k;
    }
    let truth = match truth {
        Some(p) => Some(convert::isometry(
            &parse_truth(&read(p)?).map_err(|source| CalibrateError::File { path: p.to_owned(), source })?.truth,
        )),
        None => None,
    };
    let wanted: Vec<&'static str> = match pipeline {
        Pipeline::Paper => vec!["paper"],
        Pipeline::Ours => vec!["ours"],
        Pipeline::Both => vec!["paper", "ours"],
    };
    let mut results = Vec::new();
    let mut summaries = Vec::new();
    let mut residuals = Vec::new();
    let mut failures = Vec::new();
    let mut fail = |name: &'static str, kind: &str, error: String, summaries: &mut Vec<CalibrateSummary>, ms: f64| {
        failures.push(PipelineFailureJson { pipeline: name.into(), kind: kind.into(), error: error.clone() });
        summaries.push(CalibrateSummary {
            pipeline: name,
            errors: None,
            solve_ms: ms,
            warning: None,
            failure: Some(error),
        });
    };
    let set = match prepare(&setup, &obs) {
        Ok(set) => Some(set),
        Err(e) => {
            for name in &wanted {
                fail(name, prepare_kind(&e), e.to_string(), &mut summaries, 0.0);
            }
            None
        }
    };
    if let Some(set) = &set {
        // Per-observation residuals, only when a figure is asked for.
        let per_observation = |pose: &nalgebra::Isometry3<f64>| -> Vec<f64> {
            if plot.is_none() {
                return Vec::new();
            }
            observation_residuals(set, pose).iter().map(|r| r[0].abs().max(r[1].abs())).collect()
        };
        if wanted.contains(&"paper") {
            let started = Instant::now();
            let r = solve_paper_prepared(set, &PaperConfig::default());
            let ms = started.elapsed().as_secs_f64() * 1e3;
            let r = r.map(|r| {
                let x = shaft_explanation(set, &r.pose, SHAFT_MARGIN);
                (r, x)
            });
            match r {
                // comanip's check on the paper's answer (not part of the paper's method): a pose
                // that puts the detected shafts where no instrument can be (a mirror, or a pose
                // pushed far away) is a failure, not a result.
                Ok((_, x)) if !x.explains() => {
                    let msg = format!(
                        "paper pipeline: its pose puts {} of {} observed shafts behind the camera and {} off the instrument's shaft (more than {:.0}%): a mirror or far solution (comanip's check of the result, not part of the paper's method)",
                        x.behind,
                        x.observations,
                        x.off_shaft,
                        MAX_UNEXPLAINED_SHARE * 100.0
                    );
                    fail("paper", "shafts_not_explained", msg, &mut summaries, ms);
                }
                Ok((r, _)) => {
                    let stats = estimator::calib::ours::residual_stats(set, &r.pose);
                    results.push(convert::result_json("paper", &r.pose, &stats, None, ms));
                    residuals.push(PipelineResiduals { name: "paper", residuals_px: per_observation(&r.pose) });
                    summaries.push(CalibrateSummary {
                        pipeline: "paper",
                        errors: truth.map(|t| pose_errors(&r.pose, &t)),
                        solve_ms: ms,
                        warning: None,
                        failure: None,
                    });
                }
                Err(e) => fail("paper", paper_kind(&e), format!("paper pipeline: {e}"), &mut summaries, ms),
            }
        }
        if wanted.contains(&"ours") {
            let started = Instant::now();
            let mut cfg = OursConfig { noise, estimate_noise_scale, ..OursConfig::default() };
            if search_on_all {
                cfg.search_observations = None;
            }
            if let (Some(p), Some(sel)) = (false_refusal_probability, cfg.selection.as_mut()) {
                sel.false_refusal_probability = p;
            }
            let r = solve_ours_prepared(set, &cfg);
            let ms = started.elapsed().as_secs_f64() * 1e3;
            match r {
                Ok(r) => {
                    results.push(convert::result_json("ours", &r.pose, &r.residuals, Some(&r), ms));
                    residuals.push(PipelineResiduals { name: "ours", residuals_px: per_observation(&r.pose) });
                    let refused = r.selection_refused.map(|e| {
                        format!("our pipeline: the selection-aware stage cannot model the data ({e}); the result is the unrefined (border-guarded) estimate")
                    });
                    let errors = truth.map(|t| pose_errors(&r.pose, &t));
                    match refused {
                        Some(msg) if !accept_unrefined => {
                            let msg = format!("{msg}; pass --accept-unrefined to accept it");
                            failures.push(PipelineFailureJson {
                                pipeline: "ours".into(),
                                kind: "selection_refused".into(),
                                error: msg.clone(),
                            });
                            summaries.push(CalibrateSummary {
                                pipeline: "ours",
                                errors,
                                solve_ms: ms,
                                warning: None,
                                failure: Some(msg),
                            });
                        }
                        warning => summaries.push(CalibrateSummary {
                            pipeline: "ours",
                            errors,
                            solve_ms: ms,
                            warning,
                            failure: None,
                        }),
                    }
                }
                Err(e) => fail("ours", ours_kind(&e), format!("our pipeline: {e}"), &mut summaries, ms),
            }
        }
    }
    let file = ResultFile { format: RESULT_FORMAT.into(), version: CALIB_FILE_VERSION, results, failures };
    std::fs::write(out, to_json(&file)).map_err(|source| CalibrateError::Write { path: out.to_owned(), source })?;
    if let (Some(plot), Some(set)) = (plot, &set) {
        let lines: Vec<[nalgebra::Vector2<f64>; 2]> = set.obs.iter().map(|o| o.px).collect();
        residual_figure(plot, &set.intrinsics, &lines, &residuals)?;
    }
    Ok(summaries)
}
