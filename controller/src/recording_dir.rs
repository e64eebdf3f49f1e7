//! Where the flight recorder writes when the packaged default cannot be written.
//!
//! The packaged configuration records to `/var/lib/comanip/recordings` (the systemd unit's
//! `StateDirectory`). A newcomer who runs the demo as an ordinary user cannot write there;
//! rather than stop, the daemon records to the user's state directory
//! (`$XDG_STATE_HOME/comanip/recordings`, else `~/.local/state/comanip/recordings`) with one
//! warning line, as the real-time set-up already degrades with a warning. A directory the
//! operator configured explicitly that cannot be written stays an error: they asked for it.

use std::ffi::OsString;
use std::fs;
use std::io;
use std::path::{Path, PathBuf};

/// The packaged default recording directory (`[recorder] dir`).
pub const PACKAGED_DIR: &str = "/var/lib/comanip/recordings";

/// Why no recording directory could be chosen.
#[derive(Debug, thiserror::Error)]
pub enum RecordingDirError {
    /// The packaged default cannot be written and the user has no state directory.
    #[error(
        "recorder: cannot write {packaged} ({source}), and neither XDG_STATE_HOME nor HOME is set for a fallback \
         (set recorder.dir, or run with --no-record)"
    )]
    NoFallback {
        /// The packaged default.
        packaged: PathBuf,
        /// Why it cannot be written.
        source: io::Error,
    },
}

/// The chosen directory, and a warning to print when it is the fallback.
#[derive(Debug)]
pub struct Chosen {
    /// Where to record.
    pub dir: PathBuf,
    /// Set when the packaged default could not be written: one line saying why and where
    /// the recordings go instead.
    pub warning: Option<String>,
}

/// Can `dir` be created and written? (Creates it, and a probe file it removes.)
pub fn writable(dir: &Path) -> io::Result<()> {
    fs::create_dir_all(dir)?;
    let probe = dir.join(format!(".comanip-write-probe-{}", std::process::id()));
    fs::write(&probe, b"")?;
    fs::remove_file(&probe)
}

/// The user's state directory for recordings: `$XDG_STATE_HOME/comanip/recordings` when
/// `XDG_STATE_HOME` is an absolute path, else `$HOME/.local/state/comanip/recordings`.
pub fn user_state_dir(xdg_state_home: Option<OsString>, home: Option<OsString>) -> Option<PathBuf> {
    let xdg = xdg_state_home.map(PathBuf::from).filter(|p| p.is_absolute());
    let base = match xdg {
        Some(p) => p,
        None => PathBuf::from(home.filter(|h| !h.is_empty())?).join(".local/state"),
    };
    Some(base.join("comanip/recordings"))
}

/// Chooses the recording directory: `configured` when it is not the packaged default
/// (`packaged`; errors are then the recorder's own, at start), or when it can be written;
/// otherwise the user's state directory, with a warning. Not for the real-time loop.
pub fn choose(
    configured: &Path,
    packaged: &Path,
    xdg_state_home: Option<OsString>,
    home: Option<OsString>,
) -> Result<Chosen, RecordingDirError> {
    if configured != packaged {
        return Ok(Chosen { dir: configured.to_path_buf(), warning: None });
    }
    let source = match writable(configured) {
        Ok(()) => return Ok(Chosen { dir: configured.to_path_buf(), warning: None }),
        Err(e) => e,
    };
    let Some(dir) = user_state_dir(xdg_state_home, home) else {
        return Err(RecordingDirError::NoFallback { packaged: packaged.to_path_buf(), source });
    };
    let warning = format!(
        "flight recorder: cannot write {} ({source}); recording to {} instead (set recorder.dir to choose)",
        packaged.display(),
        dir.display()
    );
    Ok(Chosen { dir, warning: Some(warning) })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("comanip-recdir-{}-{name}", std::process::id()));
        let _ = fs::remove_dir_all(&d);
        fs::create_dir_all(&d).unwrap();
        d
    }

    /// A directory nobody can create, root included: its parent is a regular file.
    fn unwritable(base: &Path) -> PathBuf {
        let file = base.join("not-a-dir");
        fs::write(&file, b"x").unwrap();
        file.join("recordings")
    }

    #[test]
    fn an_unwritable_packaged_default_falls_back_to_the_user_state_dir_with_a_warning() {
        let base = scratch("fallback");
        let packaged = unwritable(&base);
        let state = base.join("state");
        let c = choose(&packaged, &packaged, Some(state.clone().into()), None).unwrap();
        assert_eq!(c.dir, state.join("comanip/recordings"));
        let w = c.warning.expect("a warning line");
        assert!(w.contains(&packaged.display().to_string()) && w.contains("recording to"), "{w}");
        // Without XDG_STATE_HOME: ~/.local/state.
        let c = choose(&packaged, &packaged, None, Some(base.join("home").into())).unwrap();
        assert_eq!(c.dir, base.join("home/.local/state/comanip/recordings"));
        // A relative XDG_STATE_HOME is ignored (the XDG rule).
        let c = choose(&packaged, &packaged, Some("rel".into()), Some(base.join("home").into())).unwrap();
        assert_eq!(c.dir, base.join("home/.local/state/comanip/recordings"));
        // Neither: a typed error naming the way out.
        let e = choose(&packaged, &packaged, None, None).unwrap_err();
        assert!(e.to_string().contains("--no-record"), "{e}");
    }

    #[test]
    fn an_explicit_or_writable_directory_is_kept() {
        let base = scratch("keep");
        let packaged = base.join("packaged");
        // The packaged default, writable: kept, no warning.
        let c = choose(&packaged, &packaged, Some(base.join("state").into()), None).unwrap();
        assert_eq!(c.dir, packaged);
        assert!(c.warning.is_none());
        // An explicit directory is kept even when it cannot be written: the recorder's start
        // then fails with its own error (the operator asked for it).
        let explicit = unwritable(&base);
        let c = choose(&explicit, &packaged, Some(base.join("state").into()), None).unwrap();
        assert_eq!(c.dir, explicit);
        assert!(c.warning.is_none());
    }
}
