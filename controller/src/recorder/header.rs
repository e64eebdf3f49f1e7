//! What every recording file starts with: the run's description, and the file names that
//! carry the run id and the file index.

use std::time::SystemTime;

use serde::{Deserialize, Serialize};

#[cfg(doc)]
use super::FORMAT_VERSION;

/// Describes the run; written at the start of every file so that each file stands alone.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct RecordingHeader {
    /// Format version ([`FORMAT_VERSION`]).
    pub format_version: u16,
    /// What the records are, e.g. `"fulcrumd.cycle.v1"`: the reader's caller checks it.
    pub record_kind: String,
    /// Identifies the run (one daemon start); also in the file names, as 16 hex digits.
    pub run_id: u64,
    /// When this file was created, microseconds since the Unix epoch (UTC).
    pub created_unix_us: u64,
    /// The daemon's configuration as TOML text, for reproducing the run.
    pub config_toml: String,
    /// Position of this file in the run, from 0; also in the file name.
    pub file_index: u32,
}

/// What a run records and under which identity; the recorder copies it into every file header.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RunInfo {
    /// See [`RecordingHeader::record_kind`].
    pub record_kind: String,
    /// See [`RecordingHeader::run_id`]; [`new_run_id`] makes a fresh one.
    pub run_id: u64,
    /// See [`RecordingHeader::config_toml`].
    pub config_toml: String,
}

impl RunInfo {
    /// A run of `record_kind` records with a fresh [`new_run_id`].
    pub fn new(record_kind: impl Into<String>, config_toml: impl Into<String>) -> Self {
        Self { record_kind: record_kind.into(), run_id: new_run_id(), config_toml: config_toml.into() }
    }
}

/// A random 64-bit run id (std's randomly keyed SipHash over the time and the process id).
pub fn new_run_id() -> u64 {
    use std::hash::BuildHasher;
    std::hash::RandomState::new().hash_one((SystemTime::now(), std::process::id()))
}

/// File name of file `index` of run `run_id`: `fulcrumd-<run_id, 16 hex digits>-<index, at least 4 digits>.rec`.
pub fn file_name(run_id: u64, index: u32) -> String {
    format!("fulcrumd-{run_id:016x}-{index:04}.rec")
}

/// Parses a name made by [`file_name`] into (run id, file index).
pub fn parse_file_name(name: &str) -> Option<(u64, u32)> {
    let rest = name.strip_prefix("fulcrumd-")?.strip_suffix(".rec")?;
    let (run, index) = rest.split_once('-')?;
    if run.len() != 16 || index.len() < 4 || !index.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some((u64::from_str_radix(run, 16).ok()?, index.parse().ok()?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_names_round_trip_and_sort_by_index() {
        assert_eq!(file_name(0xabc, 7), "fulcrumd-0000000000000abc-0007.rec");
        assert_eq!(parse_file_name("fulcrumd-0000000000000abc-0007.rec"), Some((0xabc, 7)));
        assert_eq!(parse_file_name(&file_name(u64::MAX, 12345)), Some((u64::MAX, 12345)));
        assert_eq!(parse_file_name("fulcrumd-abc-0007.rec"), None);
        assert_eq!(parse_file_name("fulcrumd-0000000000000abc-07.rec"), None);
        assert_eq!(parse_file_name("other-0000000000000abc-0007.rec"), None);
    }
}
