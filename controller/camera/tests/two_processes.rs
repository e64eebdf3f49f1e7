//! `comanip-camera images` and `comanip-camera monitor` as two processes: every frame of an
//! image-sequence directory arrives in order, with its timestamp, its pixels saved back equal.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a panic is a failed test")]

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_comanip-camera");

fn rgb(n: u32, eye: u32) -> image::RgbImage {
    image::RgbImage::from_fn(32, 24, |x, y| image::Rgb([n as u8, (eye * 100 + x) as u8, y as u8]))
}

#[test]
fn a_publisher_and_a_monitor_process_see_every_frame_in_order() {
    let dir = tempfile::tempdir().unwrap();
    let frames = 30u32;
    let mut index = String::new();
    for n in 0..frames {
        rgb(n, 0).save(dir.path().join(format!("l{n}.png"))).unwrap();
        rgb(n, 1).save(dir.path().join(format!("r{n}.png"))).unwrap();
        index += &format!("{} 10000000 l{n}.png r{n}.png\n", 5_000_000_000u64 + u64::from(n) * 33_333_333);
    }
    std::fs::write(dir.path().join("frames.txt"), index).unwrap();
    let service = format!("comanip-test/{}/camera-two", std::process::id());
    let saved = dir.path().join("saved");
    let summary = dir.path().join("monitor.json");
    let mut monitor = Command::new(BIN)
        .args(["monitor", "--service", &service, "--frames", &frames.to_string(), "--expect-in-order"])
        .args(["--idle-timeout-s", "10", "--start-timeout-s", "60"])
        .arg("--save")
        .arg(&saved)
        .arg("--summary-json")
        .arg(&summary)
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    // The monitor must be subscribed before the first frame (no history): it says so first.
    let mut out = std::io::BufReader::new(monitor.stdout.take().unwrap());
    let mut line = String::new();
    std::io::BufRead::read_line(&mut out, &mut line).unwrap();
    assert!(line.starts_with("subscribed to"), "{line}");
    let drain = std::thread::spawn(move || std::io::Read::read_to_string(&mut out, &mut String::new()));
    let publisher_summary = dir.path().join("pub.json");
    let status = Command::new(BIN)
        .args(["images", "--paced", "--service", &service])
        .arg(dir.path())
        .arg("--summary-json")
        .arg(&publisher_summary)
        .status()
        .unwrap();
    assert!(status.success(), "{status:?}");
    let start = Instant::now();
    let status = loop {
        if let Some(s) = monitor.try_wait().unwrap() {
            break s;
        }
        assert!(start.elapsed() < Duration::from_secs(60), "monitor did not finish");
        std::thread::sleep(Duration::from_millis(50));
    };
    drain.join().unwrap().unwrap();
    let m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&summary).unwrap()).unwrap();
    assert!(status.success(), "{status:?} {m}");
    assert_eq!(m["received"], frames);
    assert_eq!(m["missed"], 0);
    assert_eq!(m["timestamps_not_increasing"], 0);
    assert_eq!(m["first_sequence"], 0);
    assert_eq!(m["last_sequence"], frames - 1);
    assert_eq!(m["format"], "32×24 rgb8 ×2");
    // Paced: stamped on CLOCK_MONOTONIC at the recorded intervals.
    let span = m["last_timestamp_ns"].as_u64().unwrap() - m["first_timestamp_ns"].as_u64().unwrap();
    assert_eq!(span, u64::from(frames - 1) * 33_333_333);
    assert!(m["median_age_ms"].as_f64().unwrap() >= 0.0);
    let p: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&publisher_summary).unwrap()).unwrap();
    assert_eq!((p["published"].as_u64(), p["source_ended"].as_bool()), (Some(u64::from(frames)), Some(true)));
    // The pixels made the trip unchanged.
    for n in [0, 17, frames - 1] {
        let left = image::open(saved.join(format!("frame_{n:06}_left.png"))).unwrap().to_rgb8();
        let right = image::open(saved.join(format!("frame_{n:06}_right.png"))).unwrap().to_rgb8();
        assert_eq!(left, rgb(n, 0));
        assert_eq!(right, rgb(n, 1));
    }
}
