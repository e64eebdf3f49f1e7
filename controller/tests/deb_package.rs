//! The Debian package (docs/packaging.md): `cargo deb` packs the binaries this test run already
//! built (`--no-build --profile dev`: CI builds debug, and a release build of the five binaries
//! would cost CI several minutes; `packaging/build-deb` makes the release package the same way),
//! then the test reads the package (`dpkg-deb --info/--contents`), lints its maintainer scripts,
//! installs it into a scratch root (`dpkg --root DIR --force-script-chrootless`: the scripts run
//! on this machine with `DPKG_ROOT=DIR` and change only DIR) and purges it again.
//!
//! Needs root (dpkg chowns the files it unpacks; CI runs as root), dpkg, and cargo-deb, which
//! the test installs from crates.io (`cargo install cargo-deb --locked`) when it is missing;
//! shellcheck is installed with apt-get when missing. The other four binaries (simrobot,
//! comanip-calib, comanip-bench, comanip-camera) belong to other workspace packages: `cargo test
//! --workspace` builds them; when they are missing the test builds them with cargo.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code (helpers too): a panic is a failed test")]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;
use std::time::Instant;

/// The binaries of the package and the workspace package that builds each.
const BINARIES: [(&str, &str); 6] = [
    ("fulcrumd", "controller"),
    ("simrobot", "sim"),
    ("comanip-calib", "comanip-calib"),
    ("comanip-bench", "comanip-bench"),
    ("comanip-camera", "comanip-camera"),
    ("comanip-track", "comanip-track"),
];

const CONFFILES: [&str; 5] = [
    "/etc/comanip/fulcrumd.toml",
    "/etc/comanip/simrobot.toml",
    "/etc/comanip/camera.env",
    "/etc/comanip/comanip-track.toml",
    "/etc/comanip/comanip-calib.toml",
];

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf()
}

/// The profile directory this test's binaries were built into (`<target>/debug`).
fn profile_dir() -> PathBuf {
    Path::new(env!("CARGO_BIN_EXE_fulcrumd")).parent().unwrap().to_path_buf()
}

fn which(program: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH").unwrap_or_else(|| "/usr/sbin:/usr/bin:/sbin:/bin".into());
    std::env::split_paths(&path).map(|d| d.join(program)).find(|p| p.is_file())
}

fn run(cmd: &mut Command) -> Output {
    let shown = format!("{cmd:?}");
    cmd.output().unwrap_or_else(|e| panic!("cannot run {shown}: {e}"))
}

fn run_ok(cmd: &mut Command) -> String {
    let shown = format!("{cmd:?}");
    let out = run(cmd);
    assert!(
        out.status.success(),
        "{shown} failed ({}):\n{}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// PATH with the directory of the cargo running this test first: cargo-deb runs `cargo metadata`
/// from PATH.
fn path_with_cargo() -> std::ffi::OsString {
    let mut dirs: Vec<PathBuf> = std::env::var_os("CARGO")
        .map(PathBuf::from)
        .and_then(|c| c.parent().map(Path::to_path_buf))
        .into_iter()
        .collect();
    dirs.extend(std::env::split_paths(&std::env::var_os("PATH").unwrap_or_default()));
    std::env::join_paths(dirs).unwrap()
}

fn cargo() -> Command {
    Command::new(std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into()))
}

/// The cargo-deb version the package is made with (docs/packaging.md). Pinned: cargo-deb warns
/// that packing a `dev` profile build will become an error in a later version.
const CARGO_DEB_VERSION: &str = "3.8.0";

/// The cargo-deb binary: the one on PATH when it is the pinned version, else the pinned version
/// installed once from crates.io into `<target>/tools/cargo-deb-<version>`.
fn cargo_deb() -> PathBuf {
    static TOOL: OnceLock<PathBuf> = OnceLock::new();
    TOOL.get_or_init(|| {
        let is_pinned = |p: &Path| {
            Command::new(p).arg("--version").output().is_ok_and(|o| {
                o.status.success()
                    && String::from_utf8_lossy(&o.stdout).trim() == format!("cargo-deb {CARGO_DEB_VERSION}")
            })
        };
        if let Some(p) = which("cargo-deb").filter(|p| is_pinned(p)) {
            return p;
        }
        let root = profile_dir().parent().unwrap().join("tools").join(format!("cargo-deb-{CARGO_DEB_VERSION}"));
        let bin = root.join("bin/cargo-deb");
        if is_pinned(&bin) {
            return bin;
        }
        let t0 = Instant::now();
        // Its own build directory: the workspace's target directory is this test run's.
        let tmp = tempfile::tempdir().unwrap();
        run_ok(
            cargo()
                .args(["install", "cargo-deb", "--locked", "--version", CARGO_DEB_VERSION, "--root"])
                .arg(&root)
                .env("CARGO_TARGET_DIR", tmp.path()),
        );
        eprintln!("installed cargo-deb {CARGO_DEB_VERSION} in {:.0} s", t0.elapsed().as_secs_f64());
        assert!(is_pinned(&bin), "cargo install cargo-deb succeeded but {} does not run", bin.display());
        bin
    })
    .clone()
}

fn ensure_apt_tool(program: &str, package: &str) -> PathBuf {
    if let Some(p) = which(program) {
        return p;
    }
    assert!(which("apt-get").is_some(), "{program} is missing and there is no apt-get: install {package}");
    let install = ["install", "-y", "--no-install-recommends", package];
    let ok = Command::new("apt-get")
        .args(install)
        .env("DEBIAN_FRONTEND", "noninteractive")
        .output()
        .is_ok_and(|o| o.status.success());
    if !ok {
        run_ok(Command::new("apt-get").arg("update").env("DEBIAN_FRONTEND", "noninteractive"));
        run_ok(Command::new("apt-get").args(install).env("DEBIAN_FRONTEND", "noninteractive"));
    }
    which(program).unwrap_or_else(|| panic!("apt-get installed {package} but {program} is not on PATH"))
}

fn is_root() -> bool {
    // SAFETY: geteuid has no preconditions and cannot fail.
    unsafe { libc::geteuid() == 0 }
}

/// Builds the package once (from the binaries in `profile_dir()`), into a directory kept for
/// the whole test binary. Returns the .deb's path.
fn deb() -> &'static Path {
    static DEB: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    &DEB.get_or_init(|| {
        let cargo_deb = cargo_deb();
        let profile_dir = profile_dir();
        let target_dir = profile_dir.parent().unwrap().to_path_buf();
        let missing: Vec<(&str, &str)> =
            BINARIES.iter().copied().filter(|(bin, _)| !profile_dir.join(bin).is_file()).collect();
        if !missing.is_empty() {
            // `cargo test -p controller` alone: build the other packages' binaries (debug).
            let mut cmd = cargo();
            cmd.args(["build", "--locked"]).env("CARGO_TARGET_DIR", &target_dir).current_dir(workspace());
            for (bin, package) in &missing {
                cmd.args(["-p", package, "--bin", bin]);
            }
            run_ok(&mut cmd);
        }
        let out_dir = tempfile::tempdir().unwrap();
        let t0 = Instant::now();
        run_ok(
            Command::new(&cargo_deb)
                .args(["--locked", "-p", "controller", "--no-build", "--profile", "dev", "--fast", "--output"])
                .arg(out_dir.path())
                .env("CARGO_TARGET_DIR", &target_dir)
                .env("PATH", path_with_cargo())
                .current_dir(workspace()),
        );
        let debs: Vec<PathBuf> = std::fs::read_dir(out_dir.path())
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|x| x == "deb"))
            .collect();
        assert_eq!(debs.len(), 1, "cargo deb should write one .deb: {debs:?}");
        let size = std::fs::metadata(&debs[0]).unwrap().len();
        eprintln!("{} ({:.1} MB) in {:.1} s", debs[0].display(), size as f64 / 1e6, t0.elapsed().as_secs_f64());
        let deb = debs[0].clone();
        (out_dir, deb)
    })
    .1
}

/// `dpkg-deb --field` of the package: field name -> value.
fn fields() -> BTreeMap<String, String> {
    let text = run_ok(Command::new("dpkg-deb").arg("--field").arg(deb()));
    let mut map = BTreeMap::new();
    let mut last = String::new();
    for line in text.lines() {
        if line.starts_with(' ') {
            map.entry(last.clone()).and_modify(|v: &mut String| v.push_str(line));
        } else if let Some((k, v)) = line.split_once(':') {
            last = k.trim().to_string();
            map.insert(last.clone(), v.trim().to_string());
        }
    }
    map
}

/// `dpkg-deb --contents`: path (without the leading ".") -> (mode string, owner/group).
fn contents() -> BTreeMap<String, (String, String)> {
    let text = run_ok(Command::new("dpkg-deb").arg("--contents").arg(deb()));
    text.lines()
        .map(|l| {
            let cols: Vec<&str> = l.split_whitespace().collect();
            let path = cols[5].trim_start_matches('.').trim_end_matches('/').to_string();
            (path, (cols[0].to_string(), cols[1].to_string()))
        })
        .collect()
}

#[test]
fn package_is_named_and_versioned_and_declares_its_conffiles() {
    let f = fields();
    assert_eq!(f["Package"], "comanip");
    assert_eq!(f["Version"], format!("{}-1", env!("CARGO_PKG_VERSION")));
    assert_eq!(f["Architecture"], "amd64");
    assert!(f["Depends"].contains("passwd"), "useradd comes from passwd: {:?}", f["Depends"]);
    assert!(f["Depends"].contains("libc6"), "the binaries link glibc: {:?}", f["Depends"]);
    let name = deb().file_name().unwrap().to_string_lossy().into_owned();
    assert_eq!(name, format!("comanip_{}-1_amd64.deb", env!("CARGO_PKG_VERSION")));

    let dir = tempfile::tempdir().unwrap();
    run_ok(Command::new("dpkg-deb").arg("--control").arg(deb()).arg(dir.path()));
    let conffiles = std::fs::read_to_string(dir.path().join("conffiles")).unwrap();
    let mut listed: Vec<&str> = conffiles.lines().collect();
    listed.sort_unstable();
    let mut expected = CONFFILES.to_vec();
    expected.sort_unstable();
    assert_eq!(listed, expected);
    for script in ["postinst", "prerm", "postrm"] {
        let p = dir.path().join(script);
        assert!(p.is_file(), "the package has no {script}");
        let text = std::fs::read_to_string(&p).unwrap();
        assert!(text.starts_with("#!/bin/sh\n"), "{script}: not a POSIX sh script");
        assert!(!text.contains("#DEBHELPER#"), "{script}: an unexpanded #DEBHELPER# token");
    }
}

#[test]
fn package_holds_the_binaries_units_configuration_header_and_docs() {
    let c = contents();
    for (bin, _) in BINARIES {
        let (mode, owner) = &c[&format!("/usr/bin/{bin}")];
        assert_eq!(mode, "-rwxr-xr-x", "/usr/bin/{bin}");
        assert_eq!(owner, "0/0", "/usr/bin/{bin} owned by root");
    }
    for unit in [
        "fulcrumd.service",
        "comanip-camera.service",
        "comanip-calib-live.service",
        "comanip-track.service",
        "comanip.target",
    ] {
        assert_eq!(c[&format!("/lib/systemd/system/{unit}")].0, "-rw-r--r--", "{unit}");
    }
    for conf in CONFFILES {
        assert_eq!(c[conf].0, "-rw-r--r--", "{conf}");
    }
    for doc in [
        "/usr/include/comanip/messages.h",
        "/usr/share/doc/comanip/README.md",
        "/usr/share/doc/comanip/copyright",
        "/usr/share/doc/comanip/docs/output.md",
        "/usr/share/doc/comanip/docs/systemd.md",
        "/usr/share/doc/comanip/docs/packaging.md",
        "/usr/share/doc/comanip/examples/python/fulcrum_subscriber.py",
        "/usr/share/doc/comanip/examples/rust/fulcrum_subscriber.rs",
    ] {
        assert!(c.contains_key(doc), "{doc} is not in the package");
    }
    // The packaged unit runs the packaged binary.
    let unit = std::fs::read_to_string(workspace().join("configs/systemd/fulcrumd.service")).unwrap();
    assert!(unit.contains("ExecStart=/usr/bin/fulcrumd "), "the unit must run /usr/bin/fulcrumd");
    // Nothing outside the places a package may use; no /usr/local, no /var (postinst makes it).
    let allowed =
        ["/usr/bin/", "/usr/include/comanip/", "/usr/share/doc/comanip/", "/lib/systemd/system/", "/etc/comanip/"];
    for (path, (mode, _)) in &c {
        if mode.starts_with('d') {
            continue;
        }
        assert!(allowed.iter().any(|a| path.starts_with(a)), "unexpected file in the package: {path}");
    }
}

#[test]
fn maintainer_scripts_pass_shellcheck() {
    let shellcheck = ensure_apt_tool("shellcheck", "shellcheck");
    let dir = tempfile::tempdir().unwrap();
    run_ok(Command::new("dpkg-deb").arg("--control").arg(deb()).arg(dir.path()));
    for script in ["postinst", "prerm", "postrm"] {
        let p = dir.path().join(script);
        run_ok(Command::new("sh").arg("-n").arg(&p));
        run_ok(Command::new(&shellcheck).args(["--shell=sh", "--severity=style"]).arg(&p));
    }
}

/// A scratch root that dpkg can install into: an empty dpkg database and the account files
/// useradd needs. `preexisting_user` adds a `comanip` user and group first.
fn scratch_root(preexisting_user: bool) -> tempfile::TempDir {
    let root = tempfile::tempdir().unwrap();
    let r = root.path();
    for d in ["var/lib/dpkg/info", "var/lib/dpkg/updates", "etc", "var/lib/other", "usr/sbin"] {
        std::fs::create_dir_all(r.join(d)).unwrap();
    }
    std::fs::write(r.join("var/lib/dpkg/status"), "").unwrap();
    std::fs::write(r.join("var/lib/dpkg/available"), "").unwrap();
    let (mut passwd, mut group, mut shadow, mut gshadow) = (
        "root:x:0:0:root:/root:/bin/bash\n".to_string(),
        "root:x:0:\n".to_string(),
        "root:*:19000:0:99999:7:::\n".to_string(),
        "root:*::\n".to_string(),
    );
    if preexisting_user {
        passwd.push_str("comanip:x:990:990:set up by hand:/var/lib/comanip:/usr/sbin/nologin\n");
        group.push_str("comanip:x:990:\n");
        shadow.push_str("comanip:!:19000::::::\n");
        gshadow.push_str("comanip:!::\n");
    }
    std::fs::write(r.join("etc/passwd"), passwd).unwrap();
    std::fs::write(r.join("etc/group"), group).unwrap();
    std::fs::write(r.join("etc/shadow"), shadow).unwrap();
    std::fs::write(r.join("etc/gshadow"), gshadow).unwrap();
    // Something the package must leave alone.
    std::fs::write(r.join("var/lib/other/keep"), "not comanip's").unwrap();
    root
}

fn dpkg(root: &Path, args: &[&str]) -> String {
    run_ok(
        Command::new("dpkg")
            .arg(format!("--root={}", root.display()))
            .args(["--force-script-chrootless", "--force-depends", "--log=/dev/null"])
            .args(args)
            .env("DEBIAN_FRONTEND", "noninteractive"),
    )
}

fn account(root: &Path, file: &str, name: &str) -> Option<Vec<String>> {
    let text = std::fs::read_to_string(root.join("etc").join(file)).unwrap();
    text.lines().find(|l| l.starts_with(&format!("{name}:"))).map(|l| l.split(':').map(str::to_string).collect())
}

fn host_accounts() -> String {
    ["/etc/passwd", "/etc/group"].iter().map(|f| std::fs::read_to_string(f).unwrap_or_default()).collect()
}

#[test]
fn install_creates_the_user_and_state_directory_and_purge_removes_exactly_those() {
    use std::os::unix::fs::MetadataExt;
    assert!(is_root(), "this test installs into a scratch root with dpkg and needs root (CI runs as root)");
    let deb = deb().to_path_buf();
    let host_before = host_accounts();
    let root = scratch_root(false);
    let r = root.path();
    dpkg(r, &["--install", deb.to_str().unwrap()]);

    let status = dpkg(r, &["--status", "comanip"]);
    assert!(status.contains("Status: install ok installed"), "{status}");
    for (bin, _) in BINARIES {
        assert!(r.join("usr/bin").join(bin).is_file(), "{bin} not installed");
    }
    let user = account(r, "passwd", "comanip").expect("postinst did not create the user comanip");
    let uid: u32 = user[2].parse().unwrap();
    assert!(uid < 1000, "comanip should be a system user, uid {uid}");
    assert_eq!(user[5], "/var/lib/comanip");
    assert_eq!(user[6], "/usr/sbin/nologin");
    let group = account(r, "group", "comanip").expect("postinst did not create the group comanip");
    assert_eq!(user[3], group[2], "the user's primary group is comanip");
    let state = std::fs::metadata(r.join("var/lib/comanip")).unwrap();
    assert!(state.is_dir());
    assert_eq!((state.uid(), state.gid()), (uid, group[2].parse().unwrap()));
    assert_eq!(state.mode() & 0o7777, 0o750);
    assert_eq!(host_accounts(), host_before, "the scripts touched this machine's accounts");

    // An operator edits a conffile and makes a recording: purge takes them too.
    std::fs::write(r.join("etc/comanip/fulcrumd.toml"), "[bus]\niface = \"can0\"\n").unwrap();
    std::fs::create_dir_all(r.join("var/lib/comanip/recordings")).unwrap();
    std::fs::write(r.join("var/lib/comanip/recordings/run.bin"), [0u8; 16]).unwrap();

    dpkg(r, &["--remove", "comanip"]);
    assert!(!r.join("usr/bin/fulcrumd").exists(), "remove leaves the binary");
    assert!(r.join("etc/comanip/fulcrumd.toml").exists(), "remove (not purge) must keep the conffiles");
    assert!(account(r, "passwd", "comanip").is_some(), "remove (not purge) must keep the user");
    assert!(r.join("var/lib/comanip/recordings/run.bin").exists(), "remove (not purge) must keep the recordings");

    dpkg(r, &["--purge", "comanip"]);
    assert!(account(r, "passwd", "comanip").is_none(), "purge left the user it created");
    assert!(account(r, "group", "comanip").is_none(), "purge left the group it created");
    assert!(!r.join("var/lib/comanip").exists(), "purge left /var/lib/comanip");
    assert!(!r.join("etc/comanip").exists(), "purge left /etc/comanip");
    assert!(!r.join("lib/systemd/system/fulcrumd.service").exists());
    assert_eq!(std::fs::read_to_string(r.join("var/lib/other/keep")).unwrap(), "not comanip's");
    assert!(account(r, "passwd", "root").is_some());
    assert_eq!(host_accounts(), host_before, "the scripts touched this machine's accounts");
}

#[test]
fn purge_keeps_a_user_and_directory_that_existed_before() {
    assert!(is_root(), "this test installs into a scratch root with dpkg and needs root (CI runs as root)");
    let deb = deb().to_path_buf();
    let root = scratch_root(true);
    let r = root.path();
    std::fs::create_dir_all(r.join("var/lib/comanip/recordings")).unwrap();
    std::fs::write(r.join("var/lib/comanip/recordings/old.bin"), [1u8; 8]).unwrap();
    let user_before = account(r, "passwd", "comanip").unwrap();

    dpkg(r, &["--install", deb.to_str().unwrap()]);
    assert_eq!(account(r, "passwd", "comanip").unwrap(), user_before, "postinst changed an existing user");
    dpkg(r, &["--purge", "comanip"]);
    assert_eq!(account(r, "passwd", "comanip").unwrap(), user_before, "purge removed a user it did not create");
    assert!(account(r, "group", "comanip").is_some(), "purge removed a group it did not create");
    assert!(r.join("var/lib/comanip/recordings/old.bin").exists(), "purge removed a directory it did not create");
    assert!(!r.join("var/lib/comanip/.created-by-package").exists(), "purge left its marker");
    assert!(!r.join("usr/bin/fulcrumd").exists());
}

#[test]
fn build_script_and_systemd_guest_scripts_pass_shellcheck() {
    // Not run by `cargo test` (packaging/build-deb builds in release; the guest takes minutes):
    // lint them so that they do not rot between their runs (docs/packaging.md, docs/systemd.md).
    let shellcheck = ensure_apt_tool("shellcheck", "shellcheck");
    for script in ["packaging/build-deb", "tests/hil/run-systemd-guest.sh", "tests/hil/systemd-guest-test.sh"] {
        let p = workspace().join(script);
        run_ok(Command::new("bash").arg("-n").arg(&p));
        run_ok(Command::new(&shellcheck).args(["--severity=style"]).arg(&p));
    }
}
