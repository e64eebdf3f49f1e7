//! `generate` and `calibrate`.

use std::path::{Path, PathBuf};
use std::time::Instant;

use estimator::calib::ours::observation_residuals;
use estimator::calib::ours::{OursConfig, OursError, solve_ours_prepared};
use estimator::calib::paper::{PaperConfig, PaperError, solve_paper_prepared};
use estimator::calib::prepare::{PrepareError, prepare};
use estimator::calib::{PoseErrors, pose_errors};
use hw_io::calib_files::{
    CALIB_FILE_VERSION, CalibFileError, IntrinsicsFileError, RESULT_FORMAT, ResultFile, TRUTH_FORMAT, TruthFile,
    parse_dataset, parse_intrinsics_yaml, parse_truth, to_json,
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
        wrong_lines: wrong.clone(),
    };
    write(truth, &to_json(&t))?;
    Ok(Generated { kept: d.observations.len(), dropped: d.dropped, generated: d.generated, wrong: wrong.len() })
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
    /// Errors against the truth file, when one was given.
    pub errors: Option<PoseErrors>,
    /// Solve time, milliseconds.
    pub solve_ms: f64,
    /// Why our selection-aware stage was refused, when it was (the result is then the
    /// border-guarded robust fit).
    pub warning: Option<String>,
}

fn read(path: &Path) -> Result<String, CalibrateError> {
    std::fs::read_to_string(path).map_err(|source| CalibrateError::Read { path: path.to_owned(), source })
}

/// Reads a dataset (optionally overriding its intrinsics from a YAML file), runs the
/// pipeline(s), writes the result file (and the residual figure to `plot`, SVG, when given),
/// and compares with a truth file if given.
pub fn calibrate(
    dataset: &Path,
    intrinsics: Option<&Path>,
    truth: Option<&Path>,
    out: &Path,
    plot: Option<&Path>,
    pipeline: Pipeline,
) -> Result<Vec<CalibrateSummary>, CalibrateError> {
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
    let set = prepare(&setup, &obs)?;
    let mut results = Vec::new();
    let mut summaries = Vec::new();
    let mut residuals = Vec::new();
    // Per-observation residuals, only when a figure is asked for.
    let per_observation = |pose: &nalgebra::Isometry3<f64>| -> Vec<f64> {
        if plot.is_none() {
            return Vec::new();
        }
        observation_residuals(&set, pose).iter().map(|r| r[0].abs().max(r[1].abs())).collect()
    };
    if matches!(pipeline, Pipeline::Paper | Pipeline::Both) {
        let started = Instant::now();
        let r = solve_paper_prepared(&set, &PaperConfig::default())?;
        let ms = started.elapsed().as_secs_f64() * 1e3;
        let stats = estimator::calib::ours::residual_stats(&set, &r.pose);
        results.push(convert::result_json("paper", &r.pose, &stats, None, ms));
        residuals.push(PipelineResiduals { name: "paper", residuals_px: per_observation(&r.pose) });
        summaries.push(CalibrateSummary {
            pipeline: "paper",
            errors: truth.map(|t| pose_errors(&r.pose, &t)),
            solve_ms: ms,
            warning: None,
        });
    }
    if matches!(pipeline, Pipeline::Ours | Pipeline::Both) {
        let started = Instant::now();
        let r = solve_ours_prepared(&set, &OursConfig { noise, ..OursConfig::default() })?;
        let ms = started.elapsed().as_secs_f64() * 1e3;
        results.push(convert::result_json("ours", &r.pose, &r.residuals, Some(&r), ms));
        residuals.push(PipelineResiduals { name: "ours", residuals_px: per_observation(&r.pose) });
        summaries.push(CalibrateSummary {
            pipeline: "ours",
            errors: truth.map(|t| pose_errors(&r.pose, &t)),
            solve_ms: ms,
            warning: r.selection_refused.map(|e| format!("selection-aware stage not applied: {e}")),
        });
    }
    let file = ResultFile { format: RESULT_FORMAT.into(), version: CALIB_FILE_VERSION, results };
    std::fs::write(out, to_json(&file)).map_err(|source| CalibrateError::Write { path: out.to_owned(), source })?;
    if let Some(plot) = plot {
        let lines: Vec<[nalgebra::Vector2<f64>; 2]> = set.obs.iter().map(|o| o.px).collect();
        residual_figure(plot, &set.intrinsics, &lines, &residuals)?;
    }
    Ok(summaries)
}
