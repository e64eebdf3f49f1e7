//! `SimRobot::on_sync` allocates nothing in steady state: a counting global allocator
//! watches it over thousands of SYNCs (insertions and extractions included). Only endless
//! mode's next scenario may allocate.

use sim::twin::{SimRobot, TwinConfig};

#[global_allocator]
static GLOBAL: hw_io::rt_alloc::RtPoolAllocator = hw_io::rt_alloc::RtPoolAllocator::new();

fn count_allocations<T>(f: impl FnOnce() -> T) -> (usize, T) {
    let (n, out) = hw_io::rt_alloc::count_thread_allocs(f);
    (n as usize, out)
}

fn config(endless: bool) -> TwinConfig {
    let mut c = TwinConfig { endless, ..TwinConfig::default() };
    c.scenario.cycles = 1;
    c.scenario.inside_s = [1.5, 2.0];
    c.scenario.outside_s = [1.0, 1.2];
    c
}

/// Runs `n` SYNCs; returns (frames, events).
fn syncs(robot: &mut SimRobot, n: u64) -> (usize, usize) {
    let (mut frames, mut events) = (0, 0);
    for i in 0..n {
        let counter = (i % 240) as u8 + 1;
        match robot.on_sync(counter, 1_700_000_000_000_000 + i * 1000) {
            Ok(Some(f)) => frames += f.len(),
            Ok(None) => break,
            Err(e) => panic!("{e}"),
        }
        events += robot.events().len();
    }
    (frames, events)
}

#[test]
fn the_counter_sees_allocations() {
    let (n, _) = count_allocations(|| std::hint::black_box((0..100).collect::<Vec<u64>>()));
    assert!(n >= 1);
}

#[test]
fn on_sync_does_not_allocate_over_a_whole_scenario() {
    let mut robot = SimRobot::new(&config(false)).unwrap();
    let len = robot.scenario().truth.len() as u64;
    let (n, (frames, events)) = count_allocations(|| syncs(&mut robot, len + 10));
    assert!(robot.is_done());
    assert_eq!(events, 2, "one insertion and one extraction were crossed");
    assert!(frames as u64 >= 3 * len);
    assert_eq!(n, 0, "{n} allocations in {len} SYNCs");
}

#[test]
fn endless_mode_allocates_only_when_it_starts_the_next_scenario() {
    let mut robot = SimRobot::new(&config(true)).unwrap();
    let len = robot.scenario().truth.len() as u64;
    let (n, _) = count_allocations(|| syncs(&mut robot, len - 1));
    assert_eq!(n, 0);
    // The next SYNC starts the next scenario (allocating); the one after is steady again.
    syncs(&mut robot, 2);
    assert_eq!(robot.scenario_seed(), 2);
    let (n, _) = count_allocations(|| syncs(&mut robot, 3000));
    assert_eq!(n, 0);
}
