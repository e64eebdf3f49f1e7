//! The in-process bus across threads: three virtual encoder nodes answer SYNCs from a
//! controller thread, like the real bus; and a blocked receive does not burn CPU.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::time::{Duration, Instant};

use hw_io::can::{
    CanBus, EncoderConfig, InProcessBus, JointAssembler, Message, NodeId, RecvError, SyncCounter, SyncSource,
};
use nix::time::{ClockId, clock_gettime};

fn thread_cpu_time() -> Duration {
    let ts = clock_gettime(ClockId::CLOCK_THREAD_CPUTIME_ID).unwrap();
    Duration::new(ts.tv_sec() as u64, ts.tv_nsec() as u32)
}

#[test]
fn blocked_recv_does_not_busy_poll() {
    let bus = InProcessBus::new();
    let mut rx = bus.endpoint().unwrap();
    let _other = bus.endpoint().unwrap();
    let cpu0 = thread_cpu_time();
    let t0 = Instant::now();
    assert!(rx.recv_timeout(Duration::from_millis(300)).unwrap().is_none());
    let wall = t0.elapsed();
    let cpu = thread_cpu_time() - cpu0;
    assert!(wall >= Duration::from_millis(300));
    assert!(cpu < Duration::from_millis(30), "waiting 300 ms used {cpu:?} of CPU");
}

#[test]
fn three_encoder_threads_answer_every_sync() {
    const CYCLES: u32 = 500;
    let bus = InProcessBus::with_capacity(4, 64);
    let mut controller = bus.endpoint().unwrap();
    let mut handles = Vec::new();
    for k in 1..=3u8 {
        let mut ep = bus.endpoint().unwrap();
        handles.push(std::thread::spawn(move || -> Result<u32, RecvError> {
            let node = NodeId::new(k).unwrap();
            let mut tracker = SyncCounter::new();
            let mut answered = 0;
            loop {
                let Some(rx) = ep.recv_timeout(Duration::from_secs(5))? else {
                    return Ok(answered);
                };
                match Message::decode(&rx.frame) {
                    Ok(Message::Sync { counter }) => {
                        tracker.observe(counter).expect("no SYNC lost on the in-process bus");
                        // Joint counts: node k, cycle n -> [n*100 + 2k-1, n*100 + 2k].
                        let n = i32::from(counter);
                        let counts = [n * 100 + 2 * i32::from(k) - 1, n * 100 + 2 * i32::from(k)];
                        ep.send(&Message::Tpdo { node, counts }.encode().unwrap()).unwrap();
                        answered += 1;
                    }
                    Ok(Message::Heartbeat { .. }) => return Ok(answered), // "stop" signal
                    _ => {}
                }
            }
        }));
    }

    let mut sync = SyncSource::new();
    let mut joints = JointAssembler::from_config(&EncoderConfig::default()).unwrap();
    for _ in 0..CYCLES {
        let Message::Sync { counter } = sync.next_message() else { unreachable!() };
        controller.send(&Message::Sync { counter }.encode().unwrap()).unwrap();
        joints.start_cycle();
        let deadline = Instant::now() + Duration::from_secs(5);
        while !joints.is_complete() {
            let left = deadline.saturating_duration_since(Instant::now());
            let rx = controller.recv_timeout(left).unwrap().expect("TPDOs within 5 s");
            if let Ok(msg) = Message::decode(&rx.frame) {
                joints.accept(&msg).unwrap();
            }
        }
        let n = i32::from(counter) * 100;
        assert_eq!(joints.counts().unwrap(), [n + 1, n + 2, n + 3, n + 4, n + 5, n + 6]);
    }
    let stop = Message::Heartbeat { node: NodeId::new(100).unwrap(), state: hw_io::can::NmtState::Stopped };
    controller.send(&stop.encode().unwrap()).unwrap();
    for h in handles {
        assert_eq!(h.join().unwrap().unwrap(), CYCLES);
    }
    assert_eq!(bus.dropped_frames(), 0);
}
