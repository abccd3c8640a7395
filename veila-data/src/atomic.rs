//! Atomic file output and the locks that tell a live writer's files from a dead one's.
//!
//! * **Files** are written to a temporary file in the destination's directory, then renamed
//!   ([`write_atomic`], [`write_atomic_all`]): a reader never sees a half-written file, and killing
//!   the process at any moment leaves either the old file or the new one.
//! * **Liveness is a lock, not a process id.** Every temporary file (`.veila-*.tmp`) is locked
//!   (`flock`, through `std::fs::File::lock`) by the process writing it for as long as it lives; an
//!   output folder is locked through its lock file [`OutputLock`] (`.veila-lock.NAME` beside it)
//!   while a command stages or publishes it. The kernel drops a lock when its owner exits, however
//!   it exits, and a lock is the same whatever process-id namespace looks at it; so a leftover
//!   that can be locked provably has no owner any more. [`sweep_stale`] removes exactly those.
//! * **Folder outputs** are staged in `.veila-staging.NAME.XXXXXX` beside `NAME` and swapped in
//!   through `.veila-backup.NAME` (the old folder, moved aside only once the new one is complete);
//!   [`OutputLock::recover`] finishes or undoes a swap that a killed process left half done, so a
//!   folder output is always wholly old or wholly new.

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::{Error, Result};

/// The prefix of every name this module leaves while it works (temporary files, staging folders,
/// backups, lock files). Outputs never start with it.
pub const HIDDEN_PREFIX: &str = ".veila-";

/// Temporary files are created private (0600); give the result the usual 0644 before it is renamed
/// into place, so outputs are readable like any other file.
fn make_readable(file: &File, path: &Path) -> Result<()> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        file.set_permissions(std::fs::Permissions::from_mode(0o644))
            .map_err(|e| Error::io(path, e))?;
    }
    #[cfg(not(unix))]
    let _ = (file, path);
    Ok(())
}

/// The prefix of temporary files (`.veila-XXXXXX.tmp`); [`sweep_stale`] recognises them by it.
pub fn temp_prefix() -> String {
    HIDDEN_PREFIX.to_string()
}

/// Whether the open `file` is still the one named `path` (a sweeper removes a leftover only while
/// holding its lock, so a file that was swept is no longer at its path).
fn is_at(file: &File, path: &Path) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        match (file.metadata(), std::fs::symlink_metadata(path)) {
            (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
            _ => false,
        }
    }
    #[cfg(not(unix))]
    {
        let _ = file;
        path.exists()
    }
}

/// The directory of `path` (`.` for a bare name).
fn dir_of(path: &Path) -> &Path {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// A temporary file in `path`'s directory (so the final rename stays within one file system),
/// locked by this process for as long as it lives; an error naming the directory when it does not
/// exist or cannot take the file.
pub fn locked_temp_beside(path: &Path) -> Result<tempfile::NamedTempFile> {
    let dir = dir_of(path);
    if !dir.is_dir() {
        return Err(Error::io(
            dir,
            std::io::Error::new(
                std::io::ErrorKind::NotFound,
                "output directory does not exist",
            ),
        ));
    }
    loop {
        let tmp = tempfile::Builder::new()
            .prefix(HIDDEN_PREFIX)
            .suffix(".tmp")
            .tempfile_in(dir)
            .map_err(|e| Error::io(dir, e))?;
        // a sweeper may hold the lock of a file it judged ownerless in the instant before ours;
        // it removes the file under that lock, and we start again with a new one
        tmp.as_file().lock().map_err(|e| Error::io(tmp.path(), e))?;
        if is_at(tmp.as_file(), tmp.path()) {
            return Ok(tmp);
        }
    }
}

// ------------------------------------------------------------------------------ output locks

/// Names beside an output folder `NAME`: its lock file, staging folders and backup.
fn lock_file_name(name: &str) -> String {
    format!("{HIDDEN_PREFIX}lock.{name}")
}

fn staging_name_prefix(name: &str) -> String {
    format!("{HIDDEN_PREFIX}staging.{name}.")
}

fn backup_name(name: &str) -> String {
    format!("{HIDDEN_PREFIX}backup.{name}")
}

/// The output a hidden name beside it belongs to (`.veila-lock.NAME`, `.veila-backup.NAME`,
/// `.veila-staging.NAME.XXXXXX`).
fn output_of_hidden(name: &str) -> Option<&str> {
    let rest = name.strip_prefix(HIDDEN_PREFIX)?;
    let out = if let Some(n) = rest.strip_prefix("lock.") {
        n
    } else if let Some(n) = rest.strip_prefix("backup.") {
        n
    } else {
        rest.strip_prefix("staging.")?.rsplit_once('.')?.0
    };
    (!out.is_empty()).then_some(out)
}

/// An output's canonical parent folder and its name: links and `.`/`..` are resolved, so every
/// spelling of one output takes the same lock. The parent must exist.
fn split_output(out: &Path) -> Result<(PathBuf, String)> {
    let resolved = match out.file_name() {
        // `--out dir/..`, `--out .`, `--out /`: the folder it names
        None => std::fs::canonicalize(out).map_err(|e| Error::io(out, e))?,
        Some(_) if std::fs::symlink_metadata(out).is_ok_and(|m| m.file_type().is_symlink()) => {
            std::fs::canonicalize(out).map_err(|e| Error::io(out, e))?
        }
        Some(name) => std::fs::canonicalize(dir_of(out))
            .map_err(|e| Error::io(dir_of(out), e))?
            .join(name),
    };
    match (resolved.parent(), resolved.file_name()) {
        (Some(p), Some(n)) => Ok((p.to_path_buf(), n.to_string_lossy().into_owned())),
        _ => Err(Error::io(
            out,
            std::io::Error::other("the root folder cannot be an output"),
        )),
    }
}

/// The exclusive lock of one output folder: `flock` on `.veila-lock.NAME` beside it, held while a
/// command stages, publishes or recovers that output, and its file removed when it is let go.
/// A second writer of the same output gets an error at once ([`OutputLock::acquire`]).
#[derive(Debug)]
pub struct OutputLock {
    /// Holds the `flock` (released when the file is closed, however the process ends).
    _file: File,
    path: PathBuf,
    parent: PathBuf,
    name: String,
}

/// The outcome of one attempt at a lock.
enum Attempt {
    Held(OutputLock),
    Busy,
}

impl OutputLock {
    /// Lock the output `out` (a folder, present or not; its parent must exist). Fails naming `out`
    /// when another process holds it.
    pub fn acquire(out: &Path) -> Result<Self> {
        let (parent, name) = split_output(out)?;
        match Self::attempt(parent, name)? {
            Attempt::Held(l) => Ok(l),
            Attempt::Busy => Err(Error::io(
                out,
                std::io::Error::new(
                    std::io::ErrorKind::WouldBlock,
                    "another veila process is writing this output (wait for it to finish or choose another output)",
                ),
            )),
        }
    }

    /// Lock the output `out` if no other process holds it: `None` when one does (a worker that
    /// shares a job with others takes the next piece instead of waiting). The lock goes with the
    /// process however it ends, so a killed worker's piece is free again at once.
    pub fn try_acquire(out: &Path) -> Result<Option<Self>> {
        let (parent, name) = split_output(out)?;
        Ok(match Self::attempt(parent, name)? {
            Attempt::Held(l) => Some(l),
            Attempt::Busy => None,
        })
    }

    fn attempt(parent: PathBuf, name: String) -> Result<Attempt> {
        let path = parent.join(lock_file_name(&name));
        loop {
            let file = std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .create(true)
                .truncate(false)
                .open(&path)
                .map_err(|e| Error::io(&path, e))?;
            match file.try_lock() {
                Ok(()) => {}
                Err(std::fs::TryLockError::WouldBlock) => return Ok(Attempt::Busy),
                Err(std::fs::TryLockError::Error(e)) => return Err(Error::io(&path, e)),
            }
            // the previous owner removes its lock file while it holds the lock: a lock on a file
            // that is no longer at the path locks nothing
            if is_at(&file, &path) {
                return Ok(Attempt::Held(OutputLock {
                    _file: file,
                    path,
                    parent,
                    name,
                }));
            }
        }
    }

    /// The lock file.
    pub fn lock_path(&self) -> &Path {
        &self.path
    }

    /// The locked output, resolved (canonical parent + name).
    pub fn output(&self) -> PathBuf {
        self.parent.join(&self.name)
    }

    /// The folder that holds the output, its staging folders and backup.
    pub fn parent(&self) -> &Path {
        &self.parent
    }

    /// The prefix of the output's staging folders (`.veila-staging.NAME.`).
    pub fn staging_prefix(&self) -> String {
        staging_name_prefix(&self.name)
    }

    /// Where the old output waits while the new one is moved into place (`.veila-backup.NAME`).
    pub fn backup_path(&self) -> PathBuf {
        self.parent.join(backup_name(&self.name))
    }

    /// Finish what a killed owner of this output left: its staging folders are removed, and a
    /// backup is put back when the output is missing (the old output, moved aside before the new one
    /// arrived) or removed when the output is there (the swap was done). Holding the lock proves
    /// their owner is gone. Returns how many leftovers were handled.
    pub fn recover(&self) -> Result<usize> {
        let mut n = 0;
        let prefix = self.staging_prefix();
        let rd = std::fs::read_dir(&self.parent).map_err(|e| Error::io(&self.parent, e))?;
        for e in rd.flatten() {
            if e.file_name().to_string_lossy().starts_with(&prefix) {
                let p = e.path();
                std::fs::remove_dir_all(&p).map_err(|e| Error::io(&p, e))?;
                n += 1;
            }
        }
        let backup = self.backup_path();
        if std::fs::symlink_metadata(&backup).is_ok() {
            let out = self.output();
            if std::fs::symlink_metadata(&out).is_ok() {
                std::fs::remove_dir_all(&backup).map_err(|e| Error::io(&backup, e))?;
            } else {
                std::fs::rename(&backup, &out).map_err(|e| Error::io(&out, e))?;
            }
            n += 1;
        }
        Ok(n)
    }
}

impl Drop for OutputLock {
    fn drop(&mut self) {
        // removed while still held, so nobody can lock the old file after this
        let _ = std::fs::remove_file(&self.path);
    }
}

// ---------------------------------------------------------------------------- stale leftovers

/// Remove the leftovers in `dir` whose owner is gone: temporary files (`.veila-*.tmp`) that nobody
/// holds locked, and the staging folders, backups and lock files of output folders whose lock is
/// free ([`OutputLock::recover`]). Anything a live process holds is left alone, whatever its
/// process id. Returns how many leftovers (files, folders, lock files) were removed or restored.
pub fn sweep_stale(dir: &Path) -> usize {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return 0;
    };
    let names: Vec<String> = rd
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(HIDDEN_PREFIX))
        .collect();
    let Ok(parent) = std::fs::canonicalize(dir) else {
        return 0;
    };
    let mut removed = 0;
    let mut outputs = std::collections::BTreeSet::new();
    for name in &names {
        if let Some(out) = output_of_hidden(name) {
            outputs.insert(out.to_string());
        } else if is_leftover_name(name) {
            // a temporary file (or an older veila's staging folder): its writer holds it locked
            removed += usize::from(remove_if_unlocked(&parent.join(name)));
        }
    }
    for out in outputs {
        let had_lock = names.contains(&lock_file_name(&out));
        if let Ok(Attempt::Held(lock)) = OutputLock::attempt(parent.clone(), out) {
            // the lock file goes when `lock` is dropped
            removed += lock.recover().unwrap_or(0) + usize::from(had_lock);
        }
    }
    removed
}

/// Whether `name` is one this module leaves while it works (a temporary file, a staging folder, a
/// backup or a lock file): what [`sweep_stale`] looks at, and what never belongs to an output.
pub fn is_leftover_name(name: &str) -> bool {
    output_of_hidden(name).is_some()
        || (name.starts_with(HIDDEN_PREFIX)
            && (name.ends_with(".tmp") || name.starts_with(".veila-staging-")))
}

/// Remove `path` (a file or folder) when nobody holds it locked.
fn remove_if_unlocked(path: &Path) -> bool {
    let Ok(file) = File::open(path) else {
        return false;
    };
    if file.try_lock().is_err() || !is_at(&file, path) {
        return false;
    }
    if file.metadata().is_ok_and(|m| m.is_dir()) {
        std::fs::remove_dir_all(path).is_ok()
    } else {
        std::fs::remove_file(path).is_ok()
    }
}

// ------------------------------------------------------------------------------------- writes

/// Write `bytes` to `path` atomically (temp file in the same directory + rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_with(path, |w| w.write_all(bytes))
}

/// Write `path` atomically through a closure that fills a buffered writer.
pub fn write_atomic_with(
    path: &Path,
    fill: impl FnOnce(&mut std::io::BufWriter<&mut File>) -> std::io::Result<()>,
) -> Result<()> {
    let mut tmp = locked_temp_beside(path)?;
    {
        let mut w = std::io::BufWriter::new(tmp.as_file_mut());
        fill(&mut w).map_err(|e| Error::io(path, e))?;
        w.flush().map_err(|e| Error::io(path, e))?;
    }
    tmp.as_file().sync_all().map_err(|e| Error::io(path, e))?;
    make_readable(tmp.as_file(), path)?;
    tmp.persist(path).map_err(|e| Error::io(path, e.error))?;
    Ok(())
}

/// Write `bytes` to `path` atomically unless `path` exists: `Ok(true)` when this call created it,
/// `Ok(false)` when a file was already there (left as it was). Of several processes racing to
/// create one file, exactly one succeeds and the others see its complete content.
pub fn write_atomic_new(path: &Path, bytes: &[u8]) -> Result<bool> {
    let mut tmp = locked_temp_beside(path)?;
    tmp.as_file_mut()
        .write_all(bytes)
        .map_err(|e| Error::io(path, e))?;
    tmp.as_file().sync_all().map_err(|e| Error::io(path, e))?;
    make_readable(tmp.as_file(), path)?;
    match tmp.persist_noclobber(path) {
        Ok(_) => Ok(true),
        Err(e) if e.error.kind() == std::io::ErrorKind::AlreadyExists => Ok(false),
        Err(e) => Err(Error::io(path, e.error)),
    }
}

/// Write several files so that either all of them appear or none does: every file is first written
/// to a temporary file beside its destination, and only when all temporaries are complete are they
/// renamed into place. A failure before that point (an unwritable folder, a full disk) leaves no
/// output at all.
pub fn write_atomic_all(files: &[(&Path, &[u8])]) -> Result<()> {
    let mut staged = Vec::with_capacity(files.len());
    for (path, bytes) in files {
        let mut tmp = locked_temp_beside(path)?;
        tmp.as_file_mut()
            .write_all(bytes)
            .map_err(|e| Error::io(*path, e))?;
        tmp.as_file().sync_all().map_err(|e| Error::io(*path, e))?;
        make_readable(tmp.as_file(), path)?;
        staged.push((tmp, *path));
    }
    for (tmp, path) in staged {
        tmp.persist(path).map_err(|e| Error::io(path, e.error))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hidden_names_name_their_output() {
        assert_eq!(output_of_hidden(".veila-lock.out"), Some("out"));
        assert_eq!(output_of_hidden(".veila-backup.a.b"), Some("a.b"));
        assert_eq!(output_of_hidden(".veila-staging.a.b.XyZ123"), Some("a.b"));
        assert_eq!(output_of_hidden(".veila-staging.x"), None);
        assert_eq!(output_of_hidden(".veila-abc.tmp"), None);
        assert_eq!(output_of_hidden("scan.bin"), None);
    }

    #[test]
    fn sweep_removes_unowned_leftovers_only() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path();
        // a killed writer's temporary file and staging folder (nobody holds them)
        std::fs::write(p.join(".veila-4294967-x.tmp"), b"x").unwrap();
        std::fs::create_dir(p.join(".veila-staging.out.abc123")).unwrap();
        std::fs::write(p.join(".veila-staging.out.abc123/f"), b"x").unwrap();
        std::fs::write(p.join(".veila-lock.out"), b"").unwrap();
        // a live writer's: this process holds them
        let live_tmp = locked_temp_beside(&p.join("dest.bin")).unwrap();
        let held = OutputLock::acquire(&p.join("busy")).unwrap();
        std::fs::create_dir(p.join(".veila-staging.busy.zzz999")).unwrap();
        std::fs::write(p.join("user.txt"), b"x").unwrap();
        // the temporary file, the staging folder and the lock file of the dead owner
        assert_eq!(sweep_stale(p), 3);
        let mut left: Vec<String> = std::fs::read_dir(p)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        left.sort();
        let tmp_name = live_tmp.path().file_name().unwrap().to_string_lossy();
        let mut want = vec![
            ".veila-lock.busy".to_string(),
            ".veila-staging.busy.zzz999".to_string(),
            tmp_name.into_owned(),
            "user.txt".to_string(),
        ];
        want.sort();
        assert_eq!(left, want);
        drop(held);
        drop(live_tmp);
        // the staging folder of `busy` (its lock file went with its owner)
        assert_eq!(sweep_stale(p), 1);
        assert_eq!(std::fs::read_dir(p).unwrap().count(), 1);
    }

    #[test]
    fn a_second_writer_is_refused_and_the_lock_file_goes_with_its_owner() {
        let d = tempfile::tempdir().unwrap();
        let out = d.path().join("o");
        let a = OutputLock::acquire(&out).unwrap();
        // another spelling of the same output is the same lock
        let other = d.path().join(".").join("o");
        let e = OutputLock::acquire(&other).unwrap_err().to_string();
        assert!(e.contains("another veila process"), "{e}");
        assert!(OutputLock::try_acquire(&other).unwrap().is_none());
        drop(a);
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 0);
        let b = OutputLock::try_acquire(&other).unwrap();
        assert!(b.is_some());
        assert!(OutputLock::acquire(&out).is_err());
    }

    #[test]
    fn recovery_restores_a_half_swapped_output() {
        let d = tempfile::tempdir().unwrap();
        let out = d.path().join("o");
        // killed between "old aside" and "new in place": the old output comes back
        std::fs::create_dir(d.path().join(".veila-backup.o")).unwrap();
        std::fs::write(d.path().join(".veila-backup.o/a"), b"old").unwrap();
        std::fs::create_dir(d.path().join(".veila-staging.o.q1w2e3")).unwrap();
        let lock = OutputLock::acquire(&out).unwrap();
        assert_eq!(lock.recover().unwrap(), 2);
        assert_eq!(std::fs::read(out.join("a")).unwrap(), b"old");
        // killed after "new in place": the backup goes
        std::fs::create_dir(d.path().join(".veila-backup.o")).unwrap();
        assert_eq!(lock.recover().unwrap(), 1);
        assert_eq!(std::fs::read(out.join("a")).unwrap(), b"old");
        drop(lock);
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 1);
    }

    #[test]
    fn a_new_file_is_written_once() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.json");
        assert!(write_atomic_new(&p, b"first").unwrap());
        assert!(!write_atomic_new(&p, b"second").unwrap());
        assert_eq!(std::fs::read(&p).unwrap(), b"first");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn all_or_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let a = dir.path().join("a.txt");
        let missing = dir.path().join("no/such/dir/b.txt");
        let e = write_atomic_all(&[(&a, b"1"), (&missing, b"2")])
            .unwrap_err()
            .to_string();
        assert!(e.contains("no/such/dir"), "{e}");
        assert!(!a.exists());
        assert_eq!(
            std::fs::read_dir(dir.path()).unwrap().count(),
            0,
            "temporaries left behind"
        );
        write_atomic_all(&[(&a, b"1"), (&dir.path().join("b.txt"), b"2")]).unwrap();
        assert_eq!(std::fs::read(&a).unwrap(), b"1");
    }
}
