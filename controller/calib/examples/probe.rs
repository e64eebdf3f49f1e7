use estimator::calib::ours::{OursConfig, solve_ours_prepared};
use estimator::calib::paper::{PaperConfig, solve_paper_prepared, linear_translation};
use estimator::calib::prepare::prepare;
use estimator::calib::pose_errors;
use sim::calib::{CalibProtocol, NoiseUnits, generate_calibration, random_geometry};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let seed: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(9000);
    let sigma: f64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(0.0);
    let units = if args.get(3).map(|s| s == "m").unwrap_or(false) { NoiseUnits::Metre } else { NoiseUnits::Millimetre };
    let trials: u64 = args.get(4).and_then(|s| s.parse().ok()).unwrap_or(1);
    let g = random_geometry(seed, (seed - 9000) % 2 == 1).unwrap();
    println!("dist {:.0} mm angle {:.0}° t {:?} ecm ins {:?} psm yaw {:?} ecm yaw {:?}", g.rcm_distance_m*1e3, g.tool_scope_angle_rad.to_degrees(), g.geometry.truth.translation.vector.as_slice(), g.geometry.ecm_insertion_m, g.geometry.psm_yaw_rad, g.geometry.ecm_yaw_rad);
    for k in 0..trials {
        let d = generate_calibration(&CalibProtocol { geometry: g.geometry, n_e: 3, n_t: 3, sigma, units, pixel_sigma_px: 0.0, seed: 1000 + k }).unwrap();
        let set = prepare(&d.setup, &d.observations).unwrap();
        let t0 = linear_translation(&set).unwrap();
        let p = solve_paper_prepared(&set, &PaperConfig::default());
        let pe = p.as_ref().map(|r| pose_errors(&r.pose, &d.truth));
        let o = solve_ours_prepared(&set, &OursConfig { noise: d.noise, ..Default::default() });
        let oe = o.as_ref().map(|r| (pose_errors(&r.pose, &d.truth), r.log_likelihood_ratio, r.selection_refused, r.guard_kept, r.selection.map(|s| (s.selected, s.plain, s.left_out, s.shift_sigmas))));
        println!("kept {} t0 err {:.1} mm | paper {:?}\n  ours {:?}", d.observations.len(), (t0 - d.truth.translation.vector).norm()*1e3, pe.map(|e| (e.translation_m*1e3, e.rotation_rad.to_degrees())), oe.map(|(e, l, s, gk, sel)| (e.translation_m*1e3, e.rotation_rad.to_degrees(), l, s, gk, sel)));
    }
}
