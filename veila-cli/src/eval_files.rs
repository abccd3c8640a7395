//! Which files of a folder `veila eval` reads: scans (.bin, .pcd.bin, .ply, .exr) and peer
//! sample sets (.npy, .npz), each scan once although `veila generate` writes it in three formats.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

fn is_scan_file(path: &Path) -> bool {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    name.ends_with(".bin") || name.ends_with(".ply") || name.ends_with(".exr")
}

/// Scan and sample files of a folder, sorted by name. A pickle in the folder is an error naming it.
pub(crate) fn list_scans(dir: &Path, what: &str) -> Result<Vec<PathBuf>> {
    let entries = std::fs::read_dir(dir)
        .with_context(|| format!("{what} folder {}: cannot read", dir.display()))?;
    let mut files = Vec::new();
    for e in entries {
        let e = e.with_context(|| format!("{what} folder {}: cannot list", dir.display()))?;
        let p = e.path();
        if !p.is_file() {
            continue;
        }
        veila_data::peer_samples::refuse_pickle(&p)?;
        if is_scan_file(&p) || veila_data::peer_samples::is_sample_file(&p) {
            files.push(p);
        }
    }
    files.sort();
    let files = one_file_per_scan(files, dir);
    if files.is_empty() {
        bail!(
            "{what} folder {} has no scans (.bin, .pcd.bin, .ply, .exr) or sample sets (.npy, .npz)",
            dir.display()
        );
    }
    Ok(files)
}

/// The formats of one scan, most direct first: `generate` writes each scan as `.bin` (its points),
/// `.ply` (the same points) and `.exr` (its range image).
const SCAN_FORMATS: [&str; 3] = ["bin", "ply", "exr"];

/// `files` (sorted) with one file per scan: of `scan_000.bin`, `scan_000.ply` and `scan_000.exr`
/// only the `.bin` (counting each scan three times would weigh its points thrice). Says so on
/// stderr when it leaves files out.
fn one_file_per_scan(files: Vec<PathBuf>, dir: &Path) -> Vec<PathBuf> {
    let rank = |p: &Path| {
        let ext = p.extension().map(|e| e.to_string_lossy().to_lowercase());
        SCAN_FORMATS.iter().position(|f| ext.as_deref() == Some(*f))
    };
    let given = files.len();
    let mut best: std::collections::BTreeMap<PathBuf, (usize, PathBuf)> = Default::default();
    let mut out = Vec::new();
    for f in files {
        match rank(&f) {
            Some(r) => {
                let e = best.entry(f.with_extension("")).or_insert((r, f.clone()));
                if r < e.0 {
                    *e = (r, f);
                }
            }
            None => out.push(f),
        }
    }
    out.extend(best.into_values().map(|(_, f)| f));
    out.sort();
    if out.len() < given {
        eprintln!(
            "note: {}: {} files are other formats of the same scans (.bin, .ply, .exr of one \
             name): each scan is read once, from its .bin (else .ply)",
            dir.display(),
            given - out.len()
        );
    }
    out
}
