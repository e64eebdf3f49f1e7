//! The live calibration's message over iceoryx2 (issue 19): published and received field for
//! field, and a broken invariant (a "valid" calibration with a non-unit quaternion) refused by
//! the subscriber.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]

use std::time::Duration;

use hw_io::ipc::{CalibrationSample, CalibrationState, Publisher, PublisherOptions, RecvError, Subscriber, WaitError};

fn service(test: &str) -> String {
    format!("comanip-test/{}/calibration-{test}", std::process::id())
}

fn valid(sequence: u64) -> CalibrationSample {
    let mut c = CalibrationSample::collecting(120);
    c.state = CalibrationState::Valid as u32;
    c.sequence = sequence;
    c.run_id = 42;
    c.timestamp_ns = 5_000_000_000 + sequence;
    c.translation_m = [0.0003, -0.2904, 0.1608];
    let h = std::f64::consts::FRAC_1_SQRT_2;
    c.quaternion_wxyz = [0.0, h, h, 0.0];
    for i in 0..6 {
        c.covariance[i * 7] = if i < 3 { 1e-7 } else { 1e-6 };
    }
    c.predicted_fulcrum_m = 0.9e-3;
    c.predicted_origin_m = 1.2e-3;
    c.predicted_rotation_rad = 3e-3;
    c.mean_fulcrum_m = [0.05, 0.3, 0.2];
    c
}

#[test]
fn collecting_then_valid_calibrations_are_received_field_for_field() {
    let name = service("roundtrip");
    let mut sub = Subscriber::<CalibrationSample>::connect(&name).unwrap();
    let mut publisher = Publisher::<CalibrationSample>::create(&name, &PublisherOptions::default()).unwrap();
    let mut collecting = CalibrationSample::collecting(30);
    collecting.run_id = 42;
    publisher.publish(&collecting).unwrap();
    publisher.publish(&valid(1)).unwrap();
    let first = sub.wait(Duration::from_secs(1)).unwrap().expect("collecting");
    assert_eq!(first.sample, collecting);
    assert_eq!(first.sample.state(), Some(CalibrationState::Collecting));
    let second = sub.wait(Duration::from_secs(1)).unwrap().expect("valid");
    assert_eq!(second.sample, valid(1));
    assert_eq!(second.sample.state(), Some(CalibrationState::Valid));
}

#[test]
fn a_valid_calibration_with_a_non_unit_quaternion_is_refused() {
    let name = service("invalid");
    let mut sub = Subscriber::<CalibrationSample>::connect(&name).unwrap();
    let mut publisher = Publisher::<CalibrationSample>::create(&name, &PublisherOptions::default()).unwrap();
    let mut bad = valid(0);
    bad.quaternion_wxyz = [0.5, 0.0, 0.0, 0.0];
    publisher.publish(&bad).unwrap();
    match sub.wait(Duration::from_secs(1)) {
        Err(WaitError::Recv(RecvError::Invalid { .. })) => {}
        other => panic!("expected an invalid-message refusal, got {other:?}"),
    }
}
