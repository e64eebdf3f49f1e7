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

/// The counter is global: the tests take turns.
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

#[test]
fn the_counter_sees_allocations_and_steps_allocate_nothing() {
    let _turn = SERIAL.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
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

#[test]
fn re_seeding_from_a_detected_axis_allocates_nothing() {
    let _turn = SERIAL.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    let model = model();
    let cams = cameras(&model);
    let mut c = TrackerConfig::new(Mode::Ours, W, H);
    c.particles = 300;
    // Tried at every frame (the trigger above any fit), accepted when it is better.
    c.proposal = Some(track::ProposalConfig { trigger_share: 1.0, ..track::ProposalConfig::default() });
    let mut t = Tracker::new(c, model.clone()).unwrap();
    let frames: Vec<[Vec<u8>; 2]> = (0..8)
        .map(|k| images(&model, &cams, &Particle { joints: joints(k), jaw_rad: 0.2, camera_delta: [0.0; 6] }, k as u32))
        .collect();
    let axis = |k: usize| {
        let f = model.instrument_in_base(&joints(k)).unwrap();
        let (o, d) = (f.translation.vector, f.rotation * nalgebra::Vector3::z());
        Some(track::ShaftAxis { point_m: o, dir: d, ends_m: Some([o - d * 0.04, o]) })
    };
    for (k, f) in frames.iter().enumerate().take(3) {
        t.set_shaft_axis(axis(k));
        t.step(&input(&cams, k, f)).unwrap();
    }
    let axes: Vec<_> = (3..8).map(axis).collect();
    COUNT.store(0, Ordering::SeqCst);
    ON.store(true, Ordering::SeqCst);
    let mut tried = 0;
    for (k, f) in frames.iter().enumerate().skip(3) {
        t.set_shaft_axis(axes[k - 3]);
        t.step(&input(&cams, k, f)).unwrap();
        tried += usize::from(t.last_reseed_share().is_finite());
    }
    ON.store(false, Ordering::SeqCst);
    assert_eq!(COUNT.load(Ordering::SeqCst), 0, "allocations in 5 steady-state frames with re-seeding");
    assert_eq!(tried, 5, "re-seeding was tried at every counted frame");
}
