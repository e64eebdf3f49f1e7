//! Solve time of the dual RCM-arm calibration for 729 observations, both pipelines, from raw
//! observations (preparation included).
//!
//! The 729 observations: the protocol's default scene at n_e = 3, n_t = 4 (1296
//! combinations, σ = 0.01), the first 729 kept. `ours` runs with the dataset's noise model
//! (whitened, two passes, both ambiguity candidates), as `comanip-calib calibrate` does.
//!
//! `cargo bench -p integration-tests --bench calib_solve`
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "bench set-up: a panic aborts the bench")]

use criterion::{Criterion, criterion_group, criterion_main};
use estimator::calib::ours::{OursConfig, solve_ours};
use estimator::calib::paper::{PaperConfig, solve_paper};
use sim::calib::{CalibGeometry, CalibProtocol, NoiseUnits, generate_calibration};

fn bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("calib_solve_729");
    for units in [NoiseUnits::Millimetre, NoiseUnits::Metre] {
        let d = generate_calibration(&CalibProtocol {
            geometry: CalibGeometry::default(),
            n_e: 3,
            n_t: 4,
            sigma: 0.01,
            units,
            pixel_sigma_px: 0.0,
            seed: 7,
        })
        .expect("protocol");
        let obs = &d.observations[..729.min(d.observations.len())];
        assert_eq!(obs.len(), 729, "the scene keeps at least 729 observations");
        let name = units.name();
        group.bench_function(format!("paper_{name}"), |b| {
            b.iter(|| solve_paper(&d.setup, obs, &PaperConfig::default()).expect("paper"))
        });
        let cfg = OursConfig { noise: d.noise, ..OursConfig::default() };
        group.bench_function(format!("ours_{name}"), |b| b.iter(|| solve_ours(&d.setup, obs, &cfg).expect("ours")));
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
