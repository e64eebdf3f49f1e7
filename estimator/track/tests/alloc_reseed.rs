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
use track::{Mode, Tracker, TrackerConfig};

/// Frames after start-up whose allocations are counted.
const COUNTED: usize = 30;
/// Start-up frames (not counted).
const WARM: usize = 7;

#[test]
fn re_seeding_from_a_detected_axis_allocates_nothing() {
    let model = model();
    let cams = cameras(&model);
    let mut c = TrackerConfig::new(Mode::Ours, W, H);
    c.particles = 300;
    c.threads = 4;
    // Tried at every frame (the trigger above any fit), accepted when it is better.
    c.proposal = Some(track::ProposalConfig { trigger_share: 1.0, ..track::ProposalConfig::default() });
    let mut t = Tracker::new(c, model.clone()).unwrap();
    let images = pose_images(&model, &cams);
    let frame = |n: usize| back_and_forth(&cams, &images, n);
    let axis = |k: usize| {
        let f = model.instrument_in_base(&joints(k)).unwrap();
        let (o, d) = (f.translation.vector, f.rotation * nalgebra::Vector3::z());
        Some(track::ShaftAxis { point_m: o, dir: d, ends_m: Some([o - d * 0.04, o]) })
    };
    for n in 0..WARM {
        t.set_shaft_axis(axis(pose_of_frame(n)));
        t.step(&frame(n)).unwrap();
    }
    let axes: Vec<_> = (WARM..WARM + COUNTED).map(|n| axis(pose_of_frame(n))).collect();
    COUNT.store(0, Ordering::SeqCst);
    ON.store(true, Ordering::SeqCst);
    let mut tried = 0;
    let mut reseeded = 0;
    let mut log = [(0usize, false, 0u8); COUNTED];
    for (i, n) in (WARM..WARM + COUNTED).enumerate() {
        t.set_shaft_axis(axes[i]);
        let e = t.step(&frame(n)).unwrap();
        tried += usize::from(t.last_reseed_share().is_finite());
        reseeded += usize::from(e.reseeded_from_vision);
        log[i] = (COUNT.load(Ordering::SeqCst), e.reseeded_from_vision, e.status as u8);
    }
    ON.store(false, Ordering::SeqCst);
    // No allocation at all, in any thread: the tracker's loops run on its own worker threads,
    // handed over without a job queue (`track::workers`).
    let n = COUNT.load(Ordering::SeqCst);
    assert_eq!(n, 0, "{log:?}: {n} allocations in {COUNTED} steady-state frames with re-seeding");
    assert_eq!(tried, COUNTED, "re-seeding was tried at every counted frame");
    eprintln!("re-seeded from vision at {reseeded} of {COUNTED} counted frames");
}
