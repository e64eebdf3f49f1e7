//! Fuzz target bodies, one per input boundary of comanip (docs/fuzzing.md).
//!
//! Each `pub fn` takes arbitrary bytes, feeds them to one boundary and **panics when an
//! invariant breaks**: a panic inside the product code, or a wrong result checked here (a
//! valid estimate with an invalidating flag or a non-finite float, an accepted configuration
//! that cannot build the pipeline, a candump record that does not read back the same...).
//! The cargo-fuzz targets (`tests/fuzz/fuzz/fuzz_targets/*.rs`) call these functions under
//! libFuzzer; `tests/fuzz/tests/corpus.rs` replays every committed corpus and regression
//! file through them on stable, so a crash once found stays a failing test until fixed.
//!
//! [`TARGETS`] lists them by the name of their cargo-fuzz target and corpus directory.

pub mod acquisition;
pub mod calib;
pub mod candump;
pub mod configs;
pub mod detectors;
pub mod frame_header;
pub mod ipc_sample;
pub mod recording;

/// One fuzz target: its name (cargo-fuzz target, `corpus/<name>/`, `regressions/<name>/`) and
/// its body.
#[derive(Clone, Copy, Debug)]
pub struct Target {
    /// Name of the cargo-fuzz target and of its corpus directories.
    pub name: &'static str,
    /// The body: panics when an invariant breaks.
    pub run: fn(&[u8]),
}

/// Every fuzz target, in the order of docs/fuzzing.md.
pub const TARGETS: &[Target] = &[
    Target { name: "acquisition", run: acquisition::run },
    Target { name: "candump", run: candump::run },
    Target { name: "recording", run: recording::run },
    Target { name: "fulcrumd_toml", run: configs::fulcrumd_toml },
    Target { name: "simrobot_toml", run: configs::simrobot_toml },
    Target { name: "calib_json", run: calib::json },
    Target { name: "camera_yaml", run: calib::yaml },
    Target { name: "ipc_sample", run: ipc_sample::run },
    Target { name: "frame_header", run: frame_header::run },
    Target { name: "detectors", run: detectors::run },
];

/// The target named `name`.
pub fn target(name: &str) -> Option<&'static Target> {
    TARGETS.iter().find(|t| t.name == name)
}

/// A little-endian cursor over fuzz bytes: every read succeeds (zeros past the end), so a
/// target decodes any input into some sequence of operations.
#[derive(Clone, Debug)]
pub struct Bytes<'a> {
    data: &'a [u8],
}

impl<'a> Bytes<'a> {
    /// A cursor at the start of `data`.
    pub fn new(data: &'a [u8]) -> Self {
        Self { data }
    }

    /// True when every byte was read.
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// The next byte (0 past the end).
    pub fn u8(&mut self) -> u8 {
        match self.data.split_first() {
            Some((&b, rest)) => {
                self.data = rest;
                b
            }
            None => 0,
        }
    }

    /// The next `N` bytes (zero-padded past the end).
    pub fn array<const N: usize>(&mut self) -> [u8; N] {
        let mut out = [0u8; N];
        let n = N.min(self.data.len());
        out[..n].copy_from_slice(&self.data[..n]);
        self.data = &self.data[n..];
        out
    }

    /// The next little-endian `u16`.
    pub fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.array())
    }

    /// The next little-endian `u32`.
    pub fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.array())
    }

    /// The next little-endian `u64`.
    pub fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.array())
    }

    /// The rest of the bytes.
    pub fn rest(&mut self) -> &'a [u8] {
        std::mem::take(&mut self.data)
    }
}
