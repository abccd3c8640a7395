//! Building the new output folder: the command's files, and the files of the old one that are not its own.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use super::inputs::*;
use anyhow::{Context, Result, bail};

/// The staged folder gets the old folder's permissions, or the usual 0755 (a temporary folder is
/// created private).
pub(super) fn set_folder_mode(staged: &Path, old: Option<&Path>) {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = old
            .and_then(|o| std::fs::metadata(o).ok())
            .map_or(0o755, |m| m.permissions().mode());
        let _ = std::fs::set_permissions(staged, std::fs::Permissions::from_mode(mode));
    }
    #[cfg(not(unix))]
    let _ = (staged, old);
}

/// A relative path as the manifest writes it.
pub(super) fn rel_key(p: &Path) -> String {
    p.components()
        .map(|c| c.as_os_str().to_string_lossy())
        .collect::<Vec<_>>()
        .join("/")
}

/// Brings the old folder's files that are not the command's own into the staged folder.
pub(super) struct Merge<'a> {
    pub(super) old_root: &'a Path,
    pub(super) new_root: &'a Path,
    pub(super) out: &'a Path,
    pub(super) own_old: &'a BTreeSet<String>,
    pub(super) new_keys: &'a BTreeSet<String>,
    pub(super) inputs: &'a Inputs,
    pub(super) command: &'a str,
}

impl Merge<'_> {
    pub(super) fn dir(&self, rel: &Path) -> Result<()> {
        let old_dir = self.old_root.join(rel);
        let mut entries: Vec<_> = std::fs::read_dir(&old_dir)
            .with_context(|| format!("{}: cannot read", self.out.join(rel).display()))?
            .collect::<std::io::Result<_>>()
            .with_context(|| format!("{}: cannot read", self.out.join(rel).display()))?;
        entries.sort_by_key(|e| e.file_name());
        if entries.is_empty() && !rel.as_os_str().is_empty() {
            // an empty folder of the user's stays
            std::fs::create_dir_all(self.new_root.join(rel))
                .with_context(|| format!("{}: cannot create", self.new_root.display()))?;
        }
        for e in entries {
            let name = e.file_name();
            let r = rel.join(&name);
            let key = rel_key(&r);
            // the manifest is rewritten; leftovers of veila's own go with the old folder
            let plain = name.to_string_lossy();
            if (rel.as_os_str().is_empty() && plain == MANIFEST)
                || veila_data::atomic::is_leftover_name(&plain)
            {
                continue;
            }
            let shown = self.out.join(&r);
            let staged = self.new_root.join(&r);
            let is_dir = e.file_type().is_ok_and(|t| t.is_dir());
            if is_dir {
                if std::fs::symlink_metadata(&staged).is_ok_and(|m| !m.is_dir()) {
                    bail!(
                        "{}: exists and is a folder; `veila {}` would write a file there",
                        shown.display(),
                        self.command
                    );
                }
                self.dir(&r)?;
                continue;
            }
            if self.own_old.contains(&key) {
                // replaced or dropped: never an input
                if let Some(input) = self.inputs.which(&e.path()) {
                    bail!(
                        "{}: is the input {}; refusing to overwrite an input (choose another --out)",
                        shown.display(),
                        input.display()
                    );
                }
                continue;
            }
            if self.new_keys.contains(&key) || std::fs::symlink_metadata(&staged).is_ok() {
                bail!(
                    "{}: exists and was not written there by `veila {}`; --force replaces only its own earlier outputs (move the file away or choose another --out)",
                    shown.display(),
                    self.command
                );
            }
            if let Some(d) = staged.parent() {
                std::fs::create_dir_all(d)
                    .with_context(|| format!("{}: cannot create", d.display()))?;
            }
            // a hard link keeps the very file (no copy, no second inode)
            if std::fs::hard_link(e.path(), &staged).is_err() {
                std::fs::copy(e.path(), &staged).with_context(|| {
                    format!("{}: cannot keep it in the new output", shown.display())
                })?;
            }
        }
        Ok(())
    }
}

pub(super) fn is_empty_dir(p: &Path) -> Result<bool> {
    Ok(std::fs::read_dir(p)
        .with_context(|| format!("{}: cannot read directory", p.display()))?
        .next()
        .is_none())
}

/// Every file under `root/rel`, as paths relative to `root`.
pub(super) fn list_files(root: &Path, rel: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
    let dir = root.join(rel);
    let mut entries: Vec<_> = std::fs::read_dir(&dir)
        .with_context(|| format!("{}: cannot read", dir.display()))?
        .collect::<std::io::Result<_>>()?;
    entries.sort_by_key(|e| e.file_name());
    for e in entries {
        let r = rel.join(e.file_name());
        if e.file_type().is_ok_and(|t| t.is_dir()) {
            list_files(root, &r, out)?;
        } else {
            out.push(r);
        }
    }
    Ok(())
}

// ------------------------------------------------------------------------------ file outputs
