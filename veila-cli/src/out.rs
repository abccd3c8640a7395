//! Standard output that never panics.
//!
//! `print!` and `println!` panic when standard output cannot be written (a full disk, `/dev/full`).
//! This module's macros of the same names, in scope in the whole binary, write through
//! [`write_fmt`] instead: the first failed write is remembered, later prints are skipped, and
//! [`finish`] (at the end of `main`) turns it into an error and a non-zero exit. A command whose
//! output files were already published keeps them; only its report to standard output is lost.
//! A closed pipe still ends the process quietly (the default SIGPIPE disposition, see `main`).
//!
//! Text from files (a bundle's `name`, a calibration line, a token, a path inside an artifact)
//! may hold terminal control sequences: a downloaded file must not clear the screen or print
//! lines of its own. Everything these macros and [`eprintln!`] print has its control characters
//! escaped ([`escape_controls`]; line breaks and tabs stay, so the commands' own layout does),
//! and a single-line field from a file is printed through [`untrusted`], which escapes line
//! breaks too. The error `main` prints goes through [`escape_controls`] as well.

use std::borrow::Cow;
use std::io::Write;
use std::sync::Mutex;

use anyhow::{Result, anyhow};

/// The first error of a write to standard output.
static FAILED: Mutex<Option<std::io::Error>> = Mutex::new(None);

/// Whether `c` is printed escaped: a C0 or C1 control character or DEL (terminal commands start
/// with ESC, CSI U+009B, BEL ends some; a carriage return or backspace overwrites what is shown),
/// or a bidirectional-text control (U+202A-U+202E, U+2066-U+2069), which reorders what is shown.
/// `keep_lines` keeps `\n` and `\t`.
fn escaped(c: char, keep_lines: bool) -> bool {
    if keep_lines && (c == '\n' || c == '\t') {
        return false;
    }
    c.is_control() || matches!(c, '\u{202a}'..='\u{202e}' | '\u{2066}'..='\u{2069}')
}

fn escape(s: &str, keep_lines: bool) -> Cow<'_, str> {
    if !s.chars().any(|c| escaped(c, keep_lines)) {
        return Cow::Borrowed(s);
    }
    let mut out = String::with_capacity(s.len() + 8);
    for c in s.chars() {
        if escaped(c, keep_lines) {
            // `\n`, `\r`, `\t` as such, the others as `\u{1b}`; other text, Unicode included, as is
            out.extend(c.escape_debug());
        } else {
            out.push(c);
        }
    }
    Cow::Owned(out)
}

/// `s` with every control character escaped but line breaks and tabs: what the print macros
/// write, and how `main` prints an error.
pub(crate) fn escape_controls(s: &str) -> Cow<'_, str> {
    escape(s, true)
}

/// A single-line text from a file (a bundle's `name`, a scene's or config's name) for printing:
/// every control character escaped, line breaks included, so the text stays on its line; other
/// Unicode stays readable (unlike `{:?}`, which also quotes and escapes quotes).
pub(crate) fn untrusted(s: &str) -> Cow<'_, str> {
    escape(s, false)
}

/// Writes to standard output, remembering the first failure instead of panicking; control
/// characters are escaped ([`escape_controls`]).
pub(crate) fn write_fmt(args: std::fmt::Arguments<'_>) {
    let mut failed = FAILED.lock().unwrap_or_else(|e| e.into_inner());
    if failed.is_some() {
        return;
    }
    let text = std::fmt::format(args);
    if let Err(e) = std::io::stdout()
        .lock()
        .write_all(escape_controls(&text).as_bytes())
    {
        *failed = Some(e);
    }
}

/// Writes a line to standard error with control characters escaped ([`escape_controls`]); a
/// failure is ignored (there is nowhere left to report it), where `std::eprintln!` panics.
pub(crate) fn write_err_line(args: std::fmt::Arguments<'_>) {
    let mut text = std::fmt::format(args);
    text.push('\n');
    let _ = std::io::stderr()
        .lock()
        .write_all(escape_controls(&text).as_bytes());
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

/// `eprintln!` through [`write_err_line`].
macro_rules! eprintln {
    () => {
        $crate::out::write_err_line(format_args!(""))
    };
    ($($arg:tt)*) => {
        $crate::out::write_err_line(format_args!($($arg)*))
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn control_characters_are_escaped_and_other_text_kept() {
        let hostile = "default\x1b[2J\x1b[H\rFAKE: all checks passed\u{7}\u{9b}31m\u{202e}txt.exe";
        let e = untrusted(hostile);
        assert_eq!(
            e,
            "default\\u{1b}[2J\\u{1b}[H\\rFAKE: all checks passed\\u{7}\\u{9b}31m\\u{202e}txt.exe"
        );
        assert!(!e.chars().any(|c| escaped(c, false)));
        // line breaks: escaped in a single-line field, kept in printed text
        assert_eq!(untrusted("a\nb\tc"), "a\\nb\\tc");
        assert_eq!(escape_controls("a\nb\tc\x1b"), "a\nb\tc\\u{1b}");
        // readable Unicode and quotes stay as they are, without a copy
        for plain in ["Straße 🚗 «β» \"q\" 'x' \\", "模型"] {
            assert!(matches!(untrusted(plain), Cow::Borrowed(_)), "{plain}");
            assert_eq!(untrusted(plain), plain);
        }
    }
}
