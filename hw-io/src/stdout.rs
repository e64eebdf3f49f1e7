//! Standard output of the command-line tools (`simrobot`, `fulcrumd` and its subcommands,
//! `comanip-bench`, `comanip-calib`), written so that a reader that goes away (`simrobot
//! generate ... | head -1`) ends the tool quietly instead of with a panic.
//!
//! Rust ignores `SIGPIPE`, so a write to a closed pipe fails with `EPIPE`, and `println!`
//! panics on it. The tools write through [`outln!`](crate::outln) instead, which returns the
//! error; they stop what they are doing, finish their files, and exit with
//! [`BROKEN_PIPE_EXIT`] and no message ([`is_broken_pipe`]), as a C tool killed by `SIGPIPE`
//! looks to a shell.

use std::fmt;
use std::io::{self, Write};

/// Exit status of a tool whose standard output was closed by its reader: 128 + `SIGPIPE`
/// (13), what a shell reports for a C tool killed by `SIGPIPE`.
pub const BROKEN_PIPE_EXIT: u8 = 141;

/// Writes `args` and a newline to the locked standard output and flushes it, so that a
/// closed pipe is reported by this very call.
pub fn write_line(args: fmt::Arguments<'_>) -> io::Result<()> {
    let mut out = io::stdout().lock();
    out.write_fmt(args)?;
    out.write_all(b"\n")?;
    out.flush()
}

/// True when `e` says that the reader of the standard output went away (`EPIPE`).
pub fn is_broken_pipe(e: &io::Error) -> bool {
    e.kind() == io::ErrorKind::BrokenPipe
}

/// `println!` that returns the `io::Result` of the write instead of panicking (see the
/// [module](crate::stdout) documentation).
#[macro_export]
macro_rules! outln {
    ($($arg:tt)*) => {
        $crate::stdout::write_line(::std::format_args!($($arg)*))
    };
}
