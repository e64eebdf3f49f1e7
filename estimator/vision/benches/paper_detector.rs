//! One 640×480 frame through the calibration paper's detector (11×11 low-pass, EDLines,
//! pairing, middle line): a synthetic scene with a slanted shaft on a textured, noisy
//! background with a few rectangles.

use criterion::{Criterion, criterion_group, criterion_main};
use estimator::calib::Intrinsics;
use std::hint::black_box;
use vision::detect::{RgbView, ShaftDetector};
use vision::paper::PaperDetector;

const W: usize = 640;
const H: usize = 480;

fn scene() -> Vec<u8> {
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut noise = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 40) as f64 / (1u64 << 24) as f64 - 0.5
    };
    // Shaft: centre line through (300, 0) and (380, 479), 46 px wide, 4×4 supersampled.
    let (p, q) = ([300.0f64, -10.0], [380.0f64, 490.0]);
    let (dx, dy) = (q[0] - p[0], q[1] - p[1]);
    let l = dx.hypot(dy);
    let n = [-dy / l, dx / l];
    let mut out = Vec::with_capacity(3 * W * H);
    for y in 0..H {
        for x in 0..W {
            let mut cover = 0.0;
            for sy in 0..4 {
                for sx in 0..4 {
                    let (u, v) = (x as f64 + (sx as f64 - 1.5) / 4.0, y as f64 + (sy as f64 - 1.5) / 4.0);
                    if ((u - p[0]) * n[0] + (v - p[1]) * n[1]).abs() <= 23.0 {
                        cover += 1.0 / 16.0;
                    }
                }
            }
            let mut bg = 110.0 + 25.0 * (x as f64 / 9.0).sin() * (y as f64 / 13.0).cos();
            if (60..180).contains(&x) && (300..420).contains(&y) || (480..600).contains(&x) && (40..140).contains(&y) {
                bg += 60.0;
            }
            let g = bg * (1.0 - cover) + 40.0 * cover + 10.0 * noise();
            let g = g.clamp(0.0, 255.0) as u8;
            out.extend_from_slice(&[g, g, g]);
        }
    }
    out
}

fn bench(c: &mut Criterion) {
    let k = Intrinsics {
        fx: 500.0,
        fy: 500.0,
        cx: 319.5,
        cy: 239.5,
        skew: 0.0,
        width: W as u32,
        height: H as u32,
        distortion: [-0.1, 0.01, 0.0, 0.0, 0.0],
    };
    let bytes = scene();
    let Ok(image) = RgbView::new(W, H, &bytes) else { return };
    let mut det = PaperDetector::new(k);
    let mut group = c.benchmark_group("paper_detector");
    group.bench_function("detect_640x480", |b| b.iter(|| black_box(det.detect(black_box(&image)))));
    group
        .bench_function("segments_640x480", |b| b.iter(|| black_box(det.segments(black_box(&image)).map(|s| s.len()))));
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
