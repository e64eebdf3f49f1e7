//! Median time of one `Detector::step` in each mode, over a simulated surgeon (insertions,
//! pivoting, extractions, free motion), and of the forward kinematics.
//!
//! `cargo bench -p integration-tests --bench detector_step`
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "bench set-up: a panic aborts the bench")]

use criterion::{BatchSize, Criterion, criterion_group, criterion_main};
use estimator::kinematics::{Achilles, AchillesConfig};
use estimator::trocar::{Detector, DetectorConfig, DetectorMode, FastConfig, LineSample};
use sim::scenario::{ScenarioConfig, generate};

fn lines() -> Vec<LineSample> {
    let s = generate(&ScenarioConfig { seed: 3, cycles: 6, ..Default::default() });
    s.measured.iter().map(|l| LineSample::new(l.wrist_base_m, l.axis_base)).collect()
}

fn bench_modes(c: &mut Criterion) {
    let lines = lines();
    let configs = [
        ("paper", DetectorConfig { mode: DetectorMode::Paper, ..Default::default() }),
        ("fast", DetectorConfig::default()),
        (
            "fast_length_memory",
            DetectorConfig {
                fast: FastConfig { instrument_length_m: Some(0.30), trocar_memory: true, ..Default::default() },
                ..Default::default()
            },
        ),
    ];
    let mut group = c.benchmark_group("detector_step");
    for (name, cfg) in configs {
        // One iteration = one step; the detector runs through the whole scenario in order,
        // so every phase (outside, inserting, inside, extracting) is sampled in proportion.
        group.bench_function(name, |b| {
            let mut d = Detector::new(&cfg).unwrap();
            let mut i = 0usize;
            b.iter(|| {
                if i == lines.len() {
                    i = 0;
                    d = Detector::new(&cfg).unwrap();
                }
                let e = d.step(std::hint::black_box(&lines[i]));
                i += 1;
                e
            })
        });
    }
    group.finish();

    let arm = Achilles::new(&AchillesConfig::default()).unwrap();
    c.bench_function("forward_kinematics", |b| {
        b.iter_batched(
            || [0.1, 0.9, 0.4, 0.2, 0.3, 0.1],
            |q| arm.forward(std::hint::black_box(&q)),
            BatchSize::SmallInput,
        )
    });
}

criterion_group!(benches, bench_modes);
criterion_main!(benches);
