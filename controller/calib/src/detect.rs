//! `comanip-calib detect`: the instrument shaft's lines in a directory of images, written as
//! a lines file (`hw_io::calib_files::LinesFile`, JSON), with an overlay image per frame when
//! asked.
//!
//! Images: the files listed in the directory's `frames.txt` (an image-sequence directory,
//! `docs/camera.md`; the left eye, or the right with `--eye right`), otherwise every `*.png`
//! in the directory except masks (`*_mask.png`), sorted by name.
//!
//! An image that cannot be read, or whose size is not the camera's, is recorded in the file
//! with its error and counted; the command goes on with the others and fails at the end.

use std::path::{Path, PathBuf};
use std::time::Instant;

use estimator::calib::Intrinsics;
use hw_io::calib_files::{ImageLinesJson, LINES_FORMAT, LINES_VERSION, LinesFile, ShaftJson};
use hw_io::camera::png::{read_rgb, write_rgb_png};
use nalgebra::{Vector2, Vector3};
use vision::shaft::ImageLine;
use vision::{RgbView, ShaftDetection, ShaftDetector};

/// Which detector.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum DetectorChoice {
    /// Ours: sub-pixel contours, cylinder pairing, the exact projected axis.
    Ours,
    /// The calibration paper's: 11×11 low-pass, EDLines, edge pairing, middle line.
    Paper,
}

/// Builds a detector for camera `k`.
pub fn make_detector(choice: DetectorChoice, k: Intrinsics) -> Result<Box<dyn ShaftDetector + Send>, String> {
    match choice {
        DetectorChoice::Ours => vision::ours::OursDetector::new(k, vision::ours::OursConfig::default())
            .map(|d| Box::new(d) as Box<dyn ShaftDetector + Send>)
            .map_err(|e| e.to_string()),
        DetectorChoice::Paper => Ok(Box::new(vision::paper::PaperDetector::new(k))),
    }
}

/// Why `detect` failed as a whole.
#[derive(Debug, thiserror::Error)]
pub enum DetectCmdError {
    /// The images directory cannot be listed, or its frames.txt is unusable.
    #[error("{path}: {message}")]
    Images {
        /// The directory or file.
        path: PathBuf,
        /// Why.
        message: String,
    },
    /// No image to examine.
    #[error("{0}: no images (no frames.txt and no *.png)")]
    NoImages(PathBuf),
    /// The detector refused the camera.
    #[error("detector: {0}")]
    Detector(String),
    /// An output file cannot be written.
    #[error("cannot write {path}: {message}")]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        message: String,
    },
}

/// The images of `dir` (see the module's doc), file names relative to `dir`.
pub fn list_images(dir: &Path, right_eye: bool) -> Result<Vec<String>, DetectCmdError> {
    let err = |path: &Path, message: String| DetectCmdError::Images { path: path.to_owned(), message };
    let index = dir.join("frames.txt");
    if index.exists() {
        let text = std::fs::read_to_string(&index).map_err(|e| err(&index, e.to_string()))?;
        let mut out = Vec::new();
        for (n, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let fields: Vec<&str> = line.split_whitespace().collect();
            let col = if right_eye { 3 } else { 2 };
            match fields.get(col) {
                Some(f) => out.push((*f).to_string()),
                None => {
                    return Err(err(
                        &index,
                        format!(
                            "line {}: no {} image (expected `t_mid_ns exposure_ns left [right]`)",
                            n + 1,
                            if right_eye { "right" } else { "left" }
                        ),
                    ));
                }
            }
        }
        return Ok(out);
    }
    let mut out: Vec<String> = std::fs::read_dir(dir)
        .map_err(|e| err(dir, e.to_string()))?
        .filter_map(|e| e.ok())
        .filter_map(|e| e.file_name().into_string().ok())
        .filter(|n| n.to_ascii_lowercase().ends_with(".png") && !n.ends_with("_mask.png"))
        .collect();
    out.sort();
    Ok(out)
}

/// What `detect` did.
#[derive(Clone, Debug, Default)]
pub struct DetectSummary {
    /// Images examined.
    pub images: usize,
    /// Images with at least one shaft.
    pub with_shaft: usize,
    /// Images not examined (unreadable or wrong size).
    pub failed: usize,
    /// Median detection time, milliseconds.
    pub median_ms: f64,
}

/// Runs the detector on every image of `dir`, writes the lines file `out`, and an overlay PNG
/// per image into `overlay` when given. `progress(done, total)` after each image.
pub fn detect_dir(
    dir: &Path,
    k: Intrinsics,
    choice: DetectorChoice,
    right_eye: bool,
    out: &Path,
    overlay: Option<&Path>,
    mut progress: impl FnMut(usize, usize),
) -> Result<DetectSummary, DetectCmdError> {
    let files = list_images(dir, right_eye)?;
    if files.is_empty() {
        return Err(DetectCmdError::NoImages(dir.to_owned()));
    }
    let mut det = make_detector(choice, k).map_err(DetectCmdError::Detector)?;
    if let Some(o) = overlay {
        std::fs::create_dir_all(o).map_err(|e| DetectCmdError::Write { path: o.to_owned(), message: e.to_string() })?;
    }
    let mut images = Vec::with_capacity(files.len());
    let mut summary = DetectSummary::default();
    let mut times = Vec::with_capacity(files.len());
    for (i, file) in files.iter().enumerate() {
        let mut entry = ImageLinesJson { file: file.clone(), shafts: vec![], error: None, detect_ms: 0.0 };
        match read_rgb(&dir.join(file)) {
            Err(e) => entry.error = Some(e.to_string()),
            Ok(img) => match RgbView::new(img.width, img.height, &img.rgb) {
                Err(e) => entry.error = Some(e.to_string()),
                Ok(view) => {
                    let t0 = Instant::now();
                    let found = det.detect(&view);
                    entry.detect_ms = t0.elapsed().as_secs_f64() * 1e3;
                    match found {
                        Err(e) => entry.error = Some(e.to_string()),
                        Ok(shafts) => {
                            times.push(entry.detect_ms);
                            entry.shafts = shafts.iter().map(shaft_json).collect();
                            if let Some(o) = overlay {
                                let mut rgb = img.rgb.clone();
                                draw_overlay(&mut rgb, img.width, img.height, &k, &shafts);
                                let stem = Path::new(file).file_stem().and_then(|s| s.to_str()).unwrap_or("image");
                                let path = o.join(format!("{stem}_overlay.png"));
                                write_rgb_png(&path, img.width, img.height, &rgb).map_err(|e| {
                                    DetectCmdError::Write { path: path.clone(), message: e.to_string() }
                                })?;
                            }
                        }
                    }
                }
            },
        }
        summary.images += 1;
        if entry.error.is_some() {
            summary.failed += 1;
        } else if !entry.shafts.is_empty() {
            summary.with_shaft += 1;
        }
        images.push(entry);
        progress(i + 1, files.len());
    }
    summary.median_ms = crate::pixels::median(&mut times);
    let file = LinesFile {
        format: LINES_FORMAT.into(),
        version: LINES_VERSION,
        detector: det.name().into(),
        intrinsics: k,
        images,
    };
    std::fs::write(out, hw_io::calib_files::to_json(&file))
        .map_err(|e| DetectCmdError::Write { path: out.to_owned(), message: e.to_string() })?;
    Ok(summary)
}

fn shaft_json(s: &ShaftDetection) -> ShaftJson {
    ShaftJson {
        centreline: s.centreline.abc,
        contours: [s.contours[0].abc, s.contours[1].abc],
        ends_px: s.ends_px,
        confidence: s.confidence,
    }
}

/// Measured (distorted) pixel of an ideal pixel `p` (through its ray; `None` when not finite).
fn distort(k: &Intrinsics, p: &Vector2<f64>) -> Option<Vector2<f64>> {
    let ray = k.k_inv() * Vector3::new(p.x, p.y, 1.0);
    let q = k.project(&ray);
    (q.x.is_finite() && q.y.is_finite()).then_some(q)
}

fn put(rgb: &mut [u8], w: usize, h: usize, q: &Vector2<f64>, c: [u8; 3]) {
    let (x, y) = (q.x.round(), q.y.round());
    if x < 0.0 || y < 0.0 || x >= w as f64 || y >= h as f64 {
        return;
    }
    let i = 3 * (y as usize * w + x as usize);
    rgb[i..i + 3].copy_from_slice(&c);
}

/// Draws an ideal (undistorted) line across the image as its distorted curve.
fn draw_ideal_line(rgb: &mut [u8], w: usize, h: usize, k: &Intrinsics, l: &ImageLine, c: [u8; 3]) {
    let [a, b, cc] = l.abc;
    // Points of the line, parameterised along its direction, over a range covering the
    // image generously (the ideal image is larger than the measured one with barrel
    // distortion).
    let foot = Vector2::new(-a * cc, -b * cc);
    let dir = Vector2::new(-b, a);
    let centre = Vector2::new(k.cx, k.cy);
    let t0 = (centre - foot).dot(&dir);
    let span = 2.0 * (w + h) as f64;
    let steps = (4.0 * span) as usize;
    for i in 0..=steps {
        let t = t0 - span + 2.0 * span * i as f64 / steps as f64;
        if let Some(q) = distort(k, &(foot + dir * t)) {
            put(rgb, w, h, &q, c);
        }
    }
}

/// Draws each detection: contours green, centreline blue (the best detection) or cyan
/// (others), the two end points as small red squares.
pub fn draw_overlay(rgb: &mut [u8], w: usize, h: usize, k: &Intrinsics, shafts: &[ShaftDetection]) {
    for (i, s) in shafts.iter().enumerate() {
        for c in &s.contours {
            draw_ideal_line(rgb, w, h, k, c, [40, 220, 60]);
        }
        draw_ideal_line(rgb, w, h, k, &s.centreline, if i == 0 { [40, 90, 255] } else { [40, 220, 220] });
        for e in &s.ends_px {
            for dy in -2..=2 {
                for dx in -2..=2 {
                    put(rgb, w, h, &Vector2::new(e[0] + f64::from(dx), e[1] + f64::from(dy)), [255, 40, 40]);
                }
            }
        }
    }
}
