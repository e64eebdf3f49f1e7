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
use track::{Mode, Tracker, TrackerConfig};

/// Frames after start-up whose allocations are counted.
const COUNTED: usize = 30;

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
    let images = pose_images(&model, &cams);
    let frame = |n: usize| back_and_forth(&cams, &images, n);
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
