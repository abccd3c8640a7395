//! What a command reads (by device and inode) and where its outputs may go.

use std::path::{Path, PathBuf};

use anyhow::{Result, bail};

/// The record of what each command wrote into a folder output.
pub(crate) const MANIFEST: &str = ".veila-outputs.json";

/// Identity of a file: device and inode (Unix), else its canonical path.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub(super) struct FileId {
    #[cfg(unix)]
    dev_ino: (u64, u64),
    #[cfg(not(unix))]
    canonical: PathBuf,
}

pub(super) fn file_id(path: &Path) -> Option<FileId> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        let m = std::fs::metadata(path).ok()?;
        Some(FileId {
            dev_ino: (m.dev(), m.ino()),
        })
    }
    #[cfg(not(unix))]
    {
        Some(FileId {
            canonical: std::fs::canonicalize(path).ok()?,
        })
    }
}

/// The files a command reads, by identity.
#[derive(Debug, Default, Clone)]
pub(crate) struct Inputs {
    files: Vec<(FileId, PathBuf)>,
}

impl Inputs {
    /// No inputs yet.
    pub(crate) fn new() -> Self {
        Self::default()
    }

    /// Record an input (a missing one is ignored here: reading it reports the error).
    pub(crate) fn add(&mut self, path: &Path) -> &mut Self {
        if let Some(id) = file_id(path) {
            self.files.push((id, path.to_path_buf()));
        }
        self
    }

    /// Record every input of a list.
    pub(crate) fn extend<'a>(&mut self, paths: impl IntoIterator<Item = &'a PathBuf>) -> &mut Self {
        for p in paths {
            self.add(p);
        }
        self
    }

    /// Inputs given as optional arguments.
    pub(crate) fn add_opt(&mut self, path: Option<&PathBuf>) -> &mut Self {
        if let Some(p) = path {
            self.add(p);
        }
        self
    }

    /// The input `path` is, when it is one (same device and inode, whatever the spelling).
    pub(crate) fn which(&self, path: &Path) -> Option<&Path> {
        let id = file_id(path)?;
        self.files
            .iter()
            .find(|(i, _)| *i == id)
            .map(|(_, p)| p.as_path())
    }

    /// Refuse `out` when it is one of the inputs.
    pub(crate) fn check_output(&self, out: &Path) -> Result<()> {
        if let Some(input) = self.which(out) {
            bail!(
                "{}: is the input {}; refusing to overwrite an input (choose another output)",
                out.display(),
                input.display()
            );
        }
        Ok(())
    }
}

/// Refuse an output whose name does not end in one of `exts` (lowercase, without the dot).
pub(crate) fn check_ext(path: &Path, what: &str, exts: &[&str]) -> Result<()> {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    if exts.iter().any(|e| name.ends_with(&format!(".{e}"))) {
        return Ok(());
    }
    let list: Vec<String> = exts.iter().map(|e| format!(".{e}")).collect();
    bail!(
        "{}: {what} must be named for the format written: end in {}",
        path.display(),
        list.join(" or ")
    )
}

// ------------------------------------------------------------------------------- folder locks

pub(super) fn parent_of(p: &Path) -> PathBuf {
    match p.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    }
}
