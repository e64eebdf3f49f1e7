//! The short fuzz run of CI (docs/fuzzing.md): builds the cargo-fuzz targets of
//! `tests/fuzz/fuzz` with the nightly toolchain and runs each under libFuzzer for a few seconds
//! from its committed corpus (seeds and `corpus-grown/`); a crash fails the test (the input is kept under
//! `<target dir>/fuzz-short/<target>/`, to be added to `tests/fuzz/regressions/<target>/`).
//!
//! Needs `rustup` with a nightly toolchain (libFuzzer's instrumentation is nightly-only) and
//! `cargo-fuzz`, which it installs when missing (`cargo install cargo-fuzz --locked`, as the HIL
//! tests install their packages). Without a nightly toolchain it prints why and passes: the
//! corpus replay (`tests/corpus.rs`) still runs every seed and regression input on stable.
//!
//! `COMANIP_FUZZ_SECONDS` sets the run time per target (default 3 s).
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

use comanip_fuzz::TARGETS;

/// Seconds of fuzzing per target, unless `COMANIP_FUZZ_SECONDS` says otherwise.
const DEFAULT_SECONDS: u64 = 3;

fn fuzz_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz")
}

/// The cargo target directory this test was built in (`<dir>/<profile>/deps/<test>`).
fn target_dir() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    exe.ancestors().nth(3).unwrap().to_owned()
}

fn rustup_nightly(args: &[&str]) -> Command {
    let mut c = Command::new("rustup");
    c.args(["run", "nightly"]).args(args);
    // The outer cargo's toolchain choice must not leak into the nightly one.
    for v in
        ["RUSTUP_TOOLCHAIN", "RUSTC", "RUSTC_WRAPPER", "RUSTFLAGS", "CARGO_ENCODED_RUSTFLAGS", "CARGO_BUILD_RUSTFLAGS"]
    {
        c.env_remove(v);
    }
    c
}

/// `Some(reason)` when nightly cannot be used here.
fn nightly_missing() -> Option<String> {
    match rustup_nightly(&["rustc", "--version"]).stdout(Stdio::null()).stderr(Stdio::null()).status() {
        Ok(s) if s.success() => None,
        Ok(_) => Some("no nightly toolchain (`rustup toolchain list`)".into()),
        Err(e) => Some(format!("rustup cannot run: {e}")),
    }
}

/// Installs cargo-fuzz when `cargo fuzz` is missing.
fn ensure_cargo_fuzz() {
    let present = rustup_nightly(&["cargo", "fuzz", "--version"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if present {
        return;
    }
    println!("cargo-fuzz is missing: cargo install cargo-fuzz --locked");
    let status = Command::new(env!("CARGO"))
        .args(["install", "cargo-fuzz", "--locked"])
        .env("CARGO_TARGET_DIR", target_dir().join("cargo-fuzz-install"))
        .status()
        .expect("cargo install cargo-fuzz");
    assert!(status.success(), "cargo install cargo-fuzz --locked failed");
}

#[test]
fn every_target_runs_briefly_without_a_crash() {
    if let Some(reason) = nightly_missing() {
        println!("SKIPPED: the short fuzz run needs nightly Rust for libFuzzer: {reason}");
        return;
    }
    ensure_cargo_fuzz();
    let seconds: u64 =
        std::env::var("COMANIP_FUZZ_SECONDS").ok().and_then(|s| s.parse().ok()).unwrap_or(DEFAULT_SECONDS);
    let fuzz_target_dir = target_dir().join("fuzz");
    let t0 = Instant::now();
    // `--sanitizer none`: the targets are safe Rust over safe Rust (docs/fuzzing.md); debug
    // assertions (overflow checks) on. Optimisation level 1 instead of the profile's 3 for this
    // short run only: the from-scratch build is most of CI's fuzz step, and level 1 builds in
    // 0.74x the time with about the same executions in 3 s per target (docs/fuzzing.md, "Time").
    let status =
        rustup_nightly(&["cargo", "fuzz", "build", "--sanitizer", "none", "--debug-assertions", "--target-dir"])
            .arg(&fuzz_target_dir)
            .env("CARGO_PROFILE_RELEASE_OPT_LEVEL", "1")
            .current_dir(fuzz_dir())
            .status()
            .expect("cargo fuzz build");
    assert!(status.success(), "cargo +nightly fuzz build failed");
    println!("fuzz build: {:.1} s", t0.elapsed().as_secs_f64());
    let host = rustup_nightly(&["rustc", "-vV"]).output().expect("rustc -vV");
    let host = String::from_utf8_lossy(&host.stdout)
        .lines()
        .find_map(|l| l.strip_prefix("host: ").map(str::to_owned))
        .expect("rustc -vV prints the host");
    let bin_dir = fuzz_target_dir.join(host).join("release");
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut failures = Vec::new();
    for t in TARGETS {
        let work = target_dir().join("fuzz-short").join(t.name);
        let _ = std::fs::remove_dir_all(&work);
        std::fs::create_dir_all(work.join("corpus")).unwrap();
        let mut c = Command::new(bin_dir.join(t.name));
        // New inputs go to the scratch corpus (the first directory), never to the committed one.
        c.arg(work.join("corpus")).arg(manifest.join("corpus").join(t.name));
        // The long run's merge-minimised additions (where committed) and the regression inputs.
        for kind in ["corpus-grown", "regressions"] {
            let d = manifest.join(kind).join(t.name);
            if d.is_dir() {
                c.arg(d);
            }
        }
        let dict = fuzz_dir().join("dicts").join(format!("{}.dict", t.name));
        if dict.is_file() {
            c.arg(format!("-dict={}", dict.display()));
        }
        c.arg(format!("-max_total_time={seconds}"))
            .arg(format!("-artifact_prefix={}/", work.display()))
            .arg("-rss_limit_mb=2048")
            .arg("-timeout=10")
            .arg("-print_final_stats=1");
        let t1 = Instant::now();
        let out = c.output().expect("run the fuzz target");
        let log = String::from_utf8_lossy(&out.stderr);
        let stats: Vec<&str> = log.lines().filter(|l| l.starts_with("stat::number_of_executed_units")).collect();
        println!("{}: {:.1} s, {}", t.name, t1.elapsed().as_secs_f64(), stats.join(" "));
        if !out.status.success() {
            let tail: Vec<&str> = log.lines().rev().take(40).collect::<Vec<_>>().into_iter().rev().collect();
            failures.push(format!("{} crashed (input kept in {}):\n{}", t.name, work.display(), tail.join("\n")));
        }
    }
    println!("short fuzz run: {:.1} s in all", t0.elapsed().as_secs_f64());
    assert!(failures.is_empty(), "{}", failures.join("\n\n"));
}
