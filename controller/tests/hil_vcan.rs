//! Hardware-in-loop suite on SocketCAN vcan (docs/hil.md): the real `fulcrumd` binary on
//! `vcan0`, the real `simrobot live` answering as the encoder nodes, a `fulcrumd monitor`
//! subscriber process and `candump`, all inside one kernel that has vcan.
//!
//! Each `#[test]` runs twice:
//! - on the host, it boots a guest through `tests/hil/run-in-vcan.sh` (a user-mode-linux
//!   kernel with vcan0 when the host has no CAN, natively otherwise) and runs **this same
//!   test binary** in it, filtered to the same test, with `HIL_SCENARIO_DIR` set;
//! - in the guest, `HIL_SCENARIO_DIR` makes the test the scenario driver: it spawns the
//!   processes, injects the faults and writes every artifact (summaries, the monitor's samples,
//!   the flight recording, the candump log, the ground truth) to that directory, a read-write
//!   mount of a host directory.
//!
//! Back on the host the test asserts on the artifacts. Timing inside the emulated kernel is
//! coarse (late wake-ups by milliseconds, one CPU), so the assertions are on behaviour and
//! counts; the one time bound is the issue's "the subscriber receives again within 1 s".
//! A VM that cannot start (exit code 125) is a failure, never a skip.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, Instant};

use controller::config::Config;
use controller::monitor::{SampleEvent, SampleLine};
use controller::replay::{self, LogReplay};
use controller::rt::monotonic_now_ns;
use controller::rt_loop::CycleRecord;
use hw_io::can::candump::CandumpReader;
use hw_io::can::{CanBus, CanFrame, SocketCanBus};
use hw_io::ipc::{HealthFlags, OutputState};
use serde_json::Value;
use sim::score::Detected;
use sim::truth_file::{At, TruthFile, score_detections};

#[path = "support/workspace_bin.rs"]
mod support;
use support::workspace_bin;

const FULCRUMD: &str = env!("CARGO_BIN_EXE_fulcrumd");
/// Set (to the artifacts directory) only in the guest run of a test.
const SCENARIO_DIR_ENV: &str = "HIL_SCENARIO_DIR";
/// The simrobot binary, passed from the host run to the guest run.
const SIMROBOT_ENV: &str = "HIL_SIMROBOT";
/// The three encoder nodes answer each SYNC with one TPDO each (COB-IDs 0x181..0x183).
const ALL_NODES: u8 = 0b111;
/// Farther than this from the true pivot, a detection is at the wrong trocar (as the demo).
const WRONG_TROCAR_M: f64 = 0.03;

// ------------------------------------------------------------------------------------------
// Scenarios

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Scenario {
    /// Several insert/extract cycles, no fault.
    Clean,
    /// Node 2 sends no TPDO for 200 ms.
    NodeSilent,
    /// Wrong-DLC and unknown-ID frames at 2 kHz.
    Malformed,
    /// Five EMCYs of node 3 in a row (every 100 ms), each cleared after 40 ms.
    EmcyBurst,
    /// The daemon is SIGKILLed and restarted while the monitor keeps running.
    KillRestart,
    /// The daemon, with a small receive queue, is SIGSTOPped while a burst of frames floods
    /// the bus: its queue overflows and the kernel drops frames, which it must count.
    RxOverflow,
    /// simrobot also films the arms (`live --camera`) and publishes frames; a frame monitor
    /// process (`comanip-camera monitor`) reads them while the daemon runs.
    Camera,
    /// simrobot films the arms; `comanip-calib live` (frames, a passive socket on vcan0,
    /// fulcrumd's output) calibrates and publishes; `comanip-calib monitor` receives it.
    CalibLive,
    /// simrobot films the arms; `comanip-track live` (frames, a passive socket on vcan0 for
    /// both arms' joints) tracks the instrument and publishes; `comanip-track monitor`
    /// receives every sample.
    TrackLive,
}

/// The camera scenario's frame rate and image size (small: the guest has one slow CPU).
const CAMERA_FPS: u64 = 10;
const CAMERA_SIZE: (u32, u32) = (160, 120);
/// The comanip-camera binary, passed from the host run to the guest run.
const CAMERA_BIN_ENV: &str = "HIL_CAMERA_BIN";
/// The live calibration scenario's camera: 160×120 (as the camera scenario) at 2 fps. simrobot
/// renders at SCHED_FIFO 90 on the guest's one CPU: at 320×240 and 5 fps, and at 240×180 and
/// 2 fps, it rendered 1.3-1.5 frames a second, skipped the rest, the daemon overran, and the
/// non-real-time processes (the calibration, niced as its unit) got so little CPU that the
/// kernel dropped 94 % of the bus frames queued for its listener.
const CALIB_CAMERA_FPS: u64 = 2;
const CALIB_CAMERA_SIZE: (u32, u32) = (160, 120);
/// Cycles of the live calibration scenario's daemon at most: 80 s at the guest's 2 ms period,
/// 160 s at the qemu guest's 4 ms ([`EMULATED_CAMERA_PERIOD_US`]) (40 s of twin time: the
/// instrument in several trocars, the endoscope moving every 1.5-3 s). The driver stops the
/// daemon 2 s after the first valid calibration reaches the subscriber (about 25 000 cycles on
/// the development VM: 20 000 gave the collector 34 observations, short of the 40 of its first
/// solve; 24 818 in the qemu guest at 4 ms: the views come with the twin's samples, not with
/// the frames), so a slower host runs longer instead of failing.
const CALIB_RUN_CYCLES: u64 = 40_000;
/// Its targets, relaxed for the short, coarse guest session (the default is 1 mm / 0.2°).
const CALIB_TARGET_MM: f64 = 8.0;
const CALIB_TARGET_DEG: f64 = 1.5;
/// The comanip-calib binary, passed from the host run to the guest run.
const CALIB_BIN_ENV: &str = "HIL_CALIB_BIN";
/// The live tracking scenario's camera: the calibration scenario's (the guest's one CPU renders
/// no more), and its daemon's cycles: 120 s at the scenario's 4 ms period ([`TRACK_PERIOD_US`]), 240 frames at 2 fps.
const TRACK_CAMERA_FPS: u64 = 2;
const TRACK_CAMERA_SIZE: (u32, u32) = (160, 120);
/// At most: the driver stops the daemon 2 s after the consumer has received
/// [`TRACK_WANTED`] TRACKING samples. On a loaded host the guest's real-time processes (the
/// daemon at SCHED_FIFO 80 overran 27 588 times in 20 000 cycles once) leave the tracker, below
/// them, almost no CPU for tens of seconds: a slower host runs longer instead of failing.
const TRACK_RUN_CYCLES: u64 = 30_000;
/// TRACKING samples the consumer must have received before the daemon is stopped.
const TRACK_WANTED: usize = 20;
/// The tracker's particles in the guest (its one CPU is shared with every other process).
const TRACK_PARTICLES: usize = 300;
/// The tracker's joint-reading limits in the guest, ms (the defaults at the guest's 2 ms period
/// are 10 / 40 ms for the tool arm): the overloaded guest skips periods and its listener falls
/// behind by tens of milliseconds; with the defaults every frame was refused as stale (86 of 86
/// once). As the live calibration's `max_age_ms = 200`.
const TRACK_JOINTS_GAP_MS: f64 = 150.0;
const TRACK_JOINTS_AGE_MS: f64 = 200.0;
/// The comanip-track binary, passed from the host run to the guest run.
const TRACK_BIN_ENV: &str = "HIL_TRACK_BIN";

/// Dropout window of node 2 in `NodeSilent`, microseconds of twin time since simrobot's first
/// SYNC (1 ms per SYNC: samples 5000 to 5199). The instrument enters its first trocar at sample
/// 2556 and leaves it at sample 7794; the daemon detects it about 1.1 s of samples later.
const SILENT_WINDOW_US: [u64; 2] = [5_000_000, 5_200_000];
/// EMCY burst of node 3: count, first at, spacing, duration (twin time since the first SYNC).
const EMCY_COUNT: u64 = 5;
const EMCY_AT_US: u64 = 5_000_000;
const EMCY_EVERY_US: u64 = 100_000;
const EMCY_DURATION_US: u64 = 40_000;
/// Malformed-frame flood: period (wall time) and length.
const JUNK_PERIOD_NS: u64 = 500_000; // 2 kHz
const JUNK_FRAMES: u64 = 8_000; // 4 s at 2 kHz
/// The malformed-frame scenario's length in the daemon's cycles (= twin samples: one per SYNC),
/// not in wall time, so that it is the same at any period and load. The flood starts once the
/// subscriber has received `JUNK_START_CYCLES` samples (5 s at 2 ms: the instrument enters its
/// first trocar at sample 2556, and the flood runs over its detection, about 1.1 s of samples
/// later); the daemon gets SIGINT once the flood is over and it has run `JUNK_TAIL_CYCLES` more
/// cycles, and [`MALFORMED_MIN_CYCLES`] in all. With the length in wall time (5 s + the flood +
/// 2 s), the daemon at the qemu guest's 4 ms ran 3489 cycles on a quiet host and stopped before
/// the detection (session 17's failure); on a loaded host the starved flood took longer, and
/// the run was long enough.
const JUNK_START_CYCLES: u64 = 2_500;
const JUNK_TAIL_CYCLES: u64 = 1_000;
/// At least this many cycles in the malformed-frame scenario: the instrument's first insertion
/// (samples 2556-7794) with 2.3 s of samples after the fast detector's p95 insertion delay
/// (2.1 s, docs/BENCHMARKS.md) past its entry, still inside it.
const MALFORMED_MIN_CYCLES: u64 = 7_000;
/// Cycles of the fault scenarios' daemon run (15 s at 2 ms): the faults come at sample 5000,
/// while the instrument is inside and detected, with time to re-detect it after them.
const FAULT_RUN_CYCLES: u64 = 9_000;
/// Kill/restart: the first daemon runs this long, the restart comes this long after the kill,
/// and the second daemon runs this many cycles.
const FIRST_RUN_MS: u64 = 3_000;
const DOWN_MS: u64 = 300;
const SECOND_RUN_CYCLES: u64 = 3_000;
/// Receive-queue overflow: the daemon's queue (bytes asked; the kernel doubles it: a few tens
/// of frames), the burst sent while it is stopped (frames, as fast as the bus takes them), and
/// how long it stays stopped at least.
const OVERFLOW_RX_BUFFER_BYTES: usize = 16 * 1024;
const OVERFLOW_BURST_FRAMES: u64 = 1_000;
const OVERFLOW_MIN_STOP_MS: u64 = 300;
/// The burst's frame: an identifier nobody uses (the daemon counts it as unknown-ID).
const OVERFLOW_COB_ID: u16 = 0x7FF;

impl Scenario {
    /// The twin's configuration (configs/simrobot.toml keys).
    fn simrobot_toml(self) -> String {
        // 4 cycles of 4-5 s inside and 1.6-2.2 s outside: about 30 000 samples (SYNCs) for the
        // clean run. The fault scenarios use the first 9 000 samples of a scenario whose first
        // insertion lasts 6-6.5 s (from about 2.6 s): detection, the fault at 5 s and the
        // re-detection after it all fall inside it, with 3 s after the fault (the fast
        // detector's insertion delay is 1.3 s mean, 2.1 s p95: docs/BENCHMARKS.md).
        let inside = if self == Scenario::Clean { "[4.0, 5.0]" } else { "[6.0, 6.5]" };
        let mut s = format!("[scenario]\nseed = 1\ncycles = 4\ninside_s = {inside}\noutside_s = [1.6, 2.2]\n");
        // Heartbeats every 50 ms of twin time (simrobot --twin-clock: 1 ms per SYNC), i.e.
        // every 100 ms of wall time at the 2 ms HIL period, as on the robot.
        let node = |dropouts: &str, emcy: &str| {
            format!("\n[[nodes]]\nheartbeat_period_us = 50000\ndropout_windows_us = [{dropouts}]\nemcy = [{emcy}]\n")
        };
        if matches!(self, Scenario::CalibLive | Scenario::TrackLive) {
            // The endoscope holder moves more often than by default: views to calibrate from,
            // and the tracker's cameras move with it.
            s += "\n[endoscope_arm]\nhold_s = [1.5, 3.0]\nmove_s = [0.8, 1.2]\n";
        }
        let mut nodes = [node("", ""), node("", ""), node("", "")];
        match self {
            Scenario::NodeSilent => {
                nodes[1] = node(&format!("[{}, {}]", SILENT_WINDOW_US[0], SILENT_WINDOW_US[1]), "");
            }
            Scenario::EmcyBurst => {
                let burst = (0..EMCY_COUNT)
                    .map(|k| {
                        format!(
                            "{{ at_us = {}, duration_us = {EMCY_DURATION_US}, code = 0x7305, register = 1, vendor = [0, 0, 0, 0, 0] }}",
                            EMCY_AT_US + k * EMCY_EVERY_US
                        )
                    })
                    .collect::<Vec<_>>()
                    .join(", ");
                nodes[2] = node("", &burst);
            }
            _ => {}
        }
        s += &nodes.concat();
        s
    }
}

/// Control period of the daemon in the guest, microseconds: 2 ms (500 Hz) instead of 1 ms.
/// Under user-mode-linux every system call and wake-up goes through the host (ptrace), and the
/// guest has one CPU for the daemon, simrobot, the monitor and candump: at 1 kHz the SYNC →
/// answer round trip alone took 0.8 ms at the median, a quarter of the cycles were incomplete
/// and more than half the periods were skipped (measured, docs/hil.md). At 2 ms the guest keeps
/// up. The detector then counts the same samples as at 1 kHz: its durations are scaled by the
/// same factor (see [`daemon_config`]), and one SYNC is one sample of the twin whatever the
/// period, so the estimates per sample are those of the 1 kHz configuration.
const HIL_PERIOD_US: u32 = 2_000;
/// The live tracking scenario's period: 4 ms. Its guest carries the most (the camera, the
/// tracker, the daemon, simrobot, two monitors and candump on one CPU); at 2 ms its real-time
/// processes took the whole CPU (68 693 overruns in 40 000 cycles on a loaded host) and left
/// the tracker nothing. The twin runs one sample per SYNC, so its motion is a quarter as fast
/// per second of wall time; the camera's frames are on wall time (2 per second).
const TRACK_PERIOD_US: u32 = 4_000;

/// The live camera and live calibration scenarios' period in the qemu guest (the fallback where
/// user-mode-linux cannot run, `tests/hil/run-in-vcan.sh`): 4 ms. Its CPU is emulated (TCG:
/// user code about 100 times slower than on the host, where user-mode-linux runs it natively),
/// and at 2 ms the bus alone filled it: 99.9 % busy while the daemon ran, and the renderer
/// (simrobot's camera thread, below every real-time process, as a camera's own hardware would
/// not be) got one frame filmed in 6 s of SYNCs. Per SYNC the bus costs about 2 ms of the
/// emulated CPU (simrobot's twin 1.0 ms, candump, the monitor and the calibration's reader
/// 0.3 ms each, the daemon 0.13 ms: `cpu_s_while_daemon_ran` in driver.json); at 4 ms half of
/// the CPU is left to the renderer and the calibration, as at 2 ms under user-mode-linux
/// (docs/hil.md, "The qemu fallback"). The twin runs one sample per SYNC: its motion is half as
/// fast per second of wall time, the camera stays on wall time (more frames per twin second).
/// The malformed-frame scenario too: its junk sender (a normal-priority thread of the driver)
/// got so little of the CPU at 2 ms that its 4 s flood took 70-106 s, and at 106 s outlasted
/// the twin's 38 072 samples (SYNCs then went unanswered).
const EMULATED_CAMERA_PERIOD_US: u32 = 4_000;

/// True in the qemu guest (`HIL_MODE=qemu`), whose CPU is emulated.
fn emulated_guest() -> bool {
    std::env::var("HIL_MODE").is_ok_and(|m| m == "qemu")
}

/// The daemon's period in the guest for `scenario`, microseconds.
fn period_us(scenario: Scenario) -> u32 {
    match scenario {
        Scenario::TrackLive => TRACK_PERIOD_US,
        Scenario::Camera | Scenario::CalibLive | Scenario::Malformed if emulated_guest() => EMULATED_CAMERA_PERIOD_US,
        _ => HIL_PERIOD_US,
    }
}

/// Heartbeat timeout of the daemon in the guest, milliseconds (default 350). simrobot runs the
/// nodes on its twin clock (`--twin-clock`: faults hit fixed samples), so a heartbeat comes
/// every 50 SYNCs, nominally 100 ms at the 2 ms period; when the guest falls behind (periods
/// skipped), 50 SYNCs took up to 0.44 s of wall time here (host load about 4 on 2 cores). A
/// guest falling behind is not a node failure; the heartbeat rule itself is covered by
/// `controller/src/health.rs`'s tests.
const HIL_HEARTBEAT_TIMEOUT_MS: u32 = 2_000;

/// The daemon's configuration in the guest: the defaults, with the scenario's period
/// ([`period_us`]), the fast detector's durations (`*_persistence_s`) scaled by period / 1 ms so that they span
/// the same number of samples as the defaults at 1 kHz, and [`HIL_HEARTBEAT_TIMEOUT_MS`].
/// The subscriber buffer of the daemon's output and of the monitor, samples: 2 s at the
/// guest's 500 Hz. The guest stalls for hundreds of milliseconds when the shared host is busy
/// (324 ms seen in a CI run, which overflowed the default 64-sample buffer); the monitor stands
/// for a subscriber that must not lose a sample, so it gets room for such a stall.
const HIL_SUBSCRIBER_BUFFER: usize = 1000;

fn daemon_config(scenario: Scenario) -> String {
    let mut c = Config::default();
    if scenario == Scenario::RxOverflow {
        c.bus.receive_buffer_bytes = OVERFLOW_RX_BUFFER_BYTES;
    }
    let period = period_us(scenario);
    let k = f64::from(period) / f64::from(c.cycle.period_us);
    c.cycle.period_us = period;
    // Frame deadline: 90 % of the period (wake-ups in the guest are late by milliseconds now
    // and then; a late answer makes an incomplete cycle, counted and flagged).
    c.cycle.frame_deadline_us = period / 10 * 9;
    c.detector.sample_period_s *= k;
    c.detector.fast.min_persistence_s *= k;
    c.detector.fast.extract_persistence_s *= k;
    c.detector.fast.memory_persistence_s *= k;
    c.health.heartbeat_timeout_ms = HIL_HEARTBEAT_TIMEOUT_MS;
    c.output.subscriber_buffer = HIL_SUBSCRIBER_BUFFER;
    toml::to_string(&c).expect("the configuration serialises")
}

/// The receive queue the daemon asks for, bytes.
fn daemon_rx_buffer() -> usize {
    controller::daemon::CAN_RECEIVE_BUFFER_BYTES
}

// ------------------------------------------------------------------------------------------
// Host side: boot the guest, run this test in it, collect the artifacts

/// One VM at a time: a second UML guest on the same two cores makes timing worse for both.
static VM: Mutex<()> = Mutex::new(());

/// What a scenario left in its directory.
struct Artifacts {
    dir: PathBuf,
    driver: Value,
}

impl Artifacts {
    fn json(&self, name: &str) -> Value {
        let p = self.dir.join(name);
        let text = std::fs::read_to_string(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
        serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
    }
}

/// The workspace's `tests/hil/run-in-vcan.sh`.
fn harness() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/hil/run-in-vcan.sh")
}

/// `simrobot`, built by cargo for the same profile as this test (cargo gives a test only its
/// own package's binaries): `$CARGO build --bin simrobot` once per test binary; cargo
/// rebuilds it only when stale.
fn simrobot() -> PathBuf {
    static BIN: OnceLock<PathBuf> = OnceLock::new();
    BIN.get_or_init(|| workspace_bin("sim", "simrobot")).clone()
}

/// `comanip-calib`, built as [`simrobot`] is.
fn calib_bin() -> PathBuf {
    static BIN: OnceLock<PathBuf> = OnceLock::new();
    BIN.get_or_init(|| workspace_bin("comanip-calib", "comanip-calib")).clone()
}

/// `comanip-track`, built as [`simrobot`] is.
fn track_bin() -> PathBuf {
    static BIN: OnceLock<PathBuf> = OnceLock::new();
    BIN.get_or_init(|| workspace_bin("comanip-track", "comanip-track")).clone()
}

/// `comanip-camera`, built as [`simrobot`] is.
fn camera_bin() -> PathBuf {
    static BIN: OnceLock<PathBuf> = OnceLock::new();
    BIN.get_or_init(|| workspace_bin("comanip-camera", "comanip-camera")).clone()
}

/// Where the artifacts of `test` go: under cargo's target tmp dir (not under /tmp: the guest
/// mounts a private overlay there, which would hide a read-write mount below it).
fn artifacts_dir(test: &str) -> PathBuf {
    let root = std::env::var_os("HIL_ARTIFACTS_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_TARGET_TMPDIR")).join("hil"));
    let dir = root.join(test);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
    dir.canonicalize().expect("canonical artifacts dir")
}

/// Runs `scenario` as test `test`. In the guest: drives it and returns None. On the host:
/// boots the guest, runs this test in it, and returns the artifacts.
fn hil(test: &str, scenario: Scenario) -> Option<Artifacts> {
    if let Some(dir) = std::env::var_os(SCENARIO_DIR_ENV) {
        drive(scenario, Path::new(&dir));
        return None;
    }
    let _one_vm = VM.lock().unwrap_or_else(|p| p.into_inner());
    let simrobot = simrobot();
    let camera = if scenario == Scenario::Camera { Some(camera_bin()) } else { None };
    let calib = if scenario == Scenario::CalibLive { Some(calib_bin()) } else { None };
    let track = if scenario == Scenario::TrackLive { Some(track_bin()) } else { None };
    let dir = artifacts_dir(test);
    let started = Instant::now();
    // The live calibration runs until its first publication, at most CALIB_RUN_CYCLES: 160 s at
    // the qemu guest's 4 ms, more when the loop overruns.
    let timeout_s = if scenario == Scenario::CalibLive { "300" } else { "240" };
    let out = Command::new(harness())
        .args(["--timeout", timeout_s, "--rw"])
        .arg(&dir)
        .arg("--")
        .arg(std::env::current_exe().expect("current_exe"))
        .args([test, "--exact", "--nocapture", "--test-threads", "1"])
        .env(SCENARIO_DIR_ENV, &dir)
        .env(SIMROBOT_ENV, &simrobot)
        .env(CAMERA_BIN_ENV, camera.unwrap_or_default())
        .env(CALIB_BIN_ENV, calib.unwrap_or_default())
        .env(TRACK_BIN_ENV, track.unwrap_or_default())
        .env("RUST_BACKTRACE", "1")
        .stdin(Stdio::null())
        .output()
        .expect("running tests/hil/run-in-vcan.sh");
    let wall = started.elapsed().as_secs_f64();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    eprintln!("--- guest stdout\n{stdout}\n--- guest stderr\n{stderr}\n--- {test}: VM run {wall:.1} s");
    match out.status.code() {
        Some(0) => {}
        Some(125) => panic!("the HIL harness failed (exit 125: the VM did not start or broke); see above"),
        Some(124) => panic!("the scenario timed out in the guest (exit 124)"),
        code => panic!("the scenario driver failed in the guest (exit {code:?}); see above"),
    }
    // The guest ran exactly this test (a wrong name would run none and exit 0).
    assert!(stdout.contains("1 passed"), "the guest did not run {test}");
    let driver_path = dir.join("driver.json");
    let driver: Value = serde_json::from_str(&std::fs::read_to_string(&driver_path).expect("driver.json"))
        .expect("driver.json is JSON");
    eprintln!(
        "[hil] {} guest, daemon period {} us; guest CPU while the daemon ran: {}",
        driver["hil_mode"], driver["period_us"], driver["guest_cpu_while_daemon_ran"]
    );
    Some(Artifacts { dir, driver })
}

// ------------------------------------------------------------------------------------------
// Guest side: the scenario driver

fn spawn(cmd: &mut Command, dir: &Path, name: &str) -> Child {
    let out = File::create(dir.join(format!("{name}.out"))).expect("stdout file");
    let err = File::create(dir.join(format!("{name}.err"))).expect("stderr file");
    cmd.stdin(Stdio::null()).stdout(out).stderr(err).spawn().unwrap_or_else(|e| panic!("spawning {name}: {e}"))
}

fn signal(child: &Child, sig: libc::c_int) {
    // SAFETY: kill(2) on our own child's pid; no memory is involved.
    unsafe { libc::kill(child.id() as libc::pid_t, sig) };
}

/// Polls the tracker's consumer's JSON lines until `wanted` are TRACKING (true) or the daemon
/// exits on its own (false).
fn wait_for_tracking(jsonl: &Path, wanted: usize, daemon: &mut Child) -> bool {
    loop {
        if std::fs::read_to_string(jsonl).is_ok_and(|t| t.matches("\"status\":\"TRACKING\"").count() >= wanted) {
            return true;
        }
        if daemon.try_wait().ok().flatten().is_some() {
            return false;
        }
        std::thread::sleep(Duration::from_millis(250));
    }
}

/// Polls the calibration subscriber's JSON lines until one carries a valid calibration (true) or
/// the daemon exits on its own (false: the session ended without a publication).
fn wait_for_published_calibration(jsonl: &Path, daemon: &mut Child) -> bool {
    loop {
        if std::fs::read_to_string(jsonl).is_ok_and(|t| t.contains("\"state\":\"valid\"")) {
            return true;
        }
        if daemon.try_wait().ok().flatten().is_some() {
            return false;
        }
        std::thread::sleep(Duration::from_millis(250));
    }
}

/// The processes whose threads' CPU the driver records while the daemon runs: the robot, the
/// subscriber, candump and the kernel's softirq threads.
fn watched_procs(
    driver: &serde_json::Map<String, Value>,
    robot: &Child,
    monitor: &Child,
    candump: &Child,
) -> Vec<(&'static str, u32)> {
    let mut procs = vec![("simrobot", robot.id()), ("monitor", monitor.id()), ("candump", candump.id())];
    let softirq = driver.get("ksoftirqd_fifo95").and_then(Value::as_str).unwrap_or_default();
    procs.extend(softirq.split(',').filter_map(|p| p.parse().ok()).map(|p| ("kernel", p)));
    procs
}

/// Counts the lines of a file another process is appending to (the monitor's samples, one per
/// cycle of the daemon; written through a buffer, so the count lags by up to 8 KiB of lines).
#[derive(Default)]
struct LineCounter {
    file: Option<File>,
    lines: u64,
}

impl LineCounter {
    /// The lines written to `path` so far (0 before it exists).
    fn poll(&mut self, path: &Path) -> u64 {
        use std::io::Read;
        if self.file.is_none() {
            self.file = File::open(path).ok();
        }
        if let Some(f) = self.file.as_mut() {
            let mut new = Vec::new();
            f.read_to_end(&mut new).expect("read the samples file");
            self.lines += new.iter().filter(|&&b| b == b'\n').count() as u64;
        }
        self.lines
    }

    /// Polls `path` until it has at least `n` lines and returns the count; fails when `daemon`
    /// exits first or after `limit`.
    fn wait_for(&mut self, path: &Path, n: u64, daemon: &mut Child, limit: Duration) -> u64 {
        let t0 = Instant::now();
        loop {
            let lines = self.poll(path);
            if lines >= n {
                return lines;
            }
            let exited = daemon.try_wait().expect("try_wait");
            assert!(exited.is_none(), "the daemon exited ({exited:?}) after {lines} samples, before {n}");
            assert!(t0.elapsed() < limit, "{lines} samples after {limit:?}, waiting for {n}");
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

/// Waits for `child` to exit within `limit`; kills it (and fails) otherwise. Returns the exit
/// code, or -signal.
fn wait_exit(child: &mut Child, name: &str, limit: Duration) -> i32 {
    let t0 = Instant::now();
    loop {
        if let Some(st) = child.try_wait().expect("try_wait") {
            use std::os::unix::process::ExitStatusExt;
            return st.code().unwrap_or_else(|| -st.signal().unwrap_or(0));
        }
        if t0.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{name} did not exit within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The guest's CPU time so far by kind, clock ticks (`/proc/stat`'s `cpu` line: user, nice,
/// system, idle, iowait, irq, softirq, ...). The guest has one CPU.
fn guest_cpu_ticks() -> Vec<u64> {
    let stat = std::fs::read_to_string("/proc/stat").expect("/proc/stat");
    let line = stat.lines().find(|l| l.starts_with("cpu ")).expect("the cpu line of /proc/stat");
    line.split_whitespace().skip(1).map(|x| x.parse().expect("a tick count")).collect()
}

/// The guest's CPU between two [`guest_cpu_ticks`] readings: the busy fraction (all but idle
/// and iowait) and the seconds by kind.
fn guest_cpu_between(before: &[u64], after: &[u64]) -> Value {
    // SAFETY: sysconf has no memory effects.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as f64;
    let d: Vec<u64> = after.iter().zip(before).map(|(a, b)| a.saturating_sub(*b)).collect();
    let total: u64 = d.iter().sum();
    let idle = d[3] + d.get(4).copied().unwrap_or(0);
    let mut v = serde_json::json!({ "busy": (total - idle) as f64 / total.max(1) as f64 });
    for (k, name) in ["user", "nice", "system", "idle", "iowait", "irq", "softirq"].iter().enumerate() {
        v[*name] = (d.get(k).copied().unwrap_or(0) as f64 / hz).into();
    }
    v
}

/// CPU time of every thread of the processes `procs` (name, pid), clock ticks (user, system),
/// by `process/thread name` (threads of the same name summed), from `/proc/<pid>/task/*/stat`.
fn thread_ticks(procs: &[(&str, u32)]) -> BTreeMap<String, (u64, u64)> {
    let mut out = BTreeMap::new();
    for (name, pid) in procs {
        for t in std::fs::read_dir(format!("/proc/{pid}/task")).into_iter().flatten().flatten() {
            let Ok(stat) = std::fs::read_to_string(t.path().join("stat")) else { continue };
            let (Some(open), Some(close)) = (stat.find('('), stat.rfind(')')) else { continue };
            // After the name: state (field 3), ..., utime (14), stime (15).
            let f: Vec<u64> = stat[close + 1..].split_whitespace().map(|x| x.parse().unwrap_or(0)).collect();
            let e: &mut (u64, u64) = out.entry(format!("{name}/{}", &stat[open + 1..close])).or_default();
            (e.0, e.1) = (e.0 + f[11], e.1 + f[12]);
        }
    }
    out
}

/// Where the guest's one CPU went between two [`thread_ticks`] readings: seconds by thread,
/// `{"user": s, "system": s}`.
fn cpu_between(before: &BTreeMap<String, (u64, u64)>, after: &BTreeMap<String, (u64, u64)>) -> Value {
    // SAFETY: sysconf has no memory effects.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) }.max(1) as f64;
    let by_thread = after.iter().map(|(k, &(u, s))| {
        let (u0, s0) = before.get(k).copied().unwrap_or_default();
        let secs = |a: u64, b: u64| a.saturating_sub(b) as f64 / hz;
        (k.clone(), serde_json::json!({ "user": secs(u, u0), "system": secs(s, s0) }))
    });
    Value::Object(by_thread.collect())
}

/// Waits until `file` contains `needle` (a process announced it is ready).
fn wait_for_line(file: &Path, needle: &str, limit: Duration) {
    let t0 = Instant::now();
    while !std::fs::read_to_string(file).is_ok_and(|t| t.contains(needle)) {
        assert!(t0.elapsed() < limit, "{} did not say {needle:?} within {limit:?}", file.display());
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn daemon_cmd(dir: &Path, service: &str, tag: &str, cycles: Option<u64>) -> Command {
    let mut c = Command::new(guest_fulcrumd());
    c.args(["--iface", "vcan0", "--service", service])
        .arg("--config")
        .arg(dir.join("fulcrumd.toml"))
        .arg("--record-dir")
        .arg(dir.join(format!("rec-{tag}")))
        .arg("--summary-json")
        .arg(dir.join(format!("{tag}.json")));
    if let Some(n) = cycles {
        c.args(["--cycles", &n.to_string()]);
    }
    c
}

/// Sends the malformed frames: in turn a TPDO of node 1 with DLC 3 (wrong DLC), an unknown
/// COB-ID 0x7FF, an extended identifier 0x181 (unknown ID to us) and a heartbeat of node 1 with
/// an unknown NMT state. Paced at `JUNK_PERIOD_NS` on absolute deadlines. Returns the frames
/// sent by kind and how long the flood took.
fn send_junk(start_ns: u64) -> BTreeMap<&'static str, u64> {
    let mut bus = SocketCanBus::open("vcan0").expect("junk sender: open vcan0");
    let kinds: [(&str, CanFrame); 4] = [
        ("wrong_dlc", CanFrame::new_standard(0x181, &[1, 2, 3]).expect("frame")),
        ("unknown_id", CanFrame::new_standard(0x7FF, &[0xA5; 8]).expect("frame")),
        ("extended_id", CanFrame::new_extended(0x181, &[0; 8]).expect("frame")),
        ("bad_nmt_state", CanFrame::new_standard(0x701, &[0x42]).expect("frame")),
    ];
    let mut sent: BTreeMap<&str, u64> = kinds.iter().map(|(k, _)| (*k, 0)).collect();
    let mut failed = 0u64;
    for i in 0..JUNK_FRAMES {
        // Absolute deadlines: after a stall of the guest the owed frames go out at once, so
        // the flood keeps its 2 kHz on average (in bursts, the harder case for the receivers).
        controller::rt::sleep_until_ns(start_ns + i * JUNK_PERIOD_NS).expect("sleep");
        let (kind, frame) = &kinds[(i % 4) as usize];
        // A full transmit queue (ENOBUFS) is retried: the point is to deliver the flood.
        if send_retrying(&mut bus, frame) {
            *sent.get_mut(kind).expect("kind") += 1;
        } else {
            failed += 1;
        }
    }
    sent.insert("send_failed", failed);
    sent.insert("duration_ms", (monotonic_now_ns() - start_ns) / 1_000_000);
    // The sender thread's own CPU (it ends before the driver reads the others').
    // SAFETY: rusage is plain integers (all-zero is valid), and getrusage writes only into the
    // struct we own.
    let ru = unsafe {
        let mut ru: libc::rusage = std::mem::zeroed();
        (libc::getrusage(libc::RUSAGE_THREAD, &mut ru) == 0).then_some(ru)
    };
    if let Some(ru) = ru {
        let ms = |t: libc::timeval| t.tv_sec as u64 * 1000 + t.tv_usec as u64 / 1000;
        sent.insert("cpu_ms", ms(ru.ru_utime) + ms(ru.ru_stime));
    }
    sent
}

/// Sends one frame, retrying a full transmit queue (ENOBUFS) up to 100 times 200 µs apart;
/// false when it never went out.
fn send_retrying(bus: &mut SocketCanBus, frame: &CanFrame) -> bool {
    for _ in 0..=100 {
        if bus.send(frame).is_ok() {
            return true;
        }
        std::thread::sleep(Duration::from_micros(200));
    }
    false
}

/// Sends `n` copies of `frame` as fast as vcan0 takes them (a full transmit queue is retried).
/// Returns (sent, failed).
fn send_burst(frame: &CanFrame, n: u64) -> (u64, u64) {
    let mut bus = SocketCanBus::open("vcan0").expect("burst sender: open vcan0");
    let (mut sent, mut failed) = (0, 0);
    for _ in 0..n {
        if send_retrying(&mut bus, frame) {
            sent += 1;
        } else {
            failed += 1;
        }
    }
    (sent, failed)
}

/// Drives `scenario` with its files in a private work directory (the guest's /tmp is a tmpfs:
/// no host file-system traffic while the loop runs), then copies them to `out`.
fn drive(scenario: Scenario, out: &Path) {
    let work = std::env::temp_dir().join(format!("hil-work-{}", std::process::id()));
    std::fs::create_dir_all(&work).expect("work dir");
    // fulcrumd from the guest's own tmpfs, as the robot PC runs it from its local disk
    // ([`guest_fulcrumd`]); not in the work dir, whose files become the artifacts.
    let bin = std::env::temp_dir().join(format!("hil-bin-{}", std::process::id()));
    std::fs::create_dir_all(&bin).expect("bin dir");
    let local = bin.join("fulcrumd");
    std::fs::copy(FULCRUMD, &local).unwrap_or_else(|e| panic!("copy {FULCRUMD} to {}: {e}", local.display()));
    GUEST_FULCRUMD.set(local).expect("one scenario per guest run");
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| drive_in(scenario, &work)));
    copy_dir(&work, out);
    let _ = std::fs::remove_dir_all(&work);
    let _ = std::fs::remove_dir_all(&bin);
    if let Err(panic) = result {
        std::panic::resume_unwind(panic);
    }
}

/// The copy of `fulcrumd` the scenario driver runs (set by [`drive`]).
static GUEST_FULCRUMD: OnceLock<PathBuf> = OnceLock::new();

/// `fulcrumd` as the guest runs it: a copy on the guest's tmpfs. Started from the host's root,
/// which the qemu guest reads over 9p, the 27 MB binary took longer to start, and on a loaded
/// host the restarted daemon of `hil_daemon_sigkill_and_restart` took 1224 ms from its spawn to
/// its first SYNC (the bound is 1 s from the spawn to the subscriber's first sample; 351-405 ms
/// on a less loaded host). `fulcrumd --version` in the qemu guest, three runs each: 963, 622 and
/// 332 ms from the 9p root, 243, 133 and 131 ms from tmpfs (session 18, host load 8-9).
fn guest_fulcrumd() -> &'static Path {
    GUEST_FULCRUMD.get().map_or(Path::new(FULCRUMD), PathBuf::as_path)
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).expect("create dir");
    for e in std::fs::read_dir(from).expect("read dir") {
        let e = e.expect("dir entry");
        let target = to.join(e.file_name());
        if e.file_type().expect("file type").is_dir() {
            copy_dir(&e.path(), &target);
        } else {
            std::fs::copy(e.path(), &target).unwrap_or_else(|err| panic!("copy {}: {err}", e.path().display()));
        }
    }
}

fn drive_in(scenario: Scenario, dir: &Path) {
    let simrobot = std::env::var_os(SIMROBOT_ENV).expect("HIL_SIMROBOT");
    let service = format!("comanip-hil/{scenario:?}/{}", std::process::id());
    std::fs::write(dir.join("simrobot.toml"), scenario.simrobot_toml()).expect("write simrobot.toml");
    std::fs::write(dir.join("fulcrumd.toml"), daemon_config(scenario)).expect("write fulcrumd.toml");
    let twin: sim::twin::TwinConfig = toml::from_str(&scenario.simrobot_toml()).expect("twin config");
    let scenario_samples = sim::twin::SimRobot::new(&twin).expect("twin").scenario().truth.len() as u64;
    let mut driver = serde_json::Map::new();
    driver.insert("scenario".into(), format!("{scenario:?}").into());
    driver.insert("scenario_samples".into(), scenario_samples.into());
    driver.insert("hil_mode".into(), std::env::var("HIL_MODE").unwrap_or_default().into());
    driver.insert("period_us".into(), period_us(scenario).into());

    // Softirqs (which deliver every CAN frame to the sockets, after the kernel has stamped it)
    // run in ksoftirqd when deferred; at its normal priority it waits behind the daemon's
    // SCHED_FIFO loop, which then closes its window before frames stamped inside it are
    // delivered. As on a PREEMPT_RT robot PC, where the softirq threads are given a priority
    // above the application's, ksoftirqd gets SCHED_FIFO 95. Only in the throw-away guest.
    if matches!(std::env::var("HIL_MODE").as_deref(), Ok("uml") | Ok("qemu")) {
        let mut raised = Vec::new();
        for e in std::fs::read_dir("/proc").expect("/proc").flatten() {
            let comm = std::fs::read_to_string(e.path().join("comm")).unwrap_or_default();
            if comm.starts_with("ksoftirqd") {
                let pid = e.file_name().to_string_lossy().into_owned();
                let ok = Command::new("chrt").args(["-f", "-p", "95", &pid]).status().is_ok_and(|s| s.success());
                assert!(ok, "chrt -f -p 95 {pid} (ksoftirqd) failed");
                raised.push(pid);
            }
        }
        assert!(!raised.is_empty(), "no ksoftirqd thread found in the guest");
        driver.insert("ksoftirqd_fifo95".into(), raised.join(",").into());
    }

    if scenario == Scenario::Malformed {
        // (Before candump starts: the probe frame is not part of the scenario's bus.)
        // hw-io's SocketCAN options the daemon relies on, on the guest's real kernel: the
        // receive queue it asks for, and the echo of its own frame with a kernel stamp.
        let mut probe = SocketCanBus::open("vcan0").expect("open vcan0");
        let granted = probe.set_receive_buffer(daemon_rx_buffer()).expect("SO_RCVBUF");
        driver.insert("rx_buffer_granted".into(), granted.into());
        probe.receive_own_frames(true).expect("CAN_RAW_RECV_OWN_MSGS");
        let probe_frame = CanFrame::new_standard(0x7FE, &[1, 2, 3, 4]).expect("frame");
        let before_us = hw_io::can::unix_time_now_us();
        probe.send(&probe_frame).expect("send");
        let mut echo = None;
        while let Ok(Some(f)) = probe.recv_timeout(Duration::from_millis(500)) {
            if f.frame == probe_frame {
                echo = Some(f);
                break;
            }
        }
        let echo = echo.expect("the echo of our own frame");
        driver.insert("own_echo_stamp_after_send_start".into(), (echo.unix_time_us >= before_us).into());
        drop(probe);
    }

    // The bus observer first, then the subscriber, then the robot; the daemon last.
    // candump at SCHED_FIFO 60 (below the monitor): at normal priority it fell behind during
    // the flood, and was stopped with frames still in its queue.
    let bus_log = File::create(dir.join("bus.log")).expect("bus.log");
    let mut candump = Command::new("chrt")
        .args(["-f", "60", "candump", "-L", "-r", "8388608", "vcan0"])
        .stdin(Stdio::null())
        .stdout(bus_log)
        .stderr(File::create(dir.join("candump.err")).expect("candump.err"))
        .spawn()
        .expect("spawning candump");
    // The subscriber stands for the guidance-force module, a real-time client on the robot PC:
    // SCHED_FIFO 70, below the daemon's loop. At normal priority, in the one-CPU guest on a
    // loaded host, it was starved for up to 0.2 s and its 64-sample buffer overflowed.
    let mut monitor = spawn(
        Command::new("chrt")
            .args(["-f", "70"])
            .arg(guest_fulcrumd())
            .args(["monitor", "--service", &service, "--buffer", &HIL_SUBSCRIBER_BUFFER.to_string()])
            .arg("--summary-json")
            .arg(dir.join("monitor.json"))
            .arg("--samples-out")
            .arg(dir.join("monitor.jsonl")),
        dir,
        "monitor",
    );
    // The encoder nodes are hardware of their own on the robot: their answer does not wait for
    // the controller's CPU. In the one-CPU guest, simrobot gets a real-time priority above the
    // daemon's loop (SCHED_FIFO 80) so that it answers a SYNC at once, all three TPDOs in a row.
    // The camera scenario: a frame monitor subscribes first, then simrobot films the arms.
    let frames_service = format!("comanip-hil/frames/{}", std::process::id());
    let calib_service = format!("comanip-hil/calibration/{}", std::process::id());
    let mut frame_monitor = (scenario == Scenario::Camera).then(|| {
        write_endoscope_config(dir, CAMERA_SIZE, CAMERA_FPS);
        let bin = std::env::var_os(CAMERA_BIN_ENV).expect("HIL_CAMERA_BIN");
        let child = spawn(
            Command::new(bin)
                .args(["monitor", "--service", &frames_service, "--every-frame"])
                .args(["--start-timeout-s", "600", "--idle-timeout-s", "600"])
                .arg("--summary-json")
                .arg(dir.join("frames.json")),
            dir,
            "frame-monitor",
        );
        wait_for_line(&dir.join("frame-monitor.out"), "subscribed", Duration::from_secs(60));
        child
    });
    // The live calibration: its subscriber first, then the process, before the robot and the
    // daemon.
    let mut calib_procs = (scenario == Scenario::CalibLive).then(|| {
        let cam = write_endoscope_config(dir, CALIB_CAMERA_SIZE, CALIB_CAMERA_FPS);
        std::fs::write(
            dir.join("comanip-calib.toml"),
            calib_live_config(dir, &cam, &service, &frames_service, &calib_service),
        )
        .expect("write comanip-calib.toml");
        let bin = std::env::var_os(CALIB_BIN_ENV).expect("HIL_CALIB_BIN");
        let monitor = spawn(
            Command::new(&bin)
                .args(["monitor", "--service", &calib_service])
                .arg("--out")
                .arg(dir.join("calibration.jsonl")),
            dir,
            "calib-monitor",
        );
        wait_for_line(&dir.join("calib-monitor.err"), "subscribed", Duration::from_secs(60));
        // SCHED_FIFO 50, below every other real-time process of the guest (candump 60, the
        // monitor 70, the daemon 80, simrobot 90), as candump and the monitor get theirs: at
        // normal priority (nice 10, as its unit) in the one-CPU guest on the shared host, its
        // bus listener read 6-18 % of the frames and the kernel dropped the rest (measured).
        let live = spawn(
            Command::new("chrt")
                .args(["-f", "50"])
                .arg(&bin)
                .arg("live")
                .arg("--live-config")
                .arg(dir.join("comanip-calib.toml"))
                .arg("--summary-json")
                .arg(dir.join("calib-live.json"))
                .env("RUST_LOG", "info"),
            dir,
            "calib-live",
        );
        wait_for_line(&dir.join("calib-live.err"), "publishing on", Duration::from_secs(60));
        (live, monitor)
    });
    // The live tracker: its subscriber first, then the process, before the robot and the daemon.
    let track_service = format!("comanip-hil/track/{}", std::process::id());
    let mut track_procs = (scenario == Scenario::TrackLive).then(|| {
        let cam = write_endoscope_config(dir, TRACK_CAMERA_SIZE, TRACK_CAMERA_FPS);
        let k = &cam.camera.intrinsics;
        for (name, baseline) in [("left.yaml", None), ("right.yaml", Some(cam.camera.baseline_m))] {
            std::fs::write(dir.join(name), hw_io::calib_files::write_camera_info_yaml(name, k, baseline))
                .expect("write the camera_info");
        }
        // The rig (T_b_e, the hand-eye, the instrument) is the configuration's default, which is
        // the twin's; the calibration service has no publisher: the configuration's is used.
        std::fs::write(
            dir.join("comanip-track.toml"),
            format!(
                "mode = \"ours\"\nparticles = {TRACK_PARTICLES}\n[filter]\nanneal_layers = 1\n\
                 [joints]\ntool_max_gap_ms = {g:?}\ntool_max_age_ms = {a:?}\nendoscope_max_gap_ms = {g:?}\n\
                 endoscope_max_age_ms = {a:?}\nwait_ms = {a:?}\n",
                g = TRACK_JOINTS_GAP_MS,
                a = TRACK_JOINTS_AGE_MS
            ),
        )
        .expect("write comanip-track.toml");
        let bin = std::env::var_os(TRACK_BIN_ENV).expect("HIL_TRACK_BIN");
        let monitor = spawn(
            Command::new(&bin)
                .args(["monitor", "--service", &track_service, "--format", "json"])
                .arg("--out")
                .arg(dir.join("track.jsonl"))
                .arg("--summary-json")
                .arg(dir.join("track-monitor.json")),
            dir,
            "track-monitor",
        );
        wait_for_line(&dir.join("track-monitor.err"), "subscribed", Duration::from_secs(60));
        // Real-time priority 50, as the live calibration and for the same reason (at the unit's
        // nice 15 on the guest's one CPU its bus listener would get too little of it), but
        // SCHED_RR: the tracker's main thread and its bus listener thread share the priority,
        // and when the overloaded guest keeps the listener's queue full, a SCHED_FIFO listener
        // never blocks and the main thread never runs (seen: no frame taken in 200 s).
        let live = spawn(
            Command::new("chrt")
                .args(["-r", "50"])
                .arg(&bin)
                .args(["live", "--iface", "vcan0", "--status-every-s", "5"])
                .arg("--config")
                .arg(dir.join("comanip-track.toml"))
                .arg("--fulcrumd-config")
                .arg(dir.join("fulcrumd.toml"))
                .arg("--cameras")
                .arg(dir.join("left.yaml"))
                .arg(dir.join("right.yaml"))
                .args(["--frame-service", &frames_service])
                .args(["--calibration-service", &calib_service])
                .args(["--output-service", &track_service])
                .arg("--summary-json")
                .arg(dir.join("track-live.json"))
                .env("RUST_LOG", "info"),
            dir,
            "track-live",
        );
        wait_for_line(&dir.join("track-live.err"), "waiting for frames", Duration::from_secs(60));
        (live, monitor)
    });
    let mut robot_cmd = Command::new("chrt");
    robot_cmd
        .args(["-f", "90"])
        .arg(&simrobot)
        .args(["live", "--iface", "vcan0", "--twin-clock"])
        .arg("--config")
        .arg(dir.join("simrobot.toml"))
        .arg("--truth")
        .arg(dir.join("truth.jsonl"))
        .arg("--summary-json")
        .arg(dir.join("simrobot.json"));
    if matches!(scenario, Scenario::Camera | Scenario::CalibLive | Scenario::TrackLive) {
        robot_cmd
            .args(["--camera", "--camera-service", &frames_service])
            .arg("--endoscope-config")
            .arg(dir.join("endoscope.toml"));
    }
    let mut robot = spawn(&mut robot_cmd, dir, "simrobot");
    wait_for_line(&dir.join("simrobot.out"), "answering", Duration::from_secs(60));
    wait_for_line(&dir.join("monitor.err"), "waiting for samples", Duration::from_secs(60));

    match scenario {
        Scenario::Clean
        | Scenario::NodeSilent
        | Scenario::EmcyBurst
        | Scenario::Camera
        | Scenario::CalibLive
        | Scenario::TrackLive => {
            // The clean run covers the whole scenario (one SYNC = one sample); the fault
            // scenarios their first FAULT_RUN_CYCLES samples; the camera scenario 3000 (6 s).
            let cycles = match scenario {
                Scenario::Clean => scenario_samples,
                Scenario::Camera => 3_000,
                Scenario::CalibLive => CALIB_RUN_CYCLES,
                Scenario::TrackLive => TRACK_RUN_CYCLES,
                _ => FAULT_RUN_CYCLES,
            };
            // Where the guest's one CPU goes while the daemon runs (docs/hil.md, "The qemu
            // fallback"): the guest's busy fraction and each thread's share.
            let mut procs = watched_procs(&driver, &robot, &monitor, &candump);
            procs.extend(frame_monitor.as_ref().map(|c| ("frame-monitor", c.id())));
            procs.extend(calib_procs.as_ref().map(|(c, _)| ("calib-live", c.id())));
            procs.extend(track_procs.as_ref().map(|(c, _)| ("track-live", c.id())));
            let (cpu0, threads0, t0) = (guest_cpu_ticks(), thread_ticks(&procs), Instant::now());
            let mut daemon = spawn(&mut daemon_cmd(dir, &service, "daemon", Some(cycles)), dir, "daemon");
            if scenario == Scenario::CalibLive {
                // The session runs until the first valid calibration reaches the subscriber (and
                // 2 s more), at most CALIB_RUN_CYCLES: how many observations the collector keeps
                // by a given cycle depends on the host's speed, the publication does not.
                let published = wait_for_published_calibration(&dir.join("calibration.jsonl"), &mut daemon);
                driver.insert("calibration_published_in_session".into(), published.into());
                if published {
                    std::thread::sleep(Duration::from_secs(2));
                    signal(&daemon, libc::SIGINT);
                }
            }
            if scenario == Scenario::TrackLive {
                let tracked = wait_for_tracking(&dir.join("track.jsonl"), TRACK_WANTED, &mut daemon);
                driver.insert("tracking_reached_in_session".into(), tracked.into());
                if tracked {
                    std::thread::sleep(Duration::from_secs(2));
                    signal(&daemon, libc::SIGINT);
                }
            }
            let limit = Duration::from_secs(cycles * u64::from(period_us(scenario)) * 4 / 1_000_000 + 60);
            // The daemon's own threads, read until it exits.
            let mut daemon_ticks = BTreeMap::new();
            while daemon.try_wait().expect("try_wait").is_none() && t0.elapsed() < limit {
                daemon_ticks = thread_ticks(&[("fulcrumd", daemon.id())]);
                std::thread::sleep(Duration::from_millis(100));
            }
            driver.insert("daemon_exit".into(), wait_exit(&mut daemon, "fulcrumd", limit).into());
            let mut threads1 = thread_ticks(&procs);
            threads1.append(&mut daemon_ticks);
            driver.insert("daemon_wall_s".into(), t0.elapsed().as_secs_f64().into());
            driver.insert("guest_cpu_while_daemon_ran".into(), guest_cpu_between(&cpu0, &guest_cpu_ticks()));
            driver.insert("cpu_s_while_daemon_ran".into(), cpu_between(&threads0, &threads1));
        }
        Scenario::Malformed => {
            // Counted in the daemon's cycles (the samples the subscriber has written), not in
            // wall time (JUNK_START_CYCLES): the flood from sample 2500 on; once it is over and
            // JUNK_TAIL_CYCLES later (MALFORMED_MIN_CYCLES at least), SIGINT (the daemon's
            // normal stop): every junk frame goes out while it runs.
            let procs = watched_procs(&driver, &robot, &monitor, &candump);
            let (cpu0, threads0, t0) = (guest_cpu_ticks(), thread_ticks(&procs), Instant::now());
            let mut daemon = spawn(&mut daemon_cmd(dir, &service, "daemon", None), dir, "daemon");
            let samples_file = dir.join("monitor.jsonl");
            let mut published = LineCounter::default();
            let limit = |cycles: u64| Duration::from_secs(cycles * u64::from(period_us(scenario)) * 4 / 1_000_000 + 60);
            let at_start = published.wait_for(&samples_file, JUNK_START_CYCLES, &mut daemon, limit(JUNK_START_CYCLES));
            let sent = std::thread::spawn(move || send_junk(monotonic_now_ns())).join().expect("junk sender panicked");
            let at_end = published.poll(&samples_file);
            driver.insert("junk_sent".into(), serde_json::to_value(sent).expect("json"));
            let stop_at = MALFORMED_MIN_CYCLES.max(at_end + JUNK_TAIL_CYCLES);
            assert!(
                stop_at < scenario_samples,
                "the flood ended at sample {at_end}: the run would outlast the twin's {scenario_samples} samples"
            );
            published.wait_for(&samples_file, stop_at, &mut daemon, limit(stop_at - at_end));
            let mut threads1 = thread_ticks(&[("fulcrumd", daemon.id())]);
            signal(&daemon, libc::SIGINT);
            for (k, v) in [("junk_start_sample", at_start), ("junk_end_sample", at_end), ("stop_sample", stop_at)] {
                driver.insert(k.into(), v.into());
            }
            driver.insert("daemon_exit".into(), wait_exit(&mut daemon, "fulcrumd", Duration::from_secs(30)).into());
            threads1.append(&mut thread_ticks(&procs));
            driver.insert("daemon_wall_s".into(), t0.elapsed().as_secs_f64().into());
            driver.insert("guest_cpu_while_daemon_ran".into(), guest_cpu_between(&cpu0, &guest_cpu_ticks()));
            driver.insert("cpu_s_while_daemon_ran".into(), cpu_between(&threads0, &threads1));
        }
        Scenario::RxOverflow => {
            // The daemon runs the fault scenarios' cycles; once it has detected the instrument in
            // its trocar it is stopped, a burst floods the bus, and it continues. No
            // cycle runs while it is stopped (no SYNC, so the robot, on its twin clock, sends
            // nothing either): the burst is the only traffic, and what the daemon's queue cannot
            // hold the kernel drops.
            let mut daemon = spawn(&mut daemon_cmd(dir, &service, "daemon", Some(FAULT_RUN_CYCLES)), dir, "daemon");
            wait_for_line(&dir.join("daemon.err"), "DETECTED inside", Duration::from_secs(120));
            signal(&daemon, libc::SIGSTOP);
            let stop_ns = monotonic_now_ns();
            let frame = CanFrame::new_standard(OVERFLOW_COB_ID, &[0x5A; 8]).expect("frame");
            let (sent, failed) = send_burst(&frame, OVERFLOW_BURST_FRAMES);
            let burst_ms = (monotonic_now_ns() - stop_ns) / 1_000_000;
            std::thread::sleep(Duration::from_millis(OVERFLOW_MIN_STOP_MS.saturating_sub(burst_ms)));
            // Taken before SIGCONT: every cycle the daemon starts after it has a later SYNC time.
            let cont_ns = monotonic_now_ns();
            signal(&daemon, libc::SIGCONT);
            for (k, v) in [("stop_ns", stop_ns), ("cont_ns", cont_ns), ("burst_sent", sent), ("burst_failed", failed)] {
                driver.insert(k.into(), v.into());
            }
            let limit = Duration::from_secs(FAULT_RUN_CYCLES * u64::from(HIL_PERIOD_US) * 4 / 1_000_000 + 60);
            driver.insert("daemon_exit".into(), wait_exit(&mut daemon, "fulcrumd", limit).into());
        }
        Scenario::KillRestart => {
            let mut first = spawn(&mut daemon_cmd(dir, &service, "daemon-1", None), dir, "daemon-1");
            std::thread::sleep(Duration::from_millis(FIRST_RUN_MS));
            signal(&first, libc::SIGKILL);
            driver.insert("kill_ns".into(), monotonic_now_ns().into());
            let code = wait_exit(&mut first, "fulcrumd (killed)", Duration::from_secs(10));
            driver.insert("daemon_1_exit".into(), code.into());
            std::thread::sleep(Duration::from_millis(DOWN_MS));
            driver.insert("restart_spawn_ns".into(), monotonic_now_ns().into());
            let mut second =
                spawn(&mut daemon_cmd(dir, &service, "daemon-2", Some(SECOND_RUN_CYCLES)), dir, "daemon-2");
            let code = wait_exit(&mut second, "fulcrumd (restarted)", Duration::from_secs(60));
            driver.insert("daemon_2_exit".into(), code.into());
        }
    }
    // Let the last samples and frames reach their readers, then stop them (SIGINT: each
    // writes its summary). candump exits at SIGINT without reading what is still queued: wait
    // until its log has stopped growing.
    std::thread::sleep(Duration::from_millis(500));
    let log_len = || std::fs::metadata(dir.join("bus.log")).map(|m| m.len()).unwrap_or(0);
    let (mut last, t0) = (log_len(), Instant::now());
    loop {
        std::thread::sleep(Duration::from_millis(500));
        let now = log_len();
        if now == last || t0.elapsed() > Duration::from_secs(60) {
            break;
        }
        last = now;
    }
    // The live calibration before the robot: it writes its summary at SIGINT; then its
    // subscriber, which has every message by then.
    if let Some((live, calib_monitor)) = calib_procs.as_mut() {
        signal(live, libc::SIGINT);
        driver.insert("calib_live_exit".into(), wait_exit(live, "comanip-calib live", Duration::from_secs(30)).into());
        std::thread::sleep(Duration::from_millis(300));
        signal(calib_monitor, libc::SIGINT);
        let code = wait_exit(calib_monitor, "comanip-calib monitor", Duration::from_secs(30));
        driver.insert("calib_monitor_exit".into(), code.into());
    }
    for (child, name) in [(&mut monitor, "monitor"), (&mut robot, "simrobot"), (&mut candump, "candump")] {
        signal(child, libc::SIGINT);
        let code = wait_exit(child, name, Duration::from_secs(30));
        driver.insert(format!("{name}_exit"), code.into());
    }
    // The tracker after the robot: every frame the camera sent is in its queue. It works through
    // them (2 s), then gets SIGINT and writes its summary; then its subscriber.
    if let Some((live, track_monitor)) = track_procs.as_mut() {
        std::thread::sleep(Duration::from_secs(2));
        signal(live, libc::SIGINT);
        driver.insert("track_live_exit".into(), wait_exit(live, "comanip-track live", Duration::from_secs(30)).into());
        std::thread::sleep(Duration::from_millis(300));
        signal(track_monitor, libc::SIGINT);
        let code = wait_exit(track_monitor, "comanip-track monitor", Duration::from_secs(30));
        driver.insert("track_monitor_exit".into(), code.into());
    }
    // The frame monitor last: simrobot's camera has stopped, every frame it sent is in.
    if let Some(child) = frame_monitor.as_mut() {
        std::thread::sleep(Duration::from_millis(300));
        signal(child, libc::SIGINT);
        let code = wait_exit(child, "frame monitor", Duration::from_secs(30));
        driver.insert("frame_monitor_exit".into(), code.into());
    }
    std::fs::write(dir.join("driver.json"), serde_json::to_string_pretty(&driver).expect("json"))
        .expect("write driver.json");
}

/// The renderer's configuration of the camera scenarios (`endoscope.toml`): the default
/// endoscope scaled to `size`, at `fps`, without motion blur or defocus (the guest's one CPU
/// goes to the real-time processes first: keep each frame cheap). Returns it.
fn write_endoscope_config(dir: &Path, size: (u32, u32), fps: u64) -> sim::endoscope::EndoscopeConfig {
    let mut cfg = sim::world::default_endoscope_config();
    let (w, h) = size;
    let k = f64::from(w) / f64::from(cfg.camera.intrinsics.width);
    let i = &mut cfg.camera.intrinsics;
    (i.width, i.height, i.fx, i.fy) = (w, h, i.fx * k, i.fy * k);
    (i.cx, i.cy) = (f64::from(w - 1) / 2.0, f64::from(h - 1) / 2.0);
    cfg.timing.fps = fps as f64;
    cfg.realism.motion_blur.enabled = false;
    cfg.realism.defocus.enabled = false;
    std::fs::write(dir.join("endoscope.toml"), toml::to_string(&cfg).expect("endoscope toml"))
        .expect("write endoscope.toml");
    cfg
}

/// `comanip-calib live`'s configuration in the guest: the rendered camera, the scenario's
/// services, fulcrumd's configuration (its encoders, deadline, health, buffer), relaxed targets
/// and pairing gaps for the guest's coarse timing: its daemon skips periods under load, and with
/// 60 ms 77 of 189 frames fell in a gap between two endoscope samples (one run).
fn calib_live_config(
    dir: &Path,
    cam: &sim::endoscope::EndoscopeConfig,
    fulcrum: &str,
    frames: &str,
    calibration: &str,
) -> String {
    let k = &cam.camera.intrinsics;
    let he = &cam.camera.hand_eye;
    format!(
        "[bus]\niface = \"vcan0\"\nfulcrumd_config = \"{fcfg}\"\n\n\
         [services]\nframes = \"{frames}\"\nfulcrum = \"{fulcrum}\"\ncalibration = \"{calibration}\"\n\n\
         [camera]\nintrinsics = {{ fx = {fx:?}, fy = {fy:?}, cx = {cx:?}, cy = {cy:?}, skew = {skew:?}, width = {w}, height = {h}, distortion = {dist:?} }}\n\
         baseline_m = {b:?}\nhand_eye = {{ translation_m = {t:?}, quaternion_wxyz = {q:?} }}\n\n\
         [target]\ntranslation_mm = {CALIB_TARGET_MM:?}\nrotation_deg = {CALIB_TARGET_DEG:?}\n\n\
         [output]\nresult_file = \"{out}\"\nprogress_every_s = 5.0\nmax_age_ms = 200.0\n\n\
         [pairing]\nendoscope_max_gap_ms = 150.0\n",
        fcfg = dir.join("fulcrumd.toml").display(),
        fx = k.fx,
        fy = k.fy,
        cx = k.cx,
        cy = k.cy,
        skew = k.skew,
        w = k.width,
        h = k.height,
        dist = k.distortion,
        b = cam.camera.baseline_m,
        t = he.translation_m,
        q = he.quaternion_wxyz,
        out = dir.join("calibration-live.json").display(),
    )
}

// ------------------------------------------------------------------------------------------
// Host side: reading the artifacts

/// One line of `fulcrumd monitor --samples-out`.
type Sample = SampleLine;

fn samples(a: &Artifacts) -> Vec<Sample> {
    let f = File::open(a.dir.join("monitor.jsonl")).expect("monitor.jsonl");
    BufReader::new(f).lines().map(|l| serde_json::from_str(&l.expect("read line")).expect("sample line")).collect()
}

/// The frames candump saw, by COB-ID (extended IDs with bit 31 set).
struct BusLog {
    by_id: BTreeMap<u32, u64>,
    /// Frames other than SYNC (0x080) after the last SYNC.
    after_last_sync: u64,
    /// TPDOs (0x181..=0x183 with 8 data bytes) after the last SYNC.
    tpdos_after_last_sync: u64,
    /// TPDOs in the whole log.
    tpdos: u64,
    /// Frames other than SYNC and the overflow burst ([`OVERFLOW_COB_ID`]) from the burst's
    /// first frame to the first SYNC after it (0 without a burst): frames that may have met the
    /// daemon's full queue in the overflow scenario.
    others_during_burst: u64,
}

impl BusLog {
    fn count(&self, id: u32) -> u64 {
        self.by_id.get(&id).copied().unwrap_or(0)
    }
    fn syncs(&self) -> u64 {
        self.count(0x080)
    }
    fn non_sync(&self) -> u64 {
        self.by_id.values().sum::<u64>() - self.syncs()
    }
    fn tpdos(&self) -> u64 {
        self.tpdos
    }
}

fn bus_log(a: &Artifacts) -> BusLog {
    let f = File::open(a.dir.join("bus.log")).expect("bus.log");
    let mut r = CandumpReader::new(BufReader::new(f));
    let mut by_id = BTreeMap::new();
    let (mut after_last_sync, mut tpdos_after_last_sync, mut tpdos) = (0, 0, 0);
    let (mut in_burst, mut others_during_burst) = (false, 0);
    while let Some(rec) = r.next_record().expect("bus.log is a candump log") {
        let fr = rec.timed.frame;
        let id = fr.id().raw() | if fr.is_extended() { 1 << 31 } else { 0 };
        *by_id.entry(id).or_insert(0) += 1;
        if id == u32::from(OVERFLOW_COB_ID) {
            in_burst = true;
        } else if id == 0x080 {
            in_burst = false;
        } else if in_burst {
            others_during_burst += 1;
        }
        if id == 0x080 {
            after_last_sync = 0;
            tpdos_after_last_sync = 0;
        } else {
            after_last_sync += 1;
            let tpdo = u64::from((0x181..=0x183).contains(&id) && fr.data().len() == 8);
            tpdos_after_last_sync += tpdo;
            tpdos += tpdo;
        }
    }
    BusLog { by_id, after_last_sync, tpdos_after_last_sync, tpdos, others_during_burst }
}

fn u(v: &Value) -> u64 {
    v.as_u64().unwrap_or_else(|| panic!("not a count: {v}"))
}

/// Stretches (first, last) of consecutive samples with `pred`, by index.
fn stretches<T>(xs: &[T], pred: impl Fn(&T) -> bool) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut start = None;
    for (i, x) in xs.iter().enumerate() {
        match (pred(x), start) {
            (true, None) => start = Some(i),
            (false, Some(s)) => {
                out.push((s, i - 1));
                start = None;
            }
            _ => {}
        }
    }
    if let Some(s) = start {
        out.push((s, xs.len() - 1));
    }
    out
}

/// What one daemon run left, read back.
struct RunCheck {
    records: Vec<CycleRecord>,
    config: Config,
    rec_dir: PathBuf,
}

/// Health flags a scenario may raise besides the ones every run may see.
#[derive(Clone, Copy)]
struct Allowed {
    emcy: bool,
    /// The daemon's receive queue may overflow (the scenario floods it on purpose).
    rx_drops: bool,
}

/// Checks shared by every daemon run: what the daemon published is what the monitor received
/// (every cycle, in order), the recording replays bit for bit, and the health rules hold cycle
/// by cycle on what acquisition had (timing-independent):
/// - a cycle missing a TPDO is flagged `INCOMPLETE_CYCLE`, and only such a cycle;
/// - `NODE_STALE[k]` exactly when node k's TPDO has been missing `stale_after_cycles` cycles
///   in a row;
/// - published valid exactly when no invalidating flag is set (never from stale data), no NaN;
/// - after a detector reset (a node flag), the first valid cycle carries `DETECTOR_RESET`;
/// - no heartbeat loss, bad sample, SYNC or bus error; no EMCY unless the scenario has some.
fn check_run(a: &Artifacts, summary: &str, rec_dir: &str, run_samples: &[&Sample], allowed: Allowed) -> RunCheck {
    let d = a.json(summary);
    let cycles = u(&d["cycles"]);
    assert!(cycles > 0);
    assert_eq!(d["published"], cycles, "every cycle published: {d}");
    assert_eq!(d["publish_errors"], 0);
    if !allowed.rx_drops {
        // Counted by the kernel (SO_RXQ_OVFL): no frame was lost on the daemon's socket.
        assert_eq!(d["bus_dropped_rx_frames"], 0, "the daemon's receive queue overflowed: {d}");
    }
    assert_eq!(d["recorder_queue_drops"], 0);
    // The monitor received every published sample, in order.
    assert_eq!(run_samples.len() as u64, cycles, "monitor received {} of {cycles}", run_samples.len());
    for (i, s) in run_samples.iter().enumerate() {
        assert_eq!(s.sequence, i as u64, "sample {i} of the run: {s:?}");
        assert_eq!(s.run_id, u(&d["run_id"]));
        assert!(s.fulcrum_base_m.iter().chain(&s.joints_rad).all(|v| v.is_finite()), "{s:?}");
    }
    // The flight recording: what acquisition had each cycle, and what was published.
    let rec_dir = a.dir.join(rec_dir);
    let rec_path = std::fs::read_dir(&rec_dir)
        .expect("recording dir")
        .map(|e| e.expect("dir entry").path())
        .find(|p| p.extension().is_some_and(|e| e == "rec"))
        .expect("a recording file");
    let (config, run_id, records, _truncations) = replay::load_recording(&rec_path).expect("recording reads");
    assert_eq!(run_id, u(&d["run_id"]));
    assert_eq!(records.len() as u64, cycles, "one record per cycle");
    let stale_after = config.health.stale_after_cycles;
    let mut missing_run = [0u32; 3];
    let mut reset_pending = false;
    let never = HealthFlags::BAD_SAMPLE
        | HealthFlags::SYNC_SEND_FAILED
        | HealthFlags::BUS_ERROR
        | HealthFlags::NODE_HEARTBEAT.into_iter().collect()
        | if allowed.emcy { HealthFlags::empty() } else { HealthFlags::NODE_EMCY.into_iter().collect() };
    // The stale-data policy (docs/daemon.md): EMCY and heartbeat faults reset; a gap of
    // invalid cycles resets when longer than `detector.max_gap_s` (counted once the detector
    // has stepped), and is resumed otherwise.
    let fault_flags: HealthFlags = HealthFlags::NODE_EMCY.into_iter().chain(HealthFlags::NODE_HEARTBEAT).collect();
    let max_gap_cycles = config.detector.max_gap_s / config.detector.sample_period_s + 1e-9;
    let mut gap_cycles = 0u64;
    let mut stepped = false;
    for (r, s) in records.iter().zip(run_samples) {
        let seq = r.sequence;
        assert_eq!(seq, s.sequence);
        // Published = recorded.
        assert_eq!((r.output.state, r.output.health, r.output.fulcrum_base_m), (s.state, s.health, s.fulcrum_base_m));
        let h = r.output.health;
        assert!(!h.intersects(never), "cycle {seq}: unexpected flags {h}");
        assert_eq!(r.input.received_mask != ALL_NODES, h.contains(HealthFlags::INCOMPLETE_CYCLE), "cycle {seq}: {r:?}");
        for (k, run) in missing_run.iter_mut().enumerate() {
            *run = if r.input.received_mask & (1 << k) == 0 { *run + 1 } else { 0 };
            let stale = h.contains(HealthFlags::NODE_STALE[k]);
            assert_eq!(*run >= stale_after, stale, "cycle {seq}: NODE_STALE[{k}] rule: {r:?}");
        }
        // Never a valid estimate from stale, missing or faulty data.
        assert_eq!(
            r.output.state == OutputState::Invalid,
            h.intersects(HealthFlags::INVALIDATING),
            "cycle {seq}: {r:?}"
        );
        if h.intersects(fault_flags) {
            reset_pending = true;
        }
        if r.output.state == OutputState::Invalid {
            gap_cycles += u64::from(stepped);
        } else {
            let expected = reset_pending || gap_cycles as f64 > max_gap_cycles;
            assert_eq!(
                h.contains(HealthFlags::DETECTOR_RESET),
                expected,
                "cycle {seq}: first valid cycle after {gap_cycles} invalid ones (fault {reset_pending}): {r:?}"
            );
            reset_pending = false;
            gap_cycles = 0;
            stepped = true;
        }
    }
    let rr = replay::replay_recording(&rec_path).expect("replay --recording");
    assert!(rr.reproduced(), "the recording does not replay bit for bit: {rr:?}");
    RunCheck { records, config, rec_dir }
}

/// The candump log replays to the estimates of the daemon's own recording, bit for bit (the
/// daemon cuts the bus into cycles by the frames' bus timestamps, the rule the replay applies
/// to the log), through the library and through `fulcrumd replay --candump ... --recording`.
fn check_candump_replay(a: &Artifacts, run: &RunCheck) -> LogReplay {
    let log = replay::replay_candump(&a.dir.join("bus.log"), &run.config).expect("replay --candump");
    let c = replay::compare_with_recording(&log, &run.records, &run.config).expect("compare");
    eprintln!("candump replay against the recording: {c:?}");
    if c.identical_inputs != run.records.len() as u64 {
        // For diagnosis: the first cycles whose inputs differ, with the log line times.
        let diff: Vec<_> = log
            .cycles
            .iter()
            .zip(&run.records)
            .filter(|(l, r)| !replay::same_bus_input(&l.input, &r.input))
            .take(5)
            .map(|(l, r)| {
                format!(
                    "cycle {} (SYNC at {} us): log {:?} vs daemon {:?} (woke {} ns late, cycle {} ns)",
                    r.sequence, l.sync_unix_us, l.input, r.input, r.wake_late_ns, r.cycle_ns
                )
            })
            .collect();
        eprintln!("first differing cycles (log cycle k = daemon cycle k):\n{}", diff.join("\n"));
    }
    assert!(c.offset.is_some(), "the candump log does not line up with the recording: {c:?}");
    assert_eq!(c.compared, run.records.len() as u64, "{c:?}");
    assert_eq!(c.identical_inputs, c.compared, "{c:?}");
    assert_eq!(c.identical_outputs, c.compared, "{c:?}");
    let out = Command::new(FULCRUMD)
        .args(["replay", "--candump"])
        .arg(a.dir.join("bus.log"))
        .arg("--recording")
        .arg(&run.rec_dir)
        .output()
        .expect("fulcrumd replay");
    assert!(out.status.success(), "fulcrumd replay --candump: {}", String::from_utf8_lossy(&out.stdout));
    log
}

/// Frames: every frame the robot (and the junk sender) sent is in the candump log, every SYNC
/// was answered, every TPDO reached the daemon (in its cycle or late).
fn check_frames(a: &Artifacts, summary: &str, junk_frames: u64) -> BusLog {
    let d = a.json(summary);
    let r = a.json("simrobot.json");
    let bus = bus_log(a);
    let cycles = u(&d["cycles"]);
    assert_eq!(r["send_errors"], 0, "{r}");
    assert_eq!(r["sync_gaps"], 0, "simrobot missed SYNCs: {r}");
    assert_eq!(u(&r["syncs"]), cycles, "every SYNC answered: {r}");
    assert_eq!(bus.syncs(), cycles, "candump saw every SYNC");
    assert_eq!(bus.non_sync(), u(&r["frames_sent"]) + junk_frames, "candump saw every frame sent");
    let acq = &d["acquisition"];
    // Every TPDO reached the daemon, except those after its last cycle's window (it stopped);
    // every other frame reached it or was dropped by the kernel (counted; 0 unless the scenario
    // overflows the daemon's queue on purpose, check_run).
    let tpdos = u(&acq["tpdos"]) + u(&acq["late_tpdos"]);
    assert!(tpdos <= bus.tpdos() && tpdos + bus.tpdos_after_last_sync >= bus.tpdos(), "{acq}, bus {}", bus.tpdos());
    let seen = u(&acq["frames"]) + u(&d["bus_dropped_rx_frames"]);
    assert!(seen <= bus.non_sync() && seen + bus.after_last_sync >= bus.non_sync(), "{acq}, bus {}", bus.non_sync());
    bus
}

fn monitor_summary_ok(a: &Artifacts, restarts: u64) {
    let m = a.json("monitor.json");
    assert_eq!(m["missed"], 0, "{m}");
    assert_eq!(m["restarts"], restarts, "{m}");
    assert_eq!(m["rejected"], 0, "{m}");
    assert_eq!(m["valid_with_invalidating_flags"], 0, "{m}");
    assert_eq!(m["non_finite"], 0, "{m}");
}

fn one_run(a: &Artifacts, allowed: Allowed) -> (Vec<Sample>, RunCheck) {
    assert_eq!(a.driver["daemon_exit"], 0, "the daemon exits cleanly: {}", a.driver);
    for p in ["monitor", "simrobot", "candump"] {
        assert_eq!(a.driver[format!("{p}_exit")], 0, "{p}: {}", a.driver);
    }
    monitor_summary_ok(a, 0);
    let s = samples(a);
    let run = check_run(a, "daemon.json", "rec-daemon", &s.iter().collect::<Vec<_>>(), allowed);
    let d = a.json("daemon.json");
    eprintln!(
        "daemon: {} cycles, {} incomplete (late answers or faults), {} periods skipped, wake-up lateness p50/p99/max {}/{}/{} us",
        d["cycles"],
        d["acquisition"]["incomplete_cycles"],
        d["overruns"],
        d["timing"]["wake_late"]["p50_us"],
        d["timing"]["wake_late"]["p99_us"],
        d["timing"]["wake_late"]["max_us"]
    );
    (s, run)
}

fn fulcrumd_stderr(a: &Artifacts, name: &str) -> String {
    std::fs::read_to_string(a.dir.join(format!("{name}.err"))).unwrap_or_default()
}

/// Per SYNC in the candump log: did node `cob_id - 0x180` send its TPDO before the next SYNC?
fn tpdo_sent_per_sync(a: &Artifacts, cob_id: u32) -> Vec<bool> {
    let f = File::open(a.dir.join("bus.log")).expect("bus.log");
    let mut r = CandumpReader::new(BufReader::new(f));
    let mut out: Vec<bool> = Vec::new();
    while let Some(rec) = r.next_record().expect("candump log") {
        let fr = rec.timed.frame;
        match (fr.is_extended(), fr.id().raw()) {
            (false, 0x080) => out.push(false),
            (false, id) if id == cob_id && fr.data().len() == 8 => {
                if let Some(last) = out.last_mut() {
                    *last = true;
                }
            }
            _ => {}
        }
    }
    out
}

/// Scores (sample, state, fulcrum) against `truth`; invalid samples are skipped (the last
/// valid estimate holds).
fn score_valid(
    truth: &TruthFile,
    estimates: impl Iterator<Item = (u64, OutputState, [f64; 3])>,
) -> controller::scoring::ScoreReport {
    let detections = estimates.filter(|&(_, state, _)| state != OutputState::Invalid).map(|(sample, state, f)| {
        let inside = state == OutputState::Inside;
        let fulcrum = inside.then(|| nalgebra::Vector3::new(f[0], f[1], f[2]));
        (At::Sample(sample), Detected { inside, fulcrum_base_m: fulcrum })
    });
    let score = score_detections(truth, detections, WRONG_TROCAR_M).expect("score");
    controller::scoring::ScoreReport::from_score(&score)
}

// ------------------------------------------------------------------------------------------
// The tests

/// Several insert/extract cycles over vcan: every insertion detected, every cycle published
/// and received, every frame accounted for, and the candump log replays identically.
#[test]
fn hil_clean_insert_extract_cycles() {
    let Some(a) = hil("hil_clean_insert_extract_cycles", Scenario::Clean) else { return };
    let (samples, run) = one_run(&a, Allowed { emcy: false, rx_drops: false });
    let bus = check_frames(&a, "daemon.json", 0);
    let d = a.json("daemon.json");
    assert_eq!(u(&d["cycles"]), u(&a.driver["scenario_samples"]), "the whole scenario ran");
    let acq = &d["acquisition"];
    for k in ["unknown_id_frames", "wrong_dlc_frames", "malformed_frames", "foreign_node_frames", "emcy_frames"] {
        assert_eq!(acq[k], 0, "{k}: {acq}");
    }
    // The robot answered every SYNC: a missing TPDO in the daemon is a late one, never a lost one.
    for id in 0x181..=0x183 {
        assert!(tpdo_sent_per_sync(&a, id).iter().all(|&sent| sent), "node {:#x} skipped a SYNC", id);
    }
    // The endoscope arm's nodes 4 and 5 on the same bus (simrobot's default): their TPDOs
    // answered exactly every 10th SYNC (counter 10, 20, ..., 240), and the daemon counted
    // each of their frames it received as another node's, none as bad or foreign (above), and
    // raised no flag for them (check_run).
    for id in [0x184, 0x185] {
        let sent = tpdo_sent_per_sync(&a, id);
        let tenth: Vec<bool> = (1..=sent.len()).map(|k| k.is_multiple_of(10)).collect();
        assert!(sent == tenth, "node {:#x}: TPDOs not exactly at every 10th SYNC", id - 0x180);
    }
    let ecm_on_bus: u64 = [0x184, 0x185, 0x704, 0x705].iter().map(|&id| bus.count(id)).sum();
    assert!(bus.count(0x184) >= bus.syncs() / 10 && bus.count(0x704) > 0, "the endoscope arm was on the bus");
    let other = u(&acq["other_node_frames"]);
    assert!(other <= ecm_on_bus && other + bus.after_last_sync >= ecm_on_bus, "{acq}: {ecm_on_bus} on the bus");
    eprintln!("endoscope arm: {ecm_on_bus} frames on the bus, {other} counted by the daemon as other nodes'");
    let incomplete = u(&acq["incomplete_cycles"]);
    check_candump_replay(&a, &run);

    // Detection through the whole chain, against simrobot's ground truth (sample n = the n-th
    // SYNC answered = the daemon's sequence n, as every SYNC was answered). An invalid sample is
    // no estimate: the last valid one holds (a client does not take a late answer for an
    // extraction).
    let truth = TruthFile::open(&a.dir.join("truth.jsonl")).expect("truth.jsonl");
    let live = score_valid(&truth, samples.iter().map(|s| (s.sequence, s.state, s.fulcrum_base_m)));
    eprintln!("live over vcan ({} TPDOs, {incomplete} late-answer cycles): {}", bus.tpdos(), live.describe());
    assert!(live.insertions >= 4, "{live:?}");
    assert_eq!(live.insertions_detected, live.insertions, "every insertion detected: {}", live.describe());
    assert_eq!(live.extractions_detected, live.extractions, "every extraction detected: {}", live.describe());

    // False detections: compared with the detector on the same scenario offline (`simrobot
    // generate`: the same counts per sample, no bus timing at all). With every cycle complete
    // the chain must reproduce it sample for sample; a late answer freezes the detector for
    // that cycle, so then the counts are compared. A false detection offline is the
    // detector's own (docs/hil.md, docs/status.md), not the chain's.
    let offline = a.dir.join("offline");
    let out = Command::new(simrobot())
        .args(["generate", "--out"])
        .arg(&offline)
        .arg("--config")
        .arg(a.dir.join("simrobot.toml"))
        .output()
        .expect("simrobot generate");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let off_log = replay::replay_candump(&offline.join("bus.log"), &run.config).expect("offline replay");
    let off_truth = TruthFile::open(&offline.join("truth.jsonl")).expect("offline truth");
    let off = score_valid(
        &off_truth,
        off_log.cycles.iter().enumerate().map(|(k, c)| (k as u64, c.output.state, c.output.fulcrum_base_m)),
    );
    eprintln!("offline (same scenario and configuration, no bus timing): {}", off.describe());
    assert_eq!(off_log.cycles.len(), samples.len());
    if incomplete == 0 {
        for (o, s) in off_log.cycles.iter().zip(&samples) {
            assert_eq!((o.output.state, o.output.fulcrum_base_m), (s.state, s.fulcrum_base_m), "sample {}", s.sequence);
        }
    }
    // A guest stall of 3 cycles or more makes a node stale, and the stale-data policy resets
    // the detector (its history then differs from the offline run's, legitimately); without
    // such a reset, the chain must not change the number of false detections.
    let resets = samples.iter().filter(|s| s.health.intersects(HealthFlags::DETECTOR_RESET)).count();
    assert_eq!(off.false_detections, 0, "the detector's own false detections on this scenario: {}", off.describe());
    if resets == 0 {
        assert_eq!(live.false_detections, 0, "false detections over vcan: {}", live.describe());
    } else {
        eprintln!(
            "{resets} detector resets after guest stalls (stale nodes): false detections live {} vs offline {} not compared",
            live.false_detections, off.false_detections
        );
    }
}

/// Node 2 stops answering for 200 ms, then answers again.
#[test]
fn hil_node_silent_200ms_then_back() {
    let Some(a) = hil("hil_node_silent_200ms_then_back", Scenario::NodeSilent) else { return };
    let (samples, run) = one_run(&a, Allowed { emcy: false, rx_drops: false });
    check_frames(&a, "daemon.json", 0);
    check_candump_replay(&a, &run);
    // On the bus: node 2 skipped the SYNCs of one stretch (the 200 ms window), and only those.
    let sent = tpdo_sent_per_sync(&a, 0x182);
    let silent = stretches(&sent, |&s| !s);
    assert_eq!(silent.len(), 1, "node 2 silent in {silent:?}");
    let (first, last) = silent[0];
    let len = last - first + 1;
    // 200 ms of twin time = 200 SYNCs, from sample 5000.
    assert_eq!((first, len), (5_000, 200), "node 2 silent for SYNCs {first}..={last}");
    for id in [0x181, 0x183] {
        assert!(tpdo_sent_per_sync(&a, id).iter().all(|&s| s), "only node 2 was silent");
    }
    // The daemon (log cycle k = its cycle k: candump ran first): stale from the 3rd silent
    // cycle to the end of the window, every cycle of the window invalid, valid again after it
    // with the detector reset (checked by the rules in check_run).
    assert!(samples[first..=last].iter().all(|s| s.state == OutputState::Invalid));
    assert!(samples[first + 2..=last].iter().all(|s| s.health.intersects(HealthFlags::NODE_STALE[1])));
    let back = samples[last + 1..].iter().find(|s| s.state != OutputState::Invalid).expect("valid again");
    assert!(back.health.intersects(HealthFlags::DETECTOR_RESET), "{back:?}");
    // The instrument was inside its trocar and detected before the fault, and again after it.
    assert!(samples[..first].iter().any(|s| s.state == OutputState::Inside), "detected before the fault");
    assert!(samples[last..].iter().any(|s| s.state == OutputState::Inside), "re-detected after the fault");
    let log = fulcrumd_stderr(&a, "daemon");
    assert!(log.contains("health node2-stale"), "the daemon logged the stale node:\n{log}");
}

/// Frames with a wrong DLC and unknown identifiers at 2 kHz while the daemon runs.
#[test]
fn hil_malformed_frames_at_2khz() {
    let Some(a) = hil("hil_malformed_frames_at_2khz", Scenario::Malformed) else { return };
    let (samples, run) = one_run(&a, Allowed { emcy: false, rx_drops: false });
    // The SocketCAN options the daemon relies on work on the guest's kernel.
    assert!(u(&a.driver["rx_buffer_granted"]) >= daemon_rx_buffer() as u64, "{}", a.driver);
    assert_eq!(a.driver["own_echo_stamp_after_send_start"], true, "{}", a.driver);
    let sent = &a.driver["junk_sent"];
    assert_eq!(sent["send_failed"], 0, "{sent}");
    let junk: u64 = ["wrong_dlc", "unknown_id", "extended_id", "bad_nmt_state"].iter().map(|k| u(&sent[*k])).sum();
    assert_eq!(junk, JUNK_FRAMES);
    let bus = check_frames(&a, "daemon.json", junk);
    assert_eq!(bus.count(0x7FF), u(&sent["unknown_id"]));
    assert_eq!(bus.count(0x181 | 1 << 31), u(&sent["extended_id"]));
    // The daemon counted each one, by kind, and simrobot ignored them.
    let acq = &a.json("daemon.json")["acquisition"];
    assert_eq!(acq["wrong_dlc_frames"], sent["wrong_dlc"], "{acq}");
    assert_eq!(u(&acq["unknown_id_frames"]), u(&sent["unknown_id"]) + u(&sent["extended_id"]), "{acq}");
    assert_eq!(acq["malformed_frames"], sent["bad_nmt_state"], "{acq}");
    assert_eq!(acq["emcy_frames"], 0);
    // simrobot ignored the junk it read; what its own socket lost of a burst while the single
    // guest CPU ran the others, the kernel counted (SO_RXQ_OVFL): read + dropped = sent. (It
    // reads only SYNCs and the junk, and check_frames found every SYNC answered.)
    let r = a.json("simrobot.json");
    eprintln!("simrobot: {} junk frames read, {} dropped by the kernel", r["ignored"], r["dropped_rx_frames"]);
    assert_eq!(u(&r["ignored"]) + u(&r["dropped_rx_frames"]), junk, "simrobot: junk read + dropped = sent: {r}");
    // The flood is no fault: the robot answered every SYNC (a missing TPDO in the daemon is a
    // late one; the health rules were checked cycle by cycle in check_run), and the estimates
    // are what the bus log replays to.
    for id in 0x181..=0x183 {
        assert!(tpdo_sent_per_sync(&a, id).iter().all(|&s| s), "node {id:#x} skipped a SYNC");
    }
    // The scenario's length in cycles, whatever the period and the load (MALFORMED_MIN_CYCLES):
    // the flood began at sample JUNK_START_CYCLES or later, and the instrument had its first
    // insertion's samples to be detected in.
    assert!(u(&a.driver["junk_start_sample"]) >= JUNK_START_CYCLES, "{}", a.driver);
    assert!(samples.len() as u64 >= MALFORMED_MIN_CYCLES, "{} cycles: {}", samples.len(), a.driver);
    let detected = samples.iter().position(|s| s.state == OutputState::Inside);
    eprintln!(
        "flood from sample {} to {}, stopped at {}; detected at sample {detected:?}",
        a.driver["junk_start_sample"], a.driver["junk_end_sample"], a.driver["stop_sample"]
    );
    assert!(detected.is_some(), "the instrument was detected in its trocar");
    check_candump_replay(&a, &run);
}

/// Node 3 raises five EMCYs in a row, each cleared 40 ms later.
#[test]
fn hil_emcy_burst() {
    let Some(a) = hil("hil_emcy_burst", Scenario::EmcyBurst) else { return };
    let (samples, run) = one_run(&a, Allowed { emcy: true, rx_drops: false });
    let bus = check_frames(&a, "daemon.json", 0);
    check_candump_replay(&a, &run);
    assert_eq!(bus.count(0x083), 2 * EMCY_COUNT, "raise and clear of each EMCY on the bus");
    assert_eq!(u(&a.json("daemon.json")["acquisition"]["emcy_frames"]), 2 * EMCY_COUNT);
    // One flagged stretch per EMCY (raise to clear), every flagged sample invalid, the detector
    // reset after each (rules in check_run); only node 3.
    let st = stretches(&samples, |s| s.health.intersects(HealthFlags::NODE_EMCY[2]));
    assert_eq!(st.len() as u64, EMCY_COUNT, "NODE_EMCY[2] stretches {st:?}");
    assert!(samples.iter().all(|s| !s.health.intersects(HealthFlags::NODE1_EMCY | HealthFlags::NODE2_EMCY)));
    assert!(st.iter().all(|&(f, l)| samples[f..=l].iter().all(|s| s.state == OutputState::Invalid)));
    let last = st.last().map_or(0, |s| s.1);
    assert!(samples[last + 1..].iter().any(|s| s.state == OutputState::Inside), "re-detected after the burst");
    assert!(fulcrumd_stderr(&a, "daemon").contains("node3-emcy"));
}

/// The daemon is killed with SIGKILL and restarted while the monitor keeps running: the
/// monitor sees the restart and receives again within 1 s of the new daemon's start.
#[test]
fn hil_daemon_sigkill_and_restart() {
    let Some(a) = hil("hil_daemon_sigkill_and_restart", Scenario::KillRestart) else { return };
    assert_eq!(a.driver["daemon_1_exit"], -libc::SIGKILL, "{}", a.driver);
    assert_eq!(a.driver["daemon_2_exit"], 0, "the restarted daemon runs and exits cleanly: {}", a.driver);
    for p in ["monitor", "simrobot", "candump"] {
        assert_eq!(a.driver[format!("{p}_exit")], 0, "{p}: {}", a.driver);
    }
    monitor_summary_ok(&a, 1);
    let samples = samples(&a);
    let d2 = a.json("daemon-2.json");
    let run2 = u(&d2["run_id"]);
    let split = samples.iter().position(|s| s.run_id == run2).expect("samples of the restarted daemon");
    let (first_run, second_run) = samples.split_at(split);
    assert!(!first_run.is_empty(), "samples of the first daemon");
    assert!(second_run.iter().all(|s| s.run_id == run2), "an old sample after the restart");
    // The first run: in order from 0, nothing missed, up to the kill.
    for (i, s) in first_run.iter().enumerate() {
        assert_eq!(s.sequence, i as u64);
        assert_eq!(s.event, if i == 0 { SampleEvent::First } else { SampleEvent::InOrder });
    }
    // The monitor reported the restart...
    assert_eq!(second_run[0].event, SampleEvent::Restart, "{:?}", second_run[0]);
    let mon_log = fulcrumd_stderr(&a, "monitor");
    assert!(mon_log.contains(&format!("daemon (re)started: run {run2:016x}")), "{mon_log}");
    // ...and received again within 1 s of the new daemon's spawn.
    let spawn_ns = u(&a.driver["restart_spawn_ns"]);
    let back_ms = second_run[0].rx_ns.saturating_sub(spawn_ns) as f64 * 1e-6;
    eprintln!("restart: first sample of the new run {back_ms:.0} ms after its spawn");
    assert!(second_run[0].rx_ns > spawn_ns && back_ms < 1000.0, "received again after {back_ms:.0} ms");
    // The new run: every cycle from 0, the health rules, its recording replays; its detector
    // starts empty (nothing carried over from the killed run).
    check_run(
        &a,
        "daemon-2.json",
        "rec-daemon-2",
        &second_run.iter().collect::<Vec<_>>(),
        Allowed { emcy: false, rx_drops: false },
    );
    // Its first estimate holds at most its own line.
    assert!(second_run[0].window_fill <= 1, "{:?}", second_run[0]);
    // The killed run's recording is readable up to the kill and reproduces bit for bit.
    let rec1 = std::fs::read_dir(a.dir.join("rec-daemon-1"))
        .expect("rec-daemon-1")
        .map(|e| e.expect("entry").path())
        .find(|p| p.extension().is_some_and(|e| e == "rec"))
        .expect("first run's recording");
    let rr = replay::replay_recording(&rec1).expect("replay of the killed run");
    eprintln!("killed run's recording: {} records, truncations {:?}", rr.records, rr.truncations);
    assert!(rr.records > 0 && rr.identical == rr.records && rr.gap_at.is_none(), "{rr:?}");
}

/// The daemon's receive queue overflows (a small `bus.receive_buffer_bytes`, the daemon
/// stopped with SIGSTOP while a burst floods the bus): the kernel drops frames, and the daemon
/// counts exactly those it lost, reports them while running, and carries on.
#[test]
fn hil_receive_queue_overflow_is_counted() {
    let Some(a) = hil("hil_receive_queue_overflow_is_counted", Scenario::RxOverflow) else { return };
    let (samples, run) = one_run(&a, Allowed { emcy: false, rx_drops: true });
    let sent = u(&a.driver["burst_sent"]);
    assert_eq!((sent, u(&a.driver["burst_failed"])), (OVERFLOW_BURST_FRAMES, 0), "{}", a.driver);
    let bus = check_frames(&a, "daemon.json", sent);
    let d = a.json("daemon.json");
    let dropped = u(&d["bus_dropped_rx_frames"]);
    let acq = &d["acquisition"];
    let read = u(&acq["unknown_id_frames"]);
    eprintln!("burst of {sent} frames while the daemon was stopped: {read} read, {dropped} dropped by the kernel");
    // The queue the daemon asked for was granted (the kernel doubles it), and it overflowed.
    let log = fulcrumd_stderr(&a, "daemon");
    assert!(
        log.contains(&format!("CAN receive queue: {} bytes", 2 * OVERFLOW_RX_BUFFER_BYTES)),
        "the daemon's receive queue:\n{log}"
    );
    assert!(dropped > 0 && read > 0, "{d}");
    // Exactly what was lost: the burst (the only frames with this identifier) is on the bus
    // in full, and each of its frames was read by the daemon or dropped by the kernel. Nothing
    // else was lost: every TPDO reached the daemon (check_frames), and a lost SYNC echo would
    // have made its cycle incomplete without a missing TPDO on the bus (the cycles were checked
    // against the candump log, check_candump_replay).
    assert_eq!(bus.count(u32::from(OVERFLOW_COB_ID)), sent, "candump saw the whole burst");
    // The kernel's count is of every frame it dropped, the burst's or not: a frame that arrived
    // while the queue was full is dropped too. In the loaded guest an answer to the SYNC sent
    // just before the stop can come after the burst's first frames (once: node 3's TPDO 51 ms
    // late, landing after the burst): so each burst frame was read or dropped, and any drop
    // beyond the burst is one of the other frames logged from the burst to the next SYNC.
    let extra = (read + dropped)
        .checked_sub(sent)
        .unwrap_or_else(|| panic!("burst frames read + dropped >= sent: {read} + {dropped} < {sent}: {acq}"));
    assert!(
        extra <= bus.others_during_burst,
        "{extra} drops beyond the burst, but only {} other frames on the bus during it: {acq}",
        bus.others_during_burst
    );
    if extra > 0 {
        eprintln!("{extra} of the {} other frames during the burst met the full queue", bus.others_during_burst);
    }
    // Reported while running (the periodic warning, or the last one at exit), with the total.
    assert!(
        log.contains("CAN frames dropped by the kernel") && log.contains(&format!("; {dropped} since start-up)")),
        "the daemon reported the drops:\n{log}"
    );
    // simrobot's socket (4 MiB) got the burst too: read + dropped = sent.
    let r = a.json("simrobot.json");
    assert_eq!(u(&r["ignored"]) + u(&r["dropped_rx_frames"]), sent, "{r}");
    // The stall: the periods the loop missed are counted and flagged `OVERRUN` on one of the
    // first two cycles after it (stopped in its sleep, the loop first runs the cycle it slept
    // for, woken late by the whole stall, then skips the deadlines that passed; stopped while
    // collecting, it finishes that cycle, then skips). Then the daemon carries on: the health
    // rules held cycle by cycle (check_run), and the instrument is detected in its trocar again.
    let (stop_ns, cont_ns) = (u(&a.driver["stop_ns"]), u(&a.driver["cont_ns"]));
    let stalled_ms = (cont_ns - stop_ns) / 1_000_000;
    let after = samples.iter().position(|s| s.timestamp_ns > cont_ns).expect("cycles after the stop");
    assert!(after > 0);
    eprintln!(
        "stopped {stalled_ms} ms; first cycle after it woke {} us late; health {:#x}, then {:#x}",
        run.records[after].wake_late_ns / 1000,
        samples[after].health,
        samples[after + 1].health
    );
    assert!(
        samples[after..after + 2].iter().any(|s| s.health.intersects(HealthFlags::OVERRUN)),
        "OVERRUN after the stop: {:?}",
        &samples[after..after + 2]
    );
    let skipped_at_least = stalled_ms * 1000 / u64::from(HIL_PERIOD_US) - 1;
    assert!(u(&d["overruns"]) >= skipped_at_least, "{} overruns, stopped {stalled_ms} ms", d["overruns"]);
    assert!(samples[..after].iter().any(|s| s.state == OutputState::Inside), "detected before the stop");
    assert!(samples[after..].iter().any(|s| s.state == OutputState::Inside), "detected after the stop");
    check_candump_replay(&a, &run);
}

/// `simrobot live --camera` and a frame subscriber as two processes beside the daemon on vcan:
/// every frame the camera published arrives, in order, with its mid-exposure time on the frame
/// grid inside the span of the SYNCs the arms answered (the bus clock, moved to
/// `CLOCK_MONOTONIC`); frames the renderer could not make in time are counted, not lost.
#[test]
fn hil_live_camera_frames_in_order_on_the_bus_clock() {
    let Some(a) = hil("hil_live_camera_frames_in_order_on_the_bus_clock", Scenario::Camera) else { return };
    for k in ["daemon_exit", "simrobot_exit", "frame_monitor_exit"] {
        assert_eq!(a.driver[k], 0, "{k}: {}", a.driver);
    }
    let r = a.json("simrobot.json");
    let f = a.json("frames.json");
    eprintln!("simrobot: {r}\nframe monitor: {f}");
    let cam = &r["camera"];
    let received = u(&f["received"]);
    assert!(received >= 5, "frames received: {f}");
    // Every published frame arrived or was counted missed: the frame service keeps 2 frames per
    // subscriber (bounded shared memory), so a guest stall of more than two frame periods
    // before the monitor runs overwrites one (seen once in a clean-clone CI run: 98 received,
    // 2 missed of 100, the monitor's oldest frame 768 ms old). A transport that loses frames
    // for any other reason would miss far more than a tenth.
    let missed = u(&f["missed"]);
    assert_eq!(u(&cam["published"]), received + missed, "every published frame arrived or was counted: {cam} {f}");
    assert!(missed * 10 <= u(&cam["published"]), "frames missed: {f}");
    for k in ["rejected", "restarts", "timestamps_not_increasing"] {
        assert_eq!(f[k], 0, "{k}: {f}");
    }
    assert_eq!(f["first_sequence"], 0);
    assert_eq!(u(&f["last_sequence"]), received + missed - 1);
    assert_eq!(f["format"], format!("{}×{} rgb8 ×2", CAMERA_SIZE.0, CAMERA_SIZE.1));
    // On the frame grid; the frames between first and last were either received or skipped.
    let (t_first, t_last) = (u(&f["first_timestamp_ns"]), u(&f["last_timestamp_ns"]));
    let period = 1_000_000_000 / CAMERA_FPS;
    assert_eq!((t_last - t_first) % period, 0, "timestamps off the frame grid: {f}");
    let slots = (t_last - t_first) / period + 1;
    assert!(slots >= received + missed && slots <= received + missed + u(&f["source_dropped"]), "{slots} slots: {f}");
    assert_eq!(u(&f["source_dropped"]), u(&cam["skipped"]), "{cam} {f}");
    // Filmed on the bus clock: the first exposure starts after the first recorded SYNC
    // (CLOCK_MONOTONIC); frames whose exposure ends after the last SYNC (the daemon stopped,
    // the twin stands still) are rendered with the arms as last recorded, and counted so.
    let (w0, w1) = (u(&r["world_first_mono_ns"]), u(&r["world_last_mono_ns"]));
    let half_exposure = 8_000_000;
    assert!(w0 <= t_first - half_exposure, "first frame at {t_first}, first SYNC at {w0}");
    let stamps: Vec<u64> = std::fs::read_to_string(a.dir.join("frame-monitor.out"))
        .expect("frame-monitor.out")
        .lines()
        .filter_map(|l| l.split("t_mid ").nth(1)?.split(' ').next()?.parse().ok())
        .collect();
    assert_eq!(stamps.len() as u64, received, "one line per frame");
    let after_last_sync = stamps.iter().filter(|&&t| t + half_exposure > w1).count() as u64;
    let during = received - after_last_sync;
    eprintln!("{during} frames while the SYNCs came, {after_last_sync} after; {} uncovered", cam["uncovered"]);
    assert!(during >= 5, "frames filmed while the daemon ran: {during}");
    assert!(u(&cam["uncovered"]) >= after_last_sync, "{cam}");
    assert_eq!(r["world_refused"], 0, "{r}");
}

/// `simrobot live --camera`, fulcrumd and `comanip-calib live` as separate processes on vcan0
/// (frames from the frame service, both arms from the calibration's own passive socket, the
/// tool line from fulcrumd's output): a calibration is published, a subscriber process receives
/// it, and it lies within its own predicted 3σ of the truth (`T_e_t = T_b_e⁻¹` of the twin's
/// endoscope arm); the result file is written; refusals are counted by reason.
#[test]
fn hil_live_calibration_published_within_its_predicted_3_sigma() {
    let Some(a) = hil("hil_live_calibration_published_within_its_predicted_3_sigma", Scenario::CalibLive) else {
        return;
    };
    for k in ["daemon_exit", "simrobot_exit", "calib_live_exit", "calib_monitor_exit"] {
        assert_eq!(a.driver[k], 0, "{k}: {}", a.driver);
    }
    let summary = a.json("calib-live.json");
    eprintln!("comanip-calib live: {summary}");
    // A subscriber received a valid calibration.
    let lines = std::fs::read_to_string(a.dir.join("calibration.jsonl")).expect("calibration.jsonl");
    let msgs: Vec<Value> = lines.lines().map(|l| serde_json::from_str(l).expect("a JSON line")).collect();
    assert!(msgs.iter().any(|m| m["state"] == "collecting"), "collecting states republished");
    // (Session 18 let the qemu guest report no publication as not measured, when every live
    // solve's selection stage was refused; session 19 found why: the twin has no abdominal
    // wall, jaws past the tip point and a noise model 20× its own (docs/calibration.md, "Why
    // the stage ran away on the twin"). A missing publication fails everywhere again.)
    let Some(valid) = msgs.iter().find(|m| m["state"] == "valid") else {
        panic!("a valid calibration received: {summary}");
    };
    eprintln!("first valid calibration: {valid}");
    let f = |v: &Value| v.as_f64().expect("a number");
    let arr = |v: &Value| v.as_array().expect("an array").iter().map(f).collect::<Vec<f64>>();
    let (t, q, m) = (arr(&valid["translation_m"]), arr(&valid["quaternion_wxyz"]), arr(&valid["mean_fulcrum_m"]));
    let est = nalgebra::Isometry3::from_parts(
        nalgebra::Translation3::new(t[0], t[1], t[2]),
        nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[0], q[1], q[2], q[3])),
    );
    let twin: sim::twin::TwinConfig = toml::from_str(&Scenario::CalibLive.simrobot_toml()).expect("twin config");
    let truth = twin.endoscope_arm.rcm_in_tool_base().expect("T_b_e").inverse();
    let p = nalgebra::Point3::new(m[0], m[1], m[2]);
    let err_fulcrum_m = (est * p - truth * p).norm();
    let err_origin_m = (est.translation.vector - truth.translation.vector).norm();
    let err_rot_rad = (est.rotation.inverse() * truth.rotation).angle();
    let (sf, so, sr) =
        (f(&valid["predicted_fulcrum_m"]), f(&valid["predicted_origin_m"]), f(&valid["predicted_rotation_rad"]));
    eprintln!(
        "error at the mean fulcrum {:.3} mm (predicted {:.3} mm, ratio {:.2}); origin {:.3} mm (predicted {:.3}); \
         rotation {:.4}° (predicted {:.4}°, ratio {:.2}); {} observations",
        err_fulcrum_m * 1e3,
        sf * 1e3,
        err_fulcrum_m / sf,
        err_origin_m * 1e3,
        so * 1e3,
        err_rot_rad.to_degrees(),
        sr.to_degrees(),
        err_rot_rad / sr,
        valid["observations"]
    );
    assert!(sf > 0.0 && sr > 0.0 && sf <= CALIB_TARGET_MM * 1e-3 && sr <= CALIB_TARGET_DEG.to_radians(), "{valid}");
    assert!(err_fulcrum_m <= 3.0 * sf, "fulcrum error {err_fulcrum_m} > 3 × {sf}");
    assert!(err_rot_rad <= 3.0 * sr, "rotation error {err_rot_rad} > 3 × {sr}");
    assert!(valid["observations"].as_u64().expect("count") >= 40, "never from too little data: {valid}");
    // The summary agrees, the result file was written, refusals were counted.
    assert!(u(&summary["published"]) >= 1 && u(&summary["result_files"]) >= 1, "{summary}");
    let result = std::fs::read_to_string(a.dir.join("calibration-live.json")).expect("the result file");
    let result: Value = serde_json::from_str(&result).expect("JSON");
    assert_eq!(result["format"], "comanip-calib-result");
    assert!(result["results"][0]["covariance"].is_array(), "{result}");
    assert!(
        u(&summary["frames"]) > 0 && u(&summary["bus_endoscope_samples"]) > 0 && u(&summary["fulcrum_samples"]) > 0
    );
    assert!(summary["refused"].as_object().is_some_and(|r| !r.is_empty()), "refusals counted: {summary}");
}

/// `simrobot live --camera`, fulcrumd and `comanip-track live` as separate processes on vcan0
/// (frames from the frame service, both arms' joints from the tracker's own passive socket at
/// each frame's time, the calibration from the configuration), and `comanip-track monitor` as
/// its consumer: every frame the camera published is accounted for by the tracker (processed,
/// skipped or rejected), every sample it published reaches the consumer or is counted missed,
/// none is refused (no NaN, no pose on a LOST or INVALID sample), and the instrument is tracked
/// (TRACKING: its rendered silhouette fits the images at the joints read from the bus).
#[test]
fn hil_live_tracking_accounts_for_every_frame_and_tracks() {
    let Some(a) = hil("hil_live_tracking_accounts_for_every_frame_and_tracks", Scenario::TrackLive) else {
        return;
    };
    for k in ["daemon_exit", "simrobot_exit", "track_live_exit", "track_monitor_exit"] {
        assert_eq!(a.driver[k], 0, "{k}: {}", a.driver);
    }
    let r = a.json("simrobot.json");
    let live = a.json("track-live.json");
    let mon = a.json("track-monitor.json");
    eprintln!("simrobot camera: {}\ncomanip-track live: {live}\ncomanip-track monitor: {mon}", r["camera"]);
    let c = &live["counters"];
    let (processed, skipped, rejected) = (u(&c["processed"]), u(&c["skipped"]), u(&c["rejected"]));
    let published_frames = u(&r["camera"]["published"]);
    assert!(published_frames >= 20, "frames published by the camera: {}", r["camera"]);
    assert_eq!(processed + skipped + rejected, published_frames, "every frame accounted for: {live}");
    assert_eq!(rejected, 0, "no corrupt frame header on a healthy frame service: {live}");
    let published = u(&live["published"]);
    assert_eq!(published, processed, "one sample per processed frame: {live}");
    // The consumer: every sample received or counted missed, none refused.
    assert_eq!(u(&mon["refused"]), 0, "{mon}");
    assert_eq!(u(&mon["received"]) + u(&mon["missed"]), published, "{mon}");
    assert_eq!(u(&mon["restarts"]), 0, "{mon}");
    let lines: Vec<Value> = std::fs::read_to_string(a.dir.join("track.jsonl"))
        .expect("track.jsonl")
        .lines()
        .map(|l| serde_json::from_str(l).expect("a JSON line"))
        .collect();
    assert_eq!(lines.len() as u64, u(&mon["received"]));
    let mut by_status = BTreeMap::<String, u64>::new();
    let mut last_frame = None;
    for l in &lines {
        let st = l["status"].as_str().expect("status").to_string();
        let fseq = u(&l["frame_sequence"]);
        assert!(last_frame.is_none_or(|p| fseq > p), "frames out of order: {l}");
        last_frame = Some(fseq);
        let nums = |k: &str| l[k].as_array().expect(k).iter().map(|v| v.as_f64().expect("number")).collect::<Vec<_>>();
        let pose: Vec<f64> =
            ["tip_camera_m", "tip_camera_wxyz", "tip_base_m", "tip_base_wxyz"].iter().flat_map(|k| nums(k)).collect();
        match st.as_str() {
            "TRACKING" | "UNCERTAIN" => {
                assert!(pose.iter().all(|v| v.is_finite()), "{l}");
                let q = nums("tip_base_wxyz");
                assert!((q.iter().map(|v| v * v).sum::<f64>() - 1.0).abs() < 1e-6, "a unit quaternion: {l}");
            }
            "LOST" | "INVALID" => assert!(pose.iter().all(|&v| v == 0.0), "no pose without tracking: {l}"),
            other => panic!("unknown status {other}: {l}"),
        }
        if st == "INVALID" {
            assert!(!l["reasons"].as_str().expect("reasons").is_empty(), "an INVALID sample says why: {l}");
        }
        assert!(l["reasons"].as_str().expect("reasons").contains("calibration-from-config"), "{l}");
        *by_status.entry(st).or_default() += 1;
    }
    eprintln!("statuses: {by_status:?}");
    let tracking = by_status.get("TRACKING").copied().unwrap_or(0);
    assert!(tracking >= 10, "the instrument was tracked in {tracking} frames: {by_status:?}");
    if u(&mon["missed"]) == 0 {
        // The tracker's own count agrees with what its consumer saw.
        assert_eq!(u(&live["counters"]["by_status"][1]), tracking, "{live}");
    }
}
