//! SVG figures of the benchmark, written with plotters (no fonts or system libraries
//! needed: SVG text is rendered by the viewer).

use std::path::Path;

use plotters::prelude::*;

use super::report::{DetectionReport, Timeline};

/// Why a figure could not be written.
#[derive(Debug, thiserror::Error)]
#[error("plot {path}: {message}")]
pub struct PlotError {
    /// File being written.
    pub path: String,
    /// What went wrong.
    pub message: String,
}

/// Draws the series legend of `chart` (white box, black border) or returns the error for `path`.
macro_rules! legend {
    ($chart:expr, $path:expr) => {
        $chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| err($path, e))?
    };
}

/// A chart on `area` with the figures' common caption font, margin and label areas.
fn chart_on<'a, 'b, DB: DrawingBackend>(
    area: &'a DrawingArea<DB, plotters::coord::Shift>,
    caption: &str,
) -> ChartBuilder<'a, 'b, DB> {
    let mut b = ChartBuilder::on(area);
    b.caption(caption, ("sans-serif", 18)).margin(10).x_label_area_size(35).y_label_area_size(60);
    b
}

fn err(path: &Path, e: impl std::fmt::Display) -> PlotError {
    PlotError { path: path.display().to_string(), message: e.to_string() }
}

/// Histogram of `values` (same unit as `range`) with `bins` bins, as (bin start, fraction).
fn histogram(values: &[f64], range: (f64, f64), bins: usize) -> Vec<(f64, f64)> {
    let w = (range.1 - range.0) / bins as f64;
    let mut h = vec![0usize; bins];
    for v in values {
        let i = (((v - range.0) / w).floor().max(0.0) as usize).min(bins - 1);
        h[i] += 1;
    }
    let n = values.len().max(1) as f64;
    h.iter().enumerate().map(|(i, c)| (range.0 + i as f64 * w, *c as f64 / n)).collect()
}

/// Delay histograms (insertion and extraction) of the paper mode and the fast mode with the
/// paper's information, seconds.
pub fn delay_histograms(report: &DetectionReport, path: &Path) -> Result<(), PlotError> {
    let root = SVGBackend::new(path, (1000, 420)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(path, e))?;
    let panels = root.split_evenly((1, 2));
    let pick = |key: &str| report.settings.iter().find(|s| s.setting.key == key);
    let (Some(paper), Some(fast)) = (pick("paper"), pick("fast")) else {
        return Err(err(path, "paper or fast setting missing"));
    };
    let (bi, be, _, _) = report.bound_stats();
    let data = [
        ("insertion delay (s)", paper.insertion_delays(), fast.insertion_delays(), (0.0, 4.0), bi.mean),
        ("extraction delay (s)", paper.extraction_delays(), fast.extraction_delays(), (0.0, 3.0), be.mean),
    ];
    for (panel, (title, p, f, range, bound)) in panels.iter().zip(data) {
        let bins = 40;
        let hp = histogram(&p, range, bins);
        let hf = histogram(&f, range, bins);
        let ymax = hp.iter().chain(&hf).map(|x| x.1).fold(0.0, f64::max) * 1.1 + 1e-9;
        let mut chart =
            chart_on(panel, title).build_cartesian_2d(range.0..range.1, 0.0..ymax).map_err(|e| err(path, e))?;
        chart
            .configure_mesh()
            .x_desc("seconds after the true event")
            .y_desc("fraction of events")
            .draw()
            .map_err(|e| err(path, e))?;
        let w = (range.1 - range.0) / bins as f64;
        for (h, color, label) in [(&hp, RED.mix(0.45), "paper"), (&hf, BLUE.mix(0.45), "fast (paper's information)")] {
            chart
                .draw_series(h.iter().map(|(x, y)| Rectangle::new([(*x, 0.0), (*x + w, *y)], color.filled())))
                .map_err(|e| err(path, e))?
                .label(label)
                .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 12, y + 5)], color.filled()));
        }
        chart
            .draw_series(LineSeries::new([(bound, 0.0), (bound, ymax)], BLACK.stroke_width(2)))
            .map_err(|e| err(path, e))?
            .label("mean motion-only bound")
            .legend(|(x, y)| PathElement::new([(x, y), (x + 12, y)], BLACK.stroke_width(2)));
        legend!(chart, path);
    }
    root.present().map_err(|e| err(path, e))
}

/// Timeline of the first trace: true and detected state (top), localisation error (bottom).
pub fn timeline(t: &Timeline, path: &Path) -> Result<(), PlotError> {
    let root = SVGBackend::new(path, (1200, 560)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(path, e))?;
    let (top, bottom) = root.split_vertically(300);
    let t_end = t.t_s.last().copied().unwrap_or(1.0);
    let mut chart = chart_on(&top, "true vs detected state (first trace)")
        .build_cartesian_2d(0.0..t_end, -0.5..5.5)
        .map_err(|e| err(path, e))?;
    chart
        .configure_mesh()
        .y_desc("state")
        .y_label_formatter(&|y: &f64| match y.round() as i64 {
            0 => "outside".into(),
            k @ 1..=4 => format!("trocar {k}"),
            _ => String::new(),
        })
        .draw()
        .map_err(|e| err(path, e))?;
    chart
        .draw_series(LineSeries::new(t.t_s.iter().zip(&t.truth).map(|(x, y)| (*x, *y as f64)), BLACK.stroke_width(2)))
        .map_err(|e| err(path, e))?
        .label("truth (trocar index)")
        .legend(|(x, y)| PathElement::new([(x, y), (x + 12, y)], BLACK.stroke_width(2)));
    let styles = [("paper", RED, 0.25), ("fast", BLUE, 0.1)];
    for (key, color, offset) in styles {
        if let Some((_, inside, _)) = t.detected.iter().find(|d| d.0 == key) {
            // Detected "inside" drawn at the true trocar's level when inside, shifted for legibility.
            let pts = t.t_s.iter().zip(inside).zip(&t.truth).map(|((x, i), tr)| {
                let level = match (*i, *tr) {
                    (0, _) => 0.0,
                    (_, 0) => 5.0,
                    (_, k) => f64::from(k),
                };
                (*x, level - offset)
            });
            chart
                .draw_series(LineSeries::new(pts, color.stroke_width(1)))
                .map_err(|e| err(path, e))?
                .label(format!("{key} detector (inside at the true level; 5 = inside while truly outside)"))
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 12, y)], color.stroke_width(1)));
        }
    }
    legend!(chart, path);

    let mut chart = chart_on(&bottom, "localisation error while both inside")
        .build_cartesian_2d(0.0..t_end, (0.1f64..100.0).log_scale())
        .map_err(|e| err(path, e))?;
    chart.configure_mesh().x_desc("time (s)").y_desc("error (mm)").draw().map_err(|e| err(path, e))?;
    for (key, color, _) in styles {
        if let Some((_, _, errs)) = t.detected.iter().find(|d| d.0 == key) {
            let pts: Vec<(f64, f64)> =
                t.t_s.iter().zip(errs).filter_map(|(x, e)| e.map(|e| (*x, (e * 1e3).clamp(0.1, 100.0)))).collect();
            chart
                .draw_series(pts.iter().map(|p| Circle::new(*p, 1, color.filled())))
                .map_err(|e| err(path, e))?
                .label(key)
                .legend(move |(x, y)| Circle::new((x + 6, y), 3, color.filled()));
        }
    }
    legend!(chart, path);
    root.present().map_err(|e| err(path, e))
}

/// A latency/duration histogram from (bucket start, count) pairs, in microseconds, log
/// counts. `series`: (label, buckets).
pub fn duration_histogram(
    title: &str,
    x_desc: &str,
    series: &[(&str, Vec<(f64, u64)>)],
    x_max: f64,
    path: &Path,
) -> Result<(), PlotError> {
    let root = SVGBackend::new(path, (900, 420)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(path, e))?;
    let ymax = series.iter().flat_map(|s| s.1.iter().map(|b| b.1)).max().unwrap_or(1).max(1) as f64 * 2.0;
    let mut chart =
        chart_on(&root, title).build_cartesian_2d(0.0..x_max, (0.5f64..ymax).log_scale()).map_err(|e| err(path, e))?;
    chart.configure_mesh().x_desc(x_desc).y_desc("count").draw().map_err(|e| err(path, e))?;
    let colors = [BLUE, RED, GREEN, MAGENTA];
    for ((label, buckets), color) in series.iter().zip(colors) {
        let pts: Vec<(f64, f64)> = buckets.iter().filter(|b| b.0 <= x_max).map(|b| (b.0, b.1 as f64)).collect();
        chart
            .draw_series(LineSeries::new(pts, color.stroke_width(1)))
            .map_err(|e| err(path, e))?
            .label(*label)
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 12, y)], color.stroke_width(2)));
    }
    legend!(chart, path);
    root.present().map_err(|e| err(path, e))
}
