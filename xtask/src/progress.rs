//! Progress bars of the long commands, the workspace they run in, and the run a report states.

use std::path::{Path, PathBuf};

use veila_diffusion::app::BundleConfig;
use veila_diffusion::app::sim_examples::{self, RenderStyle, SimExample};

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

/// The CPU cores this run may use, as a report states them.
pub(crate) fn cpu_cores() -> usize {
    std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1)
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

/// [`sim_examples::render_split_styled`] of a list relative to the workspace, behind a progress
/// bar named `label`.
pub(crate) fn render_split(
    list: &Path,
    n: usize,
    cfg: &BundleConfig,
    style: &RenderStyle,
    label: &str,
) -> anyhow::Result<Vec<SimExample>> {
    let bar = progress_bar(n as u64, label);
    let out =
        sim_examples::render_split_styled(&workspace_root().join(list), n, cfg, style, &|| {
            bar.inc(1)
        });
    bar.finish_and_clear();
    Ok(out?)
}
