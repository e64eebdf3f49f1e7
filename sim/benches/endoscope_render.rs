//! Rendering speed of the simulated stereo endoscope (`docs/vision.md`): one stereo frame,
//! 640×480 per eye, the default realism set (and, for comparison, none and all), the demo
//! motion at a new time each iteration. PNG encoding is not included.
//!
//! `cargo bench -p sim --bench endoscope_render`

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use sim::endoscope::config::{RealismConfig, SmokeConfig};
use sim::endoscope::{DemoMotion, EndoscopeConfig, StereoFrame, StereoRenderer};

fn bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("endoscope_stereo_frame_640x480");
    let default = RealismConfig::default();
    let all = RealismConfig {
        second_instrument: true,
        smoke: SmokeConfig { enabled: true, ..SmokeConfig::default() },
        ..default
    };
    for (name, realism) in [("default", default), ("none", RealismConfig::none()), ("all", all)] {
        let cfg = EndoscopeConfig { realism, ..EndoscopeConfig::default() };
        let mesh = match cfg.instrument.mesh() {
            Ok(m) => m,
            Err(e) => panic!("mesh: {e}"),
        };
        let mut renderer = match StereoRenderer::new(cfg.clone(), mesh) {
            Ok(r) => r,
            Err(e) => panic!("renderer: {e}"),
        };
        let motion = DemoMotion::default();
        let scene = |t| motion.state_at(t);
        let mut frame = StereoFrame::default();
        let mut n = 0u64;
        group.bench_function(name, |b| {
            b.iter(|| {
                n += 1;
                let t = 1_000_000_000 + n * 33_333_333;
                if let Err(e) = renderer.render_into(t, &scene, &mut frame) {
                    panic!("render: {e}");
                }
                black_box(&frame);
            })
        });
    }
    group.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(40);
    targets = bench
}
criterion_main!(benches);
