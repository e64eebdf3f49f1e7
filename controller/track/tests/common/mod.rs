//! Shared by the tests of `comanip-track`: building the workspace's binaries, a short rendered sequence
//! (`simrobot generate --frames`, 320×240, 5 frames/s), its frames in memory.
#![allow(dead_code, reason = "each test binary uses a part")]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

use comanip_track::input::{Sequence, read_sequence};
use comanip_track::live::{Incoming, MemoryFrame};
use hw_io::frame::{FrameMeta, ImageLayout, PixelFormat};

#[path = "../../../tests/support/workspace_bin.rs"]
mod support;
pub use support::workspace_bin;

/// A rendered run in `dir/run` (bus.log, frames/) at 5 frames per second.
pub fn generate(dir: &Path) -> PathBuf {
    generate_at(dir, 5)
}

/// As [`generate`], at `fps` frames per second (more frames of the same motion).
pub fn generate_at(dir: &Path, fps: u32) -> PathBuf {
    let twin = dir.join("twin.toml");
    std::fs::write(&twin, "[scenario]\ncycles = 1\ninside_s = [5.0, 5.5]\noutside_s = [1.0, 1.2]\n").unwrap();
    let endo = dir.join("endoscope.toml");
    std::fs::write(
        &endo,
        "[camera.intrinsics]\nfx = 200.0\nfy = 200.0\ncx = 159.5\ncy = 119.5\nskew = 0.0\nwidth = 320\nheight = 240\n\
         distortion = [-0.08, 0.01, 0.0, 0.0, 0.0]\n[tissue]\nplane_z_m = 0.27\nextent_m = 0.40\ntexture_px = 256\n\
         [realism]\nsecond_instrument = false\n",
    )
    .unwrap();
    let run = dir.join("run");
    let o = Command::new(workspace_bin("sim", "simrobot"))
        .args(["generate", "--frames", "--fps", &fps.to_string(), "--seed", "2", "--out"])
        .arg(&run)
        .arg("--config")
        .arg(&twin)
        .arg("--endoscope-config")
        .arg(&endo)
        .output()
        .unwrap();
    assert!(o.status.success(), "generate: {}", String::from_utf8_lossy(&o.stderr));
    run
}

/// The run's sequence (truth, joints), as `comanip-track run` reads it.
pub fn sequence(run: &Path) -> Sequence {
    let frames = run.join("frames");
    read_sequence(
        &frames,
        &run.join("bus.log"),
        [&frames.join("left.yaml"), &frames.join("right.yaml")],
        &controller::config::Config::default(),
    )
    .unwrap()
}

/// Frames `range` of the sequence in memory, stamped with their recorded times, sequence = index.
pub fn memory_frames(seq: &Sequence, range: std::ops::Range<usize>) -> Vec<Incoming<MemoryFrame>> {
    let layout = ImageLayout::packed(320, 240, PixelFormat::Rgb8).unwrap();
    seq.frames[range]
        .iter()
        .map(|f| {
            let l = hw_io::camera::png::read_rgb(&f.files[0]).unwrap();
            let r = hw_io::camera::png::read_rgb(&f.files[1]).unwrap();
            let mut px = l.rgb.clone();
            px.extend_from_slice(&r.rgb);
            Incoming::Frame(MemoryFrame {
                meta: FrameMeta {
                    sequence: f.index as u64,
                    camera_id: 0,
                    timestamp_ns: f.t_ns,
                    exposure_ns: 0,
                    eyes: 2,
                    layout,
                },
                pixels: Arc::from(px),
            })
        })
        .collect()
}

/// The first frame index from which the instrument is well in view of the left eye.
pub fn first_in_view(seq: &Sequence) -> usize {
    seq.frames.iter().position(|f| f.truth.is_some_and(|t| t.instrument_px[0] > 400)).unwrap()
}

/// Both arms' joints through the passive bus listener replaying the run's candump log, frames
/// on the log's clock.
pub fn bus_joints(run: &Path) -> comanip_track::live::BusJoints {
    use controller::bus_listen::{BusListener, ListenConfig, ListenerThread};
    let mut cfg = ListenConfig::from_daemon(&controller::config::Config::default());
    cfg.history = comanip_track::live_cli::REPLAY_HISTORY;
    let bus = hw_io::can::ReplayBus::open(run.join("bus.log"), hw_io::can::Pacing::AsFastAsPossible).unwrap();
    let listener = ListenerThread::spawn(BusListener::new(bus, &cfg).unwrap()).unwrap();
    comanip_track::live::BusJoints::new(
        listener,
        comanip_track::live::FrameClock::Offset(0),
        comanip_track::live_cli::REPLAY_CATCH_UP,
    )
}
