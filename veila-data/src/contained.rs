//! Paths read from artifacts stay inside their folder.
//!
//! A downloaded dataset, shard manifest or model bundle names other files: a nuScenes calibration
//! its image and sweep, a manifest its shards, a bundle its weights. Each such path is checked by
//! [`contained`] before anything at it is opened, hashed or read: it must be relative, without
//! `..` or a root, and every link on the way must resolve inside the folder it is relative to (the
//! dataset root, the shards folder, the bundle folder). Otherwise the error names the file that
//! holds the path and the field, and says nothing about what lies outside (whether a link's target
//! exists reads the same as where it points). A path the user types is theirs to choose: only
//! paths read from files come here.

use std::path::{Component, Path, PathBuf};

use crate::{Error, Result};

/// `rel`, the path in field `field` of the artifact `file`, resolved inside `root`: `root.join(rel)`
/// when `rel` is relative, has no `..`, root or prefix component, names a file below `root`, and
/// every link along it resolves inside `root` (canonicalized; `root` may be reached through links
/// itself). Nothing at the path is opened: links are read, files are not. A path whose rest does
/// not exist is returned too (opening it then fails naming it), since nothing outside can be read
/// through a name that is not there.
///
/// Errors: [`Error::PathOutside`] naming `file`, `field` and `rel`; [`Error::Io`] when `root`
/// cannot be resolved.
pub fn contained(root: &Path, rel: &Path, field: &str, file: &Path) -> Result<PathBuf> {
    let refuse = |reason: String| Error::PathOutside {
        file: file.to_path_buf(),
        field: field.to_string(),
        value: rel.to_string_lossy().escape_debug().to_string(),
        reason,
    };
    let mut names = Vec::new();
    for c in rel.components() {
        match c {
            Component::Normal(n) => names.push(n),
            Component::CurDir => {}
            Component::ParentDir => {
                return Err(refuse(format!(
                    "climbs out of its folder with `..`; paths in this file must stay inside {} \
                     (refused, nothing read)",
                    root.display()
                )));
            }
            Component::RootDir | Component::Prefix(_) => {
                return Err(refuse(format!(
                    "an absolute path; paths in this file must be relative to {} (refused, \
                     nothing read)",
                    root.display()
                )));
            }
        }
    }
    if names.is_empty() {
        return Err(refuse("names no file".into()));
    }
    let base = std::fs::canonicalize(root).map_err(|e| Error::io(root, e))?;
    let mut at = base.clone();
    let mut spelled = PathBuf::new();
    for n in names {
        at.push(n);
        spelled.push(n);
        let Ok(meta) = std::fs::symlink_metadata(&at) else {
            // the rest does not exist (or cannot be looked at): opening it fails inside `root`
            break;
        };
        if !meta.file_type().is_symlink() {
            continue;
        }
        match std::fs::canonicalize(&at) {
            Ok(target) if target.starts_with(&base) => at = target,
            // a dangling link reads as one that leads out: no word on what lies outside
            _ => {
                return Err(refuse(format!(
                    "leads through the link `{}` to no file inside {} (refused, nothing read)",
                    spelled.to_string_lossy().escape_debug(),
                    root.display()
                )));
            }
        }
    }
    Ok(root.join(rel))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn err(root: &Path, rel: &str) -> String {
        contained(root, Path::new(rel), "x.file", Path::new("meta.json"))
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn relative_paths_inside_are_joined_and_the_rest_refused() {
        let d = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(d.path().join("a/b")).unwrap();
        std::fs::write(d.path().join("a/b/c.bin"), b"x").unwrap();
        for rel in ["a/b/c.bin", "./a/b/c.bin", "a/b/missing.bin", "no/such/dir"] {
            let got = contained(d.path(), Path::new(rel), "f", Path::new("m.json")).unwrap();
            assert_eq!(got, d.path().join(rel));
        }
        let e = err(d.path(), "/etc/passwd");
        assert!(
            e.starts_with("meta.json: x.file `/etc/passwd`: an absolute path"),
            "{e}"
        );
        let e = err(d.path(), "a/../../outside.bin");
        assert!(
            e.contains("x.file `a/../../outside.bin`: climbs out"),
            "{e}"
        );
        // `..` is refused even where it would stay inside
        assert!(err(d.path(), "a/../a/b/c.bin").contains("climbs out"));
        assert!(err(d.path(), "").contains("names no file"));
        assert!(err(d.path(), ".").contains("names no file"));
    }

    #[cfg(unix)]
    #[test]
    fn links_must_resolve_inside_and_say_nothing_of_the_outside() {
        let d = tempfile::tempdir().unwrap();
        let root = d.path().join("root");
        let outside = d.path().join("outside");
        std::fs::create_dir_all(root.join("real")).unwrap();
        std::fs::create_dir_all(&outside).unwrap();
        std::fs::write(outside.join("secret.bin"), b"s").unwrap();
        std::fs::write(root.join("real/f.bin"), b"f").unwrap();
        let link = |target: &Path, name: &str| {
            std::os::unix::fs::symlink(target, root.join(name)).unwrap();
        };
        link(&outside.join("secret.bin"), "out.bin");
        link(&outside, "outdir");
        link(&outside.join("absent.bin"), "dangling.bin");
        link(Path::new("real"), "inside");
        link(Path::new("real/f.bin"), "f.bin");
        let a = err(&root, "out.bin");
        assert!(
            a.contains("x.file `out.bin`: leads through the link `out.bin` to no file inside"),
            "{a}"
        );
        let b = err(&root, "outdir/secret.bin");
        assert!(b.contains("the link `outdir`"), "{b}");
        // a dangling link reads like one to an existing file outside
        let c = err(&root, "dangling.bin");
        assert_eq!(c.replace("dangling.bin", "out.bin"), a);
        // links that stay inside are followed
        for rel in ["inside/f.bin", "f.bin"] {
            assert_eq!(
                contained(&root, Path::new(rel), "f", Path::new("m")).unwrap(),
                root.join(rel)
            );
        }
        // the root itself may be reached through a link
        let via = d.path().join("via");
        std::os::unix::fs::symlink(&root, &via).unwrap();
        assert!(contained(&via, Path::new("real/f.bin"), "f", Path::new("m")).is_ok());
        assert!(contained(&via, Path::new("out.bin"), "f", Path::new("m")).is_err());
    }
}
