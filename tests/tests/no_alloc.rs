//! The 1 kHz path allocates nothing: a counting global allocator watches `Detector::step`
//! over 100 000 steps of a simulated surgeon (insertions, extractions, free motion, and bad
//! samples), in both modes and with every fast-mode option on.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use estimator::kinematics::{Achilles, AchillesConfig};
use estimator::trocar::{Detector, DetectorConfig, DetectorMode, FastConfig, LineSample};
use nalgebra::Vector3;
use sim::scenario::{ScenarioConfig, generate};

#[global_allocator]
static GLOBAL: hw_io::rt_alloc::RtPoolAllocator = hw_io::rt_alloc::RtPoolAllocator::new();

/// Counts the allocations `f` makes on this thread.
fn count_allocations(f: impl FnOnce()) -> usize {
    hw_io::rt_alloc::count_thread_allocs(f).0 as usize
}

#[test]
fn the_counter_sees_allocations() {
    // Guard against a test that passes because counting is broken.
    let n = count_allocations(|| {
        let v: Vec<u64> = (0..100).collect();
        std::hint::black_box(v);
    });
    assert!(n >= 1);
}

fn run(cfg: DetectorConfig) {
    let scenario = generate(&ScenarioConfig { seed: 5, cycles: 10, ..Default::default() });
    let mut lines: Vec<LineSample> = scenario.measured.clone();
    assert!(lines.len() >= 100_000, "{} samples", lines.len());
    lines.truncate(100_000);
    // Sprinkle bad samples: they take the rejection path.
    for k in (1000..lines.len()).step_by(9973) {
        lines[k] = LineSample::new(Vector3::new(f64::NAN, 0.0, 0.0), Vector3::z());
    }
    let arm = Achilles::new(&AchillesConfig::default()).unwrap();
    let mut detector = Detector::new(&cfg).unwrap();
    let mut changes = 0usize;
    let mut prev = false;
    let n = count_allocations(|| {
        for (k, l) in lines.iter().enumerate() {
            // Forward kinematics is on the same path: run it too.
            let q = [0.01 * (k % 100) as f64, 0.8, 0.4, 0.1, 0.2, 0.3];
            std::hint::black_box(arm.forward(&q).ok());
            let e = detector.step(l);
            if e.state.is_inside() != prev {
                changes += 1;
                prev = e.state.is_inside();
            }
        }
    });
    assert_eq!(n, 0, "{:?}: {n} allocations in 100 000 steps", cfg.mode);
    assert!(changes >= 10, "{:?}: the run must exercise insertions and extractions ({changes})", cfg.mode);
}

#[test]
fn paper_mode_step_allocates_nothing() {
    run(DetectorConfig { mode: DetectorMode::Paper, ..Default::default() });
}

#[test]
fn fast_mode_step_allocates_nothing() {
    run(DetectorConfig::default());
    run(DetectorConfig {
        fast: FastConfig { instrument_length_m: Some(0.30), trocar_memory: true, ..Default::default() },
        ..Default::default()
    });
}
