//! The label space of a segmenter: the raw ids of `.label` files (SemanticKITTI's, the lower 16
//! bits) and the train ids a network predicts, through SemanticKITTI's built-in learning map
//! (`veila_data::semantic_kitti::class`) or a label-map file (`semantic-kitti.yaml`, read by
//! `veila_data::semantic_kitti::LabelMap`).
//!
//! A trained segmenter records its classes ([`SegClass`]: train id, the raw id written back for
//! it, name), so its predictions are written in the raw ids of the label map it was trained with,
//! and a label map given later is checked against them ([`check_classes`]).

use std::path::Path;

use serde::{Deserialize, Serialize};
use veila_data::semantic_kitti::{LabelMap, class};

use crate::error::{Error, Result};

/// What [`LabelSpace::source`] says of the built-in map.
pub const BUILT_IN: &str = "the built-in SemanticKITTI learning map";

/// The most train ids a label space may have (a segmenter's `veila_nn::segmenter::MAX_CLASSES`
/// and the learning maps' `u8` train ids both allow fewer).
pub const MAX_TRAIN_IDS: usize = 256;

/// One class of a segmenter.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SegClass {
    /// The network's output index.
    pub train_id: u32,
    /// The raw id `veila segment predict` writes for it (`learning_map_inv`).
    pub raw_id: u32,
    /// Its name.
    pub name: String,
}

/// Raw ids to train ids and back.
#[derive(Debug, Clone)]
pub struct LabelSpace {
    map: Option<LabelMap>,
    source: String,
}

impl LabelSpace {
    /// SemanticKITTI's learning map, built in (20 train ids, 0 ignored).
    pub fn semantic_kitti() -> Self {
        LabelSpace {
            map: None,
            source: BUILT_IN.into(),
        }
    }

    /// The label map file at `path` (`semantic-kitti.yaml`'s layout): it must give every train id
    /// from 0 to its largest a raw id to write back (`learning_map_inv`); errors name the file.
    pub fn read(path: &Path) -> Result<Self> {
        let map = LabelMap::read(path)?;
        let n = map.num_classes();
        let bad = |reason: String| Error::Input {
            path: path.to_path_buf(),
            reason,
        };
        if !(2..=MAX_TRAIN_IDS).contains(&n) {
            return Err(bad(format!(
                "the label map has {n} train ids; a segmenter needs 2 to {MAX_TRAIN_IDS}"
            )));
        }
        if let Some(t) = (0..n).find(|t| !map.learning_map_inv.contains_key(&(*t as u8))) {
            return Err(bad(format!(
                "learning_map_inv has no raw id for train id {t} (it must name one for every train id 0..{n})"
            )));
        }
        Ok(LabelSpace {
            map: Some(map),
            source: path.display().to_string(),
        })
    }

    /// [`LabelSpace::read`] of `path` when given, else [`LabelSpace::semantic_kitti`].
    pub fn read_or_built_in(path: Option<&Path>) -> Result<Self> {
        path.map_or_else(|| Ok(Self::semantic_kitti()), Self::read)
    }

    /// Where the map comes from (a file's path, or [`BUILT_IN`]).
    pub fn source(&self) -> &str {
        &self.source
    }

    /// The number of train ids (0 included).
    pub fn num_classes(&self) -> usize {
        self.map
            .as_ref()
            .map_or(class::NUM_LEARNING_CLASSES, |m| m.num_classes())
    }

    /// The train id of a raw label (its instance bits dropped; unlisted ids give 0).
    pub fn train_id(&self, raw: u32) -> u32 {
        match &self.map {
            Some(m) => u32::from(m.train_id(raw)),
            None => u32::from(class::learning_id((raw & 0xFFFF) as u16)),
        }
    }

    /// Whether the map lists the raw label's class (its lower 16 bits).
    pub fn is_listed(&self, raw: u32) -> bool {
        let id = (raw & 0xFFFF) as u16;
        match &self.map {
            Some(m) => m.learning_map.contains_key(&id),
            None => class::in_learning_map(id),
        }
    }

    /// The train ids left out of training and scoring: those `learning_ignore` marks (class 0
    /// when the map marks none, and for the built-in map).
    pub fn ignored(&self) -> Vec<usize> {
        let marked: Vec<usize> = self
            .map
            .iter()
            .flat_map(|m| m.learning_ignore.iter())
            .filter(|&(t, ignore)| *ignore && (*t as usize) < self.num_classes())
            .map(|(t, _)| *t as usize)
            .collect();
        if marked.is_empty() { vec![0] } else { marked }
    }

    /// Every train id with the raw id written back for it and its name.
    pub fn classes(&self) -> Vec<SegClass> {
        (0..self.num_classes())
            .map(|t| {
                let (raw_id, name) = match &self.map {
                    Some(m) => {
                        let raw = m.learning_map_inv.get(&(t as u8)).copied().unwrap_or(0);
                        let name = m.names.get(&raw).cloned().unwrap_or_else(|| format!("{t}"));
                        (u32::from(raw), name)
                    }
                    None => (
                        u32::from(class::LEARNING_MAP_INV[t]),
                        class::LEARNING_NAMES[t].to_string(),
                    ),
                };
                SegClass {
                    train_id: t as u32,
                    raw_id,
                    name,
                }
            })
            .collect()
    }
}

/// Checks that a model's `classes` (recorded in `model`) are those of `labels`: as many train ids,
/// each written back as the same raw id. The error names both sides and says what differs.
pub fn check_classes(classes: &[SegClass], labels: &LabelSpace, model: &Path) -> Result<()> {
    let theirs = labels.classes();
    let mismatch = |what: String| Error::Input {
        path: model.to_path_buf(),
        reason: format!(
            "mismatched label maps: {what} ({} against the model's classes)",
            labels.source()
        ),
    };
    if theirs.len() != classes.len() {
        return Err(mismatch(format!(
            "the model predicts {} train ids, the label map has {}",
            classes.len(),
            theirs.len()
        )));
    }
    if let Some((m, l)) = classes
        .iter()
        .zip(&theirs)
        .find(|(m, l)| m.raw_id != l.raw_id)
    {
        return Err(mismatch(format!(
            "train id {} is raw id {} ({}) for the model, {} ({}) for the label map",
            m.train_id, m.raw_id, m.name, l.raw_id, l.name
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_built_in_space_round_trips_every_train_id() {
        let s = LabelSpace::semantic_kitti();
        assert_eq!(s.num_classes(), 20);
        assert_eq!(s.ignored(), vec![0]);
        for c in s.classes() {
            assert_eq!(s.train_id(c.raw_id), c.train_id);
            assert!(s.is_listed(c.raw_id | (7 << 16)));
        }
        assert!(!s.is_listed(7));
        assert_eq!(s.classes()[1].name, "car");
    }

    #[test]
    fn a_label_map_with_other_classes_is_a_mismatch_naming_both() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("mine.yaml");
        std::fs::write(
            &p,
            "labels:\n  0: unlabeled\n  10: car\n  40: road\ncolor_map:\n  0: [0, 0, 0]\n  10: [1, 2, 3]\n  40: [4, 5, 6]\nlearning_map:\n  0: 0\n  10: 1\n  40: 2\nlearning_map_inv:\n  0: 0\n  1: 10\n  2: 40\nlearning_ignore:\n  0: True\n  1: False\n  2: False\n",
        )
        .unwrap();
        let mine = LabelSpace::read(&p).unwrap();
        assert_eq!(mine.num_classes(), 3);
        assert_eq!(mine.train_id(40), 2);
        let model = Path::new("models/segmenter/segmenter.json");
        let e = check_classes(&LabelSpace::semantic_kitti().classes(), &mine, model)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("mismatched label maps")
                && e.contains("mine.yaml")
                && e.contains("segmenter.json")
                && e.contains("20 train ids")
                && e.contains("has 3"),
            "{e}"
        );
        check_classes(&mine.classes(), &mine, model).unwrap();
        // a map whose inverse leaves a train id out is refused naming the file
        let holes = std::fs::read_to_string(&p)
            .unwrap()
            .replace("  1: 10\n", "");
        std::fs::write(&p, holes).unwrap();
        let e = LabelSpace::read(&p).unwrap_err().to_string();
        assert!(e.contains("mine.yaml"), "{e}");
    }
}
