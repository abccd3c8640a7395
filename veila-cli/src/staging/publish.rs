//! Single files published beside their destinations (`--json` reports and the like).

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use super::inputs::*;
use super::lock::*;
use super::signals::*;
use anyhow::{Context, Result, bail};

/// Write every `(destination, bytes)` so that all appear or none does: all checks first (no
/// destination is an input or listed twice, none exists unless `force`, every folder exists or is
/// created when `create_dirs`), then the destination folders' locks and the checks again, then
/// locked temporary files beside each destination, then the renames.
pub(crate) fn publish_files(
    files: &[(PathBuf, Vec<u8>)],
    inputs: &Inputs,
    force: bool,
    create_dirs: bool,
) -> Result<()> {
    let dests: Vec<&Path> = files.iter().map(|(p, _)| p.as_path()).collect();
    check_outputs(&dests, inputs, force, create_dirs)?;
    let mut created: Vec<PathBuf> = Vec::new();
    let result = (|| {
        let mut locks = Vec::new();
        let mut seen = BTreeSet::new();
        for dest in &dests {
            let dir = parent_of(dest);
            if create_dirs && !dir.exists() {
                let mut missing = Vec::new();
                let mut d = dir.as_path();
                while !d.as_os_str().is_empty() && !d.exists() {
                    missing.push(d.to_path_buf());
                    d = d.parent().unwrap_or(Path::new(""));
                }
                std::fs::create_dir_all(&dir)
                    .with_context(|| format!("{}: cannot create", dir.display()))?;
                created.extend(missing.into_iter().rev());
            }
            let key = std::fs::canonicalize(&dir).unwrap_or(dir.clone());
            if seen.insert(key) {
                locks.extend(lock_files_folder(&dir)?);
            }
        }
        // a writer that finished while we waited is seen now
        check_outputs(&dests, inputs, force, create_dirs)?;
        write_and_rename(files)
    })();
    if result.is_err() {
        // folders this call made for outputs that never appeared
        for d in created.iter().rev() {
            let _ = std::fs::remove_dir(d);
        }
    }
    result
}

/// How long single-file outputs wait for another writer of their folder (another file publish
/// takes milliseconds; a folder output being staged takes minutes and is refused).
pub(super) const FILE_LOCK_WAIT: std::time::Duration = std::time::Duration::from_secs(5);

/// The lock of a folder that single files are written into, waiting up to [`FILE_LOCK_WAIT`] for
/// another writer; none where the folder's parent takes no lock file (a read-only parent such as
/// `/home`), as the folder itself may still be writable.
pub(super) fn lock_files_folder(dir: &Path) -> Result<Option<FolderLock>> {
    let start = std::time::Instant::now();
    loop {
        match try_lock_files_folder(dir) {
            Err(e) if is_busy(&e) && start.elapsed() < FILE_LOCK_WAIT => {
                std::thread::sleep(std::time::Duration::from_millis(50));
            }
            other => return other,
        }
    }
}

/// Whether `e` says another process holds an output's lock.
pub(super) fn is_busy(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        c.downcast_ref::<veila_data::Error>().is_some_and(|d| {
            matches!(d, veila_data::Error::Io { source, .. }
                if source.kind() == std::io::ErrorKind::WouldBlock)
        })
    })
}

pub(super) fn try_lock_files_folder(dir: &Path) -> Result<Option<FolderLock>> {
    match lock_folder(dir) {
        Ok(l) => {
            // the temporary files of killed writers into this folder
            sweep_stale(dir);
            Ok(Some(l))
        }
        Err(e) => {
            if is_busy(&e) {
                Err(e)
            } else {
                tracing::debug!("{}: written without a lock: {e:#}", dir.display());
                sweep_stale(dir);
                Ok(None)
            }
        }
    }
}

/// What `path` is when it exists and is neither a regular file, a directory nor a symbolic link
/// (a rename replaces a link itself, never what it points to): "a character device", "a FIFO"...
pub(super) fn special_file_kind(path: &Path) -> Option<&'static str> {
    let t = std::fs::symlink_metadata(path).ok()?.file_type();
    if t.is_file() || t.is_dir() || t.is_symlink() {
        return None;
    }
    Some(veila_data::read_capped::file_type_name(&t))
}

/// The checks of [`publish_files`] alone, so a command can refuse its outputs before it works.
pub(crate) fn check_outputs(
    dests: &[&Path],
    inputs: &Inputs,
    force: bool,
    create_dirs: bool,
) -> Result<()> {
    let mut seen: Vec<(PathBuf, &Path)> = Vec::new();
    for dest in dests.iter().copied() {
        inputs.check_output(dest)?;
        if dest.is_dir() {
            bail!("{}: exists and is a directory", dest.display());
        }
        if let Some(kind) = special_file_kind(dest) {
            bail!(
                "{}: exists and is {kind}, not a regular file: outputs replace only regular \
                 files, with or without --force",
                dest.display()
            );
        }
        if dest.exists() && !force {
            bail!("{}: exists (pass --force to replace it)", dest.display());
        }
        let dir = parent_of(dest);
        if !create_dirs && !dir.is_dir() {
            bail!(
                "{}: the folder {} does not exist",
                dest.display(),
                dir.display()
            );
        }
        // the same destination twice (`a.png` and `./a.png`) would lose one output
        let key = std::fs::canonicalize(&dir)
            .unwrap_or(dir.clone())
            .join(dest.file_name().unwrap_or_default());
        if let Some((_, other)) = seen.iter().find(|(k, _)| *k == key) {
            bail!(
                "{} and {} are the same file: give each output its own name",
                other.display(),
                dest.display()
            );
        }
        seen.push((key, dest));
    }
    Ok(())
}

pub(super) fn write_and_rename(files: &[(PathBuf, Vec<u8>)]) -> Result<()> {
    use std::io::Write;
    let mut staged = Vec::with_capacity(files.len());
    for (dest, bytes) in files {
        let mut tmp = veila_data::atomic::locked_temp_beside(dest)
            .with_context(|| format!("{}: cannot write", dest.display()))?;
        register(Live::File {
            tmp: tmp.path().to_path_buf(),
            dest: dest.clone(),
        });
        let written = tmp
            .as_file_mut()
            .write_all(bytes)
            .and_then(|_| tmp.as_file().sync_all());
        if let Err(e) = written {
            unregister(tmp.path());
            return Err(e).with_context(|| format!("{}: cannot write", dest.display()));
        }
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let _ = tmp
                .as_file()
                .set_permissions(std::fs::Permissions::from_mode(0o644));
        }
        staged.push((tmp, dest));
    }
    let swap = lock(&PUBLISH);
    let mut result = Ok(());
    for (tmp, dest) in staged {
        let path = tmp.path().to_path_buf();
        if result.is_ok()
            && let Err(e) = tmp.persist(dest)
        {
            result =
                Err(e.error).with_context(|| format!("{}: cannot move into place", dest.display()));
        }
        unregister(&path);
    }
    if result.is_ok() {
        lock(&PUBLISHED).extend(files.iter().map(|(p, _)| p.clone()));
    }
    drop(swap);
    result
}
