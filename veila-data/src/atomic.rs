//! Atomic file output: write to a temporary file in the destination's directory, then rename.
//!
//! A reader never sees a half-written file, and killing the process at any moment leaves either the old
//! file or the new one, never a corrupt one.

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
        .prefix(".veila-")
        .suffix(".tmp")
        .tempfile_in(dir)
        .map_err(|e| Error::io(dir, e))
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
