//! Size and reach rules of the sources: the binary's files stay small (every `veila-cli` source
//! file at most [`CLI_MAX_LINES`] lines: logic beyond plumbing belongs in a library), xtask stays
//! automation (at most [`XTASK_MAX_LINES`] lines in all: a benchmark's logic lives in the library
//! it measures, its command is a thin driver), and no
//! source file includes another's by `#[path]` (a file shared by two crates belongs in a library
//! both depend on).

use std::path::{Path, PathBuf};

/// The most lines a `veila-cli` source file may have.
pub(super) const CLI_MAX_LINES: usize = 600;

/// The most lines xtask's sources may have together.
pub(super) const XTASK_MAX_LINES: usize = 5_000;

/// The `.rs` files under `dir`, recursively, sorted.
pub(super) fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for entry in entries.flatten() {
            let path = entry.path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                out.push(path);
            }
        }
    }
    out.sort();
    out
}

/// `path (N lines)` for every file under `dir` longer than `max` lines.
fn long_files(dir: &Path, max: usize) -> Vec<String> {
    rust_files(dir)
        .into_iter()
        .filter_map(|p| {
            let n = std::fs::read_to_string(&p).ok()?.lines().count();
            (n > max).then(|| format!("{} ({n} lines)", p.display()))
        })
        .collect()
}

/// The lines of every file under `dir`, together.
fn total_lines(dir: &Path) -> usize {
    rust_files(dir)
        .iter()
        .filter_map(|p| std::fs::read_to_string(p).ok())
        .map(|text| text.lines().count())
        .sum()
}

/// `path: line` for every `#[path = ...]` attribute in the files under `dirs`.
fn path_includes(dirs: &[PathBuf]) -> Vec<String> {
    dirs.iter()
        .flat_map(|d| rust_files(d))
        .flat_map(|p| {
            let text = std::fs::read_to_string(&p).unwrap_or_default();
            text.lines()
                .filter(|l| {
                    let l = l.trim_start();
                    l.starts_with("#[path") && l[6..].trim_start().starts_with('=')
                })
                .map(|l| format!("{}: {}", p.display(), l.trim()))
                .collect::<Vec<_>>()
        })
        .collect()
}

/// The source folders of every crate of the workspace (and of the Python extension).
fn crate_dirs() -> Vec<PathBuf> {
    let root = super::workspace_root();
    [
        "veila-geom",
        "veila-data",
        "veila-nn",
        "veila-diffusion",
        "veila-metrics",
        "veila-cli",
        "xtask",
        "python",
    ]
    .iter()
    .flat_map(|c| ["src", "tests", "benches", "examples"].map(|s| root.join(c).join(s)))
    .filter(|d| d.is_dir())
    .collect()
}

#[test]
fn cli_files_stay_small() {
    let long = long_files(
        &super::workspace_root().join("veila-cli/src"),
        CLI_MAX_LINES,
    );
    assert!(
        long.is_empty(),
        "veila-cli files over {CLI_MAX_LINES} lines (move the logic into a library):\n{}",
        long.join("\n")
    );
}

#[test]
fn xtask_stays_automation() {
    let n = total_lines(&super::workspace_root().join("xtask/src"));
    assert!(
        n <= XTASK_MAX_LINES,
        "xtask has {n} lines, over {XTASK_MAX_LINES}: move benchmark and recipe logic into the library it belongs to, and keep the command a thin driver"
    );
}

#[test]
fn no_path_includes() {
    let hits = path_includes(&crate_dirs());
    assert!(
        hits.is_empty(),
        "#[path] includes (share the code through a library instead):\n{}",
        hits.join("\n")
    );
}

#[test]
fn size_and_path_checks_catch_planted_files() {
    let dir = tempfile::tempdir().expect("temporary folder");
    std::fs::create_dir_all(dir.path().join("sub")).unwrap();
    std::fs::write(dir.path().join("short.rs"), "fn a() {}\n".repeat(3)).unwrap();
    std::fs::write(dir.path().join("sub/long.rs"), "fn a() {}\n".repeat(7)).unwrap();
    std::fs::write(
        dir.path().join("inc.rs"),
        "// #[path] in a comment is fine\n    #[path = \"../../other/src/x.rs\"]\nmod x;\n",
    )
    .unwrap();
    let long = long_files(dir.path(), 5);
    assert_eq!(long.len(), 1, "{long:?}");
    assert_eq!(total_lines(dir.path()), 3 + 7 + 3);
    assert!(long[0].contains("long.rs (7 lines)"), "{long:?}");
    let inc = path_includes(&[dir.path().to_path_buf()]);
    assert_eq!(inc.len(), 1, "{inc:?}");
    assert!(
        inc[0].contains("inc.rs") && inc[0].contains("../../other"),
        "{inc:?}"
    );
}
