use controller::bench::detection::{analyse, run, settings};
use controller::bench::trace::{PLACEMENTS, TraceSpec, generate};
use estimator::trocar::{Detector, TrocarState};
use sim::score::GroundTruth;

fn e_f(e: &estimator::trocar::Estimate) -> nalgebra::Vector3<f64> {
    e.fulcrum_base_m.unwrap()
}
fn main() {
    let key = std::env::args().nth(1).unwrap_or("fast".into());
    let seed: u64 = std::env::args().nth(2).map(|s| s.parse().unwrap()).unwrap_or(11);
    let pl: usize = std::env::var("PL").map(|s| s.parse().unwrap()).unwrap_or(0);
    let spec = TraceSpec { seed, cycles: 30, placement: PLACEMENTS[pl] };
    let trace = generate(&spec).unwrap();
    let cfg = controller::config::Config::load(std::path::Path::new(
        &std::env::var("CFG").unwrap_or("configs/fulcrumd.toml".into()),
    ))
    .unwrap();
    let sets = settings(0.30, &cfg.detector);
    let s = sets.iter().find(|s| s.key == key).unwrap();
    let r = run(&trace, s, false).unwrap();
    let a = analyse(&trace, &r);
    // re-run with full estimates for diagnostics
    let mut det = Detector::new(&s.config).unwrap();
    let ests: Vec<_> = trace.lines.iter().map(|l| det.step(&l.unwrap())).collect();
    for &i in &a.score.false_detection_samples {
        let (st, p) = trace.truth_at(i);
        // nearest event
        let ev = trace.events.iter().filter(|e| e.sample <= i).last();
        let nx = trace.events.iter().find(|e| e.sample > i).map(|e| (e.sample as f64 - i as f64) * 1e-3);
        let dur = (i..trace.lines.len()).take_while(|&j| ests[j].state.is_inside()).count();
        let nt = trace.events.iter().find(|e| e.sample > i).map(|e| e.trocar).unwrap_or(0);
        let t = nalgebra::Vector3::from(trace.trocars_base_m[nt]);
        let l = trace.lines[i].unwrap();
        print!(
            "[next event in {:?}s, lasts {} ms, dist to next trocar {:.1} mm, depth {:.1} mm] ",
            nx,
            dur,
            (e_f(&ests[i]) - t).norm() * 1e3,
            estimator::trocar::lsq::signed_depth(&l, &e_f(&ests[i])) * 1e3
        );
        let e = ests[i];
        let f = e.fulcrum_base_m.unwrap();
        let fit = e.fit.unwrap();
        if let estimator::trocar::Detector::Fast(_) = det {}
        println!(
            "spread {:.2e} false at {:.3}s truth {:?} since-last-event {:?} err {:.1}mm fit rms {:.2}mm std {:.2}mm lines {} cond {:.2e}",
            fit.minor_spread_rad2,
            i as f64 * 1e-3,
            st,
            ev.map(|ev| ((i - ev.sample) as f64 * 1e-3, ev.insertion)),
            p.map(|p| (f - p).norm() * 1e3).unwrap_or(f64::NAN),
            fit.residual_m * 1e3,
            fit.std_m * 1e3,
            fit.lines,
            fit.conditioning
        );
        let _ = TrocarState::Outside;
    }
    for ev in &a.events {
        if let Some(d) = ev.insertion_delay_s {
            let i = ev.insertion_sample + (d * 1e3).round() as usize;
            let fit = ests[i].fit.unwrap();
            println!(
                "spread {:.2e} true det delay {:.3} err {:.1}mm rms {:.2} std {:.2} lines {}",
                fit.minor_spread_rad2,
                d,
                ev.first_error_m.unwrap_or(0.0) * 1e3,
                fit.residual_m * 1e3,
                fit.std_m * 1e3,
                fit.lines
            );
        }
    }
    {
        use estimator::trocar::lsq::NormalSums;
        let mut errs = vec![];
        let mut sq = 0.0;
        let mut n = 0.0;
        for (k, e) in trace.events.iter().enumerate() {
            if !e.insertion {
                continue;
            }
            let x = trace.events[k + 1..].iter().find(|v| !v.insertion).map_or(trace.lines.len(), |v| v.sample);
            let mut s = NormalSums::new();
            let mut pm = nalgebra::Vector3::zeros();
            for j in e.sample..x {
                s.add(&trace.lines[j].unwrap());
                pm += trace.pivots[j].unwrap();
            }
            pm /= (x - e.sample) as f64;
            let f = s.solve(1e-12).unwrap().fulcrum_base_m;
            errs.push(format!("{:.2}", (f - pm).norm() * 1e3));
            for j in e.sample..x {
                sq += (f - trace.pivots[j].unwrap()).norm_squared();
                n += 1.0;
            }
        }
        println!("oracle fixed-point errors (mm): {:?} rms vs moving pivot {:.2} mm", errs, (sq / n).sqrt() * 1e3);
    }
    {
        let mut worst: Vec<(f64, usize)> = vec![];
        for ev in &a.events {
            for j in ev.insertion_sample..ev.extraction_sample {
                if let (Some(f), Some(p)) = (r.detected[j].fulcrum_base_m, trace.pivots[j]) {
                    worst.push(((f - p).norm() * 1e3, j));
                }
            }
        }
        let n = worst.len();
        let big: Vec<_> = worst.iter().filter(|w| w.0 > 10.0).collect();
        println!(
            "inside samples {n}, >10mm: {} ; first few: {:?}",
            big.len(),
            big.iter().step_by(200).take(10).map(|w| (format!("{:.0}", w.0), w.1)).collect::<Vec<_>>()
        );
    }
    let envs: Vec<f64> = controller::bench::bound::bounds(&trace).iter().map(|b| b.envelope_m * 1e3).collect();
    println!("envelopes mm: {:?}", envs.iter().map(|e| format!("{e:.1}")).collect::<Vec<_>>());
}
// (appended) nothing
