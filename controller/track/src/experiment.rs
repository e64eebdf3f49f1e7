//! The measurements of `docs/tracking.md`: convergence from perturbed starts (the paper's
//! protocol, Fig. 9: initial errors of 13 mm and 10°), errors after convergence, convergence
//! time, frames per second against particle count; and their plots (SVG, plotters).

use std::path::Path;

use nalgebra::{Vector3, Vector6};
use plotters::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use track::{ToolModel, TrackerConfig};

use crate::input::Sequence;
use crate::run::{FrameResult, RunError, RunOptions, cameras, track};

/// Converged at frame `k` of a trial when every later frame's errors are within these
/// (millimetres, degrees).
pub const CONVERGED: (f64, f64) = (2.0, 4.0);

/// One trial from a perturbed start.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Trial {
    /// Sequence label (seed).
    pub sequence: String,
    /// First frame.
    pub first: usize,
    /// Initial tip position error actually applied, millimetres, and orientation error, degrees.
    pub initial: (f64, f64),
    /// Per frame: position error (mm), orientation error (degrees); `None` when no pose (LOST).
    pub errors: Vec<Option<(f64, f64)>>,
    /// Per frame status.
    pub status: Vec<String>,
    /// First frame index (within the trial) from which the errors stay within [`CONVERGED`].
    pub converged_at: Option<usize>,
    /// Mean step time, milliseconds.
    pub step_ms: f64,
    /// Per frame: the kinematics alone (the encoders as the tracker got them, noise
    /// included) against the truth: position (mm), orientation (degrees).
    #[serde(default)]
    pub kinematics: Vec<Option<(f64, f64)>>,
    /// First frame (within the trial, after the first) at which the tracker re-initialised
    /// from the kinematics (after LOST frames).
    #[serde(default)]
    pub reinitialised_at: Option<usize>,
    /// First frame (within the trial) at which the tracker re-initialised from the detected
    /// shaft (`[proposal]`).
    #[serde(default)]
    pub reseeded_at: Option<usize>,
    /// Per frame: the best hypothesis's inlier share (0..1; ours).
    #[serde(default)]
    pub inlier_share: Vec<Option<f64>>,
    /// Per frame (`[proposal]`): the shaft's axis detected in both eyes.
    #[serde(default)]
    pub axis_detected: Vec<bool>,
    /// Per frame (`[proposal]`): the best hypothesis on the axis's inlier share, when tried.
    #[serde(default)]
    pub reseed_share: Vec<Option<f64>>,
}

/// The results of one mode on a set of trials.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ConvergeResults {
    /// `paper` or `ours`.
    pub mode: String,
    /// Particles.
    pub particles: usize,
    /// Frame rate of the sequences, frames per second.
    pub fps: f64,
    /// The motion model (`crate::run::motion_name`): `offset` (the kinematic error as state,
    /// ours' default) or `joints` (the random walk over the joints; the paper's mode's only
    /// one); empty in files written before it was recorded.
    #[serde(default)]
    pub motion: String,
    /// The trials.
    pub trials: Vec<Trial>,
}

impl ConvergeResults {
    /// The results of `trials` run with tracker configuration `cfg` (its mode, particle count
    /// and motion model recorded; frame rate 0: not a rate measurement).
    pub fn of_trials(cfg: &TrackerConfig, trials: Vec<Trial>) -> Self {
        Self {
            mode: crate::run::mode_name(cfg.mode).into(),
            particles: cfg.particles,
            fps: 0.0,
            motion: crate::run::motion_name(cfg).into(),
            trials,
        }
    }

    /// The name plots and tables give these results: `paper`, `ours (offset)`, `ours
    /// (random walk)`, or the bare mode when the motion model was not recorded.
    pub fn label(&self) -> String {
        match (self.mode.as_str(), self.motion.as_str()) {
            ("ours", "offset") => "ours (offset)".into(),
            ("ours", "joints") => "ours (random walk)".into(),
            (m, _) => m.into(),
        }
    }
}

/// A joint offset moving the tip by `dp` (metres) and turning it by `dr` (rotation vector,
/// radians) at joints `q` (first order, then corrected by two Newton steps).
pub fn joint_offset(model: &ToolModel, q: &[f64; 6], dp: &Vector3<f64>, dr: &Vector3<f64>) -> Option<[f64; 6]> {
    let t0 = model.tip_in_base(q)?;
    let target_p = t0.translation.vector + dp;
    let target_r = nalgebra::UnitQuaternion::from_scaled_axis(*dr) * t0.rotation;
    let mut x = *q;
    for _ in 0..4 {
        let t = model.tip_in_base(&x)?;
        let ep = target_p - t.translation.vector;
        let er = (target_r * t.rotation.inverse()).scaled_axis();
        let e = Vector6::new(ep.x, ep.y, ep.z, er.x, er.y, er.z);
        let j = model.tip_jacobian(&x)?;
        let d = j.lu().solve(&e)?;
        for k in 0..6 {
            x[k] += d[k];
        }
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

fn random_unit(r: &mut ChaCha8Rng) -> Vector3<f64> {
    loop {
        let v =
            Vector3::new(r.random::<f64>() * 2.0 - 1.0, r.random::<f64>() * 2.0 - 1.0, r.random::<f64>() * 2.0 - 1.0);
        let n = v.norm();
        if n > 0.1 && n <= 1.0 {
            return v / n;
        }
    }
}

/// Runs `trials` trials on `seq` (label `label`): each from a random frame among those with
/// the instrument visible in both eyes (at least `min_px` pixels) for the whole trial (`frames`
/// frames), started from the
/// encoders' joints moved so that the tip is `pos_m` away and turned by `rot_rad`.
/// `noise_rad`: standard deviation of the Gaussian noise added to every joint's encoder
/// reading, radians (0: none). `progress` is called after each tracked frame.
#[allow(clippy::too_many_arguments)]
pub fn converge(
    seq: &Sequence,
    label: &str,
    model: &ToolModel,
    cfg: TrackerConfig,
    trials: usize,
    frames: usize,
    pos_m: f64,
    rot_rad: f64,
    seed: u64,
    min_px: u64,
    noise_rad: f64,
    progress: &dyn Fn(),
) -> Result<Vec<Trial>, RunError> {
    let visible = |i: usize| {
        seq.frames.get(i).is_some_and(|f| {
            f.encoder_rad.is_some()
                && f.ecm_joints.is_some()
                && f.truth.is_some_and(|t| t.instrument_px[0] >= min_px && t.instrument_px[1] >= min_px)
        })
    };
    let starts: Vec<usize> = (0..seq.frames.len()).filter(|&i| (i..i + frames).all(visible)).collect();
    if starts.is_empty() {
        return Err(RunError::Nothing(seq.frames.len()));
    }
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    let mut out = Vec::with_capacity(trials);
    for t in 0..trials {
        let first = starts[r.random_range(0..starts.len())];
        let f = &seq.frames[first];
        let (Some(enc), Some(ecm)) = (f.encoder_rad, f.ecm_joints) else { continue };
        // The perturbation is given in the camera frame's terms; the tip's error does not
        // depend on the frame it is expressed in.
        let dp = random_unit(&mut r) * pos_m;
        let dr = random_unit(&mut r) * rot_rad;
        let Some(start) = joint_offset(model, &enc, &dp, &dr) else { continue };
        let mut c = cfg;
        c.seed = seed.wrapping_mul(1000).wrapping_add(t as u64);
        let encoder_noise = (noise_rad > 0.0)
            .then_some(crate::run::EncoderNoise { sigma_rad: [noise_rad; 6], seed: c.seed ^ 0x05EE_D0F0_015E });
        let res = track(
            seq,
            model,
            c,
            &RunOptions {
                first,
                count: frames,
                start_joints: Some(start),
                overlay: None,
                progress: &|_| progress(),
                encoder_noise,
            },
        )?;
        let init = f.truth.and_then(|tr| {
            let tip = model.tip_in_base(&start)?;
            Some(crate::run::errors(&(cameras(seq, &ecm).left_from_base * tip), &tr))
        });
        out.push(trial_of(label, first, init.unwrap_or((f64::NAN, f64::NAN)), &res));
    }
    Ok(out)
}

fn trial_of(label: &str, first: usize, initial: (f64, f64), res: &[FrameResult]) -> Trial {
    let errors: Vec<Option<(f64, f64)>> = res.iter().map(|r| r.error_mm.zip(r.error_deg)).collect();
    let ok = |e: &Option<(f64, f64)>| e.is_some_and(|(p, a)| p <= CONVERGED.0 && a <= CONVERGED.1);
    let mut converged_at = None;
    for k in (0..errors.len()).rev() {
        if ok(&errors[k]) {
            converged_at = Some(k);
        } else {
            break;
        }
    }
    let n = res.len().max(1) as f64;
    Trial {
        sequence: label.to_string(),
        first,
        initial,
        errors,
        status: res.iter().map(|r| r.status.clone()).collect(),
        converged_at,
        step_ms: res.iter().map(|r| r.step_ms).sum::<f64>() / n,
        kinematics: res.iter().map(|r| r.kinematics_error_mm.zip(r.kinematics_error_deg)).collect(),
        reinitialised_at: res.iter().skip(1).position(|r| r.reinitialised).map(|k| k + 1),
        reseeded_at: res.iter().position(|r| r.reseeded_from_vision),
        inlier_share: res.iter().map(|r| r.inlier_share).collect(),
        axis_detected: res.iter().map(|r| r.axis_detected).collect(),
        reseed_share: res.iter().map(|r| r.reseed_share).collect(),
    }
}

/// Median and 95th percentile (nearest rank) of `v`; NaN when empty.
pub fn median_p95(v: &mut [f64]) -> (f64, f64) {
    if v.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v[((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1];
    (at(0.5), at(0.95))
}

/// Summary of a mode's trials: converged fraction, errors after convergence (the frames of
/// every converged trial from its convergence on, at most its last `tail`: median and p95 of position mm, orientation deg),
/// convergence time (frames: median, p95) and mean step time.
#[derive(Clone, Debug, Serialize)]
pub struct Summary {
    /// `paper` or `ours`.
    pub mode: String,
    /// Particles.
    pub particles: usize,
    /// Trials.
    pub trials: usize,
    /// Trials converged by their end.
    pub converged: usize,
    /// … of which converged at or after a re-initialisation from the kinematics.
    pub converged_after_reinit: usize,
    /// … of which converged at or after a re-initialisation from the detected shaft, with
    /// no re-initialisation from the kinematics before convergence.
    pub converged_after_vision_reseed: usize,
    /// Position error after convergence, mm (median, p95).
    pub position_mm: (f64, f64),
    /// Orientation error after convergence, degrees (median, p95).
    pub orientation_deg: (f64, f64),
    /// Position error of every trial's last frame, converged or not, mm (median, p95).
    pub final_position_mm: (f64, f64),
    /// Orientation error of every trial's last frame, degrees (median, p95).
    pub final_orientation_deg: (f64, f64),
    /// Convergence time, frames (median, p95, over converged trials).
    pub convergence_frames: (f64, f64),
    /// Mean step time, milliseconds.
    pub step_ms: f64,
    /// LOST frames over all frames.
    pub lost_frames: usize,
    /// All frames.
    pub frames: usize,
    /// The kinematics alone over the same frames as "after convergence" of the converged
    /// trials, mm (median, p95).
    pub kinematics_mm: (f64, f64),
    /// … orientation, degrees (median, p95).
    pub kinematics_deg: (f64, f64),
    /// Tracker over every frame of every trial (LOST frames left out), mm (median, p95).
    pub all_position_mm: (f64, f64),
    /// The kinematics over every frame of every trial, mm (median, p95).
    pub all_kinematics_mm: (f64, f64),
    /// Tracker orientation over every frame of every trial (LOST left out), degrees (median,
    /// p95).
    pub all_orientation_deg: (f64, f64),
}

/// Summarises `r` (`tail` last frames of each converged trial).
pub fn summarise(r: &ConvergeResults, tail: usize) -> Summary {
    let (mut p, mut a, mut fp, mut fa, mut ct) = (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut lost = 0;
    let mut frames = 0;
    let (mut kp, mut ka, mut allp, mut allk) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut alla = Vec::new();
    for t in &r.trials {
        allp.extend(t.errors.iter().flatten().map(|e| e.0));
        alla.extend(t.errors.iter().flatten().map(|e| e.1));
        allk.extend(t.kinematics.iter().flatten().map(|e| e.0));
        if let Some(k) = t.converged_at {
            for (x, y) in t.kinematics.iter().skip(t.kinematics.len().saturating_sub(tail).max(k)).flatten() {
                kp.push(*x);
                ka.push(*y);
            }
        }
        lost += t.status.iter().filter(|s| *s == "LOST").count();
        frames += t.status.len();
        if let Some(Some((x, y))) = t.errors.last() {
            fp.push(*x);
            fa.push(*y);
        } else {
            fp.push(f64::INFINITY);
            fa.push(f64::INFINITY);
        }
        if let Some(k) = t.converged_at {
            ct.push(k as f64);
            for (x, y) in t.errors.iter().skip(t.errors.len().saturating_sub(tail).max(k)).flatten() {
                p.push(*x);
                a.push(*y);
            }
        }
    }
    Summary {
        mode: r.mode.clone(),
        particles: r.particles,
        trials: r.trials.len(),
        converged: r.trials.iter().filter(|t| t.converged_at.is_some()).count(),
        converged_after_reinit: r
            .trials
            .iter()
            .filter(|t| t.converged_at.zip(t.reinitialised_at).is_some_and(|(c, k)| c >= k))
            .count(),
        converged_after_vision_reseed: r
            .trials
            .iter()
            .filter(|t| {
                t.converged_at.zip(t.reseeded_at).is_some_and(|(c, k)| c >= k)
                    && t.converged_at.zip(t.reinitialised_at).is_none_or(|(c, k)| c < k)
            })
            .count(),
        position_mm: median_p95(&mut p),
        orientation_deg: median_p95(&mut a),
        final_position_mm: median_p95(&mut fp),
        final_orientation_deg: median_p95(&mut fa),
        convergence_frames: median_p95(&mut ct),
        step_ms: r.trials.iter().map(|t| t.step_ms).sum::<f64>() / r.trials.len().max(1) as f64,
        lost_frames: lost,
        frames,
        kinematics_mm: median_p95(&mut kp),
        kinematics_deg: median_p95(&mut ka),
        all_position_mm: median_p95(&mut allp),
        all_kinematics_mm: median_p95(&mut allk),
        all_orientation_deg: median_p95(&mut alla),
    }
}

/// Why a plot could not be written.
#[derive(Debug, thiserror::Error)]
#[error("plot {path}: {message}")]
pub struct PlotError {
    /// The file.
    pub path: String,
    /// Why.
    pub message: String,
}

fn perr(path: &Path) -> impl Fn(String) -> PlotError + '_ {
    move |message| PlotError { path: path.display().to_string(), message }
}

/// Median position error (mm) against the frame of the trial, one line per mode (log scale).
pub fn plot_convergence(path: &Path, results: &[ConvergeResults], frames: usize) -> Result<(), PlotError> {
    let e = perr(path);
    let root = SVGBackend::new(path, (720, 420)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(x.to_string()))?;
    let mut chart = ChartBuilder::on(&root)
        .caption("Convergence from 13 mm / 10° starts: median tip error per frame", ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0f64..frames as f64, (0.1f64..100f64).log_scale())
        .map_err(|x| e(x.to_string()))?;
    chart
        .configure_mesh()
        .x_desc("frame since the perturbed start")
        .y_desc("tip position error, mm (median, p90 band)")
        .draw()
        .map_err(|x| e(x.to_string()))?;
    for (ci, r) in results.iter().enumerate() {
        let colour = Palette99::pick(ci).to_rgba();
        let mut med = Vec::new();
        let mut hi = Vec::new();
        for k in 0..frames {
            let mut v: Vec<f64> = r
                .trials
                .iter()
                .filter_map(|t| t.errors.get(k).map(|x| x.map_or(100.0, |y| y.0.clamp(0.1, 100.0))))
                .collect();
            if v.is_empty() {
                continue;
            }
            v.sort_by(f64::total_cmp);
            med.push((k as f64, v[v.len() / 2]));
            hi.push((k as f64, v[((v.len() as f64 * 0.9) as usize).min(v.len() - 1)]));
        }
        chart
            .draw_series(LineSeries::new(med, colour.stroke_width(2)))
            .map_err(|x| e(x.to_string()))?
            .label(format!("{} ({} particles) median", r.mode, r.particles))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
        chart.draw_series(LineSeries::new(hi, colour.mix(0.5))).map_err(|x| e(x.to_string()))?;
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|x| e(x.to_string()))?;
    root.present().map_err(|x| e(x.to_string()))
}

/// One point of the rate measurement.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RatePoint {
    /// `paper` or `ours`.
    pub mode: String,
    /// Particles.
    pub particles: usize,
    /// Median step time, milliseconds.
    pub step_ms: f64,
    /// Frames per second (1000 / median step time).
    pub fps: f64,
}

/// Frames per second against particle count (log-log).
pub fn plot_rate(path: &Path, points: &[RatePoint]) -> Result<(), PlotError> {
    let e = perr(path);
    let root = SVGBackend::new(path, (720, 420)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(x.to_string()))?;
    let max_n = points.iter().map(|p| p.particles).max().unwrap_or(1000) as f64 * 1.5;
    let mut chart = ChartBuilder::on(&root)
        .caption("Frames per second against particles (stereo 640×480, 2-vCPU VM)", ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d((10f64..max_n).log_scale(), (0.01f64..1000f64).log_scale())
        .map_err(|x| e(x.to_string()))?;
    chart.configure_mesh().x_desc("particles").y_desc("frames per second").draw().map_err(|x| e(x.to_string()))?;
    for (ci, mode) in ["paper", "ours"].into_iter().enumerate() {
        let colour = Palette99::pick(ci).to_rgba();
        let pts: Vec<(f64, f64)> =
            points.iter().filter(|p| p.mode == mode).map(|p| (p.particles as f64, p.fps)).collect();
        chart
            .draw_series(LineSeries::new(pts.clone(), colour.stroke_width(2)))
            .map_err(|x| e(x.to_string()))?
            .label(mode)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
        chart.draw_series(pts.iter().map(|p| Circle::new(*p, 4, colour.filled()))).map_err(|x| e(x.to_string()))?;
    }
    let target = vec![(10f64, 30f64), (max_n, 30f64)];
    chart
        .draw_series(LineSeries::new(target, BLACK.mix(0.4)))
        .map_err(|x| e(x.to_string()))?
        .label("30 fps target")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK.mix(0.4)));
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|x| e(x.to_string()))?;
    root.present().map_err(|x| e(x.to_string()))
}
