//! Cost of one stereo 640×480 RGB frame (1.84 MB) through the frame service, in one process:
//! loan (zeroed) + copy of the pixels + send + receive, against a plain memcpy of the same bytes. `cargo bench -p hw-io --bench
//! frame_transport`; figures in docs/frames.md.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "benchmark code")]

use criterion::{Criterion, criterion_group, criterion_main};
use hw_io::frame::{FrameFormat, ImageLayout, PixelFormat};
use hw_io::ipc::{FramePublisher, FrameSubscriber, PublisherOptions};

fn bench(c: &mut Criterion) {
    let name = format!("comanip-bench/{}/frames", std::process::id());
    let format = FrameFormat::new(2, ImageLayout::packed(640, 480, PixelFormat::Rgb8).unwrap()).unwrap();
    let opts = PublisherOptions::frames();
    let mut sub = FrameSubscriber::connect(&name, &opts).unwrap();
    let mut publisher = FramePublisher::create(&name, format, 0, &opts).unwrap();
    let source: Vec<u8> = (0..format.payload_bytes()).map(|i| (i % 251) as u8).collect();
    let mut t = 0u64;
    c.bench_function("stereo 640x480 rgb: loan + copy + send + receive", |b| {
        b.iter(|| {
            t += 33_333_333;
            let mut slot = publisher.loan().unwrap();
            slot.pixels_mut().copy_from_slice(&source);
            slot.send(t, 16_000_000).unwrap();
            let frame = sub.try_recv().unwrap().unwrap();
            let p = frame.pixels();
            (p[0], p[p.len() - 1])
        });
    });
    c.bench_function("stereo 640x480 rgb: memcpy of the same bytes", |b| {
        let mut dst = vec![0u8; source.len()];
        b.iter(|| {
            dst.copy_from_slice(&source);
            (dst[0], dst[dst.len() - 1])
        });
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
