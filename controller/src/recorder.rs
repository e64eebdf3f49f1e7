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

use std::collections::{BTreeMap, VecDeque};
use std::fs::{self, File, OpenOptions};
use std::io::{self, Write};
use std::marker::PhantomData;
use std::path::{Path, PathBuf};
use std::ptr::NonNull;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use heapless::spsc::{Consumer, Producer, Queue};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

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

/// Size of the writer's block buffer, bytes: frames are handed to the kernel in blocks of at most this.
const WRITE_BUFFER_BYTES: usize = 64 * 1024;
/// How long the writer sleeps when the queue is empty.
const DRAIN_INTERVAL: Duration = Duration::from_millis(5);
/// Smallest interval between two warnings of the same kind from the writer.
const WARN_INTERVAL: Duration = Duration::from_secs(1);
/// How long [`RecorderHandle::set_writer_paused`] waits for the writer to acknowledge.
const PAUSE_ACK_TIMEOUT: Duration = Duration::from_secs(5);

// ---------------------------------------------------------------------------------------------
// Configuration

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

// ---------------------------------------------------------------------------------------------
// Header

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

// ---------------------------------------------------------------------------------------------
// Statistics

/// Counters shared by the producer, the writer and the daemon (all monotonic, relaxed atomics).
#[derive(Debug, Default)]
pub struct RecorderStats {
    pushed: AtomicU64,
    dropped_queue_full: AtomicU64,
    dropped_closed: AtomicU64,
    encode_errors: AtomicU64,
    written: AtomicU64,
    write_errors: AtomicU64,
    bytes_written: AtomicU64,
    files_opened: AtomicU64,
    files_deleted: AtomicU64,
    records_deleted: AtomicU64,
    queue_high_water: AtomicU64,
    old_runs_deleted: AtomicU64,
    old_files_deleted: AtomicU64,
    old_bytes_deleted: AtomicU64,
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

fn add(counter: &AtomicU64, n: u64) {
    counter.fetch_add(n, Ordering::Relaxed);
}

// ---------------------------------------------------------------------------------------------
// Queue storage

/// Owns the heap block of the queue; the producer and consumer halves borrow it for `'static`
/// and each keeps an `Arc` to this owner, declared after the half so that it drops last.
struct QueueStorage<T, const N: usize> {
    ptr: NonNull<Queue<T, N>>,
}

// SAFETY: the storage is only a heap block; access goes through the spsc halves, which are
// `Send` when `T: Send`. The block is freed only when the last `Arc` (held next to each half) drops.
unsafe impl<T: Send, const N: usize> Send for QueueStorage<T, N> {}
// SAFETY: as above; `&QueueStorage` gives no access to the queue.
unsafe impl<T: Send, const N: usize> Sync for QueueStorage<T, N> {}

impl<T, const N: usize> QueueStorage<T, N> {
    /// Allocates an empty queue directly on the heap (a `Box::new(Queue::new())` would build it
    /// on the stack first, which overflows for large `N * size_of::<T>()` in debug builds).
    fn allocate() -> Option<Self> {
        let layout = std::alloc::Layout::new::<Queue<T, N>>();
        // SAFETY: the layout is not zero-sized (the queue holds two atomics). An all-zero
        // `heapless::spsc::Queue` (0.9) is exactly `Queue::new()`: head and tail are
        // `AtomicUsize(0)` and the buffer is `[UnsafeCell<MaybeUninit<T>>; N]`, for which any
        // bytes are valid. The block comes from the global allocator with the layout of the type,
        // as `Box::from_raw` in `Drop` requires.
        let raw = unsafe { std::alloc::alloc_zeroed(layout) };
        let ptr = NonNull::new(raw.cast::<Queue<T, N>>())?;
        // A large zeroed block is fresh mmap'd memory, not yet backed by pages: touch each page
        // now, so that the real-time thread takes no page fault on its first pushes.
        let mut offset = 0;
        while offset < layout.size() {
            // SAFETY: `offset < size`, inside the block; writing 0 keeps every byte as it is.
            unsafe { std::ptr::write_volatile(raw.add(offset), 0) };
            offset += 4096;
        }
        Some(Self { ptr })
    }

    /// Splits into the two halves, borrowed for `'static`.
    ///
    /// # Safety
    /// Call once; the halves must be dropped before the last `Arc` to `self`.
    unsafe fn split(&self) -> (Producer<'static, T>, Consumer<'static, T>) {
        // SAFETY: the block is valid and initialised (see `allocate`); this is the only
        // `&mut` ever made to it, and it is not used after `split` returns.
        let queue: &'static mut Queue<T, N> = unsafe { &mut *self.ptr.as_ptr() };
        queue.split()
    }
}

impl<T, const N: usize> Drop for QueueStorage<T, N> {
    fn drop(&mut self) {
        // SAFETY: allocated in `allocate` with the layout of `Queue<T, N>`; both halves have been
        // dropped (they are declared before the `Arc` that owns `self`), so no reference remains.
        drop(unsafe { Box::from_raw(self.ptr.as_ptr()) });
    }
}

/// Flags shared by the producer, the writer and the handle.
#[derive(Debug, Default)]
struct Control {
    /// Set by the producer around its enqueue (see `RecorderProducer::push`).
    producer_busy: AtomicBool,
    /// Set by the writer before its final drain: the producer refuses records from then on.
    closed: AtomicBool,
    /// Set by the handle to stop the writer.
    shutdown: AtomicBool,
    /// Set by the handle to pause the writer.
    pause_requested: AtomicBool,
    /// Set by the writer while paused.
    paused: AtomicBool,
}

// ---------------------------------------------------------------------------------------------
// Producer

/// The real-time side of the recorder: owned by the 1 kHz thread.
pub struct RecorderProducer<T: 'static> {
    // Field order matters: the queue half must drop before `_storage`.
    queue: Producer<'static, T>,
    control: Arc<Control>,
    stats: Arc<RecorderStats>,
    capacity: usize,
    _storage: Arc<dyn Send + Sync>,
}

impl<T: Copy + Send + 'static> RecorderProducer<T> {
    /// Queues one record for the writer. Never blocks, allocates or does I/O.
    ///
    /// Returns false when the record was refused: the queue is full (counted in
    /// `dropped_queue_full`) or the recorder has shut down (counted in `dropped_closed`).
    #[inline]
    pub fn push(&mut self, rec: T) -> bool {
        // Dekker-style hand-shake with the writer's shutdown (both sides SeqCst): either this push
        // sees `closed` and refuses, or the writer sees `producer_busy` and waits for the enqueue to
        // finish before its final drain. No record is accepted and then left unwritten.
        self.control.producer_busy.store(true, Ordering::SeqCst);
        if self.control.closed.load(Ordering::SeqCst) {
            self.control.producer_busy.store(false, Ordering::Release);
            add(&self.stats.dropped_closed, 1);
            return false;
        }
        let accepted = self.queue.enqueue(rec).is_ok();
        if accepted {
            add(&self.stats.pushed, 1);
        } else {
            add(&self.stats.dropped_queue_full, 1);
        }
        self.control.producer_busy.store(false, Ordering::Release);
        accepted
    }

    /// Records the queue can hold (its const-generic size minus one).
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// The recorder's counters.
    pub fn stats(&self) -> &Arc<RecorderStats> {
        &self.stats
    }
}

// ---------------------------------------------------------------------------------------------
// Start and handle

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

// ---------------------------------------------------------------------------------------------
// Writer

struct Writer<T: 'static> {
    // Field order matters: the queue half must drop before `_storage`.
    queue: Consumer<'static, T>,
    sink: Sink,
    control: Arc<Control>,
    _storage: Arc<dyn Send + Sync>,
}

impl<T: Serialize + Copy + Send + 'static> Writer<T> {
    fn run(mut self) {
        let mut last_warn = Instant::now();
        let mut warned = self.sink.stats.snapshot();
        let mut last_queue_warn: Option<Instant> = None;
        let warn_len = (self.queue.capacity() * usize::from(self.sink.cfg.queue_warn_percent)).div_ceil(100).max(1);
        loop {
            if self.control.pause_requested.load(Ordering::SeqCst) && !self.control.shutdown.load(Ordering::SeqCst) {
                self.control.paused.store(true, Ordering::SeqCst);
                while self.control.pause_requested.load(Ordering::SeqCst)
                    && !self.control.shutdown.load(Ordering::SeqCst)
                {
                    thread::park_timeout(DRAIN_INTERVAL);
                }
                self.control.paused.store(false, Ordering::SeqCst);
                continue;
            }
            let shutting_down = self.control.shutdown.load(Ordering::SeqCst);
            let waiting = self.queue.len();
            self.sink.stats.queue_high_water.fetch_max(waiting as u64, Ordering::Relaxed);
            if waiting >= warn_len && last_queue_warn.is_none_or(|t| t.elapsed() >= WARN_INTERVAL) {
                tracing::warn!(
                    waiting,
                    capacity = self.queue.capacity(),
                    "recorder: queue {}% full: the writer is falling behind",
                    waiting * 100 / self.queue.capacity().max(1)
                );
                last_queue_warn = Some(Instant::now());
            }
            self.drain();
            self.sink.tick();
            if last_warn.elapsed() >= WARN_INTERVAL {
                warned = self.warn_losses(warned);
                last_warn = Instant::now();
            }
            if shutting_down {
                break;
            }
            thread::park_timeout(DRAIN_INTERVAL);
        }
        // Final drain: refuse new pushes, wait for a push in progress, take what is left.
        self.control.closed.store(true, Ordering::SeqCst);
        while self.control.producer_busy.load(Ordering::SeqCst) {
            thread::yield_now();
        }
        self.drain();
        self.sink.close_current();
        self.warn_losses(warned);
    }

    fn drain(&mut self) {
        while let Some(rec) = self.queue.dequeue() {
            self.sink.record(&rec);
        }
    }

    /// Warns about records lost since `before`; returns the counters now.
    fn warn_losses(&self, before: RecorderStatsSnapshot) -> RecorderStatsSnapshot {
        let now = self.sink.stats.snapshot();
        let full = now.dropped_queue_full - before.dropped_queue_full;
        let disk = now.write_errors - before.write_errors;
        let enc = now.encode_errors - before.encode_errors;
        if full + disk + enc > 0 {
            tracing::warn!(
                dropped_queue_full = full,
                write_errors = disk,
                encode_errors = enc,
                total_dropped_queue_full = now.dropped_queue_full,
                total_write_errors = now.write_errors,
                "recorder: {} records lost in the last second",
                full + disk + enc
            );
        }
        now
    }
}

/// The file currently written.
struct OpenFile {
    file: File,
    path: PathBuf,
    /// Bytes on disk plus bytes buffered for this file.
    bytes: u64,
    /// Bytes the kernel accepted.
    confirmed_bytes: u64,
    /// Records on disk plus records buffered for this file.
    records: u64,
    /// Records the kernel accepted.
    confirmed_records: u64,
}

/// A closed file of this run, kept for the total-size accounting.
struct ClosedFile {
    path: PathBuf,
    bytes: u64,
    records: u64,
}

/// Everything file-related of the writer (independent of the record type).
struct Sink {
    cfg: RecorderConfig,
    run: RunInfo,
    stats: Arc<RecorderStats>,
    /// Encode buffer: `[len: 4][payload: enc_payload][crc: 4]`, allocated once.
    enc: Vec<u8>,
    /// Block buffer of whole frames not yet handed to the kernel, allocated once.
    out: Vec<u8>,
    /// Records in `out`.
    out_records: u64,
    current: Option<OpenFile>,
    closed: VecDeque<ClosedFile>,
    closed_bytes: u64,
    next_index: u32,
    retry_at: Option<Instant>,
    last_flush: Instant,
    last_error_log: Option<Instant>,
}

impl Sink {
    fn new(cfg: RecorderConfig, run: RunInfo, stats: Arc<RecorderStats>, enc_payload: usize) -> Self {
        Self {
            cfg,
            run,
            stats,
            enc: vec![0; enc_payload + FRAME_OVERHEAD_BYTES],
            out: Vec::with_capacity(WRITE_BUFFER_BYTES),
            out_records: 0,
            current: None,
            closed: VecDeque::new(),
            closed_bytes: 0,
            next_index: 0,
            retry_at: None,
            last_flush: Instant::now(),
            last_error_log: None,
        }
    }

    /// Magic, version and header frame of file `index`.
    fn preamble(&self, index: u32) -> Result<Vec<u8>, postcard::Error> {
        let created_unix_us = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_micros() as u64);
        let header = RecordingHeader {
            format_version: FORMAT_VERSION,
            record_kind: self.run.record_kind.clone(),
            run_id: self.run.run_id,
            created_unix_us,
            config_toml: self.run.config_toml.clone(),
            file_index: index,
        };
        let payload = postcard::to_stdvec(&header)?;
        let mut v = Vec::with_capacity(PREAMBLE_BYTES + payload.len() + FRAME_OVERHEAD_BYTES);
        v.extend_from_slice(MAGIC);
        v.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        v.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        v.extend_from_slice(&payload);
        v.extend_from_slice(&crc32fast::hash(&payload).to_le_bytes());
        Ok(v)
    }

    /// Creates the next file of the run and writes its preamble. The current file must be closed.
    fn open_next(&mut self) -> Result<PathBuf, (PathBuf, io::Error)> {
        debug_assert!(self.current.is_none());
        let index = self.next_index;
        self.next_index = self.next_index.saturating_add(1);
        let path = self.cfg.dir.join(file_name(self.run.run_id, index));
        let preamble = self.preamble(index).map_err(|e| (path.clone(), io::Error::other(e)))?;
        self.enforce_total(preamble.len() as u64);
        // Re-create the directory if an operator removed it; errors surface at the open below.
        let _ = fs::create_dir_all(&self.cfg.dir);
        let mut file = OpenOptions::new().write(true).create_new(true).open(&path).map_err(|e| (path.clone(), e))?;
        if let Err(e) = file.write_all(&preamble) {
            drop(file);
            let _ = fs::remove_file(&path);
            return Err((path, e));
        }
        add(&self.stats.files_opened, 1);
        add(&self.stats.bytes_written, preamble.len() as u64);
        let n = preamble.len() as u64;
        self.current =
            Some(OpenFile { file, path: path.clone(), bytes: n, confirmed_bytes: n, records: 0, confirmed_records: 0 });
        Ok(path)
    }

    /// Makes sure a file is open; false while waiting to retry after an error.
    fn ensure_file(&mut self) -> bool {
        if self.current.is_some() {
            return true;
        }
        if self.retry_at.is_some_and(|t| Instant::now() < t) {
            return false;
        }
        match self.open_next() {
            Ok(_) => {
                self.retry_at = None;
                true
            }
            Err((path, e)) => {
                self.log_error(
                    || tracing::error!(path = %path.display(), error = %e, "recorder: cannot open a new file"),
                );
                self.retry_at = Some(Instant::now() + Duration::from_millis(self.cfg.retry_interval_ms));
                false
            }
        }
    }

    /// Encodes, frames and buffers one record.
    fn record<T: Serialize>(&mut self, rec: &T) {
        let end = self.enc.len() - 4;
        let payload_len = match postcard::to_slice(rec, &mut self.enc[4..end]) {
            Ok(p) => p.len(),
            Err(e) => {
                add(&self.stats.encode_errors, 1);
                let cap = end - 4;
                self.log_error(|| tracing::error!(error = %e, cap, "recorder: cannot encode a record"));
                return;
            }
        };
        let frame_len = payload_len + FRAME_OVERHEAD_BYTES;
        let crc = crc32fast::hash(&self.enc[4..4 + payload_len]);
        self.enc[..4].copy_from_slice(&(payload_len as u32).to_le_bytes());
        self.enc[4 + payload_len..frame_len].copy_from_slice(&crc.to_le_bytes());

        if !self.ensure_file() {
            add(&self.stats.write_errors, 1);
            return;
        }
        if self.current.as_ref().is_some_and(|c| c.bytes + frame_len as u64 > self.cfg.max_file_bytes) {
            self.close_current();
            if !self.ensure_file() {
                add(&self.stats.write_errors, 1);
                return;
            }
        }
        self.enforce_total(frame_len as u64);
        if self.out.len() + frame_len > self.out.capacity() {
            self.write_out();
            if self.current.is_none() {
                add(&self.stats.write_errors, 1);
                return;
            }
        }
        self.out.extend_from_slice(&self.enc[..frame_len]);
        self.out_records += 1;
        if let Some(c) = &mut self.current {
            c.bytes += frame_len as u64;
            c.records += 1;
        }
    }

    /// Deletes the oldest closed files of the run until `incoming` more bytes fit in `max_total_bytes`.
    fn enforce_total(&mut self, incoming: u64) {
        let current = self.current.as_ref().map_or(0, |c| c.bytes);
        while self.closed_bytes + current + incoming > self.cfg.max_total_bytes {
            let Some(old) = self.closed.pop_front() else { break };
            self.closed_bytes -= old.bytes;
            match fs::remove_file(&old.path) {
                Ok(()) => {
                    add(&self.stats.files_deleted, 1);
                    add(&self.stats.records_deleted, old.records);
                }
                Err(e) if e.kind() == io::ErrorKind::NotFound => {}
                Err(e) => self.log_error(
                    || tracing::error!(path = %old.path.display(), error = %e, "recorder: cannot delete an old file"),
                ),
            }
        }
    }

    /// Hands the buffered frames to the kernel; on failure the file is abandoned.
    fn write_out(&mut self) {
        if self.out.is_empty() {
            return;
        }
        let Some(cur) = &mut self.current else {
            // Unreachable: frames are only buffered while a file is open.
            add(&self.stats.write_errors, self.out_records);
            self.out.clear();
            self.out_records = 0;
            return;
        };
        let (done, error) = write_counting(&mut cur.file, &self.out);
        match error {
            None => {
                add(&self.stats.written, self.out_records);
                add(&self.stats.bytes_written, done as u64);
                cur.confirmed_bytes = cur.bytes;
                cur.confirmed_records = cur.records;
            }
            Some(e) => {
                // The frames wholly written before the error are on disk (the reader returns them);
                // the rest, including a partial frame, are lost.
                let whole = whole_frames(&self.out[..done]);
                add(&self.stats.written, whole);
                add(&self.stats.write_errors, self.out_records - whole);
                add(&self.stats.bytes_written, done as u64);
                let path = cur.path.clone();
                let on_disk = cur.confirmed_bytes + done as u64;
                let records = cur.confirmed_records + whole;
                self.current = None;
                self.closed_bytes += on_disk;
                self.closed.push_back(ClosedFile { path: path.clone(), bytes: on_disk, records });
                self.retry_at = Some(Instant::now() + Duration::from_millis(self.cfg.retry_interval_ms));
                self.log_error(|| tracing::error!(path = %path.display(), error = %e, "recorder: write failed"));
            }
        }
        self.out.clear();
        self.out_records = 0;
        self.last_flush = Instant::now();
    }

    /// Writes out, syncs and closes the current file.
    fn close_current(&mut self) {
        self.write_out();
        if let Some(cur) = self.current.take() {
            if let Err(e) = cur.file.sync_data() {
                self.log_error(|| tracing::warn!(path = %cur.path.display(), error = %e, "recorder: fsync failed"));
            }
            self.closed_bytes += cur.bytes;
            self.closed.push_back(ClosedFile { path: cur.path, bytes: cur.bytes, records: cur.records });
        }
    }

    /// Periodic work: flush on the interval.
    fn tick(&mut self) {
        if self.last_flush.elapsed() >= Duration::from_millis(self.cfg.flush_interval_ms) {
            self.write_out();
            self.last_flush = Instant::now();
        }
    }

    /// Runs `log` unless an error was logged less than a second ago.
    fn log_error(&mut self, log: impl FnOnce()) {
        if self.last_error_log.is_none_or(|t| t.elapsed() >= WARN_INTERVAL) {
            log();
            self.last_error_log = Some(Instant::now());
        }
    }
}

/// Writes `buf` like `write_all`, but says how many bytes the kernel accepted before an error.
fn write_counting(file: &mut File, buf: &[u8]) -> (usize, Option<io::Error>) {
    let mut done = 0;
    while done < buf.len() {
        match file.write(&buf[done..]) {
            Ok(0) => return (done, Some(io::ErrorKind::WriteZero.into())),
            Ok(n) => done += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return (done, Some(e)),
        }
    }
    (done, None)
}

/// Frames wholly contained in `buf`, which starts at a frame boundary.
fn whole_frames(buf: &[u8]) -> u64 {
    let mut pos = 0;
    let mut n = 0;
    while let Some(len) = buf.get(pos..pos + 4) {
        let len = u32::from_le_bytes([len[0], len[1], len[2], len[3]]) as usize;
        let end = pos + len + FRAME_OVERHEAD_BYTES;
        if end > buf.len() {
            break;
        }
        n += 1;
        pos = end;
    }
    n
}

// ---------------------------------------------------------------------------------------------
// Reader

/// Why a recording could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// A file or directory could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// File or directory.
        path: PathBuf,
        /// OS error.
        source: io::Error,
    },
    /// The file does not start with the magic bytes `COMANIPREC`.
    #[error("{path} is not a comanip recording (bad magic bytes)")]
    NotARecording {
        /// The file.
        path: PathBuf,
    },
    /// The file's format version is not [`FORMAT_VERSION`].
    #[error("{path}: recording format version {found} is not supported (this reader reads version {supported})")]
    UnsupportedVersion {
        /// The file.
        path: PathBuf,
        /// Version in the file.
        found: u16,
        /// Version this reader reads.
        supported: u16,
    },
    /// A frame's CRC-32 does not match its payload.
    #[error("{path}: corrupt frame at byte {offset}: CRC-32 {stored:#010x} stored, {computed:#010x} computed")]
    CorruptFrame {
        /// The file.
        path: PathBuf,
        /// Offset of the frame (its length field) in the file, bytes.
        offset: u64,
        /// CRC in the file.
        stored: u32,
        /// CRC of the payload as read.
        computed: u32,
    },
    /// A frame announces an impossible length.
    #[error("{path}: corrupt frame at byte {offset}: length {length} exceeds {max} bytes", max = MAX_FRAME_PAYLOAD_BYTES)]
    BadFrameLength {
        /// The file.
        path: PathBuf,
        /// Offset of the frame in the file, bytes.
        offset: u64,
        /// Announced payload length, bytes.
        length: u32,
    },
    /// A frame passed its CRC but its payload is not a valid record (or header).
    #[error("{path}: frame at byte {offset} does not decode: {source}")]
    Decode {
        /// The file.
        path: PathBuf,
        /// Offset of the frame in the file, bytes.
        offset: u64,
        /// Postcard's error.
        source: postcard::Error,
    },
    /// A frame decoded but left bytes unread: the record type does not match the file.
    #[error("{path}: frame at byte {offset} decodes with {extra} bytes left over: wrong record type?")]
    TrailingBytes {
        /// The file.
        path: PathBuf,
        /// Offset of the frame in the file, bytes.
        offset: u64,
        /// Bytes left, bytes.
        extra: usize,
    },
    /// A file's header disagrees with the run's first file or with its own name.
    #[error("{path}: header field {field} does not match the run")]
    HeaderMismatch {
        /// The file.
        path: PathBuf,
        /// Which header field.
        field: &'static str,
    },
    /// The directory holds no recording file.
    #[error("no recording files (fulcrumd-*.rec) in {dir}")]
    NoRecordings {
        /// The directory.
        dir: PathBuf,
    },
    /// The directory holds several runs: pick one with [`RecordingReader::open_run`].
    #[error("{dir} holds {} runs ({}): open one with its run id", run_ids.len(), hex_list(run_ids))]
    MultipleRuns {
        /// The directory.
        dir: PathBuf,
        /// Run ids found.
        run_ids: Vec<u64>,
    },
}

fn hex_list(ids: &[u64]) -> String {
    ids.iter().map(|id| format!("{id:016x}")).collect::<Vec<_>>().join(", ")
}

/// An incomplete frame at the end of a file: what a crash (or a failed write) leaves. The reader
/// returns the records before it and goes on with the next file of the run.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Truncation {
    /// The file.
    pub path: PathBuf,
    /// Offset of the incomplete frame (or 0 for an incomplete magic/version), bytes.
    pub offset: u64,
    /// Bytes of the incomplete frame present in the file (ignored), bytes.
    pub partial_bytes: u64,
    /// Bytes missing to complete the frame, when its length field was complete, bytes.
    pub missing_bytes: Option<u64>,
}

/// The files of one run in a directory.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RunFiles {
    /// The run id, from the file names.
    pub run_id: u64,
    /// (file index, path), by increasing index.
    pub files: Vec<(u32, PathBuf)>,
}

/// Lists the runs in `dir` (files named like [`file_name`]), by increasing run id.
pub fn list_runs(dir: &Path) -> Result<Vec<RunFiles>, ReadError> {
    let io_err = |source| ReadError::Io { path: dir.to_owned(), source };
    let mut runs: BTreeMap<u64, Vec<(u32, PathBuf)>> = BTreeMap::new();
    for entry in fs::read_dir(dir).map_err(io_err)? {
        let entry = entry.map_err(io_err)?;
        let name = entry.file_name();
        if let Some((run, index)) = name.to_str().and_then(parse_file_name) {
            runs.entry(run).or_default().push((index, entry.path()));
        }
    }
    Ok(runs
        .into_iter()
        .map(|(run_id, mut files)| {
            files.sort();
            RunFiles { run_id, files }
        })
        .collect())
}

/// A whole recording read into memory by [`RecordingReader::read_all`].
#[derive(Clone, Debug, PartialEq)]
pub struct Recording<T> {
    /// Header of the first readable file.
    pub header: Option<RecordingHeader>,
    /// Every record, in order.
    pub records: Vec<T>,
    /// Incomplete frames met (normally at most one, at the end of the last file).
    pub truncations: Vec<Truncation>,
}

/// One file read into memory.
struct FileCursor {
    path: PathBuf,
    data: Vec<u8>,
    pos: usize,
}

enum Frame<'a> {
    End,
    Whole { payload: &'a [u8], next: usize },
    Cut(Truncation),
}

/// Iterates over the records of one file or of a run's files, in order. Yields `Err` once (at a
/// corrupt frame, a bad header...) and then ends: nothing is skipped silently.
pub struct RecordingReader<T> {
    files: Vec<PathBuf>,
    next_file: usize,
    current: Option<FileCursor>,
    header: Option<RecordingHeader>,
    truncations: Vec<Truncation>,
    failed: bool,
    _marker: PhantomData<fn() -> T>,
}

impl<T: DeserializeOwned> RecordingReader<T> {
    /// Reads one file.
    pub fn open(path: &Path) -> Result<Self, ReadError> {
        Self::from_files(vec![path.to_owned()])
    }

    /// Reads every file of the only run in `dir`, oldest first.
    pub fn open_dir(dir: &Path) -> Result<Self, ReadError> {
        let mut runs = list_runs(dir)?;
        match runs.len() {
            0 => Err(ReadError::NoRecordings { dir: dir.to_owned() }),
            1 => Self::from_run(runs.remove(0)),
            _ => Err(ReadError::MultipleRuns { dir: dir.to_owned(), run_ids: runs.iter().map(|r| r.run_id).collect() }),
        }
    }

    /// Reads every file of run `run_id` in `dir`, oldest first.
    pub fn open_run(dir: &Path, run_id: u64) -> Result<Self, ReadError> {
        let run = list_runs(dir)?
            .into_iter()
            .find(|r| r.run_id == run_id)
            .ok_or_else(|| ReadError::NoRecordings { dir: dir.to_owned() })?;
        Self::from_run(run)
    }

    fn from_run(run: RunFiles) -> Result<Self, ReadError> {
        Self::from_files(run.files.into_iter().map(|(_, p)| p).collect())
    }

    fn from_files(files: Vec<PathBuf>) -> Result<Self, ReadError> {
        let mut reader = Self {
            files,
            next_file: 0,
            current: None,
            header: None,
            truncations: Vec::new(),
            failed: false,
            _marker: PhantomData,
        };
        // Load the first file now, so that a bad magic or version is an error of `open`.
        reader.load_next()?;
        Ok(reader)
    }

    /// Header of the first file with a readable header (`None` if none had one yet).
    pub fn header(&self) -> Option<&RecordingHeader> {
        self.header.as_ref()
    }

    /// Incomplete frames met so far.
    pub fn truncations(&self) -> &[Truncation] {
        &self.truncations
    }

    /// Reads every remaining record.
    pub fn read_all(mut self) -> Result<Recording<T>, ReadError> {
        let mut records = Vec::new();
        for r in &mut self {
            records.push(r?);
        }
        Ok(Recording { header: self.header, records, truncations: self.truncations })
    }

    /// Opens the next file into `current` (or leaves it `None` when there is none, or when the
    /// file's preamble is cut: that is recorded as a truncation).
    fn load_next(&mut self) -> Result<(), ReadError> {
        self.current = None;
        let Some(path) = self.files.get(self.next_file).cloned() else { return Ok(()) };
        self.next_file += 1;
        let data = fs::read(&path).map_err(|source| ReadError::Io { path: path.clone(), source })?;
        if data.len() < PREAMBLE_BYTES {
            let n = data.len().min(MAGIC.len());
            if data[..n] != MAGIC[..n] {
                return Err(ReadError::NotARecording { path });
            }
            let missing = (PREAMBLE_BYTES - data.len()) as u64;
            self.truncations.push(Truncation {
                path,
                offset: 0,
                partial_bytes: data.len() as u64,
                missing_bytes: Some(missing),
            });
            return Ok(());
        }
        if data[..MAGIC.len()] != MAGIC[..] {
            return Err(ReadError::NotARecording { path });
        }
        let version = u16::from_le_bytes([data[MAGIC.len()], data[MAGIC.len() + 1]]);
        if version != FORMAT_VERSION {
            return Err(ReadError::UnsupportedVersion { path, found: version, supported: FORMAT_VERSION });
        }
        let (header, next) =
            match parse_frame(&path, &data, PREAMBLE_BYTES)? {
                Frame::End => {
                    let t = Truncation { path, offset: PREAMBLE_BYTES as u64, partial_bytes: 0, missing_bytes: None };
                    self.truncations.push(t);
                    return Ok(());
                }
                Frame::Cut(t) => {
                    self.truncations.push(t);
                    return Ok(());
                }
                Frame::Whole { payload, next } => {
                    let header = postcard::from_bytes::<RecordingHeader>(payload).map_err(|source| {
                        ReadError::Decode { path: path.clone(), offset: PREAMBLE_BYTES as u64, source }
                    })?;
                    (header, next)
                }
            };
        if let Some((run, index)) = path.file_name().and_then(|n| n.to_str()).and_then(parse_file_name) {
            if run != header.run_id {
                return Err(ReadError::HeaderMismatch { path, field: "run_id" });
            }
            if index != header.file_index {
                return Err(ReadError::HeaderMismatch { path, field: "file_index" });
            }
        }
        match &self.header {
            Some(first) if first.run_id != header.run_id => {
                return Err(ReadError::HeaderMismatch { path, field: "run_id" });
            }
            Some(first) if first.record_kind != header.record_kind => {
                return Err(ReadError::HeaderMismatch { path, field: "record_kind" });
            }
            Some(_) => {}
            None => self.header = Some(header),
        }
        self.current = Some(FileCursor { path, data, pos: next });
        Ok(())
    }

    fn next_record(&mut self) -> Option<Result<T, ReadError>> {
        loop {
            let Some(cur) = &mut self.current else {
                if self.next_file >= self.files.len() {
                    return None;
                }
                if let Err(e) = self.load_next() {
                    return Some(Err(e));
                }
                continue;
            };
            let offset = cur.pos;
            // Turn the borrowed frame into an owned outcome before touching `self`.
            let outcome = match parse_frame(&cur.path, &cur.data, offset) {
                Err(e) => return Some(Err(e)),
                Ok(Frame::End) => None,
                Ok(Frame::Cut(t)) => Some(Err(t)),
                Ok(Frame::Whole { payload, next }) => {
                    let result = match postcard::take_from_bytes::<T>(payload) {
                        Ok((rec, [])) => Ok(rec),
                        Ok((_, rest)) => Err(ReadError::TrailingBytes {
                            path: cur.path.clone(),
                            offset: offset as u64,
                            extra: rest.len(),
                        }),
                        Err(source) => Err(ReadError::Decode { path: cur.path.clone(), offset: offset as u64, source }),
                    };
                    Some(Ok((result, next)))
                }
            };
            match outcome {
                None => self.current = None,
                Some(Err(t)) => {
                    self.truncations.push(t);
                    self.current = None;
                }
                Some(Ok((result, next))) => {
                    cur.pos = next;
                    return Some(result);
                }
            }
        }
    }
}

impl<T: DeserializeOwned> Iterator for RecordingReader<T> {
    type Item = Result<T, ReadError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.failed {
            return None;
        }
        let item = self.next_record();
        if matches!(item, Some(Err(_))) {
            self.failed = true;
        }
        item
    }
}

/// Parses the frame at `pos` of `data`.
fn parse_frame<'a>(path: &Path, data: &'a [u8], pos: usize) -> Result<Frame<'a>, ReadError> {
    let rest = &data[pos.min(data.len())..];
    if rest.is_empty() {
        return Ok(Frame::End);
    }
    let cut = |missing: Option<usize>| {
        Frame::Cut(Truncation {
            path: path.to_owned(),
            offset: pos as u64,
            partial_bytes: rest.len() as u64,
            missing_bytes: missing.map(|m| m as u64),
        })
    };
    let Some((len_bytes, after_len)) = rest.split_first_chunk::<4>() else { return Ok(cut(None)) };
    let length = u32::from_le_bytes(*len_bytes);
    if length == 0 && after_len.iter().all(|&b| b == 0) {
        // A zero-filled tail: blocks allocated but never written before a power loss.
        return Ok(cut(None));
    }
    if length > MAX_FRAME_PAYLOAD_BYTES {
        return Err(ReadError::BadFrameLength { path: path.to_owned(), offset: pos as u64, length });
    }
    let need = length as usize + FRAME_OVERHEAD_BYTES;
    if rest.len() < need {
        return Ok(cut(Some(need - rest.len())));
    }
    let payload = &after_len[..length as usize];
    let mut crc_bytes = [0u8; 4];
    crc_bytes.copy_from_slice(&after_len[length as usize..length as usize + 4]);
    let stored = u32::from_le_bytes(crc_bytes);
    let computed = crc32fast::hash(payload);
    if stored != computed {
        return Err(ReadError::CorruptFrame { path: path.to_owned(), offset: pos as u64, stored, computed });
    }
    Ok(Frame::Whole { payload, next: pos + need })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
    struct Rec {
        seq: u64,
        x: f64,
    }

    fn cfg(dir: &Path) -> RecorderConfig {
        RecorderConfig { dir: dir.to_owned(), flush_interval_ms: 10, retry_interval_ms: 10, ..Default::default() }
    }

    #[test]
    fn file_names_round_trip_and_sort_by_index() {
        assert_eq!(file_name(0xabc, 7), "fulcrumd-0000000000000abc-0007.rec");
        assert_eq!(parse_file_name("fulcrumd-0000000000000abc-0007.rec"), Some((0xabc, 7)));
        assert_eq!(parse_file_name(&file_name(u64::MAX, 12345)), Some((u64::MAX, 12345)));
        assert_eq!(parse_file_name("fulcrumd-abc-0007.rec"), None);
        assert_eq!(parse_file_name("fulcrumd-0000000000000abc-07.rec"), None);
        assert_eq!(parse_file_name("other-0000000000000abc-0007.rec"), None);
    }

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

    #[test]
    fn queue_layout_is_two_counters_and_the_buffer() {
        // `QueueStorage::allocate` relies on heapless 0.9's queue being exactly head, tail and
        // the slot array (all valid when zeroed): a new field would change the size.
        fn expected<T, const N: usize>() -> usize {
            let align = std::mem::align_of::<Queue<T, N>>();
            (2 * std::mem::size_of::<usize>() + N * std::mem::size_of::<T>()).next_multiple_of(align)
        }
        assert_eq!(std::mem::size_of::<Queue<u8, 5>>(), expected::<u8, 5>());
        assert_eq!(std::mem::size_of::<Queue<u64, 4096>>(), expected::<u64, 4096>());
        assert_eq!(std::mem::size_of::<Queue<[f64; 7], 64>>(), expected::<[f64; 7], 64>());
        assert_eq!(std::mem::size_of::<Queue<u128, 8>>(), expected::<u128, 8>());
    }

    #[test]
    fn zeroed_queue_behaves_like_a_new_one() {
        // The allocation trick of `QueueStorage`: an all-zero queue must be empty, hold N-1
        // items and wrap around correctly.
        let storage = Arc::new(QueueStorage::<u32, 4>::allocate().unwrap());
        let (mut p, mut c) = unsafe { storage.split() };
        assert_eq!(c.capacity(), 3);
        assert!(c.dequeue().is_none());
        for round in 0..10u32 {
            for i in 0..3 {
                assert!(p.enqueue(round * 10 + i).is_ok());
            }
            assert!(p.enqueue(99).is_err(), "a full queue refuses");
            for i in 0..3 {
                assert_eq!(c.dequeue(), Some(round * 10 + i));
            }
        }
    }

    #[test]
    fn header_frame_is_self_contained() {
        let dir = tempfile::tempdir().unwrap();
        let run = RunInfo { record_kind: "test.v1".into(), run_id: 0x1234, config_toml: "a = 1\n".into() };
        let (mut p, h) = start::<Rec, 16>(&cfg(dir.path()), run).unwrap();
        assert!(p.push(Rec { seq: 1, x: 0.5 }));
        let stats = h.shutdown().unwrap();
        assert_eq!(stats.written, 1);
        let path = dir.path().join(file_name(0x1234, 0));
        let bytes = fs::read(&path).unwrap();
        assert_eq!(&bytes[..10], b"COMANIPREC");
        assert_eq!(u16::from_le_bytes([bytes[10], bytes[11]]), FORMAT_VERSION);
        let len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
        let header: RecordingHeader = postcard::from_bytes(&bytes[16..16 + len]).unwrap();
        assert_eq!(header.record_kind, "test.v1");
        assert_eq!(header.run_id, 0x1234);
        assert_eq!(header.config_toml, "a = 1\n");
        assert_eq!(header.file_index, 0);
        assert_eq!(stats.bytes_written, bytes.len() as u64);
        let crc = u32::from_le_bytes(bytes[16 + len..20 + len].try_into().unwrap());
        assert_eq!(crc, crc32fast::hash(&bytes[16..16 + len]));
        let r = RecordingReader::<Rec>::open(&path).unwrap().read_all().unwrap();
        assert_eq!(r.records, vec![Rec { seq: 1, x: 0.5 }]);
        assert_eq!(r.header.unwrap().run_id, 0x1234);
    }

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
