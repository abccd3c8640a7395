//! Standard output that never panics.
//!
//! `print!` and `println!` panic when standard output cannot be written (a full disk, `/dev/full`).
//! This module's macros of the same names, in scope in the whole binary, write through
//! [`write_fmt`] instead: the first failed write is remembered, later prints are skipped, and
//! [`finish`] (at the end of `main`) turns it into an error and a non-zero exit. A command whose
//! output files were already published keeps them; only its report to standard output is lost.
//! A closed pipe still ends the process quietly (the default SIGPIPE disposition, see `main`).

use std::io::Write;
use std::sync::Mutex;

use anyhow::{Result, anyhow};

/// The first error of a write to standard output.
static FAILED: Mutex<Option<std::io::Error>> = Mutex::new(None);

/// Writes to standard output, remembering the first failure instead of panicking.
pub(crate) fn write_fmt(args: std::fmt::Arguments<'_>) {
    let mut failed = FAILED.lock().unwrap_or_else(|e| e.into_inner());
    if failed.is_some() {
        return;
    }
    if let Err(e) = std::io::stdout().lock().write_fmt(args) {
        *failed = Some(e);
    }
}

/// Writes `bytes` to standard output ([`write_fmt`]'s rules).
pub(crate) fn write_bytes(bytes: &[u8]) {
    let mut failed = FAILED.lock().unwrap_or_else(|e| e.into_inner());
    if failed.is_some() {
        return;
    }
    if let Err(e) = std::io::stdout().lock().write_all(bytes) {
        *failed = Some(e);
    }
}

/// Flushes standard output; an error when any write to it failed.
pub(crate) fn finish() -> Result<()> {
    let flushed = std::io::stdout().lock().flush();
    let failed = FAILED.lock().unwrap_or_else(|e| e.into_inner()).take();
    match failed.map_or(flushed, Err) {
        Ok(()) => Ok(()),
        Err(e) => Err(anyhow!("cannot write to standard output: {e}")),
    }
}

/// `print!` through [`write_fmt`].
macro_rules! print {
    ($($arg:tt)*) => {
        $crate::out::write_fmt(format_args!($($arg)*))
    };
}

/// `println!` through [`write_fmt`].
macro_rules! println {
    () => {
        $crate::out::write_fmt(format_args!("\n"))
    };
    ($($arg:tt)*) => {
        $crate::out::write_fmt(format_args!("{}\n", format_args!($($arg)*)))
    };
}
