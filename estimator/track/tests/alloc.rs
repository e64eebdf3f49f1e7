//! `Tracker::step` in our mode allocates nothing after start-up, in any thread: a counting
//! global allocator (all threads, the tracker's worker threads included) watches 30
//! steady-state frames.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]

mod common;
#[path = "common/counting.rs"]
mod counting;

use std::sync::atomic::Ordering;

use common::*;
use counting::{COUNT, ON};
use track::{FrameInput, Mode, Particle, Tracker, TrackerConfig};

/// Frames after start-up whose allocations are counted.
const COUNTED: usize = 30;

/// The pose index of frame `n`: back and forth over `joints(0..=8)` (the instrument stays in
/// view however many frames are counted).
fn pose_of_frame(n: usize) -> usize {
    let k = n % 16;
    if k <= 8 { k } else { 16 - k }
}

#[test]
fn the_counter_sees_allocations_and_steps_allocate_nothing() {
    ON.store(true, Ordering::SeqCst);
    let v: Vec<u64> = std::hint::black_box(vec![1, 2, 3]);
    ON.store(false, Ordering::SeqCst);
    assert!(COUNT.load(Ordering::SeqCst) >= 1 && v.len() == 3);

    let model = model();
    let cams = cameras(&model);
    let mut c = TrackerConfig::new(Mode::Ours, W, H);
    c.particles = 300;
    // More threads than this machine may have: the hand-over between them is what is counted.
    c.threads = 4;
    let mut t = Tracker::new(c, model.clone()).unwrap();
    let images: Vec<[Vec<u8>; 2]> = (0..=8)
        .map(|k| images(&model, &cams, &Particle { joints: joints(k), jaw_rad: 0.2, camera_delta: [0.0; 6] }, k as u32))
        .collect();
    let frame = |n: usize| {
        let f = &images[pose_of_frame(n)];
        FrameInput {
            encoder_rad: joints(pose_of_frame(n)),
            cameras: cams,
            rgb: [&f[0], &f[1]],
            time_ns: Some(n as u64 * 100_000_000),
        }
    };
    // Start-up: the first frames (the worker threads start at the first).
    for n in 0..3 {
        t.step(&frame(n)).unwrap();
    }
    COUNT.store(0, Ordering::SeqCst);
    ON.store(true, Ordering::SeqCst);
    let mut published = 0;
    for n in 3..3 + COUNTED {
        published += usize::from(t.step(&frame(n)).unwrap().pose.is_some());
    }
    ON.store(false, Ordering::SeqCst);
    assert_eq!(COUNT.load(Ordering::SeqCst), 0, "allocations in {COUNTED} steady-state frames");
    assert!(published >= COUNTED * 4 / 5, "the frames were tracked ({published} poses), not skipped");
}
