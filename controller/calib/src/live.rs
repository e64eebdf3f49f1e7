//! The live calibration's loop ([`LiveLoop`]: one stereo frame and both arms' data at its time
//! in, our shaft detector on both eyes, the [`crate::collector::Collector`] deciding what to
//! keep and when to solve) and its two input sources:
//! - `comanip-calib live --replay DIR` ([`replay`]): a recorded natural session (`simrobot
//!   generate --frames`) in time order: both arms from the candump log (the tool arm through
//!   fulcrumd's own replay, [`crate::bus_run`]), the frames from their PNG files; the report
//!   compares the result with the run's ground truth;
//! - `comanip-calib live` on the bus ([`crate::live_process`]): frames from the frame service,
//!   the endoscope arm's joints from a passive socket on the bus (`controller::bus_listen`),
//!   the tool line from fulcrumd's output.

use std::fmt::Write as _;
use std::hash::{Hash, Hasher};
use std::path::Path;

use controller::config::Config;
use estimator::calib::{KinematicNoise, Observation, Setup};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

use crate::bus_run::{BusRunError, read_run};
use crate::collector::{
    Calibration, Collector, CollectorConfig, Event, EyeDetection, Progress, Refusal, Sample, ToolSample,
};

/// The replay's options.
#[derive(Clone, Copy, Debug)]
pub struct ReplayOptions {
    /// The observation noise model (weights and Fisher information).
    pub noise: KinematicNoise,
    /// Target: predicted RMS translation at the mean fulcrum, metres.
    pub target_translation_m: f64,
    /// Target: predicted RMS rotation, radians.
    pub target_rotation_rad: f64,
    /// Session time between two lines of the progress log, seconds.
    pub log_every_s: f64,
}

/// Why a replay failed.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// The run cannot be read.
    #[error(transparent)]
    Run(#[from] BusRunError),
    /// The detector cannot be built for the run's camera.
    #[error("detector: {0}")]
    Detector(String),
}

/// Errors of a calibration against the truth and its predicted precision.
#[derive(Clone, Copy, Debug)]
pub struct Scored {
    /// Session time of the solve, seconds from the first frame.
    pub at_s: f64,
    /// Observations used.
    pub observations: usize,
    /// Error of the mean fulcrum mapped into `{e}`, metres.
    pub fulcrum_err_m: f64,
    /// Error of `{t}`'s origin (the tool arm's base), metres.
    pub origin_err_m: f64,
    /// Rotation error, radians.
    pub rotation_err_rad: f64,
    /// The predicted precision (Fisher information).
    pub precision: crate::collector::Precision,
}

/// What the replay found.
#[derive(Clone, Debug)]
pub struct ReplayReport {
    /// The first calibration that reached the target (what the live process publishes).
    pub published: Option<(Calibration, Scored)>,
    /// A final solve on everything kept by the end of the session.
    pub at_end: Option<(Calibration, Scored)>,
    /// Why the final solve failed, when it did.
    pub end_error: Option<String>,
    /// The collector's counts at the end.
    pub progress: Progress,
    /// Session length (first to last frame), seconds.
    pub duration_s: f64,
    /// Progress lines (session time, one line each), for the docs.
    pub log: Vec<String>,
    /// Drift events.
    pub drifts: usize,
    /// The truth `T_e_t` (`{t}` = the tool arm's base).
    pub truth: Isometry3<f64>,
    /// Mean distance of the kept fulcrums to the nearest true trocar, metres.
    pub fulcrum_to_trocar_m: f64,
    /// Camera, hand-eye, right eye and selection rule the collector used.
    pub setup: Setup,
    /// The observations kept at the end (what the final solve used), in the calibration's
    /// dataset form (joints in radians and metres, lines in measured pixels).
    pub kept: Vec<Observation>,
}

/// One stereo frame as a source delivers it, with both arms' data at its exposure mid time.
#[derive(Clone, Copy, Debug)]
pub struct FrameInput<'a> {
    /// Exposure mid time, nanoseconds (the source's clock; strictly increasing for a live
    /// camera: a repeat counts as a frozen camera).
    pub t_ns: u64,
    /// Left and right images: width, height (pixels) and packed 8-bit sRGB bytes; `None` for an
    /// eye the source could not deliver (counted as no instrument).
    pub eyes: [Option<(usize, usize, &'a [u8])>; 2],
    /// The endoscope arm's joints `[yaw rad, pitch rad, insertion m, roll rad]` (any value
    /// when `ecm_age_ns` is `u64::MAX`).
    pub ecm_joints: [f64; 4],
    /// Age of those joints at the frame's time, nanoseconds (`u64::MAX`: none).
    pub ecm_age_ns: u64,
    /// The tool arm's line (fulcrumd's fulcrum, axis, wrist centre) with its ages.
    pub tool: ToolSample,
}

/// The loop both sources run: our detector on both eyes, then the collector.
pub struct LiveLoop {
    det: Box<dyn vision::ShaftDetector + Send>,
    col: Collector,
}

impl LiveLoop {
    /// The loop for the collector settings `cfg` (our detector for its camera).
    pub fn new(cfg: CollectorConfig) -> Result<Self, ReplayError> {
        let det = crate::detect::make_detector(crate::detect::DetectorChoice::Ours, cfg.setup.intrinsics)
            .map_err(ReplayError::Detector)?;
        Ok(Self { det, col: Collector::new(cfg) })
    }

    /// Detects the tool in both eyes of `f` and feeds the collector; returns what it caused.
    pub fn on_frame(&mut self, f: &FrameInput<'_>) -> Event {
        let mut hasher = std::collections::hash_map::DefaultHasher::new();
        let mut eyes = [EyeDetection::default(); 2];
        for (eye, img) in f.eyes.iter().enumerate() {
            let Some((w, h, rgb)) = img else { continue };
            rgb.hash(&mut hasher);
            let Ok(view) = vision::RgbView::new(*w, *h, rgb) else { continue };
            if let Ok(found) = self.det.detect(&view) {
                eyes[eye] = EyeDetection {
                    found: found.len(),
                    ends_px: found.first().map(|d| d.ends_px),
                    confidence: found.first().map_or(0.0, |d| d.confidence),
                    second_confidence: found.get(1).map_or(0.0, |d| d.confidence),
                    sharpness: None,
                };
            }
        }
        let sample = Sample {
            t_ns: f.t_ns,
            frame_digest: hasher.finish(),
            eyes,
            ecm_joints: f.ecm_joints,
            ecm_age_ns: f.ecm_age_ns,
            tool: f.tool,
        };
        self.col.push(&sample)
    }

    /// The collector (counts, precision, result).
    pub fn collector(&self) -> &Collector {
        &self.col
    }

    /// The collector, to solve on request or restart.
    pub fn collector_mut(&mut self) -> &mut Collector {
        &mut self.col
    }
}

/// One progress line (kept, refused by reason, coverage, predicted precision).
pub fn progress_line(p: &Progress, t_s: f64) -> String {
    let mut s = format!("t={t_s:6.1}s frames {:4} kept {:4} |", p.frames, p.kept);
    for r in Refusal::ALL {
        let n = p.refused.get(&r).copied().unwrap_or(0);
        if n > 0 {
            let _ = write!(s, " {} {n},", r.name());
        }
    }
    let _ = write!(
        s,
        " | fulcrum sites {} axis ±{:.1}° scope ±{:.1}°",
        p.trocars,
        p.axis_spread_rad.to_degrees(),
        p.ecm_spread_rad.to_degrees() / 2.0
    );
    match &p.precision {
        Some(q) => {
            let _ = write!(
                s,
                " | predicted {:.2} mm (fulcrum) {:.3}°{}",
                q.fulcrum_m * 1e3,
                q.rotation_rad.to_degrees(),
                if p.solved { " SOLVED" } else { "" }
            );
        }
        None => s.push_str(" | predicted -"),
    }
    s
}

fn score(cal: &Calibration, truth: &Isometry3<f64>, mean_fulcrum: &Vector3<f64>, t0_ns: u64) -> Scored {
    let at = |p: &Isometry3<f64>| p * Point3::from(*mean_fulcrum);
    Scored {
        at_s: cal.t_ns.saturating_sub(t0_ns) as f64 * 1e-9,
        observations: cal.observations,
        fulcrum_err_m: (at(&cal.pose) - at(truth)).norm(),
        origin_err_m: (cal.pose.translation.vector - truth.translation.vector).norm(),
        rotation_err_rad: (cal.pose.rotation.inverse() * truth.rotation).angle(),
        precision: cal.precision,
    }
}

/// Runs the collector over a `simrobot generate --frames` directory in time order.
/// `on_progress(progress, session seconds)` after every frame.
pub fn replay(
    dir: &Path,
    cfg: &Config,
    opts: &ReplayOptions,
    mut on_progress: impl FnMut(&Progress, f64),
) -> Result<ReplayReport, ReplayError> {
    let data = read_run(dir, cfg)?;
    let k = data.intrinsics;
    let setup = Setup {
        intrinsics: k,
        hand_eye: data.hand_eye,
        right_eye: Some(Isometry3::from_parts(
            Translation3::new(data.baseline_m, 0.0, 0.0),
            UnitQuaternion::identity(),
        )),
        selection: crate::pixels::selection_rule(),
        shaft_extent: data.shaft_extent,
    };
    let mut ccfg = CollectorConfig::new(setup, opts.noise);
    ccfg.target_translation_m = opts.target_translation_m;
    ccfg.target_rotation_rad = opts.target_rotation_rad;
    let mut lp = LiveLoop::new(ccfg)?;
    let truth = data.ecm_in_tool_base.inverse();
    let frames_dir = dir.join("frames");
    let t0 = data.timeline.first().map_or(0, |f| f.t_ns);
    let mut published: Option<Calibration> = None;
    let mut log = Vec::new();
    let mut next_log = 0.0;
    let mut drifts = 0;
    for f in &data.timeline {
        let t_s = f.t_ns.saturating_sub(t0) as f64 * 1e-9;
        let imgs = f.files.clone().map(|file| hw_io::camera::png::read_rgb(&frames_dir.join(file)).ok());
        let eyes = [0, 1].map(|e| imgs[e].as_ref().map(|i| (i.width, i.height, i.rgb.as_slice())));
        let input = FrameInput {
            t_ns: f.t_ns,
            eyes,
            ecm_joints: f.ecm_joints,
            ecm_age_ns: f.ecm_age_ns,
            tool: ToolSample {
                fulcrum_valid: f.inside,
                fulcrum_m: f.fulcrum_b.into(),
                axis: f.axis_b.into(),
                wrist_m: f.wrist_b.into(),
                wrist_to_tip_m: data.tip_m,
                age_ns: f.tool_age_ns,
                fulcrum_age_ns: f.tool_age_ns,
            },
        };
        match lp.on_frame(&input) {
            Event::Solved(c) if published.is_none() => published = Some(*c),
            Event::Drift { .. } => drifts += 1,
            _ => {}
        }
        on_progress(lp.collector().progress(), t_s);
        if t_s >= next_log {
            log.push(progress_line(lp.collector().progress(), t_s));
            next_log += opts.log_every_s;
        }
    }
    let col = lp.collector_mut();
    let duration_s = data.timeline.last().map_or(0.0, |f| f.t_ns.saturating_sub(t0) as f64 * 1e-9);
    let t_end = data.timeline.last().map_or(0, |f| f.t_ns);
    let (at_end, end_error) = match col.solve_now(t_end) {
        Some(Ok(c)) => (Some(c), None),
        Some(Err(e)) => (None, Some(e.to_string())),
        None => (None, Some(format!("only {} observations kept", col.observations().len()))),
    };
    log.push(progress_line(col.progress(), duration_s));
    let kept = col.observations();
    let mean_fulcrum =
        kept.iter().map(|o| Vector3::from(o.tool_point_m)).sum::<Vector3<f64>>() / kept.len().max(1) as f64;
    let fulcrum_to_trocar_m = kept
        .iter()
        .map(|o| {
            data.trocars_b.iter().map(|t| (t - Vector3::from(o.tool_point_m)).norm()).fold(f64::INFINITY, f64::min)
        })
        .sum::<f64>()
        / kept.len().max(1) as f64;
    Ok(ReplayReport {
        published: published.map(|c| {
            let s = score(&c, &truth, &mean_fulcrum, t0);
            (c, s)
        }),
        at_end: at_end.map(|c| {
            let s = score(&c, &truth, &mean_fulcrum, t0);
            (c, s)
        }),
        end_error,
        progress: col.progress().clone(),
        duration_s,
        log,
        drifts,
        truth,
        fulcrum_to_trocar_m,
        setup,
        kept: kept.to_vec(),
    })
}

/// Writes the observations kept at the end of a replay as a calibration dataset
/// (`dir/dataset.json`, with the replay's noise model) and the run's truth (`dir/truth.json`;
/// the protocol fields say what they can of a recorded run: `units` is `"run"`, `generated`
/// the frames seen).
pub fn write_dataset(r: &ReplayReport, opts: &ReplayOptions, dir: &Path) -> Result<(), std::io::Error> {
    use hw_io::calib_files::{CALIB_FILE_VERSION, TRUTH_FORMAT, TruthFile, to_json};
    std::fs::create_dir_all(dir)?;
    let file = crate::convert::dataset_json(&r.setup, &r.kept, Some(opts.noise));
    std::fs::write(dir.join("dataset.json"), to_json(&file))?;
    let t = TruthFile {
        format: TRUTH_FORMAT.into(),
        version: CALIB_FILE_VERSION,
        truth: crate::convert::transform_json(&r.truth),
        n_e: 0,
        n_t: 0,
        sigma: 0.0,
        units: "run".into(),
        pixel_sigma_px: 0.0,
        seed: 0,
        generated: r.progress.frames,
        dropped: r.progress.frames.saturating_sub(r.kept.len()),
        collided: 0,
        wrong_lines: vec![],
    };
    std::fs::write(dir.join("truth.json"), to_json(&t))
}

/// The report as Markdown (the command line that produced it first).
pub fn report_markdown(r: &ReplayReport, opts: &ReplayOptions, command: &str) -> String {
    let mut md = String::new();
    let _ = writeln!(md, "<!-- written by `{command}` -->");
    let _ = writeln!(
        md,
        "Session {:.1} s, {} frames; noise model: {:.2} px, {:.2} mrad, {:.2} mm per frame; target {:.2} mm (at the mean fulcrum) / {:.3}°.\n",
        r.duration_s,
        r.progress.frames,
        opts.noise.pixel_px,
        opts.noise.rot_rad * 1e3,
        opts.noise.trans_m * 1e3,
        opts.target_translation_m * 1e3,
        opts.target_rotation_rad.to_degrees()
    );
    let _ = writeln!(
        md,
        "Kept fulcrums are {:.2} mm (mean) from the nearest true trocar; drift events: {}.\n",
        r.fulcrum_to_trocar_m * 1e3,
        r.drifts
    );
    let _ = writeln!(
        md,
        "| result | at (s) | observations | error at fulcrum mm | predicted mm | ratio | error rotation ° | predicted ° | ratio | error base origin mm | predicted mm |"
    );
    let _ = writeln!(md, "|---|---|---|---|---|---|---|---|---|---|---|");
    for (name, s) in [("published (target reached)", &r.published), ("end of session (all kept)", &r.at_end)] {
        match s {
            Some((_, s)) => {
                let _ = writeln!(
                    md,
                    "| {name} | {:.1} | {} | {:.3} | {:.3} | {:.2} | {:.4} | {:.4} | {:.2} | {:.2} | {:.2} |",
                    s.at_s,
                    s.observations,
                    s.fulcrum_err_m * 1e3,
                    s.precision.fulcrum_m * 1e3,
                    s.fulcrum_err_m / s.precision.fulcrum_m,
                    s.rotation_err_rad.to_degrees(),
                    s.precision.rotation_rad.to_degrees(),
                    s.rotation_err_rad / s.precision.rotation_rad,
                    s.origin_err_m * 1e3,
                    s.precision.origin_m * 1e3
                );
            }
            None => {
                let why = if name.starts_with("end") {
                    r.end_error.clone().unwrap_or_default()
                } else {
                    "target not reached".into()
                };
                let _ = writeln!(md, "| {name} | – | – | {why} | | | | | | | |");
            }
        }
    }
    let _ = writeln!(md, "\nProgress (one line per {:.0} s of session):\n\n```text", opts.log_every_s);
    for l in &r.log {
        let _ = writeln!(md, "{l}");
    }
    let _ = writeln!(md, "```");
    md
}
