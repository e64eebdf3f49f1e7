//! configs/systemd/fulcrumd.service: `systemd-analyze verify` accepts it (pointed at the real
//! fulcrumd binary) without a warning, and it has the keys docs/systemd.md explains.
//!
//! systemd-analyze works without systemd as PID 1 (containers, CI). When it is missing the test
//! installs Debian's `systemd` package with apt-get; without apt-get it fails with a message.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;
use std::time::Instant;

const UNIT_NAME: &str = "fulcrumd.service";

fn unit_text() -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/systemd").join(UNIT_NAME);
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()))
}

fn which(program: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH").unwrap_or_else(|| "/usr/sbin:/usr/bin:/sbin:/bin".into());
    std::env::split_paths(&path).map(|d| d.join(program)).find(|p| p.is_file())
}

fn apt_get(args: &[&str]) -> Result<(), String> {
    let out = Command::new("apt-get")
        .args(args)
        .env("DEBIAN_FRONTEND", "noninteractive")
        .output()
        .map_err(|e| format!("cannot run apt-get: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "apt-get {} failed ({}):\n{}\n{}",
            args.join(" "),
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ))
    }
}

/// Path of systemd-analyze, installing Debian's `systemd` package once if it is missing.
fn systemd_analyze() -> &'static Path {
    static TOOL: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    let tool = TOOL.get_or_init(|| {
        if let Some(p) = which("systemd-analyze") {
            return Ok(p);
        }
        if which("apt-get").is_none() {
            return Err("systemd-analyze is missing and apt-get is not available: install systemd's tools \
                        (Debian/Ubuntu: apt-get install systemd) to run this test"
                .into());
        }
        let t0 = Instant::now();
        let install = ["install", "-y", "--no-install-recommends", "systemd"];
        if apt_get(&install).is_err() {
            // The package lists may be missing or stale on a fresh machine.
            apt_get(&["update"])?;
            apt_get(&install)?;
        }
        eprintln!("installed systemd with apt-get in {:.1} s", t0.elapsed().as_secs_f64());
        which("systemd-analyze").ok_or_else(|| "apt-get installed systemd but systemd-analyze is not on PATH".into())
    });
    match tool {
        Ok(p) => p,
        Err(msg) => panic!("{msg}"),
    }
}

/// Runs `systemd-analyze verify` on `text` saved as fulcrumd.service in a fresh directory.
/// Returns (success, the output lines that concern the unit, all output).
fn verify(text: &str) -> (bool, Vec<String>, String) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(UNIT_NAME);
    std::fs::write(&path, text).unwrap();
    let out = Command::new(systemd_analyze())
        .args(["--man=no", "--generators=no", "verify"])
        .arg(&path)
        .env("SYSTEMD_LOG_COLOR", "0")
        .env("SYSTEMD_LOG_LEVEL", "info")
        .output()
        .unwrap();
    let all = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    let dir_str = dir.path().display().to_string();
    let about_unit =
        all.lines().filter(|l| l.contains(UNIT_NAME) || l.contains(&dir_str)).map(str::to_string).collect();
    (out.status.success(), about_unit, all)
}

/// The unit with ExecStart pointing at the binary built for this test.
fn unit_with_built_binary() -> String {
    let bin = env!("CARGO_BIN_EXE_fulcrumd");
    let text = unit_text();
    let rewritten = text.replace("ExecStart=/usr/local/bin/fulcrumd ", &format!("ExecStart={bin} "));
    assert_ne!(rewritten, text, "ExecStart=/usr/local/bin/fulcrumd not found in the unit");
    rewritten
}

#[test]
fn unit_passes_systemd_analyze_verify_without_warnings() {
    let (ok, about_unit, all) = verify(&unit_with_built_binary());
    assert!(ok, "systemd-analyze verify failed:\n{all}");
    assert!(about_unit.is_empty(), "systemd-analyze verify warns about the unit:\n{}", about_unit.join("\n"));
}

#[test]
fn verify_does_catch_mistakes() {
    // Controls for the test above: a misspelt key is a warning (exit 0), a missing binary an error.
    let text = unit_with_built_binary().replace("WatchdogSec=1", "WatchdogSecs=1");
    let (ok, about_unit, all) = verify(&text);
    assert!(ok, "{all}");
    assert!(about_unit.iter().any(|l| l.contains("WatchdogSecs")), "no warning for a misspelt key:\n{all}");
    let (ok, _, all) = verify(&unit_text().replace("/usr/local/bin/fulcrumd", "/nonexistent/fulcrumd"));
    assert!(!ok, "a missing ExecStart binary passed:\n{all}");
}

/// (section, key, value) of every assignment, in order.
fn assignments(text: &str) -> Vec<(String, String, String)> {
    let mut section = String::new();
    let mut v = Vec::new();
    for line in text.lines().map(str::trim) {
        if line.is_empty() || line.starts_with('#') || line.starts_with(';') {
            continue;
        }
        if let Some(s) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
            section = s.to_string();
        } else if let Some((k, val)) = line.split_once('=') {
            v.push((section.clone(), k.trim().to_string(), val.trim().to_string()));
        } else {
            panic!("unparsable unit line: {line}");
        }
    }
    v
}

#[test]
fn unit_has_the_required_keys() {
    let a = assignments(&unit_text());
    let get = |key: &str| -> Vec<&str> {
        a.iter().filter(|(s, k, _)| s == "Service" && k == key).map(|(_, _, v)| v.as_str()).collect()
    };
    let one = |key: &str| -> String {
        let v = get(key);
        assert_eq!(v.len(), 1, "[Service] {key}= should appear once, found {v:?}");
        v[0].to_string()
    };
    assert_eq!(one("Type"), "notify");
    assert_eq!(one("NotifyAccess"), "main");
    assert_eq!(one("ExecStart"), "/usr/local/bin/fulcrumd --config /etc/comanip/fulcrumd.toml");
    assert_eq!(one("WatchdogSec"), "1");
    assert_eq!(one("Restart"), "on-failure");
    assert!(!one("RestartSec").is_empty());
    assert_eq!(one("LimitRTPRIO"), "95");
    assert_eq!(one("LimitMEMLOCK"), "infinity");
    assert_eq!(one("NoNewPrivileges"), "yes");
    assert_eq!(one("ProtectSystem"), "strict");
    assert_eq!(one("ProtectHome"), "yes");
    assert_eq!(one("PrivateTmp"), "no", "PrivateTmp would hide iceoryx2's /tmp/iceoryx2 from the subscribers");
    let rw_paths = one("ReadWritePaths");
    let rw: Vec<&str> = rw_paths.split_whitespace().collect();
    for p in ["/var/lib/comanip", "/dev/shm", "/tmp/iceoryx2"] {
        assert!(rw.contains(&p), "ReadWritePaths lacks {p}: {rw:?}");
    }
    assert_eq!(one("ProtectKernelTunables"), "yes");
    assert_eq!(one("ProtectControlGroups"), "yes");
    assert_eq!(one("RestrictAddressFamilies"), "AF_CAN AF_UNIX AF_NETLINK");
    assert_eq!(one("StateDirectory"), "comanip");
    assert!(!one("User").is_empty() && one("User") != "root");
    // No capability at all: the real-time limits above are enough (docs/systemd.md).
    assert_eq!(one("CapabilityBoundingSet"), "");
    // Keys that would break the daemon.
    for (key, bad) in [
        ("CPUSchedulingPolicy", None),
        ("RestrictRealtime", Some("yes")),
        ("DynamicUser", Some("yes")),
        ("PrivateNetwork", Some("yes")),
        ("RemoveIPC", Some("yes")),
    ] {
        let v = get(key);
        assert!(v.iter().all(|v| bad.is_some_and(|b| *v != b)), "[Service] {key}={v:?} must not be set");
    }
    assert!(a.iter().any(|(s, k, v)| s == "Install" && k == "WantedBy" && v == "multi-user.target"));
}
