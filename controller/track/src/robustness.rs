//! The robustness experiments of `docs/tracking.md`: joint-sensor noise (the paper's Fig. 10
//! and Fig. 11) and the scene conditions (a second instrument crossing, smoke, an occluder
//! hiding half or all of the instrument for a time window) with tracking loss and recovery;
//! their summaries and plots (SVG, plotters).

use std::path::Path;

use plotters::prelude::*;
use serde::{Deserialize, Serialize};
use track::{ToolModel, TrackerConfig};

use crate::experiment::{ConvergeResults, PlotError, median_p95};
use crate::input::Sequence;
use crate::run::{RunError, RunOptions, mode_name, track};

/// One joint-sensor noise level's trials.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct NoiseLevel {
    /// Standard deviation of the noise added to every joint's reading, milliradians.
    pub sigma_mrad: f64,
    /// The trials (as `converge`'s).
    pub results: ConvergeResults,
}

/// A sweep over noise levels (one mode).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct NoiseSweep {
    /// Initial tip position error of the trials, millimetres (0: started at the truth).
    pub pos_mm: f64,
    /// Initial orientation error, degrees.
    pub rot_deg: f64,
    /// The levels.
    pub levels: Vec<NoiseLevel>,
}

fn perr(path: &Path) -> impl Fn(String) -> PlotError + '_ {
    move |message| PlotError { path: path.display().to_string(), message }
}

/// Median tip error over every frame of every trial (converged or not, LOST frames left out)
/// against the noise level, one line per sweep (labelled by [`ConvergeResults::label`]), and
/// the kinematics alone (dashed) over the first sweep's frames (the same frames and noise
/// draws as the others' when they were run with the same settings and seed); the converged
/// trials' share is in the table.
pub fn plot_noise(path: &Path, sweeps: &[NoiseSweep], tail: usize, title: &str) -> Result<(), PlotError> {
    let e = perr(path);
    let root = SVGBackend::new(path, (720, 420)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(x.to_string()))?;
    let max_s = sweeps.iter().flat_map(|s| s.levels.iter().map(|l| l.sigma_mrad)).fold(1.0, f64::max);
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0f64..max_s * 1.05, (0.1f64..30f64).log_scale())
        .map_err(|x| e(x.to_string()))?;
    chart
        .configure_mesh()
        .x_desc("joint-sensor noise σ per joint, mrad")
        .y_desc("tip error, mm (median, all frames)")
        .draw()
        .map_err(|x| e(x.to_string()))?;
    let mut kinematics = Vec::new();
    for (ci, s) in sweeps.iter().enumerate() {
        let colour = Palette99::pick(ci).to_rgba();
        let name = s.levels.first().map_or_else(String::new, |l| l.results.label());
        let trials = s.levels.first().map_or(0, |l| l.results.trials.len());
        let mut tr = Vec::new();
        let mut kin = Vec::new();
        for l in &s.levels {
            let sm = crate::experiment::summarise(&l.results, tail);
            tr.push((l.sigma_mrad, sm.all_position_mm.0.clamp(0.1, 30.0)));
            kin.push((l.sigma_mrad, sm.all_kinematics_mm.0.clamp(0.1, 30.0)));
        }
        chart
            .draw_series(LineSeries::new(tr.clone(), colour.stroke_width(2)))
            .map_err(|x| e(x.to_string()))?
            .label(format!("{name}: tracker ({trials} trials per level)"))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
        chart.draw_series(tr.iter().map(|p| Circle::new(*p, 4, colour.filled()))).map_err(|x| e(x.to_string()))?;
        if ci == 0 {
            kinematics = kin;
        }
    }
    let grey = BLACK.mix(0.5);
    chart
        .draw_series(DashedLineSeries::new(kinematics, 6, 4, grey.stroke_width(2)))
        .map_err(|x| e(x.to_string()))?
        .label("kinematics alone (noisy encoders)")
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], grey.stroke_width(2)));
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|x| e(x.to_string()))?;
    root.present().map_err(|x| e(x.to_string()))
}

/// Median over the trials of frame `k`'s error (mm, clamped to 0.1-30 for the log scale; a
/// frame without a pose counts as 30), per frame `k`; `pick` takes a trial's per-frame errors.
fn median_per_frame(
    trials: &[crate::experiment::Trial],
    frames: usize,
    pick: impl Fn(&crate::experiment::Trial) -> &[Option<(f64, f64)>],
) -> Vec<(f64, f64)> {
    let mut med = Vec::new();
    for k in 0..frames {
        let mut v: Vec<f64> =
            trials.iter().filter_map(|t| pick(t).get(k).map(|x| x.map_or(30.0, |y| y.0.clamp(0.1, 30.0)))).collect();
        if v.is_empty() {
            continue;
        }
        v.sort_by(f64::total_cmp);
        med.push((k as f64, v[v.len() / 2]));
    }
    med
}

/// The paper's Fig. 11: median tip error per frame of the trajectories, one panel per noise
/// level (the levels of the first sweep), in each one line per sweep (labelled by
/// [`ConvergeResults::label`]) and the kinematics alone (dashed) over the first sweep's
/// trajectories.
pub fn plot_noise_frames(path: &Path, sweeps: &[NoiseSweep], title: &str) -> Result<(), PlotError> {
    let e = perr(path);
    let sigmas: Vec<f64> = sweeps.first().map(|s| s.levels.iter().map(|l| l.sigma_mrad).collect()).unwrap_or_default();
    let panels = sigmas.len().max(1);
    let root = SVGBackend::new(path, (360 * panels as u32 + 20, 440)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(x.to_string()))?;
    let root = root.titled(title, ("sans-serif", 18)).map_err(|x| e(x.to_string()))?;
    let frames = sweeps
        .iter()
        .flat_map(|s| s.levels.iter().flat_map(|l| l.results.trials.iter().map(|t| t.errors.len())))
        .max()
        .unwrap_or(1);
    for (pi, (area, &sigma)) in root.split_evenly((1, panels)).iter().zip(&sigmas).enumerate() {
        let mut chart = ChartBuilder::on(area)
            .caption(format!("σ = {sigma} mrad per joint"), ("sans-serif", 15))
            .margin(8)
            .x_label_area_size(40)
            .y_label_area_size(if pi == 0 { 60 } else { 40 })
            .build_cartesian_2d(0f64..(frames.saturating_sub(1).max(1)) as f64, (0.1f64..30f64).log_scale())
            .map_err(|x| e(x.to_string()))?;
        let mut mesh = chart.configure_mesh();
        mesh.x_desc("frame of the trajectory (10 fps)");
        if pi == 0 {
            mesh.y_desc("tip error, mm (median over trajectories)");
        }
        mesh.draw().map_err(|x| e(x.to_string()))?;
        let mut kinematics = None;
        for (ci, s) in sweeps.iter().enumerate() {
            let Some(l) = s.levels.iter().find(|l| l.sigma_mrad == sigma) else { continue };
            let colour = Palette99::pick(ci).to_rgba();
            let med = median_per_frame(&l.results.trials, frames, |t| &t.errors);
            chart
                .draw_series(LineSeries::new(med, colour.stroke_width(2)))
                .map_err(|x| e(x.to_string()))?
                .label(format!("{} ({} trajectories)", l.results.label(), l.results.trials.len()))
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
            if kinematics.is_none() {
                kinematics = Some(median_per_frame(&l.results.trials, frames, |t| &t.kinematics));
            }
        }
        if let Some(kin) = kinematics {
            let grey = BLACK.mix(0.5);
            chart
                .draw_series(DashedLineSeries::new(kin, 6, 4, grey.stroke_width(2)))
                .map_err(|x| e(x.to_string()))?
                .label("kinematics alone (noisy encoders)")
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], grey.stroke_width(2)));
        }
        if pi == 0 {
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::LowerRight)
                .background_style(WHITE.mix(0.8))
                .border_style(BLACK)
                .draw()
                .map_err(|x| e(x.to_string()))?;
        }
    }
    root.present().map_err(|x| e(x.to_string()))
}

/// One tracked frame of a scene run.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SceneFrame {
    /// Index in the sequence.
    pub index: usize,
    /// TRACKING, UNCERTAIN, LOST or SKIPPED.
    pub status: String,
    /// Tracker against the truth: position (mm), orientation (degrees); `None` without pose.
    pub error: Option<(f64, f64)>,
    /// The kinematics alone against the truth.
    pub kinematics: Option<(f64, f64)>,
    /// The instrument's visible fraction, left and right eyes (renderer's truth).
    pub visible: [Option<f64>; 2],
    /// The occluder window's target fraction at this frame.
    pub target: Option<f64>,
}

/// One mode tracking one sequence of one condition.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SceneRun {
    /// The condition (`baseline`, `second instrument`, `smoke`, `occluder`...).
    pub condition: String,
    /// The sequence (run directory name).
    pub sequence: String,
    /// `paper` or `ours`.
    pub mode: String,
    /// Particles.
    pub particles: usize,
    /// Frame rate of the sequence, frames per second.
    pub fps: f64,
    /// Mean step time, milliseconds.
    pub step_ms: f64,
    /// The frames, in order.
    pub frames: Vec<SceneFrame>,
}

/// Tracks `seq` from the first to the last frame where the instrument covers at least
/// `min_px` pixels in both eyes (the tracker starting from the kinematics there).
#[allow(clippy::too_many_arguments)]
pub fn scene(
    seq: &Sequence,
    sequence: &str,
    condition: &str,
    model: &ToolModel,
    cfg: TrackerConfig,
    min_px: u64,
    progress: &dyn Fn(usize),
) -> Result<SceneRun, RunError> {
    // The occluded frames count as visible: their unoccluded pixels are visible px / fraction.
    let seen = |i: usize| {
        seq.frames[i].truth.is_some_and(|t| {
            (0..2).all(|e| {
                let f = t.visible_fraction[e].unwrap_or(1.0).max(1e-3);
                t.instrument_px[e] as f64 / f >= min_px as f64 || t.occlusion_target.is_some()
            })
        })
    };
    let idx: Vec<usize> = (0..seq.frames.len()).filter(|&i| seen(i)).collect();
    let (Some(&first), Some(&last)) = (idx.first(), idx.last()) else {
        return Err(RunError::Nothing(seq.frames.len()));
    };
    let res = track(
        seq,
        model,
        cfg,
        &RunOptions {
            first,
            count: last - first + 1,
            start_joints: None,
            overlay: None,
            progress,
            encoder_noise: None,
        },
    )?;
    let dt: Vec<f64> = seq.frames.windows(2).map(|w| (w[1].t_ns.saturating_sub(w[0].t_ns)) as f64 * 1e-9).collect();
    let fps = if dt.is_empty() { 0.0 } else { dt.len() as f64 / dt.iter().sum::<f64>().max(1e-9) };
    let n = res.len().max(1) as f64;
    Ok(SceneRun {
        condition: condition.to_string(),
        sequence: sequence.to_string(),
        mode: mode_name(cfg.mode).to_string(),
        particles: cfg.particles,
        fps,
        step_ms: res.iter().map(|r| r.step_ms).sum::<f64>() / n,
        frames: res
            .iter()
            .map(|r| SceneFrame {
                index: r.index,
                status: r.status.clone(),
                error: r.error_mm.zip(r.error_deg),
                kinematics: r.kinematics_error_mm.zip(r.kinematics_error_deg),
                visible: r.visible_fraction,
                target: r.occlusion_target,
            })
            .collect(),
    })
}

/// A run's summary outside the occluder windows.
#[derive(Clone, Debug, Serialize)]
pub struct ConditionSummary {
    /// Condition.
    pub condition: String,
    /// Sequence.
    pub sequence: String,
    /// Mode.
    pub mode: String,
    /// Frames tracked (outside occluder windows).
    pub frames: usize,
    /// LOST frames among them.
    pub lost: usize,
    /// UNCERTAIN frames among them.
    pub uncertain: usize,
    /// Tracker position error, mm (median, p95; frames with a pose).
    pub position_mm: (f64, f64),
    /// Orientation error, degrees (median, p95).
    pub orientation_deg: (f64, f64),
    /// The kinematics alone, mm (median, p95).
    pub kinematics_mm: (f64, f64),
    /// Median of the left eye's visible fraction.
    pub visible_median: f64,
    /// Lowest left-eye visible fraction.
    pub visible_min: f64,
    /// Mean step time, ms.
    pub step_ms: f64,
}

/// Summary of `r` over the frames outside occluder windows.
pub fn summarise_condition(r: &SceneRun) -> ConditionSummary {
    let fr: Vec<&SceneFrame> = r.frames.iter().filter(|f| f.target.is_none() && f.status != "SKIPPED").collect();
    let mut p: Vec<f64> = fr.iter().filter_map(|f| f.error.map(|e| e.0)).collect();
    let mut a: Vec<f64> = fr.iter().filter_map(|f| f.error.map(|e| e.1)).collect();
    let mut k: Vec<f64> = fr.iter().filter_map(|f| f.kinematics.map(|e| e.0)).collect();
    let mut v: Vec<f64> = fr.iter().filter_map(|f| f.visible[0]).collect();
    let vmin = v.iter().copied().fold(f64::INFINITY, f64::min);
    ConditionSummary {
        condition: r.condition.clone(),
        sequence: r.sequence.clone(),
        mode: r.mode.clone(),
        frames: fr.len(),
        lost: fr.iter().filter(|f| f.status == "LOST").count(),
        uncertain: fr.iter().filter(|f| f.status == "UNCERTAIN").count(),
        position_mm: median_p95(&mut p),
        orientation_deg: median_p95(&mut a),
        kinematics_mm: median_p95(&mut k),
        visible_median: median_p95(&mut v).0,
        visible_min: vmin,
        step_ms: r.step_ms,
    }
}

/// Thresholds of "recovered": TRACKING with errors within these (millimetres, degrees).
pub const RECOVERED: (f64, f64) = (1.0, 2.0);
/// A looser recovery criterion (the convergence criterion of `converge`).
pub const RECOVERED_LOOSE: (f64, f64) = crate::experiment::CONVERGED;

/// One occluder window of a run: what the tracker did through it and after it.
#[derive(Clone, Debug, Serialize)]
pub struct WindowSummary {
    /// Condition.
    pub condition: String,
    /// Sequence.
    pub sequence: String,
    /// Mode.
    pub mode: String,
    /// The window's target fraction hidden.
    pub target: f64,
    /// First frame of the window (sequence index).
    pub start: usize,
    /// Frames in the window.
    pub frames: usize,
    /// Mean visible fraction in the window, left and right eyes.
    pub visible: [f64; 2],
    /// LOST frames in the window.
    pub lost: usize,
    /// UNCERTAIN frames in the window.
    pub uncertain: usize,
    /// Median position error of the frames with a pose in the window, mm.
    pub position_mm: f64,
    /// Seconds from the window's start to its first LOST frame.
    pub first_lost_s: Option<f64>,
    /// LOST frames in the second after the window (the instrument visible again).
    pub lost_after: usize,
    /// Seconds from the reappearance (first frame after the window) to the first TRACKING
    /// frame.
    pub tracking_after_s: Option<f64>,
    /// … to the first TRACKING frame within [`RECOVERED`] (1 mm, 2°).
    pub recovered_s: Option<f64>,
    /// … to the first TRACKING frame within [`RECOVERED_LOOSE`] (2 mm, 4°).
    pub recovered_loose_s: Option<f64>,
    /// Median position error over the second after the window, mm.
    pub after_position_mm: f64,
}

/// The occluder windows of `r`.
pub fn summarise_windows(r: &SceneRun) -> Vec<WindowSummary> {
    let mut out = Vec::new();
    let f = &r.frames;
    let fps = if r.fps > 0.0 { r.fps } else { 10.0 };
    let mut i = 0;
    while i < f.len() {
        let Some(target) = f[i].target else {
            i += 1;
            continue;
        };
        let start = i;
        while i < f.len() && f[i].target.is_some() {
            i += 1;
        }
        let win = &f[start..i];
        let after = &f[i..f.len().min(i + fps.round() as usize)];
        let mean = |e: usize| {
            let v: Vec<f64> = win.iter().filter_map(|x| x.visible[e]).collect();
            if v.is_empty() { 0.0 } else { v.iter().sum::<f64>() / v.len() as f64 }
        };
        let mut wp: Vec<f64> = win.iter().filter_map(|x| x.error.map(|e| e.0)).collect();
        let mut ap: Vec<f64> = after.iter().filter_map(|x| x.error.map(|e| e.0)).collect();
        let first_ok = |lim: Option<(f64, f64)>| {
            f[i..].iter().position(|x| {
                x.status == "TRACKING" && lim.is_none_or(|(p, a)| x.error.is_some_and(|e| e.0 <= p && e.1 <= a))
            })
        };
        out.push(WindowSummary {
            condition: r.condition.clone(),
            sequence: r.sequence.clone(),
            mode: r.mode.clone(),
            target,
            start: win[0].index,
            frames: win.len(),
            visible: [mean(0), mean(1)],
            lost: win.iter().filter(|x| x.status == "LOST").count(),
            uncertain: win.iter().filter(|x| x.status == "UNCERTAIN").count(),
            position_mm: median_p95(&mut wp).0,
            first_lost_s: win.iter().position(|x| x.status == "LOST").map(|k| k as f64 / fps),
            lost_after: after.iter().filter(|x| x.status == "LOST").count(),
            tracking_after_s: first_ok(None).map(|k| k as f64 / fps),
            recovered_s: first_ok(Some(RECOVERED)).map(|k| k as f64 / fps),
            recovered_loose_s: first_ok(Some(RECOVERED_LOOSE)).map(|k| k as f64 / fps),
            after_position_mm: median_p95(&mut ap).0,
        });
    }
    out
}

/// Tip error against time for the runs of one sequence and condition (one line per mode,
/// LOST frames as crosses at the top, the kinematics dashed, occluder windows shaded).
pub fn plot_scene(path: &Path, runs: &[&SceneRun], title: &str) -> Result<(), PlotError> {
    let e = perr(path);
    let root = SVGBackend::new(path, (820, 400)).into_drawing_area();
    root.fill(&WHITE).map_err(|x| e(x.to_string()))?;
    let fps = runs.first().map_or(10.0, |r| if r.fps > 0.0 { r.fps } else { 10.0 });
    let i0 = runs.iter().filter_map(|r| r.frames.first().map(|f| f.index)).min().unwrap_or(0);
    let i1 = runs.iter().filter_map(|r| r.frames.last().map(|f| f.index)).max().unwrap_or(1);
    let t = |i: usize| i as f64 / fps;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 18))
        .margin(10)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(t(i0)..t(i1 + 1), (0.1f64..60f64).log_scale())
        .map_err(|x| e(x.to_string()))?;
    chart
        .configure_mesh()
        .x_desc("time, s (frame index / fps); shaded: occluder (darker: all hidden); x: LOST")
        .y_desc("tip error, mm")
        .draw()
        .map_err(|x| e(x.to_string()))?;
    if let Some(r) = runs.first() {
        let shade = r.frames.iter().filter_map(|f| {
            f.target.map(|g| {
                let c = if g >= 1.0 { BLACK.mix(0.25) } else { BLACK.mix(0.1) };
                Rectangle::new([(t(f.index) - 0.5 / fps, 0.1), (t(f.index) + 0.5 / fps, 60.0)], c.filled())
            })
        });
        chart.draw_series(shade).map_err(|x| e(x.to_string()))?;
        let kin: Vec<(f64, f64)> =
            r.frames.iter().filter_map(|f| f.kinematics.map(|k| (t(f.index), k.0.clamp(0.1, 60.0)))).collect();
        let grey = BLACK.mix(0.5);
        chart
            .draw_series(DashedLineSeries::new(kin, 5, 4, grey.stroke_width(1)))
            .map_err(|x| e(x.to_string()))?
            .label("kinematics alone")
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], grey));
    }
    for (ci, r) in runs.iter().enumerate() {
        let colour = Palette99::pick(ci).to_rgba();
        let pts: Vec<(f64, f64)> =
            r.frames.iter().filter_map(|f| f.error.map(|x| (t(f.index), x.0.clamp(0.1, 60.0)))).collect();
        chart
            .draw_series(LineSeries::new(pts, colour.stroke_width(2)))
            .map_err(|x| e(x.to_string()))?
            .label(format!("{} ({} particles)", r.mode, r.particles))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
        let y = 40.0 - 12.0 * ci as f64;
        let lost = r.frames.iter().filter(|f| f.status == "LOST").map(|f| Cross::new((t(f.index), y), 4, colour));
        chart.draw_series(lost).map_err(|x| e(x.to_string()))?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|x| e(x.to_string()))?;
    root.present().map_err(|x| e(x.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(index: usize, status: &str, err: Option<f64>, target: Option<f64>) -> SceneFrame {
        SceneFrame {
            index,
            status: status.into(),
            error: err.map(|e| (e, 1.0)),
            kinematics: Some((0.5, 0.1)),
            visible: [Some(if target.is_some() { 0.0 } else { 1.0 }); 2],
            target,
        }
    }

    #[test]
    fn windows_count_loss_and_time_the_recovery() {
        // 10 fps: 3 frames in view, 4 hidden (LOST from the second), then UNCERTAIN, a 3 mm
        // TRACKING frame, a 1.5 mm one and 0.5 mm ones.
        let mut frames = vec![frame(0, "TRACKING", Some(0.4), None), frame(1, "TRACKING", Some(0.6), None)];
        frames.push(frame(2, "TRACKING", Some(0.5), None));
        frames.push(frame(3, "TRACKING", Some(4.0), Some(1.0)));
        for i in 4..7 {
            frames.push(frame(i, "LOST", None, Some(1.0)));
        }
        frames.push(frame(7, "UNCERTAIN", Some(5.0), None));
        frames.push(frame(8, "TRACKING", Some(3.0), None));
        frames.push(frame(9, "TRACKING", Some(1.5), None));
        frames.push(frame(10, "TRACKING", Some(0.5), None));
        let r = SceneRun {
            condition: "occluder".into(),
            sequence: "s".into(),
            mode: "ours".into(),
            particles: 10,
            fps: 10.0,
            step_ms: 1.0,
            frames,
        };
        let w = summarise_windows(&r);
        assert_eq!(w.len(), 1);
        let w = &w[0];
        assert_eq!((w.start, w.frames, w.lost, w.uncertain), (3, 4, 3, 0));
        assert_eq!(w.first_lost_s, Some(0.1));
        assert_eq!(w.tracking_after_s, Some(0.1));
        assert_eq!(w.recovered_loose_s, Some(0.2));
        assert_eq!(w.recovered_s, Some(0.3));
        assert_eq!(w.visible, [0.0, 0.0]);
        let c = summarise_condition(&r);
        assert_eq!((c.frames, c.lost, c.uncertain), (7, 0, 1));
        assert_eq!(c.position_mm.0, 0.6);
    }

    fn trial(errors: &[Option<f64>], kinematics: f64) -> crate::experiment::Trial {
        crate::experiment::Trial {
            sequence: "s".into(),
            first: 0,
            initial: (0.0, 0.0),
            errors: errors.iter().map(|e| e.map(|x| (x, 0.1))).collect(),
            status: errors.iter().map(|e| if e.is_some() { "TRACKING" } else { "LOST" }.to_string()).collect(),
            converged_at: None,
            step_ms: 1.0,
            kinematics: errors.iter().map(|_| Some((kinematics, 0.2))).collect(),
            reinitialised_at: None,
            reseeded_at: None,
            inlier_share: Vec::new(),
            axis_detected: Vec::new(),
            reseed_share: Vec::new(),
        }
    }

    #[test]
    fn median_per_frame_counts_a_frame_without_pose_as_the_top_of_the_scale() {
        let t = [trial(&[Some(1.0), None], 0.5), trial(&[Some(2.0), None], 0.5), trial(&[Some(3.0), Some(0.01)], 0.5)];
        let m = median_per_frame(&t, 2, |t| &t.errors);
        // Frame 0: 1, 2, 3 -> 2; frame 1: 30 (LOST), 30 (LOST), 0.1 (clamped) -> 30.
        assert_eq!(m, vec![(0.0, 2.0), (1.0, 30.0)]);
        assert_eq!(median_per_frame(&t, 2, |t| &t.kinematics), vec![(0.0, 0.5), (1.0, 0.5)]);
    }

    #[test]
    fn results_are_named_by_mode_and_motion_model_and_old_files_still_read() {
        let old = r#"{"mode":"ours","particles":10,"fps":0.0,"trials":[]}"#;
        let r: ConvergeResults = serde_json::from_str(old).unwrap();
        assert_eq!((r.motion.as_str(), r.label().as_str()), ("", "ours"));
        let named = |mode: &str, motion: &str| {
            ConvergeResults { mode: mode.into(), particles: 1, fps: 0.0, motion: motion.into(), trials: Vec::new() }
                .label()
        };
        assert_eq!(named("ours", "offset"), "ours (offset)");
        assert_eq!(named("ours", "joints"), "ours (random walk)");
        assert_eq!(named("paper", "joints"), "paper");
    }

    #[test]
    fn the_trajectory_plot_has_a_panel_per_level_with_each_mode_and_the_kinematics() {
        let sweep = |mode: &str, motion: &str, err: f64| NoiseSweep {
            pos_mm: 0.0,
            rot_deg: 0.0,
            levels: [1.0, 3.0]
                .iter()
                .map(|&sigma_mrad| NoiseLevel {
                    sigma_mrad,
                    results: ConvergeResults {
                        mode: mode.into(),
                        particles: 1,
                        fps: 0.0,
                        motion: motion.into(),
                        trials: vec![trial(&[Some(err); 3], 2.0), trial(&[Some(err); 3], 2.0)],
                    },
                })
                .collect(),
        };
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.svg");
        plot_noise_frames(&path, &[sweep("ours", "offset", 0.5), sweep("paper", "joints", 8.0)], "title").unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        for text in
            ["σ = 1 mrad per joint", "σ = 3 mrad per joint", "ours (offset) (2 trajectories)", "paper (2 trajectories)"]
        {
            assert!(svg.contains(text), "{text} missing");
        }
        // The legend (first panel only) names the kinematics once.
        assert_eq!(svg.matches("kinematics alone").count(), 1);
        let path = dir.path().join("l.svg");
        plot_noise(&path, &[sweep("ours", "offset", 0.5), sweep("paper", "joints", 8.0)], 5, "title").unwrap();
        let svg = std::fs::read_to_string(&path).unwrap();
        assert!(svg.contains("ours (offset): tracker (2 trials per level)"));
        assert!(svg.contains("paper: tracker (2 trials per level)"));
    }
}
