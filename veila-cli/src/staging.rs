//! Output folders that appear whole or not at all.
//!
//! A command renders into a staging folder beside its `--out` folder and moves the result into place
//! only when everything succeeded, so a failure (or Ctrl-C) leaves no partial output behind.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

/// A staging folder for one output folder.
#[derive(Debug)]
pub(crate) struct Staged {
    out: PathBuf,
    dir: tempfile::TempDir,
    existed: bool,
}

/// Check `out` (a directory that is absent, empty, or non-empty with `force`) and create its staging
/// folder next to it.
pub(crate) fn stage(out: &Path, force: bool) -> Result<Staged> {
    let existed = out.exists();
    if existed && !out.is_dir() {
        bail!("{}: exists and is not a directory", out.display());
    }
    if existed && !force && !is_empty_dir(out)? {
        bail!(
            "{}: exists and is not empty (choose another --out or pass --force)",
            out.display()
        );
    }
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent)
        .with_context(|| format!("{}: cannot create", parent.display()))?;
    let dir = tempfile::Builder::new()
        .prefix(".veila-staging-")
        .tempdir_in(&parent)
        .with_context(|| format!("{}: cannot create a staging directory", parent.display()))?;
    Ok(Staged {
        out: out.to_path_buf(),
        dir,
        existed,
    })
}

impl Staged {
    /// Where to write.
    pub(crate) fn path(&self) -> &Path {
        self.dir.path()
    }

    /// Move the staged files into place (a rename of the whole folder when `out` did not exist).
    pub(crate) fn commit(self) -> Result<()> {
        if self.existed {
            merge_into(self.dir.path(), &self.out)
        } else {
            let staged = self.dir.keep();
            std::fs::rename(&staged, &self.out).with_context(|| {
                format!("{}: cannot move the output into place", self.out.display())
            })
        }
    }
}

fn is_empty_dir(p: &Path) -> Result<bool> {
    Ok(std::fs::read_dir(p)
        .with_context(|| format!("{}: cannot read directory", p.display()))?
        .next()
        .is_none())
}

/// Move every file under `from` to the same relative path under `to` (renames within one file system).
fn merge_into(from: &Path, to: &Path) -> Result<()> {
    for entry in
        std::fs::read_dir(from).with_context(|| format!("{}: cannot read", from.display()))?
    {
        let entry = entry?;
        let src = entry.path();
        let dst = to.join(entry.file_name());
        if src.is_dir() {
            std::fs::create_dir_all(&dst)
                .with_context(|| format!("{}: cannot create", dst.display()))?;
            merge_into(&src, &dst)?;
        } else {
            std::fs::rename(&src, &dst)
                .with_context(|| format!("{}: cannot move into place", dst.display()))?;
        }
    }
    Ok(())
}
