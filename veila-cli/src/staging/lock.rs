//! The exclusive lock of an output folder, and what a killed earlier owner left in it.

use std::path::Path;

use anyhow::{Context, Result};

pub(crate) use veila_data::atomic::{OutputLock, sweep_stale};

use super::inputs::*;
use super::signals::*;

/// The exclusive lock of an output folder, held by this process: its lock file goes with a
/// signal too.
#[derive(Debug)]
pub(crate) struct FolderLock {
    lock: Option<OutputLock>,
}

/// Take the exclusive lock of the folder `out` (present or not; its parent is created), finish
/// what a killed earlier owner of it left ([`OutputLock::recover`]) and sweep the ownerless
/// leftovers beside it. A second writer gets an error naming `out`.
pub(crate) fn lock_folder(out: &Path) -> Result<FolderLock> {
    let parent = parent_of(out);
    std::fs::create_dir_all(&parent)
        .with_context(|| format!("{}: cannot create", parent.display()))?;
    let l = OutputLock::acquire(out)?;
    register(Live::Lock(l.lock_path().to_path_buf()));
    let held = FolderLock { lock: Some(l) };
    held.held()
        .recover()
        .with_context(|| format!("{}: recovering an interrupted earlier run", out.display()))?;
    sweep_stale(held.held().parent());
    Ok(held)
}

impl FolderLock {
    pub(super) fn held(&self) -> &OutputLock {
        self.lock.as_ref().expect("lock held until dropped")
    }
}

impl Drop for FolderLock {
    fn drop(&mut self) {
        if let Some(l) = self.lock.take() {
            unregister(l.lock_path());
        }
    }
}

/// Remove the entries of `dir` (the locked folder or one inside it) that `is_partial` recognises
/// as the partial files of a killed earlier owner (`.step-N.tmp-PID`, `.bundle.tmp-PID`): the lock
/// proves nobody else writes them. Returns how many were removed.
pub(crate) fn remove_partial(
    _held: &FolderLock,
    dir: &Path,
    is_partial: impl Fn(&str) -> bool,
) -> Result<usize> {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return Ok(0);
    };
    let mut n = 0;
    for e in rd.flatten() {
        if !is_partial(&e.file_name().to_string_lossy()) {
            continue;
        }
        let p = e.path();
        if e.file_type().is_ok_and(|t| t.is_dir()) {
            std::fs::remove_dir_all(&p)
        } else {
            std::fs::remove_file(&p)
        }
        .with_context(|| format!("{}: cannot remove a killed run's partial file", p.display()))?;
        n += 1;
    }
    Ok(n)
}

/// The highest `N` of the `step-N` checkpoint folders in `dir` or a folder inside it.
pub(super) fn newest_checkpoint_step(dir: &Path) -> Option<u64> {
    let step = |p: &Path| -> Option<u64> {
        std::fs::read_dir(p)
            .ok()?
            .flatten()
            .filter_map(|e| {
                e.file_name()
                    .to_str()?
                    .strip_prefix("step-")?
                    .parse::<u64>()
                    .ok()
            })
            .max()
    };
    let inner = std::fs::read_dir(dir)
        .ok()?
        .flatten()
        .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
        .filter_map(|e| step(&e.path()));
    step(dir).or_else(|| inner.max())
}

// ---------------------------------------------------------------------------- folder outputs
