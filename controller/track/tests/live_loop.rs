//! The live loop (`comanip_track::live::run`) on in-process inputs: a rendered sequence's frames
//! in memory, both arms' joints from its candump log. Every frame is accounted for (processed +
//! skipped = delivered; the newest frame wins), the tracked poses follow the rendered truth,
//! and bad input (stale or non-finite joints, a wrong format, a corrupt header, a refused or
//! drifting calibration) gives flagged samples, never a non-finite number.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

mod common;

use std::path::PathBuf;
use std::sync::OnceLock;
use std::sync::atomic::AtomicBool;

use comanip_track::input::Sequence;
use comanip_track::live::{
    ArmJoints, BusJoints, CalibrationPoll, CalibrationSource, Incoming, JointsAt, JointsError, LiveTracker,
    LoopOptions, MemoryFrames, NoCalibration, Rig, run,
};
use hw_io::frame::FrameMeta;
use hw_io::ipc::FrameHeaderError;
use hw_io::ipc::{CalibrationSample, CalibrationState, Message, TrackReasons, TrackSample, TrackStatus};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};

struct Fixture {
    _dir: tempfile::TempDir,
    run: PathBuf,
    seq: Sequence,
}

fn fixture() -> &'static Fixture {
    static F: OnceLock<Fixture> = OnceLock::new();
    F.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let run = common::generate(dir.path());
        let seq = common::sequence(&run);
        Fixture { _dir: dir, run, seq }
    })
}

fn live(seq: &Sequence) -> LiveTracker {
    let fcfg = controller::config::Config::default();
    let model = comanip_track::run::build_model(seq, &comanip_track::config::ToolSection::default(), &fcfg).unwrap();
    let mut c = track::TrackerConfig::new(track::Mode::Ours, 320, 240);
    c.particles = 300;
    let rig = Rig { intrinsics: seq.intrinsics, right_from_left: seq.right_from_left, hand_eye: seq.hand_eye };
    LiveTracker::new(c, model, rig, seq.ecm_in_tool_base, 99).unwrap()
}

fn joints(f: &Fixture) -> BusJoints {
    common::bus_joints(&f.run)
}

fn pose(p: [f64; 3], q: [f64; 4]) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::from(Vector3::from(p)),
        UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3])),
    )
}

fn all_finite(s: &TrackSample) -> bool {
    s.tip_camera_m
        .iter()
        .chain(&s.tip_camera_wxyz)
        .chain(&s.tip_base_m)
        .chain(&s.tip_base_wxyz)
        .chain([&s.jaw_rad, &s.spread_m, &s.best_cost_px])
        .chain(&s.camera_delta)
        .all(|v| v.is_finite())
}

fn run_burst(f: &Fixture, first: usize, n: usize, burst: usize) -> Vec<TrackSample> {
    let mut l = live(&f.seq);
    let mut src = MemoryFrames::new(common::memory_frames(&f.seq, first..first + n), burst);
    let mut out: Vec<TrackSample> = Vec::new();
    let stop = AtomicBool::new(false);
    let opts = LoopOptions { max_frames: Some(n as u64), idle_timeout: Some(std::time::Duration::ZERO), stop: &stop };
    let c = run(&mut l, &mut src, &mut joints(f), &mut NoCalibration, &mut out, &opts, &mut |_, _| {}).unwrap();
    assert_eq!(c.processed + c.skipped, n as u64, "every frame processed or skipped: {c:?}");
    assert_eq!(c.processed, out.len() as u64);
    out
}

#[test]
fn every_frame_is_accounted_for_the_newest_wins_and_the_poses_follow_the_truth() {
    let f = fixture();
    let first = common::first_in_view(&f.seq);
    let n = 12.min(f.seq.frames.len() - first);
    assert!(n >= 8, "the sequence is too short: {n} frames in view");

    // One frame at a time: all processed, in order, consecutive message numbers.
    let all = run_burst(f, first, n, 1);
    assert_eq!(all.len(), n);
    for (k, s) in all.iter().enumerate() {
        assert_eq!(s.sequence, k as u64);
        assert_eq!(s.frame_sequence, (first + k) as u64);
        assert_eq!(s.frames_skipped, 0);
        assert_eq!(s.check(), Ok(()), "{s:?}");
        assert!(all_finite(s));
        assert!(s.reasons().contains(TrackReasons::CALIBRATION_FROM_CONFIG), "no live calibration: said so");
        assert_eq!(s.calibration_source, 0);
    }
    assert!(all[0].reasons().contains(TrackReasons::REINITIALISED), "the first frame initialises");
    let mut errs: Vec<f64> = all
        .iter()
        .skip(2)
        .filter(|s| s.status().is_some_and(TrackStatus::has_pose))
        .map(|s| {
            let truth = f.seq.frames[s.frame_sequence as usize].truth.unwrap();
            comanip_track::run::errors(&pose(s.tip_camera_m, s.tip_camera_wxyz), &truth).0
        })
        .collect();
    assert!(errs.len() >= 5, "poses on {} of {} frames after the first two", errs.len(), n - 2);
    let (median, _) = comanip_track::experiment::median_p95(&mut errs);
    assert!(median < 3.0, "median tip error {median:.2} mm (the offline run's bound on this sequence)");

    // Three frames arrive per step: the newest is tracked, the other two are counted as skipped.
    let some = run_burst(f, first, n, 3);
    assert_eq!(some.len(), n.div_ceil(3));
    for (k, s) in some.iter().enumerate() {
        let newest = (first + (3 * k + 2).min(n - 1)) as u64;
        assert_eq!(s.frame_sequence, newest, "sample {k} is of the newest frame");
        assert_eq!(s.frames_processed, k as u64 + 1);
        assert_eq!(s.frames_skipped, ((3 * k + 3).min(n) - (k + 1)) as u64);
        assert!(s.reasons().contains(TrackReasons::SKIPPED_BEFORE), "{:?}", s.reasons());
        assert_eq!(s.check(), Ok(()));
    }
}

/// Told to stop with frames still waiting (published while the loop was busy): they are counted
/// as skipped, a corrupt one as rejected with its refusal published, none tracked; without the
/// stop's drain the counters would account for none of them.
#[test]
fn frames_waiting_at_the_stop_are_counted_not_lost() {
    let f = fixture();
    let first = common::first_in_view(&f.seq);
    let mut frames = common::memory_frames(&f.seq, first..first + 3);
    frames.insert(1, Incoming::Rejected(FrameHeaderError::Version { found: 9, expected: 1 }));
    let mut l = live(&f.seq);
    let mut src = MemoryFrames::new(frames, 1).waiting(4);
    let mut out: Vec<TrackSample> = Vec::new();
    let stop = AtomicBool::new(true);
    let opts = LoopOptions { max_frames: None, idle_timeout: None, stop: &stop };
    let c = run(&mut l, &mut src, &mut joints(f), &mut NoCalibration, &mut out, &opts, &mut |_, _| {}).unwrap();
    assert_eq!((c.processed, c.skipped, c.rejected), (0, 3, 1), "{c:?}");
    assert_eq!(out.len(), 1, "one refusal published");
    assert_eq!(out[0].status(), Some(TrackStatus::Invalid));
}

/// Joints from the log, NaN for one frame.
struct NanAt(BusJoints, u64);

impl JointsAt for NanAt {
    fn joints_at(&mut self, frame: &FrameMeta) -> Result<ArmJoints, JointsError> {
        let mut j = self.0.joints_at(frame)?;
        if frame.sequence == self.1 {
            j.tool_rad[2] = f64::NAN;
        }
        Ok(j)
    }
}

/// Calibration polls in order, then nothing.
struct Scripted(Vec<CalibrationPoll>);

impl CalibrationSource for Scripted {
    fn poll(&mut self) -> CalibrationPoll {
        if self.0.is_empty() { CalibrationPoll::Nothing } else { self.0.remove(0) }
    }
}

#[test]
fn bad_input_is_flagged_and_never_published_as_valid() {
    let f = fixture();
    let first = common::first_in_view(&f.seq);
    let mut frames = common::memory_frames(&f.seq, first..first + 8);
    // Frame 2: a corrupt header (refused by the source). Frame 3: mono. Frame 4: stamped an
    // hour after the log. Frame 5: NaN joints.
    frames.insert(2, Incoming::Rejected(FrameHeaderError::Version { found: 9, expected: 1 }));
    if let Incoming::Frame(m) = &mut frames[3] {
        m.meta.eyes = 1;
    }
    if let Incoming::Frame(m) = &mut frames[4] {
        m.meta.timestamp_ns += 3_600_000_000_000;
    }
    let nan_seq = (first + 4) as u64;
    let t_e_t = f.seq.ecm_in_tool_base.inverse();
    let mut valid = CalibrationSample::collecting(100);
    valid.state = CalibrationState::Valid as u32;
    valid.sequence = 17;
    valid.run_id = 5;
    valid.translation_m = t_e_t.translation.vector.into();
    let q = t_e_t.rotation;
    valid.quaternion_wxyz = [q.w, q.i, q.j, q.k];
    let mut drift = valid;
    drift.state = CalibrationState::Drift as u32;
    // Polls per tracked frame: nothing, valid, refused, nothing, nothing, drift, nothing, ...
    let mut calib = Scripted(vec![
        CalibrationPoll::Nothing,
        CalibrationPoll::Sample(valid),
        CalibrationPoll::Refused,
        CalibrationPoll::Nothing,
        CalibrationPoll::Nothing,
        CalibrationPoll::Sample(drift),
    ]);
    let mut l = live(&f.seq);
    let mut src = MemoryFrames::new(frames, 1);
    let mut out: Vec<TrackSample> = Vec::new();
    let stop = AtomicBool::new(false);
    let opts = LoopOptions { max_frames: None, idle_timeout: Some(std::time::Duration::ZERO), stop: &stop };
    let mut joints = NanAt(joints(f), nan_seq);
    let c = run(&mut l, &mut src, &mut joints, &mut calib, &mut out, &opts, &mut |_, _| {}).unwrap();
    assert_eq!(out.len(), 9, "{out:#?}");
    assert_eq!((c.processed, c.rejected, c.skipped, c.invalid), (8, 1, 0, 3), "{c:?}");
    for s in &out {
        assert_eq!(s.check(), Ok(()), "{s:?}");
        assert!(all_finite(s), "{s:?}");
        if s.status() == Some(TrackStatus::Invalid) {
            assert_eq!(s.tip_camera_m, [0.0; 3]);
            assert_eq!(s.tip_camera_wxyz, [0.0; 4]);
        }
    }
    let st = |s: &TrackSample| s.status().unwrap();
    // 0: configuration's calibration, said so.
    assert!(out[0].reasons().contains(TrackReasons::CALIBRATION_FROM_CONFIG));
    // 1: the live calibration in use.
    assert_eq!((out[1].calibration_source, out[1].calibration_sequence, out[1].calibration_run_id), (1, 17, 5));
    assert!(!out[1].reasons().contains(TrackReasons::CALIBRATION_FROM_CONFIG));
    assert!(st(&out[1]).has_pose(), "{:?}", out[1]);
    // 2: the corrupt header.
    assert_eq!(st(&out[2]), TrackStatus::Invalid);
    assert!(out[2].reasons().contains(TrackReasons::FRAME_HEADER));
    assert_eq!(out[2].frames_rejected, 1);
    // 3: mono frame; the refused calibration message flagged, the previous one kept.
    assert_eq!(st(&out[3]), TrackStatus::Invalid);
    assert!(out[3].reasons().contains(TrackReasons::FRAME_FORMAT | TrackReasons::CALIBRATION_REFUSED));
    assert_eq!(out[3].calibration_source, 1);
    // 4: stale joints of both arms.
    assert_eq!(st(&out[4]), TrackStatus::Invalid);
    assert!(out[4].reasons().contains(TrackReasons::TOOL_JOINTS_STALE | TrackReasons::ENDOSCOPE_JOINTS_STALE));
    // 5: NaN joints.
    assert_eq!(st(&out[5]), TrackStatus::Invalid);
    assert_eq!(out[5].frame_sequence, nan_seq);
    assert!(out[5].reasons().contains(TrackReasons::NOT_FINITE));
    // 6: drift: back to the configuration, flagged.
    assert!(out[6].reasons().contains(TrackReasons::CALIBRATION_DRIFT | TrackReasons::CALIBRATION_FROM_CONFIG));
    assert_eq!(out[6].calibration_source, 0);
    // The good frames after the bad ones are tracked again.
    assert!(out[6..].iter().any(|s| st(s).has_pose()), "{:?}", &out[6..]);
    assert_eq!(out.last().unwrap().frames_invalid, 3);
}
