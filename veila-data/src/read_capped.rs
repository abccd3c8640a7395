//! Metadata files read whole, with a size cap: bundle and dataset manifests, configs, sensor
//! files, calibrations, label maps and `.label` files come from downloads and command lines, so a
//! hostile or broken one must not exhaust memory or block the process.
//!
//! [`read_metadata`] refuses, before anything is read:
//! - anything but a regular file, after following links (a link to `/dev/zero`, a FIFO, a
//!   directory, a device). The check is made on the path before it is opened, since opening a FIFO
//!   blocks until a writer comes, and again on the opened file;
//! - a file longer than the cap for its kind (one of the `MAX_*_BYTES` constants). A sparse file
//!   costs nothing: its length is read, not its content.
//!
//! It then reads at most the cap plus one byte, so a file that grows while it is read is refused
//! too. Every error names the file.

use std::fs::File;
use std::io::{Read, Take};
use std::path::Path;

use crate::scan::{KITTI_RECORD_BYTES, MAX_SCAN_POINTS, NUSCENES_RECORD_BYTES};
use crate::{Error, Result};

/// Cap of JSON metadata: `bundle.json` and a bundle's `manifest.json`, a converted dataset's
/// `manifest.json` and shard sidecars, training checkpoint state. 64 MiB: the bundled model's are
/// a few KiB, and a shard manifest listing nuScenes' 390 000 sweeps by 32-digit token is about
/// 15 MiB.
pub const MAX_JSON_METADATA_BYTES: u64 = 64 << 20;

/// Cap of configuration text: the training TOML, scene TOML and scene lists, sensor files, the
/// label-map YAML. 1 MiB: real ones are a few KiB (`semantic-kitti.yaml` is about 7 KiB).
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// Cap of per-frame calibration and annotation files: KITTI `calib/*.txt` and `label_2/*.txt`,
/// odometry `calib.txt`, nuScenes per-sample JSON (its annotated boxes included: a few hundred, at
/// most about 1 KiB each pretty-printed). 4 MiB; a KITTI calibration is under 1 KiB.
pub const MAX_CALIBRATION_BYTES: u64 = 4 << 20;

/// Cap of a SemanticKITTI `.label` file: one `u32` per point, for at most
/// [`MAX_SCAN_POINTS`] points (64 MiB), the scan readers' own limit.
pub const MAX_LABEL_FILE_BYTES: u64 = MAX_SCAN_POINTS as u64 * 4;

/// Cap of a KITTI `.bin` scan: [`MAX_SCAN_POINTS`] records of 16 bytes (256 MiB), the length
/// [`crate::scan::read_kitti_bin`] accepts.
pub const MAX_KITTI_SCAN_BYTES: u64 = (MAX_SCAN_POINTS * KITTI_RECORD_BYTES) as u64;

/// Cap of a nuScenes `.pcd.bin` scan: [`MAX_SCAN_POINTS`] records of 20 bytes (320 MiB).
pub const MAX_NUSCENES_SCAN_BYTES: u64 = (MAX_SCAN_POINTS * NUSCENES_RECORD_BYTES) as u64;

/// Cap of a dataset's camera image where `veila convert` hashes its sources: 256 MiB (a KITTI PNG
/// is about 1 MiB, a nuScenes JPEG about 200 KiB). The image decoder has limits of its own.
pub const MAX_CAMERA_IMAGE_BYTES: u64 = 256 << 20;

/// The whole content of the metadata file `path`, at most `cap` bytes; `kind` names what the file
/// is, with its article, in errors ("a bundle file"). See the module docs for what is refused.
pub fn read_metadata(path: &Path, cap: u64, kind: &str) -> Result<Vec<u8>> {
    let (file, len) = open_capped(path, cap, kind)?;
    // `len <= cap`; a file that grew since is caught by the limit of `take`
    let mut bytes = Vec::with_capacity(usize::try_from(len).unwrap_or(0));
    file.take(cap.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(|e| Error::io(path, e))?;
    check_len(path, bytes.len() as u64, cap, kind)?;
    Ok(bytes)
}

/// [`read_metadata`] as UTF-8 text (anything else is an error naming the file).
pub fn read_metadata_string(path: &Path, cap: u64, kind: &str) -> Result<String> {
    String::from_utf8(read_metadata(path, cap, kind)?)
        .map_err(|e| Error::format(path, format!("not UTF-8 text: {e}")))
}

/// Refuses `path` unless it is, after following links, a regular file. Never opens it.
pub(crate) fn check_regular_file(path: &Path) -> Result<std::fs::Metadata> {
    let meta = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    if meta.is_file() {
        Ok(meta)
    } else {
        Err(not_regular(path, &meta))
    }
}

/// Opens the regular file `path` of at most `cap` bytes (checked before and after opening) and
/// returns it with its length. A reader should take at most `cap + 1` bytes and pass the count it
/// got to [`check_len`], which refuses a file that grew.
pub(crate) fn open_capped(path: &Path, cap: u64, kind: &str) -> Result<(File, u64)> {
    check_regular_file(path)?;
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    let meta = file.metadata().map_err(|e| Error::io(path, e))?;
    if !meta.is_file() {
        // replaced between the check and the open
        return Err(not_regular(path, &meta));
    }
    check_len(path, meta.len(), cap, kind)?;
    Ok((file, meta.len()))
}

/// [`open_capped`]'s file, limited to `cap + 1` bytes.
pub(crate) fn open_capped_take(path: &Path, cap: u64, kind: &str) -> Result<Take<File>> {
    Ok(open_capped(path, cap, kind)?.0.take(cap.saturating_add(1)))
}

/// Refuses a length `len` of `path` over `cap`.
pub(crate) fn check_len(path: &Path, len: u64, cap: u64, kind: &str) -> Result<()> {
    if len <= cap {
        return Ok(());
    }
    Err(Error::Refused {
        path: path.to_path_buf(),
        message: format!("{len} bytes, more than the cap of {cap} bytes for {kind}"),
    })
}

fn not_regular(path: &Path, meta: &std::fs::Metadata) -> Error {
    Error::Refused {
        path: path.to_path_buf(),
        message: format!("not a regular file ({})", file_type_name(&meta.file_type())),
    }
}

/// What a file that is not a regular file is, in words with its article: "a FIFO", "a character
/// device", "a block device", "a socket", "a directory", else "a special file".
pub fn file_type_name(t: &std::fs::FileType) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_fifo() {
            return "a FIFO";
        }
        if t.is_char_device() {
            return "a character device";
        }
        if t.is_block_device() {
            return "a block device";
        }
        if t.is_socket() {
            return "a socket";
        }
    }
    if t.is_dir() {
        "a directory"
    } else {
        "a special file"
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const KIND: &str = "a test file";

    fn err(path: &Path, cap: u64) -> String {
        read_metadata(path, cap, KIND).unwrap_err().to_string()
    }

    #[test]
    fn a_file_of_exactly_the_cap_is_read_and_one_byte_more_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.json");
        std::fs::write(&p, b"{\"a\": 1}").unwrap();
        assert_eq!(read_metadata(&p, 8, KIND).unwrap(), b"{\"a\": 1}");
        assert_eq!(read_metadata_string(&p, 8, KIND).unwrap(), "{\"a\": 1}");
        let e = err(&p, 7);
        assert!(
            e.contains("m.json")
                && e.contains("8 bytes, more than the cap of 7 bytes for a test file"),
            "{e}"
        );
    }

    #[test]
    fn a_sparse_file_over_the_cap_is_refused_from_its_length() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bundle.json");
        // 3 GiB of holes: no disk, and nothing is read
        File::create(&p).unwrap().set_len(3 << 30).unwrap();
        let e = err(&p, MAX_JSON_METADATA_BYTES);
        assert!(
            e.contains("bundle.json")
                && e.contains("3221225472 bytes, more than the cap of 67108864"),
            "{e}"
        );
        // just over a small cap, too
        File::create(&p).unwrap().set_len(1025).unwrap();
        assert!(err(&p, 1024).contains("1025 bytes"));
    }

    #[test]
    fn a_directory_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let e = err(dir.path(), 1024);
        assert!(e.contains("not a regular file (a directory)"), "{e}");
    }

    #[test]
    fn non_utf8_text_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.toml");
        std::fs::write(&p, [0xff, 0xfe]).unwrap();
        let e = read_metadata_string(&p, 16, KIND).unwrap_err().to_string();
        assert!(e.contains("c.toml") && e.contains("not UTF-8"), "{e}");
    }

    #[test]
    fn a_missing_file_is_an_io_error_naming_it() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("absent.json");
        let e = read_metadata(&p, 16, KIND).unwrap_err();
        assert!(
            matches!(&e, Error::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound)
        );
        assert!(e.to_string().contains("absent.json"), "{e}");
    }

    #[cfg(unix)]
    #[test]
    fn a_link_to_dev_zero_is_refused_without_reading() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bundle.json");
        std::os::unix::fs::symlink("/dev/zero", &p).unwrap();
        let e = err(&p, MAX_JSON_METADATA_BYTES);
        assert!(
            e.contains("bundle.json") && e.contains("not a regular file (a character device)"),
            "{e}"
        );
    }

    #[cfg(unix)]
    #[test]
    fn a_fifo_is_refused_without_opening_it() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("manifest.json");
        match std::process::Command::new("mkfifo").arg(&p).status() {
            Ok(s) if s.success() => {}
            other => {
                eprintln!("skipped: mkfifo is unavailable ({other:?})");
                return;
            }
        }
        // opening it would block until a writer came: the check comes first
        let e = err(&p, MAX_JSON_METADATA_BYTES);
        assert!(
            e.contains("manifest.json") && e.contains("not a regular file (a FIFO)"),
            "{e}"
        );
        // a link to it too
        let link = dir.path().join("link.json");
        std::os::unix::fs::symlink(&p, &link).unwrap();
        assert!(err(&link, 16).contains("(a FIFO)"));
    }

    #[test]
    fn a_file_that_grows_past_the_cap_while_read_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("grows.json");
        std::fs::write(&p, b"1234").unwrap();
        let (file, len) = open_capped(&p, 4, KIND).unwrap();
        assert_eq!(len, 4);
        std::fs::write(&p, b"123456").unwrap();
        let mut got = Vec::new();
        file.take(5).read_to_end(&mut got).unwrap();
        let e = check_len(&p, got.len() as u64, 4, KIND)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("grows.json") && e.contains("5 bytes, more than the cap of 4"),
            "{e}"
        );
    }
}
