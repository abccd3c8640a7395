//! `dataset.json`, the record of the job a generated dataset's folder belongs to: the bundle (its
//! manifest's SHA-256), the sampler settings, the base seed and the rule that gives each frame its
//! seed, the source kind, the labeller, and every frame's name. Written once, by whichever worker
//! comes first; every later worker and every resume compares its own job with it byte for byte,
//! and a folder of another job is refused with the fields that differ.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use veila_data::atomic::{HIDDEN_PREFIX, write_atomic_new};
use veila_data::read_capped::read_metadata;

use super::source::{MAX_FRAMES, MAX_NAME_BYTES};
use crate::error::{Error, Result};
use crate::sampler::SamplerConfig;

/// The manifest's file name in the output folder.
pub const DATASET_MANIFEST: &str = "dataset.json";

/// The `format` field of every manifest.
pub const DATASET_FORMAT: &str = "veila-generated-dataset/1";

/// Sub-folder of the scans.
pub const SCANS_DIR: &str = "velodyne";

/// Sub-folder of the point labels, when a labeller is given.
pub const LABELS_DIR: &str = "labels";

/// The rule of [`frame_seed`], in words, as the manifest records it.
pub const SEED_RULE: &str = "frame seed = first 8 bytes (big-endian) of SHA-256 of \
                             \"veila-frame-seed/1\\n{seed}\\n{name}\"";

/// The largest `dataset.json` read back: every frame name at its longest, and the rest.
const MAX_MANIFEST_BYTES: u64 = (MAX_FRAMES * (MAX_NAME_BYTES + 16)) as u64 + (1 << 20);

/// The noise seed of frame `name` in a job of base seed `seed` ([`SEED_RULE`]): a function of
/// these two alone, so a frame's scan does not depend on the order frames are generated in, on
/// how many workers share the job, or on a resume.
pub fn frame_seed(seed: u64, name: &str) -> u64 {
    let hex =
        veila_data::shard::sha256_hex(format!("veila-frame-seed/1\n{seed}\n{name}").as_bytes());
    u64::from_str_radix(&hex[..16], 16).expect("sha256_hex gives hex digits")
}

/// The bundle a dataset is generated with.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BundleId {
    /// Its `name`.
    pub name: String,
    /// SHA-256 of its `manifest.json`.
    pub manifest_sha256: String,
}

/// The job of a generated dataset (`dataset.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetManifest {
    /// [`DATASET_FORMAT`].
    pub format: String,
    /// The model.
    pub bundle: BundleId,
    /// The sampler settings.
    pub sampler: SamplerConfig,
    /// Residual bundles: the weight of the sampled residual.
    pub residual_weight: f64,
    /// The base seed.
    pub seed: u64,
    /// How each frame's seed follows from the base seed and its name ([`SEED_RULE`]).
    pub seed_rule: String,
    /// `kitti-layout` or `shards`.
    pub source: String,
    /// The pseudo-labeller's identity, when the scans are labelled (`labels/NAME.label`).
    pub labeller: Option<String>,
    /// Every frame's name, in the source's order.
    pub frames: Vec<String>,
}

impl DatasetManifest {
    /// The file's bytes (pretty JSON, a final newline): the same job gives the same bytes.
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        let mut b = serde_json::to_vec_pretty(self).map_err(|source| Error::Json {
            path: PathBuf::from(DATASET_MANIFEST),
            source,
        })?;
        b.push(b'\n');
        Ok(b)
    }

    /// Reads `dataset.json` (a regular file within its cap, checked before it is read).
    pub fn read(path: &Path) -> Result<Self> {
        let bytes = read_metadata(path, MAX_MANIFEST_BYTES, "a generated dataset's manifest")?;
        serde_json::from_slice(&bytes).map_err(|e| Error::Output {
            path: path.to_path_buf(),
            reason: format!(
                "not the manifest of a dataset `veila generate --frames` made ({e}); choose \
                 another --out (nothing was changed)"
            ),
        })
    }

    /// What differs between the job `self` describes and `other`'s, in words: each differing
    /// field by its path (`sampler.steps: this run 3, the folder's 2`), the frames by their count
    /// and the first that differs.
    fn differences(&self, other: &Self) -> Vec<String> {
        let mut d = Vec::new();
        let (mine, theirs) = (serde_json::to_value(self), serde_json::to_value(other));
        if let (Ok(serde_json::Value::Object(mine)), Ok(serde_json::Value::Object(theirs))) =
            (mine, theirs)
        {
            for (key, a) in mine.iter().filter(|(k, _)| *k != "frames") {
                let b = theirs.get(key).unwrap_or(&serde_json::Value::Null);
                json_differences(key, a, b, &mut d);
            }
        }
        if self.frames != other.frames {
            let first = self
                .frames
                .iter()
                .zip(&other.frames)
                .position(|(a, b)| a != b)
                .unwrap_or(self.frames.len().min(other.frames.len()));
            let at = |f: &[String]| {
                f.get(first)
                    .map_or("none".to_string(), |n| format!("`{n}`"))
            };
            d.push(format!(
                "frames: this run {}, the folder's {} (frame {first}: this run {}, the folder's {})",
                self.frames.len(),
                other.frames.len(),
                at(&self.frames),
                at(&other.frames)
            ));
        }
        d
    }
}

/// The leaves where `a` (this run's) and `b` (the folder's) differ, by their dotted path.
fn json_differences(
    path: &str,
    a: &serde_json::Value,
    b: &serde_json::Value,
    out: &mut Vec<String>,
) {
    use serde_json::Value;
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            let keys: std::collections::BTreeSet<&String> = x.keys().chain(y.keys()).collect();
            for k in keys {
                let (p, q) = (x.get(k), y.get(k));
                json_differences(
                    &format!("{path}.{k}"),
                    p.unwrap_or(&Value::Null),
                    q.unwrap_or(&Value::Null),
                    out,
                );
            }
        }
        _ if a != b => out.push(format!("{path}: this run {a}, the folder's {b}")),
        _ => {}
    }
}

/// Claims the folder `out` for the job `manifest` describes: creates it, refuses it when it holds
/// anything but this layout's entries, and writes `dataset.json` unless it is there; when it is,
/// it must be this job's, byte for byte. Nothing is changed in a refused folder.
pub(crate) fn claim(out: &Path, manifest: &DatasetManifest) -> Result<()> {
    std::fs::create_dir_all(out).map_err(|source| Error::Io {
        action: "creating the output folder",
        path: out.to_path_buf(),
        source,
    })?;
    check_own_folder(out)?;
    let bytes = manifest.to_bytes()?;
    let path = out.join(DATASET_MANIFEST);
    if !path.exists() {
        for sub in [SCANS_DIR, LABELS_DIR] {
            if has_visible_entries(&out.join(sub))? {
                return Err(Error::Output {
                    path: out.join(sub),
                    reason: format!(
                        "holds files but the folder has no {DATASET_MANIFEST}: not a dataset \
                         this command made; choose another --out (nothing was changed)"
                    ),
                });
            }
        }
        // of workers starting together, one writes it; the others compare with it below
        if write_atomic_new(&path, &bytes)? {
            return Ok(());
        }
    }
    let theirs = read_metadata(&path, MAX_MANIFEST_BYTES, "a generated dataset's manifest")?;
    if theirs == bytes {
        return Ok(());
    }
    let other = DatasetManifest::read(&path)?;
    let mut diffs = manifest.differences(&other);
    if diffs.is_empty() {
        diffs.push("the file's bytes (edited by hand?)".into());
    }
    Err(Error::Output {
        path,
        reason: format!(
            "this folder holds a dataset of another job ({}); run with that job's model, sampler \
             flags, --seed and frames to resume it, or choose another --out (nothing was changed)",
            diffs.join("; ")
        ),
    })
}

/// Refuses a folder holding anything but `dataset.json`, the scan and label folders, and the
/// hidden leftovers of atomic writes.
fn check_own_folder(out: &Path) -> Result<()> {
    let mut names: Vec<String> = read_dir_names(out)?;
    names.sort();
    let ours = |n: &str| {
        n == DATASET_MANIFEST || n == SCANS_DIR || n == LABELS_DIR || n.starts_with(HIDDEN_PREFIX)
    };
    if let Some(n) = names.iter().find(|n| !ours(n)) {
        return Err(Error::Output {
            path: out.join(n),
            reason: "is not part of a generated dataset, and `veila generate --frames` writes \
                     only into an empty folder or its own earlier output; choose another --out \
                     (nothing was changed)"
                .into(),
        });
    }
    Ok(())
}

fn read_dir_names(dir: &Path) -> Result<Vec<String>> {
    let rd = std::fs::read_dir(dir).map_err(|source| Error::Io {
        action: "listing the output folder",
        path: dir.to_path_buf(),
        source,
    })?;
    Ok(rd
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect())
}

/// Whether `dir` exists and holds a name that is not a hidden leftover.
fn has_visible_entries(dir: &Path) -> Result<bool> {
    if !dir.exists() {
        return Ok(false);
    }
    Ok(read_dir_names(dir)?
        .iter()
        .any(|n| !n.starts_with(HIDDEN_PREFIX)))
}
