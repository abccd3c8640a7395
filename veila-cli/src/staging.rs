//! The output discipline every command follows: nothing the user had is ever lost.
//!
//! * **Inputs are never outputs.** [`Inputs`] records every input by device and inode (after
//!   following links), so `--out .`, `--out ./`, an absolute spelling, a symbolic or a hard link of an
//!   input are all recognised; publishing refuses any destination that is an input.
//! * **Extensions match the format written** ([`check_ext`]).
//! * **No file is replaced without `--force`**, and a folder output that is republished with
//!   `--force` drops the command's own stale files (a `scan_001.bin` of an earlier run with more
//!   samples) instead of leaving them next to a record that no longer lists them.
//! * **All or nothing.** A folder output is rendered into a staging folder beside `--out` and moved
//!   into place when everything succeeded ([`stage_checked`]); a set of single files is written to temporary
//!   files beside their destinations and renamed only when all are complete ([`publish_files`]).
//!   Every check runs before the first rename.
//! * **Inputs first.** Commands read and check every input before they call [`stage_checked`] or
//!   [`publish_files`], which are the only places that create anything.
//! * **Clean interrupts.** Staging folders and temporary files are registered while they live;
//!   SIGINT, SIGTERM and SIGHUP remove them before the process exits ([`install_signal_cleanup`]).
//!   SIGKILL cannot be caught: staging names carry the process id (`.veila-staging-PID-*`,
//!   `.veila-PID-*.tmp`), and the next command that writes beside them removes those whose process
//!   is gone ([`sweep_stale`]).
//! * **Errors name `--out`**, not the hidden staging path ([`explain`]).

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use anyhow::{Context, Result, bail};

/// What lives on disk only while this process runs: removed on a signal.
#[derive(Debug)]
enum Live {
    /// A staging folder and the output it stands for.
    Dir { staging: PathBuf, out: PathBuf },
    /// A temporary file and its destination.
    File { tmp: PathBuf, dest: PathBuf },
}

static LIVE: Mutex<Vec<Live>> = Mutex::new(Vec::new());

/// Every staging path this process made and the output it stood for (kept for error messages).
static NAMES: Mutex<Vec<(PathBuf, PathBuf)>> = Mutex::new(Vec::new());

fn live() -> std::sync::MutexGuard<'static, Vec<Live>> {
    LIVE.lock().unwrap_or_else(|e| e.into_inner())
}

fn register(l: Live) {
    let pair = match &l {
        Live::Dir { staging, out } => (staging.clone(), out.clone()),
        Live::File { tmp, dest } => (tmp.clone(), dest.clone()),
    };
    NAMES.lock().unwrap_or_else(|e| e.into_inner()).push(pair);
    live().push(l);
}

fn unregister(path: &Path) {
    live().retain(|l| match l {
        Live::Dir { staging, .. } => staging != path,
        Live::File { tmp, .. } => tmp != path,
    });
}

/// Remove every registered staging folder and temporary file (the signal handler's work).
fn remove_live() {
    let mut l = live();
    for item in l.drain(..) {
        match item {
            Live::Dir { staging, .. } => {
                let _ = std::fs::remove_dir_all(staging);
            }
            Live::File { tmp, .. } => {
                let _ = std::fs::remove_file(tmp);
            }
        }
    }
}

/// On SIGINT, SIGTERM or SIGHUP: remove this process's staging folders and temporary files, then
/// exit with 130 (the shell's code for an interrupted command). Call once, first thing in `main`.
pub(crate) fn install_signal_cleanup() {
    // ctrlc runs the handler on its own thread (not in signal context), so taking a lock is fine
    let _ = ctrlc::set_handler(|| {
        remove_live();
        eprintln!("interrupted: no output was written");
        std::process::exit(130);
    });
}

/// Rewrite an error so that it names the output the user asked for instead of a staging path.
pub(crate) fn explain(err: anyhow::Error) -> anyhow::Error {
    let mut msg = format!("{err:#}");
    let names = NAMES.lock().unwrap_or_else(|e| e.into_inner());
    let mut changed = false;
    for (from, to) in names.iter() {
        let from = from.display().to_string();
        if msg.contains(&from) {
            msg = msg.replace(&from, &to.display().to_string());
            changed = true;
        }
    }
    if changed { anyhow::anyhow!(msg) } else { err }
}

// ---------------------------------------------------------------------------------------- inputs

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

// ---------------------------------------------------------------------------- stale leftovers

fn parent_of(p: &Path) -> PathBuf {
    match p.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

pub(crate) use veila_data::atomic::sweep_stale;

// ---------------------------------------------------------------------------- folder outputs

/// A staging folder for one output folder.
#[derive(Debug)]
pub(crate) struct Staged {
    out: PathBuf,
    dir: Option<tempfile::TempDir>,
    existed: bool,
    force: bool,
    inputs: Inputs,
}

/// Check `out` (a directory that is absent, empty, or non-empty with `force`; not an input) and
/// create its staging folder next to it. Stale staging of killed runs beside it is removed first.
/// Publishing never writes over any of `inputs`.
pub(crate) fn stage_checked(out: &Path, force: bool, inputs: &Inputs) -> Result<Staged> {
    let existed = out.exists();
    if existed && !out.is_dir() {
        bail!("{}: exists and is not a directory", out.display());
    }
    if let Some(input) = inputs.which(out) {
        bail!("--out {}: is the input {}", out.display(), input.display());
    }
    if existed && !force && !is_empty_dir(out)? {
        bail!(
            "{}: exists and is not empty (choose another --out or pass --force)",
            out.display()
        );
    }
    let parent = parent_of(out);
    std::fs::create_dir_all(&parent)
        .with_context(|| format!("{}: cannot create", parent.display()))?;
    sweep_stale(&parent);
    let dir = tempfile::Builder::new()
        .prefix(&format!(".veila-staging-{}-", std::process::id()))
        .tempdir_in(&parent)
        .with_context(|| format!("{}: cannot create a staging directory", parent.display()))?;
    register(Live::Dir {
        staging: dir.path().to_path_buf(),
        out: out.to_path_buf(),
    });
    Ok(Staged {
        out: out.to_path_buf(),
        dir: Some(dir),
        existed,
        force,
        inputs: inputs.clone(),
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

    /// Move the staged files into place (a rename of the whole folder when `out` did not exist).
    pub(crate) fn commit(self) -> Result<()> {
        self.commit_owning(|_| false)
    }

    /// [`commit`](Self::commit); when `out` already existed (`--force`), first remove the files at
    /// its top level that `owned` recognises as this command's and that the new output does not
    /// have, so no stale output of an earlier run stays next to the new record.
    pub(crate) fn commit_owning(mut self, owned: impl Fn(&str) -> bool) -> Result<()> {
        let dir = self.dir.take().expect("staging folder present");
        let staged = dir.path().to_path_buf();
        let result = self.publish(&staged, &owned);
        unregister(&staged);
        match result {
            Ok(true) => {
                // the folder itself was renamed into place
                let _ = dir.keep();
                Ok(())
            }
            Ok(false) => Ok(()),
            Err(e) => Err(e),
        }
    }

    /// Returns true when the staging folder itself became `out`.
    fn publish(&self, staged: &Path, owned: &dyn Fn(&str) -> bool) -> Result<bool> {
        let mut files = Vec::new();
        list_files(staged, Path::new(""), &mut files)?;
        if !self.existed && !self.out.exists() {
            std::fs::rename(staged, &self.out).with_context(|| {
                format!("{}: cannot move the output into place", self.out.display())
            })?;
            return Ok(true);
        }
        // every check before the first rename
        let new_names: BTreeSet<&Path> = files.iter().map(|p| p.as_path()).collect();
        for rel in &files {
            let dst = self.out.join(rel);
            self.inputs.check_output(&dst)?;
            if dst.is_dir() {
                bail!("{}: exists and is a directory", dst.display());
            }
            if !self.force && dst.exists() {
                bail!(
                    "{}: exists (choose another --out or pass --force)",
                    dst.display()
                );
            }
        }
        let mut stale = Vec::new();
        for e in std::fs::read_dir(&self.out)
            .with_context(|| format!("{}: cannot read directory", self.out.display()))?
            .flatten()
        {
            let name = e.file_name().to_string_lossy().into_owned();
            if e.path().is_file() && owned(&name) && !new_names.contains(Path::new(&name)) {
                self.inputs.check_output(&e.path()).with_context(|| {
                    format!("{}: a stale output of an earlier run", e.path().display())
                })?;
                stale.push(e.path());
            }
        }
        for p in stale {
            std::fs::remove_file(&p).with_context(|| format!("{}: cannot remove", p.display()))?;
        }
        for rel in &files {
            let (src, dst) = (staged.join(rel), self.out.join(rel));
            if let Some(d) = dst.parent() {
                std::fs::create_dir_all(d)
                    .with_context(|| format!("{}: cannot create", d.display()))?;
            }
            std::fs::rename(&src, &dst)
                .with_context(|| format!("{}: cannot move into place", dst.display()))?;
        }
        Ok(false)
    }
}

fn is_empty_dir(p: &Path) -> Result<bool> {
    Ok(std::fs::read_dir(p)
        .with_context(|| format!("{}: cannot read directory", p.display()))?
        .next()
        .is_none())
}

/// Every file under `root/rel`, as paths relative to `root`.
fn list_files(root: &Path, rel: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
    let dir = root.join(rel);
    let mut entries: Vec<_> = std::fs::read_dir(&dir)
        .with_context(|| format!("{}: cannot read", dir.display()))?
        .collect::<std::io::Result<_>>()?;
    entries.sort_by_key(|e| e.file_name());
    for e in entries {
        let r = rel.join(e.file_name());
        if e.path().is_dir() {
            list_files(root, &r, out)?;
        } else {
            out.push(r);
        }
    }
    Ok(())
}

// ------------------------------------------------------------------------------ file outputs

/// Write every `(destination, bytes)` so that all appear or none does: all checks first (no
/// destination is an input or listed twice, none exists unless `force`, every folder exists or is
/// created when `create_dirs`), then temporary files beside each destination, then the renames.
pub(crate) fn publish_files(
    files: &[(PathBuf, Vec<u8>)],
    inputs: &Inputs,
    force: bool,
    create_dirs: bool,
) -> Result<()> {
    let dests: Vec<&Path> = files.iter().map(|(p, _)| p.as_path()).collect();
    check_outputs(&dests, inputs, force, create_dirs)?;
    let mut created: Vec<PathBuf> = Vec::new();
    let result = write_and_rename(files, create_dirs, &mut created);
    if result.is_err() {
        // folders this call made for outputs that never appeared
        for d in created.iter().rev() {
            let _ = std::fs::remove_dir(d);
        }
    }
    result
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

fn write_and_rename(
    files: &[(PathBuf, Vec<u8>)],
    create_dirs: bool,
    created: &mut Vec<PathBuf>,
) -> Result<()> {
    use std::io::Write;
    let mut staged = Vec::with_capacity(files.len());
    for (dest, bytes) in files {
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
        sweep_stale(&dir);
        let mut tmp = tempfile::Builder::new()
            .prefix(&format!(".veila-{}-", std::process::id()))
            .suffix(".tmp")
            .tempfile_in(&dir)
            .with_context(|| format!("{}: cannot write into {}", dest.display(), dir.display()))?;
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
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inputs_are_recognised_by_identity() {
        let d = tempfile::tempdir().unwrap();
        let a = d.path().join("a.bin");
        std::fs::write(&a, b"1").unwrap();
        let mut inputs = Inputs::new();
        inputs.add(&a);
        let other = d.path().join(".").join("sub/../a.bin");
        std::fs::create_dir(d.path().join("sub")).unwrap();
        assert!(inputs.check_output(&other).is_err());
        #[cfg(unix)]
        {
            std::fs::hard_link(&a, d.path().join("hard.bin")).unwrap();
            assert!(inputs.check_output(&d.path().join("hard.bin")).is_err());
        }
        assert!(inputs.check_output(&d.path().join("new.bin")).is_ok());
    }

    #[test]
    fn errors_name_the_output_not_the_staging_folder() {
        let d = tempfile::tempdir().unwrap();
        let out = d.path().join("result");
        let staged = stage_checked(&out, false, &Inputs::new()).unwrap();
        let hidden = staged.path().join("scan_000.bin");
        let err = anyhow::anyhow!("{}: No space left on device", hidden.display());
        drop(staged);
        let msg = explain(err).to_string();
        assert!(
            msg.contains(&out.join("scan_000.bin").display().to_string()),
            "{msg}"
        );
        assert!(!msg.contains(".veila-staging-"), "{msg}");
        // the staging folder went with the failed command
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 0);
    }

    #[test]
    fn force_republish_drops_own_stale_files_only() {
        let d = tempfile::tempdir().unwrap();
        let out = d.path().join("o");
        std::fs::create_dir(&out).unwrap();
        for n in ["scan_000.bin", "scan_001.bin", "notes.txt"] {
            std::fs::write(out.join(n), b"old").unwrap();
        }
        let refused = stage_checked(&out, false, &Inputs::new())
            .unwrap_err()
            .to_string();
        assert!(refused.contains("--force"), "{refused}");
        let staged = stage_checked(&out, true, &Inputs::new()).unwrap();
        std::fs::write(staged.path().join("scan_000.bin"), b"new").unwrap();
        staged.commit_owning(|n| n.starts_with("scan_")).unwrap();
        assert_eq!(std::fs::read(out.join("scan_000.bin")).unwrap(), b"new");
        assert!(!out.join("scan_001.bin").exists());
        assert_eq!(std::fs::read(out.join("notes.txt")).unwrap(), b"old");
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 1);
    }

    #[test]
    fn publish_is_all_or_nothing() {
        let d = tempfile::tempdir().unwrap();
        let a = d.path().join("a.txt");
        let b = d.path().join("b.txt");
        std::fs::write(&b, b"old").unwrap();
        let files = vec![(a.clone(), b"1".to_vec()), (b.clone(), b"2".to_vec())];
        let e = publish_files(&files, &Inputs::new(), false, false).unwrap_err();
        assert!(e.to_string().contains("b.txt"), "{e}");
        assert!(!a.exists());
        assert_eq!(std::fs::read(&b).unwrap(), b"old");
        publish_files(&files, &Inputs::new(), true, false).unwrap();
        assert_eq!(std::fs::read(&b).unwrap(), b"2");
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 2);
    }
}
