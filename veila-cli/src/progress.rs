//! Progress and logging shared by every command.
//!
//! On a terminal, bars are drawn on stderr and log lines (`tracing`, `-v` / `-q` / `RUST_LOG`) are
//! printed above them: every bar joins one `MultiProgress` and the log writer suspends it while a
//! line is written, so a message never tears a bar (what `indicatif-log-bridge` does for `log`,
//! in a few lines, with the indicatif we already use). When stderr is not a terminal (Slurm, CI,
//! a pipe), each bar prints a plain progress line at most every [`LINE_EVERY`] instead of nothing.
//! `--quiet` hides bars and lines.

use std::io::{IsTerminal, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, Instant};

use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle, TermLike};

static QUIET: AtomicBool = AtomicBool::new(false);

/// Every bar drawn on a terminal, so that log lines can be printed above them.
static MULTI: OnceLock<MultiProgress> = OnceLock::new();

/// The least time between two progress lines when stderr is not a terminal.
pub(crate) const LINE_EVERY: Duration = Duration::from_secs(5);

fn multi() -> &'static MultiProgress {
    MULTI.get_or_init(|| MultiProgress::with_draw_target(ProgressDrawTarget::stderr()))
}

/// Silence every progress bar created after this call.
pub(crate) fn set_quiet(quiet: bool) {
    QUIET.store(quiet, Ordering::Relaxed);
}

/// A progress bar of `len` steps with a message prefix: drawn on stderr on a terminal, a line
/// every few seconds otherwise, nothing when quiet.
pub(crate) fn bar(len: u64, prefix: &str) -> ProgressBar {
    let quiet = QUIET.load(Ordering::Relaxed);
    let tty = std::io::stderr().is_terminal();
    let pb = if quiet {
        ProgressBar::with_draw_target(Some(len), ProgressDrawTarget::hidden())
    } else if tty {
        multi().add(ProgressBar::new(len))
    } else {
        ProgressBar::with_draw_target(
            Some(len),
            ProgressDrawTarget::term_like(Box::new(LineTerm::new(LINE_EVERY))),
        )
    };
    let template = if tty {
        "{prefix:>10.bold} [{bar:30}] {pos}/{len} {per_sec} eta {eta} {msg}"
    } else {
        "{prefix:>10} {pos}/{len} ({percent}%) {per_sec} elapsed {elapsed} eta {eta} {msg}"
    };
    pb.set_style(
        ProgressStyle::with_template(template)
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb.set_prefix(prefix.to_string());
    pb
}

/// A `TermLike` that turns redraws into whole lines on stderr, at most one per `every` (the first
/// at once): the progress of a run whose stderr is a log file.
#[derive(Debug)]
struct LineTerm {
    every: Duration,
    last: Mutex<Option<Instant>>,
}

impl LineTerm {
    fn new(every: Duration) -> Self {
        LineTerm {
            every,
            last: Mutex::new(None),
        }
    }

    fn line(&self, s: &str) -> std::io::Result<()> {
        let s = s.trim_end();
        if s.is_empty() {
            return Ok(());
        }
        let mut last = self.last.lock().unwrap_or_else(|p| p.into_inner());
        if last.is_some_and(|t| t.elapsed() < self.every) {
            return Ok(());
        }
        *last = Some(Instant::now());
        writeln!(std::io::stderr().lock(), "{s}")
    }
}

impl TermLike for LineTerm {
    fn width(&self) -> u16 {
        160
    }
    fn move_cursor_up(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn move_cursor_down(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn move_cursor_right(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn move_cursor_left(&self, _: usize) -> std::io::Result<()> {
        Ok(())
    }
    fn write_line(&self, s: &str) -> std::io::Result<()> {
        self.line(s)
    }
    fn write_str(&self, s: &str) -> std::io::Result<()> {
        self.line(s)
    }
    fn clear_line(&self) -> std::io::Result<()> {
        Ok(())
    }
    fn flush(&self) -> std::io::Result<()> {
        std::io::stderr().flush()
    }
}

/// The `tracing` writer: whole lines on stderr, printed with the terminal's bars suspended.
#[derive(Debug, Default)]
pub(crate) struct LogWriter {
    buf: Vec<u8>,
}

impl Write for LogWriter {
    fn write(&mut self, data: &[u8]) -> std::io::Result<usize> {
        self.buf.extend_from_slice(data);
        Ok(data.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        if self.buf.is_empty() {
            return Ok(());
        }
        let buf = std::mem::take(&mut self.buf);
        let write = || std::io::stderr().lock().write_all(&buf);
        match MULTI.get() {
            Some(m) => m.suspend(write),
            None => write(),
        }
    }
}

impl Drop for LogWriter {
    fn drop(&mut self) {
        let _ = self.flush();
    }
}

/// Installs the `tracing` subscriber: `RUST_LOG` when set, else `info` for Veila's crates and
/// `warn` for the rest, one level more per `-v` and only errors with `-q`.
pub(crate) fn init_logging(verbose: u8, quiet: bool) {
    use tracing_subscriber::EnvFilter;
    let level = match (quiet, verbose) {
        (true, _) => "error",
        (false, 0) => "info",
        (false, 1) => "debug",
        (false, _) => "trace",
    };
    let filter = std::env::var("RUST_LOG")
        .ok()
        .filter(|v| !v.is_empty())
        .and_then(|v| EnvFilter::try_new(v).ok())
        .unwrap_or_else(|| {
            let veila = [
                "veila",
                "veila_geom",
                "veila_data",
                "veila_nn",
                "veila_diffusion",
                "veila_metrics",
            ]
            .map(|c| format!("{c}={level}"))
            .join(",");
            EnvFilter::new(format!("{},{veila}", if quiet { "error" } else { "warn" }))
        });
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_target(false)
        .without_time()
        .with_ansi(std::io::stderr().is_terminal())
        .with_writer(LogWriter::default)
        .try_init();
}

/// The process's peak resident set (`VmHWM` of `/proc/self/status`, Linux) in MiB.
pub(crate) fn peak_host_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}
