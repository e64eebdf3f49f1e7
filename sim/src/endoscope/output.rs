//! Files: stereo PNG frames, label masks, the ground truth as JSON Lines, and one sample
//! image per realism option (`docs/vision/`).
//!
//! The ground-truth file (`truth.jsonl`), one JSON object per line, told apart by `"type"`:
//! - `header` (line 1): format `comanip-endoscope-truth`, version, the whole renderer
//!   configuration, the first frame's mid time;
//! - `frame`: frame index, mid time (ns), the endoscope arm joints, the file names of the four
//!   images and each eye's [`EyeTruth`];
//! - `end`: number of frames (a truncated file is detected).

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use serde::Serialize;

use super::config::{EndoscopeConfig, RealismConfig};
use super::mesh::InstrumentMesh;
use super::render::{
    EyeImage, EyeTruth, NewRendererError, RenderError, StereoFrame, StereoRenderer, frame_mid_time_ns,
};
use super::scene::DemoMotion;

/// Value of the header's `format` field.
pub const FORMAT: &str = "comanip-endoscope-truth";

/// Version of the ground-truth format.
pub const VERSION: u32 = 1;

/// Why files could not be written.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    /// The renderer could not be built.
    #[error(transparent)]
    Renderer(#[from] NewRendererError),
    /// A frame could not be rendered.
    #[error(transparent)]
    Render(#[from] RenderError),
    /// A file could not be created or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A PNG could not be encoded.
    #[error("{path}: {source}")]
    Png {
        /// The file.
        path: PathBuf,
        /// Why.
        source: image::ImageError,
    },
    /// The ground truth could not be serialised.
    #[error("{path}: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// Why.
        source: serde_json::Error,
    },
}

/// Writes an eye's image as an 8-bit RGB PNG.
pub fn write_png(path: &Path, img: &EyeImage) -> Result<(), OutputError> {
    image::save_buffer(path, &img.rgb, img.width, img.height, image::ExtendedColorType::Rgb8)
        .map_err(|source| OutputError::Png { path: path.to_owned(), source })
}

/// Writes an eye's label mask as an 8-bit grey PNG holding the raw labels (0, 1, 2).
pub fn write_mask_png(path: &Path, img: &EyeImage) -> Result<(), OutputError> {
    image::save_buffer(path, &img.labels, img.width, img.height, image::ExtendedColorType::L8)
        .map_err(|source| OutputError::Png { path: path.to_owned(), source })
}

#[derive(Serialize)]
struct Header<'a> {
    #[serde(rename = "type")]
    kind: &'static str,
    format: &'static str,
    version: u32,
    t0_ns: u64,
    config: &'a EndoscopeConfig,
}

#[derive(Serialize)]
struct FrameLine<'a> {
    #[serde(rename = "type")]
    kind: &'static str,
    index: u64,
    t_mid_ns: u64,
    ecm_joints: [f64; 4],
    files: [&'a str; 4],
    left: &'a EyeTruth,
    right: &'a EyeTruth,
}

#[derive(Serialize)]
struct EndLine {
    #[serde(rename = "type")]
    kind: &'static str,
    frames: u64,
}

/// Which frames [`render_sequence`] writes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sequence {
    /// Number of stereo frames.
    pub frames: u64,
    /// Mid time of the first frame's exposure, nanoseconds.
    pub t0_ns: u64,
    /// Also write the label masks.
    pub masks: bool,
}

/// What [`render_sequence`] did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SequenceSummary {
    /// Frames written.
    pub frames: u64,
    /// Time spent rendering (not encoding), seconds.
    pub render_s: f64,
    /// Total time, seconds.
    pub total_s: f64,
}

fn create(path: &Path) -> Result<BufWriter<File>, OutputError> {
    File::create(path).map(BufWriter::new).map_err(|source| OutputError::Io { path: path.to_owned(), source })
}

/// Renders `seq.frames` stereo frames of `motion` at the configured frame rate from `seq.t0_ns`,
/// writing `DIR/frame_NNNNNN_{left,right}.png`, with `masks` also
/// `DIR/frame_NNNNNN_{left,right}_mask.png`, and `DIR/truth.jsonl`.
pub fn render_sequence(
    cfg: &EndoscopeConfig,
    mesh: InstrumentMesh,
    motion: &DemoMotion,
    seq: &Sequence,
    dir: &Path,
    mut progress: impl FnMut(u64),
) -> Result<SequenceSummary, OutputError> {
    let Sequence { frames, t0_ns, masks } = *seq;
    let started = std::time::Instant::now();
    std::fs::create_dir_all(dir).map_err(|source| OutputError::Io { path: dir.to_owned(), source })?;
    let mut renderer = StereoRenderer::new(cfg.clone(), mesh)?;
    let truth_path = dir.join("truth.jsonl");
    let mut truth = create(&truth_path)?;
    let io = |source| OutputError::Io { path: truth_path.clone(), source };
    let json = |source| OutputError::Json { path: truth_path.clone(), source };
    serde_json::to_writer(&mut truth, &Header { kind: "header", format: FORMAT, version: VERSION, t0_ns, config: cfg })
        .map_err(json)?;
    truth.write_all(b"\n").map_err(io)?;
    let mut frame = StereoFrame::default();
    let mut render_s = 0.0;
    let scene = |t| motion.state_at(t);
    for n in 0..frames {
        let t = frame_mid_time_ns(t0_ns, cfg.timing.fps, n);
        let r0 = std::time::Instant::now();
        renderer.render_into(t, &scene, &mut frame)?;
        render_s += r0.elapsed().as_secs_f64();
        let names = [
            format!("frame_{n:06}_left.png"),
            format!("frame_{n:06}_right.png"),
            format!("frame_{n:06}_left_mask.png"),
            format!("frame_{n:06}_right_mask.png"),
        ];
        for eye in 0..2 {
            write_png(&dir.join(&names[eye]), &frame.images[eye])?;
            if masks {
                write_mask_png(&dir.join(&names[2 + eye]), &frame.images[eye])?;
            }
        }
        let none = "";
        let files = [
            names[0].as_str(),
            names[1].as_str(),
            if masks { names[2].as_str() } else { none },
            if masks { names[3].as_str() } else { none },
        ];
        let line = FrameLine {
            kind: "frame",
            index: n,
            t_mid_ns: t,
            ecm_joints: frame.ecm_joints,
            files,
            left: &frame.truth[0],
            right: &frame.truth[1],
        };
        serde_json::to_writer(&mut truth, &line).map_err(json)?;
        truth.write_all(b"\n").map_err(io)?;
        progress(n + 1);
    }
    serde_json::to_writer(&mut truth, &EndLine { kind: "end", frames }).map_err(json)?;
    truth.write_all(b"\n").map_err(io)?;
    truth.flush().map_err(io)?;
    Ok(SequenceSummary { frames, render_s, total_s: started.elapsed().as_secs_f64() })
}

/// The sample images: each realism option alone (on top of the ideal image), the default
/// set, and everything; `(file stem, realism)`.
pub fn sample_options() -> Vec<(&'static str, RealismConfig)> {
    let none = RealismConfig::none();
    let default = RealismConfig::default();
    let mut v = none;
    v.vignetting.enabled = true;
    let mut d = none;
    d.defocus.enabled = true;
    let mut m = none;
    m.motion_blur.enabled = true;
    let mut n = none;
    n.noise.enabled = true;
    let mut s = none;
    s.smoke.enabled = true;
    vec![
        ("none", none),
        ("specular", RealismConfig { specular: true, ..none }),
        ("tissue_texture", RealismConfig { tissue_texture: true, ..none }),
        ("vignetting", v),
        ("defocus", d),
        ("motion_blur", m),
        ("noise", n),
        ("second_instrument", RealismConfig { second_instrument: true, ..none }),
        ("smoke", s),
        ("default", default),
        (
            "all",
            RealismConfig {
                second_instrument: true,
                smoke: super::config::SmokeConfig { enabled: true, ..s.smoke },
                ..default
            },
        ),
    ]
}

/// Writes one left-eye PNG per realism option into `dir` (`vision_<option>.png`), a
/// stereo pair of the default set side by side (`vision_stereo.png`), and the ground truth
/// drawn over the ideal image (`vision_truth.png`: contours green, axis blue, tip yellow).
/// The scene: [`DemoMotion`] at `t_ns`, at `speed` (fast enough to show motion blur).
pub fn write_samples(base: &EndoscopeConfig, dir: &Path, t_ns: u64, speed: f64) -> Result<Vec<PathBuf>, OutputError> {
    std::fs::create_dir_all(dir).map_err(|source| OutputError::Io { path: dir.to_owned(), source })?;
    let motion = DemoMotion { speed, ..Default::default() };
    let scene = |t| motion.state_at(t);
    let mesh = base.instrument.mesh().map_err(|e| NewRendererError::Config(e.into()))?;
    let mut written = Vec::new();
    for (name, realism) in sample_options() {
        let cfg = EndoscopeConfig { realism, ..base.clone() };
        let mut r = StereoRenderer::new(cfg, mesh.clone())?;
        let f = r.render(t_ns, &scene)?;
        let path = dir.join(format!("vision_{name}.png"));
        write_png(&path, &f.images[0])?;
        written.push(path);
        if name == "default" {
            let (w, h) = (f.images[0].width as usize, f.images[0].height as usize);
            let mut rgb = vec![0u8; 2 * w * h * 3];
            for y in 0..h {
                for eye in 0..2 {
                    let src = &f.images[eye].rgb[y * w * 3..(y + 1) * w * 3];
                    let dst = y * 2 * w * 3 + eye * w * 3;
                    rgb[dst..dst + w * 3].copy_from_slice(src);
                }
            }
            let img = EyeImage { width: 2 * w as u32, height: h as u32, rgb, labels: vec![0; 2 * w * h] };
            let path = dir.join("vision_stereo.png");
            write_png(&path, &img)?;
            written.push(path);
        }
        if name == "tissue_texture" {
            let mut img = f.images[0].clone();
            overlay_truth(&mut img, &f.truth[0]);
            let path = dir.join("vision_truth.png");
            write_png(&path, &img)?;
            written.push(path);
        }
    }
    Ok(written)
}

/// Draws the ground truth over an image: contours green, axis blue (polylines through the
/// distorted points), tip yellow.
pub fn overlay_truth(img: &mut EyeImage, truth: &EyeTruth) {
    let (w, h) = (img.width as i64, img.height as i64);
    let mut put = |x: f64, y: f64, c: [u8; 3]| {
        let (xi, yi) = (x.round() as i64, y.round() as i64);
        if xi >= 0 && yi >= 0 && xi < w && yi < h {
            let i = 3 * (yi * w + xi) as usize;
            img.rgb[i..i + 3].copy_from_slice(&c);
        }
    };
    let polyline = |pts: &[[f64; 2]], c: [u8; 3], put: &mut dyn FnMut(f64, f64, [u8; 3])| {
        for pair in pts.windows(2) {
            let (a, b) = (pair[0], pair[1]);
            let n = ((b[0] - a[0]).abs().max((b[1] - a[1]).abs()).ceil() as usize).max(1);
            for k in 0..=n {
                let t = k as f64 / n as f64;
                put(a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, c);
            }
        }
    };
    for inst in &truth.instruments {
        if let Some(cs) = &inst.contours {
            for c in cs {
                polyline(&c.polyline_px, [40, 255, 40], &mut put);
            }
        }
        if let Some(a) = &inst.axis {
            polyline(&a.polyline_px, [60, 120, 255], &mut put);
        }
        if let Some(t) = inst.tip_px {
            for d in -4..=4 {
                put(t[0] + d as f64, t[1], [255, 230, 0]);
                put(t[0], t[1] + d as f64, [255, 230, 0]);
            }
        }
    }
}
