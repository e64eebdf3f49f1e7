//! `comanip-track monitor`: the tracking service read back as a consumer would, in-process
//! (`comanip_track::monitor::monitor`) and as the command.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use comanip_track::monitor::{MonitorFormat, MonitorOptions, StopReason, monitor};
use hw_io::ipc::{Publisher, PublisherOptions, Subscriber, TrackReasons, TrackSample, TrackStatus};

fn service(test: &str) -> String {
    format!("comanip-test/{}/track-monitor-{test}", std::process::id())
}

fn sample(sequence: u64, status: TrackStatus) -> TrackSample {
    let mut s = TrackSample::invalid(TrackReasons::TOOL_JOINTS_STALE);
    s.sequence = sequence;
    s.run_id = 3;
    s.frame_sequence = 100 + sequence;
    s.frames_processed = sequence + 1;
    s.frames_skipped = sequence / 2;
    s.published_ns = hw_io::frame::monotonic_now_ns();
    if status.has_pose() {
        s.status = status as u32;
        s.reasons = 0;
        s.tip_camera_m = [0.01, 0.0, 0.1];
        s.tip_camera_wxyz = [1.0, 0.0, 0.0, 0.0];
        s.tip_base_m = [0.1, 0.2, -0.05];
        s.tip_base_wxyz = [1.0, 0.0, 0.0, 0.0];
        s.spread_m = 0.001;
        s.best_cost_px = 1.5;
    } else if status == TrackStatus::Lost {
        s.status = status as u32;
        s.reasons = 0;
    }
    s
}

#[test]
fn every_sample_is_a_line_and_the_summary_counts_statuses_refusals_and_gaps() {
    let name = service("inproc");
    let mut sub = Subscriber::<TrackSample>::connect(&name).unwrap();
    let mut publisher = Publisher::<TrackSample>::create(&name, &PublisherOptions::default()).unwrap();
    publisher.publish(&sample(0, TrackStatus::Tracking)).unwrap();
    publisher.publish(&sample(1, TrackStatus::Lost)).unwrap();
    // A corrupt sample: a NaN pose marked as tracking, refused by the subscriber.
    let mut bad = sample(2, TrackStatus::Tracking);
    bad.tip_base_m[1] = f64::NAN;
    publisher.publish(&bad).unwrap();
    publisher.publish(&sample(3, TrackStatus::Invalid)).unwrap();
    // Sequence 4 never arrives: a gap of one.
    publisher.publish(&sample(5, TrackStatus::Uncertain)).unwrap();
    let mut out = Vec::new();
    let opts =
        MonitorOptions { format: MonitorFormat::Json, count: Some(4), idle_timeout: Some(Duration::from_secs(5)) };
    let summary = monitor(&mut sub, &opts, &mut out, &AtomicBool::new(false)).unwrap();
    let lines: Vec<serde_json::Value> =
        String::from_utf8(out).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let statuses: Vec<&str> = lines.iter().map(|l| l["status"].as_str().unwrap()).collect();
    assert_eq!(statuses, ["TRACKING", "LOST", "INVALID", "UNCERTAIN"]);
    assert_eq!(lines[0]["tip_base_m"][1].as_f64(), Some(0.2));
    assert_eq!(lines[3]["sequence"].as_u64(), Some(5));
    assert_eq!(summary.stopped, StopReason::Count);
    assert_eq!((summary.tracking, summary.lost, summary.invalid, summary.uncertain), (1, 1, 1, 1));
    assert_eq!(summary.received, 4);
    assert_eq!(summary.refused, 1);
    // The refused sample and the one never published are both gaps in the accepted sequence.
    assert_eq!(summary.missed, 2);
    assert_eq!(summary.last_frames_skipped, Some(2));
    let (p50, p99) = (summary.latency_ms_p50.unwrap(), summary.latency_ms_p99.unwrap());
    assert!(p50.is_finite() && p50 >= 0.0 && p99 >= p50, "{p50} {p99}");
}

#[test]
fn the_monitor_stops_idle_and_at_the_stop_flag() {
    let name = service("idle");
    let mut sub = Subscriber::<TrackSample>::connect(&name).unwrap();
    let opts =
        MonitorOptions { format: MonitorFormat::Text, count: None, idle_timeout: Some(Duration::from_millis(300)) };
    let mut out = Vec::new();
    let summary = monitor(&mut sub, &opts, &mut out, &AtomicBool::new(false)).unwrap();
    assert_eq!(summary.stopped, StopReason::Idle);
    assert_eq!(summary.received, 0);
    assert_eq!(summary.latency_ms_p50, None);
    assert!(out.is_empty());
    let opts = MonitorOptions { format: MonitorFormat::Text, count: None, idle_timeout: None };
    let summary = monitor(&mut sub, &opts, &mut out, &AtomicBool::new(true)).unwrap();
    assert_eq!(summary.stopped, StopReason::Signal);
}

#[test]
fn the_command_prints_text_lines_and_writes_its_summary() {
    let name = service("cli");
    let dir = tempfile::tempdir().unwrap();
    let summary_path = dir.path().join("summary.json");
    let mut child = Command::new(env!("CARGO_BIN_EXE_comanip-track"))
        .args(["monitor", "--service", &name, "--format", "text", "--count", "3", "--idle-timeout-s", "20"])
        .arg("--summary-json")
        .arg(&summary_path)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Publish once the monitor says it is subscribed (a sample before that would not reach it).
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    let mut line = String::new();
    stderr.read_line(&mut line).unwrap();
    assert!(line.contains("subscribed"), "{line}");
    let mut publisher = Publisher::<TrackSample>::create(&name, &PublisherOptions::default()).unwrap();
    publisher.publish(&sample(0, TrackStatus::Tracking)).unwrap();
    publisher.publish(&sample(1, TrackStatus::Lost)).unwrap();
    publisher.publish(&sample(2, TrackStatus::Invalid)).unwrap();
    let out = child.wait_with_output().unwrap();
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut stderr, &mut rest).unwrap();
    assert!(out.status.success(), "{rest}");
    let text = String::from_utf8(out.stdout).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 3, "{text}");
    assert!(lines[0].contains("TRACKING") && lines[0].contains("tip_base_mm=(  100.00,  200.00,  -50.00)"), "{text}");
    assert!(lines[1].contains("LOST") && !lines[1].contains("tip_base_mm"), "{text}");
    assert!(lines[2].contains("INVALID") && lines[2].contains("reasons="), "{text}");
    assert!(rest.contains("3 samples (TRACKING 1, UNCERTAIN 0, LOST 1, INVALID 1)"), "{rest}");
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&summary_path).unwrap()).unwrap();
    assert_eq!(summary["received"].as_u64(), Some(3));
    assert_eq!(summary["stopped"].as_str(), Some("count"));
}

#[test]
fn the_command_fails_when_nothing_arrives() {
    let name = service("silent");
    let out = Command::new(env!("CARGO_BIN_EXE_comanip-track"))
        .args(["monitor", "--service", &name, "--idle-timeout-s", "0.3"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("nothing received within the idle timeout"));
    let out = Command::new(env!("CARGO_BIN_EXE_comanip-track"))
        .args(["monitor", "--service", &name, "--idle-timeout-s", "nan"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--idle-timeout-s must be a positive number"));
}
