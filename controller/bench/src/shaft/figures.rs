//! The shaft benchmark's figures: overlay PNGs (the true axis and every detector's
//! centrelines drawn on a rendered frame) and the SVG of the error distributions.

use std::path::Path;

use estimator::calib::Intrinsics;
use nalgebra::Vector3;
use plotters::prelude::*;
use sim::endoscope::EyeImage;

use crate::plots::PlotError;

/// Colour of the true axis in the overlays (green).
pub const TRUTH_RGB: [u8; 3] = [40, 230, 40];

/// Colours of the detectors in the overlays and the plot, in the report's order: red,
/// yellow, magenta, cyan, then white.
pub const DETECTOR_RGB: [[u8; 3]; 5] = [[255, 40, 40], [255, 220, 0], [255, 0, 255], [0, 230, 255], [255, 255, 255]];

/// The same hues, darker, for the SVG on white: red, ochre, magenta, teal, then grey.
pub const PLOT_RGB: [[u8; 3]; 5] = [[220, 20, 20], [190, 140, 0], [190, 0, 190], [0, 140, 190], [90, 90, 90]];

/// Sets the pixels within `half` px of `(x, y)` (a square brush) to `c`.
fn dot(img: &mut EyeImage, x: f64, y: f64, half: i64, c: [u8; 3]) {
    let (w, h) = (i64::from(img.width), i64::from(img.height));
    let (xi, yi) = (x.round() as i64, y.round() as i64);
    for dy in -half..=half {
        for dx in -half..=half {
            let (px, py) = (xi + dx, yi + dy);
            if px >= 0 && py >= 0 && px < w && py < h {
                let i = 3 * (py * w + px) as usize;
                img.rgb[i..i + 3].copy_from_slice(&c);
            }
        }
    }
}

/// Draws a polyline of measured (distorted) pixels.
pub fn draw_polyline(img: &mut EyeImage, pts: &[[f64; 2]], half: i64, c: [u8; 3]) {
    for pair in pts.windows(2) {
        let (a, b) = (pair[0], pair[1]);
        let n = ((b[0] - a[0]).hypot(b[1] - a[1]).ceil() as usize).clamp(1, 100_000);
        for k in 0..=n {
            let t = k as f64 / n as f64;
            dot(img, a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, half, c);
        }
    }
}

/// Length of one dash of the overlays' dashed lines, pixels along the line.
pub const DASH_PX: f64 = 6.0;

/// Draws the line `abc` (undistorted pixels) where it falls in the image, through the lens
/// distortion of `k` (so a straight line in undistorted pixels may be drawn curved). Dashed
/// as dash `index` of every `of` (dashes of [`DASH_PX`], counted from the foot of the
/// principal point): the lines of `of` detectors on the same place all show, alternating.
pub fn draw_ideal_line(
    img: &mut EyeImage,
    k: &Intrinsics,
    abc: &[f64; 3],
    half: i64,
    c: [u8; 3],
    index: usize,
    of: usize,
) {
    let n = abc[0].hypot(abc[1]);
    if !(n > 1e-12 && abc.iter().all(|v| v.is_finite())) {
        return;
    }
    let [a, b, cc] = abc.map(|v| v / n);
    // The foot of the principal point, and the direction along the line.
    let d0 = a * k.cx + b * k.cy + cc;
    let (u0, v0) = (k.cx - a * d0, k.cy - b * d0);
    let (tu, tv) = (-b, a);
    let k_inv = k.k_inv();
    // The undistorted image reaches a little past the image (barrel distortion).
    let reach = 1.3 * f64::from(k.width).hypot(f64::from(k.height));
    let steps = (4.0 * reach) as i64;
    for i in -steps..=steps {
        let s = i as f64 * 0.5;
        if (s / DASH_PX).floor().rem_euclid(of.max(1) as f64) as usize != index {
            continue;
        }
        let (u, v) = (u0 + s * tu, v0 + s * tv);
        let ray = k_inv * Vector3::new(u, v, 1.0);
        // Far outside the image the distortion polynomial folds back: keep to rays within
        // the field of view.
        if ray.x.abs() > 1.5 || ray.y.abs() > 1.5 {
            continue;
        }
        let px = k.project(&ray);
        if k.in_image(&px) {
            dot(img, px.x, px.y, half, c);
        }
    }
}

/// One series of a CDF panel: label, colour, values.
pub type Series = (String, [u8; 3], Vec<f64>);

/// One CDF panel: title, x-axis description, largest x, the series.
pub type Panel<'a> = (&'a str, &'a str, f64, Vec<Series>);

/// An empirical cumulative distribution per series, `x` from 0 to `x_max`: fraction of
/// values ≤ x; one panel beside the other.
pub fn cdf_panels(panels: &[Panel<'_>], path: &Path) -> Result<(), PlotError> {
    let err = |e: &dyn std::fmt::Display| PlotError { path: path.display().to_string(), message: e.to_string() };
    let root = SVGBackend::new(path, (1100, 440)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| err(&e))?;
    let areas = root.split_evenly((1, panels.len().max(1)));
    for (area, (title, x_desc, x_max, series)) in areas.iter().zip(panels) {
        let mut chart = ChartBuilder::on(area)
            .caption(*title, ("sans-serif", 18))
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(50)
            .build_cartesian_2d(0.0..*x_max, 0.0..1.0)
            .map_err(|e| err(&e))?;
        chart.configure_mesh().x_desc(*x_desc).y_desc("fraction of matched frames ≤ x").draw().map_err(|e| err(&e))?;
        for (label, rgb, values) in series {
            let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
            if v.is_empty() {
                continue;
            }
            v.sort_by(f64::total_cmp);
            let n = v.len() as f64;
            let mut pts = vec![(0.0, 0.0)];
            for (i, x) in v.iter().enumerate() {
                let x = x.min(*x_max);
                pts.push((x, i as f64 / n));
                pts.push((x, (i + 1) as f64 / n));
            }
            pts.push((*x_max, 1.0));
            let colour = RGBColor(rgb[0], rgb[1], rgb[2]);
            chart
                .draw_series(LineSeries::new(pts, colour.stroke_width(2)))
                .map_err(|e| err(&e))?
                .label(format!("{label} ({})", v.len()))
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 14, y)], colour.stroke_width(2)));
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| err(&e))?;
    }
    root.present().map_err(|e| err(&e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_ideal_line_is_drawn_where_it_crosses_the_image() {
        let k = Intrinsics {
            fx: 400.0,
            fy: 400.0,
            cx: 319.5,
            cy: 239.5,
            skew: 0.0,
            width: 640,
            height: 480,
            distortion: [0.0; 5],
        };
        let mut img = EyeImage { width: 640, height: 480, rgb: vec![0; 640 * 480 * 3], labels: vec![0; 640 * 480] };
        // v = 100.
        draw_ideal_line(&mut img, &k, &[0.0, 2.0, -200.0], 0, [9, 9, 9], 0, 1);
        for x in [0usize, 320, 639] {
            assert_eq!(img.rgb[3 * (100 * 640 + x)], 9, "{x}");
            assert_eq!(img.rgb[3 * (101 * 640 + x)], 0, "{x}");
        }
        // Not a line: nothing drawn.
        let before = img.rgb.clone();
        draw_ideal_line(&mut img, &k, &[0.0, 0.0, 1.0], 0, [200, 9, 9], 0, 1);
        assert_eq!(before, img.rgb);
        // Dash 1 of 2: the second 6 px of every 12 from the foot (u = 319.5) along the line's
        // direction (−b, a) = (−1, 0): pixel 316 (3.5 px along) stays, 310 (9.5 px) is drawn.
        draw_ideal_line(&mut img, &k, &[0.0, 1.0, -200.0], 0, [7, 7, 7], 1, 2);
        assert_eq!(img.rgb[3 * (200 * 640 + 316)], 0);
        assert_eq!(img.rgb[3 * (200 * 640 + 310)], 7);
    }
}
