//! Rendering speed of the simulated stereo endoscope (`docs/vision.md`): one stereo frame,
//! 640×480 per eye, the default realism set (and, for comparison, none and all), the demo
//! motion at a new time each iteration. PNG encoding is not included.
//!
//! Two motions of the endoscope: `moving`, the demo motion (the endoscope drifts, so every
//! frame is seen from another pose and the tissue is rasterised again), and `still`, the
//! same scene with the endoscope arm held at its pose of t = 1 s (the instruments still
//! move; the renderer reuses each eye's rasterised tissue). The benchmark names without a
//! motion (`default`, `none`, `all`) are the moving ones, as before.
//!
//! `cargo bench -p sim --bench endoscope_render`

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use sim::endoscope::config::{RealismConfig, SmokeConfig};
use sim::endoscope::{DemoMotion, EndoscopeConfig, SceneState, StereoFrame, StereoRenderer};

fn bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("endoscope_stereo_frame_640x480");
    let default = RealismConfig::default();
    let all = RealismConfig {
        second_instrument: true,
        smoke: SmokeConfig { enabled: true, ..SmokeConfig::default() },
        ..default
    };
    let cases = [
        ("default", default, false),
        ("default_still", default, true),
        ("none", RealismConfig::none(), false),
        ("all", all, false),
        ("all_still", all, true),
    ];
    for (name, realism, still) in cases {
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
        let held = motion.state_at(1_000_000_000).ecm_joints;
        let scene = |t| {
            let mut s: SceneState = motion.state_at(t);
            if still {
                s.ecm_joints = held;
            }
            s
        };
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
