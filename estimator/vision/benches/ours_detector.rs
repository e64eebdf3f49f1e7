//! Our shaft detector's time per 640×480 frame (one core): a synthetic frame with one shaft
//! over textured tissue with vessels and folds (`vision::synth`), and the same tissue without
//! a shaft (the "nothing found" path, where every hypothesis is checked and refused).

use criterion::{Criterion, criterion_group, criterion_main};
use std::hint::black_box;
use vision::ours::{OursConfig, OursDetector};
use vision::synth::{Cylinder, Scene, render};
use vision::{RgbView, ShaftDetector};

fn bench(c: &mut Criterion) {
    let k = vision::synth::endoscope_camera();
    let shaft = Cylinder {
        point_m: [-0.004, 0.002, 0.07],
        direction: [0.9, 0.35, 0.25],
        radius_m: 0.004,
        extent_m: [0.0, 0.4],
        albedo: 0.8,
    };
    let with = render(&k, &Scene { shafts: vec![shaft], seed: 3, vessels: true, folds: true, noise: 4.0 });
    let without = render(&k, &Scene { shafts: vec![], seed: 3, vessels: true, folds: true, noise: 4.0 });
    let mut det = match OursDetector::new(k, OursConfig::default()) {
        Ok(d) => d,
        Err(e) => panic!("detector: {e}"),
    };
    let mut g = c.benchmark_group("ours_detector");
    for (name, img) in [("shaft_640x480", &with), ("tissue_only_640x480", &without)] {
        let view = match RgbView::new(640, 480, img) {
            Ok(v) => v,
            Err(e) => panic!("image: {e}"),
        };
        g.bench_function(name, |b| b.iter(|| black_box(det.detect(black_box(&view)).map(|v| v.len()))));
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
