//! The C declarations of the shared-memory messages (`hw-io/include/comanip/messages.h`) match
//! the Rust types: a C program compiled against the header prints every field's offset, each
//! struct's size and alignment, and they must equal `offset_of!`, `size_of` and `align_of` of
//! the `#[repr(C)]` types. The C blocks quoted in docs/output.md and docs/frames.md must be the
//! header's own lines.
//!
//! Needs a C compiler (`cc`, or `gcc`); when none is on PATH the test installs Debian's `gcc`
//! with apt-get, and fails with a message when it cannot.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a panic is a failed test")]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use hw_io::ipc::{CalibrationSample, FrameHeader, FulcrumSample, TrackSample};

fn which(program: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path).map(|d| d.join(program)).find(|p| p.is_file())
}

fn c_compiler() -> PathBuf {
    if let Some(cc) = which("cc").or_else(|| which("gcc")) {
        return cc;
    }
    let install = |args: &[&str]| {
        Command::new("apt-get").args(args).env("DEBIAN_FRONTEND", "noninteractive").status().is_ok_and(|s| s.success())
    };
    if !install(&["install", "-y", "--no-install-recommends", "gcc", "libc6-dev"]) {
        assert!(install(&["update"]), "no C compiler, and apt-get update failed: install gcc to run this test");
        assert!(
            install(&["install", "-y", "--no-install-recommends", "gcc", "libc6-dev"]),
            "apt-get install gcc failed"
        );
    }
    which("cc").or_else(|| which("gcc")).expect("gcc installed but not on PATH")
}

fn manifest() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

macro_rules! fields {
    ($t:ty, $cname:literal: $($f:ident),* $(,)?) => {{
        let mut c = String::new();
        let mut rust = BTreeMap::new();
        $(
            c += &format!("    printf(\"{} {} %zu\\n\", offsetof({}, {}));\n", $cname, stringify!($f), $cname, stringify!($f));
            rust.insert(format!("{} {}", $cname, stringify!($f)), core::mem::offset_of!($t, $f));
        )*
        c += &format!("    printf(\"{} sizeof %zu\\n\", sizeof({}));\n", $cname, $cname);
        c += &format!("    printf(\"{} alignof %zu\\n\", _Alignof({}));\n", $cname, $cname);
        rust.insert(format!("{} sizeof", $cname), core::mem::size_of::<$t>());
        rust.insert(format!("{} alignof", $cname), core::mem::align_of::<$t>());
        (c, rust)
    }};
}

#[test]
fn the_c_header_has_the_rust_layouts() {
    let (c1, mut expected) = fields!(FulcrumSample, "FulcrumSample":
        version, state, sequence, run_id, timestamp_ns, health, trocar_id, fulcrum_base_m, residual_m,
        fulcrum_std_m, conditioning, wrist_base_m, axis_base, joints_rad, window_fill, window_len, fit_lines,
        reserved, wake_late_ns, prev_cycle_compute_ns);
    let (c2, r2) = fields!(FrameHeader, "comanip_frame_header_t":
        version, camera_id, sequence, run_id, timestamp_ns, exposure_ns, eyes, width, height, stride,
        pixel_format, payload_bytes, source_dropped);
    expected.extend(r2);
    let (c3, r3) = fields!(TrackSample, "TrackSample":
        version, status, sequence, run_id, frame_timestamp_ns, frame_sequence, published_ns, reasons,
        calibration_source, calibration_sequence, calibration_run_id, tip_camera_m, tip_camera_wxyz, tip_base_m,
        tip_base_wxyz, jaw_rad, spread_m, best_cost_px, camera_delta, frames_processed, frames_skipped,
        frames_rejected, frames_invalid);
    expected.extend(r3);
    let (c4, r4) = fields!(CalibrationSample, "CalibrationSample":
        version, state, sequence, run_id, timestamp_ns, observations, drifts, translation_m, quaternion_wxyz,
        covariance, predicted_fulcrum_m, predicted_origin_m, predicted_rotation_rad, mean_fulcrum_m);
    expected.extend(r4);
    let program = format!(
        "#include <stddef.h>\n#include <stdio.h>\n#include \"comanip/messages.h\"\nint main(void) {{\n{c1}{c2}{c3}{c4}    return 0;\n}}\n"
    );
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("layout.c");
    let exe = dir.path().join("layout");
    std::fs::write(&src, program).unwrap();
    let out = Command::new(c_compiler())
        .args(["-std=c11", "-Wall", "-Wextra", "-Werror", "-pedantic", "-I"])
        .arg(manifest().join("include"))
        .arg(&src)
        .arg("-o")
        .arg(&exe)
        .output()
        .unwrap();
    assert!(out.status.success(), "the header does not compile:\n{}", String::from_utf8_lossy(&out.stderr));
    let run = Command::new(&exe).output().unwrap();
    assert!(run.status.success());
    let c: BTreeMap<String, usize> = String::from_utf8(run.stdout)
        .unwrap()
        .lines()
        .map(|l| {
            let (k, v) = l.rsplit_once(' ').unwrap();
            (k.to_string(), v.parse().unwrap())
        })
        .collect();
    assert_eq!(c.len(), expected.len());
    for (k, v) in &expected {
        assert_eq!(c.get(k), Some(v), "{k}: C {:?}, Rust {v}", c.get(k));
    }
}

#[test]
fn the_docs_quote_the_header() {
    let header = std::fs::read_to_string(manifest().join("include/comanip/messages.h")).unwrap();
    for (doc, after) in [
        ("../docs/output.md", "## C and C++ subscribers"),
        ("../docs/output.md", "### The tracker's message: `TrackSample`"),
        ("../docs/output.md", "### The calibration's message: `CalibrationSample`"),
        ("../docs/frames.md", "## The frame header"),
    ] {
        let text = std::fs::read_to_string(manifest().join(doc)).unwrap();
        let from = text.find(after).unwrap_or_else(|| panic!("{doc}: no section {after:?}"));
        let start = text[from..].find("```c\n").map(|i| from + i + 5).unwrap_or_else(|| panic!("{doc}: no C block"));
        let end = start + text[start..].find("```").unwrap();
        for line in text[start..end].lines().filter(|l| !l.trim().is_empty()) {
            assert!(header.lines().any(|h| h == line), "{doc}: line not in messages.h: {line}");
        }
    }
}
