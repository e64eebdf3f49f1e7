//! Flight recorder, end to end through files on disk: round trip, rotation and the disk budget,
//! exact drop counts, corruption, truncation, bad files and disk errors.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::fs;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use controller::recorder::{
    self, ReadError, RecorderConfig, RecorderProducer, RecordingReader, RunInfo, StartError, Truncation,
};
use serde::{Deserialize, Serialize};

/// A record shaped like the daemon's cycle record.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
struct Cycle {
    seq: u64,
    t_ns: u64,
    q_rad: [f64; 6],
    state: u8,
    health: u32,
}

fn rec(seq: u64) -> Cycle {
    let x = seq as f64 * 1e-3;
    Cycle {
        seq,
        t_ns: 1_000_000 * seq + 17,
        q_rad: [x, -x, x.sin(), x.cos(), 0.5 * x, 1.0],
        state: (seq % 3) as u8,
        health: (seq % 7) as u32,
    }
}

fn config(dir: &Path) -> RecorderConfig {
    RecorderConfig { dir: dir.to_owned(), flush_interval_ms: 20, retry_interval_ms: 20, ..Default::default() }
}

fn run(id: u64) -> RunInfo {
    RunInfo { record_kind: "test.cycle.v1".into(), run_id: id, config_toml: "[loop]\nperiod_us = 1000\n".into() }
}

/// Pushes records `range`, retrying a refused push after a short sleep (as a test producer may);
/// returns the number of refusals.
fn push_range(p: &mut RecorderProducer<Cycle>, range: std::ops::Range<u64>) -> u64 {
    let mut refused = 0;
    for i in range {
        while !p.push(rec(i)) {
            refused += 1;
            std::thread::sleep(Duration::from_micros(200));
        }
    }
    refused
}

fn rec_files(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "rec"))
        .collect();
    v.sort();
    v
}

/// Offsets of the record frames of a file (after the magic, version and header frame).
fn frame_offsets(bytes: &[u8]) -> Vec<usize> {
    let mut pos = 12;
    let len = |p: usize| u32::from_le_bytes(bytes[p..p + 4].try_into().unwrap()) as usize;
    pos += 8 + len(pos); // header frame
    let mut v = Vec::new();
    while pos < bytes.len() {
        v.push(pos);
        pos += 8 + len(pos);
    }
    assert_eq!(pos, bytes.len(), "frames do not tile the file");
    v
}

/// Writes `n` records into a fresh single-file recording; returns its path.
fn write_small_recording(dir: &Path, n: u64) -> PathBuf {
    let (mut p, h) = recorder::start::<Cycle, 1024>(&config(dir), run(0xfeed)).unwrap();
    push_range(&mut p, 0..n);
    let s = h.shutdown().unwrap();
    assert_eq!(s.written, n);
    let files = rec_files(dir);
    assert_eq!(files.len(), 1);
    files[0].clone()
}

#[test]
fn round_trip_of_100_000_records() {
    let dir = tempfile::tempdir().unwrap();
    let (mut p, h) = recorder::start::<Cycle, 4096>(&config(dir.path()), run(0x0123_4567_89ab_cdef)).unwrap();
    assert_eq!(p.capacity(), 4095);
    let refused = push_range(&mut p, 0..100_000);
    let s = h.shutdown().unwrap();
    assert_eq!(s.pushed, 100_000);
    assert_eq!(s.dropped_queue_full, refused, "every refusal counted");
    assert_eq!((s.written, s.write_errors, s.encode_errors), (100_000, 0, 0));
    assert_eq!((s.files_opened, s.files_deleted, s.records_deleted), (1, 0, 0));
    let files = rec_files(dir.path());
    assert_eq!(files, vec![dir.path().join("fulcrumd-0123456789abcdef-0000.rec")]);
    assert_eq!(s.bytes_written, fs::metadata(&files[0]).unwrap().len());

    let r = RecordingReader::<Cycle>::open_dir(dir.path()).unwrap().read_all().unwrap();
    assert!(r.truncations.is_empty(), "{:?}", r.truncations);
    let h = r.header.unwrap();
    assert_eq!(h.record_kind, "test.cycle.v1");
    assert_eq!(h.run_id, 0x0123_4567_89ab_cdef);
    assert_eq!(h.config_toml, "[loop]\nperiod_us = 1000\n");
    assert_eq!(r.records.len(), 100_000);
    for (i, got) in r.records.iter().enumerate() {
        assert_eq!(*got, rec(i as u64));
    }
}

#[test]
fn rotation_respects_file_and_total_limits() {
    const MAX_FILE: u64 = 8192;
    const MAX_TOTAL: u64 = 5 * MAX_FILE;
    let dir = tempfile::tempdir().unwrap();
    let cfg = RecorderConfig { max_file_bytes: MAX_FILE, max_total_bytes: MAX_TOTAL, ..config(dir.path()) };
    let (mut p, h) = recorder::start::<Cycle, 256>(&cfg, run(7)).unwrap();

    // The budget must hold whenever the writer stands still. A watcher polling the directory
    // concurrently cannot check it: listing and sizing files is not atomic, so a file deleted
    // after it was sized and its successor created before the listing ends are both counted.
    // Pausing the writer between chunks gives exact snapshots; the chunk length (97, coprime
    // with the ~117 frames of a file) moves the snapshot through every phase of the rotation.
    let mut peak = 0u64;
    let mut snapshots = 0;
    for start in (0..20_000u64).step_by(97) {
        push_range(&mut p, start..(start + 97).min(20_000));
        assert!(h.set_writer_paused(true), "writer did not acknowledge the pause");
        let sizes: Vec<u64> = fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().metadata().unwrap().len()).collect();
        assert!(sizes.iter().all(|&b| b <= MAX_FILE), "{sizes:?}");
        peak = peak.max(sizes.iter().sum());
        snapshots += 1;
        assert!(h.set_writer_paused(false));
    }
    let s = h.shutdown().unwrap();
    assert!(peak <= MAX_TOTAL, "peak {peak} bytes over {snapshots} snapshots");
    assert!(peak > MAX_TOTAL - MAX_FILE, "the budget was never approached: peak {peak} bytes");

    let files = rec_files(dir.path());
    let sizes: Vec<u64> = files.iter().map(|f| fs::metadata(f).unwrap().len()).collect();
    assert!(sizes.iter().all(|&b| b <= MAX_FILE), "{sizes:?}");
    assert!(sizes.iter().sum::<u64>() <= MAX_TOTAL, "{sizes:?}");
    // Files are filled close to the limit before rotating (a frame is ~70 bytes).
    assert!(sizes[..sizes.len() - 1].iter().all(|&b| b > MAX_FILE - 200), "{sizes:?}");
    assert_eq!(s.written, 20_000);
    assert!(s.files_opened > 100, "{s:?}");
    assert_eq!(s.files_deleted, s.files_opened - files.len() as u64, "{s:?}");

    let r = RecordingReader::<Cycle>::open_dir(dir.path()).unwrap().read_all().unwrap();
    assert!(r.truncations.is_empty());
    assert_eq!(r.records.len() as u64, s.written - s.records_deleted, "{s:?}");
    // What remains is the newest part of the run, in order.
    assert_eq!(r.records[0].seq, s.records_deleted);
    assert!(r.records.iter().zip(s.records_deleted..).all(|(r, i)| *r == rec(i)));
    assert_eq!(r.header.unwrap().file_index as u64, s.files_deleted);

    // Each file stands alone.
    let last = RecordingReader::<Cycle>::open(files.last().unwrap()).unwrap();
    assert_eq!(last.header().unwrap().run_id, 7);
    assert_eq!(last.map(|r| r.unwrap().seq).max(), Some(19_999));
}

#[test]
fn queue_full_drops_are_counted_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let (mut p, h) = recorder::start::<Cycle, 8>(&config(dir.path()), run(8)).unwrap();
    assert_eq!(p.capacity(), 7);
    assert!(h.set_writer_paused(true), "writer did not acknowledge the pause");
    let accepted: Vec<bool> = (0..100).map(|i| p.push(rec(i))).collect();
    assert!(accepted[..7].iter().all(|&a| a) && accepted[7..].iter().all(|&a| !a), "{accepted:?}");
    let s = p.stats().snapshot();
    assert_eq!((s.pushed, s.dropped_queue_full, s.written), (7, 93, 0));
    assert!(h.set_writer_paused(false));
    // Once drained, there is room again.
    let t0 = Instant::now();
    while p.stats().snapshot().written < 7 {
        assert!(t0.elapsed() < Duration::from_secs(10), "writer does not drain");
        std::thread::sleep(Duration::from_millis(2));
    }
    assert!(p.push(rec(100)));
    let s = h.shutdown().unwrap();
    assert_eq!((s.pushed, s.dropped_queue_full, s.written, s.write_errors), (8, 93, 8, 0));
    assert!(!p.push(rec(101)), "push after shutdown accepted");
    assert_eq!(p.stats().snapshot().dropped_closed, 1);
    let seqs: Vec<u64> = RecordingReader::<Cycle>::open_dir(dir.path()).unwrap().map(|r| r.unwrap().seq).collect();
    assert_eq!(seqs, vec![0, 1, 2, 3, 4, 5, 6, 100]);
}

#[test]
fn corrupt_byte_is_a_crc_error_with_its_offset() {
    let dir = tempfile::tempdir().unwrap();
    let path = write_small_recording(dir.path(), 1000);
    let mut bytes = fs::read(&path).unwrap();
    let offsets = frame_offsets(&bytes);
    assert_eq!(offsets.len(), 1000);
    let at = offsets[500];
    bytes[at + 4 + 10] ^= 0x20;
    fs::write(&path, &bytes).unwrap();

    let mut reader = RecordingReader::<Cycle>::open(&path).unwrap();
    for i in 0..500 {
        assert_eq!(reader.next().unwrap().unwrap(), rec(i));
    }
    match reader.next() {
        Some(Err(ReadError::CorruptFrame { path: p, offset, stored, computed })) => {
            assert_eq!(p, path);
            assert_eq!(offset, at as u64);
            assert_ne!(stored, computed);
        }
        other => panic!("expected a CRC error, got {other:?}"),
    }
    assert!(reader.next().is_none(), "the reader skipped past a corrupt frame");
    let msg = RecordingReader::<Cycle>::open(&path).unwrap().read_all().unwrap_err().to_string();
    assert!(msg.contains(&format!("byte {at}")) && msg.contains("fulcrumd-"), "{msg}");
}

#[test]
fn impossible_frame_length_is_corrupt_not_truncated() {
    let dir = tempfile::tempdir().unwrap();
    let path = write_small_recording(dir.path(), 100);
    let mut bytes = fs::read(&path).unwrap();
    let at = frame_offsets(&bytes)[40];
    bytes[at..at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
    fs::write(&path, &bytes).unwrap();
    let err = RecordingReader::<Cycle>::open(&path).unwrap().read_all().unwrap_err();
    assert!(matches!(err, ReadError::BadFrameLength { offset, length: u32::MAX, .. } if offset == at as u64), "{err}");
}

#[test]
fn truncated_final_frame_is_a_non_fatal_truncation() {
    let dir = tempfile::tempdir().unwrap();
    let path = write_small_recording(dir.path(), 1000);
    let bytes = fs::read(&path).unwrap();
    let last = *frame_offsets(&bytes).last().unwrap();
    let frame_len = bytes.len() - last;

    // Cut in the payload: the frame's length is known, so are the missing bytes.
    fs::write(&path, &bytes[..bytes.len() - 5]).unwrap();
    let r = RecordingReader::<Cycle>::open(&path).unwrap().read_all().unwrap();
    assert_eq!(r.records.len(), 999);
    assert_eq!(r.records[998], rec(998));
    assert_eq!(
        r.truncations,
        vec![Truncation {
            path: path.clone(),
            offset: last as u64,
            partial_bytes: (frame_len - 5) as u64,
            missing_bytes: Some(5)
        }]
    );

    // Cut in the length field: the missing size is unknown.
    fs::write(&path, &bytes[..last + 2]).unwrap();
    let r = RecordingReader::<Cycle>::open(&path).unwrap().read_all().unwrap();
    assert_eq!(r.records.len(), 999);
    assert_eq!(r.truncations[0].missing_bytes, None);
    assert_eq!(r.truncations[0].partial_bytes, 2);

    // A zero-filled tail (power loss after the size grew) is a truncation too.
    let mut zeros = bytes.clone();
    zeros.extend_from_slice(&[0u8; 4096]);
    fs::write(&path, &zeros).unwrap();
    let r = RecordingReader::<Cycle>::open(&path).unwrap().read_all().unwrap();
    assert_eq!(r.records.len(), 1000);
    assert_eq!(r.truncations.len(), 1);
    assert_eq!(r.truncations[0].offset, bytes.len() as u64);

    // A file cut inside its magic: nothing to read, one truncation, no error.
    fs::write(&path, b"COMANI").unwrap();
    let r = RecordingReader::<Cycle>::open(&path).unwrap().read_all().unwrap();
    assert!(r.records.is_empty() && r.header.is_none());
    assert_eq!(r.truncations.len(), 1);
}

#[test]
fn wrong_magic_and_unsupported_version_are_typed_errors() {
    let dir = tempfile::tempdir().unwrap();
    let path = write_small_recording(dir.path(), 10);
    let good = fs::read(&path).unwrap();

    let other = dir.path().join("notes.txt");
    fs::write(&other, b"this is not a recording at all").unwrap();
    let e = RecordingReader::<Cycle>::open(&other).err().unwrap();
    assert!(matches!(&e, ReadError::NotARecording { path } if *path == other), "{e}");
    fs::write(&other, b"NOT").unwrap();
    assert!(matches!(RecordingReader::<Cycle>::open(&other), Err(ReadError::NotARecording { .. })));

    let mut v2 = good.clone();
    v2[10..12].copy_from_slice(&2u16.to_le_bytes());
    fs::write(&path, &v2).unwrap();
    let e = RecordingReader::<Cycle>::open(&path).err().unwrap();
    assert!(matches!(e, ReadError::UnsupportedVersion { found: 2, supported: 1, .. }), "{e}");

    // A record type that does not match the file is reported, not misread.
    fs::write(&path, &good).unwrap();
    let e = RecordingReader::<(u8, u8)>::open(&path).unwrap().read_all().unwrap_err();
    assert!(matches!(e, ReadError::TrailingBytes { .. }), "{e}");

    // Several runs in one directory: open_dir asks for a run id.
    let (mut p, h) = recorder::start::<Cycle, 16>(&config(dir.path()), run(0xbeef)).unwrap();
    push_range(&mut p, 0..3);
    h.shutdown().unwrap();
    let e = RecordingReader::<Cycle>::open_dir(dir.path()).err().unwrap();
    assert!(matches!(&e, ReadError::MultipleRuns { run_ids, .. } if run_ids == &vec![0xbeef, 0xfeed]), "{e}");
    let r = RecordingReader::<Cycle>::open_run(dir.path(), 0xbeef).unwrap().read_all().unwrap();
    assert_eq!(r.records.len(), 3);
    let empty = tempfile::tempdir().unwrap();
    assert!(matches!(RecordingReader::<Cycle>::open_dir(empty.path()), Err(ReadError::NoRecordings { .. })));
}

#[test]
fn unwritable_directory_is_a_typed_error_at_start() {
    // Root ignores permission bits: use a path below a regular file instead.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("plain-file");
    fs::write(&file, b"x").unwrap();
    let cfg = config(&file.join("recordings"));
    match recorder::start::<Cycle, 16>(&cfg, run(1)) {
        Err(e @ StartError::CreateDir { .. }) => assert!(e.to_string().contains("recorder.dir"), "{e}"),
        Err(e) => panic!("wrong error: {e}"),
        Ok(_) => panic!("started in an impossible directory"),
    }
    // The first file cannot be created (its name is taken): typed error naming the file.
    let taken = dir.path().join(recorder::file_name(2, 0));
    fs::create_dir(&taken).unwrap();
    match recorder::start::<Cycle, 16>(&config(dir.path()), run(2)) {
        Err(StartError::CreateFile { path, .. }) => assert_eq!(path, taken),
        Err(e) => panic!("wrong error: {e}"),
        Ok(_) => panic!("started over an existing file"),
    }
    // Invalid configuration: typed error naming the key.
    let bad = RecorderConfig { max_file_bytes: 10, ..config(dir.path()) };
    let e = recorder::start::<Cycle, 16>(&bad, run(3)).err().unwrap();
    assert!(matches!(e, StartError::Config(_)) && e.to_string().contains("recorder.max_file_bytes"), "{e}");
}

/// Waits until the writer has taken every pushed record.
fn wait_drained(p: &RecorderProducer<Cycle>) {
    let t0 = Instant::now();
    loop {
        let s = p.stats().snapshot();
        if s.written + s.write_errors + s.encode_errors == s.pushed {
            return;
        }
        assert!(t0.elapsed() < Duration::from_secs(20), "writer stuck: {s:?}");
        std::thread::sleep(Duration::from_millis(5));
    }
}

#[test]
fn directory_replaced_mid_run_counts_write_errors_and_recovers() {
    let root = tempfile::tempdir().unwrap();
    let dir = root.path().join("rec");
    let cfg = RecorderConfig { max_file_bytes: 8192, max_total_bytes: 1 << 20, ..config(&dir) };
    let (mut p, h) = recorder::start::<Cycle, 256>(&cfg, run(9)).unwrap();
    push_range(&mut p, 0..1000);
    wait_drained(&p);
    assert_eq!(p.stats().snapshot().write_errors, 0);

    // An operator replaces the directory with a file: new files cannot be opened.
    fs::remove_dir_all(&dir).unwrap();
    fs::write(&dir, b"in the way").unwrap();
    push_range(&mut p, 1000..3000);
    wait_drained(&p);
    let during = p.stats().snapshot();
    assert!(during.write_errors > 0, "{during:?}");

    // The obstacle goes: the writer re-creates the directory and records again.
    fs::remove_file(&dir).unwrap();
    std::thread::sleep(Duration::from_millis(50));
    push_range(&mut p, 3000..4000);
    let s = h.shutdown().expect("the writer survived");
    assert_eq!(s.pushed, 4000);
    assert_eq!(s.written + s.write_errors, 4000, "{s:?}");
    let r = RecordingReader::<Cycle>::open_dir(&dir).unwrap().read_all().unwrap();
    assert!(!r.records.is_empty());
    assert_eq!(r.records.last().unwrap().seq, 3999);
    assert!(r.records.windows(2).all(|w| w[0].seq < w[1].seq));
}

/// Child of `file_size_limit_write_errors_are_counted_not_fatal`: RLIMIT_FSIZE makes every file
/// fail past 32 KiB (EFBIG; SIGXFSZ ignored), as a full disk would.
#[test]
#[ignore = "run by file_size_limit_write_errors_are_counted_not_fatal in a child process"]
fn child_file_size_limit() {
    let Some(dir) = std::env::var_os("COMANIP_RECORDER_CHILD_DIR") else { return };
    const LIMIT: u64 = 32 * 1024;
    // SAFETY: installs SIG_IGN, no handler code.
    unsafe { nix::sys::signal::signal(nix::sys::signal::Signal::SIGXFSZ, nix::sys::signal::SigHandler::SigIgn) }
        .unwrap();
    nix::sys::resource::setrlimit(nix::sys::resource::Resource::RLIMIT_FSIZE, LIMIT, LIMIT).unwrap();
    let dir = PathBuf::from(dir);
    let cfg =
        RecorderConfig { max_file_bytes: 1 << 20, max_total_bytes: 64 << 20, retry_interval_ms: 5, ..config(&dir) };
    let (mut p, h) = recorder::start::<Cycle, 1024>(&cfg, run(10)).unwrap();
    for chunk in 0..10 {
        push_range(&mut p, chunk * 500..(chunk + 1) * 500);
        std::thread::sleep(Duration::from_millis(10));
    }
    let s = h.shutdown().expect("the writer survived");
    println!("child stats: {s:?}");
    assert_eq!(s.pushed, 5000);
    assert!(s.write_errors > 0, "{s:?}");
    assert!(s.files_opened >= 3, "{s:?}");
    assert_eq!(s.written + s.write_errors, s.pushed, "{s:?}");
    for f in rec_files(&dir) {
        assert!(fs::metadata(&f).unwrap().len() <= LIMIT);
    }
    // Every file ends in a cut frame where the limit struck; the reader reports, not fails.
    let r = RecordingReader::<Cycle>::open_dir(&dir).unwrap().read_all().unwrap();
    assert!(!r.truncations.is_empty());
    assert_eq!(r.records.len() as u64, s.written, "records on disk = records counted written");
    assert!(r.records.windows(2).all(|w| w[0].seq < w[1].seq));
}

#[test]
fn file_size_limit_write_errors_are_counted_not_fatal() {
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(std::env::current_exe().unwrap())
        .args(["--exact", "child_file_size_limit", "--ignored", "--nocapture"])
        .env("COMANIP_RECORDER_CHILD_DIR", dir.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "child failed ({}):\n{stdout}\n{stderr}", out.status);
    assert!(stdout.contains("1 passed") && stdout.contains("child stats"), "child did not run:\n{stdout}");
    assert!(!rec_files(dir.path()).is_empty());
}

/// Writes a stand-in file of `len` bytes for file `index` of an earlier run, last modified
/// `age_s` seconds ago.
fn old_file(dir: &Path, run_id: u64, index: u32, len: u64, age_s: u64) -> PathBuf {
    let path = dir.join(recorder::file_name(run_id, index));
    let f = fs::File::create(&path).unwrap();
    f.set_len(len).unwrap();
    f.set_modified(std::time::SystemTime::now() - Duration::from_secs(age_s)).unwrap();
    path
}

/// Starts and stops run 7 in `dir` with these budgets (bytes); its counters.
fn start_with_dir_limit(dir: &Path, max_total_bytes: u64, max_dir_bytes: u64) -> recorder::RecorderStatsSnapshot {
    let cfg = RecorderConfig { max_file_bytes: 64 * 1024, max_total_bytes, max_dir_bytes, ..config(dir) };
    let (_p, h) = recorder::start::<Cycle, 16>(&cfg, run(7)).unwrap();
    h.shutdown().unwrap()
}

#[test]
fn start_deletes_the_oldest_earlier_runs_beyond_max_dir_bytes() {
    const MIB: u64 = 1 << 20;
    let dir = tempfile::tempdir().unwrap();
    // Four earlier runs of 1 MiB each (two files each), oldest first; a foreign file.
    let mut runs = Vec::new();
    for (k, age) in [400u64, 300, 200, 100].into_iter().enumerate() {
        let id = 0x1000 + k as u64;
        runs.push(vec![old_file(dir.path(), id, 0, MIB / 2, age + 1), old_file(dir.path(), id, 1, MIB / 2, age)]);
    }
    let foreign = dir.path().join("notes.txt");
    fs::write(&foreign, vec![0u8; (4 * MIB) as usize]).unwrap();
    // Budget for earlier runs: 3 MiB − 1 MiB (this run) = 2 MiB → the two oldest go.
    let s = start_with_dir_limit(dir.path(), MIB, 3 * MIB);
    assert_eq!((s.old_runs_deleted, s.old_files_deleted, s.old_bytes_deleted), (2, 4, 2 * MIB));
    for f in runs[..2].iter().flatten() {
        assert!(!f.exists(), "{} should be deleted", f.display());
    }
    for f in runs[2..].iter().flatten() {
        assert!(f.exists(), "{} should be kept", f.display());
    }
    assert!(foreign.exists(), "files not named by the recorder are never touched");
}

#[test]
fn start_keeps_the_most_recent_earlier_run_even_over_budget() {
    const MIB: u64 = 1 << 20;
    let dir = tempfile::tempdir().unwrap();
    let older = old_file(dir.path(), 0xa, 0, MIB, 200);
    let crash = old_file(dir.path(), 0xb, 0, 5 * MIB, 100);
    let s = start_with_dir_limit(dir.path(), MIB, 2 * MIB);
    assert!(!older.exists());
    assert!(crash.exists(), "the run before this start is kept whatever its size");
    assert_eq!((s.old_runs_deleted, s.old_files_deleted), (1, 1));
}

#[test]
fn max_dir_bytes_must_hold_two_runs() {
    let cfg = RecorderConfig {
        max_file_bytes: 64 * 1024,
        max_total_bytes: 1 << 20,
        max_dir_bytes: (2 << 20) - 1,
        ..config(Path::new("/tmp"))
    };
    assert!(RecorderConfig { max_dir_bytes: 2 << 20, ..cfg.clone() }.validate().is_ok());
    let e = cfg.validate().unwrap_err();
    assert!(e.to_string().contains("recorder.max_dir_bytes"), "{e}");
}
