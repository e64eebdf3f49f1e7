//! The frame service: stereo frames from a publisher to subscribers in shared memory, in order,
//! with their headers; a slow subscriber's losses counted; a publisher restart seen; a frame
//! with a header this program cannot read refused and counted.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a panic is a failed test")]

use std::time::Duration;

use hw_io::frame::{FrameFormat, ImageLayout, PixelFormat};
use hw_io::ipc::{
    Continuity, FRAME_HEADER_VERSION, FrameHeader, FramePublishError, FramePublisher, FrameRecvError, FrameSubscriber,
    PublisherOptions,
};
use iceoryx2::prelude::*;

fn service(test: &str) -> String {
    format!("comanip-test/{}/frames/{test}", std::process::id())
}

fn format() -> FrameFormat {
    FrameFormat::new(2, ImageLayout::packed(64, 48, PixelFormat::Rgb8).unwrap()).unwrap()
}

/// Pixels of frame `n`: every byte depends on the frame, the eye and the position.
fn pattern(n: u64, len: usize) -> Vec<u8> {
    (0..len).map(|i| ((i as u64 * 31 + n * 7 + (i as u64 / 9216) * 101) % 251) as u8).collect()
}

#[test]
fn stereo_frames_arrive_in_order_with_pixels_and_timestamps() {
    let name = service("order");
    let opts = PublisherOptions::frames();
    let mut sub = FrameSubscriber::connect(&name, &opts).unwrap();
    let mut publisher = FramePublisher::create(&name, format(), 3, &opts).unwrap();
    let len = format().payload_bytes();
    assert_eq!(len, 2 * 64 * 48 * 3);
    for n in 0..40u64 {
        let t = 1_000_000_000 + n * 33_333_333;
        if n % 2 == 0 {
            let header = publisher.publish(&pattern(n, len), t, 16_000_000).unwrap();
            assert_eq!(header.sequence, n);
        } else {
            // Zero-copy path: write into the loaned slot.
            let mut slot = publisher.loan().unwrap();
            assert!(slot.pixels_mut().iter().all(|&b| b == 0), "a loaned slot starts zeroed");
            slot.pixels_mut().copy_from_slice(&pattern(n, len));
            slot.send(t, 16_000_000).unwrap();
        }
        let frame = sub.wait(Duration::from_secs(2)).unwrap().expect("frame within 2 s");
        let m = frame.meta();
        assert_eq!((m.sequence, m.timestamp_ns, m.exposure_ns, m.camera_id, m.eyes), (n, t, 16_000_000, 3, 2));
        assert_eq!(m.layout, format().layout);
        assert_eq!(frame.event, if n == 0 { Continuity::First } else { Continuity::InOrder });
        let expected = pattern(n, len);
        assert_eq!(frame.pixels(), &expected[..]);
        assert_eq!(frame.eye(0).unwrap(), &expected[..len / 2]);
        assert_eq!(frame.eye(1).unwrap(), &expected[len / 2..]);
        assert!(frame.eye(2).is_none());
        assert_eq!(frame.header().version, FRAME_HEADER_VERSION);
        assert_eq!(frame.header().run_id, publisher.run_id());
    }
    let c = sub.counters();
    assert_eq!((c.received, c.missed, c.restarts, c.rejected), (40, 0, 0, 0));
    assert_eq!(publisher.published(), 40);
    // A frame of the wrong size is refused before anything is sent.
    assert!(matches!(
        publisher.publish(&[0u8; 10], 0, 0),
        Err(FramePublishError::Size { expected, got: 10 }) if expected == len
    ));
    assert!(sub.try_recv().unwrap().is_none());
}

#[test]
fn a_slow_subscriber_loses_the_oldest_frames_and_counts_them() {
    let name = service("slow");
    let opts = PublisherOptions::frames();
    let mut sub = FrameSubscriber::connect(&name, &opts).unwrap();
    let mut publisher = FramePublisher::create(&name, format(), 0, &opts).unwrap();
    let len = format().payload_bytes();
    publisher.publish(&pattern(0, len), 10, 0).unwrap();
    assert_eq!(sub.try_recv().unwrap().unwrap().meta().sequence, 0);
    for n in 1..=10 {
        publisher.publish(&pattern(n, len), 10 + n, 0).unwrap();
    }
    // The buffer holds the 2 newest (9, 10): frames 1..=8 are lost, counted as a gap.
    let f = sub.try_recv().unwrap().unwrap();
    assert_eq!(f.meta().sequence, 9);
    assert_eq!(f.event, Continuity::Gap { missed: 8 });
    assert_eq!(f.pixels(), &pattern(9, len)[..]);
    let g = sub.try_recv().unwrap().unwrap();
    assert_eq!((g.meta().sequence, g.event), (10, Continuity::InOrder));
    drop((f, g));
    assert!(sub.try_recv().unwrap().is_none());
    assert_eq!(sub.counters().missed, 8);
    // The source's own losses travel in the header.
    publisher.set_source_dropped(4);
    publisher.publish(&pattern(11, len), 30, 0).unwrap();
    assert_eq!(sub.try_recv().unwrap().unwrap().header().source_dropped, 4);
    assert_eq!(sub.counters().source_dropped, 4);
}

#[test]
fn a_restarted_publisher_is_seen_as_a_restart() {
    let name = service("restart");
    let opts = PublisherOptions::frames();
    let mut sub = FrameSubscriber::connect(&name, &opts).unwrap();
    let len = format().payload_bytes();
    {
        let mut p = FramePublisher::create(&name, format(), 0, &opts).unwrap();
        for n in 0..3 {
            p.publish(&pattern(n, len), n, 0).unwrap();
            assert!(sub.wait(Duration::from_secs(1)).unwrap().is_some());
        }
    }
    let mut p = FramePublisher::create(&name, format(), 0, &opts).unwrap();
    p.publish(&pattern(0, len), 100, 0).unwrap();
    let f = sub.wait(Duration::from_secs(1)).unwrap().unwrap();
    assert_eq!((f.meta().sequence, f.event), (0, Continuity::Restart));
    assert_eq!(sub.counters().restarts, 1);
}

#[test]
fn a_second_publisher_on_the_same_service_is_refused() {
    let name = service("two");
    let opts = PublisherOptions::frames();
    let _first = FramePublisher::create(&name, format(), 0, &opts).unwrap();
    assert!(FramePublisher::create(&name, format(), 0, &opts).is_err());
}

#[test]
fn frames_with_unreadable_headers_are_refused_and_counted() {
    let name = service("bad");
    let opts = PublisherOptions { subscriber_buffer: 4, ..PublisherOptions::frames() };
    let mut sub = FrameSubscriber::connect(&name, &opts).unwrap();
    // A raw iceoryx2 publisher on the same service, as a corrupt or newer writer would be.
    let node = NodeBuilder::new().create::<ipc::Service>().unwrap();
    let svc = node
        .service_builder(&ServiceName::new(&name).unwrap())
        .publish_subscribe::<[u8]>()
        .user_header::<FrameHeader>()
        .max_publishers(1)
        .max_subscribers(opts.max_subscribers)
        .max_nodes(opts.max_subscribers + 2)
        .subscriber_max_buffer_size(opts.subscriber_buffer)
        .subscriber_max_borrowed_samples(2)
        .history_size(0)
        .enable_safe_overflow(true)
        .open_or_create()
        .unwrap();
    let raw = svc.publisher_builder().initial_max_slice_len(64).create().unwrap();
    let good_layout = ImageLayout::packed(4, 4, PixelFormat::Gray8).unwrap();
    let send = |header: FrameHeader, len: usize| {
        let mut s = raw.loan_slice(len).unwrap();
        *s.user_header_mut() = header;
        s.send().unwrap();
    };
    let meta = hw_io::frame::FrameMeta {
        sequence: 0,
        camera_id: 0,
        timestamp_ns: 5,
        exposure_ns: 0,
        eyes: 1,
        layout: good_layout,
    };
    let good = FrameHeader::new(&meta, 77, 0);
    let mut newer = good;
    newer.version = FRAME_HEADER_VERSION + 1;
    send(newer, 16);
    let mut short = good;
    short.sequence = 1;
    send(short, 15); // payload shorter than the layout
    let mut unknown = good;
    unknown.pixel_format = 42;
    send(unknown, 16);
    let mut ok = good;
    ok.sequence = 2;
    send(ok, 16);
    assert!(matches!(sub.try_recv(), Err(FrameRecvError::Header(hw_io::ipc::FrameHeaderError::Version { .. }))));
    assert!(matches!(
        sub.try_recv(),
        Err(FrameRecvError::Header(hw_io::ipc::FrameHeaderError::PayloadLength { actual: 15, .. }))
    ));
    assert!(matches!(sub.try_recv(), Err(FrameRecvError::Header(hw_io::ipc::FrameHeaderError::PixelFormat(_)))));
    // ... and the subscriber goes on with the next readable frame.
    let f = sub.try_recv().unwrap().unwrap();
    assert_eq!((f.meta().sequence, f.event, f.pixels().len()), (2, Continuity::First, 16));
    let c = sub.counters();
    assert_eq!((c.received, c.rejected), (1, 3));
}
