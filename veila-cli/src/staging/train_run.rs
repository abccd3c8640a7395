//! `veila train`'s run folder (`[output] dir`): the same discipline as every other output, for a
//! folder that is written over hours instead of published at once.
//!
//! * **Its own folder.** The folder must be absent, empty, carry train's marker [`TRAIN_MARKER`]
//!   (`.veila-train.json`, written on the first run), or hold nothing but what train writes there
//!   ([`is_train_name`]: a run from before the marker). Any other folder is refused before
//!   anything is written, `--force` or not: a downloaded config's `dir = "../.."` cannot reach a
//!   user's files.
//! * **Not its inputs.** The folder may not be, hold or lie inside the shards folder or the
//!   `encoders_from` bundle, and no input file (the config, `[model] bundle`, pretrained weights)
//!   may lie where train writes (`bundle/`, `checkpoints/`, the logs, the marker). Paths are
//!   compared canonicalized, so `..`, links and absolute spellings are all seen through.
//! * **One writer**: the folder's lock ([`lock_folder`]) for the whole run.
//! * **Cleanup of its own partial files only**: the exact names train's writers use, `.NAME.tmp-PID`
//!   and `.NAME.old-PID` for `NAME` one of train's (`bundle` in the folder; `step-N` checkpoints
//!   and `run.json` in `checkpoints/` and `checkpoints/mean/`), and veila's own locked temporary
//!   files, in a folder carrying the marker; a user's `.bashrc.old-2023` is never one of them.
//! * **`--force` to replace a bundle**: a finished run's `bundle/` is replaced only with `--force`
//!   ([`check_train_bundle`]), and only when it is a folder.

use std::path::{Component, Path, PathBuf};

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};
use veila_data::read_capped::{MAX_CONFIG_BYTES, read_metadata};

use super::lock::*;
use super::signals::*;

/// The marker of a folder `veila train` writes its run into.
pub(crate) const TRAIN_MARKER: &str = ".veila-train.json";

const MARKER_FORMAT: &str = "veila-train-run/1";

/// The names train writes at the top of its folder (`veila segment train` writes `segmenter`
/// where `veila train` writes `bundle`).
pub(crate) const BUNDLE: &str = "bundle";
pub(crate) const SEGMENTER: &str = "segmenter";
const CHECKPOINTS: &str = "checkpoints";
const LOG: &str = "train_log.jsonl";

/// The marker's content: its format and the names train writes in the folder.
#[derive(Debug, Serialize, Deserialize)]
struct Marker {
    format: String,
    files: Vec<String>,
}

/// What a run reads, for the checks of its folder: folders (`[data] shards`, `[model]
/// encoders_from`) and files (the config, `[model] bundle`, pretrained weights), each with the name
/// errors give it.
#[derive(Debug, Default)]
pub(crate) struct TrainInputs {
    folders: Vec<(String, PathBuf)>,
    files: Vec<(String, PathBuf)>,
}

impl TrainInputs {
    /// An input folder.
    pub(crate) fn folder(&mut self, what: &str, path: &Path) -> &mut Self {
        self.folders.push((what.into(), path.to_path_buf()));
        self
    }

    /// An input file.
    pub(crate) fn file(&mut self, what: &str, path: &Path) -> &mut Self {
        self.files.push((what.into(), path.to_path_buf()));
        self
    }
}

/// Whether `name`, at the top of a run folder, is one train writes there: `bundle` (or
/// `segmenter`), `checkpoints`,
/// `train_log.jsonl`, `train_log.rank-N.jsonl`, the marker, a partial bundle of a killed run, or
/// one of veila's own temporary files.
pub(crate) fn is_train_name(name: &str) -> bool {
    let rank_log = name
        .strip_prefix("train_log.rank-")
        .and_then(|r| r.strip_suffix(".jsonl"))
        .is_some_and(is_digits);
    matches!(name, BUNDLE | SEGMENTER | CHECKPOINTS | LOG | TRAIN_MARKER)
        || rank_log
        || is_partial_of(name, is_model_name)
        || veila_data::atomic::is_leftover_name(name)
}

fn is_model_name(name: &str) -> bool {
    name == BUNDLE || name == SEGMENTER
}

fn is_digits(s: &str) -> bool {
    !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit())
}

/// Whether `entry` is `.NAME.tmp-PID` or `.NAME.old-PID` (PID decimal) for a `NAME` that `own`
/// accepts: the partial file of one of train's writers.
pub(crate) fn is_partial_of(entry: &str, own: impl Fn(&str) -> bool) -> bool {
    let Some(rest) = entry.strip_prefix('.') else {
        return false;
    };
    [".tmp-", ".old-"].iter().any(|sep| {
        rest.rsplit_once(sep)
            .is_some_and(|(name, pid)| is_digits(pid) && own(name))
    })
}

/// A checkpoint folder's own names: `step-N` (ten digits) and `run.json`.
fn is_checkpoint_name(name: &str) -> bool {
    name == veila_diffusion::trainer::RUN_RECORD_FILE
        || name
            .strip_prefix("step-")
            .is_some_and(|n| n.len() == 10 && is_digits(n))
}

/// `p` made absolute with links resolved: canonicalized where it exists, else its nearest
/// existing ancestor canonicalized and the rest appended (`..` there taken lexically: a folder
/// that does not exist is no link).
fn resolved(p: &Path) -> Option<PathBuf> {
    if let Ok(c) = std::fs::canonicalize(p) {
        return Some(c);
    }
    let abs = std::path::absolute(p).ok()?;
    let mut base = abs.as_path();
    let mut rest = Vec::new();
    loop {
        if let Ok(c) = std::fs::canonicalize(base) {
            let mut out = c;
            for comp in rest.iter().rev() {
                match comp {
                    Component::ParentDir => {
                        out.pop();
                    }
                    Component::Normal(n) => out.push(n),
                    _ => {}
                }
            }
            return Some(out);
        }
        rest.push(base.components().next_back()?);
        base = base.parent()?;
    }
}

fn describe(p: &Path) -> String {
    p.display().to_string().escape_debug().to_string()
}

/// `out` as given, and the folder it resolves to when that reads otherwise (`../..`).
fn describe_out(out: &Path) -> String {
    match resolved(out) {
        Some(r) if r != out => format!("{} (that is {})", describe(out), describe(&r)),
        _ => describe(out),
    }
}

/// Refuse `out` when it is, holds or lies inside an input folder, or when an input file lies where
/// train writes.
fn check_inputs(out: &Path, inputs: &TrainInputs) -> Result<()> {
    let Some(o) = resolved(out) else {
        return Ok(());
    };
    for (what, p) in &inputs.folders {
        let Ok(i) = std::fs::canonicalize(p) else {
            continue;
        };
        let relation = if o == i {
            "is"
        } else if o.starts_with(&i) {
            "is inside"
        } else if i.starts_with(&o) {
            "holds"
        } else {
            continue;
        };
        bail!(
            "{}: [output] dir {relation} the {what} {}; train writes its checkpoints, log and \
             bundle there, so give the run a folder of its own (nothing was changed)",
            describe_out(out),
            describe(p)
        );
    }
    let owned = [BUNDLE, SEGMENTER, CHECKPOINTS, TRAIN_MARKER].map(|n| o.join(n));
    for (what, p) in &inputs.files {
        let Ok(i) = std::fs::canonicalize(p) else {
            continue;
        };
        let log = i.parent() == Some(o.as_path())
            && i.file_name().and_then(|n| n.to_str()).is_some_and(|n| {
                n == LOG || (n.starts_with("train_log.") && n.ends_with(".jsonl"))
            });
        if log || owned.iter().any(|d| i.starts_with(d)) {
            bail!(
                "{}: the {what} {} lies where train writes in its [output] dir (bundle/, \
                 checkpoints/, the logs); move it or choose another folder (nothing was changed)",
                describe_out(out),
                describe(p)
            );
        }
    }
    Ok(())
}

/// The marker of `out`, when it has one; an error when it has one that is not train's.
fn read_marker(out: &Path) -> Result<Option<Marker>> {
    let p = out.join(TRAIN_MARKER);
    if std::fs::symlink_metadata(&p).is_err() {
        return Ok(None);
    }
    let bytes = read_metadata(&p, MAX_CONFIG_BYTES, "a training run's marker")?;
    let m: Marker = serde_json::from_slice(&bytes)
        .ok()
        .filter(|m: &Marker| m.format == MARKER_FORMAT)
        .with_context(|| {
            format!(
                "{}: not the marker `veila train` writes (format {MARKER_FORMAT}); choose another \
                 [output] dir (nothing was changed)",
                describe(&p)
            )
        })?;
    Ok(Some(m))
}

/// Refuse `out` unless it is absent, an empty folder, a folder carrying train's marker, or one
/// holding nothing but what train writes (real files and folders, not links).
fn check_own_folder(out: &Path) -> Result<()> {
    let Ok(meta) = std::fs::metadata(out) else {
        if std::fs::symlink_metadata(out).is_ok() {
            bail!("{}: [output] dir is a broken link", describe(out));
        }
        return Ok(());
    };
    if !meta.is_dir() {
        bail!(
            "{}: [output] dir exists and is not a directory",
            describe(out)
        );
    }
    if read_marker(out)?.is_some() {
        return Ok(());
    }
    let rd = std::fs::read_dir(out).with_context(|| format!("{}: cannot read", describe(out)))?;
    let mut names: Vec<(String, bool)> = rd
        .flatten()
        .map(|e| {
            let link = e.file_type().is_ok_and(|t| t.is_symlink());
            (e.file_name().to_string_lossy().into_owned(), link)
        })
        .collect();
    names.sort();
    if let Some((name, _)) = names.iter().find(|(n, link)| *link || !is_train_name(n)) {
        bail!(
            "{}: [output] dir is not empty and is not a folder `veila train` made (it has no \
             {TRAIN_MARKER}, and `{}` is not one of train's files); train writes only into an \
             empty folder or its own run, with or without --force: choose another folder \
             (nothing was changed)",
            describe_out(out),
            name.escape_debug()
        );
    }
    Ok(())
}

/// Claim `out` for a training run of `ranks` processes writing its model to `out/model` (`bundle`
/// or `segmenter`): the checks of the module docs, then its lock (held until the returned lock is
/// dropped), its marker, `checkpoints/`, the partial files of a killed earlier run removed, and an
/// interrupt that says which checkpoints were kept.
pub(crate) fn claim_train_run(
    out: &Path,
    model: &str,
    ranks: usize,
    inputs: &TrainInputs,
) -> Result<FolderLock> {
    check_inputs(out, inputs)?;
    check_own_folder(out)?;
    let held = lock_folder(out)?;
    // what a writer that finished while we waited left
    check_own_folder(out)?;
    std::fs::create_dir_all(out).with_context(|| format!("{}: cannot create", describe(out)))?;
    write_marker(out, model, ranks)?;
    let ck = out.join(CHECKPOINTS);
    std::fs::create_dir_all(&ck).with_context(|| format!("{}: cannot create", describe(&ck)))?;
    // a killed earlier run's partial files: only train's own names, and veila's locked temporaries
    remove_partial(&held, out, |n| is_partial_of(n, is_model_name))?;
    veila_data::atomic::sweep_stale(out);
    for d in [ck.clone(), ck.join("mean")] {
        remove_partial(&held, &d, |n| is_partial_of(n, is_checkpoint_name))?;
        veila_data::atomic::sweep_stale(&d);
    }
    veila_data::atomic::sweep_stale(&ck.join("encoders"));
    set_interrupt_note(move || match newest_checkpoint_step(&ck) {
        Some(step) => format!(
            "checkpoints up to step {step} kept in {} (rerun the same command to resume)",
            ck.display()
        ),
        None => format!("no checkpoint was written yet in {}", ck.display()),
    });
    Ok(held)
}

/// Write (or complete) the marker: the names this run writes in `out`.
fn write_marker(out: &Path, model: &str, ranks: usize) -> Result<()> {
    let old = read_marker(out)?;
    let mut files: Vec<String> = old.map(|m| m.files).unwrap_or_default();
    let mut mine = vec![model.to_string(), CHECKPOINTS.into(), LOG.into()];
    mine.extend((1..ranks).map(|r| format!("train_log.rank-{r}.jsonl")));
    let before = files.clone();
    for n in mine {
        if !files.contains(&n) {
            files.push(n);
        }
    }
    if !before.is_empty() && before == files {
        return Ok(());
    }
    let marker = Marker {
        format: MARKER_FORMAT.into(),
        files,
    };
    let json = serde_json::to_vec_pretty(&marker)?;
    veila_data::atomic::write_atomic(&out.join(TRAIN_MARKER), &json)?;
    Ok(())
}

/// Before a run that will write `out/model` (`bundle` or `segmenter`): an existing one is
/// replaced only with `force`, and only when it is a folder.
pub(crate) fn check_train_bundle(out: &Path, model: &str, force: bool) -> Result<()> {
    let b = out.join(model);
    let Ok(meta) = std::fs::symlink_metadata(&b) else {
        return Ok(());
    };
    let t = meta.file_type();
    if !t.is_dir() {
        let kind = if t.is_symlink() {
            "a symbolic link"
        } else if t.is_file() {
            "a file"
        } else {
            veila_data::read_capped::file_type_name(&t)
        };
        bail!(
            "{}: exists and is {kind}, not a {model} folder: train replaces only its own \
             {model} folder, with or without --force (nothing was changed)",
            describe(&b)
        );
    }
    if !force {
        bail!(
            "{}: a {model} is already there (a finished run's): pass --force to replace it \
             with this run's, or choose another [output] dir (nothing was changed)",
            describe(&b)
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_exact_names_of_trains_writers_are_partial_files() {
        for own in [
            ".bundle.tmp-4242",
            ".bundle.old-1",
            ".step-0000000010.tmp-77",
            ".run.json.tmp-9",
        ] {
            assert!(
                is_partial_of(own, |n| n == BUNDLE || is_checkpoint_name(n)),
                "{own}"
            );
        }
        for user in [
            ".bashrc.old-2023",
            ".mydata.tmp-keep",
            ".bundle.tmp-",
            "bundle.tmp-1",
            ".step-10.tmp-7",
            ".bundle.tmp-12x",
            ".notes.bundle.tmp-3",
        ] {
            assert!(
                !is_partial_of(user, |n| n == BUNDLE || is_checkpoint_name(n)),
                "{user}"
            );
        }
        for name in [
            "bundle",
            "checkpoints",
            "train_log.jsonl",
            "train_log.rank-3.jsonl",
        ] {
            assert!(is_train_name(name), "{name}");
        }
        for name in [
            "notes.txt",
            ".bashrc.old-2023",
            "train_log.rank-x.jsonl",
            "Downloads",
        ] {
            assert!(!is_train_name(name), "{name}");
        }
    }
}
