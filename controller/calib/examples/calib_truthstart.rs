//! Diagnostic: does our pipeline pick a wrong candidate because the truth's basin was never
//! found, or because the likelihood prefers the wrong one? Solves each trial twice: as the
//! product does, and with the true rotation as an extra start (`OursConfig::initial_quaternion`),
//! printing both results' errors and how many observed shafts each puts behind the camera or
//! off the instrument ([`shaft_explanation`]). Usage: `cargo run --release -p comanip-calib
//! --example calib_truthstart -- <geometry seed> <mm|m> <sigma> <distorted 0|1> <trial>...`
//! (trial `k` uses noise seed `1000 + k`, as the sweep).
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "diagnostic tool: a panic is a bug report")]

use comanip_calib::generalise::protocol;
use estimator::calib::ours::{OursConfig, SHAFT_MARGIN, shaft_explanation, solve_ours_prepared};
use estimator::calib::prepare::prepare;
use sim::calib::{NoiseUnits, generate_calibration, random_geometry};

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let seed: u64 = a[1].parse().unwrap();
    let units = if a[2] == "m" { NoiseUnits::Metre } else { NoiseUnits::Millimetre };
    let sigma: f64 = a[3].parse().unwrap();
    let distort: bool = a[4] == "1";
    for k in a[5..].iter().map(|s| s.parse::<u64>().unwrap()) {
        let draw = random_geometry(seed, distort).unwrap();
        let p = protocol(&draw, units, sigma, 1000 + k);
        let d = generate_calibration(&p).unwrap();
        let set = prepare(&d.setup, &d.observations).unwrap();
        let q = d.truth.rotation.into_inner();
        println!("{seed} {k} truth {:?}", shaft_explanation(&set, &d.truth, SHAFT_MARGIN));
        for (name, cfg) in [
            ("product", OursConfig { noise: d.noise, ..OursConfig::default() }),
            (
                "truth-start",
                OursConfig { noise: d.noise, initial_quaternion: Some([q.w, q.i, q.j, q.k]), ..OursConfig::default() },
            ),
            ("no-stage", OursConfig { noise: d.noise, selection: None, ..OursConfig::default() }),
            (
                "no-stage truth-start",
                OursConfig {
                    noise: d.noise,
                    selection: None,
                    initial_quaternion: Some([q.w, q.i, q.j, q.k]),
                    ..OursConfig::default()
                },
            ),
        ] {
            match solve_ours_prepared(&set, &cfg) {
                Ok(r) => {
                    let et = (r.pose.translation.vector - d.truth.translation.vector).norm() * 1e3;
                    let er = (r.pose.rotation.inverse() * d.truth.rotation).angle().to_degrees();
                    let ea = (r.alternative.rotation.inverse() * d.truth.rotation).angle().to_degrees();
                    println!(
                        "{seed} {k} {name:22} et {et:.2} er {er:.2} {:?} alt {:?} llr {:.1} alt er {ea:.1} kept {} scale {:.2} refused {:?}",
                        shaft_explanation(&set, &r.pose, SHAFT_MARGIN),
                        shaft_explanation(&set, &r.alternative, SHAFT_MARGIN),
                        r.log_likelihood_ratio,
                        r.guard_kept,
                        r.scale,
                        r.selection_refused.map(|e| e.to_string())
                    );
                }
                Err(e) => println!("{seed} {k} {name:22} error {e}"),
            }
        }
    }
}
