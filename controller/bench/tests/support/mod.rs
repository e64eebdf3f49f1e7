//! What the detector tests on rendered frames share.
#![allow(clippy::unwrap_used, reason = "test code: a panic is a failed test")]

use comanip_bench::shaft::RenderedFrame;
use comanip_bench::shaft::metrics::{FrameScore, score_frame};
use vision::ShaftDetector as _;
use vision::ours::OursDetector;

/// One frame's score (the benchmark's match rule) with detector `old` and with `new`:
/// instrument 1 when it is eligible, instrument 2 when some of it is in view.
pub fn score_both(old: &mut OursDetector, new: &mut OursDetector, f: &RenderedFrame) -> (FrameScore, FrameScore) {
    let view = f.view().unwrap();
    let inst1 = f.inst1.as_ref().filter(|t| t.eligible());
    let inst2 = if f.inst2_in_view { f.inst2.as_ref() } else { None };
    (score_frame(&old.detect(&view).unwrap(), inst1, inst2), score_frame(&new.detect(&view).unwrap(), inst1, inst2))
}
