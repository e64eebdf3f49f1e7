//! Diagnostic probe of our pipeline on the generalisation protocol's geometries: one line per
//! trial with the pose errors, the outcome and the selection-aware stage's shift, and the
//! solve time. For comparing builds (`diff` the outputs) and for looking at refusals.
//!
//! `cargo run --release -p comanip-calib --example calib_probe -- <first seed> <geometries>
//! <trials> [mm|m] [sigma] [first trial]` (tuning geometries: seeds 9000..9019). Environment:
//! `NO_SHAFT_POSITION=1` runs the lines alone (`OursConfig::shaft_position` off, in the fit and
//! the selection stage), `FALSE_REFUSAL=<p>` the move test's false-refusal probability,
//! `BORDER_GUARD=<sigmas>` sets the border guard (0: off), `DIAG=1`
//! prints the guarded fit and the selection stage separately, `AXIS=1` the axis of the
//! rotation error against the line of sight and the tool (which 180° turn a mirror is).
//! `MOVING=1` turns on the moving-covariance step (`SelectionConfig::moving_covariance_step`;
//! printed as `moving gain <g> sd <its jackknife standard error, n/a when not computed>
//! taken|held`), `MOVING=force`
//! takes it whatever its gain, `MOVING_Z=<z>` sets `SelectionConfig::moving_step_gain_z`.
//! `GEOMETRY=1` prints each geometry's class (RCM distance, tool-scope angle, distortion) on stderr.
//! `INFLUENCE=0` judges the stage's move with the efficiency-based covariance, `INFLUENCE=1`
//! with its measured covariance (`SelectionConfig::influence_move_test`, the default since session 26). `LIK=0` turns the likelihood descent of the
//! unexplained candidates off (`OursConfig::likelihood_descent`). `BASIN=0` leaves the candidates that
//! explain the shafts where their refinement ended (`OursConfig::descend_every_basin`). `FROM_TRUTH=1` adds the truth's rotation as a
//! start (`OursConfig::initial_quaternion`). `SEARCH=<n>` searches the candidates on n observations
//! (`OursConfig::search_observations`; 0: on all of them). The default searches from a cover of
//! rotation space every time (`OursConfig::cover_search_scale`, since session 31); `COVER=0` never
//! does, `COVER=<s>` only when the usual starts' answer has a robust scale above s (1.5: the default
//! until session 31), `COVER=always` every time; a trial whose answer comes from that search is
//! marked `cover`.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "diagnostic tool: a panic is a bug report")]

use estimator::calib::ours::{OursConfig, SHAFT_MARGIN, shaft_explanation, solve_ours_prepared};
use estimator::calib::prepare::{PreparedSet, prepare};
use estimator::calib::selection::{SelectionConfig, refine_selected};
use nalgebra::{Isometry3, Matrix6, Vector6};

/// Mahalanobis distance (in `cov`'s standard deviations) of `truth` from `pose`.
fn mahalanobis(pose: &Isometry3<f64>, truth: &Isometry3<f64>, cov: &Matrix6<f64>) -> f64 {
    let mut d = Vector6::zeros();
    d.fixed_rows_mut::<3>(0).copy_from(&(truth.translation.vector - pose.translation.vector));
    d.fixed_rows_mut::<3>(3).copy_from(&(truth.rotation * pose.rotation.inverse()).scaled_axis());
    cov.try_inverse().map_or(f64::NAN, |i| d.dot(&(i * d)).max(0.0).sqrt())
}

/// The guarded fit (no selection stage), its error against the truth in its own standard
/// deviations, and the selection stage without its run-away limit.
fn diag(set: &PreparedSet, cfg: &OursConfig, truth: &Isometry3<f64>, seed: u64, k: u64) {
    let err = |p: &Isometry3<f64>| {
        (
            (p.translation.vector - truth.translation.vector).norm() * 1e3,
            (p.rotation.inverse() * truth.rotation).angle().to_degrees(),
        )
    };
    let guarded = match solve_ours_prepared(set, &OursConfig { selection: None, ..*cfg }) {
        Ok(g) => g,
        Err(e) => {
            println!("{seed} {k} error {e}");
            return;
        }
    };
    let (gt, gr) = err(&guarded.pose);
    let sd_t = (guarded.covariance[(0, 0)] + guarded.covariance[(1, 1)] + guarded.covariance[(2, 2)]).sqrt() * 1e3;
    let mg = mahalanobis(&guarded.pose, truth, &guarded.covariance);
    let sel = SelectionConfig { false_refusal_probability: 0.0, ..SelectionConfig::default() };
    let stage = match refine_selected(set, &cfg.noise.unwrap(), &guarded.pose, &guarded.covariance, &sel) {
        Ok(f) => {
            let (st, sr) = err(&f.pose);
            let ms = mahalanobis(&f.pose, truth, &f.covariance);
            let h = match f.move_test {
                Some(t) => format!(
                    "hausman {:.1} (rank {}) limit {:.1} {}",
                    t.statistic,
                    t.hausman_rank,
                    t.limit,
                    if t.passes() { "pass" } else { "REFUSE" }
                ),
                None => "hausman n/a REFUSE".into(),
            };
            format!(
                "stage et {st:.2} er {sr:.3} shift {:.1} {h} truth@{ms:.1}sd sel {} plain {} out {}",
                f.shift_sigmas, f.selected, f.plain, f.left_out
            )
        }
        Err(e) => format!("stage error {e}"),
    };
    println!(
        "{seed} {k} n={} guarded et {gt:.2} er {gr:.3} sd_t {sd_t:.2} truth@{mg:.1}sd scale {:.2} kept {} | {stage}",
        set.obs.len(),
        guarded.scale,
        guarded.guard_kept
    );
}
use comanip_calib::generalise::protocol;
use sim::calib::{NoiseUnits, generate_calibration, random_geometry};

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let first: u64 = a.get(1).map_or(9000, |s| s.parse().unwrap());
    let n: u64 = a.get(2).map_or(5, |s| s.parse().unwrap());
    let trials: u64 = a.get(3).map_or(3, |s| s.parse().unwrap());
    let units = match a.get(4).map(String::as_str) {
        Some("m") => NoiseUnits::Metre,
        _ => NoiseUnits::Millimetre,
    };
    let sigma: f64 = a.get(5).map_or(0.01, |s| s.parse().unwrap());
    let first_trial: u64 = a.get(6).map_or(0, |s| s.parse().unwrap());
    let mut total = 0.0;
    for g in 0..n {
        let seed = first + g;
        // Distortion on odd seeds, as `sweep` draws them (its sets start at even seeds).
        let draw = random_geometry(seed, seed % 2 == 1).unwrap();
        if std::env::var("GEOMETRY").is_ok() {
            eprintln!(
                "geometry {seed}: RCM distance {:.0} mm, tool-scope angle {:.1}°, distorted {}",
                draw.rcm_distance_m * 1e3,
                draw.tool_scope_angle_rad.to_degrees(),
                draw.distorted
            );
        }
        for k in first_trial..first_trial + trials {
            let p = protocol(&draw, units, sigma, 1000 + k);
            let d = generate_calibration(&p).unwrap();
            let set = prepare(&d.setup, &d.observations).unwrap();
            // NO_SHAFT_POSITION=1: the lines alone (the objective before the shaft-position term).
            let shaft_position = std::env::var("NO_SHAFT_POSITION").is_err();
            let mut cfg = OursConfig { noise: d.noise, shaft_position, ..OursConfig::default() };
            // BORDER_GUARD=<sigmas>: the border guard's threshold (0 disables it).
            if let Ok(v) = std::env::var("BORDER_GUARD") {
                cfg.border_guard_sigmas = v.parse().unwrap();
            }
            // MOVING=1/0: the last step on the moving-covariance likelihood on / off.
            if let (Ok(v), Some(sel)) = (std::env::var("MOVING"), cfg.selection.as_mut()) {
                sel.moving_covariance_step = v != "0";
                // MOVING=force: take every step (the test reported, not applied).
                if v == "force" {
                    sel.moving_step_min_gain = f64::NEG_INFINITY;
                }
                // MOVING_Z=<z>: the gain must clear the threshold by z of its standard errors
                // (0: session 20's gate, the gain as measured).
                if let Ok(z) = std::env::var("MOVING_Z") {
                    sel.moving_step_gain_z = z.parse().unwrap();
                }
            }
            // FALSE_REFUSAL=<p>: the move test's false-refusal probability (default 1e-3).
            if let (Some(p), Some(sel)) =
                (std::env::var("FALSE_REFUSAL").ok().and_then(|v| v.parse::<f64>().ok()), cfg.selection.as_mut())
            {
                sel.false_refusal_probability = p;
            }
            // LIK=0: the candidates that do not explain the shafts are compared where their
            // refinement left them (no likelihood descent).
            if let Ok(v) = std::env::var("LIK") {
                cfg.likelihood_descent = v != "0";
            }
            // BASIN=0: only the unexplained candidates descend; the others are compared where
            // their refinement left them.
            if let Ok(v) = std::env::var("BASIN") {
                cfg.descend_every_basin = v != "0";
            }
            // SEARCH=<n>: the candidates searched on n observations (0: on all of them).
            if let Ok(v) = std::env::var("SEARCH") {
                let n: usize = v.parse().unwrap();
                cfg.search_observations = (n > 0).then_some(n);
            }
            // COVER=0: never searched from a cover of rotation space; COVER=<s>: when the usual
            // starts' answer's robust scale is above s; COVER=always: every time (the default).
            if let Ok(v) = std::env::var("COVER") {
                cfg.cover_search_scale = match v.as_str() {
                    "always" => Some(0.0),
                    _ => Some(v.parse::<f64>().unwrap()).filter(|s| *s > 0.0),
                };
            }
            // INFLUENCE=1/0: the stage's move test with the measured covariance of the move.
            if let (Ok(v), Some(sel)) = (std::env::var("INFLUENCE"), cfg.selection.as_mut()) {
                sel.influence_move_test = v != "0";
            }
            // FROM_TRUTH=1: the truth's rotation as one more start (is there a basin the starts
            // missed?).
            if std::env::var("FROM_TRUTH").is_ok() {
                let q = d.truth.rotation;
                cfg.initial_quaternion = Some([q.w, q.i, q.j, q.k]);
            }
            if std::env::var("NLLDIAG").is_ok() {
                let q = d.truth.rotation;
                let t = d.truth.translation.vector;
                eprintln!("NLLTRUTH={},{},{},{},{},{},{}", q.w, q.i, q.j, q.k, t.x, t.y, t.z);
            }
            let t0 = std::time::Instant::now();
            let r = solve_ours_prepared(&set, &cfg);
            let dt = t0.elapsed().as_secs_f64() * 1e3;
            total += dt;
            if std::env::var("DIAG").is_ok() {
                diag(&set, &cfg, &d.truth, seed, k);
                continue;
            }
            let line = match r {
                Ok(r) => {
                    let et = (r.pose.translation.vector - d.truth.translation.vector).norm() * 1e3;
                    let er = (r.pose.rotation.inverse() * d.truth.rotation).angle().to_degrees();
                    let stage = match (&r.selection, &r.selection_refused) {
                        (Some(s), _) => format!(
                            "applied shift {:.2} stat {:.2}{}{}{}",
                            s.shift_sigmas,
                            s.move_statistic.map_or(f64::NAN, |(x, _)| x),
                            if s.accepted_on_likelihood { " on likelihood" } else { "" },
                            if s.move_test_measured { " measured" } else { "" },
                            s.moving_step.map_or(String::new(), |(h, hsd, take)| format!(
                                " moving gain {h:.2} sd {} {}",
                                hsd.map_or("n/a".into(), |v| format!("{v:.3}")),
                                if take { "taken" } else { "held" }
                            ))
                        ),
                        (None, Some(e)) => format!("refused {e}"),
                        _ => "none".into(),
                    };
                    if std::env::var("AXIS").is_ok() {
                        let n = set.obs.len() as f64;
                        let mc = set.obs.iter().map(|o| o.o_ec).sum::<nalgebra::Vector3<f64>>() / n;
                        let mp = set.obs.iter().map(|o| o.p_t).sum::<nalgebra::Vector3<f64>>() / n;
                        let sight = (r.pose * nalgebra::Point3::from(mp)).coords - mc;
                        let mm = set.obs.iter().map(|o| o.m_t).sum::<nalgebra::Vector3<f64>>() / n;
                        let tool = r.pose.rotation * mm;
                        let d_t = d.truth.translation.vector;
                        let d = d.truth.rotation * r.pose.rotation.inverse();
                        let ax = d.axis().map_or(nalgebra::Vector3::z(), |a| a.into_inner());
                        println!(
                            "AXIS angle {:.1} axis·sight {:.3} axis·tool {:.3} |sight| {:.3} truth t {:?}",
                            d.angle().to_degrees(),
                            ax.dot(&sight.normalize()),
                            ax.dot(&tool.normalize()),
                            sight.norm(),
                            d_t.as_slice()
                        );
                    }
                    let x = shaft_explanation(&set, &r.pose, SHAFT_MARGIN);
                    let (b, o) = (x.behind, x.off_shaft);
                    let xt = shaft_explanation(&set, &d.truth, SHAFT_MARGIN);
                    let (tb, to) = (xt.behind, xt.off_shaft);
                    format!(
                        "et {et:.4} mm er {er:.5} deg llr {:.2} kept {} scale {:.2} behind {b} off {o} truth {tb} {to}{} | {stage}",
                        r.log_likelihood_ratio,
                        r.guard_kept,
                        r.scale,
                        if r.cover_searched { " cover" } else { "" }
                    )
                }
                Err(e) => format!("error {e}"),
            };
            println!("{seed} {k} n={} {line} | {dt:.1} ms", set.obs.len());
        }
    }
    eprintln!("total solve time {total:.0} ms");
}
