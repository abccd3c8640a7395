//! Progress bars of the long commands, the workspace they run in, and the command line a report
//! states.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use veila_diffusion::app::progress::{Bar, Progress};

/// The workspace root (xtask lives one level below it).
pub(crate) fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."))
}

/// This run's command line as a report states it (`cargo xtask bench-realism --model ...`).
pub(crate) fn command_line() -> String {
    std::iter::once("cargo xtask".to_string())
        .chain(std::env::args().skip(1))
        .collect::<Vec<_>>()
        .join(" ")
}

/// A path a command was given, relative to the workspace root (an absolute path stays as it is:
/// `Path::join` keeps it).
pub(crate) fn in_workspace(p: &Path) -> PathBuf {
    workspace_root().join(p)
}

/// A progress bar on stderr (hidden when stderr is not a terminal).
pub(crate) fn progress_bar(len: u64, label: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len);
    if let Ok(style) = indicatif::ProgressStyle::with_template(
        "{prefix:>24} [{bar:30}] {pos}/{len} {elapsed_precise} eta {eta} {msg}",
    ) {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_prefix(label.to_string());
    bar
}

/// The long runs of the libraries (`veila_diffusion::app::progress`) on the terminal: their lines
/// on stdout, their bars on stderr (hidden, with a line every 50 units of a bar with a status,
/// when stderr is not a terminal).
#[derive(Debug, Default)]
pub(crate) struct Terminal {
    /// The bar drawn now: lines are printed above it.
    current: Mutex<Option<indicatif::ProgressBar>>,
}

impl Progress for Terminal {
    fn line(&self, text: &str) {
        let current = self.current.lock().ok().and_then(|b| b.clone());
        match current.filter(|b| !b.is_finished()) {
            Some(bar) => bar.suspend(|| println!("{text}")),
            None => println!("{text}"),
        }
    }

    fn bar(&self, label: &str, total: u64) -> Box<dyn Bar + '_> {
        let bar = progress_bar(total, label);
        if let Ok(mut current) = self.current.lock() {
            *current = Some(bar.clone());
        }
        Box::new(TerminalBar(bar))
    }
}

/// A bar of [`Terminal`], cleared when dropped.
struct TerminalBar(indicatif::ProgressBar);

impl Bar for TerminalBar {
    fn inc(&self) {
        self.0.inc(1);
    }

    fn set(&self, done: u64, status: &str) {
        self.0.set_position(done);
        if self.0.is_hidden() && !status.is_empty() && (done.is_multiple_of(50) || done == 1) {
            eprintln!("  step {done} {status}");
        }
        self.0.set_message(status.to_string());
    }
}

impl Drop for TerminalBar {
    fn drop(&mut self) {
        self.0.finish_and_clear();
    }
}
