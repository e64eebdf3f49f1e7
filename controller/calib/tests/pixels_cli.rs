//! `comanip-calib detect` on rendered frames written as PNG files (lines file, overlays,
//! unreadable images counted and failing the run), and the calibration-from-pixels chain on
//! a small noise-free grid (exact lines recover the truth exactly; detected lines closely).
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::path::Path;
use std::process::Command;

use comanip_calib::detect::{DetectorChoice, make_detector};
use comanip_calib::pixels::{LineSource, PixelProtocol, calibrate_all, observations, render_and_detect};
use estimator::calib::Eye;
use hw_io::calib_files::{parse_lines, write_camera_info_yaml};
use hw_io::camera::png::write_rgb_png;
use sim::calib::NoiseUnits;
use sim::endoscope::{DemoMotion, StereoRenderer};
use vision::shaft::ImageLine;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_comanip-calib"))
}

/// Renders `n` left-eye frames of the demo motion into `dir`; returns each frame's true axis
/// (undistorted pixels) when at least 100 px of it is visible.
fn render_frames(dir: &Path, n: u64) -> Vec<Option<ImageLine>> {
    let cfg = sim::world::default_endoscope_config();
    let mesh = cfg.instrument.mesh().unwrap();
    let k = cfg.camera.intrinsics;
    std::fs::write(dir.join("left.yaml"), write_camera_info_yaml("left", &k, None)).unwrap();
    let mut r = StereoRenderer::new(cfg, mesh).unwrap();
    let motion = DemoMotion::default();
    (0..n)
        .map(|i| {
            let f = r.render(i * 700_000_000, &|t| motion.state_at(t)).unwrap();
            let img = &f.images[0];
            write_rgb_png(&dir.join(format!("f{i:02}.png")), img.width as usize, img.height as usize, &img.rgb)
                .unwrap();
            let axis = f.truth[0].instruments.first()?.axis.as_ref()?;
            let s = axis.segment_ideal_px?;
            ((s[0][0] - s[1][0]).hypot(s[0][1] - s[1][1]) >= 100.0).then(|| ImageLine::new(axis.line_ideal).unwrap())
        })
        .collect()
}

#[test]
fn detect_writes_lines_and_overlays_and_counts_unreadable_images() {
    let dir = tempfile::tempdir().unwrap();
    let images = dir.path().join("images");
    std::fs::create_dir(&images).unwrap();
    let truth = render_frames(&images, 4);
    assert!(truth.iter().filter(|t| t.is_some()).count() >= 2, "the demo motion shows the shaft");
    let camera = images.join("left.yaml");
    let out = dir.path().join("lines.json");
    let overlay = dir.path().join("overlay");
    let run = |extra: &[&str]| {
        bin()
            .arg("detect")
            .arg("--images")
            .arg(&images)
            .arg("--camera")
            .arg(&camera)
            .arg("--out")
            .arg(&out)
            .arg("--overlay")
            .arg(&overlay)
            .args(extra)
            .output()
            .unwrap()
    };
    let o = run(&[]);
    assert!(o.status.success(), "stderr: {}", String::from_utf8_lossy(&o.stderr));
    let lines = parse_lines(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(lines.detector, "ours");
    assert_eq!(lines.images.len(), 4);
    for (img, t) in lines.images.iter().zip(&truth) {
        assert!(img.error.is_none(), "{img:?}");
        assert!(overlay.join(img.file.replace(".png", "_overlay.png")).exists());
        if let Some(t) = t {
            let best = img.shafts.first().unwrap_or_else(|| panic!("{}: no shaft found", img.file));
            let d = best.centreline;
            let angle = (t.abc[0] * d[0] + t.abc[1] * d[1]).abs().min(1.0).acos().to_degrees();
            assert!(angle < 1.0, "{}: {angle}° from the true axis", img.file);
        }
    }
    // The paper's detector through the same command.
    let o = run(&["--detector", "paper"]);
    assert!(o.status.success(), "stderr: {}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(parse_lines(&std::fs::read_to_string(&out).unwrap()).unwrap().detector, "paper");
    // An unreadable image is listed with its error, the others are still examined, and the
    // run fails.
    std::fs::write(images.join("f99.png"), b"not a png").unwrap();
    let o = run(&[]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("1 image(s) could not be examined"));
    let lines = parse_lines(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(lines.images.len(), 5);
    assert!(lines.images[4].error.as_deref().unwrap().contains("f99.png"), "{:?}", lines.images[4]);
    assert!(lines.images[..4].iter().all(|i| i.error.is_none()));
    // A camera of another size: every image refused with the size in the message.
    std::fs::remove_file(images.join("f99.png")).unwrap();
    let mut small = sim::world::default_endoscope_config().camera.intrinsics;
    small.width = 320;
    small.height = 240;
    std::fs::write(&camera, write_camera_info_yaml("left", &small, None)).unwrap();
    let o = run(&[]);
    assert!(!o.status.success());
    let lines = parse_lines(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert!(lines.images.iter().all(|i| i.error.as_deref().is_some_and(|e| e.contains("320x240"))), "{lines:?}");
}

#[test]
fn calibration_from_rendered_pixels_recovers_the_pose() {
    let p = PixelProtocol { n_e: 2, n_t: 2, sigma: 0.0, units: NoiseUnits::Millimetre, ..PixelProtocol::default() };
    let k = p.endoscope.camera.intrinsics;
    let mut detectors =
        vec![make_detector(DetectorChoice::Paper, k).unwrap(), make_detector(DetectorChoice::Ours, k).unwrap()];
    let run = render_and_detect(&p, &mut detectors, |_, _| {}).unwrap();
    assert_eq!(run.poses.len(), 16 * 4);
    let truth_both = observations(&run, LineSource::Truth, true);
    assert!(truth_both.iter().any(|o| o.eye == Eye::Right) && truth_both.iter().any(|o| o.eye == Eye::Left));
    let ours_lines = observations(&run, LineSource::Detector(1), true);
    assert!(ours_lines.len() * 10 >= truth_both.len() * 8, "{} of {}", ours_lines.len(), truth_both.len());
    let rows = calibrate_all(&run);
    let row = |source: &str, eyes: &str| rows.iter().find(|r| r.source == source && r.eyes == eyes).unwrap();
    // Exact lines, no kinematic noise: both pipelines recover the truth exactly, from either
    // eye set.
    for eyes in ["left", "both"] {
        let r = row("truth", eyes);
        for (name, res) in [("paper", &r.paper), ("ours", &r.ours)] {
            let (t_mm, r_deg) = res.clone().unwrap_or_else(|e| panic!("{name}, {eyes}: {e}"));
            assert!(t_mm < 1e-4 && r_deg < 1e-5, "{name}, {eyes}: {t_mm} mm, {r_deg}°");
        }
    }
    // Detected lines: our pipeline on our detector's lines stays within a few millimetres.
    let (t_mm, r_deg) = row("ours", "both").ours.clone().unwrap();
    assert!(t_mm < 5.0 && r_deg < 1.0, "{t_mm} mm, {r_deg}°");
}

#[test]
fn detected_lines_carry_a_pixel_term_and_truth_lines_none() {
    // One pose, kinematic noise on: the truth lines are exact projections (no pixel term), a
    // detector's lines get the stated pixel σ on top of the same kinematic noise.
    let p = PixelProtocol { n_e: 1, n_t: 1, sigma: 0.01, detected_sigma_px: 0.7, ..PixelProtocol::default() };
    let k = p.endoscope.camera.intrinsics;
    let mut detectors = vec![make_detector(DetectorChoice::Ours, k).unwrap()];
    let run = render_and_detect(&p, &mut detectors, |_, _| {}).unwrap();
    let truth = run.noise_of(LineSource::Truth).unwrap();
    let detected = run.noise_of(LineSource::Detector(0)).unwrap();
    assert_eq!(truth.pixel_px, 0.0);
    assert_eq!(detected.pixel_px, 0.7);
    assert_eq!((detected.rot_rad, detected.trans_m), (truth.rot_rad, truth.trans_m));
    assert!(truth.rot_rad > 0.0);
    // A pixel σ that is not a standard deviation is refused before anything is rendered.
    for bad in [-0.1, f64::NAN] {
        let p = PixelProtocol { n_e: 1, n_t: 1, detected_sigma_px: bad, ..PixelProtocol::default() };
        let e = render_and_detect(&p, &mut detectors, |_, _| {}).err().unwrap();
        assert!(e.to_string().contains("noise σ"), "{e}");
    }
}
