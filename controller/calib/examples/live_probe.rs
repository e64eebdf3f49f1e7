//! Diagnostic: a saved live dataset (`live --replay ... --save-dataset DIR`) solved under
//! variants of the noise model and the pipeline's stages, errors against the run's truth;
//! first, where the line points lie along the tool at the truth (`s / L`, and the points off
//! `[0, L]`) and the shaft-position residuals there (`LIVE_PROBE_S=1`: every observation;
//! `LIVE_PROBE_LEFT=1`: the left eye's observations only).
//! Usage: `cargo run --release -p comanip-calib --example live_probe -- DIR [px mrad mm]...`
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "diagnostic tool: a panic is a bug report")]

use estimator::calib::KinematicNoise;
use estimator::calib::ours::{OursConfig, solve_ours_prepared};
use estimator::calib::prepare::prepare;
use estimator::calib::selection::SelectionConfig;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let dir = std::path::PathBuf::from(&a[1]);
    let ds: hw_io::calib_files::DatasetFile =
        serde_json::from_str(&std::fs::read_to_string(dir.join("dataset.json")).unwrap()).unwrap();
    let tf: hw_io::calib_files::TruthFile =
        serde_json::from_str(&std::fs::read_to_string(dir.join("truth.json")).unwrap()).unwrap();
    let truth = comanip_calib::convert::isometry(&tf.truth);
    let (mut setup, mut obs, noise) = comanip_calib::convert::dataset(&ds);
    // LIVE_PROBE_JAWTIP=1: the tip taken at the end of the visible instrument (the jaws'
    // tips) for every model, the extent past it 0.
    if std::env::var("LIVE_PROBE_JAWTIP").is_ok() {
        let b = setup.shaft_extent.beyond_tip_m;
        for o in &mut obs {
            let m = estimator::calib::rcm_arms::psm_axis(&o.psm_joints);
            *o = estimator::calib::Observation::from_tool_line(
                o.ecm_joints,
                o.tool_point_m,
                m.into(),
                o.psm_joints[2] + b,
                o.line_px,
                o.eye,
            )
            .unwrap();
        }
        setup.shaft_extent.beyond_tip_m = 0.0;
    }
    // LIVE_PROBE_LEFT=1: the left eye's observations only.
    if std::env::var("LIVE_PROBE_LEFT").is_ok() {
        obs.retain(|o| o.eye == estimator::calib::Eye::Left);
    }
    if let Some(v) = std::env::var("LIVE_PROBE_END_PX").ok().and_then(|v| v.parse::<f64>().ok()) {
        setup.shaft_extent.end_sd_px = v;
    }
    let mut noises = vec![noise.unwrap()];
    for c in a[2..].chunks(3) {
        let v: Vec<f64> = c.iter().map(|s| s.parse().unwrap()).collect();
        noises.push(KinematicNoise { pixel_px: v[0], rot_rad: v[1] * 1e-3, trans_m: v[2] * 1e-3 });
    }
    let set = prepare(&setup, &obs).unwrap();
    println!("{} observations", obs.len());
    {
        use estimator::calib::shaft_position::{axis_seen_at, shaft_position_residuals};
        let (r, t) = (truth.rotation.to_rotation_matrix().into_inner(), truth.translation.vector);
        let mut fr = Vec::new();
        let mut worst = Vec::new();
        for (i, o) in set.obs.iter().enumerate() {
            for (k, u) in o.px.iter().enumerate() {
                if let Some((depth, s)) = axis_seen_at(&set, o, &r, &t, u) {
                    fr.push(s / o.insertion_m);
                    if s > o.insertion_m || s < 0.0 || depth < 0.0 {
                        worst.push((i, k, s * 1e3, o.insertion_m * 1e3, depth * 1e3));
                    }
                }
            }
            if std::env::var("LIVE_PROBE_S").is_ok() {
                let v: Vec<_> =
                    o.px.iter()
                        .filter_map(|u| axis_seen_at(&set, o, &r, &t, u))
                        .map(|(d, s)| (s * 1e3, d * 1e3))
                        .collect();
                let tip = estimator::calib::selection::tip_px(&set, o, &r, &t);
                let d: Vec<f64> = o.px.iter().map(|u| tip.map_or(f64::NAN, |tp| (u - tp).norm())).collect();
                println!("T {i} tip px {:?} dist to ends px {:?}", tip.map(|v| (v.x.round(), v.y.round())), d);
                println!(
                    "S {i} eye {:?} L {:.1} px {:?} (s mm, depth mm) {:?}",
                    obs[i].eye,
                    o.insertion_m * 1e3,
                    obs[i].line_px,
                    v
                );
            }
            let res = shaft_position_residuals(&set, o, &r, &t, &noise.unwrap());
            if i < 8 || res.iter().any(|v| v.abs() > 3.0) {
                println!(
                    "obs {i} end {:?} ins {:.1} mm shaft residuals at truth {:?}",
                    o.shaft_end,
                    o.insertion_m * 1e3,
                    res.map(|v| (v * 100.0).round() / 100.0)
                );
            }
        }
        // Residuals beyond the visible extent at the truth, in their standard deviations.
        let mut ex: Vec<(f64, usize)> = set
            .obs
            .iter()
            .enumerate()
            .map(|(i, o)| {
                let e = shaft_position_residuals(&set, o, &r, &t, &noise.unwrap());
                (e.iter().fold(0.0f64, |m, v| m.max(v.abs())), i)
            })
            .collect();
        ex.sort_by(|a, b| b.0.total_cmp(&a.0));
        let n3 = ex.iter().filter(|v| v.0 > 3.0).count();
        println!("shaft residuals at truth beyond 3 sd: {n3} of {}; largest {:?}", ex.len(), &ex[..ex.len().min(8)]);
        // Pixel distance from each line end lying past the visible instrument to the image of
        // the visible instrument's end.
        let mut past_px: Vec<f64> = Vec::new();
        for (i, o) in set.obs.iter().enumerate() {
            let m = estimator::calib::rcm_arms::psm_axis(&obs[i].psm_joints);
            let Some(jt) = estimator::calib::Observation::from_tool_line(
                obs[i].ecm_joints,
                obs[i].tool_point_m,
                m.into(),
                o.visible_m[1],
                obs[i].line_px,
                obs[i].eye,
            ) else {
                continue;
            };
            let Ok(one) = estimator::calib::prepare::prepare_unchecked(&setup, &[jt]) else { continue };
            let Some(end_px) = estimator::calib::selection::tip_px(&one, &one.obs[0], &r, &t) else { continue };
            for u in &o.px {
                if let Some((_, s)) = axis_seen_at(&set, o, &r, &t, u)
                    && s > o.visible_m[1]
                {
                    past_px.push((u - end_px).norm());
                }
            }
        }
        past_px.sort_by(f64::total_cmp);
        if !past_px.is_empty() {
            let q = |p: f64| past_px[((past_px.len() - 1) as f64 * p) as usize];
            println!(
                "line ends past the visible instrument: {} points, image distance px median {:.1} p90 {:.1} max {:.1}",
                past_px.len(),
                q(0.5),
                q(0.9),
                q(1.0)
            );
        }
        for &(_, i) in ex.iter().take(4) {
            let o = &set.obs[i];
            let v: Vec<_> =
                o.px.iter().filter_map(|u| axis_seen_at(&set, o, &r, &t, u)).map(|(d, s)| (s * 1e3, d * 1e3)).collect();
            println!(
                "  obs {i} eye {:?} L {:.1} mm visible {:?} px {:?} (s mm, depth mm) {:?}",
                obs[i].eye,
                o.insertion_m * 1e3,
                o.visible_m,
                obs[i].line_px,
                v
            );
        }
        fr.sort_by(f64::total_cmp);
        let q = |p: f64| fr[((fr.len() - 1) as f64 * p) as usize];
        println!(
            "s/insertion at truth: min {:.3} p5 {:.3} median {:.3} p95 {:.3} max {:.3}",
            q(0.0),
            q(0.05),
            q(0.5),
            q(0.95),
            q(1.0)
        );
        println!("outside [0, tip] or behind: {} e.g. {:?}", worst.len(), &worst[..worst.len().min(10)]);
    }
    for n in noises {
        let forced = SelectionConfig { false_refusal_probability: 0.0, ..SelectionConfig::default() };
        let measured = SelectionConfig { influence_move_test: true, ..SelectionConfig::default() };
        for (name, cfg) in [
            ("product", OursConfig { noise: Some(n), ..OursConfig::default() }),
            ("stage forced", OursConfig { noise: Some(n), selection: Some(forced), ..OursConfig::default() }),
            ("measured test", OursConfig { noise: Some(n), selection: Some(measured), ..OursConfig::default() }),
            ("no stage", OursConfig { noise: Some(n), selection: None, ..OursConfig::default() }),
            ("no shaft", OursConfig { noise: Some(n), shaft_position: false, ..OursConfig::default() }),
            (
                "no shaft forced",
                OursConfig { noise: Some(n), shaft_position: false, selection: Some(forced), ..OursConfig::default() },
            ),
        ] {
            let t0 = std::time::Instant::now();
            match solve_ours_prepared(&set, &cfg) {
                Ok(r) => {
                    let et = (r.pose.translation.vector - truth.translation.vector).norm() * 1e3;
                    let er = (r.pose.rotation.inverse() * truth.rotation).angle().to_degrees();
                    println!(
                        "{:.2}px {:.1}mrad {:.2}mm {name:16} et {et:7.2} mm er {er:6.3} deg scale {:.2} llr {:.1} kept {} sel {:?} refused {:?} {:.0} ms",
                        n.pixel_px,
                        n.rot_rad * 1e3,
                        n.trans_m * 1e3,
                        r.scale,
                        r.log_likelihood_ratio,
                        r.guard_kept,
                        r.selection.map(|s| (s.selected, s.plain, s.left_out, (s.shift_sigmas * 10.0).round() / 10.0)),
                        r.selection_refused.map(|e| e.to_string()),
                        t0.elapsed().as_secs_f64() * 1e3
                    );
                }
                Err(e) => println!("{:.2}px {name:16} error {e}", n.pixel_px),
            }
        }
    }
}
