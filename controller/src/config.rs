//! fulcrumd's configuration file (TOML): loading and validation.
//!
//! Every key is documented in `configs/fulcrumd.toml` and `docs/configuration.md`. Unknown
//! keys are refused (a misspelt key must not silently fall back to a default).

use std::path::{Path, PathBuf};

use estimator::kinematics::{AchillesConfig, KinematicsConfigError};
use estimator::trocar::{ConfigError as DetectorConfigError, DetectorConfig};
use hw_io::can::{ConfigError as EncoderConfigError, EncoderConfig};
use serde::{Deserialize, Serialize};

use crate::health::{HealthConfig, HealthConfigError};
use crate::recorder::{RecorderConfig, RecorderConfigError};
use crate::rt::{RealtimeConfig, RealtimeConfigError};

/// The whole configuration of fulcrumd.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// The control cycle.
    #[serde(rename = "loop")]
    pub cycle: LoopConfig,
    /// The encoder bus.
    pub bus: BusConfig,
    /// Data-health thresholds.
    pub health: HealthConfig,
    /// Arm geometry and joint calibration.
    pub kinematics: AchillesConfig,
    /// Trocar detector.
    pub detector: DetectorConfig,
    /// The shared-memory output.
    pub output: OutputConfig,
    /// Real-time set-up of the loop's thread.
    pub realtime: RealtimeConfig,
    /// The flight recorder.
    pub recorder: RecorderConfig,
}

/// The control cycle (`[loop]`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LoopConfig {
    /// Cycle period, microseconds (100 ..= 100 000; default 1000 = 1 kHz). Must equal
    /// `detector.sample_period_s`.
    pub period_us: u32,
    /// After sending SYNC, the cycle waits at most this long for the nodes' TPDOs,
    /// microseconds (50 ..= period_us − 50; default 700). Frames arriving later are counted
    /// as late and not used.
    pub frame_deadline_us: u32,
}

impl Default for LoopConfig {
    fn default() -> Self {
        Self { period_us: 1000, frame_deadline_us: 700 }
    }
}

/// The encoder bus (`[bus]`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BusConfig {
    /// SocketCAN interface (`can0`, `vcan0`, ...). Empty: the built-in simulated robot on an
    /// in-process bus.
    pub iface: String,
    /// Kernel receive queue the daemon asks for on its SocketCAN socket, bytes
    /// ([`BUS_RECEIVE_BUFFER_RANGE`]; default [`DEFAULT_RECEIVE_BUFFER_BYTES`]). The kernel
    /// doubles the request for its bookkeeping (about 1 KiB per classic frame); a frame
    /// arriving at a full queue is dropped and counted (`bus_dropped_rx_frames`).
    pub receive_buffer_bytes: usize,
    /// Encoder nodes and counts-to-radians conversion.
    pub encoder: EncoderConfig,
    /// Node IDs of other nodes expected on the same bus whose frames fulcrumd ignores (the
    /// endoscope-holder arm's encoder nodes: TPDOs every 10th SYNC and heartbeats;
    /// `docs/can-protocol.md`): counted as `other_node_frames`, never a health flag, never in
    /// the estimate. 1..=127, distinct, none of `encoder.node_ids`, at most 125. Default
    /// [`DEFAULT_OTHER_NODE_IDS`]. A node on the bus that is neither is counted as foreign.
    pub other_node_ids: Vec<u8>,
}

/// Default of `bus.other_node_ids`: the endoscope-holder arm's two encoder nodes.
pub const DEFAULT_OTHER_NODE_IDS: [u8; 2] = [4, 5];

/// Default of `bus.receive_buffer_bytes`, bytes: 2 MiB asked, 4 MiB granted by the kernel,
/// about 4000 classic frames (half a second of a saturated 1 Mbit/s bus).
pub const DEFAULT_RECEIVE_BUFFER_BYTES: usize = 2 << 20;

/// Allowed `bus.receive_buffer_bytes`, bytes (1 KiB ..= 256 MiB; the kernel raises a request
/// below its minimum, about 2.3 KiB, to that minimum).
pub const BUS_RECEIVE_BUFFER_RANGE: std::ops::RangeInclusive<usize> = 1024..=(256 << 20);

impl Default for BusConfig {
    fn default() -> Self {
        Self {
            iface: String::new(),
            receive_buffer_bytes: DEFAULT_RECEIVE_BUFFER_BYTES,
            encoder: EncoderConfig::default(),
            other_node_ids: DEFAULT_OTHER_NODE_IDS.to_vec(),
        }
    }
}

/// The shared-memory output (`[output]`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OutputConfig {
    /// iceoryx2 service name the estimates are published on.
    pub service: String,
    /// Samples each subscriber's buffer holds, samples (1 ..= 65536; default 64, 64 ms at
    /// 1 kHz). A subscriber that falls further behind loses the oldest samples and sees the
    /// gap (`missed`); a larger buffer rides out longer stalls of the subscriber. Subscribers
    /// ask for at most this (`fulcrumd monitor --buffer`).
    pub subscriber_buffer: usize,
}

impl Default for OutputConfig {
    fn default() -> Self {
        Self { service: "comanip/fulcrum".into(), subscriber_buffer: 64 }
    }
}

/// Accepted `output.subscriber_buffer`, samples.
pub const SUBSCRIBER_BUFFER_RANGE: std::ops::RangeInclusive<usize> = 1..=65_536;

/// Why the daemon-level keys (`[loop]`, `[bus]`, `[output]`) were refused; names the key.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DaemonConfigError {
    /// `loop.period_us` outside 100 ..= 100 000.
    #[error("loop.period_us = {0}: must be in 100 ..= 100000 microseconds")]
    Period(u32),
    /// `loop.frame_deadline_us` outside 50 ..= period − 50.
    #[error("loop.frame_deadline_us = {deadline}: must be in 50 ..= loop.period_us - 50 = {max} microseconds")]
    FrameDeadline {
        /// Value given, microseconds.
        deadline: u32,
        /// Largest allowed, microseconds.
        max: u32,
    },
    /// `detector.sample_period_s` differs from `loop.period_us`.
    #[error("detector.sample_period_s = {sample_s} s differs from loop.period_us = {period_us} us: they must match")]
    PeriodMismatch {
        /// `detector.sample_period_s`, seconds.
        sample_s: f64,
        /// `loop.period_us`, microseconds.
        period_us: u32,
    },
    /// `bus.iface` is not a valid interface name.
    #[error("bus.iface = {0:?}: an interface name has 1 to 15 characters, no '/', no whitespace")]
    Iface(String),
    /// `bus.receive_buffer_bytes` outside [`BUS_RECEIVE_BUFFER_RANGE`].
    #[error("bus.receive_buffer_bytes = {0}: must be in 1024 ..= 268435456 bytes")]
    ReceiveBuffer(usize),
    /// `bus.encoder` is invalid.
    #[error("bus.{0}")]
    Encoders(EncoderConfigError),
    /// `bus.other_node_ids` has a node ID outside 1..=127, twice, or one of the encoder nodes.
    #[error(
        "bus.other_node_ids[{index}] = {value}: must be a node ID 1..=127, listed once, not one of bus.encoder.node_ids"
    )]
    OtherNode {
        /// Index into the list.
        index: usize,
        /// The value given.
        value: u8,
    },
    /// `output.service` is not a valid service name.
    #[error("output.service = {0:?}: must have 1 to 200 printable ASCII characters")]
    Service(String),
    /// `output.subscriber_buffer` outside [`SUBSCRIBER_BUFFER_RANGE`].
    #[error("output.subscriber_buffer = {0}: must be in 1 ..= 65536 samples")]
    SubscriberBuffer(usize),
}

impl Config {
    /// Checks the daemon-level keys and their consistency with the detector.
    pub fn validate_daemon(&self) -> Result<(), DaemonConfigError> {
        let p = self.cycle.period_us;
        if !(100..=100_000).contains(&p) {
            return Err(DaemonConfigError::Period(p));
        }
        let max = p - 50;
        if !(50..=max).contains(&self.cycle.frame_deadline_us) {
            return Err(DaemonConfigError::FrameDeadline { deadline: self.cycle.frame_deadline_us, max });
        }
        let s = self.detector.sample_period_s;
        if (s * 1e6 - f64::from(p)).abs() > 1e-6 {
            return Err(DaemonConfigError::PeriodMismatch { sample_s: s, period_us: p });
        }
        let iface = &self.bus.iface;
        if iface.len() > 15 || iface.contains('/') || iface.chars().any(char::is_whitespace) {
            return Err(DaemonConfigError::Iface(iface.clone()));
        }
        if !BUS_RECEIVE_BUFFER_RANGE.contains(&self.bus.receive_buffer_bytes) {
            return Err(DaemonConfigError::ReceiveBuffer(self.bus.receive_buffer_bytes));
        }
        self.bus.encoder.validate().map_err(DaemonConfigError::Encoders)?;
        let others = &self.bus.other_node_ids;
        for (index, &value) in others.iter().enumerate() {
            if !(1..=127).contains(&value)
                || others[..index].contains(&value)
                || self.bus.encoder.node_ids.contains(&value)
            {
                return Err(DaemonConfigError::OtherNode { index, value });
            }
        }
        let svc = &self.output.service;
        if svc.is_empty() || svc.len() > 200 || !svc.chars().all(|c| c.is_ascii_graphic()) {
            return Err(DaemonConfigError::Service(svc.clone()));
        }
        if !SUBSCRIBER_BUFFER_RANGE.contains(&self.output.subscriber_buffer) {
            return Err(DaemonConfigError::SubscriberBuffer(self.output.subscriber_buffer));
        }
        Ok(())
    }
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
    /// A health threshold is out of range.
    #[error("config file {path}: {source}")]
    Health {
        /// File path.
        path: PathBuf,
        /// Which key, and why.
        source: HealthConfigError,
    },
    /// A real-time key is out of range.
    #[error("config file {path}: {source}")]
    Realtime {
        /// File path.
        path: PathBuf,
        /// Which key, and why.
        source: RealtimeConfigError,
    },
    /// A recorder key is out of range.
    #[error("config file {path}: {source}")]
    Recorder {
        /// File path.
        path: PathBuf,
        /// Which key, and why.
        source: RecorderConfigError,
    },
    /// A loop, bus or output key is out of range or inconsistent.
    #[error("config file {path}: {source}")]
    Daemon {
        /// File path.
        path: PathBuf,
        /// Which key, and why.
        source: DaemonConfigError,
    },
}

impl Config {
    /// Parses and validates a configuration from TOML text; `path` only labels errors.
    pub fn from_toml(text: &str, path: &Path) -> Result<Self, LoadError> {
        let cfg: Config =
            toml::from_str(text).map_err(|e| LoadError::Parse { path: path.to_owned(), message: e.to_string() })?;
        cfg.kinematics.validate().map_err(|source| LoadError::Kinematics { path: path.to_owned(), source })?;
        cfg.detector.validate().map_err(|source| LoadError::Detector { path: path.to_owned(), source })?;
        cfg.health.validate().map_err(|source| LoadError::Health { path: path.to_owned(), source })?;
        cfg.realtime.validate().map_err(|source| LoadError::Realtime { path: path.to_owned(), source })?;
        cfg.recorder.validate().map_err(|source| LoadError::Recorder { path: path.to_owned(), source })?;
        cfg.validate_daemon().map_err(|source| LoadError::Daemon { path: path.to_owned(), source })?;
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
    fn daemon_keys_are_validated_by_name() {
        for (text, key) in [
            ("[loop]\nperiod_us = 50\n", "loop.period_us"),
            ("[loop]\nframe_deadline_us = 990\n", "loop.frame_deadline_us"),
            ("[loop]\nperiod_us = 2000\nframe_deadline_us = 700\n", "detector.sample_period_s"),
            ("[bus]\niface = \"can 0\"\n", "bus.iface"),
            ("[bus]\nreceive_buffer_bytes = 1000\n", "bus.receive_buffer_bytes"),
            ("[bus]\nreceive_buffer_bytes = 268435457\n", "bus.receive_buffer_bytes"),
            ("[bus.encoder]\nnode_ids = [1, 1, 3]\n", "node_ids"),
            ("[output]\nservice = \"\"\n", "output.service"),
            ("[output]\nsubscriber_buffer = 0\n", "output.subscriber_buffer"),
            ("[output]\nsubscriber_buffer = 65537\n", "output.subscriber_buffer"),
            ("[health]\nstale_after_cycles = 0\n", "health.stale_after_cycles"),
        ] {
            let err = parse(text).unwrap_err();
            assert!(err.to_string().contains(key), "{text:?}: {err}");
        }
        let ok = parse("[loop]\nperiod_us = 2000\n[detector]\nsample_period_s = 0.002\n").unwrap();
        assert_eq!(ok.cycle.period_us, 2000);
        let ok = parse("[bus]\nreceive_buffer_bytes = 1024\n").unwrap();
        assert_eq!(ok.bus.receive_buffer_bytes, 1024);
    }

    #[test]
    fn missing_file_is_a_read_error() {
        let err = Config::load(Path::new("/nonexistent/fulcrumd.toml")).unwrap_err();
        assert!(matches!(err, LoadError::Read { .. }));
    }
}
