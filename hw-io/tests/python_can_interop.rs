//! The candump files we write are read by python-can's `can.CanutilsLogReader`, and the
//! files python-can's `can.CanutilsLogWriter` writes are read by our reader.
//!
//! Needs `python3` with python-can; the test installs it with pip if it is missing and
//! FAILS (never skips) if that does not work.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::path::{Path, PathBuf};
use std::process::Command;

use hw_io::can::candump::{CandumpReader, CandumpWriter, Direction};
use hw_io::can::{CanFrame, CanId, TimedFrame};

fn ensure_python_can() {
    let importable =
        || Command::new("python3").args(["-c", "import can"]).output().map(|o| o.status.success()).unwrap_or(false);
    if importable() {
        return;
    }
    let pip = Command::new("python3")
        .args(["-m", "pip", "install", "--quiet", "python-can"])
        .output()
        .unwrap_or_else(|e| panic!("python3 not runnable ({e}): this test needs python3 with python-can"));
    assert!(
        importable(),
        "python-can is not importable and `python3 -m pip install python-can` failed \
         (exit {:?}): {}{}\nInstall python-can (PyPI `python-can`) to run this test.",
        pip.status.code(),
        String::from_utf8_lossy(&pip.stdout),
        String::from_utf8_lossy(&pip.stderr)
    );
}

fn temp_path(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("hw-io-python-can-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn python(script: &str, file: &Path) -> String {
    let out = Command::new("python3").args(["-c", script]).arg(file).output().unwrap();
    assert!(out.status.success(), "python-can script failed: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}

fn frames() -> Vec<TimedFrame> {
    let f = |frame, unix_time_us| TimedFrame { frame, unix_time_us };
    vec![
        f(CanFrame::new_standard(0x080, &[1]).unwrap(), 1_699_999_999_123_456),
        f(CanFrame::new_standard(0x181, &[1, 2, 3, 4, 5, 6, 7, 8]).unwrap(), 1_699_999_999_123_500),
        f(CanFrame::new_standard(0x701, &[0x05]).unwrap(), 1_699_999_999_200_000),
        f(CanFrame::new_standard(0x082, &[0x10, 0x73, 0x81, 0, 0, 0, 0, 0xFF]).unwrap(), 1_700_000_000_000_001),
        f(CanFrame::new_standard(0x7FF, &[]).unwrap(), 1_700_000_000_000_002),
        f(CanFrame::new_extended(0x1234_5678, &[0xDE, 0xAD, 0xBE, 0xEF]).unwrap(), 1_700_000_000_000_003),
        f(CanFrame::new_extended(0x0000_0001, &[]).unwrap(), 1_700_000_000_000_004),
        f(CanFrame::new_remote(CanId::Standard(0x701), 1).unwrap(), 1_700_000_000_000_005),
        f(CanFrame::new_remote(CanId::Extended(0x1FFF_FFFF), 8).unwrap(), 1_700_000_000_000_006),
    ]
}

/// One line per message: timestamp id extended remote dlc data-hex.
const PY_READ: &str = r#"
import sys, can
for m in can.CanutilsLogReader(sys.argv[1]):
    data = bytes(m.data).hex().upper() if m.data is not None else ""
    print(f"{m.timestamp:.6f} {m.arbitration_id:X} {int(m.is_extended_id)} {int(m.is_remote_frame)} {m.dlc} {m.channel} [{data}]")
"#;

#[test]
fn python_can_reads_our_candump_files() {
    ensure_python_can();
    let path = temp_path("ours.log");
    let mut w = CandumpWriter::new(std::fs::File::create(&path).unwrap(), "vcan0").unwrap();
    for t in frames() {
        w.write(&t).unwrap();
    }
    w.flush().unwrap();
    drop(w);

    let got = python(PY_READ, &path);
    let expected: Vec<String> = frames()
        .iter()
        .map(|t| {
            let f = &t.frame;
            let data: String = f.data().iter().map(|b| format!("{b:02X}")).collect();
            format!(
                "{}.{:06} {:X} {} {} {} vcan0 [{}]",
                t.unix_time_us / 1_000_000,
                t.unix_time_us % 1_000_000,
                f.id().raw(),
                u8::from(f.is_extended()),
                u8::from(f.is_remote()),
                f.dlc(),
                data
            )
        })
        .collect();
    assert_eq!(got.lines().collect::<Vec<_>>(), expected);
    // And our own reader gives back exactly what was written.
    let file = std::io::BufReader::new(std::fs::File::open(&path).unwrap());
    let back: Vec<TimedFrame> = CandumpReader::new(file).collect::<Result<_, _>>().unwrap();
    assert_eq!(back, frames());
    let _ = std::fs::remove_file(&path);
}

/// python-can writes `(%f) channel ID#DATA R|T`; remote frames without a length.
const PY_WRITE: &str = r#"
import sys, can
msgs = [
    can.Message(timestamp=1699999999.123456, arbitration_id=0x80, is_extended_id=False, data=[1], channel="vcan0"),
    can.Message(timestamp=1699999999.1236, arbitration_id=0x181, is_extended_id=False, data=[1,2,3,4,5,6,7,8], channel="vcan0", is_rx=False),
    can.Message(timestamp=1699999999.2, arbitration_id=0x1ABCDEF, is_extended_id=True, data=[0xAA], channel="vcan0"),
    can.Message(timestamp=1699999999.3, arbitration_id=0x701, is_extended_id=False, is_remote_frame=True, channel="vcan0"),
]
with can.CanutilsLogWriter(sys.argv[1]) as w:
    for m in msgs:
        w.on_message_received(m)
"#;

#[test]
fn we_read_python_can_candump_files() {
    ensure_python_can();
    let path = temp_path("python.log");
    python(PY_WRITE, &path);
    let text = std::fs::read(&path).unwrap();
    let mut r = CandumpReader::new(&text[..]);
    let mut got = Vec::new();
    while let Some(rec) = r.next_record().unwrap() {
        got.push((rec.timed, rec.interface.to_owned(), rec.direction));
    }
    let f = |frame, unix_time_us| TimedFrame { frame, unix_time_us };
    let expected = vec![
        (f(CanFrame::new_standard(0x80, &[1]).unwrap(), 1_699_999_999_123_456), Some(Direction::Rx)),
        (
            f(CanFrame::new_standard(0x181, &[1, 2, 3, 4, 5, 6, 7, 8]).unwrap(), 1_699_999_999_123_600),
            Some(Direction::Tx),
        ),
        (f(CanFrame::new_extended(0x1AB_CDEF, &[0xAA]).unwrap(), 1_699_999_999_200_000), Some(Direction::Rx)),
        (f(CanFrame::new_remote(CanId::Standard(0x701), 0).unwrap(), 1_699_999_999_300_000), Some(Direction::Rx)),
    ];
    assert_eq!(got.len(), expected.len(), "{}", String::from_utf8_lossy(&text));
    for ((timed, iface, dir), (exp, exp_dir)) in got.into_iter().zip(expected) {
        assert_eq!(timed, exp, "{}", String::from_utf8_lossy(&text));
        assert_eq!(iface, "vcan0");
        assert_eq!(dir, exp_dir);
    }
    let _ = std::fs::remove_file(&path);
}
