//! The detection benchmark end to end on a small run: twin traces decoded as the daemon does,
//! the four settings scored on the same lines, the motion-only bound, the report and figures.

use comanip_bench::plots;
use comanip_bench::report::{DetectionOptions, run_detection};
use comanip_bench::trace::PLACEMENTS;
use hw_io::rt_alloc::{RtPoolAllocator, count_thread_allocs};

#[global_allocator]
static ALLOC: RtPoolAllocator = RtPoolAllocator::new();

#[test]
fn a_small_detection_benchmark_scores_every_setting_on_the_same_traces() {
    // The allocation counter this benchmark relies on does count on this thread.
    let (n, v) = count_thread_allocs(|| vec![0u8; 64]);
    assert!(n >= 1 && v.len() == 64);

    let opts = DetectionOptions {
        seeds: vec![7],
        cycles_per_trace: 3,
        placements: vec![PLACEMENTS[0], PLACEMENTS[1]],
        timeline_s: 20.0,
        ..Default::default()
    };
    let report = run_detection(&opts, &|| {}).expect("benchmark");
    assert_eq!(report.specs.len(), 2);
    assert_eq!(report.settings.len(), 4);
    let keys: Vec<&str> = report.settings.iter().map(|s| s.setting.key).collect();
    assert_eq!(keys, ["paper", "fast", "fast_length", "fast_memory"]);

    // One motion-only bound per true insertion, each within its cycle.
    assert_eq!(report.bounds.iter().map(Vec::len).sum::<usize>(), 6);
    for b in report.bounds.iter().flatten() {
        let ins = b.insertion_s.expect("the motion locates every fulcrum");
        assert!(ins > 0.0 && ins < 12.0, "{ins}");
        assert!(b.envelope_m > 0.0 && b.envelope_m < 0.01, "{}", b.envelope_m);
    }
    for s in &report.settings {
        let h = s.headline();
        assert_eq!(h.insertions, 6, "{}", h.key);
        assert_eq!(s.allocations, 0, "{} allocated in its steps", h.key);
        assert!(s.steps > 20_000, "{}: {} steps", h.key, s.steps);
        assert!(s.step_times.count() > 0, "{}: steps were not timed", h.key);
    }
    let fast = report.settings[1].headline();
    assert_eq!(fast.insertions_detected, 6, "fast mode missed an insertion");
    assert_eq!(fast.false_detections, 0);
    assert_eq!(fast.extractions_missed, 0);
    // With the length known, extraction is a matter of milliseconds, not of lateral motion.
    let with_length = report.settings[2].headline();
    assert!(
        with_length.extraction.mean < fast.extraction.mean,
        "{:?} vs {:?}",
        with_length.extraction,
        fast.extraction
    );

    let md = report.markdown();
    for row in ["insertions detected", "false detections", "motion-only bound", "Trocar inter-distances"] {
        assert!(md.contains(row), "report lacks {row}");
    }

    let dir = tempfile::tempdir().unwrap();
    plots::delay_histograms(&report, &dir.path().join("d.svg")).unwrap();
    plots::timeline(&report.timeline, &dir.path().join("t.svg")).unwrap();
    for f in ["d.svg", "t.svg"] {
        let text = std::fs::read_to_string(dir.path().join(f)).unwrap();
        assert!(text.contains("<svg") && text.len() > 2000, "{f} is not a figure");
    }
}
