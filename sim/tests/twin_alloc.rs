//! `SimRobot::on_sync` allocates nothing in steady state: a counting global allocator
//! watches it over thousands of SYNCs (insertions and extractions included). Only endless
//! mode's next scenario may allocate.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use sim::twin::{SimRobot, TwinConfig};

struct Counting;

thread_local! {
    // Per thread: tests running in parallel do not mix their counts.
    static ARMED: Cell<bool> = const { Cell::new(false) };
    static ALLOCATIONS: Cell<usize> = const { Cell::new(0) };
}

fn bump() {
    if ARMED.with(|a| a.get()) {
        ALLOCATIONS.with(|c| c.set(c.get() + 1));
    }
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        bump();
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        bump();
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

fn count_allocations<T>(f: impl FnOnce() -> T) -> (usize, T) {
    let before = ALLOCATIONS.with(|c| c.get());
    ARMED.with(|a| a.set(true));
    let out = f();
    ARMED.with(|a| a.set(false));
    (ALLOCATIONS.with(|c| c.get()) - before, out)
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
