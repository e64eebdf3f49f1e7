//! configs/systemd/: `systemd-analyze verify` accepts fulcrumd.service (pointed at the real
//! fulcrumd binary), comanip-camera.service and comanip.target without a warning; every service
//! rates at most 2.0 in `systemd-analyze security --offline=yes`; and the units have the keys
//! docs/systemd.md explains.
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
    let rewritten = text.replace("ExecStart=/usr/bin/fulcrumd ", &format!("ExecStart={bin} "));
    assert_ne!(rewritten, text, "ExecStart=/usr/bin/fulcrumd not found in the unit");
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
    let (ok, _, all) = verify(&unit_text().replace("/usr/bin/fulcrumd", "/nonexistent/fulcrumd"));
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
    assert_eq!(one("ExecStart"), "/usr/bin/fulcrumd --config /etc/comanip/fulcrumd.toml");
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
    for p in ["/var/lib/comanip", "/dev/shm", "-/tmp/iceoryx2"] {
        assert!(rw.contains(&p), "ReadWritePaths lacks {p}: {rw:?}");
    }
    // "-": /tmp/iceoryx2 may not exist yet when systemd sets up the namespace of ExecStartPre=,
    // which creates it; without "-" the start fails with 226/NAMESPACE (found under a booted
    // systemd 252, tests/hil/run-systemd-guest.sh).
    assert_eq!(one("ExecStartPre"), "+/usr/bin/install -d -m 1777 /tmp/iceoryx2");
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
    assert!(a.iter().any(|(s, k, v)| s == "Install" && k == "WantedBy" && v == "multi-user.target comanip.target"));
    assert!(a.iter().any(|(s, k, v)| s == "Unit" && k == "PartOf" && v == "comanip.target"));
}

fn systemd_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/systemd")
}

/// Every unit file of configs/systemd, by name.
fn all_units() -> Vec<(String, String)> {
    let mut units: Vec<(String, String)> = std::fs::read_dir(systemd_dir())
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "service" || x == "target"))
        .map(|p| (p.file_name().unwrap().to_string_lossy().into_owned(), std::fs::read_to_string(&p).unwrap()))
        .collect();
    units.sort();
    units
}

/// The units with the packaged binaries' paths pointed at binaries that exist here (the fulcrumd
/// built for this test; `/bin/true` for the other processes, whose binaries belong to other
/// packages of the workspace: the package test checks those).
fn units_for_verify() -> Vec<(String, String)> {
    all_units()
        .into_iter()
        .map(|(name, text)| {
            let text = text
                .replace("/usr/bin/fulcrumd ", &format!("{} ", env!("CARGO_BIN_EXE_fulcrumd")))
                .replace("/usr/bin/comanip-camera ", "/bin/true ")
                .replace("/usr/bin/comanip-track ", "/bin/true ")
                .replace("/usr/bin/comanip-calib ", "/bin/true ");
            (name, text)
        })
        .collect()
}

#[test]
fn every_unit_passes_systemd_analyze_verify_together() {
    let units = units_for_verify();
    assert!(units.len() >= 3, "configs/systemd should hold fulcrumd, comanip-camera and comanip.target: {units:?}");
    let dir = tempfile::tempdir().unwrap();
    let mut paths = Vec::new();
    for (name, text) in &units {
        let p = dir.path().join(name);
        std::fs::write(&p, text).unwrap();
        paths.push(p);
    }
    let out = Command::new(systemd_analyze())
        .args(["--man=no", "--generators=no", "verify"])
        .args(&paths)
        .env("SYSTEMD_LOG_COLOR", "0")
        .output()
        .unwrap();
    let all = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    let dir_str = dir.path().display().to_string();
    let about: Vec<&str> =
        all.lines().filter(|l| l.contains(&dir_str) || units.iter().any(|(n, _)| l.contains(n.as_str()))).collect();
    assert!(out.status.success(), "systemd-analyze verify failed:\n{all}");
    assert!(about.is_empty(), "systemd-analyze verify warns:\n{}", about.join("\n"));
}

/// `systemd-analyze security --offline=yes` of one unit text: (overall exposure, full output).
fn exposure(name: &str, text: &str) -> (f64, String) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(name);
    std::fs::write(&path, text).unwrap();
    let out = Command::new(systemd_analyze())
        .args(["--man=no", "security", "--offline=yes", "--no-pager"])
        .arg(&path)
        .env("SYSTEMD_LOG_COLOR", "0")
        .env("SYSTEMD_COLORS", "0")
        .output()
        .unwrap();
    let all = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    let line = all
        .lines()
        .find(|l| l.contains("Overall exposure level for"))
        .unwrap_or_else(|| panic!("no exposure line for {name}:\n{all}"));
    let value = line
        .rsplit_once(':')
        .and_then(|(_, rest)| rest.split_whitespace().next())
        .and_then(|v| v.parse::<f64>().ok())
        .unwrap_or_else(|| panic!("cannot read the exposure from {line:?}"));
    (value, all)
}

#[test]
fn every_service_rates_at_most_2_0_in_systemd_analyze_security() {
    let services: Vec<(String, String)> = all_units().into_iter().filter(|(n, _)| n.ends_with(".service")).collect();
    assert!(services.len() >= 2, "{services:?}");
    for (name, text) in &services {
        let (value, all) = exposure(name, text);
        eprintln!("{name}: exposure {value:.1}");
        assert!(value <= 2.0, "{name}: exposure {value} > 2.0 (docs/systemd.md explains each remaining one):\n{all}");
    }
    // Control: the same rating without the sandbox is far worse, so the figure above does measure it.
    let (name, text) = &services[0];
    let bare: String = text
        .lines()
        .filter(|l| {
            ["Protect", "Private", "Restrict", "SystemCall", "Capability", "NoNewPrivileges", "IPAddress"]
                .iter()
                .all(|k| !l.starts_with(k))
        })
        .map(|l| format!("{l}\n"))
        .collect();
    let (bare_value, _) = exposure(name, &bare);
    assert!(bare_value > 5.0, "{name} without its sandbox rates {bare_value}: the check cannot fail");
}

#[test]
fn companion_units_stay_off_the_loop_and_the_target_starts_the_set() {
    let units = all_units();
    // comanip-camera and the live calibration: lower priority, off the loop's CPU.
    for companion in ["comanip-camera.service", "comanip-calib-live.service"] {
        let text = &units.iter().find(|(n, _)| n == companion).unwrap_or_else(|| panic!("{companion}")).1;
        let a = assignments(text);
        let one = |key: &str| -> String {
            let v: Vec<&str> =
                a.iter().filter(|(s, k, _)| s == "Service" && k == key).map(|(_, _, v)| v.as_str()).collect();
            assert_eq!(v.len(), 1, "{companion} [Service] {key}= should appear once, found {v:?}");
            v[0].to_string()
        };
        // docs/realtime.md pins the loop to CPU 1 on the 2-core target; companions keep to CPU 0.
        assert_eq!(one("CPUAffinity"), "0", "{companion}");
        assert!(one("Nice").parse::<i32>().unwrap() > 0, "{companion} must be niced");
        assert!(one("CPUWeight").parse::<u32>().unwrap() < 100, "{companion}: below the default weight 100");
        assert_eq!(one("RestrictRealtime"), "yes", "{companion}");
        assert_eq!(one("User"), "comanip", "{companion}");
        assert_eq!(one("PrivateTmp"), "no", "{companion}: iceoryx2's /tmp/iceoryx2 must be the host's");
        assert!(a.iter().any(|(s, k, v)| s == "Unit" && k == "PartOf" && v == "comanip.target"), "{companion}");
    }
    // The live calibration reads the CAN bus (no private network) but never IP.
    let calib = assignments(&units.iter().find(|(n, _)| n == "comanip-calib-live.service").unwrap().1);
    let has = |key: &str, val: &str| calib.iter().any(|(s, k, v)| s == "Service" && k == key && v.contains(val));
    assert!(has("RestrictAddressFamilies", "AF_CAN") && has("IPAddressDeny", "any"));
    assert!(!calib.iter().any(|(_, k, _)| k == "PrivateNetwork"), "a private network would hide the CAN bus");
    assert!(has("ExecStart", "--live-config /etc/comanip/comanip-calib.toml"));

    // The tracker: lower still, on the camera's CPU, no real-time, the bus but no IP.
    let tracker = &units.iter().find(|(n, _)| n == "comanip-track.service").expect("comanip-track.service").1;
    let t = assignments(tracker);
    let tone = |key: &str| -> String {
        let v: Vec<&str> =
            t.iter().filter(|(s, k, _)| s == "Service" && k == key).map(|(_, _, v)| v.as_str()).collect();
        assert_eq!(v.len(), 1, "comanip-track [Service] {key}= should appear once, found {v:?}");
        v[0].to_string()
    };
    assert_eq!(tone("CPUAffinity"), "0", "off the loop's CPU (docs/realtime.md: the loop on CPU 1)");
    let camera_nice = assignments(&units.iter().find(|(n, _)| n == "comanip-camera.service").unwrap().1)
        .into_iter()
        .find(|(s, k, _)| s == "Service" && k == "Nice")
        .map(|(_, _, v)| v.parse::<i32>().unwrap())
        .expect("the camera's Nice=");
    assert!(tone("Nice").parse::<i32>().unwrap() >= camera_nice, "niced at least as the camera");
    assert!(tone("CPUWeight").parse::<u32>().unwrap() < 100, "below the default weight 100");
    assert_eq!(tone("RestrictRealtime"), "yes", "no SCHED_FIFO for the tracker");
    assert!(t.iter().all(|(_, k, _)| k != "CPUSchedulingPolicy" && k != "LimitRTPRIO"));
    assert_eq!(tone("User"), "comanip");
    assert_eq!(tone("PrivateTmp"), "no", "iceoryx2's /tmp/iceoryx2 must be the host's");
    assert!(tone("RestrictAddressFamilies").split_whitespace().any(|f| f == "AF_CAN"), "the passive bus socket");
    assert!(t.iter().all(|(_, k, v)| !(k == "PrivateNetwork" && v == "yes")), "can0 is in the host's namespace");
    assert_eq!(tone("IPAddressDeny"), "any");
    assert_eq!(
        tone("ExecStart"),
        "/usr/bin/comanip-track live --config /etc/comanip/comanip-track.toml --fulcrumd-config /etc/comanip/fulcrumd.toml"
    );
    assert!(t.iter().any(|(s, k, v)| s == "Unit" && k == "PartOf" && v == "comanip.target"));

    let target = &units.iter().find(|(n, _)| n == "comanip.target").expect("comanip.target").1;
    let wants: Vec<String> = assignments(target)
        .into_iter()
        .filter(|(s, k, _)| s == "Unit" && k == "Wants")
        .flat_map(|(_, _, v)| v.split_whitespace().map(str::to_string).collect::<Vec<_>>())
        .collect();
    for (name, text) in units.iter().filter(|(n, _)| n.ends_with(".service")) {
        assert!(wants.contains(name), "comanip.target does not start {name}: Wants={wants:?}");
        assert!(
            assignments(text).iter().any(|(s, k, v)| s == "Unit" && k == "PartOf" && v == "comanip.target"),
            "{name} lacks PartOf=comanip.target"
        );
    }
}
