//! Atomic file output: write to a temporary file in the destination's directory, then rename.
//!
//! A reader never sees a half-written file, and killing the process at any moment leaves either the old
//! file or the new one, never a corrupt one. A process killed by SIGKILL leaves its temporary file
//! (`.veila-PID-*.tmp`); [`sweep_stale`] removes those whose process is gone.

use std::io::Write;
use std::path::Path;

use crate::{Error, Result};

/// Temporary files are created private (0600); give the result the usual 0644 before it is renamed
/// into place, so outputs are readable like any other file.
fn make_readable(file: &std::fs::File, path: &Path) -> Result<()> {
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

/// Temporary files carry the process id (`.veila-PID-XXXXXX.tmp`), so that [`sweep_stale`] can tell
/// those of a killed process from those of a running one.
pub fn temp_prefix() -> String {
    format!(".veila-{}-", std::process::id())
}

/// A temporary file in `path`'s directory (so the final rename stays within one file system); an
/// error naming the directory when it does not exist or cannot take the file.
fn temp_beside(path: &Path) -> Result<tempfile::NamedTempFile> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    if !dir.is_dir() {
        return Err(Error::io(
            dir,
            std::io::Error::new(
                std::io::ErrorKind::NotFound,
                "output directory does not exist",
            ),
        ));
    }
    tempfile::Builder::new()
        .prefix(&temp_prefix())
        .suffix(".tmp")
        .tempfile_in(dir)
        .map_err(|e| Error::io(dir, e))
}

/// The process id a staging name carries: `.veila-staging-PID-*` or `.veila-PID-*.tmp`.
pub fn staging_pid(name: &str) -> Option<u32> {
    let rest = name.strip_prefix(".veila-staging-").or_else(|| {
        name.strip_prefix(".veila-")
            .filter(|_| name.ends_with(".tmp"))
    })?;
    let (pid, tail) = rest.split_once('-')?;
    if tail.is_empty() || pid.is_empty() || !pid.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    pid.parse().ok()
}

/// Whether process `pid` still runs. Unknown (no `/proc`) counts as running, so nothing of a live
/// process is ever removed.
fn pid_alive(pid: u32) -> bool {
    if pid == std::process::id() {
        return true;
    }
    let proc = Path::new("/proc");
    if !proc.join("self").exists() {
        return true;
    }
    proc.join(pid.to_string()).exists()
}

/// Remove the staging folders and temporary files in `dir` left by killed veila processes
/// (recognised by name; only those whose process is gone). Returns how many were removed.
pub fn sweep_stale(dir: &Path) -> usize {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return 0;
    };
    let mut removed = 0;
    for e in rd.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(pid) = staging_pid(&name) else {
            continue;
        };
        if pid_alive(pid) {
            continue;
        }
        let p = e.path();
        let ok = if p.is_dir() && name.starts_with(".veila-staging-") {
            std::fs::remove_dir_all(&p).is_ok()
        } else if p.is_file() {
            std::fs::remove_file(&p).is_ok()
        } else {
            false
        };
        if ok {
            removed += 1;
        }
    }
    removed
}

/// Write `bytes` to `path` atomically (temp file in the same directory + rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_with(path, |w| w.write_all(bytes))
}

/// Write `path` atomically through a closure that fills a buffered writer.
pub fn write_atomic_with(
    path: &Path,
    fill: impl FnOnce(&mut std::io::BufWriter<&mut std::fs::File>) -> std::io::Result<()>,
) -> Result<()> {
    let mut tmp = temp_beside(path)?;
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

/// Write several files so that either all of them appear or none does: every file is first written
/// to a temporary file beside its destination, and only when all temporaries are complete are they
/// renamed into place. A failure before that point (an unwritable folder, a full disk) leaves no
/// output at all.
pub fn write_atomic_all(files: &[(&Path, &[u8])]) -> Result<()> {
    let mut staged = Vec::with_capacity(files.len());
    for (path, bytes) in files {
        let mut tmp = temp_beside(path)?;
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
    fn staging_names_carry_the_pid() {
        assert_eq!(staging_pid(".veila-staging-123-abc"), Some(123));
        assert_eq!(staging_pid(".veila-77-x1.tmp"), Some(77));
        assert_eq!(staging_pid(".veila-77-x1"), None);
        assert_eq!(staging_pid(".veila-staging-abc"), None);
        assert_eq!(staging_pid(".veila-write-probe"), None);
        assert_eq!(staging_pid("scan.bin"), None);
    }

    #[test]
    fn sweep_removes_dead_leftovers_only() {
        let d = tempfile::tempdir().unwrap();
        // a pid far above any pid_max of a Linux system is certainly gone
        let dead = ".veila-staging-4294967-abc";
        let mine = format!(".veila-staging-{}-abc", std::process::id());
        std::fs::create_dir(d.path().join(dead)).unwrap();
        std::fs::write(d.path().join(dead).join("f"), b"x").unwrap();
        std::fs::create_dir(d.path().join(&mine)).unwrap();
        std::fs::write(d.path().join(".veila-4294967-x.tmp"), b"x").unwrap();
        std::fs::write(d.path().join("user.txt"), b"x").unwrap();
        let n = sweep_stale(d.path());
        if Path::new("/proc/self").exists() {
            assert_eq!(n, 2);
            assert!(!d.path().join(dead).exists());
            assert!(!d.path().join(".veila-4294967-x.tmp").exists());
        }
        assert!(d.path().join(&mine).exists());
        assert!(d.path().join("user.txt").exists());
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
