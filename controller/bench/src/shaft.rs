//! The shaft-detector benchmark on rendered frames (`comanip-bench shaft`,
//! `docs/detection.md`): the calibration paper's detector, ours and the OpenCV peers on the
//! same frames of the simulated endoscope, against its analytic ground truth, per clutter
//! level and per scenario family.
//!
//! - [`scenes`]: the scenario families, the tuning and report seed sets, the clutter levels;
//! - [`metrics`]: eligibility, the match rule, angle and offset errors, quantiles (pure);
//! - [`peers`]: OpenCV's EdgeDrawing/EDLines and LSD through a Python script;
//! - [`figures`]: overlay PNGs and the SVG of the error distributions;
//! - [`diagnose`]: why ours misses a shaft (`--diagnose`).
//!
//! One run: for each clutter level, the frames are rendered (left eye, in parallel), then
//! every detector runs on them one frame after another on one thread (timed per frame), the
//! peers' script runs once on the frames written as PNGs, and every detection is scored.

pub mod diagnose;
pub mod figures;
pub mod metrics;
pub mod peers;
pub mod scenes;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use estimator::calib::Intrinsics;
use rayon::prelude::*;
use serde::Serialize;
use sim::endoscope::output::{OutputError, write_png};
use sim::endoscope::render::{EyeTruth, NewRendererError, RenderError};
use sim::endoscope::{EndoscopeConfig, EyeImage, StereoRenderer, label};
use vision::{DetectError, ImageError, RgbView, Segment, ShaftDetection, ShaftDetector};

use metrics::{FrameScore, TruthAxis, quantile, score_frame, visible_length_px};
use peers::{PEER_NAMES, PeerError, PeerOutput};
use scenes::{ClutterLevel, FAMILIES, FrameSpec, SceneError, SeedSet, frame_specs};

/// Families drawn as overlay PNGs (the first seed of each), per clutter level.
pub const OVERLAY_FAMILIES: [&str; 2] = ["mid", "border"];

/// The camera and renderer configuration of a run: the simulator's default endoscope, the
/// tissue texture of the seed set, the realism of the level.
pub fn endoscope_config(set: SeedSet, level: ClutterLevel) -> EndoscopeConfig {
    EndoscopeConfig { seed: set.tissue_seed(), realism: level.realism(), ..EndoscopeConfig::default() }
}

/// The intrinsics of the benchmark's (left) camera, undistorted and measured pixels.
pub fn intrinsics() -> Intrinsics {
    EndoscopeConfig::default().camera.intrinsics
}

/// Why the benchmark stopped.
#[derive(Debug, thiserror::Error)]
pub enum ShaftBenchError {
    /// A scene could not be drawn.
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// The renderer refused its configuration.
    #[error("renderer: {0}")]
    Renderer(#[from] NewRendererError),
    /// A frame could not be rendered.
    #[error("render: {0}")]
    Render(#[from] RenderError),
    /// A rendered image is not an image.
    #[error("image: {0}")]
    Image(#[from] ImageError),
    /// A detector refused a frame.
    #[error("detector {detector}: {source}")]
    Detect {
        /// The detector.
        detector: String,
        /// Its error.
        source: DetectError,
    },
    /// A file could not be written.
    #[error("{path}: {message}")]
    Io {
        /// The file.
        path: String,
        /// What went wrong.
        message: String,
    },
    /// The peers' script failed.
    #[error("peers: {0}")]
    Peer(#[from] PeerError),
    /// A PNG could not be written.
    #[error(transparent)]
    Output(#[from] OutputError),
    /// A figure could not be written.
    #[error(transparent)]
    Plot(#[from] crate::plots::PlotError),
}

fn io_err(path: &Path, e: impl std::fmt::Display) -> ShaftBenchError {
    ShaftBenchError::Io { path: path.display().to_string(), message: e.to_string() }
}

/// A detector's detections on one frame and its time, milliseconds.
type Timed = (Vec<ShaftDetection>, f64);

/// The peers' pairing: a segment list (measured pixels) to at most one shaft.
pub type Pairing<'a> = &'a dyn Fn(&[Segment]) -> Option<ShaftDetection>;

/// How the peers run.
#[derive(Clone, Debug)]
pub struct PeerOptions {
    /// The Python interpreter.
    pub python: String,
    /// `opencv_lines.py`.
    pub script: PathBuf,
    /// Where the frames are written as PNGs (one subdirectory per level; removed afterwards).
    pub work_dir: PathBuf,
}

/// What to run.
#[derive(Clone, Debug)]
pub struct ShaftOptions {
    /// Tuning or report set.
    pub set: SeedSet,
    /// Seeds per family.
    pub frames_per_family: usize,
    /// The clutter levels.
    pub levels: Vec<ClutterLevel>,
    /// The peers (None: not run).
    pub peers: Option<PeerOptions>,
}

impl Default for ShaftOptions {
    fn default() -> Self {
        Self { set: SeedSet::Report, frames_per_family: 14, levels: ClutterLevel::ALL.to_vec(), peers: None }
    }
}

/// One rendered frame (left eye) with its truth.
#[derive(Clone, Debug)]
pub struct RenderedFrame {
    /// What was rendered.
    pub spec: FrameSpec,
    /// The left image and its mask.
    pub image: EyeImage,
    /// The left eye's ground truth.
    pub truth: EyeTruth,
    /// Instrument 1's true axis when some of it is in the image.
    pub inst1: Option<TruthAxis>,
    /// Instrument 2's true axis when drawn and some of it is in the image.
    pub inst2: Option<TruthAxis>,
    /// Some pixel of the image shows instrument 1, or its axis is in the image.
    pub inst1_in_view: bool,
    /// Some pixel of the image shows instrument 2.
    pub inst2_in_view: bool,
}

/// The true axis of instrument `label` in `truth`, its visible length taken from the mask.
fn truth_axis(truth: &EyeTruth, image: &EyeImage, lab: u8, other: u8) -> Option<TruthAxis> {
    let inst = truth.instruments.iter().find(|i| i.label == lab)?;
    let axis = inst.axis.as_ref()?;
    let segment = axis.segment_ideal_px?;
    let len = (segment[1][0] - segment[0][0]).hypot(segment[1][1] - segment[0][1]);
    let (visible_px, crossed_fraction) = visible_length_px(
        len,
        &axis.polyline_px,
        &image.labels,
        image.width as usize,
        image.height as usize,
        lab,
        other,
    );
    Some(TruthAxis { line: axis.line_ideal, segment, visible_px, crossed_fraction })
}

impl RenderedFrame {
    fn new(spec: FrameSpec, image: EyeImage, truth: EyeTruth) -> Self {
        let inst1 = truth_axis(&truth, &image, label::INSTRUMENT, label::SECOND);
        let inst2 = truth_axis(&truth, &image, label::SECOND, label::INSTRUMENT);
        let inst1_in_view = inst1.is_some() || image.labels.contains(&label::INSTRUMENT);
        let inst2_in_view = image.labels.contains(&label::SECOND);
        Self { spec, image, truth, inst1, inst2, inst1_in_view, inst2_in_view }
    }

    /// The image as a detector sees it.
    pub fn view(&self) -> Result<RgbView<'_>, ImageError> {
        RgbView::new(self.image.width as usize, self.image.height as usize, &self.image.rgb)
    }
}

/// Renders `specs` at `level` (left eye), in parallel, one renderer per worker; `progress`
/// is called once per frame.
pub fn render_frames(
    set: SeedSet,
    level: ClutterLevel,
    specs: &[FrameSpec],
    progress: &(dyn Fn() + Sync),
) -> Result<Vec<RenderedFrame>, ShaftBenchError> {
    let cfg = endoscope_config(set, level);
    let mesh = cfg.instrument.mesh().map_err(|e| NewRendererError::Config(e.into()))?;
    let workers = rayon::current_num_threads().max(1);
    let chunk = specs.len().div_ceil(workers).max(1);
    let chunks: Vec<Result<Vec<RenderedFrame>, ShaftBenchError>> = specs
        .par_chunks(chunk)
        .map(|part| {
            let mut r = StereoRenderer::new(cfg.clone(), mesh.clone())?;
            let mut out = Vec::with_capacity(part.len());
            for spec in part {
                let scene = spec.scene;
                let f = r.render(scene.t_mid_ns, &|t| scene.state_at(t))?;
                let [left, _] = f.images;
                let [truth, _] = f.truth;
                out.push(RenderedFrame::new(*spec, left, truth));
                progress();
            }
            Ok(out)
        })
        .collect();
    let mut frames = Vec::with_capacity(specs.len());
    for c in chunks {
        frames.extend(c?);
    }
    Ok(frames)
}

/// One detector's output on one frame.
#[derive(Clone, Debug, Serialize)]
pub struct DetectorResult {
    /// The detector.
    pub detector: String,
    /// The score.
    pub score: FrameScore,
    /// Time for the frame, milliseconds, the shortest of [`TIMING_REPEATS`] (ours and the
    /// paper's: `detect`, measured here; peers: the script's grey conversion and detection,
    /// plus the pairing here).
    pub ms: f64,
    /// The returned centrelines, best first, `[a, b, c]` undistorted pixels.
    pub centrelines: Vec<[f64; 3]>,
}

/// One frame's record (the JSON's rows).
#[derive(Clone, Debug, Serialize)]
pub struct FrameRecord {
    /// Clutter level.
    pub level: ClutterLevel,
    /// Family key.
    pub family: &'static str,
    /// A tuning family.
    pub tuned_family: bool,
    /// Seed.
    pub seed: u64,
    /// Instrument 1's visible segment before occlusion, pixels (0 when none).
    pub segment_px: f64,
    /// Its visible length from the mask, pixels.
    pub visible_px: f64,
    /// Fraction of its axis covered by instrument 2.
    pub crossed_fraction: f64,
    /// At least [`metrics::ELIGIBLE_PX`] visible.
    pub eligible: bool,
    /// Instrument 1 in the image at all.
    pub instrument_in_view: bool,
    /// Instrument 2 in the image.
    pub second_in_view: bool,
    /// Every detector's result.
    pub results: Vec<DetectorResult>,
}

/// A frame kept for an overlay PNG.
#[derive(Clone, Debug)]
pub struct Overlay {
    /// Clutter level.
    pub level: ClutterLevel,
    /// Family key.
    pub family: &'static str,
    /// Seed.
    pub seed: u64,
    /// The frame.
    pub image: EyeImage,
    /// Its truth.
    pub truth: EyeTruth,
    /// Every detector's centrelines, in the report's detector order.
    pub centrelines: Vec<Vec<[f64; 3]>>,
}

/// What happened to the peers.
#[derive(Clone, Debug, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PeerStatus {
    /// Not asked for.
    NotRequested,
    /// Asked for but not available (why).
    Skipped(String),
    /// Ran: OpenCV's version and the exact parameters.
    Ran {
        /// `cv2.__version__`.
        opencv_version: String,
        /// OpenCV threads.
        threads: i64,
        /// EdgeDrawing parameters.
        ed_params: serde_json::Value,
        /// LSD parameters.
        lsd_params: serde_json::Value,
    },
}

/// The benchmark's result.
#[derive(Clone, Debug, Serialize)]
pub struct ShaftReport {
    /// The seed set.
    pub set: SeedSet,
    /// Seeds per family.
    pub frames_per_family: usize,
    /// The seeds.
    pub seeds: Vec<u64>,
    /// The levels.
    pub levels: Vec<ClutterLevel>,
    /// The detectors, in report order (ours and the paper's first, then the peers).
    pub detectors: Vec<String>,
    /// The peers.
    pub peers: PeerStatus,
    /// One record per frame and level.
    pub records: Vec<FrameRecord>,
    /// The frames kept for overlays.
    #[serde(skip)]
    pub overlays: Vec<Overlay>,
    /// Wall time of the run, seconds.
    pub elapsed_s: f64,
    /// `/proc/loadavg` (1, 5, 15 min) at the start and the end of the run (the machine is
    /// shared: times are only as quiet as it was).
    pub load_average: [String; 2],
}

/// The first three fields of `/proc/loadavg` (empty when unreadable).
fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}

/// Each frame's detection is timed this many times and the shortest kept (the shared
/// machine's other tenants only ever add time); the peers' script does the same.
pub const TIMING_REPEATS: usize = 3;

/// The detections of the first call and the shortest of [`TIMING_REPEATS`] times.
fn time_detect(det: &mut dyn ShaftDetector, frame: &RenderedFrame) -> Result<Timed, ShaftBenchError> {
    let view = frame.view()?;
    let mut first = None;
    let mut best = f64::INFINITY;
    for _ in 0..TIMING_REPEATS {
        let t0 = Instant::now();
        let out =
            det.detect(&view).map_err(|source| ShaftBenchError::Detect { detector: det.name().to_owned(), source })?;
        best = best.min(t0.elapsed().as_secs_f64() * 1e3);
        first.get_or_insert(out);
    }
    Ok((first.unwrap_or_default(), best))
}

/// Writes the frames as `NNNNN.png` into `dir` (created), in parallel.
fn write_frames(dir: &Path, frames: &[RenderedFrame]) -> Result<(), ShaftBenchError> {
    std::fs::create_dir_all(dir).map_err(|e| io_err(dir, e))?;
    frames.par_iter().enumerate().try_for_each(|(i, f)| write_png(&dir.join(format!("{i:05}.png")), &f.image))?;
    Ok(())
}

/// The peers' detections and times on `frames` (per frame: per peer, detections and ms).
fn run_peers(
    opts: &PeerOptions,
    level: ClutterLevel,
    frames: &[RenderedFrame],
    pairing: Pairing<'_>,
) -> Result<(PeerOutput, Vec<[Timed; 2]>), ShaftBenchError> {
    let dir = opts.work_dir.join(level.key());
    write_frames(&dir, frames)?;
    let json = opts.work_dir.join(format!("{}.json", level.key()));
    let out = peers::run(&opts.python, &opts.script, &dir, &json)?;
    let _ = std::fs::remove_dir_all(&dir);
    if out.images.len() != frames.len() {
        return Err(PeerError::Output {
            path: json.display().to_string(),
            message: format!("{} images for {} frames", out.images.len(), frames.len()),
        }
        .into());
    }
    let mut per_frame = Vec::with_capacity(frames.len());
    for (i, img) in out.images.iter().enumerate() {
        if img.file != format!("{i:05}.png") {
            return Err(PeerError::Output {
                path: json.display().to_string(),
                message: format!("image {i} is {}", img.file),
            }
            .into());
        }
        let pair = |s: &peers::PeerSegments| {
            let segs = s.to_segments();
            let t0 = Instant::now();
            let d = pairing(&segs);
            (d.into_iter().collect::<Vec<_>>(), s.ms + t0.elapsed().as_secs_f64() * 1e3)
        };
        per_frame.push([pair(&img.ed), pair(&img.lsd)]);
    }
    let _ = std::fs::remove_file(&json);
    Ok((out, per_frame))
}

/// Runs the benchmark. `detectors` run in this order (ours first, by convention); the
/// peers need `pairing` (the paper's shaft pairing for the benchmark's camera) and
/// `opts.peers`. `progress(done, total)` is called as frames are rendered and scored.
pub fn run(
    opts: &ShaftOptions,
    detectors: &mut [Box<dyn ShaftDetector>],
    pairing: Option<Pairing<'_>>,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<ShaftReport, ShaftBenchError> {
    let started = Instant::now();
    let load_start = load_average();
    let cfg0 = endoscope_config(opts.set, ClutterLevel::Clean);
    let specs = frame_specs(opts.set, opts.frames_per_family, &cfg0)?;
    let peer_opts = match (&opts.peers, pairing) {
        (Some(p), Some(_)) => match peers::unavailable(&p.python) {
            None => Some(p),
            Some(why) => {
                eprintln!("comanip-bench shaft: peers skipped: {why}");
                None
            }
        },
        _ => None,
    };
    let mut peer_status = match (&opts.peers, pairing, peer_opts) {
        (None, _, _) => PeerStatus::NotRequested,
        (Some(_), None, _) => PeerStatus::Skipped("no pairing function given".into()),
        (Some(p), Some(_), None) => {
            PeerStatus::Skipped(peers::unavailable(&p.python).unwrap_or_else(|| "unavailable".into()))
        }
        (Some(_), Some(_), Some(_)) => PeerStatus::NotRequested,
    };
    let mut names: Vec<String> = detectors.iter().map(|d| d.name().to_owned()).collect();
    if peer_opts.is_some() {
        names.extend(PEER_NAMES.iter().map(|s| (*s).to_owned()));
    }
    let total = (opts.levels.len() * specs.len() * 2) as u64;
    let done = std::sync::atomic::AtomicU64::new(0);
    let tick = || {
        let d = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        progress(d, total);
    };
    let mut records = Vec::new();
    let mut overlays = Vec::new();
    for &level in &opts.levels {
        let frames = render_frames(opts.set, level, &specs, &tick)?;
        // Ours and the paper's: one frame after another on this thread, timed.
        let mut results: Vec<Vec<Timed>> = vec![Vec::with_capacity(frames.len()); frames.len()];
        for f_i in 0..frames.len() {
            for det in detectors.iter_mut() {
                results[f_i].push(time_detect(det.as_mut(), &frames[f_i])?);
            }
            tick();
        }
        if let (Some(p), Some(pair)) = (peer_opts, pairing) {
            let (out, per_frame) = run_peers(p, level, &frames, pair)?;
            for (r, [ed, lsd]) in results.iter_mut().zip(per_frame) {
                r.push(ed);
                r.push(lsd);
            }
            peer_status = PeerStatus::Ran {
                opencv_version: out.opencv_version,
                threads: out.threads,
                ed_params: out.ed_params,
                lsd_params: out.lsd_params,
            };
        }
        let mut overlay_done = [false; OVERLAY_FAMILIES.len()];
        for (frame, res) in frames.into_iter().zip(results) {
            let fam = &FAMILIES[frame.spec.family];
            let inst2 = if frame.inst2_in_view { frame.inst2.as_ref() } else { None };
            let det_results: Vec<DetectorResult> = res
                .iter()
                .zip(&names)
                .map(|((dets, ms), name)| DetectorResult {
                    detector: name.clone(),
                    score: score_frame(dets, frame.inst1.as_ref(), inst2),
                    ms: *ms,
                    centrelines: dets.iter().map(|d| d.centreline.abc).collect(),
                })
                .collect();
            let i1 = frame.inst1.as_ref();
            records.push(FrameRecord {
                level,
                family: fam.key,
                tuned_family: fam.tuned,
                seed: frame.spec.seed,
                segment_px: i1.map_or(0.0, TruthAxis::segment_px),
                visible_px: i1.map_or(0.0, |t| t.visible_px),
                crossed_fraction: i1.map_or(0.0, |t| t.crossed_fraction),
                eligible: i1.is_some_and(TruthAxis::eligible),
                instrument_in_view: frame.inst1_in_view,
                second_in_view: frame.inst2_in_view,
                results: det_results,
            });
            if let Some(k) = OVERLAY_FAMILIES.iter().position(|f| *f == fam.key)
                && !overlay_done[k]
            {
                overlay_done[k] = true;
                overlays.push(Overlay {
                    level,
                    family: fam.key,
                    seed: frame.spec.seed,
                    centrelines: res.iter().map(|(d, _)| d.iter().map(|x| x.centreline.abc).collect()).collect(),
                    image: frame.image,
                    truth: frame.truth,
                });
            }
        }
    }
    Ok(ShaftReport {
        set: opts.set,
        frames_per_family: opts.frames_per_family,
        seeds: opts.set.seeds(opts.frames_per_family),
        levels: opts.levels.clone(),
        detectors: names,
        peers: peer_status,
        records,
        overlays,
        elapsed_s: started.elapsed().as_secs_f64(),
        load_average: [load_start, load_average()],
    })
}

/// One detector's aggregate over a set of frames.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Cell {
    /// Frames.
    pub frames: usize,
    /// Eligible frames.
    pub eligible: usize,
    /// Eligible frames where instrument 1 was crossed by instrument 2 (some of its axis
    /// covered).
    pub eligible_crossed: usize,
    /// Eligible frames whose instrument 1 was matched.
    pub detected: usize,
    /// Detections matching no instrument, all frames.
    pub false_detections: usize,
    /// Frames without instrument 1 in view.
    pub free_frames: usize,
    /// False detections on those.
    pub false_on_free: usize,
    /// Angle error of the matched detections (eligible frames), degrees: median, p95.
    pub angle_deg: [Option<f64>; 2],
    /// Midpoint offset of the matched detections, pixels: median, p95.
    pub offset_px: [Option<f64>; 2],
    /// Largest offset over the visible segment, pixels: median, p95.
    pub offset_max_px: [Option<f64>; 2],
    /// Time per frame, milliseconds: median, p95.
    pub ms: [Option<f64>; 2],
}

impl Cell {
    /// Detection rate over eligible frames, `None` without any.
    pub fn rate(&self) -> Option<f64> {
        (self.eligible > 0).then(|| self.detected as f64 / self.eligible as f64)
    }
}

/// The aggregate of detector `d` (index into the report's detectors) over `records`.
pub fn cell<'a>(records: impl Iterator<Item = &'a FrameRecord>, d: usize) -> Cell {
    let mut c = Cell::default();
    let (mut ang, mut off, mut offmax, mut ms) = (vec![], vec![], vec![], vec![]);
    for r in records {
        let Some(res) = r.results.get(d) else { continue };
        c.frames += 1;
        ms.push(res.ms);
        c.false_detections += res.score.false_detections;
        if !r.instrument_in_view {
            c.free_frames += 1;
            c.false_on_free += res.score.false_detections;
        }
        if r.eligible {
            c.eligible += 1;
            c.eligible_crossed += usize::from(r.crossed_fraction > 0.0);
            if let Some(e) = res.score.matched {
                c.detected += 1;
                ang.push(e.angle_deg);
                off.push(e.offset_mid_px);
                offmax.push(e.offset_max_px);
            }
        }
    }
    let mp = |v: &[f64]| [quantile(v, 0.5), quantile(v, 0.95)];
    c.angle_deg = mp(&ang);
    c.offset_px = mp(&off);
    c.offset_max_px = mp(&offmax);
    c.ms = mp(&ms);
    c
}

/// Detector `a` against detector `b` on the eligible frames where both matched instrument 1
/// (the unpaired medians of [`Cell`] are over different frames: a detector that finds harder
/// frames carries their errors).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct PairedCell {
    /// Eligible frames both matched.
    pub common: usize,
    /// Angle error medians on those frames, degrees: `a`'s, `b`'s.
    pub angle_deg: [Option<f64>; 2],
    /// Midpoint offset medians on those frames, pixels: `a`'s, `b`'s.
    pub offset_px: [Option<f64>; 2],
    /// Frames where `a`'s angle error is smaller than `b`'s, and where its offset is.
    pub a_better: [usize; 2],
}

/// Detector `a` against detector `b` (indices into the report's detectors) over `records`,
/// on the eligible frames both matched.
pub fn paired<'a>(records: impl Iterator<Item = &'a FrameRecord>, a: usize, b: usize) -> PairedCell {
    let mut p = PairedCell::default();
    let (mut aa, mut ba, mut ao, mut bo) = (vec![], vec![], vec![], vec![]);
    for r in records.filter(|r| r.eligible) {
        let (Some(ea), Some(eb)) =
            (r.results.get(a).and_then(|x| x.score.matched), r.results.get(b).and_then(|x| x.score.matched))
        else {
            continue;
        };
        p.common += 1;
        p.a_better[0] += usize::from(ea.angle_deg < eb.angle_deg);
        p.a_better[1] += usize::from(ea.offset_mid_px < eb.offset_mid_px);
        aa.push(ea.angle_deg);
        ba.push(eb.angle_deg);
        ao.push(ea.offset_mid_px);
        bo.push(eb.offset_mid_px);
    }
    p.angle_deg = [quantile(&aa, 0.5), quantile(&ba, 0.5)];
    p.offset_px = [quantile(&ao, 0.5), quantile(&bo, 0.5)];
    p
}

fn f(v: Option<f64>, digits: usize) -> String {
    v.map_or_else(|| "–".into(), |x| format!("{x:.digits$}"))
}

fn table_header(first: &str) -> String {
    format!(
        "| {first} | detector | eligible (crossed) | detected | false: all / instrument-free frames (n) | angle ° \
         median / p95 | offset px median / p95 | max offset px median / p95 | ms/frame median |\n|---|---|---|---|---|\
         ---|---|---|---|\n"
    )
}

fn table_row(first: &str, name: &str, c: &Cell) -> String {
    format!(
        "| {first} | {name} | {} ({}) | {} ({}) | {} / {} ({}) | {} / {} | {} / {} | {} / {} | {} |\n",
        c.eligible,
        c.eligible_crossed,
        c.rate().map_or_else(|| "–".into(), |r| format!("{:.1} %", 100.0 * r)),
        c.detected,
        c.false_detections,
        c.false_on_free,
        c.free_frames,
        f(c.angle_deg[0], 3),
        f(c.angle_deg[1], 3),
        f(c.offset_px[0], 2),
        f(c.offset_px[1], 2),
        f(c.offset_max_px[0], 2),
        f(c.offset_max_px[1], 2),
        f(c.ms[0], 2),
    )
}

impl ShaftReport {
    /// The aggregate of detector `d` at `level`.
    pub fn level_cell(&self, level: ClutterLevel, d: usize) -> Cell {
        cell(self.records.iter().filter(|r| r.level == level), d)
    }

    /// The aggregate of detector `d` on family `key`, every level.
    pub fn family_cell(&self, key: &str, d: usize) -> Cell {
        cell(self.records.iter().filter(|r| r.family == key), d)
    }

    /// The Markdown report: the set, the per-level table, the per-family table.
    pub fn markdown(&self) -> String {
        let mut m = String::new();
        let fams = self.set.families();
        let _ = writeln!(
            m,
            "Seed set: **{}** (seeds {}..={}, {} per family; tissue texture seed {}). Families: {} \
             (tuning families: {}; held out: {}). Left eye, 640×480, {} frames per level. Eligible: ≥ {} px of the \
             instrument's axis visible in the mask; a match: ≤ {}° and ≤ {} px from the midpoint of the true visible \
             segment; errors over matched eligible frames. Wall time {:.0} s; load average (1, 5, 15 min) {} at the \
             start, {} at the end.\n",
            self.set.key(),
            self.seeds.first().copied().unwrap_or(0),
            self.seeds.last().copied().unwrap_or(0),
            self.frames_per_family,
            self.set.tissue_seed(),
            fams.iter().map(|f| f.key).collect::<Vec<_>>().join(", "),
            fams.iter().filter(|f| f.tuned).map(|f| f.key).collect::<Vec<_>>().join(", "),
            FAMILIES.iter().filter(|f| !f.tuned).map(|f| f.key).collect::<Vec<_>>().join(", "),
            fams.len() * self.frames_per_family,
            metrics::ELIGIBLE_PX,
            metrics::MATCH_ANGLE_DEG,
            metrics::MATCH_OFFSET_PX,
            self.elapsed_s,
            self.load_average[0],
            self.load_average[1],
        );
        match &self.peers {
            PeerStatus::NotRequested => {
                let _ = writeln!(m, "Peers: not run (`--peers`).\n");
            }
            PeerStatus::Skipped(why) => {
                let _ = writeln!(m, "Peers: **skipped**: {why}.\n");
            }
            PeerStatus::Ran { opencv_version, threads, ed_params, lsd_params } => {
                let _ = writeln!(
                    m,
                    "Peers: OpenCV {opencv_version} (opencv-contrib-python-headless, {threads} thread), EdgeDrawing \
                     parameters `{ed_params}`, LSD parameters `{lsd_params}`; their time is the script's grey \
                     conversion and detection plus the pairing. Times: the shortest of {TIMING_REPEATS} runs per \
                     frame.\n"
                );
            }
        }
        if matches!(self.peers, PeerStatus::NotRequested | PeerStatus::Skipped(_)) {
            let _ = writeln!(m, "Times: the shortest of {TIMING_REPEATS} runs per frame.\n");
        }
        let _ = writeln!(m, "### Per clutter level\n");
        m.push_str(&table_header("level"));
        for &level in &self.levels {
            for (d, name) in self.detectors.iter().enumerate() {
                m.push_str(&table_row(level.key(), name, &self.level_cell(level, d)));
            }
        }
        if let Some(t) = self.paired_markdown() {
            let _ = writeln!(m, "\n### Paired accuracy: ours against each other detector on the frames both detect\n");
            m.push_str(&t);
        }
        if let Some(t) = self.targets_markdown() {
            let _ = writeln!(m, "\n### Issue 17's targets for ours\n");
            m.push_str(&t);
        }
        let _ = writeln!(m, "\n### Per family (every level)\n");
        m.push_str(&table_header("family"));
        for fam in fams {
            let tag = format!("{} ({})", fam.key, if fam.tuned { "tuning" } else { "held out" });
            for (d, name) in self.detectors.iter().enumerate() {
                m.push_str(&table_row(&tag, name, &self.family_cell(fam.key, d)));
            }
        }
        m
    }

    /// Ours (the detector named `ours`) against each other detector, per level, on the
    /// eligible frames both matched: the medians of the angle error and the offset on those
    /// frames, and on how many of them ours' error is the smaller. `None` without `ours`.
    pub fn paired_markdown(&self) -> Option<String> {
        let ours = self.detectors.iter().position(|d| d == "ours")?;
        let mut m = String::from(
            "| level | other detector | frames both detect | angle ° median ours / other | offset px median ours / \
             other | ours smaller: angle / offset (frames) |\n|---|---|---|---|---|---|\n",
        );
        for &level in &self.levels {
            for (d, name) in self.detectors.iter().enumerate().filter(|&(d, _)| d != ours) {
                let p = paired(self.records.iter().filter(|r| r.level == level), ours, d);
                let _ = writeln!(
                    m,
                    "| {} | {name} | {} | {} / {} | {} / {} | {} / {} |",
                    level.key(),
                    p.common,
                    f(p.angle_deg[0], 3),
                    f(p.angle_deg[1], 3),
                    f(p.offset_px[0], 2),
                    f(p.offset_px[1], 2),
                    p.a_better[0],
                    p.a_better[1],
                );
            }
        }
        Some(m)
    }

    /// Issue 17's targets for the detector named `ours`, per level: detection ≥ 95 % of the
    /// eligible frames, median angle ≤ 0.1°, median offset ≤ 0.3 px, no false detection on
    /// instrument-free frames, smaller median angle and offset than every other detector,
    /// median time ≤ 5 ms. `None` without a detector named `ours`.
    pub fn targets_markdown(&self) -> Option<String> {
        let ours = self.detectors.iter().position(|d| d == "ours")?;
        let yn = |ok: Option<bool>| match ok {
            Some(true) => "yes",
            Some(false) => "**no**",
            None => "–",
        };
        let mut m = String::from(
            "| level | detected ≥ 95 % | angle median ≤ 0.1° | offset median ≤ 0.3 px | 0 false on instrument-free \
             frames | angle and offset medians below every other detector's | time median ≤ 5 ms |\n|---|---|---|---|\
             ---|---|---|\n",
        );
        for &level in &self.levels {
            let c = self.level_cell(level, ours);
            let others: Vec<Cell> =
                (0..self.detectors.len()).filter(|&d| d != ours).map(|d| self.level_cell(level, d)).collect();
            let better = |pick: fn(&Cell) -> Option<f64>| {
                let mine = pick(&c)?;
                Some(others.iter().all(|o| pick(o).is_none_or(|x| mine < x)))
            };
            let more_accurate = match (better(|x| x.angle_deg[0]), better(|x| x.offset_px[0])) {
                (Some(a), Some(b)) => Some(a && b),
                _ => None,
            };
            let _ = writeln!(
                m,
                "| {} | {} | {} | {} | {} | {} | {} |",
                level.key(),
                yn(c.rate().map(|r| r >= 0.95)),
                yn(c.angle_deg[0].map(|a| a <= 0.1)),
                yn(c.offset_px[0].map(|o| o <= 0.3)),
                yn((c.free_frames > 0).then_some(c.false_on_free == 0)),
                yn(more_accurate),
                yn(c.ms[0].map(|t| t <= 5.0)),
            );
        }
        Some(m)
    }

    /// Writes `table.md`, `results.json` into `out`, and the overlay PNGs and
    /// `shaft_errors.svg` into `figures`; returns the files written.
    pub fn write(&self, out: &Path, figures: &Path) -> Result<Vec<PathBuf>, ShaftBenchError> {
        std::fs::create_dir_all(out).map_err(|e| io_err(out, e))?;
        std::fs::create_dir_all(figures).map_err(|e| io_err(figures, e))?;
        let mut written = Vec::new();
        let md = out.join("table.md");
        std::fs::write(&md, self.markdown()).map_err(|e| io_err(&md, e))?;
        written.push(md);
        let json = out.join("results.json");
        let text = serde_json::to_string(self).map_err(|e| io_err(&json, e))?;
        std::fs::write(&json, text).map_err(|e| io_err(&json, e))?;
        written.push(json);
        let k = intrinsics();
        for o in &self.overlays {
            let mut img = o.image.clone();
            for inst in &o.truth.instruments {
                if let Some(a) = &inst.axis {
                    figures::draw_polyline(&mut img, &a.polyline_px, 1, figures::TRUTH_RGB);
                }
            }
            let n = o.centrelines.len();
            for (d, lines) in o.centrelines.iter().enumerate() {
                let c = figures::DETECTOR_RGB[d.min(figures::DETECTOR_RGB.len() - 1)];
                for l in lines {
                    figures::draw_ideal_line(&mut img, &k, l, 0, c, d, n);
                }
            }
            let p = figures.join(format!("shaft_{}_{}_{}.png", o.level.key(), o.family, o.seed));
            write_png(&p, &img)?;
            written.push(p);
        }
        let series = |pick: fn(&metrics::LineErrors) -> f64| -> Vec<figures::Series> {
            self.detectors
                .iter()
                .enumerate()
                .map(|(d, name)| {
                    let v = self
                        .records
                        .iter()
                        .filter(|r| r.eligible)
                        .filter_map(|r| r.results.get(d).and_then(|x| x.score.matched).map(|e| pick(&e)))
                        .collect();
                    (name.clone(), figures::PLOT_RGB[d.min(figures::PLOT_RGB.len() - 1)], v)
                })
                .collect()
        };
        let svg = figures.join("shaft_errors.svg");
        figures::cdf_panels(
            &[
                ("centreline offset at the segment midpoint", "offset (px)", 3.0, series(|e| e.offset_mid_px)),
                ("centreline angle error", "angle error (°)", 1.0, series(|e| e.angle_deg)),
            ],
            &svg,
        )?;
        written.push(svg);
        Ok(written)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use metrics::LineErrors;

    fn result(name: &str, matched: Option<(f64, f64)>, false_detections: usize, ms: f64) -> DetectorResult {
        DetectorResult {
            detector: name.into(),
            score: FrameScore {
                matched: matched.map(|(a, o)| LineErrors { angle_deg: a, offset_mid_px: o, offset_max_px: o }),
                false_detections,
                ..Default::default()
            },
            ms,
            centrelines: vec![],
        }
    }

    fn record(eligible: bool, in_view: bool, results: Vec<DetectorResult>) -> FrameRecord {
        FrameRecord {
            level: ClutterLevel::Clean,
            family: "mid",
            tuned_family: true,
            seed: 1,
            segment_px: 200.0,
            visible_px: if eligible { 200.0 } else { 50.0 },
            crossed_fraction: 0.0,
            eligible,
            instrument_in_view: in_view,
            second_in_view: false,
            results,
        }
    }

    #[test]
    fn cells_aggregate_and_the_targets_compare_ours_with_every_other_detector() {
        let records = vec![
            record(
                true,
                true,
                vec![result("ours", Some((0.05, 0.1)), 0, 2.0), result("peer", Some((0.2, 0.5)), 1, 9.0)],
            ),
            record(true, true, vec![result("ours", Some((0.07, 0.3)), 0, 4.0), result("peer", None, 0, 9.0)]),
            record(false, false, vec![result("ours", None, 0, 1.0), result("peer", None, 2, 9.0)]),
        ];
        let c = cell(records.iter(), 1);
        assert_eq!(
            (c.frames, c.eligible, c.detected, c.false_detections, c.free_frames, c.false_on_free),
            (3, 2, 1, 3, 1, 2)
        );
        assert_eq!(c.rate(), Some(0.5));
        let c = cell(records.iter(), 0);
        assert_eq!(c.rate(), Some(1.0));
        assert!((c.offset_px[0].unwrap() - 0.2).abs() < 1e-12);
        assert_eq!(c.ms[0], Some(2.0));
        let report = clean_report(records);
        let t = report.targets_markdown().unwrap();
        // Detected 100 %, angle 0.06°, offset 0.2 px, no false, better than the peer, 2 ms.
        assert!(t.contains("| clean | yes | yes | yes | yes | yes | yes |"), "{t}");
        let mut worse = report.clone();
        worse.records[0].results[0].score.matched =
            Some(LineErrors { angle_deg: 0.5, offset_mid_px: 0.9, offset_max_px: 1.0 });
        let t = worse.targets_markdown().unwrap();
        assert!(t.contains("| clean | yes | **no** | **no** | yes | **no** | yes |"), "{t}");
        let md = report.markdown();
        assert!(md.contains("| clean | ours | 2 (0) | 100.0 % (2) | 0 / 0 (1) |"), "{md}");
    }

    /// A report of `records` at the clean level, ours against one peer.
    fn clean_report(records: Vec<FrameRecord>) -> ShaftReport {
        ShaftReport {
            set: SeedSet::Report,
            frames_per_family: 1,
            seeds: vec![1],
            levels: vec![ClutterLevel::Clean],
            detectors: vec!["ours".into(), "peer".into()],
            peers: PeerStatus::NotRequested,
            records,
            overlays: vec![],
            elapsed_s: 0.0,
            load_average: [String::new(), String::new()],
        }
    }

    #[test]
    fn the_paired_medians_are_over_the_frames_both_detectors_match_only() {
        // Ours matches three frames, the peer two of them; ours' hardest frame (angle 1.0°)
        // is one the peer misses: unpaired, ours' median is the worse; paired, the better.
        let records = vec![
            record(
                true,
                true,
                vec![result("ours", Some((0.02, 0.1)), 0, 1.0), result("peer", Some((0.05, 0.4)), 0, 1.0)],
            ),
            record(
                true,
                true,
                vec![result("ours", Some((0.06, 0.2)), 0, 1.0), result("peer", Some((0.03, 0.3)), 0, 1.0)],
            ),
            record(true, true, vec![result("ours", Some((1.0, 3.0)), 0, 1.0), result("peer", None, 0, 1.0)]),
            record(
                false,
                true,
                vec![result("ours", Some((0.9, 0.9)), 0, 1.0), result("peer", Some((0.0, 0.0)), 0, 1.0)],
            ),
        ];
        let unpaired = (cell(records.iter(), 0).angle_deg[0], cell(records.iter(), 1).angle_deg[0]);
        assert!(unpaired.0.unwrap() > unpaired.1.unwrap());
        let p = paired(records.iter(), 0, 1);
        assert_eq!(p.common, 2);
        assert!((p.angle_deg[0].unwrap() - 0.04).abs() < 1e-12, "{p:?}");
        assert!((p.angle_deg[1].unwrap() - 0.04).abs() < 1e-12, "{p:?}");
        assert!((p.offset_px[0].unwrap() - 0.15).abs() < 1e-12, "{p:?}");
        assert!((p.offset_px[1].unwrap() - 0.35).abs() < 1e-12, "{p:?}");
        assert_eq!(p.a_better, [1, 2]);
        let report = clean_report(records);
        let t = report.paired_markdown().unwrap();
        assert!(t.contains("| clean | peer | 2 | 0.040 / 0.040 | 0.15 / 0.35 | 1 / 2 |"), "{t}");
        assert!(report.markdown().contains("### Paired accuracy"));
    }
}
