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

/// The SocketCAN backend's receive path (`recvmsg` with the timestamp and the kernel's drop
/// counter, `hw_io::can::rx_meta`), on a UDP socket (this kernel has no CAN): after
/// construction, receiving, reading both control messages and counting drops allocate nothing.
#[test]
fn receiving_with_timestamps_and_the_drop_counter_allocates_nothing() {
    use hw_io::can::rx_meta::MsgReceiver;
    use std::os::fd::AsFd;
    let rx = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    let tx = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    tx.connect(rx.local_addr().unwrap()).unwrap();
    MsgReceiver::enable(rx.as_fd()).unwrap();
    rx.set_read_timeout(Some(Duration::from_secs(1))).unwrap();
    let mut r = MsgReceiver::new();
    let mut buf = [0u8; 16];
    let (mut received, mut stamped) = (0u64, 0u64);
    let n = allocations_in(|| {
        for round in 0..20u32 {
            // A burst larger than the default queue holds on some rounds, then read it all.
            for i in 0..(if round % 5 == 0 { 2000 } else { 10 }) {
                tx.send(&u32::to_le_bytes(i)).unwrap();
            }
            rx.set_nonblocking(true).unwrap();
            while let Ok(m) = r.recv(&rx, &mut buf) {
                received += 1;
                stamped += u64::from(m.unix_time_us.is_some());
            }
            rx.set_nonblocking(false).unwrap();
        }
    });
    assert_eq!(n, 0, "receiving allocated {n} times");
    assert!(received > 0 && stamped == received);
    assert!(r.dropped() > 0, "the bursts overflowed the queue: the drop counter path ran");
}
