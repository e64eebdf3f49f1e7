//! `comanip-track live` as a process on the host: `comanip-camera images --paced` publishes a
//! rendered sequence on a frame service (stamped on this machine's clock at the recorded
//! intervals), the joints come from the sequence's recorded candump log (matched by the frames'
//! sequence numbers), and the process publishes TrackSamples over iceoryx2. Every published
//! frame is accounted for (processed + skipped + rejected = published), and the poses follow
//! the renderer's truth.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

mod common;

use std::io::BufRead as _;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, mpsc};
use std::time::{Duration, Instant};

use hw_io::ipc::{Subscriber, TrackSample};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};

fn f64s(v: &serde_json::Value) -> Vec<f64> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect()
}

#[test]
fn the_live_process_tracks_a_paced_frame_stream_and_accounts_for_every_frame() {
    let dir = tempfile::tempdir().unwrap();
    let run = common::generate(dir.path());
    let seq = common::sequence(&run);
    let frames_dir = run.join("frames");
    let camera = common::workspace_bin("comanip-camera", "comanip-camera");
    let id = std::process::id();
    let (fsvc, csvc, osvc) =
        (format!("comanip-test/{id}/frames"), format!("comanip-test/{id}/calib"), format!("comanip-test/{id}/track"));
    let cfg = dir.path().join("track.toml");
    std::fs::write(&cfg, "mode = \"ours\"\nparticles = 150\n[filter]\nanneal_layers = 1\n").unwrap();
    let summary = dir.path().join("summary.json");
    let samples = dir.path().join("samples.jsonl");
    // A subscriber of the output on its own thread, reading while the tracker runs (a sample
    // buffered for a publisher that has exited is gone with it).
    let done = Arc::new(AtomicBool::new(false));
    let (ready_tx, ready_rx) = mpsc::channel();
    let sub_thread = {
        let (osvc, done) = (osvc.clone(), Arc::clone(&done));
        std::thread::spawn(move || {
            let mut sub = Subscriber::<TrackSample>::connect(&osvc).unwrap();
            ready_tx.send(()).unwrap();
            let mut got = Vec::new();
            while !done.load(Ordering::Relaxed) {
                if let Some(r) = sub.wait(Duration::from_millis(50)).unwrap() {
                    got.push(r.sample);
                }
            }
            (got, sub.counters())
        })
    };
    ready_rx.recv().unwrap();

    let mut tracker = Command::new(env!("CARGO_BIN_EXE_comanip-track"))
        .args(["live", "--idle-timeout-s", "3", "--status-every-s", "1"])
        .arg("--cameras")
        .arg(frames_dir.join("left.yaml"))
        .arg(frames_dir.join("right.yaml"))
        .arg("--candump")
        .arg(run.join("bus.log"))
        .arg("--candump-frames-index")
        .arg(frames_dir.join("frames.txt"))
        .arg("--rig-from-truth")
        .arg(frames_dir.join("truth.jsonl"))
        .args(["--frame-service", &fsvc, "--calibration-service", &csvc, "--output-service", &osvc])
        .arg("--config")
        .arg(&cfg)
        .arg("--summary-json")
        .arg(&summary)
        .arg("--samples-jsonl")
        .arg(&samples)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Wait until the tracker has subscribed (its start line), so that no frame is published
    // before it listens.
    let (tx, rx) = mpsc::channel();
    let stderr = tracker.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut all = String::new();
        for line in std::io::BufReader::new(stderr).lines().map_while(Result::ok) {
            let _ = tx.send(line.clone());
            all += &line;
            all.push('\n');
        }
        all
    });
    let t0 = Instant::now();
    loop {
        let line = rx.recv_timeout(Duration::from_secs(120)).expect("comanip-track live did not start");
        if line.contains("waiting for frames") {
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(120));
    }
    let cam_summary = dir.path().join("camera.json");
    let published = 30u64.min(seq.frames.len() as u64);
    let o = Command::new(&camera)
        .arg("images")
        .arg(&frames_dir)
        .args(["--paced", "--service", &fsvc, "--frames", &published.to_string(), "--summary-json"])
        .arg(&cam_summary)
        .output()
        .unwrap();
    assert!(o.status.success(), "comanip-camera: {}", String::from_utf8_lossy(&o.stderr));
    let cam: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&cam_summary).unwrap()).unwrap();
    assert_eq!(cam["published"].as_u64(), Some(published));
    let status = tracker.wait().unwrap();
    let log = reader.join().unwrap();
    assert!(status.success(), "comanip-track live failed:\n{log}");

    let s: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&summary).unwrap()).unwrap();
    let c = &s["counters"];
    let (processed, skipped, rejected) =
        (c["processed"].as_u64().unwrap(), c["skipped"].as_u64().unwrap(), c["rejected"].as_u64().unwrap());
    assert_eq!(processed + skipped + rejected, published, "every frame accounted for: {s}");
    assert_eq!(rejected, 0);
    assert_eq!(s["published"].as_u64(), Some(processed));

    let lines: Vec<serde_json::Value> =
        std::fs::read_to_string(&samples).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(lines.len() as u64, processed);
    let mut last_frame = None;
    let mut errs = Vec::new();
    let mut posed = 0;
    for (k, l) in lines.iter().enumerate() {
        assert_eq!(l["sequence"].as_u64(), Some(k as u64));
        let fseq = l["frame_sequence"].as_u64().unwrap();
        assert!(last_frame.is_none_or(|p| fseq > p), "frames out of order");
        last_frame = Some(fseq);
        let st = l["status"].as_str().unwrap();
        assert!(["TRACKING", "UNCERTAIN", "LOST", "INVALID"].contains(&st), "{st}");
        assert!(l["reasons"].as_str().unwrap().contains("calibration-from-config"), "no calibration was published");
        if st == "TRACKING" || st == "UNCERTAIN" {
            posed += 1;
            let p = f64s(&l["tip_camera_m"]);
            let q = f64s(&l["tip_camera_wxyz"]);
            assert!(p.iter().chain(&q).all(|v| v.is_finite()));
            let truth = seq.frames[fseq as usize].truth;
            if posed > 2
                && let Some(t) = truth.filter(|t| t.instrument_px[0] > 400)
            {
                let pose = Isometry3::from_parts(
                    Translation3::from(Vector3::new(p[0], p[1], p[2])),
                    UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3])),
                );
                errs.push(comanip_track::run::errors(&pose, &t).0);
            }
        }
    }
    assert!(errs.len() >= 5, "{} poses compared with the truth ({posed} posed of {processed})", errs.len());
    let (median, _) = comanip_track::experiment::median_p95(&mut errs);
    assert!(median < 3.0, "median tip error {median:.2} mm after convergence");
    // The same samples over iceoryx2: each checked by the subscriber (no NaN marked valid).
    done.store(true, Ordering::Relaxed);
    let (got, counters) = sub_thread.join().unwrap();
    assert_eq!(counters.rejected, 0, "a sample broke its invariants");
    assert_eq!(got.len() as u64 + counters.missed, processed, "every sample received or counted as missed");
    assert!(!got.is_empty(), "nothing received over iceoryx2");
    assert_eq!(got.last().unwrap().frames_processed, processed);
    assert!(s["receive_to_publish"]["count"].as_u64().unwrap() == processed);
}

#[test]
fn live_without_cameras_or_bus_fails_with_a_message() {
    let o = Command::new(env!("CARGO_BIN_EXE_comanip-track")).args(["live"]).output().unwrap();
    assert_eq!(o.status.code(), Some(1));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("no cameras") && e.contains("[rig] cameras"), "{e}");
    // Cameras given, but fulcrumd's default configuration has no bus (its simulated robot).
    let dir = tempfile::tempdir().unwrap();
    let yaml = "image_width: 4\nimage_height: 3\ncamera_name: x\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: [2.0, 0.0, 1.5, 0.0, 2.0, 1.0, 0.0, 0.0, 1.0]\n\
                distortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [0.0, 0.0, 0.0, 0.0, 0.0]\n\
                rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]\n\
                projection_matrix:\n  rows: 3\n  cols: 4\n  data: [2.0, 0.0, 1.5, 0.0, 0.0, 2.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]\n";
    let (l, r) = (dir.path().join("l.yaml"), dir.path().join("r.yaml"));
    std::fs::write(&l, yaml).unwrap();
    std::fs::write(&r, yaml.replace("data: [2.0, 0.0, 1.5, 0.0, 0.0, 2.0", "data: [2.0, 0.0, 1.5, -0.01, 0.0, 2.0"))
        .unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_comanip-track"))
        .arg("live")
        .arg("--cameras")
        .arg(&l)
        .arg(&r)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("no bus") && e.contains("--iface"), "{e}");
    // Durations that are not a positive number of seconds are refused before anything opens.
    for (option, value) in [("--status-every-s", "inf"), ("--idle-timeout-s", "-1"), ("--idle-timeout-s", "nan")] {
        let o = Command::new(env!("CARGO_BIN_EXE_comanip-track"))
            .args(["live", &format!("{option}={value}"), "--cameras"])
            .arg(&l)
            .arg(&r)
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(1), "{option} {value}");
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains(option) && e.contains("positive number of seconds"), "{option} {value}: {e}");
    }
}
