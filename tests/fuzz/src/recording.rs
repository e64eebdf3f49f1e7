//! Flight-recording files: framing, CRC, truncation, version skew, the header's embedded
//! configuration, and the replay of the records through the pipeline.

use std::path::PathBuf;

use controller::recorder::RecordingReader;
use controller::replay::replay_recording;
use controller::rt_loop::CycleRecord;

thread_local! {
    /// A file of this process and thread (the reader reads files, not bytes).
    static PATH: PathBuf = std::env::temp_dir().join(format!(
        "comanip-fuzz-{}-{:?}.rec",
        std::process::id(),
        std::thread::current().id()
    ).replace(['(', ')'], ""));
}

/// Writes `data` as a recording file and reads it back as fulcrumd's `cycle` records, then
/// replays it; panics when a reader panics or when the two disagree on whether the file reads.
pub fn run(data: &[u8]) {
    PATH.with(|path| {
        if std::fs::write(path, data).is_err() {
            return; // no temporary directory: nothing to test
        }
        let read = RecordingReader::<CycleRecord>::open(path).and_then(|r| r.read_all());
        let replayed = replay_recording(path);
        if let Ok(replay) = &replayed {
            // What the replay read, the reader read too.
            let Ok(recording) = &read else {
                panic!("the replay read a file the reader refuses: {read:?}");
            };
            assert_eq!(replay.records, recording.records.len() as u64);
            assert!(replay.identical + replay.mismatches <= replay.records);
        }
        let _ = std::fs::remove_file(path);
    });
}
