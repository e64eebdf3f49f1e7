//! The `simrobot` binary: `generate` is deterministic and its bus.log holds exactly the frames
//! of the twin; errors give the documented exit codes.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use hw_io::can::candump::CandumpReader;
use hw_io::can::{CanFrame, SYNC_COB_ID, SyncSource, TimedFrame};
use sim::truth_file::TruthFile;
use sim::twin::{SimRobot, TwinEvent};

const EXE: &str = env!("CARGO_BIN_EXE_simrobot");
const T0_US: u64 = 1_700_000_000_000_000;

/// A fresh scratch directory for one test, removed when dropped.
struct Scratch(PathBuf);

impl Scratch {
    fn new(name: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("simrobot-cli-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        Self(dir)
    }
    fn path(&self, p: &str) -> PathBuf {
        self.0.join(p)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A short scenario (about 4 s) as a config file.
fn small_config(dir: &Scratch, extra: &str) -> PathBuf {
    let path = dir.path("twin.toml");
    let text = format!("[scenario]\ncycles = 1\ninside_s = [1.5, 2.0]\noutside_s = [1.0, 1.2]\n{extra}");
    std::fs::write(&path, text).unwrap();
    path
}

fn simrobot(args: &[&str]) -> Output {
    Command::new(EXE).args(args).output().unwrap()
}

fn generate(config: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut args = vec!["generate", "--out", out.to_str().unwrap(), "--config", config.to_str().unwrap()];
    args.extend_from_slice(extra);
    let o = simrobot(&args);
    assert!(o.status.success(), "generate failed: {}", String::from_utf8_lossy(&o.stderr));
    o
}

fn read(p: PathBuf) -> Vec<u8> {
    std::fs::read(p).unwrap()
}

#[test]
fn the_same_seed_gives_the_same_bytes() {
    let dir = Scratch::new("same-seed");
    let config = small_config(&dir, "");
    let (a, b, c) = (dir.path("a"), dir.path("b"), dir.path("c"));
    let out = generate(&config, &a, &["--seed", "5"]);
    generate(&config, &b, &["--seed", "5"]);
    generate(&config, &c, &["--seed", "6"]);
    let summary = String::from_utf8(out.stdout).unwrap();
    assert!(summary.contains("seed 5, 1 cycles") && summary.contains("frames"), "{summary}");
    // Not a terminal: no progress bar on stderr.
    assert!(out.stderr.is_empty(), "{}", String::from_utf8_lossy(&out.stderr));
    for file in ["bus.log", "truth.jsonl"] {
        let bytes = read(a.join(file));
        assert!(bytes.len() > 10_000, "{file}: {} bytes", bytes.len());
        assert_eq!(bytes, read(b.join(file)), "{file} differs for the same seed");
        assert_ne!(bytes, read(c.join(file)), "{file} is the same for another seed");
    }
}

/// The frames the twin of `truth.jsonl`'s header produces, with the controller's SYNCs, in
/// bus order; and its events.
fn replay(truth: &TruthFile) -> (Vec<TimedFrame>, Vec<TwinEvent>) {
    let config = truth.header().twin.clone().expect("simrobot writes the twin config");
    let mut robot = SimRobot::new(&config).unwrap();
    let mut sync = SyncSource::new();
    let (mut frames, mut events) = (Vec::new(), Vec::new());
    for i in 0.. {
        let t_us = T0_US + i * 1000;
        let counter = sync.next_counter();
        let Some(answer) = robot.on_sync(counter, t_us).unwrap() else { break };
        let frame = CanFrame::new_standard(SYNC_COB_ID, &[counter]).unwrap();
        frames.push(TimedFrame { frame, unix_time_us: t_us });
        frames.extend_from_slice(&answer);
        events.extend_from_slice(robot.events());
    }
    // Bus order: by time, then by identifier (arbitration); stable for equal keys.
    frames.sort_by_key(|f| (f.unix_time_us, f.frame.id().raw()));
    (frames, events)
}

fn check_log_against_twin(extra_config: &str, name: &str) -> usize {
    let dir = Scratch::new(name);
    let config = small_config(&dir, extra_config);
    let out = dir.path("out");
    generate(&config, &out, &[]);
    let truth = TruthFile::open(&out.join("truth.jsonl")).unwrap();
    let (expected, events) = replay(&truth);
    assert_eq!(truth.events(), &events[..]);
    assert_eq!(truth.header().t0_unix_time_us, T0_US);
    let text = read(out.join("bus.log"));
    let mut reader = CandumpReader::new(&text[..]);
    let mut got = Vec::new();
    while let Some(rec) = reader.next_record().unwrap() {
        assert_eq!(rec.interface, "vcan0");
        got.push(rec.timed);
    }
    assert_eq!(got.len(), expected.len());
    for (k, (g, e)) in got.iter().zip(&expected).enumerate() {
        assert_eq!(g, e, "frame {k} (line {})", k + 1);
    }
    let syncs = got.iter().filter(|f| f.frame.id().raw() == 0x080).count() as u64;
    assert_eq!(syncs, truth.samples());
    got.len()
}

#[test]
fn bus_log_holds_exactly_the_frames_of_the_twin() {
    let n = check_log_against_twin("", "frames");
    assert!(n > 10_000, "{n} frames");
}

#[test]
fn answers_later_than_the_next_sync_are_logged_in_bus_order() {
    // Node 1 answers 1.5 ms after the SYNC (after the next SYNC); node 3 drops TPDOs and
    // raises an EMCY.
    let extra = "[[nodes]]\nlatency_us = 1500\n[[nodes]]\n[[nodes]]\ndropout_probability = 0.1\n\
                 emcy = [{ at_us = 20000, duration_us = 5000, code = 0x7305 }]\n";
    check_log_against_twin(extra, "late");
}

#[test]
fn errors_give_the_documented_exit_codes() {
    let dir = Scratch::new("errors");
    // Bad config: 2, naming the key.
    let bad = dir.path("bad.toml");
    std::fs::write(&bad, "[scenario]\ncycels = 1\n").unwrap();
    let o = simrobot(&["generate", "--out", dir.path("x").to_str().unwrap(), "--config", bad.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("cycels"));
    // Usage: --cycles and --minutes together.
    let o = simrobot(&["generate", "--out", "x", "--cycles", "1", "--minutes", "1"]);
    assert_eq!(o.status.code(), Some(2));
    // No such CAN interface (or no CAN in the kernel at all): 3, with the interface named.
    let o = simrobot(&["live", "--iface", "simrobotno0", "--cycles", "1"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{err}");
    assert!(err.contains("simrobotno0") && err.contains("CAN"), "{err}");
}

/// `simrobot generate ... | head -1` once head has gone: no panic, the quiet exit status 141
/// (128 + SIGPIPE), and the files are complete (the summary is printed after they are written).
#[test]
fn generate_exits_quietly_when_its_stdout_is_closed() {
    let dir = Scratch::new("epipe");
    let config = small_config(&dir, "");
    let out = dir.path("run");
    let mut child = Command::new(EXE)
        .args(["generate", "--out", out.to_str().unwrap(), "--config", config.to_str().unwrap()])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take()); // the reader goes away before simrobot writes anything
    let o = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(141), "{stderr}");
    assert!(stderr.is_empty(), "nothing on stderr, no panic: {stderr}");
    let reference = dir.path("reference");
    generate(&config, &reference, &[]);
    assert_eq!(read(out.join("bus.log")), read(reference.join("bus.log")));
    assert_eq!(read(out.join("truth.jsonl")), read(reference.join("truth.jsonl")));
}
