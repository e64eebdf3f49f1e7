//! The `[recorder]` table: where and how much the recorder writes, and the range of each key.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use super::MIN_FILE_BYTES;

/// Where and how much the recorder writes. Keys of the `[recorder]` table.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RecorderConfig {
    /// Record at all (default true). `fulcrumd --no-record` turns it off for one run.
    pub enabled: bool,
    /// Directory of the recording files; created if missing. Default `/var/lib/comanip/recordings`.
    pub dir: PathBuf,
    /// A file is closed and the next one opened before it would exceed this size, bytes
    /// (>= 4096; default 64 MiB).
    pub max_file_bytes: u64,
    /// The run's files together never exceed this size, bytes: the oldest files of the run are
    /// deleted first (>= `max_file_bytes`; default 1 GiB).
    pub max_total_bytes: u64,
    /// All runs' recording files in `dir` together, bytes: at start, whole older runs are
    /// deleted, oldest first, until they and this run's `max_total_bytes` fit; the most recent
    /// earlier run (the one a crash left) is always kept (>= 2 × `max_total_bytes`; default
    /// 8 GiB).
    pub max_dir_bytes: u64,
    /// Buffered frames are handed to the kernel at least this often, milliseconds (1..=60000; default 1000).
    pub flush_interval_ms: u64,
    /// The writer warns (at most once a second) when the queue is at least this full, percent
    /// of its capacity (1..=100; default 50).
    pub queue_warn_percent: u8,
    /// After a disk error, the writer waits this long before opening a new file, milliseconds
    /// (1..=600000; default 1000). Records arriving meanwhile are counted as `write_errors`.
    pub retry_interval_ms: u64,
}

impl Default for RecorderConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            dir: PathBuf::from("/var/lib/comanip/recordings"),
            max_file_bytes: 64 * 1024 * 1024,
            max_total_bytes: 1024 * 1024 * 1024,
            max_dir_bytes: 8 * 1024 * 1024 * 1024,
            flush_interval_ms: 1000,
            queue_warn_percent: 50,
            retry_interval_ms: 1000,
        }
    }
}

/// A recorder configuration value out of range; the message names the key.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RecorderConfigError {
    /// `dir` is empty.
    #[error("recorder.dir must not be empty")]
    EmptyDir,
    /// `max_file_bytes` below [`MIN_FILE_BYTES`].
    #[error("recorder.max_file_bytes = {value}: must be at least {min} bytes", min = MIN_FILE_BYTES)]
    FileTooSmall {
        /// Configured value, bytes.
        value: u64,
    },
    /// `max_total_bytes` below `max_file_bytes`.
    #[error("recorder.max_total_bytes = {total}: must be at least recorder.max_file_bytes = {file}")]
    TotalBelowFile {
        /// Configured `max_total_bytes`, bytes.
        total: u64,
        /// Configured `max_file_bytes`, bytes.
        file: u64,
    },
    /// `max_dir_bytes` below twice `max_total_bytes` (this run and the previous one must fit).
    #[error("recorder.max_dir_bytes = {dir}: must be at least 2 × recorder.max_total_bytes = {total}")]
    DirBelowTwoRuns {
        /// Configured `max_dir_bytes`, bytes.
        dir: u64,
        /// Configured `max_total_bytes`, bytes.
        total: u64,
    },
    /// `flush_interval_ms` out of 1..=60000.
    #[error("recorder.flush_interval_ms = {value}: must be in 1..=60000")]
    FlushInterval {
        /// Configured value, milliseconds.
        value: u64,
    },
    /// `queue_warn_percent` out of 1..=100.
    #[error("recorder.queue_warn_percent = {value}: must be in 1..=100")]
    QueueWarnPercent {
        /// Configured value, percent.
        value: u8,
    },
    /// `retry_interval_ms` out of 1..=600000.
    #[error("recorder.retry_interval_ms = {value}: must be in 1..=600000")]
    RetryInterval {
        /// Configured value, milliseconds.
        value: u64,
    },
}

impl RecorderConfig {
    /// Checks every key's range.
    pub fn validate(&self) -> Result<(), RecorderConfigError> {
        if self.dir.as_os_str().is_empty() {
            return Err(RecorderConfigError::EmptyDir);
        }
        if self.max_file_bytes < MIN_FILE_BYTES {
            return Err(RecorderConfigError::FileTooSmall { value: self.max_file_bytes });
        }
        if self.max_total_bytes < self.max_file_bytes {
            return Err(RecorderConfigError::TotalBelowFile { total: self.max_total_bytes, file: self.max_file_bytes });
        }
        if self.max_dir_bytes / 2 < self.max_total_bytes {
            return Err(RecorderConfigError::DirBelowTwoRuns { dir: self.max_dir_bytes, total: self.max_total_bytes });
        }
        if !(1..=60_000).contains(&self.flush_interval_ms) {
            return Err(RecorderConfigError::FlushInterval { value: self.flush_interval_ms });
        }
        if !(1..=100).contains(&self.queue_warn_percent) {
            return Err(RecorderConfigError::QueueWarnPercent { value: self.queue_warn_percent });
        }
        if !(1..=600_000).contains(&self.retry_interval_ms) {
            return Err(RecorderConfigError::RetryInterval { value: self.retry_interval_ms });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validation_names_the_key() {
        let ok = RecorderConfig::default();
        assert_eq!(ok.validate(), Ok(()));
        let cases: [(RecorderConfig, &str); 6] = [
            (RecorderConfig { dir: PathBuf::new(), ..ok.clone() }, "recorder.dir"),
            (RecorderConfig { max_file_bytes: 100, ..ok.clone() }, "recorder.max_file_bytes"),
            (RecorderConfig { max_total_bytes: ok.max_file_bytes - 1, ..ok.clone() }, "recorder.max_total_bytes"),
            (RecorderConfig { flush_interval_ms: 0, ..ok.clone() }, "recorder.flush_interval_ms"),
            (RecorderConfig { queue_warn_percent: 101, ..ok.clone() }, "recorder.queue_warn_percent"),
            (RecorderConfig { retry_interval_ms: 0, ..ok.clone() }, "recorder.retry_interval_ms"),
        ];
        for (c, key) in cases {
            let e = c.validate().expect_err(key);
            assert!(e.to_string().contains(key), "{e} should name {key}");
        }
    }

    #[test]
    fn config_from_toml_refuses_unknown_keys() {
        let c: RecorderConfig = toml::from_str("dir = \"/x\"\nmax_file_bytes = 8192\n").unwrap();
        assert_eq!(c.dir, PathBuf::from("/x"));
        assert_eq!(c.max_file_bytes, 8192);
        assert_eq!(c.max_total_bytes, RecorderConfig::default().max_total_bytes);
        assert!(toml::from_str::<RecorderConfig>("max_file_byte = 1\n").is_err());
    }
}
