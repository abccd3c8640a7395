//! The output discipline every command follows: nothing the user had is ever lost, and an output
//! is wholly old or wholly new whatever happens to the process.
//!
//! The API the commands call (names kept stable):
//!
//! * [`Inputs`] (`new`, `add`, `extend`, `add_opt`, `which`, `check_output`): every input by device
//!   and inode (after following links), so `--out .`, an absolute spelling, a symbolic or a hard
//!   link of an input are all recognised; no publish ever writes over one. [`check_ext`]: an
//!   output's extension matches the format written.
//! * **Folder outputs**: [`stage_output`] (or [`stage_checked`], which takes the command's name
//!   from [`set_command`]) checks `--out` (absent, empty, or `--force`; not an input), takes the
//!   folder's **exclusive lock** (a second writer of the same folder gets an error at once, never a
//!   mix), finishes what a killed earlier owner left ([`OutputLock::recover`]) and returns a
//!   [`Staged`] folder beside `--out` to write into; [`Staged::commit`] publishes it **atomically at
//!   the folder level**: the complete new folder (the command's new files, plus hard links of every
//!   file in the old folder that is not the command's own) is built first, then the old folder is
//!   moved aside, the new one renamed into place and the old one removed. A kill at any instant
//!   leaves the old folder or the new one; the next writer beside it restores or removes the rest.
//! * **`--force` replaces only the command's own files**: each folder output records what each
//!   command wrote there in [`MANIFEST`] (`.veila-outputs.json`, sorted, byte-identical across
//!   identical runs). Republishing drops the command's stale files (the `scan_001.bin` of an
//!   earlier run with more samples, the frames of a longer `simulate`), keeps every other file,
//!   and refuses to write over a file it did not write there.
//! * **File outputs**: [`publish_files`] writes a set of single files all or nothing (locked,
//!   temporary files beside each destination, renamed when all are complete); [`check_outputs`]
//!   runs its checks alone, so a command can refuse its outputs before it works.
//! * **Other folders a command keeps writing** (`train`'s checkpoints): [`lock_folder`] takes the
//!   same lock; [`remove_partial`] then removes the partial files a killed owner left in it.
//! * **Liveness is a lock, never a process id** (`veila_data::atomic`): staging folders, backups
//!   and temporary files are removed only when their owner's lock is free ([`sweep_stale`], run by
//!   every command that writes beside them), so a veila in another PID namespace is never robbed.
//! * **Interrupts** (SIGINT, SIGTERM, SIGHUP; [`install_signal_cleanup`]) wait for a swap in
//!   progress, remove this process's staging folders, temporary files and locks, and say what was
//!   kept: outputs already published, what [`set_interrupt_note`] describes (`train`'s
//!   checkpoints), and which outputs were left as they were.
//! * **Errors name `--out`**, not the hidden staging path ([`explain`]).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, OnceLock};

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};
pub(crate) use veila_data::atomic::{OutputLock, sweep_stale};

mod merge;
mod publish;
mod signals;

use merge::*;
pub(crate) use publish::{check_outputs, publish_files};
use signals::*;
pub(crate) use signals::{explain, install_signal_cleanup, set_command, set_interrupt_note};

/// The record of what each command wrote into a folder output.
pub(crate) const MANIFEST: &str = ".veila-outputs.json";

/// Identity of a file: device and inode (Unix), else its canonical path.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
struct FileId {
    #[cfg(unix)]
    dev_ino: (u64, u64),
    #[cfg(not(unix))]
    canonical: PathBuf,
}

fn file_id(path: &Path) -> Option<FileId> {
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

fn parent_of(p: &Path) -> PathBuf {
    match p.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

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
    fn held(&self) -> &OutputLock {
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

/// `train`'s discipline for its run folder `out`: its lock ([`lock_folder`]) for the whole run,
/// the partial checkpoints and bundles of a killed earlier run removed (`.NAME.tmp-PID`,
/// `.NAME.old-PID` in `out`, `checkpoints` and the folders in it), and an interrupt that says which
/// checkpoints were kept.
pub(crate) fn lock_train_run(out: &Path, checkpoints: &Path) -> Result<FolderLock> {
    let held = lock_folder(out)?;
    let is_partial = |n: &str| n.starts_with('.') && (n.contains(".tmp-") || n.contains(".old-"));
    let mut dirs = vec![out.to_path_buf(), checkpoints.to_path_buf()];
    if let Ok(rd) = std::fs::read_dir(checkpoints) {
        dirs.extend(
            rd.flatten()
                .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
                .map(|e| e.path()),
        );
    }
    for d in &dirs {
        remove_partial(&held, d, is_partial)?;
    }
    let ck = checkpoints.to_path_buf();
    set_interrupt_note(move || match newest_checkpoint_step(&ck) {
        Some(step) => format!(
            "checkpoints up to step {step} kept in {} (rerun the same command to resume)",
            ck.display()
        ),
        None => format!("no checkpoint was written yet in {}", ck.display()),
    });
    Ok(held)
}

/// The highest `N` of the `step-N` checkpoint folders in `dir` or a folder inside it.
fn newest_checkpoint_step(dir: &Path) -> Option<u64> {
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

/// The manifest of a folder output: each command's files (relative paths with `/`).
#[derive(Debug, Default, Serialize, Deserialize)]
struct Manifest {
    format: String,
    commands: BTreeMap<String, BTreeSet<String>>,
}

const MANIFEST_FORMAT: &str = "veila-outputs/1";

fn read_manifest(dir: &Path) -> Result<Manifest> {
    let p = dir.join(MANIFEST);
    match std::fs::read(&p) {
        Ok(bytes) => serde_json::from_slice(&bytes).with_context(|| {
            format!(
                "{}: unreadable record of this folder's outputs",
                p.display()
            )
        }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Manifest::default()),
        Err(e) => Err(e).with_context(|| format!("{}: cannot read", p.display())),
    }
}

/// A staging folder for one output folder; the folder's lock is held until it is committed or
/// dropped.
#[derive(Debug)]
pub(crate) struct Staged {
    out: PathBuf,
    command: String,
    inputs: Inputs,
    dir: Option<tempfile::TempDir>,
    lock: FolderLock,
}

/// [`stage_output`] for the command [`set_command`] named.
pub(crate) fn stage_checked(out: &Path, force: bool, inputs: &Inputs) -> Result<Staged> {
    stage_output(out, force, inputs, command_name())
}

fn check_folder(out: &Path, force: bool, inputs: &Inputs) -> Result<()> {
    if out.exists() && !out.is_dir() {
        bail!("{}: exists and is not a directory", out.display());
    }
    if let Some(input) = inputs.which(out) {
        bail!("--out {}: is the input {}", out.display(), input.display());
    }
    if out.exists() && !force && !is_empty_dir(out)? {
        bail!(
            "{}: exists and is not empty (choose another --out or pass --force)",
            out.display()
        );
    }
    Ok(())
}

/// Check `out` (a directory that is absent, empty, or non-empty with `force`; not an input), take
/// its lock ([`lock_folder`]) and create its staging folder next to it. `command` names the
/// command in the folder's manifest; publishing never writes over any of `inputs`.
pub(crate) fn stage_output(
    out: &Path,
    force: bool,
    inputs: &Inputs,
    command: &str,
) -> Result<Staged> {
    check_folder(out, force, inputs)?;
    let lock = lock_folder(out)?;
    // a recovered earlier output is checked like any other
    check_folder(out, force, inputs)?;
    let l = lock.held();
    // the folder is replaced whole: never the one the user stands in
    if l.output().exists()
        && let Ok(cwd) = std::env::current_dir().and_then(|c| c.canonicalize())
        && cwd.starts_with(l.output())
    {
        bail!(
            "--out {}: is the current folder (or holds it); a folder output is replaced whole, so give it a folder of its own",
            out.display()
        );
    }
    let dir = tempfile::Builder::new()
        .prefix(&l.staging_prefix())
        .rand_bytes(6)
        .tempdir_in(l.parent())
        .with_context(|| {
            format!(
                "{}: cannot create a staging directory",
                l.parent().display()
            )
        })?;
    register(Live::Staging {
        path: dir.path().to_path_buf(),
        out: out.to_path_buf(),
    });
    Ok(Staged {
        out: out.to_path_buf(),
        command: command.to_string(),
        inputs: inputs.clone(),
        dir: Some(dir),
        lock,
    })
}

impl Drop for Staged {
    fn drop(&mut self) {
        if let Some(d) = &self.dir {
            unregister(d.path());
        }
    }
}

impl Staged {
    /// Where to write.
    pub(crate) fn path(&self) -> &Path {
        self.dir.as_ref().expect("staging folder present").path()
    }

    /// Publish the staged folder as `out`, atomically: see the module header.
    pub(crate) fn commit(mut self) -> Result<()> {
        let dir = self.dir.take().expect("staging folder present");
        let staged = dir.path().to_path_buf();
        let result = self.publish(&staged);
        unregister(&staged);
        if result.is_ok() {
            // the folder itself is the output now
            let _ = dir.keep();
        }
        result
    }

    /// [`commit`](Self::commit), for callers written before the manifest: which files are the
    /// command's own is now what the manifest records, not a guess from their names.
    pub(crate) fn commit_owning(self, _owned: impl Fn(&str) -> bool) -> Result<()> {
        self.commit()
    }

    fn publish(&self, staged: &Path) -> Result<()> {
        let target = self.lock.held().output();
        let mut new_files = Vec::new();
        list_files(staged, Path::new(""), &mut new_files)?;
        let new_keys: BTreeSet<String> = new_files.iter().map(|p| rel_key(p)).collect();
        let existed = std::fs::symlink_metadata(&target).is_ok();
        let mut manifest = Manifest::default();
        if existed {
            manifest = read_manifest(&target)?;
            let own_old = manifest.commands.remove(&self.command).unwrap_or_default();
            let merge = Merge {
                old_root: &target,
                new_root: staged,
                out: &self.out,
                own_old: &own_old,
                new_keys: &new_keys,
                inputs: &self.inputs,
                command: &self.command,
            };
            merge.dir(Path::new(""))?;
            // the other commands' records keep what is still there
            for files in manifest.commands.values_mut() {
                files.retain(|f| staged.join(f).exists());
            }
            manifest.commands.retain(|_, f| !f.is_empty());
        }
        manifest.format = MANIFEST_FORMAT.into();
        manifest.commands.insert(self.command.clone(), new_keys);
        let json = serde_json::to_vec_pretty(&manifest)?;
        veila_data::atomic::write_atomic(&staged.join(MANIFEST), &json)?;
        set_folder_mode(staged, existed.then_some(target.as_path()));

        let swap = lock(&PUBLISH);
        if !existed {
            std::fs::rename(staged, &target).with_context(|| {
                format!("{}: cannot move the output into place", self.out.display())
            })?;
            lock(&PUBLISHED).push(self.out.clone());
            return Ok(());
        }
        let backup = self.lock.held().backup_path();
        std::fs::rename(&target, &backup)
            .with_context(|| format!("{}: cannot move the old output aside", self.out.display()))?;
        if let Err(e) = std::fs::rename(staged, &target) {
            let _ = std::fs::rename(&backup, &target);
            return Err(e).with_context(|| {
                format!("{}: cannot move the output into place", self.out.display())
            });
        }
        register(Live::Backup(backup.clone()));
        lock(&PUBLISHED).push(self.out.clone());
        drop(swap);
        let removed = std::fs::remove_dir_all(&backup);
        unregister(&backup);
        // a backup that could not be removed is swept by the next writer beside it
        if let Err(e) = removed {
            tracing::warn!("{}: cannot remove the old output: {e}", backup.display());
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests;
