//! A plain driver of the simulated stereo endoscope (`docs/vision.md`), for instruction
//! counting with callgrind and quick wall-clock figures: renders `FRAMES` stereo frames of the
//! demo motion (640×480 per eye) with one realism set, the endoscope moving every frame or
//! held still, and prints the wall time per frame. PNG encoding is not included.
//!
//! ```text
//! cargo bench -p sim --bench endoscope_frames -- [default|all|none] [moving|still] [FRAMES]
//! valgrind --tool=callgrind target/release/deps/endoscope_frames-* default moving 5
//! ```
//!
//! Callgrind counts the renderer's construction too (the 1024² tissue texture): the cost of
//! a frame is the difference between two runs with different frame counts, divided by the
//! difference of the counts.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "a bench driver: a failure is a panic")]

use std::hint::black_box;
use std::time::Instant;

use sim::endoscope::config::{RealismConfig, SmokeConfig};
use sim::endoscope::{DemoMotion, EndoscopeConfig, SceneState, StereoFrame, StereoRenderer};

fn main() {
    // `cargo bench` passes `--bench`; skip flags.
    let args: Vec<String> = std::env::args().skip(1).filter(|a| !a.starts_with("--")).collect();
    let set = args.first().map_or("default", String::as_str);
    let motion_kind = args.get(1).map_or("moving", String::as_str);
    let frames: u64 = args.get(2).map_or(60, |s| s.parse().expect("FRAMES: a number"));
    let default = RealismConfig::default();
    let realism = match set {
        "default" => default,
        "none" => RealismConfig::none(),
        "all" => RealismConfig {
            second_instrument: true,
            smoke: SmokeConfig { enabled: true, ..SmokeConfig::default() },
            ..default
        },
        other => panic!("unknown realism set {other} (default, all, none)"),
    };
    let still = match motion_kind {
        "moving" => false,
        "still" => true,
        other => panic!("unknown motion {other} (moving, still)"),
    };
    let cfg = EndoscopeConfig { realism, ..EndoscopeConfig::default() };
    let mesh = cfg.instrument.mesh().unwrap();
    let mut renderer = StereoRenderer::new(cfg, mesh).unwrap();
    let motion = DemoMotion::default();
    let held = motion.state_at(1_000_000_000).ecm_joints;
    let scene = |t| {
        let mut s: SceneState = motion.state_at(t);
        if still {
            s.ecm_joints = held;
        }
        s
    };
    let mut frame = StereoFrame::default();
    let start = Instant::now();
    for n in 0..frames {
        let t = 1_000_000_000 + n * 33_333_333;
        renderer.render_into(t, &scene, &mut frame).unwrap();
        black_box(&frame);
    }
    let s = start.elapsed().as_secs_f64();
    if frames > 0 {
        println!(
            "{set} {motion_kind}: {frames} stereo frames, {:.2} ms per frame ({:.1} frames/s)",
            1e3 * s / frames as f64,
            frames as f64 / s
        );
    }
}
