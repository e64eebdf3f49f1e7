//! The OpenCV peers: EdgeDrawing/EDLines and LSD run by a small Python script
//! (`controller/bench/peers/opencv_lines.py`) on the same frames, written as PNGs; each
//! image's segments are then paired by the calibration paper's shaft pairing in Rust.
//!
//! OpenCV is a tool of the benchmark only (the `opencv-contrib-python-headless` wheel), never
//! a dependency of the product; when `python3 -c "import cv2"` fails, the peers are skipped
//! and the report says so.

use std::path::{Path, PathBuf};
use std::process::Command;

use serde::{Deserialize, Serialize};
use vision::Segment;

/// Names of the two peers in the report.
pub const PEER_NAMES: [&str; 2] = ["opencv-ed+pairing", "opencv-lsd+pairing"];

/// The script, as found in the source tree at build time.
pub fn default_script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("peers").join("opencv_lines.py")
}

/// Why the peers could not run.
#[derive(Debug, thiserror::Error)]
pub enum PeerError {
    /// The interpreter could not be started.
    #[error("{python}: {source}")]
    Spawn {
        /// The interpreter.
        python: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The script failed.
    #[error("{script} exited with {status}: {stderr}")]
    Script {
        /// The script.
        script: String,
        /// Its exit status.
        status: String,
        /// Its standard error.
        stderr: String,
    },
    /// Its output could not be read.
    #[error("{path}: {message}")]
    Output {
        /// The JSON file.
        path: String,
        /// What is wrong.
        message: String,
    },
}

/// One detector's result on one image.
#[derive(Clone, Debug, Deserialize, Serialize)]
pub struct PeerSegments {
    /// `[x1, y1, x2, y2]`, measured (distorted) pixels, centre of the top-left pixel at 0.
    pub segments: Vec<[f64; 4]>,
    /// Grey conversion plus detection, milliseconds (the script's `time.perf_counter`).
    pub ms: f64,
}

impl PeerSegments {
    /// The segments as [`Segment`]s.
    pub fn to_segments(&self) -> Vec<Segment> {
        self.segments.iter().map(|s| Segment { a: [s[0], s[1]], b: [s[2], s[3]] }).collect()
    }
}

/// The script's result on one image.
#[derive(Clone, Debug, Deserialize, Serialize)]
pub struct PeerImage {
    /// File name.
    pub file: String,
    /// EdgeDrawing's EDLines.
    pub ed: PeerSegments,
    /// LSD.
    pub lsd: PeerSegments,
}

/// The script's output file.
#[derive(Clone, Debug, Deserialize, Serialize)]
pub struct PeerOutput {
    /// `cv2.__version__`.
    pub opencv_version: String,
    /// `cv2.getNumThreads()` after `cv2.setNumThreads(1)`.
    pub threads: i64,
    /// EdgeDrawing's parameters as set.
    pub ed_params: serde_json::Value,
    /// LSD's parameters as set.
    pub lsd_params: serde_json::Value,
    /// Per image, sorted by file name.
    pub images: Vec<PeerImage>,
}

/// `None` when `python -c "import cv2"` works, else why not.
pub fn unavailable(python: &str) -> Option<String> {
    match Command::new(python).args(["-c", "import cv2, cv2.ximgproc"]).output() {
        Ok(o) if o.status.success() => None,
        Ok(o) => Some(format!(
            "`{python} -c \"import cv2, cv2.ximgproc\"` failed ({}); install the benchmark's tool with `pip install \
             --break-system-packages opencv-contrib-python-headless`",
            String::from_utf8_lossy(&o.stderr).trim().lines().last().unwrap_or("no message")
        )),
        Err(e) => Some(format!("cannot run {python}: {e}")),
    }
}

/// Runs the script on the PNGs of `dir`, its JSON written to `out`.
pub fn run(python: &str, script: &Path, dir: &Path, out: &Path) -> Result<PeerOutput, PeerError> {
    let o = Command::new(python)
        .arg(script)
        .arg(dir)
        .arg(out)
        .output()
        .map_err(|source| PeerError::Spawn { python: python.to_owned(), source })?;
    if !o.status.success() {
        return Err(PeerError::Script {
            script: script.display().to_string(),
            status: o.status.to_string(),
            stderr: String::from_utf8_lossy(&o.stderr).into_owned(),
        });
    }
    let text = std::fs::read_to_string(out)
        .map_err(|e| PeerError::Output { path: out.display().to_string(), message: e.to_string() })?;
    serde_json::from_str(&text)
        .map_err(|e| PeerError::Output { path: out.display().to_string(), message: e.to_string() })
}
