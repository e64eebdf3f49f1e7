//! fulcrumd's configuration file (TOML): loading and validation.
//!
//! Every key is documented in `configs/fulcrumd.toml` and `docs/configuration.md`. Unknown
//! keys are refused (a misspelt key must not silently fall back to a default).

use std::path::{Path, PathBuf};

use estimator::kinematics::{AchillesConfig, KinematicsConfigError};
use estimator::trocar::{ConfigError as DetectorConfigError, DetectorConfig};
use serde::{Deserialize, Serialize};

/// The whole configuration of fulcrumd.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// Arm geometry and joint calibration.
    pub kinematics: AchillesConfig,
    /// Trocar detector.
    pub detector: DetectorConfig,
}

/// Why a configuration could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// The file could not be read.
    #[error("cannot read config file {path}: {source}")]
    Read {
        /// File path.
        path: PathBuf,
        /// OS error.
        source: std::io::Error,
    },
    /// The file is not valid TOML for this schema (syntax, unknown key, wrong type).
    #[error("config file {path}: {message}")]
    Parse {
        /// File path.
        path: PathBuf,
        /// Parser message, with the line and the key.
        message: String,
    },
    /// A kinematic parameter is out of range.
    #[error("config file {path}: {source}")]
    Kinematics {
        /// File path.
        path: PathBuf,
        /// Which key, and why.
        source: KinematicsConfigError,
    },
    /// A detector parameter is out of range.
    #[error("config file {path}: {source}")]
    Detector {
        /// File path.
        path: PathBuf,
        /// Which key, and why.
        source: DetectorConfigError,
    },
}

impl Config {
    /// Parses and validates a configuration from TOML text; `path` only labels errors.
    pub fn from_toml(text: &str, path: &Path) -> Result<Self, LoadError> {
        let cfg: Config =
            toml::from_str(text).map_err(|e| LoadError::Parse { path: path.to_owned(), message: e.to_string() })?;
        cfg.kinematics.validate().map_err(|source| LoadError::Kinematics { path: path.to_owned(), source })?;
        cfg.detector.validate().map_err(|source| LoadError::Detector { path: path.to_owned(), source })?;
        Ok(cfg)
    }

    /// Reads, parses and validates a configuration file.
    pub fn load(path: &Path) -> Result<Self, LoadError> {
        let text = std::fs::read_to_string(path).map_err(|source| LoadError::Read { path: path.to_owned(), source })?;
        Self::from_toml(&text, path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Config, LoadError> {
        Config::from_toml(text, Path::new("test.toml"))
    }

    #[test]
    fn shipped_config_loads_and_matches_defaults() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/fulcrumd.toml");
        let cfg = Config::load(&path).unwrap();
        // The shipped file documents the defaults: it must not drift from them.
        assert_eq!(cfg, Config::default());
    }

    #[test]
    fn empty_file_gives_defaults() {
        assert_eq!(parse("").unwrap(), Config::default());
    }

    #[test]
    fn mode_and_thresholds_are_read() {
        let cfg = parse("[detector]\nmode = \"paper\"\n[detector.paper]\nwindow_short = 10\n").unwrap();
        assert_eq!(cfg.detector.mode, estimator::trocar::DetectorMode::Paper);
        assert_eq!(cfg.detector.paper.window_short, 10);
    }

    #[test]
    fn unknown_key_is_refused_with_its_name() {
        let err = parse("[detector.paper]\nwindow_shrot = 10\n").unwrap_err();
        assert!(matches!(err, LoadError::Parse { .. }));
        assert!(err.to_string().contains("window_shrot"), "{err}");
    }

    #[test]
    fn wrong_type_is_a_parse_error() {
        let err = parse("[detector]\nsample_period_s = \"fast\"\n").unwrap_err();
        assert!(matches!(err, LoadError::Parse { .. }), "{err}");
    }

    #[test]
    fn unknown_mode_is_refused() {
        let err = parse("[detector]\nmode = \"turbo\"\n").unwrap_err();
        assert!(err.to_string().contains("turbo") || err.to_string().contains("mode"), "{err}");
    }

    #[test]
    fn out_of_range_values_name_the_key_and_range() {
        let err = parse("[detector.paper]\nwindow_short = 2\n").unwrap_err();
        let msg = err.to_string();
        assert!(matches!(err, LoadError::Detector { .. }));
        assert!(msg.contains("paper.window_short") && msg.contains("3"), "{msg}");
        let err = parse("[detector.fast]\ninstrument_length_m = -1.0\n").unwrap_err();
        assert!(err.to_string().contains("fast.instrument_length_m"), "{err}");
        let err = parse("[[kinematics.joints]]\nsign = 2.0\nzero_offset_rad = 0.0\n").unwrap_err();
        // Five joints missing: the array must have exactly six entries.
        assert!(matches!(err, LoadError::Parse { .. }), "{err}");
    }

    #[test]
    fn missing_file_is_a_read_error() {
        let err = Config::load(Path::new("/nonexistent/fulcrumd.toml")).unwrap_err();
        assert!(matches!(err, LoadError::Read { .. }));
    }
}
