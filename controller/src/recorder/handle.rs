//! Starting the recorder, and the daemon's handle on it (counters, pause, shutdown); the
//! retention of earlier runs applied at start.

use std::collections::BTreeMap;
use std::fs;
use std::io;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use heapless::spsc::Queue;
use serde::Serialize;
use serde::de::DeserializeOwned;

use super::FRAME_OVERHEAD_BYTES;
use super::config::{RecorderConfig, RecorderConfigError};
use super::header::{RunInfo, parse_file_name};
use super::queue::{Control, QueueStorage, RecorderProducer};
use super::stats::{RecorderStats, RecorderStatsSnapshot, add};
use super::writer::{Sink, Writer};

#[cfg(doc)]
use super::header::file_name;

/// How long [`RecorderHandle::set_writer_paused`] waits for the writer to acknowledge.
const PAUSE_ACK_TIMEOUT: Duration = Duration::from_secs(5);

/// Why the recorder could not start.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// A configuration value is out of range.
    #[error(transparent)]
    Config(#[from] RecorderConfigError),
    /// The recording directory could not be created.
    #[error("recorder: cannot create directory {dir} (recorder.dir): {source}")]
    CreateDir {
        /// The directory.
        dir: PathBuf,
        /// OS error.
        source: io::Error,
    },
    /// The first recording file could not be created or its header written.
    #[error("recorder: cannot create recording file {path}: {source}")]
    CreateFile {
        /// The file.
        path: PathBuf,
        /// OS error.
        source: io::Error,
    },
    /// The header (with `config_toml`) plus one record does not fit in `max_file_bytes`.
    #[error(
        "recorder: a file header of {header_bytes} bytes plus a record of up to {record_bytes} bytes \
         does not fit in recorder.max_file_bytes = {max_file_bytes}"
    )]
    HeaderTooLarge {
        /// Magic, version and header frame, bytes.
        header_bytes: usize,
        /// Largest record frame the encode buffer allows, bytes.
        record_bytes: usize,
        /// Configured `max_file_bytes`, bytes.
        max_file_bytes: u64,
    },
    /// The header could not be encoded.
    #[error("recorder: cannot encode the file header: {0}")]
    EncodeHeader(postcard::Error),
    /// The queue could not be allocated.
    #[error("recorder: cannot allocate the queue ({bytes} bytes)")]
    QueueAlloc {
        /// Size of the queue, bytes.
        bytes: usize,
    },
    /// The writer thread could not be spawned.
    #[error("recorder: cannot spawn the writer thread: {0}")]
    Spawn(io::Error),
}

/// Why [`RecorderHandle::shutdown`] could not return the final counters.
#[derive(Debug, thiserror::Error)]
pub enum ShutdownError {
    /// The writer thread panicked (a bug); `stats` are the counters as it left them.
    #[error("recorder: the writer thread panicked (counters: {stats:?})")]
    WriterPanicked {
        /// Counters when the thread ended.
        stats: RecorderStatsSnapshot,
    },
}

/// The daemon's side of the recorder: counters, pause, shutdown. Dropping it shuts down too.
pub struct RecorderHandle {
    control: Arc<Control>,
    stats: Arc<RecorderStats>,
    thread: Option<JoinHandle<()>>,
    capacity: usize,
    first_file: PathBuf,
}

impl RecorderHandle {
    /// The recorder's counters (shared, live).
    pub fn stats(&self) -> &Arc<RecorderStats> {
        &self.stats
    }

    /// Records the queue can hold.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Path of the run's first file.
    pub fn first_file(&self) -> &Path {
        &self.first_file
    }

    /// Pauses (`true`) or resumes (`false`) the writer. While paused it does not drain the queue,
    /// so pushes beyond the capacity are refused and counted: for tests and diagnostics.
    /// Returns once the writer has acknowledged (true), or false after 5 s without acknowledgement.
    pub fn set_writer_paused(&self, paused: bool) -> bool {
        self.control.pause_requested.store(paused, Ordering::SeqCst);
        if let Some(t) = &self.thread {
            t.thread().unpark();
        }
        let start = Instant::now();
        while self.control.paused.load(Ordering::SeqCst) != paused {
            if start.elapsed() > PAUSE_ACK_TIMEOUT || self.thread.as_ref().is_none_or(|t| t.is_finished()) {
                return false;
            }
            thread::sleep(Duration::from_millis(1));
        }
        true
    }

    /// Stops the writer: it drains what is queued, writes it, syncs and closes the file, and
    /// the final counters are returned. Pushes after this are refused (`dropped_closed`).
    pub fn shutdown(mut self) -> Result<RecorderStatsSnapshot, ShutdownError> {
        let joined = self.stop();
        let stats = self.stats.snapshot();
        if joined { Ok(stats) } else { Err(ShutdownError::WriterPanicked { stats }) }
    }

    /// Signals the writer and joins it; false if it panicked.
    fn stop(&mut self) -> bool {
        let Some(t) = self.thread.take() else { return true };
        self.control.pause_requested.store(false, Ordering::SeqCst);
        self.control.shutdown.store(true, Ordering::SeqCst);
        t.thread().unpark();
        t.join().is_ok()
    }
}

impl Drop for RecorderHandle {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Starts a recorder with a queue of `N - 1` records (`N >= 2`; a power of two is fastest): creates
/// the directory, creates the run's first file (so an unwritable directory is reported here),
/// allocates the queue and spawns the writer thread `recorder-writer`.
pub fn start<T, const N: usize>(
    config: &RecorderConfig,
    run: RunInfo,
) -> Result<(RecorderProducer<T>, RecorderHandle), StartError>
where
    T: Serialize + DeserializeOwned + Copy + Send + 'static,
{
    const { assert!(N >= 2, "the recorder queue needs N >= 2 (it holds N - 1 records)") };
    config.validate()?;
    fs::create_dir_all(&config.dir).map_err(|source| StartError::CreateDir { dir: config.dir.clone(), source })?;

    let stats = Arc::new(RecorderStats::default());
    prune_old_runs(config, run.run_id, &stats);
    let control = Arc::new(Control::default());
    // Postcard output is bounded by a small multiple of the in-memory size for `Copy` types
    // (varints take at most 10 bytes for 8, options and enums a tag byte).
    let enc_payload = 4 * std::mem::size_of::<T>() + 256;
    let mut sink = Sink::new(config.clone(), run, stats.clone(), enc_payload);
    let header_bytes = sink.preamble(0).map_err(StartError::EncodeHeader)?.len();
    let record_bytes = enc_payload + FRAME_OVERHEAD_BYTES;
    if (header_bytes + record_bytes) as u64 > config.max_file_bytes {
        return Err(StartError::HeaderTooLarge { header_bytes, record_bytes, max_file_bytes: config.max_file_bytes });
    }
    let first_file = sink.open_next().map_err(|(path, source)| StartError::CreateFile { path, source })?;

    let storage =
        QueueStorage::<T, N>::allocate().ok_or(StartError::QueueAlloc { bytes: std::mem::size_of::<Queue<T, N>>() })?;
    let storage = Arc::new(storage);
    // SAFETY: split once; each half is stored next to a clone of `storage`, declared after it.
    let (producer, consumer) = unsafe { storage.split() };
    let capacity = consumer.capacity();

    let writer = Writer { queue: consumer, sink, control: control.clone(), _storage: storage.clone() };
    let thread = thread::Builder::new().name("recorder-writer".into()).spawn(move || writer.run()).map_err(|e| {
        // The writer (and its file) is gone with the closure; nothing else to undo.
        StartError::Spawn(e)
    })?;
    let producer = RecorderProducer {
        queue: producer,
        control: control.clone(),
        stats: stats.clone(),
        capacity,
        _storage: storage,
    };
    let handle = RecorderHandle { control, stats, thread: Some(thread), capacity, first_file };
    Ok((producer, handle))
}

/// One earlier run's files in the recording directory.
struct OldRun {
    files: Vec<(PathBuf, u64)>,
    bytes: u64,
    newest: SystemTime,
}

/// Deletes whole earlier runs, oldest first (by their newest file's modification time), until
/// the earlier runs' files plus this run's `max_total_bytes` fit in `max_dir_bytes`. The most
/// recent earlier run is always kept: it may hold the recording of the crash this start
/// follows. Only names made by [`file_name`] are considered; errors are logged, never fatal.
fn prune_old_runs(config: &RecorderConfig, this_run: u64, stats: &RecorderStats) {
    let entries = match fs::read_dir(&config.dir) {
        Ok(e) => e,
        Err(e) => {
            tracing::warn!(dir = %config.dir.display(), error = %e, "recorder: cannot list the directory for the retention limit");
            return;
        }
    };
    let mut runs: BTreeMap<u64, OldRun> = BTreeMap::new();
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some((run_id, _)) = name.to_str().and_then(parse_file_name) else { continue };
        let Ok(meta) = entry.metadata() else { continue };
        if run_id == this_run || !meta.is_file() {
            continue;
        }
        let modified = meta.modified().unwrap_or(UNIX_EPOCH);
        let run = runs.entry(run_id).or_insert(OldRun { files: Vec::new(), bytes: 0, newest: UNIX_EPOCH });
        run.files.push((entry.path(), meta.len()));
        run.bytes += meta.len();
        run.newest = run.newest.max(modified);
    }
    let mut runs: Vec<(u64, OldRun)> = runs.into_iter().collect();
    runs.sort_by_key(|(id, r)| (r.newest, *id));
    let mut total: u64 = runs.iter().map(|(_, r)| r.bytes).sum();
    let budget = config.max_dir_bytes.saturating_sub(config.max_total_bytes);
    // Keep the last (most recent) earlier run whatever its size.
    let deletable = runs.len().saturating_sub(1);
    for (run_id, run) in runs.iter().take(deletable) {
        if total <= budget {
            break;
        }
        let mut freed = 0;
        for (path, len) in &run.files {
            match fs::remove_file(path) {
                Ok(()) => {
                    freed += len;
                    add(&stats.old_files_deleted, 1);
                }
                Err(e) if e.kind() == io::ErrorKind::NotFound => freed += len,
                Err(e) => {
                    tracing::error!(path = %path.display(), error = %e, "recorder: cannot delete an old run's file")
                }
            }
        }
        total -= freed;
        add(&stats.old_runs_deleted, 1);
        add(&stats.old_bytes_deleted, freed);
        tracing::info!(
            run = format_args!("{run_id:016x}"),
            files = run.files.len(),
            bytes = freed,
            "recorder: deleted an old run to respect recorder.max_dir_bytes"
        );
    }
    if total > budget {
        tracing::warn!(
            bytes = total,
            budget,
            "recorder: earlier runs still exceed recorder.max_dir_bytes − max_total_bytes (the most recent one is kept)"
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recorder::test_support::{Rec, cfg};

    #[test]
    fn push_after_shutdown_is_refused_and_counted() {
        let dir = tempfile::tempdir().unwrap();
        let (mut p, h) = start::<Rec, 16>(&cfg(dir.path()), RunInfo::new("t", "")).unwrap();
        assert!(p.push(Rec { seq: 0, x: 0.0 }));
        let s = h.shutdown().unwrap();
        assert_eq!((s.pushed, s.written), (1, 1));
        assert!(!p.push(Rec { seq: 1, x: 0.0 }));
        assert_eq!(p.stats().snapshot().dropped_closed, 1);
    }

    #[test]
    fn header_too_large_for_file_size_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let c = RecorderConfig { max_file_bytes: 4096, max_total_bytes: 8192, ..cfg(dir.path()) };
        let run = RunInfo::new("t", "x".repeat(5000));
        let e = start::<Rec, 16>(&c, run).err().expect("must fail");
        assert!(matches!(e, StartError::HeaderTooLarge { .. }), "{e}");
        assert!(e.to_string().contains("recorder.max_file_bytes"), "{e}");
    }
}
