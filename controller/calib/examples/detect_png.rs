//! Ours on one PNG frame of the simulated endoscope (default camera): the returned detections
//! and every verified pair's figures, printed. A debugging aid.
//!
//! `cargo run --release -p comanip-calib --example detect_png -- FRAME.png` (`OURS` the
//! detector's settings as JSON, `OursConfig`'s fields to change).
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "diagnostic tool: a panic is a bug report")]

use vision::RgbView;
use vision::ours::{OursConfig, OursDetector};

fn main() {
    let path = std::env::args().nth(1).expect("a PNG");
    let img = hw_io::camera::png::read_rgb(std::path::Path::new(&path)).unwrap();
    let cfg: OursConfig = serde_json::from_str(&std::env::var("OURS").unwrap_or_else(|_| "{}".into())).unwrap();
    let k = comanip_calib::pixels::PixelProtocol::default().endoscope.camera.intrinsics;
    let mut det = OursDetector::new(k, cfg).unwrap();
    let view = RgbView::new(img.width, img.height, &img.rgb).unwrap();
    let (dets, trace) = det.detect_traced(&view).unwrap();
    for d in &dets {
        println!("det conf {:.2} ends {:?}", d.confidence, d.ends_px);
    }
    for p in trace.pairs.iter().filter(|p| p.verified.is_some() || p.rank.is_some()) {
        println!("pair {:?} rank {:?} {:?} {:?}", p.lines, p.rank, p.outcome, p.verified);
    }
}
