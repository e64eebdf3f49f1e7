//! The Python subscriber example (`hw-io/examples/python/fulcrum_subscriber.py`: the `iceoryx2`
//! package from PyPI and a ctypes mirror of `FulcrumSample`) against a running fulcrumd on its
//! built-in simulated robot: every cycle arrives, in order, and every field it decodes equals
//! what the Rust subscriber (`fulcrumd monitor --samples-out`) reads from the same samples.
//!
//! Needs `python3` (pip is installed with apt-get when missing); the test installs the `iceoryx2` package in the version of the Rust
//! crate in Cargo.lock when it is missing or another version (the wire format is only
//! guaranteed between equal versions), and FAILS (never skips) if that does not work.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::Value;

/// Cycles the daemon runs (4 s at 1 kHz: the simulated surgeon enters the first trocar after
/// about 2 s).
const CYCLES: u64 = 4000;

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf()
}

/// The iceoryx2 version fulcrumd is built with, from Cargo.lock.
fn locked_iceoryx2_version() -> String {
    let lock = std::fs::read_to_string(workspace().join("Cargo.lock")).unwrap();
    let mut lines = lock.lines();
    while let Some(l) = lines.next() {
        if l == "name = \"iceoryx2\"" {
            let v = lines.next().unwrap();
            return v.trim_start_matches("version = \"").trim_end_matches('"').to_string();
        }
    }
    panic!("iceoryx2 is not in Cargo.lock");
}

fn python_iceoryx2_version() -> Option<String> {
    let out = Command::new("python3")
        .args(["-c", "import importlib.metadata as m, iceoryx2; print(m.version('iceoryx2'))"])
        .output()
        .ok()?;
    out.status.success().then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
}

/// Python's iceoryx2 in the locked version, installed with pip when missing.
fn ensure_python_iceoryx2() {
    let want = locked_iceoryx2_version();
    if python_iceoryx2_version().as_deref() == Some(want.as_str()) {
        return;
    }
    let spec = format!("iceoryx2=={want}");
    let mut log = String::new();
    let has_pip =
        || Command::new("python3").args(["-m", "pip", "--version"]).output().is_ok_and(|o| o.status.success());
    if !has_pip() {
        // A fresh Debian 12 has python3 without pip.
        let apt = Command::new("apt-get")
            .args(["install", "-y", "--no-install-recommends", "python3-pip"])
            .env("DEBIAN_FRONTEND", "noninteractive")
            .output();
        if !apt.is_ok_and(|o| o.status.success()) {
            let _ = Command::new("apt-get").arg("update").env("DEBIAN_FRONTEND", "noninteractive").output();
            let _ = Command::new("apt-get")
                .args(["install", "-y", "--no-install-recommends", "python3-pip"])
                .env("DEBIAN_FRONTEND", "noninteractive")
                .output();
        }
    }
    // A Debian python3 is "externally managed" (PEP 668): retry with its override.
    for extra in [&[][..], &["--break-system-packages"][..]] {
        let out = Command::new("python3")
            .args(["-m", "pip", "install", "--quiet"])
            .args(extra)
            .arg(&spec)
            .output()
            .unwrap_or_else(|e| panic!("python3 not runnable ({e}): this test needs python3 with pip"));
        log.push_str(&String::from_utf8_lossy(&out.stderr));
        if python_iceoryx2_version().as_deref() == Some(want.as_str()) {
            return;
        }
    }
    panic!(
        "Python's iceoryx2 {want} is not importable and `python3 -m pip install {spec}` failed:\n{log}\n\
         Install it (PyPI `iceoryx2`, the version of the Rust crate in Cargo.lock) to run this test."
    );
}

/// A child whose stderr lines arrive on a channel (and are kept for failure messages).
struct Proc {
    child: Child,
    lines: mpsc::Receiver<String>,
    seen: Vec<String>,
    name: &'static str,
}

impl Proc {
    fn spawn(name: &'static str, cmd: &mut Command) -> Self {
        let mut child = cmd.stdout(Stdio::null()).stderr(Stdio::piped()).spawn().unwrap();
        let stderr = child.stderr.take().unwrap();
        let (tx, lines) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Self { child, lines, seen: Vec::new(), name }
    }

    /// Waits (at most `limit`) for a stderr line containing `text`.
    fn wait_for_line(&mut self, text: &str, limit: Duration) {
        let end = Instant::now() + limit;
        while let Some(left) = end.checked_duration_since(Instant::now()) {
            match self.lines.recv_timeout(left) {
                Ok(l) => {
                    let hit = l.contains(text);
                    self.seen.push(l);
                    if hit {
                        return;
                    }
                }
                Err(_) => break,
            }
        }
        let _ = self.child.kill();
        panic!("{}: no line with {text:?} within {limit:?}; stderr:\n{}", self.name, self.seen.join("\n"));
    }

    /// Waits (at most `limit`) for the exit; kills the process after that. Returns stderr.
    fn finish(mut self, limit: Duration) -> String {
        let end = Instant::now() + limit;
        let status = loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                break Some(s);
            }
            if Instant::now() > end {
                let _ = self.child.kill();
                let _ = self.child.wait();
                break None;
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        std::thread::sleep(Duration::from_millis(50));
        self.seen.extend(self.lines.try_iter());
        let text = self.seen.join("\n");
        match status {
            Some(s) => assert!(s.success(), "{} exited with {s}; stderr:\n{text}", self.name),
            None => panic!("{} did not finish within {limit:?}; stderr:\n{text}", self.name),
        }
        text
    }
}

fn read_jsonl(path: &Path) -> Vec<Value> {
    std::fs::read_to_string(path)
        .unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()))
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

fn u(v: &Value, key: &str) -> u64 {
    v[key].as_u64().unwrap_or_else(|| panic!("{key} is not an unsigned integer in {v}"))
}

fn floats(v: &Value, key: &str) -> Vec<f64> {
    v[key]
        .as_array()
        .unwrap_or_else(|| panic!("{key} is not an array in {v}"))
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

#[test]
fn python_subscriber_receives_every_cycle_in_order_and_decodes_every_field() {
    ensure_python_iceoryx2();
    let dir = tempfile::tempdir().unwrap();
    let service = format!("comanip/test/python-subscriber-{}", std::process::id());
    // A large buffer: the check is decoding and order, not how fast Python keeps up on a loaded
    // 2-core CI machine (a slow reader would show a gap, which fails the test).
    let buffer = 4096;
    let config = dir.path().join("fulcrumd.toml");
    std::fs::write(&config, format!("[output]\nservice = \"{service}\"\nsubscriber_buffer = {buffer}\n")).unwrap();
    let py_out = dir.path().join("python.jsonl");
    let rs_out = dir.path().join("rust.jsonl");
    let script = workspace().join("hw-io/examples/python/fulcrum_subscriber.py");

    // Both subscribers first (the first creates the services), then the daemon.
    let mut python = Proc::spawn(
        "python subscriber",
        Command::new("python3")
            .arg(&script)
            .args(["--service", &service, "--buffer", &buffer.to_string(), "--count", &CYCLES.to_string()])
            .args(["--idle-timeout-s", "10", "--expect-in-order", "--jsonl"])
            .arg(&py_out),
    );
    python.wait_for_line("listening on", Duration::from_secs(60));
    let mut rust = Proc::spawn(
        "fulcrumd monitor",
        Command::new(env!("CARGO_BIN_EXE_fulcrumd"))
            .args(["monitor", "--service", &service, "--buffer", &buffer.to_string(), "--count", &CYCLES.to_string()])
            .arg("--samples-out")
            .arg(&rs_out)
            .env("RUST_LOG", "info"),
    );
    rust.wait_for_line("waiting for samples", Duration::from_secs(60));
    let summary = dir.path().join("summary.json");
    let daemon = Command::new(env!("CARGO_BIN_EXE_fulcrumd"))
        .arg("--config")
        .arg(&config)
        .args(["--cycles", &CYCLES.to_string(), "--no-record", "--summary-json"])
        .arg(&summary)
        .output()
        .unwrap();
    assert!(daemon.status.success(), "fulcrumd failed:\n{}", String::from_utf8_lossy(&daemon.stderr));
    let py_log = python.finish(Duration::from_secs(60));
    rust.finish(Duration::from_secs(60));

    let py = read_jsonl(&py_out);
    let rs = read_jsonl(&rs_out);
    assert_eq!(py.len() as u64, CYCLES, "python received {} of {CYCLES} samples; its log:\n{py_log}", py.len());
    assert_eq!(rs.len(), py.len(), "the Rust subscriber received {} samples", rs.len());
    assert!(
        py_log.contains(&format!("received {CYCLES}, missed 0, restarts 0, refused 0")),
        "python's counters: {py_log}"
    );

    let run_id = u(&py[0], "run_id");
    let mut states = [0u64; 3];
    for (i, (p, r)) in py.iter().zip(&rs).enumerate() {
        // Every cycle, in order, of one run.
        assert_eq!(u(p, "sequence"), i as u64, "python sample {i}");
        assert_eq!(p["event"], if i == 0 { "first" } else { "in_order" }, "python sample {i}");
        assert_eq!(u(p, "run_id"), run_id);
        if i > 0 {
            assert!(u(p, "timestamp_ns") > u(&py[i - 1], "timestamp_ns"), "timestamps must increase: {p}");
        }
        // The same values as the Rust subscriber, field by field.
        for key in ["run_id", "sequence", "timestamp_ns", "state", "health", "trocar_id", "window_fill"] {
            assert_eq!(u(p, key), u(r, key), "{key} of sample {i}: python {p} rust {r}");
        }
        for key in ["fulcrum_base_m", "joints_rad"] {
            assert_eq!(floats(p, key), floats(r, key), "{key} of sample {i}");
        }
        assert_eq!(p["event"], r["event"], "continuity of sample {i}");
        // As docs/output.md documents them.
        assert_eq!(u(p, "version"), 1);
        assert_eq!(u(p, "reserved"), 0);
        let state = u(p, "state");
        assert!(state <= 2, "unknown state {state}");
        states[state as usize] += 1;
        let fulcrum = floats(p, "fulcrum_base_m");
        if state == 2 {
            // (trocar ids count from 0: the first trocar found is 0, like "not inside".)
            assert!(fulcrum.iter().any(|x| *x != 0.0), "inside with a zero fulcrum: {p}");
            assert!(u(p, "fit_lines") > 0, "inside without a fit: {p}");
        } else {
            assert_eq!(u(p, "trocar_id"), 0, "a trocar while not inside: {p}");
            assert_eq!(fulcrum, [0.0; 3], "a fulcrum while not inside: {p}");
        }
        if state != 0 {
            assert_eq!(u(p, "health") & 0x3BFF, 0, "a valid sample with an invalidating flag: {p}");
            let axis = floats(p, "axis_base");
            let norm = axis.iter().map(|x| x * x).sum::<f64>().sqrt();
            assert!((norm - 1.0).abs() < 1e-9, "axis_base is not a unit vector: {p}");
            assert!(u(p, "window_fill") <= u(p, "window_len"), "{p}");
        }
        for key in ["fulcrum_base_m", "wrist_base_m", "axis_base", "joints_rad"] {
            assert!(floats(p, key).iter().all(|x| x.is_finite()), "{key} not finite: {p}");
        }
        for key in ["residual_m", "fulcrum_std_m", "conditioning"] {
            assert!(p[key].as_f64().unwrap().is_finite(), "{key}: {p}");
        }
    }
    eprintln!("python subscriber: {CYCLES} samples in order; invalid/outside/inside = {states:?}");
    // The simulated surgeon goes outside and then into a trocar within the run.
    assert!(states[1] > 0 && states[2] > 0, "expected outside and inside samples, got {states:?}");
}

#[test]
fn python_mirror_has_the_rust_layout() {
    use hw_io::ipc::FulcrumSample as S;
    use std::mem::offset_of;
    ensure_python_iceoryx2();
    let script = workspace().join("hw-io/examples/python/fulcrum_subscriber.py");
    let code = "import importlib.util, sys\n\
                spec = importlib.util.spec_from_file_location('sub', sys.argv[1])\n\
                m = importlib.util.module_from_spec(spec); spec.loader.exec_module(m)\n\
                import ctypes\n\
                T = m.FulcrumSample\n\
                print('size', ctypes.sizeof(T), ctypes.alignment(T))\n\
                for name, _ in T._fields_: print(name, getattr(T, name).offset, getattr(T, name).size)\n\
                print('type_name', T.type_name())\n";
    let out = Command::new("python3").args(["-c", code]).arg(&script).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let got = String::from_utf8(out.stdout).unwrap();
    let fields: [(&str, usize, usize); 20] = [
        ("version", offset_of!(S, version), 4),
        ("state", offset_of!(S, state), 4),
        ("sequence", offset_of!(S, sequence), 8),
        ("run_id", offset_of!(S, run_id), 8),
        ("timestamp_ns", offset_of!(S, timestamp_ns), 8),
        ("health", offset_of!(S, health), 4),
        ("trocar_id", offset_of!(S, trocar_id), 4),
        ("fulcrum_base_m", offset_of!(S, fulcrum_base_m), 24),
        ("residual_m", offset_of!(S, residual_m), 8),
        ("fulcrum_std_m", offset_of!(S, fulcrum_std_m), 8),
        ("conditioning", offset_of!(S, conditioning), 8),
        ("wrist_base_m", offset_of!(S, wrist_base_m), 24),
        ("axis_base", offset_of!(S, axis_base), 24),
        ("joints_rad", offset_of!(S, joints_rad), 48),
        ("window_fill", offset_of!(S, window_fill), 2),
        ("window_len", offset_of!(S, window_len), 2),
        ("fit_lines", offset_of!(S, fit_lines), 2),
        ("reserved", offset_of!(S, reserved), 2),
        ("wake_late_ns", offset_of!(S, wake_late_ns), 4),
        ("prev_cycle_compute_ns", offset_of!(S, prev_cycle_compute_ns), 4),
    ];
    let mut expected = vec![format!("size {} {}", size_of::<S>(), align_of::<S>())];
    expected.extend(fields.iter().map(|(n, o, s)| format!("{n} {o} {s}")));
    expected.push(format!("type_name {}", <S as hw_io::ipc::Message>::TYPE_NAME));
    assert_eq!(got.lines().collect::<Vec<_>>(), expected);
}
