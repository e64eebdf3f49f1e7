//! The recorder's counters, shared by the producer, the writer and the daemon.

use std::sync::atomic::{AtomicU64, Ordering};

use serde::{Deserialize, Serialize};

/// Counters shared by the producer, the writer and the daemon (all monotonic, relaxed atomics).
#[derive(Debug, Default)]
pub struct RecorderStats {
    pub(super) pushed: AtomicU64,
    pub(super) dropped_queue_full: AtomicU64,
    pub(super) dropped_closed: AtomicU64,
    pub(super) encode_errors: AtomicU64,
    pub(super) written: AtomicU64,
    pub(super) write_errors: AtomicU64,
    pub(super) bytes_written: AtomicU64,
    pub(super) files_opened: AtomicU64,
    pub(super) files_deleted: AtomicU64,
    pub(super) records_deleted: AtomicU64,
    pub(super) queue_high_water: AtomicU64,
    pub(super) old_runs_deleted: AtomicU64,
    pub(super) old_files_deleted: AtomicU64,
    pub(super) old_bytes_deleted: AtomicU64,
}

/// A copy of the counters at one instant.
///
/// Once the recorder has shut down, `pushed == written + write_errors + encode_errors`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RecorderStatsSnapshot {
    /// Records accepted into the queue.
    pub pushed: u64,
    /// Records refused because the queue was full (the writer fell behind).
    pub dropped_queue_full: u64,
    /// Records refused because the recorder had shut down.
    pub dropped_closed: u64,
    /// Records that could not be encoded (larger than the encode buffer): never written.
    pub encode_errors: u64,
    /// Records handed to the kernel in a recording file.
    pub written: u64,
    /// Records lost to disk errors (failed write, or no file open while waiting to retry).
    pub write_errors: u64,
    /// Bytes handed to the kernel, headers included.
    pub bytes_written: u64,
    /// Recording files created.
    pub files_opened: u64,
    /// Files of this run deleted to stay within `max_total_bytes`.
    pub files_deleted: u64,
    /// Records those deleted files held ("overwritten").
    pub records_deleted: u64,
    /// Most records seen waiting in the queue by the writer.
    pub queue_high_water: u64,
    /// Earlier runs deleted at start to respect `max_dir_bytes`.
    #[serde(default)]
    pub old_runs_deleted: u64,
    /// Their files.
    #[serde(default)]
    pub old_files_deleted: u64,
    /// Their bytes.
    #[serde(default)]
    pub old_bytes_deleted: u64,
}

impl RecorderStats {
    /// Reads every counter (each one atomically; the set is not one atomic snapshot while running).
    pub fn snapshot(&self) -> RecorderStatsSnapshot {
        let r = |a: &AtomicU64| a.load(Ordering::Relaxed);
        RecorderStatsSnapshot {
            pushed: r(&self.pushed),
            dropped_queue_full: r(&self.dropped_queue_full),
            dropped_closed: r(&self.dropped_closed),
            encode_errors: r(&self.encode_errors),
            written: r(&self.written),
            write_errors: r(&self.write_errors),
            bytes_written: r(&self.bytes_written),
            files_opened: r(&self.files_opened),
            files_deleted: r(&self.files_deleted),
            records_deleted: r(&self.records_deleted),
            queue_high_water: r(&self.queue_high_water),
            old_runs_deleted: r(&self.old_runs_deleted),
            old_files_deleted: r(&self.old_files_deleted),
            old_bytes_deleted: r(&self.old_bytes_deleted),
        }
    }
}

/// Adds `n` to `counter` (relaxed: the counters order nothing).
pub(super) fn add(counter: &AtomicU64, n: u64) {
    counter.fetch_add(n, Ordering::Relaxed);
}
