//! What a signal must clean up, and what the interrupted command says it kept.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, OnceLock};

/// What lives on disk only while this process runs: removed on a signal.
#[derive(Debug)]
pub(super) enum Live {
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

pub(super) static LIVE: Mutex<Vec<Live>> = Mutex::new(Vec::new());

/// Every staging path this process made and the output it stood for (kept for error messages).
pub(super) static NAMES: Mutex<Vec<(PathBuf, PathBuf)>> = Mutex::new(Vec::new());

/// Held while an output is swapped into place; the signal handler takes it and never lets go.
pub(super) static PUBLISH: Mutex<()> = Mutex::new(());

/// Outputs this process published completely.
pub(super) static PUBLISHED: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());

type Note = Box<dyn Fn() -> String + Send>;

/// What the command keeps when it is interrupted ([`set_interrupt_note`]).
pub(super) static NOTE: Mutex<Option<Note>> = Mutex::new(None);

/// The running command's name (`generate`, `simulate`, ...), for the manifest.
pub(super) static COMMAND: OnceLock<String> = OnceLock::new();

/// Set once a signal arrived.
pub(super) static STOPPING: AtomicBool = AtomicBool::new(false);

pub(super) fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

pub(super) fn register(l: Live) {
    match &l {
        Live::Staging { path, out } => lock(&NAMES).push((path.clone(), out.clone())),
        Live::File { tmp, dest } => lock(&NAMES).push((tmp.clone(), dest.clone())),
        Live::Backup(_) | Live::Lock(_) => {}
    }
    lock(&LIVE).push(l);
}

pub(super) fn unregister(path: &Path) {
    lock(&LIVE).retain(|l| l.path() != path);
}

/// Remove every registered staging folder, backup, temporary file and lock file (the signal
/// handler's work). A staging folder is removed until it stays gone (the main thread may still
/// be writing into it).
pub(super) fn remove_live() {
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
pub(super) fn interrupt_message() -> String {
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

pub(super) fn join_paths(p: &[PathBuf]) -> String {
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

pub(super) fn command_name() -> &'static str {
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
