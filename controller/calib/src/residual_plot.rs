//! The residual figure of `comanip-calib calibrate --plot`: where each observed tool line
//! lies in the image, coloured by its distance to the tool axis the calibration predicts, and
//! the distribution of those distances per pipeline. Lines a detector got wrong (another
//! instrument's edge, a reflection) stand out in red; a wrong model (hand-eye, intrinsics)
//! shows as residuals that grow toward one part of the image.

use std::path::{Path, PathBuf};

use estimator::calib::Intrinsics;
use nalgebra::Vector2;
use plotters::prelude::*;

/// One pipeline's residuals.
#[derive(Clone, Debug)]
pub struct PipelineResiduals {
    /// `"paper"` / `"ours"`.
    pub name: &'static str,
    /// Per observation, in dataset order: the larger distance of its two line points to the
    /// predicted tool axis, pixels (ideal, undistorted).
    pub residuals_px: Vec<f64>,
}

/// Why the figure could not be written.
#[derive(Debug, thiserror::Error)]
#[error("cannot write the residual plot {path}: {message}")]
pub struct ResidualPlotError {
    /// The file.
    pub path: PathBuf,
    /// What went wrong.
    pub message: String,
}

/// The robust scale of residuals (pixels): 1.4826 × their median, so that it is the standard
/// deviation for Gaussian residuals whatever the outliers; at least 1e-9.
pub fn robust_scale(residuals_px: &[f64]) -> f64 {
    let mut v: Vec<f64> = residuals_px.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return 1e-9;
    }
    v.sort_unstable_by(f64::total_cmp);
    (1.4826 * v[v.len() / 2]).max(1e-9)
}

/// The classes of the image panel, in units of the robust scale: (upper limit, label, colour,
/// stroke width).
const CLASSES: [(f64, &str, RGBColor, u32); 3] = [
    (3.0, "≤ 3 robust SD", RGBColor(70, 110, 170), 1),
    (6.0, "3-6 robust SD", RGBColor(235, 140, 20), 2),
    (f64::INFINITY, "> 6 robust SD (outlier?)", RGBColor(210, 30, 30), 2),
];

/// Which class of the image panel a residual (pixels) falls in, given the robust scale
/// `scale_px`: 0 up to 3 robust SD, 1 from 3 to 6, 2 beyond.
pub fn residual_class(residual_px: f64, scale_px: f64) -> usize {
    let z = residual_px / scale_px;
    CLASSES.iter().position(|c| z <= c.0).unwrap_or(CLASSES.len() - 1)
}

/// Draws the series legend of a chart (white box, black border), or returns the error.
macro_rules! legend {
    ($chart:expr, $err:expr) => {
        $chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()
            .map_err(|e| $err(&e))?
    };
}

/// Root mean square of residuals (pixels); 0 for none.
fn rms(residuals_px: &[f64]) -> f64 {
    (residuals_px.iter().map(|r| r * r).sum::<f64>() / residuals_px.len().max(1) as f64).sqrt()
}

/// Writes the figure (SVG) for the observed lines `lines_px` (ideal pixels, dataset order)
/// and the pipelines' residuals; the image panel shows the last pipeline's.
pub fn residual_figure(
    path: &Path,
    intrinsics: &Intrinsics,
    lines_px: &[[Vector2<f64>; 2]],
    pipelines: &[PipelineResiduals],
) -> Result<(), ResidualPlotError> {
    let err = |e: &dyn std::fmt::Display| ResidualPlotError { path: path.to_owned(), message: e.to_string() };
    let Some(shown) = pipelines.last() else { return Err(err(&"no pipeline to plot")) };
    if shown.residuals_px.len() != lines_px.len() {
        return Err(err(&format!("{} residuals for {} lines", shown.residuals_px.len(), lines_px.len())));
    }
    let (w, h) = (f64::from(intrinsics.width), f64::from(intrinsics.height));
    let root = SVGBackend::new(path, (1300, 560)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let (left, right) = root.split_horizontally(700);

    // Image panel: v grows downward, as in the image.
    let scale = robust_scale(&shown.residuals_px);
    let shown_rms = rms(&shown.residuals_px);
    let mut chart = ChartBuilder::on(&left)
        .caption(
            format!("{}: observed lines by residual (robust SD {scale:.2} px, RMS {shown_rms:.2} px)", shown.name),
            ("sans-serif", 16),
        )
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(50)
        .build_cartesian_2d(0.0..w, h..0.0)
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .disable_x_mesh()
        .disable_y_mesh()
        .x_desc("u (px)")
        .y_desc("v (px)")
        .draw()
        .map_err(|e| err(&e))?;
    chart
        .draw_series(std::iter::once(Rectangle::new([(0.0, 0.0), (w, h)], BLACK.stroke_width(1))))
        .map_err(|e| err(&e))?;
    // Draw the classes in order, so that the outliers lie on top.
    for (k, (_, label, color, width)) in CLASSES.iter().enumerate() {
        let members: Vec<&[Vector2<f64>; 2]> = lines_px
            .iter()
            .zip(&shown.residuals_px)
            .filter(|(_, r)| residual_class(**r, scale) == k)
            .map(|(l, _)| l)
            .collect();
        let style = color.stroke_width(*width);
        chart
            .draw_series(members.iter().map(|l| PathElement::new(vec![(l[0].x, l[0].y), (l[1].x, l[1].y)], style)))
            .map_err(|e| err(&e))?
            .label(format!("{label}: {}", members.len()))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 14, y)], style));
    }
    legend!(chart, err);

    // Histogram panel: every pipeline, residuals beyond the axis counted in its last bin.
    let all: Vec<f64> =
        pipelines.iter().flat_map(|p| p.residuals_px.iter().copied()).filter(|r| r.is_finite()).collect();
    let x_max = {
        let mut v = all.clone();
        v.sort_unstable_by(f64::total_cmp);
        let p99 = v.get((v.len() * 99) / 100).copied().unwrap_or(1.0);
        (1.2 * p99).max(12.0 * scale).max(1e-6)
    };
    const BINS: usize = 40;
    let bin = x_max / BINS as f64;
    let counts = |p: &PipelineResiduals| -> Vec<u32> {
        let mut c = vec![0u32; BINS];
        for r in p.residuals_px.iter().filter(|r| r.is_finite()) {
            c[((r / bin) as usize).min(BINS - 1)] += 1;
        }
        c
    };
    let y_max = pipelines.iter().flat_map(&counts).max().unwrap_or(1).max(1) as f64 * 2.0;
    let mut chart = ChartBuilder::on(&right)
        .caption("per-observation residual (larger of the two line points)", ("sans-serif", 16))
        .margin(10)
        .x_label_area_size(35)
        .y_label_area_size(50)
        .build_cartesian_2d(0.0..x_max, (0.5f64..y_max).log_scale())
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .x_desc(format!("residual (px; the last bin holds everything beyond {x_max:.1})"))
        .y_desc("observations")
        .draw()
        .map_err(|e| err(&e))?;
    let colors = [RGBColor(120, 120, 120), RGBColor(40, 90, 200)];
    for (p, color) in pipelines.iter().zip(colors.iter().cycle().skip(2 - pipelines.len().min(2))) {
        let c = counts(p);
        // A step outline: (left edge, count), (right edge, count) per bin; empty bins at 0.5.
        let pts: Vec<(f64, f64)> = c
            .iter()
            .enumerate()
            .flat_map(|(i, n)| {
                let y = f64::from(*n).max(0.5);
                [(i as f64 * bin, y), ((i + 1) as f64 * bin, y)]
            })
            .collect();
        let style = color.stroke_width(2);
        let p_rms = rms(&p.residuals_px);
        chart
            .draw_series(LineSeries::new(pts, style))
            .map_err(|e| err(&e))?
            .label(format!("{} (RMS {p_rms:.2} px)", p.name))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 14, y)], style));
    }
    legend!(chart, err);
    root.present().map_err(|e| err(&e))
}
