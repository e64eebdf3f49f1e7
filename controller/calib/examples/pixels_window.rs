//! Diagnostic of our detector's Hough normal window on the calibration-from-pixels grid
//! (`comanip-calib pixels`): the grid rendered once, the lines detected by ours with two
//! settings (A: the default, B: `hough_normal_window_deg` set), every frame where the two
//! differ printed against the render's truth, and our pipeline run on A's lines, on B's, and
//! on A's with B's lines swapped in for chosen frames (to find which lines move the
//! calibration's selection stage).
//!
//! `cargo run --release -p comanip-calib --example pixels_window -- [n_e] [n_t] [sigma_mm] [seed]`
//! (default 3 3 0.01 1, the pixels command's `--n-e 3 --n-t 3 --sigma 0.01 --units mm`).
//! Environment: `OURS_A` and `OURS_B` the two detector configurations as JSON (`OursConfig`'s
//! fields; default `{}` and `{"hough_normal_window_deg":5}`); `SWAP=i,j,...` swaps B's lines
//! into A's at those differing frames' indices (as printed) and solves; `SWAP=each` solves
//! once per differing frame (A with that frame's B line); `DROP=each` solves B with A's line
//! in each differing frame in turn; `EXPERIMENTS=1` solves A and B without their wrong lines
//! (more than `BAD_DEG`, default 1°, off the truth axis, or on an eye without a truth line), A
//! with B's wrong lines where A's are not, and B with A's lines where B's are wrong;
//! `TSV=FILE` writes one row per eye (truth ends; per detector its ends, angle and offset
//! errors, widths and axis depths at its ends, confidence, and the returned pair's support,
//! residual scale, contrast, length and width); `PNG_DIR=DIR` with `PNG_FRAMES=pose:eye,...`
//! draws both detectors' overlays of those frames; `QUIET=1` leaves out the per-frame listing.
//! Session 23's use: docs/detection.md, eleventh round.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "diagnostic tool: a panic is a bug report")]

use std::sync::{Arc, Mutex};

use comanip_calib::pixels::{LineSource, PixelProtocol, PixelRun, line_error, observations, render_and_detect};
use estimator::calib::ours::{OursConfig as CalibConfig, solve_ours};
use estimator::calib::pose_errors;
use vision::ours::{OursConfig, OursDetector};
use vision::{RgbView, ShaftDetection, ShaftDetector};

type Log = Arc<Mutex<Vec<Vec<ShaftDetection>>>>;
/// Per call, the returned best pair's verification figures.
type VLog = Arc<Mutex<Vec<Option<vision::ours::TraceVerified>>>>;

/// Ours, every call's detections recorded.
struct Recording {
    inner: OursDetector,
    log: Log,
    vlog: VLog,
    /// `PNG_DIR` and the calls (`2·pose + eye`) of `PNG_FRAMES` (`pose:eye,...`) to draw.
    png: Option<(std::path::PathBuf, Vec<usize>, &'static str)>,
}

impl ShaftDetector for Recording {
    fn name(&self) -> &'static str {
        "ours"
    }
    fn intrinsics(&self) -> &estimator::calib::Intrinsics {
        self.inner.intrinsics()
    }
    fn detect(&mut self, image: &RgbView<'_>) -> Result<Vec<ShaftDetection>, vision::DetectError> {
        let (r, tr) = self.inner.detect_traced(image)?;
        let v = tr.pairs.iter().find(|p| p.outcome == vision::ours::PairOutcome::Returned(0)).and_then(|p| p.verified);
        self.vlog.lock().unwrap().push(v);
        let mut log = self.log.lock().unwrap();
        if let Some((dir, calls, tag)) = &self.png
            && calls.contains(&log.len())
        {
            let (w, h) = (image.width(), image.height());
            let mut rgb = image.data().to_vec();
            comanip_calib::detect::draw_overlay(&mut rgb, w, h, self.inner.intrinsics(), &r);
            let n = log.len();
            let path = dir.join(format!("pose{}_eye{}_{tag}.png", n / 2, n % 2));
            hw_io::camera::png::write_rgb_png(&path, w, h, &rgb).unwrap();
            if *tag == "A" {
                let path = dir.join(format!("pose{}_eye{}_raw.png", n / 2, n % 2));
                hw_io::camera::png::write_rgb_png(&path, w, h, image.data()).unwrap();
            }
        }
        log.push(r.clone());
        Ok(r)
    }
}

/// The cylinder of a detection's two contours (radius 4 mm): at each end of its span
/// (undistorted), the width between the contours (px) and the axis's depth (m).
fn geometry(d: &ShaftDetection, k: &estimator::calib::Intrinsics) -> [f64; 4] {
    use nalgebra::{Vector2, Vector3};
    let ends = d.ends_px.map(|e| k.undistort_px(&Vector2::new(e[0], e[1])));
    let mid = (ends[0] + ends[1]) * 0.5;
    let kt = k.k().transpose();
    let plane = |l: &vision::shaft::ImageLine| {
        let s = if l.distance_px(mid.x, mid.y) >= 0.0 { 1.0 } else { -1.0 };
        (kt * Vector3::new(s * l.abc[0], s * l.abc[1], s * l.abc[2])).normalize()
    };
    let (na, nb) = (plane(&d.contours[0]), plane(&d.contours[1]));
    let half = (0.5 * (1.0 + na.dot(&nb))).max(0.0).sqrt();
    let dist = 0.004 / half;
    let dir = na.cross(&nb).normalize();
    let p0 = (na + nb).normalize() * dist;
    let depth = |px: &Vector2<f64>| {
        let r = k.k_inv() * Vector3::new(px.x, px.y, 1.0);
        let (rr, rd, rp, dp) = (r.dot(&r), r.dot(&dir), r.dot(&p0), dir.dot(&p0));
        let lam = (rd * rp - rr * dp) / (rr - rd * rd);
        (p0 + dir * lam).z
    };
    let width =
        |px: &Vector2<f64>| d.contours[0].distance_px(px.x, px.y).abs() + d.contours[1].distance_px(px.x, px.y).abs();
    [width(&ends[0]), width(&ends[1]), depth(&ends[0]), depth(&ends[1])]
}

fn cfg(var: &str, default: &str) -> OursConfig {
    let s = std::env::var(var).unwrap_or_else(|_| default.to_string());
    serde_json::from_str(&s).expect("OursConfig JSON")
}

fn solve(run: &PixelRun, source: LineSource, label: &str) {
    for (both, eyes) in [(false, "left"), (true, "both")] {
        let obs = observations(run, source, both);
        let c = CalibConfig {
            noise: run.noise_of(source),
            estimate_noise_scale: run.estimate_noise_scale,
            ..CalibConfig::default()
        };
        match solve_ours(&run.setup, &obs, &c) {
            Ok(r) => {
                let e = pose_errors(&r.pose, &run.truth);
                let stat = r
                    .selection
                    .as_ref()
                    .and_then(|s| s.move_statistic)
                    .map(|(st, lim)| format!("move {st:.1} (limit {lim:.1})"))
                    .unwrap_or_default();
                let refused = r.selection_refused.as_ref().map(|w| format!(" REFUSED: {w}")).unwrap_or_default();
                println!(
                    "{label} {eyes:4} n={} {:.3} mm / {:.4} deg {stat}{refused}",
                    obs.len(),
                    e.translation_m * 1e3,
                    e.rotation_rad.to_degrees()
                );
            }
            Err(e) => println!("{label} {eyes:4} n={} failed: {e}", obs.len()),
        }
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let n_e = args.get(1).map_or(3, |s| s.parse().unwrap());
    let n_t = args.get(2).map_or(3, |s| s.parse().unwrap());
    let sigma = args.get(3).map_or(0.01, |s| s.parse().unwrap());
    let seed = args.get(4).map_or(1, |s| s.parse().unwrap());
    let p = PixelProtocol { n_e, n_t, sigma, seed, ..PixelProtocol::default() };
    let k = p.endoscope.camera.intrinsics;
    let (ca, cb) = (cfg("OURS_A", "{}"), cfg("OURS_B", r#"{"hough_normal_window_deg":5}"#));
    let (la, lb): (Log, Log) = Default::default();
    let (va, vb): (VLog, VLog) = Default::default();
    let png = |tag: &'static str| {
        let dir = std::path::PathBuf::from(std::env::var("PNG_DIR").ok()?);
        std::fs::create_dir_all(&dir).unwrap();
        let calls = std::env::var("PNG_FRAMES")
            .ok()?
            .split(',')
            .map(|s| {
                let (p, e) = s.split_once(':').unwrap();
                2 * p.trim().parse::<usize>().unwrap() + e.trim().parse::<usize>().unwrap()
            })
            .collect();
        Some((dir, calls, tag))
    };
    let mut dets: Vec<Box<dyn ShaftDetector + Send>> = vec![
        Box::new(Recording {
            inner: OursDetector::new(k, ca).unwrap(),
            log: la.clone(),
            vlog: va.clone(),
            png: png("A"),
        }),
        Box::new(Recording {
            inner: OursDetector::new(k, cb).unwrap(),
            log: lb.clone(),
            vlog: vb.clone(),
            png: png("B"),
        }),
    ];
    let t0 = std::time::Instant::now();
    let run = render_and_detect(&p, &mut dets, |_, _| {}).unwrap();
    eprintln!("rendered and detected in {:.1} s", t0.elapsed().as_secs_f64());
    let (la, lb) = (la.lock().unwrap().clone(), lb.lock().unwrap().clone());
    let (va, vb) = (va.lock().unwrap().clone(), vb.lock().unwrap().clone());
    let kk = &run.setup.intrinsics;
    // Frames where A's and B's best lines differ.
    let mut diffs = Vec::new();
    let (mut na, mut nb) = (0, 0);
    for (pi, pose) in run.poses.iter().enumerate() {
        for eye in 0..2 {
            let (a, b) = (&pose.detected[0][eye], &pose.detected[1][eye]);
            na += a.is_some() as usize;
            nb += b.is_some() as usize;
            let same = match (a, b) {
                (None, None) => true,
                (Some(x), Some(y)) => x.0 == y.0 && x.1.abc == y.1.abc,
                _ => false,
            };
            if !same {
                diffs.push((pi, eye));
            }
        }
    }
    println!("lines: A {na}, B {nb}; frames differing: {}", diffs.len());
    let fmt = |l: &Option<comanip_calib::pixels::EyeLine>, t: &Option<comanip_calib::pixels::EyeLine>| match (l, t) {
        (None, _) => "none".to_string(),
        (Some(l), Some(t)) => {
            let (a, o) = line_error(t, &l.1, kk);
            format!(
                "ang {a:.3} off {o:.2} ends ({:.0},{:.0})-({:.0},{:.0})",
                l.0[0][0], l.0[0][1], l.0[1][0], l.0[1][1]
            )
        }
        (Some(l), None) => {
            format!("NO TRUTH ends ({:.0},{:.0})-({:.0},{:.0})", l.0[0][0], l.0[0][1], l.0[1][0], l.0[1][1])
        }
    };
    for (i, &(pi, eye)) in diffs.iter().enumerate() {
        if std::env::var("QUIET").is_ok() {
            break;
        }
        let pose = &run.poses[pi];
        let t = &pose.truth[eye];
        let ts = t.as_ref().map_or("no truth".into(), |t| {
            format!("truth seg distal ({:.0},{:.0}) proximal ({:.0},{:.0})", t.0[0][0], t.0[0][1], t.0[1][0], t.0[1][1])
        });
        let nda = la[2 * pi + eye].len();
        let ndb = lb[2 * pi + eye].len();
        let conf =
            |v: &Vec<ShaftDetection>| v.iter().map(|d| format!("{:.2}", d.confidence)).collect::<Vec<_>>().join(",");
        println!(
            "#{i} pose {pi} eye {eye} ecm {:?} psm {:?}: {ts}\n   A[{nda}: {}] {}\n   B[{ndb}: {}] {}",
            pose.ecm_joints.map(|v| (v * 1000.0).round() / 1000.0),
            pose.psm_joints.map(|v| (v * 1000.0).round() / 1000.0),
            conf(&la[2 * pi + eye]),
            fmt(&pose.detected[0][eye], t),
            conf(&lb[2 * pi + eye]),
            fmt(&pose.detected[1][eye], t),
        );
    }
    if let Ok(path) = std::env::var("TSV") {
        // Every eye: pose, eye, truth ends (distal first, measured px), A's and B's ends and
        // their angle (deg) and offset (px) errors (NaN: none).
        use std::fmt::Write;
        let mut s = String::new();
        let nan = f64::NAN;
        for (pi, pose) in run.poses.iter().enumerate() {
            for eye in 0..2 {
                let t = &pose.truth[eye];
                let te = t.as_ref().map_or([[nan; 2]; 2], |t| t.0);
                let _ = write!(s, "{pi}\t{eye}\t{}\t{}\t{}\t{}", te[0][0], te[0][1], te[1][0], te[1][1]);
                for d in 0..2 {
                    let l = &pose.detected[d][eye];
                    let e = l.as_ref().map_or([[nan; 2]; 2], |l| l.0);
                    let (a, o) = match (l, t) {
                        (Some(l), Some(t)) => line_error(t, &l.1, kk),
                        _ => (nan, nan),
                    };
                    let _ = write!(s, "\t{}\t{}\t{}\t{}\t{a}\t{o}", e[0][0], e[0][1], e[1][0], e[1][1]);
                }
                for (l, v) in [(&la, &va), (&lb, &vb)] {
                    let g = l[2 * pi + eye].first().map_or([nan; 4], |d| geometry(d, kk));
                    let c = l[2 * pi + eye].first().map_or(nan, |d| d.confidence);
                    let _ = write!(s, "\t{}\t{}\t{}\t{}\t{c}", g[0], g[1], g[2], g[3]);
                    let f = v[2 * pi + eye]
                        .map_or([nan; 5], |v| [v.support, v.sigma_px, v.contrast, v.length_px, v.width_px]);
                    let _ = write!(s, "\t{}\t{}\t{}\t{}\t{}", f[0], f[1], f[2], f[3], f[4]);
                }
                s.push('\n');
            }
        }
        std::fs::write(path, s).unwrap();
    }
    solve(&run, LineSource::Detector(0), "A");
    solve(&run, LineSource::Detector(1), "B");
    let swapped = |idx: &[usize]| {
        let mut r = run.clone();
        for &i in idx {
            let (pi, eye) = diffs[i];
            r.poses[pi].detected[0][eye] = run.poses[pi].detected[1][eye];
        }
        r
    };
    match std::env::var("SWAP").as_deref() {
        Ok("each") => {
            for i in 0..diffs.len() {
                solve(&swapped(&[i]), LineSource::Detector(0), &format!("A+B#{i}"));
            }
        }
        Ok(list) if !list.is_empty() => {
            let idx: Vec<usize> = list.split(',').map(|s| s.trim().parse().unwrap()).collect();
            solve(&swapped(&idx), LineSource::Detector(0), &format!("A+B{idx:?}"));
        }
        _ => {}
    }
    if std::env::var("EXPERIMENTS").is_ok() {
        let bad_deg: f64 = std::env::var("BAD_DEG").map_or(1.0, |s| s.parse().unwrap());
        // A line is bad: no truth line in that eye, or more than `bad_deg` off it.
        let bad = |pose: &comanip_calib::pixels::PoseLines, d: usize, eye: usize| match (
            &pose.detected[d][eye],
            &pose.truth[eye],
        ) {
            (None, _) => false,
            (Some(_), None) => true,
            (Some(l), Some(t)) => line_error(t, &l.1, kk).0 > bad_deg,
        };
        let variant =
            |f: &dyn Fn(&comanip_calib::pixels::PoseLines, usize) -> Option<comanip_calib::pixels::EyeLine>| {
                let mut r = run.clone();
                for (pi, pose) in run.poses.iter().enumerate() {
                    for eye in 0..2 {
                        r.poses[pi].detected[0][eye] = f(pose, eye);
                    }
                }
                r
            };
        let nbad = |d: usize| run.poses.iter().map(|p| (0..2).filter(|&e| bad(p, d, e)).count()).sum::<usize>();
        println!("bad lines (> {bad_deg} deg or no truth): A {}, B {}", nbad(0), nbad(1));
        let r = variant(&|p, e| if bad(p, 0, e) { None } else { p.detected[0][e] });
        solve(&r, LineSource::Detector(0), "A without its bad lines");
        let r = variant(&|p, e| if bad(p, 1, e) { None } else { p.detected[1][e] });
        solve(&r, LineSource::Detector(0), "B without its bad lines");
        let r = variant(&|p, e| if bad(p, 1, e) && !bad(p, 0, e) { p.detected[1][e] } else { p.detected[0][e] });
        solve(&r, LineSource::Detector(0), "A + B's new bad lines");
        let r = variant(&|p, e| if bad(p, 1, e) { p.detected[0][e] } else { p.detected[1][e] });
        solve(&r, LineSource::Detector(0), "B with A's line where B's is bad");
        let r = variant(&|p, e| if !bad(p, 1, e) { p.detected[1][e] } else { p.detected[0][e] });
        solve(&r, LineSource::Detector(0), "A + B's good lines (B where B's is good)");
    }
    if let Ok(c) = std::env::var("MIN_CONF") {
        // A consumer's gate: the lines whose detection's confidence is under `c` left out.
        let c: f64 = c.parse().unwrap();
        let mut r = run.clone();
        let mut dropped = [0usize; 2];
        for (pi, pose) in r.poses.iter_mut().enumerate() {
            for eye in 0..2 {
                for (d, l) in [&la, &lb].into_iter().enumerate() {
                    if l[2 * pi + eye].first().is_some_and(|x| x.confidence < c) {
                        pose.detected[d][eye] = None;
                        dropped[d] += 1;
                    }
                }
            }
        }
        println!("confidence under {c}: A {} lines left out, B {}", dropped[0], dropped[1]);
        solve(&r, LineSource::Detector(0), &format!("A, confidence >= {c}"));
        solve(&r, LineSource::Detector(1), &format!("B, confidence >= {c}"));
    }
    if std::env::var("DROP").as_deref() == Ok("each") {
        for (i, &(pi, eye)) in diffs.iter().enumerate() {
            let mut r = run.clone();
            r.poses[pi].detected[1][eye] = run.poses[pi].detected[0][eye];
            solve(&r, LineSource::Detector(1), &format!("B-#{i}"));
        }
    }
}
