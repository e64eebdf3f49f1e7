//! The live camera against a world fed as `simrobot live` feeds it (one SYNC per millisecond,
//! recorded at its CLOCK_MONOTONIC time): every frame reaches a subscriber in order, stamped on
//! the frame grid inside the recorded span, and its pixels are exactly the rendering of the two
//! arms' recorded states at that time.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a panic is a failed test")]

use std::sync::{Arc, Mutex};
use std::time::Duration;

use hw_io::frame::monotonic_now_ns;
use hw_io::ipc::{Continuity, FrameSubscriber, PublisherOptions};
use sim::endoscope::StereoRenderer;
use sim::live_camera::{LiveCamera, LiveCameraConfig, lock};
use sim::twin::{SimRobot, TwinConfig};
use sim::world::{World, default_endoscope_config};

#[test]
fn live_frames_arrive_in_order_on_the_bus_clock_and_show_the_recorded_arms() {
    let twin = TwinConfig::default();
    assert!(twin.endoscope_arm.enabled, "the default twin has the endoscope arm");
    let mut robot = SimRobot::new(&twin).unwrap();
    let mut cfg = default_endoscope_config();
    (cfg.camera.intrinsics.width, cfg.camera.intrinsics.height) = (160, 120);
    (cfg.camera.intrinsics.fx, cfg.camera.intrinsics.fy) = (100.0, 100.0);
    (cfg.camera.intrinsics.cx, cfg.camera.intrinsics.cy) = (79.5, 59.5);
    cfg.timing.fps = 20.0;
    let mesh = cfg.instrument.mesh().unwrap();
    // Keep everything: the frames are re-rendered from the same history afterwards.
    let world = Arc::new(Mutex::new(World::new(&twin, &cfg.instrument, 60_000_000_000).unwrap()));
    let service = format!("comanip-test/{}/live-camera", std::process::id());
    let mut sub = FrameSubscriber::connect(&service, &PublisherOptions::frames()).unwrap();
    let camera = LiveCamera::spawn(
        Arc::clone(&world),
        LiveCameraConfig { endoscope: cfg.clone(), mesh: mesh.clone(), service: service.clone(), camera_id: 2 },
    )
    .unwrap();

    // The bus: one SYNC per millisecond, the twin answering, the world recording each answer at
    // its monotonic time; on its own thread, as simrobot's SYNC loop beside its camera thread.
    let start = monotonic_now_ns();
    let feeding = Arc::new(std::sync::atomic::AtomicBool::new(true));
    let feeder = {
        let (world, feeding) = (Arc::clone(&world), Arc::clone(&feeding));
        std::thread::spawn(move || {
            let mut counter = 0u8;
            let mut next_sync = monotonic_now_ns();
            while feeding.load(std::sync::atomic::Ordering::Relaxed) {
                let now = monotonic_now_ns();
                if now >= next_sync {
                    let t_us = 1_700_000_000_000_000 + (now - start) / 1000;
                    robot.on_sync(counter, t_us).unwrap().expect("scenario long enough");
                    lock(&world).record(now, &robot).unwrap();
                    counter = counter.wrapping_add(1);
                    next_sync += 1_000_000;
                }
                std::thread::sleep(Duration::from_micros(200));
            }
        })
    };
    let mut frames = Vec::new();
    let mut take = |sub: &mut FrameSubscriber| {
        while let Some(f) = sub.try_recv().unwrap() {
            frames.push((*f.meta(), f.event, f.header().source_dropped, f.pixels().to_vec()));
        }
    };
    while monotonic_now_ns() < start + 1_500_000_000 {
        take(&mut sub);
        std::thread::sleep(Duration::from_millis(2));
    }
    // The camera stops while the SYNCs still come: every frame it made had its SYNCs.
    let counts = camera.stop().unwrap();
    feeding.store(false, std::sync::atomic::Ordering::Relaxed);
    feeder.join().unwrap();
    let end = monotonic_now_ns();
    take(&mut sub);

    assert!(frames.len() >= 10, "{} frames in 1.5 s at 20 fps", frames.len());
    assert_eq!(counts.published, frames.len() as u64, "{counts:?}");
    assert_eq!(sub.counters().missed, 0);
    let (first, ..) = &frames[0];
    let period = 50_000_000u64;
    let mut renderer = StereoRenderer::new(cfg.clone(), mesh).unwrap();
    for (k, (m, event, dropped, pixels)) in frames.iter().enumerate() {
        assert_eq!(*event, if k == 0 { Continuity::First } else { Continuity::InOrder });
        assert_eq!(m.camera_id, 2);
        assert!(m.timestamp_ns > start && m.timestamp_ns < end, "inside the recorded span");
        // On the frame grid; a frame the renderer skipped shows in source_dropped.
        let offset = m.timestamp_ns - first.timestamp_ns;
        assert_eq!(offset % period, 0, "frame {k}");
        assert_eq!(offset / period, k as u64 + dropped, "frame {k}: skipped frames are counted");
        // Exactly the arms' recorded states at that time (motion blur included).
        let w = lock(&world);
        let span = (w.history().next().map(|s| s.t_ns), w.history().last().map(|s| s.t_ns));
        assert!(
            w.covers(m.timestamp_ns - 8_000_000, m.timestamp_ns + 8_000_000),
            "frame {k} at {}: {span:?}",
            m.timestamp_ns
        );
        let expected = renderer.render(m.timestamp_ns, &|t| w.scene_at(t).unwrap()).unwrap();
        let half = pixels.len() / 2;
        assert!(pixels[..half] == expected.images[0].rgb[..], "frame {k}: left eye differs from the recorded scene");
        assert!(pixels[half..] == expected.images[1].rgb[..], "frame {k}: right eye differs");
    }
    assert_eq!(counts.uncovered, 0, "{counts:?}");
}
