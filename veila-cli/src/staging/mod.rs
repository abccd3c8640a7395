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
//!   mix), finishes what a killed earlier owner left ([`veila_data::atomic::OutputLock::recover`]) and returns a
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
//! * **`train`'s run folder**, written over hours rather than published at once
//!   ([`claim_train_run`], [`check_train_bundle`]; see [`train_run`]): absent, empty or carrying
//!   train's marker (`.veila-train.json`), never one of its inputs, locked like any output, cleaned
//!   of only the exact partial files train's writers leave, its bundle replaced only with `--force`.
//! * **Liveness is a lock, never a process id** (`veila_data::atomic`): staging folders, backups
//!   and temporary files are removed only when their owner's lock is free ([`veila_data::atomic::sweep_stale`], run by
//!   every command that writes beside them), so a veila in another PID namespace is never robbed.
//! * **Interrupts** (SIGINT, SIGTERM, SIGHUP; [`install_signal_cleanup`]) wait for a swap in
//!   progress, remove this process's staging folders, temporary files and locks, and say what was
//!   kept: outputs already published, what [`set_interrupt_note`] describes (`train`'s
//!   checkpoints), and which outputs were left as they were.
//! * **Errors name `--out`**, not the hidden staging path ([`explain`]).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};
use veila_data::read_capped::MAX_JSON_METADATA_BYTES;

mod inputs;
mod lock;
mod merge;
mod publish;
mod signals;
mod train_run;

pub(crate) use inputs::{Inputs, MANIFEST, check_ext};
#[cfg(test)]
use lock::remove_partial;
pub(crate) use lock::{FolderLock, lock_folder};
use merge::*;
#[cfg(test)]
use publish::special_file_kind;
pub(crate) use publish::{check_outputs, publish_files};
use signals::*;
pub(crate) use signals::{explain, install_signal_cleanup, set_command, set_interrupt_note};
pub(crate) use train_run::{BUNDLE, SEGMENTER, TrainInputs, check_train_bundle, claim_train_run};

/// The manifest of a folder output: each command's files (relative paths with `/`).
#[derive(Debug, Default, Serialize, Deserialize)]
struct Manifest {
    format: String,
    commands: BTreeMap<String, BTreeSet<String>>,
}

const MANIFEST_FORMAT: &str = "veila-outputs/1";

fn read_manifest(dir: &Path) -> Result<Manifest> {
    let p = dir.join(MANIFEST);
    let what = "a record of a folder's outputs";
    match veila_data::read_capped::read_metadata(&p, MAX_JSON_METADATA_BYTES, what) {
        Ok(bytes) => serde_json::from_slice(&bytes).with_context(|| {
            format!(
                "{}: unreadable record of this folder's outputs",
                p.display()
            )
        }),
        Err(veila_data::Error::Io { source, .. })
            if source.kind() == std::io::ErrorKind::NotFound =>
        {
            Ok(Manifest::default())
        }
        Err(e) => Err(e.into()),
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
