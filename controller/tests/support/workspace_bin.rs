//! Building another package's binary from a test: one copy, included by path by the tests that
//! need it (`controller/tests/hil_vcan.rs`, `controller/calib/tests/from_run.rs`,
//! `controller/track/tests/common/mod.rs`): cargo gives an integration test only its own
//! package's binaries.

use std::path::{Path, PathBuf};
use std::process::Command;

/// Binary `bin` of workspace package `package`, built by cargo for the same profile as this
/// test (`$CARGO build -p package --bin bin` into the same target directory; cargo rebuilds it
/// only when stale). Panics with cargo's output when the build fails.
pub fn workspace_bin(package: &str, bin: &str) -> PathBuf {
    let exe = std::env::current_exe().expect("current_exe");
    // target/<profile dir>/deps/<this test>
    let profile_dir = exe.parent().and_then(Path::parent).expect("test binary in target/<profile>/deps");
    let target_dir = profile_dir.parent().expect("target dir");
    let profile = match profile_dir.file_name().and_then(|n| n.to_str()) {
        Some("debug") => "test".to_string(), // what `cargo test` builds binaries with
        Some(other) => other.to_string(),
        None => panic!("unexpected target layout: {}", exe.display()),
    };
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let out = Command::new(&cargo)
        .args(["build", "--quiet", "-p", package, "--bin", bin, "--profile", &profile])
        .arg("--target-dir")
        .arg(target_dir)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .output()
        .unwrap_or_else(|e| panic!("running cargo to build {bin}: {e}"));
    assert!(out.status.success(), "cargo build {bin} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    let path = profile_dir.join(bin);
    assert!(path.is_file(), "{} was not built", path.display());
    path
}
