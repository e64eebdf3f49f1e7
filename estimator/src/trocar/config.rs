//! Detector configuration (the `[detector]` tables of a config file) and its validation.
//!
//! Every key is documented in `configs/fulcrumd.toml` and `docs/configuration.md`.
//! [`DetectorConfig::validate`] names the offending key and its allowed range.

use serde::{Deserialize, Serialize};

use super::WINDOW_CAPACITY;

/// Which detector runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum DetectorMode {
    /// Dong & Morel's method, reproduced faithfully.
    Paper,
    /// comanip's own method.
    #[default]
    Fast,
}

/// Top-level detector configuration.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DetectorConfig {
    /// `"paper"` or `"fast"`.
    pub mode: DetectorMode,
    /// Sample period, seconds (1 kHz: 0.001). Converts the fast mode's durations to samples.
    pub sample_period_s: f64,
    /// Longest gap in the input (samples that never reached the detector: missing TPDOs,
    /// a stale node, a failed SYNC) after which the detector resumes where it was, seconds;
    /// a longer gap resets it (the instrument may have moved anywhere). Range [0, 10].
    pub max_gap_s: f64,
    /// Paper-mode parameters.
    pub paper: PaperConfig,
    /// Fast-mode parameters.
    pub fast: FastConfig,
}

impl Default for DetectorConfig {
    fn default() -> Self {
        Self {
            mode: DetectorMode::Fast,
            sample_period_s: 0.001,
            max_gap_s: 0.05,
            paper: PaperConfig::default(),
            fast: FastConfig::default(),
        }
    }
}

/// Paper-mode parameters; the defaults are the paper's (Sec. V).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PaperConfig {
    /// `m`: lines in the short window `L_m` (paper: 20). Range 3..=`window_long`.
    pub window_short: usize,
    /// `n`: lines in the long window `L_n` (paper: 100). Range `window_short`..=256.
    pub window_long: usize,
    /// `δ_d`: wrist displacement normal to the axis that includes a sample, metres (paper: 0.005).
    pub include_distance_m: f64,
    /// `δ_θ`: axis rotation that includes a sample, degrees (paper: 5). Range (0, 180).
    pub include_angle_deg: f64,
    /// `δ_em`: insertion needs `e_m` below this, metres (paper: 0.009).
    pub insert_max_residual_m: f64,
    /// `δ_depth`: insertion needs `|F − P|` above this, metres (paper: 0.05).
    pub insert_min_depth_m: f64,
    /// `Δ_em`: extraction when `e_m` exceeds this while `L_n` is not full, metres (paper: 0.025).
    /// Must be ≥ `insert_max_residual_m`.
    pub extract_residual_short_m: f64,
    /// `Δ_en`: extraction when `e_n` exceeds this once `L_n` is full, metres (paper: 0.025).
    /// Must be ≥ `insert_max_residual_m`.
    pub extract_residual_long_m: f64,
}

impl Default for PaperConfig {
    fn default() -> Self {
        Self {
            window_short: 20,
            window_long: 100,
            include_distance_m: 0.005,
            include_angle_deg: 5.0,
            insert_max_residual_m: 0.009,
            insert_min_depth_m: 0.05,
            extract_residual_short_m: 0.025,
            extract_residual_long_m: 0.025,
        }
    }
}

/// Fast-mode parameters (comanip's method; see `docs/trocar-detection.md`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FastConfig {
    /// Most lines in the fit window (a sliding window over the current consistent segment).
    /// Range `min_lines`..=256.
    pub window: usize,
    /// Wrist displacement normal to the axis that includes a sample, metres. Range (0, 0.1].
    pub include_distance_m: f64,
    /// Axis rotation that includes a sample, degrees. Range (0, 90].
    pub include_angle_deg: f64,
    /// Fewest lines before an insertion may be declared. Range 3..=`window`.
    pub min_lines: usize,
    /// Smallest per-line noise assumed when computing the fulcrum's uncertainty, metres
    /// (encoder quantisation, trocar compliance, model error). Range (0, 0.05].
    pub noise_floor_m: f64,
    /// Insertion needs the fulcrum's one-sigma uncertainty (worst direction) below this, metres.
    pub insert_max_std_m: f64,
    /// Insertion needs the lines' directions to spread out of their main swing plane by at
    /// least this (RMS angle, degrees): a swing about one axis always has a virtual pivot (the
    /// envelope of a one-parameter family of coplanar lines), so a point common to coplanar
    /// lines is no evidence of a trocar; lines meeting in one point from a cone of directions
    /// are. The default is just above the encoders' noise. Range [0, 10].
    pub insert_min_cross_spread_deg: f64,
    /// Insertion needs the segment's RMS line distance below this, metres; a segment whose RMS
    /// exceeds it is trimmed from its oldest end.
    pub consistency_rms_m: f64,
    /// Insertion needs the fulcrum in front of the wrist, along the axis towards the tip, by
    /// more than this, metres (signed depth guard; the paper's trap is a pivot at the wrist).
    pub insert_min_depth_m: f64,
    /// Insertion needs the instrument to have slid through the fulcrum by at least this
    /// much over the segment's lines, metres: the range of the fulcrum's depth along the
    /// shaft, `zᵀ(F − P)`. A body wall lets the tool slide through it while it pivots; the
    /// virtual pivot of a hand (a point of the shaft that stays still for a moment) stays at
    /// one place on the shaft. Range [0, 0.1].
    pub insert_min_slide_m: f64,
    /// An insertion becomes a confirmed trocar (enters the trocar list, can be re-entered
    /// from memory) once it has lasted this long, seconds. Range [0, 10].
    pub confirm_s: f64,
    /// Insertion needs the segment to span at least this long, seconds (persistence: a trocar
    /// constrains the axis continuously, a momentary virtual pivot does not).
    pub min_persistence_s: f64,
    /// An included line farther than this from a well-determined segment fulcrum starts a new
    /// segment, metres. Must be ≥ `consistency_rms_m`.
    pub break_gate_m: f64,
    /// Outside, a pure slide of the instrument along its own axis by more than this since the
    /// last included line starts a new segment, metres: entering a port is an axial slide,
    /// and the lines of the approach before it belong to no trocar. Range (0, 1].
    pub slide_restart_m: f64,
    /// While inside, a sample whose line passes farther than this from the fulcrum counts as
    /// evidence of extraction, metres. Must be ≥ `consistency_rms_m`.
    pub extract_gate_m: f64,
    /// Extraction needs that evidence for this long without interruption, seconds.
    pub extract_persistence_s: f64,
    /// Adaptive extraction gate: while inside, the gate shrinks from `extract_gate_m` to this
    /// many times the RMS distance of the recent lines to the fulcrum (the trocar's own
    /// noise: compliance, calibration error), but never below `extract_gate_min_m`.
    /// Range [1, 100].
    pub extract_gate_sigmas: f64,
    /// Smallest adaptive extraction gate, metres. Range (0, `extract_gate_m`].
    pub extract_gate_min_m: f64,
    /// While inside, the fulcrum is the least-squares point of the included lines since the
    /// insertion with exponential forgetting over about this many lines (averages the noise,
    /// follows a slowly moving trocar). Range [10, 100000].
    pub inside_memory_lines: f64,
    /// Instrument length from the wrist centre to the tip, metres, when known (omit the key
    /// when not). Extraction is then declared when the tip comes back over the fulcrum, and
    /// insertion needs the tip beyond it.
    pub instrument_length_m: Option<f64>,
    /// Hysteresis on the tip-over-fulcrum test, metres.
    pub tip_margin_m: f64,
    /// Recognise a re-insertion into a trocar found earlier from its first few lines.
    pub trocar_memory: bool,
    /// A line within this distance of a remembered trocar supports re-insertion into it, metres.
    pub memory_gate_m: f64,
    /// Re-insertion needs that support for this long without interruption, seconds.
    pub memory_persistence_s: f64,
    /// Fulcrums closer than this are the same trocar, metres.
    pub memory_merge_m: f64,
    /// Sliding sums are rebuilt from the window after this many updates (drift guard).
    pub rebuild_every: u32,
}

impl Default for FastConfig {
    fn default() -> Self {
        Self {
            window: 128,
            include_distance_m: 0.001,
            include_angle_deg: 0.5,
            min_lines: 8,
            noise_floor_m: 0.001,
            insert_max_std_m: 0.004,
            insert_min_cross_spread_deg: 0.03,
            consistency_rms_m: 0.0006,
            insert_min_depth_m: 0.05,
            insert_min_slide_m: 0.0005,
            confirm_s: 1.5,
            min_persistence_s: 0.3,
            break_gate_m: 0.006,
            slide_restart_m: 0.01,
            extract_gate_m: 0.008,
            extract_persistence_s: 0.01,
            extract_gate_sigmas: 3.5,
            extract_gate_min_m: 0.0025,
            inside_memory_lines: 400.0,
            instrument_length_m: None,
            tip_margin_m: 0.003,
            trocar_memory: false,
            memory_gate_m: 0.004,
            memory_persistence_s: 0.06,
            memory_merge_m: 0.015,
            rebuild_every: 4096,
        }
    }
}

/// Why a detector configuration was refused. Each variant names the key (as written in the
/// config file, under `[detector]`) and the allowed range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ConfigError {
    /// A number is outside its allowed range (or NaN).
    #[error("detector.{key} = {value}: allowed range is {allowed}")]
    OutOfRange {
        /// Key, e.g. `paper.window_short`.
        key: &'static str,
        /// Offending value.
        value: f64,
        /// Allowed range in words, e.g. `3 ..= window_long (100)`.
        allowed: &'static str,
    },
    /// Two keys contradict each other.
    #[error("detector.{key} = {value} must be >= detector.{other} = {other_value}")]
    Ordering {
        /// Key that must be the larger.
        key: &'static str,
        /// Its value.
        value: f64,
        /// Key that must be the smaller.
        other: &'static str,
        /// Its value.
        other_value: f64,
    },
}

fn positive(key: &'static str, v: f64, max: f64, allowed: &'static str) -> Result<(), ConfigError> {
    if v.is_finite() && v > 0.0 && v <= max { Ok(()) } else { Err(ConfigError::OutOfRange { key, value: v, allowed }) }
}

/// A duration in [0, 10] s.
fn duration(key: &'static str, v: f64) -> Result<(), ConfigError> {
    if v.is_finite() && (0.0..=10.0).contains(&v) {
        Ok(())
    } else {
        Err(ConfigError::OutOfRange { key, value: v, allowed: "[0, 10] s" })
    }
}

fn at_least(key: &'static str, v: f64, other: &'static str, o: f64) -> Result<(), ConfigError> {
    if v >= o { Ok(()) } else { Err(ConfigError::Ordering { key, value: v, other, other_value: o }) }
}

impl DetectorConfig {
    /// Checks every key; the first violation is returned.
    pub fn validate(&self) -> Result<(), ConfigError> {
        positive("sample_period_s", self.sample_period_s, 1.0, "(0, 1] s")?;
        duration("max_gap_s", self.max_gap_s)?;
        self.paper.validate()?;
        self.fast.validate()
    }
}

impl PaperConfig {
    /// Checks every paper-mode key.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let m = self.window_short;
        let n = self.window_long;
        if m < 3 {
            return Err(ConfigError::OutOfRange {
                key: "paper.window_short",
                value: m as f64,
                allowed: "3 ..= paper.window_long",
            });
        }
        if n > WINDOW_CAPACITY {
            return Err(ConfigError::OutOfRange {
                key: "paper.window_long",
                value: n as f64,
                allowed: "paper.window_short ..= 256 (compiled capacity)",
            });
        }
        at_least("paper.window_long", n as f64, "paper.window_short", m as f64)?;
        positive("paper.include_distance_m", self.include_distance_m, 1.0, "(0, 1] m")?;
        if !(self.include_angle_deg.is_finite() && self.include_angle_deg > 0.0 && self.include_angle_deg < 180.0) {
            return Err(ConfigError::OutOfRange {
                key: "paper.include_angle_deg",
                value: self.include_angle_deg,
                allowed: "(0, 180) degrees",
            });
        }
        positive("paper.insert_max_residual_m", self.insert_max_residual_m, 1.0, "(0, 1] m")?;
        positive("paper.insert_min_depth_m", self.insert_min_depth_m, 2.0, "(0, 2] m")?;
        positive("paper.extract_residual_short_m", self.extract_residual_short_m, 1.0, "(0, 1] m")?;
        positive("paper.extract_residual_long_m", self.extract_residual_long_m, 1.0, "(0, 1] m")?;
        at_least(
            "paper.extract_residual_short_m",
            self.extract_residual_short_m,
            "paper.insert_max_residual_m",
            self.insert_max_residual_m,
        )?;
        at_least(
            "paper.extract_residual_long_m",
            self.extract_residual_long_m,
            "paper.insert_max_residual_m",
            self.insert_max_residual_m,
        )?;
        Ok(())
    }
}

impl FastConfig {
    /// Checks every fast-mode key.
    pub fn validate(&self) -> Result<(), ConfigError> {
        if self.min_lines < 3 {
            return Err(ConfigError::OutOfRange {
                key: "fast.min_lines",
                value: self.min_lines as f64,
                allowed: "3 ..= fast.window",
            });
        }
        if self.window > WINDOW_CAPACITY {
            return Err(ConfigError::OutOfRange {
                key: "fast.window",
                value: self.window as f64,
                allowed: "fast.min_lines ..= 256 (compiled capacity)",
            });
        }
        at_least("fast.window", self.window as f64, "fast.min_lines", self.min_lines as f64)?;
        positive("fast.include_distance_m", self.include_distance_m, 0.1, "(0, 0.1] m")?;
        positive("fast.include_angle_deg", self.include_angle_deg, 90.0, "(0, 90] degrees")?;
        positive("fast.noise_floor_m", self.noise_floor_m, 0.05, "(0, 0.05] m")?;
        positive("fast.insert_max_std_m", self.insert_max_std_m, 0.1, "(0, 0.1] m")?;
        positive("fast.consistency_rms_m", self.consistency_rms_m, 0.1, "(0, 0.1] m")?;
        positive("fast.insert_min_depth_m", self.insert_min_depth_m, 2.0, "(0, 2] m")?;
        duration("fast.min_persistence_s", self.min_persistence_s)?;
        duration("fast.confirm_s", self.confirm_s)?;
        if !(0.0..=0.1).contains(&self.insert_min_slide_m) {
            return Err(ConfigError::OutOfRange {
                key: "fast.insert_min_slide_m",
                value: self.insert_min_slide_m,
                allowed: "[0, 0.1] m",
            });
        }
        positive("fast.break_gate_m", self.break_gate_m, 0.5, "(0, 0.5] m")?;
        positive("fast.slide_restart_m", self.slide_restart_m, 1.0, "(0, 1] m")?;
        if !(self.insert_min_cross_spread_deg.is_finite() && (0.0..=10.0).contains(&self.insert_min_cross_spread_deg)) {
            return Err(ConfigError::OutOfRange {
                key: "fast.insert_min_cross_spread_deg",
                value: self.insert_min_cross_spread_deg,
                allowed: "[0, 10] degrees",
            });
        }
        if !(self.extract_gate_sigmas.is_finite() && (1.0..=100.0).contains(&self.extract_gate_sigmas)) {
            return Err(ConfigError::OutOfRange {
                key: "fast.extract_gate_sigmas",
                value: self.extract_gate_sigmas,
                allowed: "[1, 100]",
            });
        }
        positive("fast.extract_gate_min_m", self.extract_gate_min_m, 0.5, "(0, fast.extract_gate_m] m")?;
        at_least("fast.extract_gate_m", self.extract_gate_m, "fast.extract_gate_min_m", self.extract_gate_min_m)?;
        if !(self.inside_memory_lines.is_finite() && (10.0..=100_000.0).contains(&self.inside_memory_lines)) {
            return Err(ConfigError::OutOfRange {
                key: "fast.inside_memory_lines",
                value: self.inside_memory_lines,
                allowed: "[10, 100000] lines",
            });
        }
        positive("fast.extract_gate_m", self.extract_gate_m, 0.5, "(0, 0.5] m")?;
        at_least("fast.break_gate_m", self.break_gate_m, "fast.consistency_rms_m", self.consistency_rms_m)?;
        at_least("fast.extract_gate_m", self.extract_gate_m, "fast.consistency_rms_m", self.consistency_rms_m)?;
        duration("fast.extract_persistence_s", self.extract_persistence_s)?;
        if let Some(l) = self.instrument_length_m {
            positive("fast.instrument_length_m", l, 2.0, "(0, 2] m")?;
            at_least("fast.instrument_length_m", l, "fast.insert_min_depth_m", self.insert_min_depth_m)?;
        }
        positive("fast.tip_margin_m", self.tip_margin_m, 0.1, "(0, 0.1] m")?;
        positive("fast.memory_gate_m", self.memory_gate_m, 0.1, "(0, 0.1] m")?;
        duration("fast.memory_persistence_s", self.memory_persistence_s)?;
        positive("fast.memory_merge_m", self.memory_merge_m, 0.5, "(0, 0.5] m")?;
        if self.rebuild_every == 0 {
            return Err(ConfigError::OutOfRange {
                key: "fast.rebuild_every",
                value: 0.0,
                allowed: "1 ..= 4294967295 updates",
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key_of(e: ConfigError) -> &'static str {
        match e {
            ConfigError::OutOfRange { key, .. } | ConfigError::Ordering { key, .. } => key,
        }
    }

    #[test]
    fn defaults_are_valid() {
        DetectorConfig::default().validate().unwrap();
    }

    #[test]
    fn each_invalid_value_names_its_key() {
        type Edit = fn(&mut DetectorConfig);
        let cases: &[(Edit, &str)] = &[
            (|c| c.sample_period_s = 0.0, "sample_period_s"),
            (|c| c.paper.window_short = 2, "paper.window_short"),
            (|c| c.paper.window_long = 300, "paper.window_long"),
            (|c| c.paper.window_long = 10, "paper.window_long"),
            (|c| c.paper.include_distance_m = -1.0, "paper.include_distance_m"),
            (|c| c.paper.include_angle_deg = f64::NAN, "paper.include_angle_deg"),
            (|c| c.paper.insert_max_residual_m = 0.0, "paper.insert_max_residual_m"),
            (|c| c.paper.insert_min_depth_m = f64::INFINITY, "paper.insert_min_depth_m"),
            (|c| c.paper.extract_residual_short_m = 0.005, "paper.extract_residual_short_m"),
            (|c| c.paper.extract_residual_long_m = 0.001, "paper.extract_residual_long_m"),
            (|c| c.fast.min_lines = 1, "fast.min_lines"),
            (|c| c.fast.window = 1000, "fast.window"),
            (|c| c.fast.window = 4, "fast.window"),
            (|c| c.fast.include_distance_m = 0.0, "fast.include_distance_m"),
            (|c| c.fast.include_angle_deg = 100.0, "fast.include_angle_deg"),
            (|c| c.fast.noise_floor_m = -0.1, "fast.noise_floor_m"),
            (|c| c.fast.insert_max_std_m = 0.0, "fast.insert_max_std_m"),
            (|c| c.fast.consistency_rms_m = f64::NAN, "fast.consistency_rms_m"),
            (|c| c.fast.insert_min_depth_m = 0.0, "fast.insert_min_depth_m"),
            (|c| c.fast.min_persistence_s = -1.0, "fast.min_persistence_s"),
            (|c| c.fast.break_gate_m = 0.0004, "fast.break_gate_m"),
            (|c| c.fast.slide_restart_m = 0.0, "fast.slide_restart_m"),
            (|c| c.fast.insert_min_cross_spread_deg = -1.0, "fast.insert_min_cross_spread_deg"),
            (|c| c.fast.extract_gate_sigmas = 0.5, "fast.extract_gate_sigmas"),
            (|c| c.fast.extract_gate_min_m = 0.02, "fast.extract_gate_m"),
            (|c| c.fast.inside_memory_lines = 1.0, "fast.inside_memory_lines"),
            (|c| c.fast.extract_gate_m = 0.001, "fast.extract_gate_m"),
            (|c| c.fast.extract_persistence_s = 11.0, "fast.extract_persistence_s"),
            (|c| c.fast.instrument_length_m = Some(-0.3), "fast.instrument_length_m"),
            (|c| c.fast.instrument_length_m = Some(0.01), "fast.instrument_length_m"),
            (|c| c.fast.tip_margin_m = 0.0, "fast.tip_margin_m"),
            (|c| c.fast.memory_gate_m = 1.0, "fast.memory_gate_m"),
            (|c| c.fast.memory_persistence_s = f64::NAN, "fast.memory_persistence_s"),
            (|c| c.fast.memory_merge_m = 0.0, "fast.memory_merge_m"),
            (|c| c.fast.rebuild_every = 0, "fast.rebuild_every"),
        ];
        for (edit, key) in cases {
            let mut c = DetectorConfig::default();
            edit(&mut c);
            let err = c.validate().expect_err(key);
            let msg = std::format!("{err}");
            assert_eq!(key_of(err), *key, "{msg}");
            assert!(msg.contains(key), "message must name the key: {msg}");
        }
    }
}
