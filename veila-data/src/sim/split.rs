//! Scene lists: which scene files and seeds make up a split (`scenes/train.txt`, `scenes/test.txt`).
//!
//! One entry per line, `SCENE_FILE FIRST_SEED LAST_SEED` (seeds inclusive, the file relative to the
//! list); `#` starts a comment.

use std::ops::RangeInclusive;
use std::path::{Path, PathBuf};

use crate::{Error, Result};

/// One line of a scene list.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SceneListEntry {
    /// The scene file (resolved relative to the list's folder).
    pub scene: PathBuf,
    /// The seeds to render it with.
    pub seeds: RangeInclusive<u64>,
}

/// A split: scene files with seed ranges.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct SceneList {
    /// The entries in file order.
    pub entries: Vec<SceneListEntry>,
}

impl SceneList {
    /// Parse list text; `path` names the list in errors and anchors relative scene paths.
    pub fn parse(text: &str, path: &Path) -> Result<Self> {
        let base = path.parent().unwrap_or(Path::new(""));
        let mut entries = Vec::new();
        for (i, raw) in text.lines().enumerate() {
            let line = raw.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let fields: Vec<&str> = line.split_whitespace().collect();
            let [file, first, last] = fields[..] else {
                return Err(Error::format(
                    path,
                    format!(
                        "line {}: expected `SCENE_FILE FIRST_SEED LAST_SEED`, got `{line}`",
                        i + 1
                    ),
                ));
            };
            let seed = |s: &str| {
                s.parse::<u64>().map_err(|_| {
                    Error::format(
                        path,
                        format!(
                            "line {}: `{s}` is not a seed (a non-negative integer)",
                            i + 1
                        ),
                    )
                })
            };
            let (a, b) = (seed(first)?, seed(last)?);
            if a > b {
                return Err(Error::format(
                    path,
                    format!(
                        "line {}: first seed {a} is greater than last seed {b}",
                        i + 1
                    ),
                ));
            }
            entries.push(SceneListEntry {
                scene: base.join(file),
                seeds: a..=b,
            });
        }
        Ok(SceneList { entries })
    }

    /// Read a list file.
    pub fn read(path: &Path) -> Result<Self> {
        let text = crate::read_capped::read_metadata_string(
            path,
            crate::read_capped::MAX_CONFIG_BYTES,
            "a scene list",
        )?;
        Self::parse(&text, path)
    }

    /// Total number of (scene, seed) pairs.
    pub fn len(&self) -> u64 {
        self.entries
            .iter()
            .map(|e| e.seeds.end() - e.seeds.start() + 1)
            .sum()
    }

    /// True when the list has no entry.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Every (scene file, seed) pair, in order.
    pub fn iter(&self) -> impl Iterator<Item = (&Path, u64)> + '_ {
        self.entries
            .iter()
            .flat_map(|e| e.seeds.clone().map(move |s| (e.scene.as_path(), s)))
    }
}
