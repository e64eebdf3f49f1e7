//! `Tracker::step` in our mode allocates nothing after start-up, in any thread: a counting
//! global allocator (all threads, rayon's workers included) watches steady-state frames.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]

mod common;
#[path = "common/counting.rs"]
mod counting;

use std::sync::atomic::Ordering;

use common::*;
use counting::{COUNT, ON};
use track::{Mode, Particle, Tracker, TrackerConfig};

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
    let mut t = Tracker::new(c, model.clone()).unwrap();
    let frames: Vec<[Vec<u8>; 2]> = (0..8)
        .map(|k| images(&model, &cams, &Particle { joints: joints(k), jaw_rad: 0.2, camera_delta: [0.0; 6] }, k as u32))
        .collect();
    // Start-up: the first frames (rayon's pool starts).
    for (k, f) in frames.iter().enumerate().take(3) {
        t.step(&input(&cams, k, f)).unwrap();
    }
    COUNT.store(0, Ordering::SeqCst);
    ON.store(true, Ordering::SeqCst);
    let mut published = 0;
    for (k, f) in frames.iter().enumerate().skip(3) {
        published += usize::from(t.step(&input(&cams, k, f)).unwrap().pose.is_some());
    }
    ON.store(false, Ordering::SeqCst);
    assert_eq!(COUNT.load(Ordering::SeqCst), 0, "allocations in 5 steady-state frames");
    assert!(published >= 4, "the frames were tracked ({published} poses), not skipped");
}
