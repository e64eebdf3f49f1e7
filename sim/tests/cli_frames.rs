//! `simrobot generate --frames`: stereo frames of the instrument seen from the endoscope arm,
//! stamped on the bus clock, deterministic by seed, the instrument visible in most frames;
//! the endoscope arm's nodes in bus.log and its joints in truth.jsonl.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::path::{Path, PathBuf};
use std::process::Command;

use hw_io::can::candump::CandumpReader;
use hw_io::can::{Message, SYNC_COB_ID};
use sim::truth_file::TruthFile;

const EXE: &str = env!("CARGO_BIN_EXE_simrobot");
const T0_NS: u64 = 1_700_000_000_000_000_000;

struct Scratch(PathBuf);

impl Scratch {
    fn new(name: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("simrobot-frames-{}-{name}", std::process::id()));
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

/// One insert/extract cycle (about 6 s) and a small image, so that a debug build is quick.
fn configs(dir: &Scratch) -> (PathBuf, PathBuf) {
    let twin = dir.path("twin.toml");
    std::fs::write(&twin, "[scenario]\ncycles = 1\ninside_s = [3.0, 3.5]\noutside_s = [1.0, 1.2]\n").unwrap();
    let endo = dir.path("endoscope.toml");
    let text = "[camera.intrinsics]\nfx = 100.0\nfy = 100.0\ncx = 79.5\ncy = 59.5\nskew = 0.0\nwidth = 160\nheight = 120\n\
                distortion = [-0.08, 0.01, 0.0, 0.0, 0.0]\n[tissue]\nplane_z_m = 0.27\nextent_m = 0.40\ntexture_px = 128\n\
                [realism]\nsecond_instrument = false\n";
    std::fs::write(&endo, text).unwrap();
    (twin, endo)
}

fn generate(twin: &Path, endo: &Path, out: &Path, seed: &str) {
    let o = Command::new(EXE)
        .args(["generate", "--frames", "--fps", "6", "--seed", seed, "--out"])
        .arg(out)
        .arg("--config")
        .arg(twin)
        .arg("--endoscope-config")
        .arg(endo)
        .output()
        .unwrap();
    assert!(o.status.success(), "generate failed: {}", String::from_utf8_lossy(&o.stderr));
}

fn frame_lines(dir: &Path) -> Vec<serde_json::Value> {
    let text = std::fs::read_to_string(dir.join("frames/truth.jsonl")).unwrap();
    text.lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

#[test]
fn frames_are_on_the_bus_clock_deterministic_and_show_the_instrument() {
    let dir = Scratch::new("main");
    let (twin, endo) = configs(&dir);
    let (a, b, c) = (dir.path("a"), dir.path("b"), dir.path("c"));
    generate(&twin, &endo, &a, "3");
    generate(&twin, &endo, &b, "3");
    generate(&twin, &endo, &c, "4");

    // Deterministic by seed: the same bytes, frames included; another seed, other frames.
    for f in ["bus.log", "truth.jsonl", "frames/truth.jsonl", "frames/frame_000010_left.png"] {
        assert_eq!(std::fs::read(a.join(f)).unwrap(), std::fs::read(b.join(f)).unwrap(), "{f}");
    }
    assert_ne!(
        std::fs::read(a.join("frames/truth.jsonl")).unwrap(),
        std::fs::read(c.join("frames/truth.jsonl")).unwrap()
    );

    // The bus clock: the SYNC times of bus.log.
    let mut syncs = Vec::new();
    let mut ecm_tpdos = 0u64;
    for r in CandumpReader::new(std::io::BufReader::new(std::fs::File::open(a.join("bus.log")).unwrap())) {
        let f = r.unwrap();
        if f.frame.id().raw() == u32::from(SYNC_COB_ID) {
            syncs.push(f.unix_time_us);
        } else if let Ok(Message::Tpdo { node, .. }) = Message::decode(&f.frame) {
            ecm_tpdos += u64::from(node.get() >= 4);
        }
    }
    assert_eq!(syncs[0] * 1000, T0_NS);
    assert_eq!(ecm_tpdos, 2 * (syncs.len() as u64 / 10), "two endoscope TPDOs every 10th SYNC");

    let lines = frame_lines(&a);
    assert_eq!(lines[0]["type"], "header");
    assert_eq!(lines[0]["t0_ns"], T0_NS);
    let frames: Vec<_> = lines.iter().filter(|l| l["type"] == "frame").collect();
    let end = lines.last().unwrap();
    assert_eq!(end["type"], "end");
    assert_eq!(end["frames"], frames.len() as u64);
    // 6 fps over the run, the last exposure within it.
    let run_s = syncs.len() as f64 * 1e-3;
    assert!(frames.len() as f64 >= (run_s - 0.1) * 6.0 && frames.len() as f64 <= run_s * 6.0 + 1.0, "{}", frames.len());
    let truth = TruthFile::open(&a.join("truth.jsonl")).unwrap();
    let (mut visible, mut agree) = (0, 0);
    for (n, f) in frames.iter().enumerate() {
        assert_eq!(f["index"], n as u64);
        let t = f["t_mid_ns"].as_u64().unwrap();
        assert_eq!(t, T0_NS + (n as f64 * 1e9 / 6.0).round() as u64, "frame {n}: mid time");
        assert_eq!(f["unix_time_us"].as_u64().unwrap(), t / 1000);
        // Its sample is the last SYNC at or before the mid time, on the bus log's clock.
        let k = f["sample"].as_u64().unwrap() as usize;
        assert!(syncs[k] * 1000 <= t && syncs.get(k + 1).is_none_or(|&s| s * 1000 > t), "frame {n}: sample {k}");
        // Both arms' joints: the endoscope's as in truth.jsonl's nearest endoscope line (at
        // most 9 ms away; the holder turns by under 6 mrad in that time).
        let ecm: Vec<f64> = f["ecm_joints"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        let rec = truth.endoscope().iter().min_by_key(|r| r.sample.abs_diff(k as u64)).unwrap();
        assert!(rec.sample.abs_diff(k as u64) <= 9);
        assert_eq!(ecm.len(), 4);
        for (j, (q, truth_q)) in ecm.iter().zip(rec.joints).enumerate() {
            assert!((q - truth_q).abs() < 0.02, "frame {n} joint {j}: {q} vs {truth_q}");
        }
        assert_eq!(f["tool_joints"].as_array().unwrap().len(), 6);
        for name in f["files"].as_array().unwrap() {
            assert!(a.join("frames").join(name.as_str().unwrap()).is_file());
        }
        let px = f["instrument_px"][0].as_u64().unwrap();
        visible += usize::from(px >= sim::world::VISIBLE_MIN_PX);
        // The analytic ground truth and the mask agree on whether the instrument is in view
        // (not always at the image border: distortion, the shaft's width, the jaws).
        let axis_in_image = !f["left"]["instruments"][0]["axis"]["segment_px"].is_null();
        agree += usize::from(axis_in_image == (px >= sim::world::VISIBLE_MIN_PX));
    }
    assert!(agree * 10 >= frames.len() * 9, "truth and mask agree in {agree} of {} frames", frames.len());
    eprintln!("instrument visible in {visible} of {} frames", frames.len());
    assert!(visible * 2 > frames.len(), "visible in {visible} of {} frames", frames.len());
    assert_eq!(end["frames_with_instrument"], visible as u64);
    // The directory plays as a camera source (frames.txt) with the rig's camera_info.
    let mut src = hw_io::camera::image_sequence::ImageSequence::open(
        hw_io::camera::image_sequence::ImageSequenceConfig::new(a.join("frames")),
    )
    .unwrap();
    assert_eq!(src.len(), frames.len());
    let mut buf = vec![0u8; hw_io::camera::CameraSource::format(&src).payload_bytes()];
    for f in frames.iter().take(3) {
        let next = hw_io::camera::CameraSource::next_into(&mut src, &mut buf, std::time::Duration::ZERO).unwrap();
        let hw_io::camera::Next::Frame(m) = next else { panic!("{next:?}") };
        assert_eq!(m.timestamp_ns, f["t_mid_ns"].as_u64().unwrap());
        let left = image::open(a.join("frames").join(f["files"][0].as_str().unwrap())).unwrap().to_rgb8();
        assert_eq!(&buf[..buf.len() / 2], left.as_raw().as_slice());
    }
    let rig = hw_io::calib_files::parse_stereo_camera_info(
        &std::fs::read_to_string(a.join("frames/left.yaml")).unwrap(),
        &std::fs::read_to_string(a.join("frames/right.yaml")).unwrap(),
    )
    .unwrap();
    assert!(rig.baseline_m() > 0.001 && rig.baseline_m() < 0.02, "{}", rig.baseline_m());
}

#[test]
fn frames_need_the_endoscope_arm() {
    let dir = Scratch::new("off");
    let (twin, _) = configs(&dir);
    let o = Command::new(EXE)
        .args(["generate", "--frames", "--no-endoscope", "--out"])
        .arg(dir.path("x"))
        .arg("--config")
        .arg(&twin)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--no-endoscope"));
    let o =
        Command::new(EXE).args(["generate", "--frames", "--fps", "0", "--out"]).arg(dir.path("y")).output().unwrap();
    assert_eq!(o.status.code(), Some(2));
}
