//! candump logs: the line parser, the reader, the replay bus and the replay cutter
//! (`controller::replay::replay_candump_reader`, which cuts a log into cycles at its SYNCs).

use std::io::Cursor;
use std::time::Duration;

use controller::config::Config;
use controller::replay::replay_candump_reader;
use hw_io::can::candump::{CandumpReader, CandumpWriter, parse_line};
use hw_io::can::{CanBus, Pacing, ReplayBus};

/// Feeds `data` as a candump log to every reader; panics when one panics, when a parsed record
/// does not write back and re-parse to the same frame, or when a cut cycle breaks the output
/// invariants ([`crate::acquisition::check_output`]).
pub fn run(data: &[u8]) {
    // The line parser, and the writer's round trip of every record it accepts.
    if let Ok(text) = std::str::from_utf8(data) {
        for line in text.lines() {
            if let Ok(Some(rec)) = parse_line(line) {
                let frame = rec.timed.frame;
                assert!(frame.dlc() <= 8);
                let Ok(mut w) = CandumpWriter::new(Vec::new(), rec.interface) else { continue };
                assert!(w.write(&rec.timed).is_ok());
                let written = w.into_inner();
                let Ok(back) = std::str::from_utf8(&written) else {
                    panic!("the writer wrote non-UTF-8");
                };
                match parse_line(back.trim_end()) {
                    Ok(Some(again)) => assert_eq!(again.timed, rec.timed, "{line:?} wrote {back:?}"),
                    other => panic!("{line:?} wrote {back:?}, which reads as {other:?}"),
                }
            }
        }
    }
    // The streaming reader: ends or errs, never loops.
    let mut reader = CandumpReader::new(Cursor::new(data));
    let mut records = 0u64;
    while let Ok(Some(_)) = reader.next_record() {
        records += 1;
        assert!(records <= data.len() as u64, "more records than bytes");
    }
    // The replay bus hands out every frame once, then ends.
    if let Ok(mut bus) = ReplayBus::from_reader(Cursor::new(data), Pacing::AsFastAsPossible) {
        let n = bus.remaining();
        let mut got = 0usize;
        while let Ok(Some(_)) = bus.recv_timeout(Duration::ZERO) {
            got += 1;
            assert!(got <= n, "the replay bus handed out more frames than it read");
        }
        assert_eq!(got, n);
    }
    // The cutter with the default pipeline.
    let cfg = Config::default();
    if let Ok(replay) = replay_candump_reader(Cursor::new(data), &cfg) {
        for c in &replay.cycles {
            crate::acquisition::check_output(&cfg, &c.input, &c.output);
        }
    }
}
