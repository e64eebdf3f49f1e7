//! Not a test: measures our detector on frames of `simrobot render` converted to raw RGB
//! with a truth list (`OURS_EVAL_DIR/list.txt`: per line the `.rgb` file, then per instrument
//! `label a b c x0 y0 x1 y1`, the true axis and its visible segment, undistorted pixels).
//! `OURS_EVAL_DIR=DIR cargo test --release -p vision --test ours_eval -- --ignored --nocapture`
//!
//! Files ending in `.png` are decoded (so `simrobot generate --frames` runs are scored in
//! place); `OURS_EVAL_LIST` names the list file instead of `DIR/list.txt`, and
//! `OURS_EVAL_MIN_VIS` the visible length (undistorted pixels, default 100) from which a shaft
//! counts as eligible. A frame whose list line has no instrument counts towards the false
//! detections (any detection there is unmatched).
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::time::Instant;
use vision::ours::{OursConfig, OursDetector};
use vision::{RgbView, ShaftDetector};

#[test]
#[ignore = "measurement on rendered frames (needs OURS_EVAL_DIR)"]
fn evaluate_on_rendered_frames() {
    // Run on purpose (`--ignored`) without frames: say so instead of passing silently.
    let dir = std::env::var_os("OURS_EVAL_DIR")
        .expect("set OURS_EVAL_DIR to a directory of rendered frames (docs/shaft-detector-ours.md)");
    let dir = std::path::PathBuf::from(dir);
    let k = vision::synth::endoscope_camera();
    let mut cfg = OursConfig::default();
    let env = |name: &str| std::env::var(name).ok().and_then(|v| v.parse::<f64>().ok());
    if let Some(v) = env("OURS_EDGE_T") {
        cfg.edge_threshold = v;
    }
    if let Some(v) = env("OURS_MIN_LEN") {
        cfg.min_length_px = v;
    }
    if let Some(v) = env("OURS_LUMA_W") {
        cfg.luma_weight = v;
    }
    if let Some(v) = env("OURS_LONG_SPAN") {
        cfg.long_span_px = v;
    }
    if let Some(v) = env("OURS_MIN_LC") {
        cfg.min_luma_contrast = v;
    }
    if let Some(v) = env("OURS_MIN_CC") {
        cfg.min_chroma_contrast = v;
    }
    if let Some(v) = env("OURS_CC_RATIO") {
        cfg.max_interior_chroma_ratio = v;
    }
    if let Some(v) = env("OURS_BORDER") {
        cfg.border_margin_px = v;
    }
    if let Some(v) = env("OURS_MIN_SUPPORT") {
        cfg.min_support = v;
    }
    if let Some(v) = env("OURS_MAX_DEPTH") {
        cfg.max_depth_m = v;
    }
    if let Some(v) = env("OURS_PLUMA_W") {
        cfg.profile_luma_weight = v;
    }
    let mut det = OursDetector::new(k, cfg).unwrap();
    let list_path = std::env::var_os("OURS_EVAL_LIST").map_or_else(|| dir.join("list.txt"), std::path::PathBuf::from);
    let list = std::fs::read_to_string(list_path).unwrap();
    let min_vis = env("OURS_EVAL_MIN_VIS").unwrap_or(100.0);
    let mut empty_frames_with_det = 0;
    let (mut angles, mut offsets, mut times) = (Vec::new(), Vec::new(), Vec::new());
    let (mut eligible, mut found, mut false_det, mut frames) = (0, 0, 0, 0);
    let verbose = std::env::var_os("OURS_EVAL_VERBOSE").is_some();
    for line in list.lines() {
        let mut it = line.split_whitespace();
        let file = it.next().unwrap();
        if std::env::var("OURS_EVAL_ONLY").is_ok_and(|only| only != file) {
            continue;
        }
        let nums: Vec<f64> = it.map(|s| s.parse().unwrap()).collect();
        let bytes = if file.ends_with(".png") {
            image::open(dir.join(file)).unwrap().to_rgb8().into_raw()
        } else {
            std::fs::read(dir.join(file)).unwrap()
        };
        let view = RgbView::new(640, 480, &bytes).unwrap();
        let t0 = Instant::now();
        let dets = det.detect(&view).unwrap();
        times.push(t0.elapsed().as_secs_f64() * 1e3);
        frames += 1;
        let mut matched = vec![false; dets.len()];
        for tr in nums.chunks(8) {
            let [label, a, b, _c, x0, y0, x1, y1] = tr.try_into().unwrap();
            let len = (x1 - x0).hypot(y1 - y0);
            let (mx, my) = (0.5 * (x0 + x1), 0.5 * (y0 + y1));
            // The detection nearest this axis.
            let mut best: Option<(usize, f64, f64)> = None;
            for (i, d) in dets.iter().enumerate() {
                let l = d.centreline.abc;
                let ang = (l[0] * b - l[1] * a).abs().min(1.0).asin().to_degrees();
                let off = d.centreline.distance_px(mx, my).abs();
                if ang < 3.0 && off < 10.0 && best.is_none_or(|bb| off < bb.2) {
                    best = Some((i, ang, off));
                }
            }
            if let Some((i, _, _)) = best {
                matched[i] = true;
                if std::env::var_os("OURS_EVAL_CONF").is_some() {
                    println!("matched conf {:.3}", dets[i].confidence);
                }
            }
            if len >= min_vis {
                eligible += 1;
                if let Some((_, ang, off)) = best {
                    found += 1;
                    angles.push(ang);
                    offsets.push(off);
                    if verbose {
                        println!("{file} label {label} len {len:.0}: angle {ang:.4} offset {off:.3}");
                    }
                } else if verbose {
                    println!("{file} label {label} len {len:.0}: MISSED ({} detections)", dets.len());
                }
            }
        }
        let extra = matched.iter().filter(|m| !**m).count();
        if extra > 0 && verbose {
            for (d, m) in dets.iter().zip(&matched) {
                if !m {
                    println!("{file}: unmatched detection ends {:?} conf {:.2}", d.ends_px, d.confidence);
                }
            }
        }
        false_det += extra;
        if nums.is_empty() && !dets.is_empty() {
            empty_frames_with_det += 1;
        }
    }
    let med = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        if v.is_empty() { f64::NAN } else { v[v.len() / 2] }
    };
    let p90 = |v: &Vec<f64>| if v.is_empty() { f64::NAN } else { v[(v.len() * 9) / 10] };
    let (ma, mo, mt) = (med(&mut angles), med(&mut offsets), med(&mut times));
    println!(
        "frames {frames}: detected {found}/{eligible} eligible shafts ({:.1} %), median angle {ma:.4}° (p90 {:.4}), median offset {mo:.3} px (p90 {:.3}), unmatched detections {false_det} (frames without instrument but with a detection: {empty_frames_with_det}), median time {mt:.2} ms (max {:.2})",
        100.0 * found as f64 / eligible.max(1) as f64,
        p90(&angles),
        p90(&offsets),
        times.last().copied().unwrap_or(f64::NAN)
    );
}
