//! The live loop (`comanip_track::live::run`) in our mode allocates nothing per frame after
//! start-up, in any thread: a counting global allocator watches 30 steady-state frames delivered by
//! an in-process source (in bursts, so that the newest-frame-wins path runs too), joints from
//! the passive bus listener replaying the recorded log, samples into a pre-sized `Vec`.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]

mod common;
#[path = "../../../estimator/track/tests/common/counting.rs"]
mod counting;

use std::sync::atomic::{AtomicBool, Ordering};

use comanip_track::live::{LiveTracker, LoopOptions, MemoryFrames, NoCalibration, Rig, run};
use counting::{COUNT, ON};
use hw_io::ipc::{TrackSample, TrackStatus};

#[test]
fn the_counter_sees_allocations_and_the_live_loop_allocates_nothing_per_frame() {
    ON.store(true, Ordering::SeqCst);
    let v: Vec<u64> = std::hint::black_box(vec![1, 2, 3]);
    ON.store(false, Ordering::SeqCst);
    assert!(COUNT.load(Ordering::SeqCst) >= 1 && v.len() == 3);

    let dir = tempfile::tempdir().unwrap();
    // The tracking thread as the process sets it up: below the listener (its worker threads,
    // started by the first step, inherit it).
    comanip_track::live_cli::become_the_tracking_thread();
    // 15 frames per second: enough frames in view for 30 samples with every other one skipped.
    let run_dir = common::generate_at(dir.path(), 15);
    let seq = common::sequence(&run_dir);
    let fcfg = controller::config::Config::default();
    let model = comanip_track::run::build_model(&seq, &comanip_track::config::ToolSection::default(), &fcfg).unwrap();
    let mut c = track::TrackerConfig::new(track::Mode::Ours, 320, 240);
    c.particles = 300;
    let rig = Rig { intrinsics: seq.intrinsics, right_from_left: seq.right_from_left, hand_eye: seq.hand_eye };
    let mut live = LiveTracker::new(c, model, rig, seq.ecm_in_tool_base, 1).unwrap();
    let first = common::first_in_view(&seq);
    let n = 66.min(seq.frames.len() - first);
    let mut src = MemoryFrames::new(common::memory_frames(&seq, first..first + n), 2);
    let mut joints = common::bus_joints(&run_dir);
    let mut out: Vec<TrackSample> = Vec::with_capacity(64);
    let stop = AtomicBool::new(false);
    let opts = LoopOptions { max_frames: None, idle_timeout: Some(std::time::Duration::ZERO), stop: &stop };
    COUNT.store(0, Ordering::SeqCst);
    let mut seen = 0usize;
    // Start-up: the first two samples (the worker threads start, buffers warm); then count.
    let counters = run(&mut live, &mut src, &mut joints, &mut NoCalibration, &mut out, &opts, &mut |_, _| {
        seen += 1;
        if seen == 2 {
            ON.store(true, Ordering::SeqCst);
        }
    })
    .unwrap();
    ON.store(false, Ordering::SeqCst);
    assert_eq!(COUNT.load(Ordering::SeqCst), 0, "allocations in {} steady-state frames", out.len() - 2);
    assert!(out.len() >= 32, "{} samples: fewer than 30 counted", out.len());
    assert!(counters.skipped >= 5, "the newest-frame-wins path ran: {counters:?}");
    let posed = out.iter().filter(|s| s.status().is_some_and(TrackStatus::has_pose)).count();
    let reasons: Vec<String> = out.iter().map(|s| format!("{:?} {}", s.status(), s.reasons())).collect();
    assert!(
        posed >= out.len() / 2,
        "the frames were tracked ({posed} poses of {}), not refused: {reasons:?}",
        out.len()
    );
    // The tracker's worker threads were started from the lowered tracking thread: same nice.
    let nice = |stat: &str| -> i64 {
        // Fields after the command's closing parenthesis: state is field 3, nice field 19.
        let rest = &stat[stat.rfind(')').unwrap() + 2..];
        rest.split_whitespace().nth(16).unwrap().parse().unwrap()
    };
    let mine = nice(&std::fs::read_to_string("/proc/thread-self/stat").unwrap());
    let mut workers = 0;
    for t in std::fs::read_dir("/proc/self/task").unwrap() {
        let t = t.unwrap().path();
        if std::fs::read_to_string(t.join("comm")).unwrap().starts_with("track-") {
            workers += 1;
            assert_eq!(nice(&std::fs::read_to_string(t.join("stat")).unwrap()), mine, "{}", t.display());
        }
    }
    assert_eq!(workers, track::workers::available_threads() - 1, "the tracker's worker threads");
}
