//! The writer thread: drains the queue, encodes and frames each record, writes blocks, rotates
//! files and keeps the run within its size limit.

use std::collections::VecDeque;
use std::fs::{self, File, OpenOptions};
use std::io::{self, Write};
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::thread;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use heapless::spsc::Consumer;
use serde::Serialize;

use super::config::RecorderConfig;
use super::header::{RecordingHeader, RunInfo, file_name};
use super::queue::Control;
use super::stats::{RecorderStats, RecorderStatsSnapshot, add};
use super::{FORMAT_VERSION, FRAME_OVERHEAD_BYTES, MAGIC, PREAMBLE_BYTES};

/// Size of the writer's block buffer, bytes: frames are handed to the kernel in blocks of at most this.
const WRITE_BUFFER_BYTES: usize = 64 * 1024;
/// How long the writer sleeps when the queue is empty.
const DRAIN_INTERVAL: Duration = Duration::from_millis(5);
/// Smallest interval between two warnings of the same kind from the writer.
const WARN_INTERVAL: Duration = Duration::from_secs(1);

pub(super) struct Writer<T: 'static> {
    // Field order matters: the queue half must drop before `_storage`.
    pub(super) queue: Consumer<'static, T>,
    pub(super) sink: Sink,
    pub(super) control: Arc<Control>,
    pub(super) _storage: Arc<dyn Send + Sync>,
}

impl<T: Serialize + Copy + Send + 'static> Writer<T> {
    pub(super) fn run(mut self) {
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
pub(super) struct Sink {
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
    pub(super) fn new(cfg: RecorderConfig, run: RunInfo, stats: Arc<RecorderStats>, enc_payload: usize) -> Self {
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
    pub(super) fn preamble(&self, index: u32) -> Result<Vec<u8>, postcard::Error> {
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
    pub(super) fn open_next(&mut self) -> Result<PathBuf, (PathBuf, io::Error)> {
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
    pub(super) fn close_current(&mut self) {
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

#[cfg(test)]
mod tests {
    use std::fs;

    use super::super::*;
    use crate::recorder::test_support::{Rec, cfg};

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
}
