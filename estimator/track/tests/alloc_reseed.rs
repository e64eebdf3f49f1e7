//! The tracker's re-seeding from a detected shaft axis allocates nothing after start-up, in any
//! thread (its own test binary: the counting allocator is global, and the harness itself
//! allocates when another test of the same binary finishes).
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code")]

mod common;
#[path = "common/counting.rs"]
mod counting;

use std::sync::atomic::Ordering;

use common::*;
use counting::{COUNT, ON};
use track::{Mode, Particle, Tracker, TrackerConfig};

#[test]
fn re_seeding_from_a_detected_axis_allocates_nothing() {
    let model = model();
    let cams = cameras(&model);
    let mut c = TrackerConfig::new(Mode::Ours, W, H);
    c.particles = 300;
    // Tried at every frame (the trigger above any fit), accepted when it is better.
    c.proposal = Some(track::ProposalConfig { trigger_share: 1.0, ..track::ProposalConfig::default() });
    let mut t = Tracker::new(c, model.clone()).unwrap();
    let frames: Vec<[Vec<u8>; 2]> = (0..12)
        .map(|k| images(&model, &cams, &Particle { joints: joints(k), jaw_rad: 0.2, camera_delta: [0.0; 6] }, k as u32))
        .collect();
    let axis = |k: usize| {
        let f = model.instrument_in_base(&joints(k)).unwrap();
        let (o, d) = (f.translation.vector, f.rotation * nalgebra::Vector3::z());
        Some(track::ShaftAxis { point_m: o, dir: d, ends_m: Some([o - d * 0.04, o]) })
    };
    for (k, f) in frames.iter().enumerate().take(7) {
        t.set_shaft_axis(axis(k));
        t.step(&input(&cams, k, f)).unwrap();
    }
    let axes: Vec<_> = (7..12).map(axis).collect();
    COUNT.store(0, Ordering::SeqCst);
    ON.store(true, Ordering::SeqCst);
    t.set_shaft_axis(axes[0]);
    let before = COUNT.load(Ordering::SeqCst);
    let mut tried = 0;
    let mut log = [(0usize, false, 0u8); 5];
    for (k, f) in frames.iter().enumerate().skip(7) {
        t.set_shaft_axis(axes[k - 7]);
        let e = t.step(&input(&cams, k, f)).unwrap();
        tried += usize::from(t.last_reseed_share().is_finite());
        log[k - 7] = (COUNT.load(Ordering::SeqCst), e.reseeded_from_vision, e.status as u8);
    }
    ON.store(false, Ordering::SeqCst);
    // One allocation appears once in these frames (never per frame), with or without the
    // re-seeding: rayon's. Each parallel loop started from outside the pool pushes a job onto
    // rayon's shared injector queue, which allocates a new block every few dozen jobs (about
    // one allocation every six frames; measured in session 14: 0 allocations when the same
    // steps run inside a pool worker, `ThreadPool::install`). Running the tracking thread as a
    // worker (`use_current_thread`) removed it here but made other, load-dependent one-off
    // allocations appear (6 of 18 test runs under load), so the product keeps the injector
    // (docs/tracking.md "Missing"). What this test holds is that the re-seeding adds none.
    let n = COUNT.load(Ordering::SeqCst);
    assert!(before == 0 && n <= 1, "{log:?}: {n} allocations in 5 steady-state frames with re-seeding");
    assert_eq!(tried, 5, "re-seeding was tried at every counted frame");
}
