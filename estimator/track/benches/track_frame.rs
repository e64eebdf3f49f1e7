//! `track_frame`: one `Tracker::step` on a stereo 640×480 frame (the synthetic scene of the
//! tests: the instrument's silhouette on a noisy background), ours at 250 / 1000 / 2000
//! particles and the paper's mode at 100. `cargo bench -p track --bench track_frame`.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "bench code")]

#[path = "../tests/common/mod.rs"]
mod common;

use common::*;
use criterion::{Criterion, criterion_group, criterion_main};
use track::{Mode, Particle, Tracker, TrackerConfig};

fn bench(c: &mut Criterion) {
    let model = model();
    let cams = cameras(&model);
    let frames: Vec<[Vec<u8>; 2]> = (0..8)
        .map(|k| images(&model, &cams, &Particle { joints: joints(k), jaw_rad: 0.2, camera_delta: [0.0; 6] }, k as u32))
        .collect();
    let mut g = c.benchmark_group("track_frame");
    g.sample_size(10);
    for (mode, n) in [(Mode::Ours, 250), (Mode::Ours, 1000), (Mode::Ours, 2000), (Mode::Paper, 100)] {
        let mut cfg = TrackerConfig::new(mode, W, H);
        cfg.particles = n;
        let mut t = Tracker::new(cfg, model.clone()).unwrap();
        t.step(&input(&cams, 0, &frames[0])).unwrap();
        let mut k = 1usize;
        g.bench_function(format!("{mode:?}_{n}").to_lowercase(), |b| {
            b.iter(|| {
                let f = &frames[k % frames.len()];
                let e = t.step(&input(&cams, k % frames.len(), f)).unwrap();
                k += 1;
                e
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
