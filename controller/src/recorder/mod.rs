//! Flight recorder: the 1 kHz loop's records, written to bounded, self-describing files.
//!
//! The real-time thread owns a [`RecorderProducer`] and calls [`RecorderProducer::push`] once a
//! cycle: a few atomic operations and a copy into a lock-free single-producer single-consumer queue
//! (`heapless::spsc::Queue`, allocated once at [`start`]). It never blocks, never allocates and
//! never does I/O; a full queue refuses the record and counts it ([`RecorderStatsSnapshot::dropped_queue_full`]).
//!
//! A lower-priority writer thread drains the queue, encodes each record with postcard into a
//! buffer allocated at start, frames it (`[u32 LE length][payload][u32 LE CRC-32 of payload]`) and
//! writes the frames in blocks of up to 64 KiB. Files rotate at `max_file_bytes`; the oldest files
//! of the run are deleted when the run's total would exceed `max_total_bytes` (counted as
//! `files_deleted` / `records_deleted`). Disk errors never panic: the records concerned are
//! counted as `write_errors` and the writer opens a new file after `retry_interval_ms`.
//!
//! [`RecordingReader`] reads one file or every file of a run back, checking magic, version, CRC
//! and framing; a frame cut short by a crash is reported as a [`Truncation`], not an error.
//! The byte layout is in `docs/recorder.md`.
//!
//! ## Files
//! One topic per file, in the order of a record's journey; everything public is re-exported here:
//! `config` (the `[recorder]` table), `header` (what opens every file, file names), `stats`
//! (the shared counters), `queue` (the lock-free queue and the real-time producer), `handle`
//! (start, pause, shutdown, retention of earlier runs), `writer` (the writer thread and the
//! file sink), `reader` (reading back).

mod config;
mod handle;
mod header;
mod queue;
mod reader;
mod stats;
mod writer;

pub use config::{RecorderConfig, RecorderConfigError};
pub use handle::{RecorderHandle, ShutdownError, StartError, start};
pub use header::{RecordingHeader, RunInfo, file_name, new_run_id, parse_file_name};
pub use queue::RecorderProducer;
pub use reader::{ReadError, Recording, RecordingReader, RunFiles, Truncation, list_runs};
pub use stats::{RecorderStats, RecorderStatsSnapshot};

/// First bytes of every recording file (10 bytes).
pub const MAGIC: &[u8; 10] = b"COMANIPREC";
/// Format version written after the magic (u16 LE) and in the header; the reader accepts only it.
pub const FORMAT_VERSION: u16 = 1;
/// Largest payload a frame may announce, bytes; a larger length field is reported as corrupt.
pub const MAX_FRAME_PAYLOAD_BYTES: u32 = 16 * 1024 * 1024;
/// Smallest accepted `max_file_bytes`, bytes.
pub const MIN_FILE_BYTES: u64 = 4096;
/// Bytes a frame adds around its payload: the length (4) and the CRC-32 (4).
pub const FRAME_OVERHEAD_BYTES: usize = 8;
/// Bytes before the header frame: the magic and the format version.
pub const PREAMBLE_BYTES: usize = MAGIC.len() + 2;

/// Test helpers shared by the submodules' tests: a small record type and a fast-flushing configuration.
#[cfg(test)]
mod test_support {
    use std::path::Path;

    use serde::{Deserialize, Serialize};

    use super::RecorderConfig;

    #[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
    pub(super) struct Rec {
        pub(super) seq: u64,
        pub(super) x: f64,
    }

    pub(super) fn cfg(dir: &Path) -> RecorderConfig {
        RecorderConfig { dir: dir.to_owned(), flush_interval_ms: 10, retry_interval_ms: 10, ..Default::default() }
    }
}
