//! The 1 kHz receive path allocates nothing: in-process send/recv, decoding, SYNC
//! tracking, joint assembly and counts-to-radians; and candump reading after warm-up.
//!
//! A counting global allocator counts the allocations of the current thread only.

use std::time::Duration;

use hw_io::can::candump::CandumpReader;
use hw_io::can::{CanBus, EncoderConfig, InProcessBus, JointAssembler, Message, NodeId, SyncCounter, SyncSource};

#[global_allocator]
static GLOBAL: hw_io::rt_alloc::RtPoolAllocator = hw_io::rt_alloc::RtPoolAllocator::new();

fn allocations_in(f: impl FnOnce()) -> u64 {
    hw_io::rt_alloc::count_thread_allocs(f).0
}

#[test]
fn the_counter_counts() {
    assert!(allocations_in(|| drop(std::hint::black_box(vec![1u8; 10]))) >= 1);
}

#[test]
fn control_cycle_on_the_in_process_bus_allocates_nothing() {
    let config = EncoderConfig::default();
    let bus = InProcessBus::with_capacity(4, 16);
    let mut controller = bus.endpoint().unwrap();
    let mut encoders = bus.endpoint().unwrap(); // one endpoint playing all three nodes
    let mut sync = SyncSource::new();
    let mut tracker = SyncCounter::new();
    let mut joints = JointAssembler::from_config(&config).unwrap();
    let nodes = [1, 2, 3].map(|k| NodeId::new(k).unwrap());
    let mut checksum = 0.0;

    let n = allocations_in(|| {
        for cycle in 0..2000i32 {
            controller.send(&sync.next_frame()).unwrap();
            joints.start_cycle();
            // Encoder side: see the SYNC, answer with three TPDOs.
            let rx = encoders.recv_timeout(Duration::from_millis(100)).unwrap().unwrap();
            let Ok(Message::Sync { counter }) = Message::decode(&rx.frame) else { panic!() };
            tracker.observe(counter).unwrap();
            for (i, node) in nodes.iter().enumerate() {
                let counts = [cycle * 10 + 2 * i as i32, cycle * 10 + 2 * i as i32 + 1];
                encoders.send(&Message::Tpdo { node: *node, counts }.encode().unwrap()).unwrap();
            }
            // Controller side: collect until complete.
            while !joints.is_complete() {
                let rx = controller.recv_timeout(Duration::from_millis(100)).unwrap().unwrap();
                joints.accept(&Message::decode(&rx.frame).unwrap()).unwrap();
            }
            let q = config.counts_to_rad(&joints.counts().unwrap());
            checksum += q[5];
        }
        // A timed-out receive allocates nothing either.
        assert!(controller.recv_timeout(Duration::from_millis(2)).unwrap().is_none());
    });
    assert_eq!(n, 0, "the control cycle allocated {n} times");
    assert!(checksum > 0.0);
    assert_eq!(controller.dropped_rx_frames() + encoders.dropped_rx_frames(), 0);
}

#[test]
fn candump_reading_allocates_nothing_after_warm_up() {
    let mut log = String::new();
    for i in 0..1000u64 {
        log.push_str(&format!("({}.{:06}) vcan0 181#0102030405060708\n", 1_700_000_000 + i / 1000, i % 1000 * 1000));
    }
    let mut reader = CandumpReader::new(log.as_bytes());
    reader.next_record().unwrap().unwrap(); // warm-up: the line buffer grows once
    let mut frames = 0;
    let n = allocations_in(|| {
        while let Some(rec) = reader.next_record().unwrap() {
            frames += usize::from(rec.timed.frame.dlc() == 8);
        }
    });
    assert_eq!(frames, 999);
    assert_eq!(n, 0, "reading 999 records allocated {n} times");
}
