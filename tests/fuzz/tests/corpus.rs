//! Replays every committed seed (`tests/fuzz/corpus/<target>/`), every input the long fuzz run
//! added to them (`tests/fuzz/corpus-grown/<target>/`, merge-minimised) and every regression
//! input (`tests/fuzz/regressions/<target>/`, the crashes the fuzzers found, fixed since) through the
//! fuzz target bodies, on stable, in `cargo test --workspace`: a crash once found stays a
//! failing test. docs/fuzzing.md.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::path::{Path, PathBuf};

use comanip_fuzz::{TARGETS, Target};

// The acquisition target checks that the cycle path allocates nothing: it needs the counting
// allocator, as the fuzz target has.
#[global_allocator]
static GLOBAL: hw_io::rt_alloc::RtPoolAllocator = hw_io::rt_alloc::RtPoolAllocator::new();

fn dir(kind: &str, target: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(kind).join(target)
}

/// The files of `dir` (none when it does not exist), sorted.
fn files(dir: &Path) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(dir) else { return Vec::new() };
    let mut v: Vec<PathBuf> = entries.map(|e| e.unwrap().path()).filter(|p| p.is_file()).collect();
    v.sort();
    v
}

/// Runs `t` on every file of its corpus, grown corpus and regression directories; the count of
/// each.
fn replay(t: &Target) -> (usize, usize, usize) {
    let corpus = files(&dir("corpus", t.name));
    let grown = files(&dir("corpus-grown", t.name));
    let regressions = files(&dir("regressions", t.name));
    for f in corpus.iter().chain(&grown).chain(&regressions) {
        let data = std::fs::read(f).unwrap();
        let r = std::panic::catch_unwind(|| (t.run)(&data));
        assert!(r.is_ok(), "target {} panics on {}", t.name, f.display());
    }
    (corpus.len(), grown.len(), regressions.len())
}

#[test]
fn every_target_has_seeds() {
    for t in TARGETS {
        assert!(!files(&dir("corpus", t.name)).is_empty(), "no seed for target {}", t.name);
    }
}

#[test]
fn the_allocation_counter_is_active() {
    // Otherwise the acquisition target's no-allocation check would pass vacuously.
    assert!(comanip_fuzz::acquisition::allocation_counting_active());
}

macro_rules! replay_tests {
    ($($name:ident),* $(,)?) => {$(
        #[test]
        fn $name() {
            let t = comanip_fuzz::target(stringify!($name)).unwrap();
            let (seeds, grown, regressions) = replay(t);
            println!("{}: {seeds} seeds, {grown} grown, {regressions} regression inputs replayed", t.name);
        }
    )*};
}

replay_tests!(
    acquisition,
    candump,
    recording,
    fulcrumd_toml,
    simrobot_toml,
    calib_json,
    camera_yaml,
    ipc_sample,
    frame_header,
    detectors,
);

#[test]
fn the_replay_tests_cover_every_target() {
    // One replay test above per target: a new target must be added there too.
    let names = [
        "acquisition",
        "candump",
        "recording",
        "fulcrumd_toml",
        "simrobot_toml",
        "calib_json",
        "camera_yaml",
        "ipc_sample",
        "frame_header",
        "detectors",
    ];
    let mut all: Vec<&str> = TARGETS.iter().map(|t| t.name).collect();
    all.sort_unstable();
    let mut listed = names.to_vec();
    listed.sort_unstable();
    assert_eq!(all, listed);
}

#[test]
fn the_acquisition_checks_catch_a_valid_output_from_a_flagged_input() {
    // The invariant checks can fail: a valid output whose input was incomplete is refused.
    use controller::config::Config;
    use controller::cycle::{CycleInput, CycleOutput};
    use hw_io::ipc::{HealthFlags, OutputState};
    let cfg = Config::default();
    let input = CycleInput { counts: [0; 6], received_mask: 0b011, flags: HealthFlags::INCOMPLETE_CYCLE };
    let out = CycleOutput { state: OutputState::Outside, health: HealthFlags::INCOMPLETE_CYCLE, ..Default::default() };
    let r = std::panic::catch_unwind(|| comanip_fuzz::acquisition::check_output(&cfg, &input, &out));
    assert!(r.is_err());
}
