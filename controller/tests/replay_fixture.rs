//! A flight recording written by an older fulcrumd (`tests/fixtures/cycle-v1/`, see its README)
//! still reads and replays bit for bit: the postcard encoding of `CycleRecord` (and so of
//! `CycleOutput`'s state and health) must not change under a refactoring of the types.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::path::{Path, PathBuf};
use std::process::Command;

use controller::recorder::{MAGIC, PREAMBLE_BYTES, ReadError, RecordingReader};
use controller::replay::{self, load_recording};
use controller::rt_loop::CycleRecord;
use hw_io::ipc::{HealthFlags, OutputState};

fn fixture_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/cycle-v1")
}

fn fixture_file() -> PathBuf {
    let mut files: Vec<PathBuf> = std::fs::read_dir(fixture_dir())
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "rec"))
        .collect();
    assert_eq!(files.len(), 1, "one recording file in the fixture: {files:?}");
    files.pop().unwrap()
}

/// The payloads of every frame of a recording file (header first), by the file layout of
/// `docs/recorder.md`: magic, version, then `[len u32 LE][payload][crc u32 LE]` frames.
fn frame_payloads(bytes: &[u8]) -> Vec<&[u8]> {
    assert_eq!(&bytes[..MAGIC.len()], MAGIC);
    let mut at = PREAMBLE_BYTES;
    let mut out = Vec::new();
    while at < bytes.len() {
        let len = u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap()) as usize;
        let payload = &bytes[at + 4..at + 4 + len];
        let crc = u32::from_le_bytes(bytes[at + 4 + len..at + 8 + len].try_into().unwrap());
        assert_eq!(crc, crc32fast::hash(payload), "frame at byte {at}");
        out.push(payload);
        at += 8 + len;
    }
    out
}

#[test]
fn the_old_recording_replays_bit_for_bit() {
    let r = replay::replay_recording(&fixture_dir()).unwrap();
    assert_eq!(r.records, 3600, "{r:?}");
    assert!(r.reproduced(), "{r:?}");
    assert_eq!(r.mismatches, 0);
}

#[test]
fn the_old_recording_covers_every_state_and_some_health_flags() {
    // What makes the bit-for-bit check above meaningful: the fixture holds invalid, outside and
    // inside cycles, and cycles with health flags set.
    let (_, _, records, truncations) = load_recording(&fixture_dir()).unwrap();
    assert!(truncations.is_empty(), "{truncations:?}");
    let count = |f: &dyn Fn(&CycleRecord) -> bool| records.iter().filter(|r| f(r)).count();
    assert!(count(&|r| r.output.state == OutputState::Invalid) > 0);
    assert!(count(&|r| r.output.state == OutputState::Outside) > 0);
    assert!(count(&|r| r.output.state == OutputState::Inside) > 0);
    assert!(count(&|r| !r.output.health.is_empty()) > 0);
    assert!(count(&|r| r.output.health.contains(HealthFlags::INCOMPLETE_CYCLE)) > 0);
    assert!(count(&|r| r.input.flags.contains(HealthFlags::OVERRUN)) > 0);
}

#[test]
fn every_record_reencodes_to_the_same_postcard_bytes() {
    let bytes = std::fs::read(fixture_file()).unwrap();
    let payloads = frame_payloads(&bytes);
    assert_eq!(payloads.len(), 3601, "header and 3600 records");
    for (i, p) in payloads[1..].iter().enumerate() {
        let (rec, rest): (CycleRecord, _) = postcard::take_from_bytes(p).unwrap();
        assert!(rest.is_empty(), "record {i}: {} bytes left over", rest.len());
        assert_eq!(rec.sequence, i as u64);
        assert_eq!(postcard::to_allocvec(&rec).unwrap(), *p, "record {i} re-encodes differently");
    }
}

#[test]
fn a_record_with_an_unknown_state_is_a_typed_read_error() {
    // The fixture's file with one record's state byte set to 7 (and its CRC fixed): the reader
    // must return `ReadError::Decode` at that frame, not panic.
    let mut bytes = std::fs::read(fixture_file()).unwrap();
    let (mut at, mut k) = (PREAMBLE_BYTES, 0);
    let frame_at = loop {
        let len = u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap()) as usize;
        if k == 1001 {
            break at;
        }
        at += 8 + len;
        k += 1;
    };
    let len = u32::from_le_bytes(bytes[frame_at..frame_at + 4].try_into().unwrap()) as usize;
    let payload = &bytes[frame_at + 4..frame_at + 4 + len];
    let rec: CycleRecord = postcard::from_bytes(payload).unwrap();
    // The output's state follows sequence, sync_ns and input: find its offset by re-encoding.
    let head = postcard::to_allocvec(&(rec.sequence, rec.sync_ns, rec.input)).unwrap().len();
    assert_eq!(payload[head], u8::try_from(u32::from(rec.output.state)).unwrap(), "the state byte");
    bytes[frame_at + 4 + head] = 7;
    let crc = crc32fast::hash(&bytes[frame_at + 4..frame_at + 4 + len]);
    bytes[frame_at + 4 + len..frame_at + 8 + len].copy_from_slice(&crc.to_le_bytes());
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(fixture_file().file_name().unwrap());
    std::fs::write(&path, &bytes).unwrap();
    match RecordingReader::<CycleRecord>::open(&path).unwrap().read_all() {
        Err(ReadError::Decode { offset, .. }) => assert_eq!(offset, frame_at as u64),
        other => panic!("expected a decode error, got {:?}", other.map(|r| r.records.len())),
    }
    let err = replay::replay_recording(&path).unwrap_err();
    assert!(err.to_string().contains("does not decode"), "{err}");
}

#[test]
fn fulcrumd_replay_reproduces_the_old_recording() {
    let out = Command::new(env!("CARGO_BIN_EXE_fulcrumd"))
        .args(["replay", "--recording"])
        .arg(fixture_dir())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{:?}\n{stdout}\n{}", out.status, String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("3600 records, 3600 identical, 0 mismatches"), "{stdout}");
}
