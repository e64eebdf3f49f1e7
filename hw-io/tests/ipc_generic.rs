//! The generic shared-memory path with a message that is not a `FulcrumSample`: a test-only
//! tool pose. Publish and receive, version refusal, continuity (gap, restart), and that two
//! message types cannot share one service name by mistake. Every test uses its own service.

use std::time::Duration;

use hw_io::ipc::{
    ConnectError, Continuity, FulcrumSubscriber, Message, OpenError, Publisher, PublisherOptions, RecvError,
    Subscriber, WaitError, ZeroCopySend,
};

/// A tracked tool pose: position (metres) and unit quaternion (w, x, y, z), robot base frame.
#[derive(Clone, Copy, Debug, PartialEq, ZeroCopySend)]
#[type_name("comanip-test::ToolPose")]
#[repr(C)]
struct ToolPose {
    version: u32,
    tracker_id: u32,
    sequence: u64,
    run_id: u64,
    timestamp_ns: u64,
    position_base_m: [f64; 3],
    orientation_base: [f64; 4],
}

impl Message for ToolPose {
    const TYPE_NAME: &'static str = "comanip-test::ToolPose";
    const VERSION: u32 = 3;

    fn version(&self) -> u32 {
        self.version
    }

    fn sequence(&self) -> u64 {
        self.sequence
    }

    fn run_id(&self) -> u64 {
        self.run_id
    }
}

fn service(test: &str) -> String {
    format!("comanip-test/{}/generic-{test}", std::process::id())
}

fn pose(run_id: u64, sequence: u64) -> ToolPose {
    let s = sequence as f64;
    ToolPose {
        version: ToolPose::VERSION,
        tracker_id: 7,
        sequence,
        run_id,
        timestamp_ns: 1_000_000 * sequence,
        position_base_m: [0.1 * s, -0.2, 0.3 + 1e-3 * s],
        orientation_base: [1.0, 0.0, 0.0, 0.0],
    }
}

fn recv(sub: &mut Subscriber<ToolPose>) -> Result<Option<(ToolPose, Continuity)>, WaitError> {
    Ok(sub.wait(Duration::from_secs(1))?.map(|r| (r.sample, r.event)))
}

#[test]
fn the_type_name_is_iceoryx2s() {
    // SAFETY: `type_name` only returns the string of `#[type_name(..)]`; its safety contract
    // concerns implementing the trait (the layout), not calling it.
    assert_eq!(unsafe { <ToolPose as ZeroCopySend>::type_name() }, ToolPose::TYPE_NAME);
}

#[test]
fn another_message_type_is_published_and_received_field_for_field() {
    let name = service("roundtrip");
    let mut sub = Subscriber::<ToolPose>::connect(&name).unwrap();
    let mut publisher = Publisher::<ToolPose>::create(&name, &PublisherOptions::default()).unwrap();
    for seq in 0..20 {
        publisher.publish(&pose(5, seq)).unwrap();
    }
    assert_eq!(publisher.published(), 20);
    for seq in 0..20 {
        let (p, event) = recv(&mut sub).unwrap().expect("a pose");
        assert_eq!(p, pose(5, seq));
        assert_eq!(event, if seq == 0 { Continuity::First } else { Continuity::InOrder });
    }
    assert!(sub.try_recv().unwrap().is_none());
    let c = sub.counters();
    assert_eq!((c.received, c.missed, c.restarts, c.rejected), (20, 0, 0, 0));
}

#[test]
fn another_version_of_the_message_is_refused_with_its_type_name() {
    let name = service("version");
    let mut sub = Subscriber::<ToolPose>::connect(&name).unwrap();
    let mut publisher = Publisher::<ToolPose>::create(&name, &PublisherOptions::default()).unwrap();
    publisher.publish(&pose(1, 0)).unwrap();
    publisher.publish(&ToolPose { version: ToolPose::VERSION + 1, ..pose(1, 1) }).unwrap();
    publisher.publish(&pose(1, 2)).unwrap();
    assert_eq!(recv(&mut sub).unwrap().map(|(p, e)| (p.sequence, e)), Some((0, Continuity::First)));
    match sub.try_recv() {
        Err(e @ RecvError::VersionMismatch { type_name, found, expected }) => {
            assert_eq!((type_name, found, expected), ("comanip-test::ToolPose", 4, 3));
            assert!(e.to_string().contains("comanip-test::ToolPose layout version 4"), "{e}");
        }
        other => panic!("expected a version mismatch, got {other:?}"),
    }
    // The refused message does not count for continuity: 2 follows 0 as a gap of one.
    assert_eq!(recv(&mut sub).unwrap().map(|(p, e)| (p.sequence, e)), Some((2, Continuity::Gap { missed: 1 })));
    let c = sub.counters();
    assert_eq!((c.received, c.missed, c.rejected), (2, 1, 1));
}

#[test]
fn gaps_and_restarts_of_another_message_type() {
    let name = service("continuity");
    let mut sub = Subscriber::<ToolPose>::connect(&name).unwrap();
    let mut publisher = Publisher::<ToolPose>::create(&name, &PublisherOptions::default()).unwrap();
    for (run, seq) in [(1, 10), (1, 11), (1, 15), (2, 0), (2, 1)] {
        publisher.publish(&pose(run, seq)).unwrap();
    }
    let events: Vec<Continuity> = (0..5).map(|_| recv(&mut sub).unwrap().expect("a pose").1).collect();
    assert_eq!(
        events,
        [
            Continuity::First,
            Continuity::InOrder,
            Continuity::Gap { missed: 3 },
            Continuity::Restart,
            Continuity::InOrder
        ]
    );
    let c = sub.counters();
    assert_eq!((c.received, c.missed, c.restarts), (5, 3, 1));
}

#[test]
fn a_fulcrum_subscriber_cannot_open_a_service_of_another_message_type() {
    let name = service("types");
    let _publisher = Publisher::<ToolPose>::create(&name, &PublisherOptions::default()).unwrap();
    match FulcrumSubscriber::connect(&name) {
        Err(ConnectError::Open(OpenError::Service(_))) => {}
        other => panic!("expected an incompatible service, got {other:?}"),
    }
}
