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

/// The record of what each command wrote into a folder output.
pub(crate) const MANIFEST: &str = ".veila-outputs.json";

/// What lives on disk only while this process runs: removed on a signal.
#[derive(Debug)]
enum Live {
    /// A staging folder and the output it stands for.
    Staging { path: PathBuf, out: PathBuf },
    /// A temporary file and its destination.
    File { tmp: PathBuf, dest: PathBuf },
    /// An old output folder moved aside (the new one is in place).
    Backup(PathBuf),
    /// The lock file of an output folder this process holds.
    Lock(PathBuf),
}

impl Live {
    fn path(&self) -> &Path {
        match self {
            Live::Staging { path, .. } | Live::File { tmp: path, .. } => path,
            Live::Backup(p) | Live::Lock(p) => p,
        }
    }
}

static LIVE: Mutex<Vec<Live>> = Mutex::new(Vec::new());

/// Every staging path this process made and the output it stood for (kept for error messages).
static NAMES: Mutex<Vec<(PathBuf, PathBuf)>> = Mutex::new(Vec::new());

/// Held while an output is swapped into place; the signal handler takes it and never lets go.
static PUBLISH: Mutex<()> = Mutex::new(());

/// Outputs this process published completely.
static PUBLISHED: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

type Note = Box<dyn Fn() -> String + Send>;

/// What the command keeps when it is interrupted ([`set_interrupt_note`]).
static NOTE: Mutex<Option<Note>> = Mutex::new(None);

/// The running command's name (`generate`, `simulate`, ...), for the manifest.
static COMMAND: OnceLock<String> = OnceLock::new();

/// Set once a signal arrived.
static STOPPING: AtomicBool = AtomicBool::new(false);

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

fn register(l: Live) {
    match &l {
        Live::Staging { path, out } => lock(&NAMES).push((path.clone(), out.clone())),
        Live::File { tmp, dest } => lock(&NAMES).push((tmp.clone(), dest.clone())),
        Live::Backup(_) | Live::Lock(_) => {}
    }
    lock(&LIVE).push(l);
}

fn unregister(path: &Path) {
    lock(&LIVE).retain(|l| l.path() != path);
}

/// Remove every registered staging folder, backup, temporary file and lock file (the signal
/// handler's work). A staging folder is removed until it stays gone (the main thread may still
/// be writing into it).
fn remove_live() {
    let mut items: Vec<Live> = lock(&LIVE).drain(..).collect();
    // locks last: nothing of an output may outlive the lock that guards it
    items.sort_by_key(|l| matches!(l, Live::Lock(_)));
    for item in items {
        match item {
            Live::Staging { path, .. } | Live::Backup(path) => {
                for _ in 0..100 {
                    if std::fs::symlink_metadata(&path).is_err() {
                        break;
                    }
                    let _ = std::fs::remove_dir_all(&path);
                }
            }
            Live::File { tmp: p, .. } | Live::Lock(p) => {
                let _ = std::fs::remove_file(p);
            }
        }
    }
}

/// The line printed on an interrupt: what was published, what the command keeps, and which
/// outputs were left as they were.
fn interrupt_message() -> String {
    let mut parts = Vec::new();
    let published = lock(&PUBLISHED);
    if !published.is_empty() {
        parts.push(format!("{} written completely", join_paths(&published)));
    }
    if let Some(note) = lock(&NOTE).as_ref() {
        parts.push(note());
    }
    let unfinished: Vec<PathBuf> = lock(&LIVE)
        .iter()
        .filter_map(|l| match l {
            Live::Staging { out, .. } | Live::File { dest: out, .. } => Some(out.clone()),
            _ => None,
        })
        .collect::<BTreeSet<_>>()
        .into_iter()
        .collect();
    if !unfinished.is_empty() {
        parts.push(format!(
            "nothing was written to {} (left as it was)",
            join_paths(&unfinished)
        ));
    }
    if parts.is_empty() {
        "interrupted: no output was written".into()
    } else {
        format!("interrupted: {}", parts.join("; "))
    }
}

fn join_paths(p: &[PathBuf]) -> String {
    p.iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(", ")
}

/// On SIGINT, SIGTERM or SIGHUP: wait for an output swap in progress to finish, remove this
/// process's staging folders, temporary files and locks, say what was kept, and exit with 130 (the
/// shell's code for an interrupted command). Call once, first thing in `main`.
pub(crate) fn install_signal_cleanup() {
    // ctrlc runs the handler on its own thread (not in signal context), so taking a lock is fine
    let _ = ctrlc::set_handler(|| {
        STOPPING.store(true, Ordering::SeqCst);
        // no swap is half done from here on, and none starts
        std::mem::forget(lock(&PUBLISH));
        let msg = interrupt_message();
        remove_live();
        eprintln!("{msg}");
        std::process::exit(130);
    });
}

/// Describe what the running command keeps when it is interrupted (called at the interrupt, so it
/// can look at the disk: `train` names its newest checkpoint).
pub(crate) fn set_interrupt_note(note: impl Fn() -> String + Send + 'static) {
    *lock(&NOTE) = Some(Box::new(note));
}

/// Name the running command (`main` does, from the subcommand): the manifest records each
/// command's files under its name.
pub(crate) fn set_command(name: &str) {
    let _ = COMMAND.set(name.to_string());
}

fn command_name() -> &'static str {
    COMMAND.get().map_or("veila", String::as_str)
}

/// Rewrite an error so that it names the output the user asked for instead of a staging path.
pub(crate) fn explain(err: anyhow::Error) -> anyhow::Error {
    let mut msg = format!("{err:#}");
    let names = lock(&NAMES);
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

/// The staged folder gets the old folder's permissions, or the usual 0755 (a temporary folder is
/// created private).
fn set_folder_mode(staged: &Path, old: Option<&Path>) {
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
fn rel_key(p: &Path) -> String {
    p.components()
        .map(|c| c.as_os_str().to_string_lossy())
        .collect::<Vec<_>>()
        .join("/")
}

/// Brings the old folder's files that are not the command's own into the staged folder.
struct Merge<'a> {
    old_root: &'a Path,
    new_root: &'a Path,
    out: &'a Path,
    own_old: &'a BTreeSet<String>,
    new_keys: &'a BTreeSet<String>,
    inputs: &'a Inputs,
    command: &'a str,
}

impl Merge<'_> {
    fn dir(&self, rel: &Path) -> Result<()> {
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
        if e.file_type().is_ok_and(|t| t.is_dir()) {
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
const FILE_LOCK_WAIT: std::time::Duration = std::time::Duration::from_secs(5);

/// The lock of a folder that single files are written into, waiting up to [`FILE_LOCK_WAIT`] for
/// another writer; none where the folder's parent takes no lock file (a read-only parent such as
/// `/home`), as the folder itself may still be writable.
fn lock_files_folder(dir: &Path) -> Result<Option<FolderLock>> {
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
fn is_busy(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        c.downcast_ref::<veila_data::Error>().is_some_and(|d| {
            matches!(d, veila_data::Error::Io { source, .. }
                if source.kind() == std::io::ErrorKind::WouldBlock)
        })
    })
}

fn try_lock_files_folder(dir: &Path) -> Result<Option<FolderLock>> {
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

fn write_and_rename(files: &[(PathBuf, Vec<u8>)]) -> Result<()> {
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

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

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
        let staged = stage_output(&out, false, &Inputs::new(), "generate").unwrap();
        let hidden = staged.path().join("scan_000.bin");
        let err = anyhow::anyhow!("{}: No space left on device", hidden.display());
        drop(staged);
        let msg = explain(err).to_string();
        assert!(
            msg.contains(&out.join("scan_000.bin").display().to_string()),
            "{msg}"
        );
        assert!(!msg.contains(".veila-staging"), "{msg}");
        // the staging folder and the lock went with the failed command
        assert_eq!(names(d.path()), Vec::<String>::new());
    }

    fn publish(out: &Path, command: &str, files: &[(&str, &str)]) -> Result<()> {
        let staged = stage_output(out, true, &Inputs::new(), command)?;
        for (n, text) in files {
            let p = staged.path().join(n);
            std::fs::create_dir_all(p.parent().unwrap()).unwrap();
            std::fs::write(p, text).unwrap();
        }
        staged.commit()
    }

    #[test]
    fn force_replaces_the_commands_own_files_only() {
        let d = tempfile::tempdir().unwrap();
        let out = d.path().join("o");
        publish(
            &out,
            "generate",
            &[
                ("scan_000.bin", "g0"),
                ("scan_001.bin", "g1"),
                ("generate.json", "g"),
            ],
        )
        .unwrap();
        // the user's files, one named like an output
        std::fs::write(out.join("scan_2024_notes.txt"), "mine").unwrap();
        std::fs::write(out.join("notes.txt"), "mine").unwrap();
        // without --force a non-empty folder is refused
        let refused = stage_output(&out, false, &Inputs::new(), "generate")
            .unwrap_err()
            .to_string();
        assert!(refused.contains("--force"), "{refused}");
        // a smaller run drops its stale scan and keeps everything else
        publish(
            &out,
            "generate",
            &[("scan_000.bin", "G0"), ("generate.json", "G")],
        )
        .unwrap();
        assert_eq!(
            names(&out),
            [
                MANIFEST,
                "generate.json",
                "notes.txt",
                "scan_000.bin",
                "scan_2024_notes.txt"
            ]
        );
        assert_eq!(
            std::fs::read_to_string(out.join("scan_000.bin")).unwrap(),
            "G0"
        );
        // another command never replaces generate's files, and drops none of them
        let e = publish(&out, "edit", &[("scan_000.bin", "E"), ("edit.json", "e")])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("scan_000.bin") && e.contains("veila edit"),
            "{e}"
        );
        assert_eq!(
            std::fs::read_to_string(out.join("scan_000.bin")).unwrap(),
            "G0"
        );
        publish(&out, "edit", &[("edit.json", "e")]).unwrap();
        publish(&out, "edit", &[("edit2.json", "e")]).unwrap();
        assert_eq!(
            names(&out),
            [
                MANIFEST,
                "edit2.json",
                "generate.json",
                "notes.txt",
                "scan_000.bin",
                "scan_2024_notes.txt"
            ]
        );
        // nor does it write over the user's file
        let e = publish(&out, "generate", &[("notes.txt", "x")])
            .unwrap_err()
            .to_string();
        assert!(e.contains("notes.txt"), "{e}");
        assert_eq!(
            std::fs::read_to_string(out.join("notes.txt")).unwrap(),
            "mine"
        );
        // nothing is left beside the output
        assert_eq!(names(d.path()), ["o"]);
        let m = read_manifest(&out).unwrap();
        assert_eq!(m.commands["generate"].len(), 2);
        assert_eq!(
            m.commands["edit"].iter().collect::<Vec<_>>(),
            ["edit2.json"]
        );
    }

    #[test]
    fn a_rerun_with_fewer_frames_leaves_no_stale_frames_in_subfolders() {
        let d = tempfile::tempdir().unwrap();
        let out = d.path().join("sim");
        publish(
            &out,
            "simulate",
            &[
                ("velodyne/0.bin", "a"),
                ("velodyne/1.bin", "b"),
                ("poses.txt", "2"),
            ],
        )
        .unwrap();
        std::fs::write(out.join("velodyne/user.txt"), "mine").unwrap();
        publish(
            &out,
            "simulate",
            &[("velodyne/0.bin", "A"), ("poses.txt", "1")],
        )
        .unwrap();
        assert_eq!(names(&out.join("velodyne")), ["0.bin", "user.txt"]);
    }

    #[test]
    fn a_second_writer_of_one_folder_is_refused() {
        let d = tempfile::tempdir().unwrap();
        let out = d.path().join("o");
        let first = stage_output(&out, true, &Inputs::new(), "generate").unwrap();
        let e = stage_output(&d.path().join("./o"), true, &Inputs::new(), "generate")
            .unwrap_err()
            .to_string();
        assert!(e.contains("another veila process"), "{e}");
        // and file outputs into that folder wait for no one: they are refused too
        std::fs::create_dir(&out).unwrap();
        let e = publish_files(
            &[(out.join("a.txt"), b"1".to_vec())],
            &Inputs::new(),
            true,
            false,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("another veila process"), "{e}");
        std::fs::remove_dir(&out).unwrap();
        std::fs::write(first.path().join("f"), "x").unwrap();
        first.commit().unwrap();
        assert_eq!(names(d.path()), ["o"]);
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
        assert_eq!(names(d.path()), ["a.txt", "b.txt"]);
    }

    #[test]
    fn partial_files_of_a_killed_owner_go_under_the_lock() {
        let d = tempfile::tempdir().unwrap();
        let ck = d.path().join("run/checkpoints");
        std::fs::create_dir_all(ck.join(".step-0000000010.tmp-77")).unwrap();
        std::fs::create_dir_all(ck.join("step-0000000005")).unwrap();
        let held = lock_folder(&d.path().join("run")).unwrap();
        let n = remove_partial(&held, &ck, |n| n.contains(".tmp-")).unwrap();
        assert_eq!(n, 1);
        assert_eq!(names(&ck), ["step-0000000005"]);
    }
}
