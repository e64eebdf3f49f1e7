//! The live tracker's message over iceoryx2 (issue 18): published and received field for field,
//! and a sample with a NaN marked as tracking refused by the subscriber.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]

use std::time::Duration;

use hw_io::ipc::{
    Publisher, PublisherOptions, RecvError, Subscriber, TrackReasons, TrackSample, TrackStatus, WaitError,
};

fn service(test: &str) -> String {
    format!("comanip-test/{}/track-{test}", std::process::id())
}

fn tracking(sequence: u64) -> TrackSample {
    let mut s = TrackSample::invalid(TrackReasons::empty());
    s.status = TrackStatus::Tracking as u32;
    s.reasons = TrackReasons::CALIBRATION_FROM_CONFIG.bits();
    s.sequence = sequence;
    s.run_id = 7;
    s.frame_sequence = 10 + sequence;
    s.frame_timestamp_ns = 1_000_000_000 + sequence * 33_333_333;
    s.tip_camera_m = [0.01, -0.003, 0.11];
    s.tip_camera_wxyz = [0.5, 0.5, -0.5, 0.5];
    s.tip_base_m = [0.1, 0.32, 0.05];
    s.tip_base_wxyz = [0.0, 1.0, 0.0, 0.0];
    s.jaw_rad = 0.2;
    s.spread_m = 0.0007;
    s.best_cost_px = 1.4;
    s.frames_processed = sequence + 1;
    s
}

#[test]
fn invalid_then_tracking_samples_are_received_field_for_field() {
    let name = service("roundtrip");
    let mut sub = Subscriber::<TrackSample>::connect(&name).unwrap();
    let mut publisher = Publisher::<TrackSample>::create(&name, &PublisherOptions::default()).unwrap();
    let mut invalid = TrackSample::invalid(TrackReasons::TOOL_JOINTS_STALE);
    invalid.run_id = 7;
    publisher.publish(&invalid).unwrap();
    publisher.publish(&tracking(1)).unwrap();
    let first = sub.wait(Duration::from_secs(1)).unwrap().expect("invalid");
    assert_eq!(first.sample, invalid);
    assert_eq!(first.sample.status(), Some(TrackStatus::Invalid));
    assert!(first.sample.reasons().contains(TrackReasons::TOOL_JOINTS_STALE));
    let second = sub.wait(Duration::from_secs(1)).unwrap().expect("tracking");
    assert_eq!(second.sample, tracking(1));
    assert_eq!(second.sample.status(), Some(TrackStatus::Tracking));
}

#[test]
fn a_tracking_sample_with_a_nan_is_refused() {
    let name = service("nan");
    let mut sub = Subscriber::<TrackSample>::connect(&name).unwrap();
    let mut publisher = Publisher::<TrackSample>::create(&name, &PublisherOptions::default()).unwrap();
    let mut bad = tracking(0);
    bad.tip_camera_m[2] = f64::NAN;
    publisher.publish(&bad).unwrap();
    match sub.wait(Duration::from_secs(1)) {
        Err(WaitError::Recv(RecvError::Invalid { .. })) => {}
        other => panic!("expected an invalid-message refusal, got {other:?}"),
    }
    assert_eq!(sub.counters().rejected, 1);
    publisher.publish(&tracking(1)).unwrap();
    assert_eq!(sub.wait(Duration::from_secs(1)).unwrap().expect("next").sample, tracking(1));
}
