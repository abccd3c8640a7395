//! Scoring point labels as the SemanticKITTI API does (`veila segment eval`): every `NAME.label`
//! of a ground-truth folder against `NAME.label` of a prediction folder, both raw ids mapped to
//! train ids by one label map, one confusion matrix over every point of every scan
//! ([`veila_metrics::segmentation::IouEval`]): per-class IoU, mIoU over the classes not ignored,
//! and the mean over those present in the ground truth.
//!
//! Errors name the file: a ground truth without its prediction, a prediction with another number
//! of points, a raw id the label map does not list (a file written under another label map).

use std::path::Path;

use serde::{Deserialize, Serialize};
use veila_data::kitti::list_stems;
use veila_data::semantic_kitti::read_labels;
use veila_metrics::segmentation::{IouEval, SegmentationScores};

use super::labels::LabelSpace;
use crate::error::{Error, Result};

/// The scores of a prediction folder.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FolderScores {
    /// The scores (IoU per train id, mIoU, the mean over present classes, accuracy).
    pub scores: SegmentationScores,
    /// The name of each train id.
    pub class_names: Vec<String>,
    /// Scans scored.
    pub scans: usize,
    /// Where the label map came from.
    pub label_map: String,
}

/// The first raw label of `labels` the map does not list, as an error naming `path`.
fn check_listed(labels: &[u32], space: &LabelSpace, path: &Path, what: &str) -> Result<()> {
    if let Some(i) = labels.iter().position(|&r| !space.is_listed(r)) {
        return Err(Error::Input {
            path: path.to_path_buf(),
            reason: format!(
                "mismatched label maps: point {i} of this {what} has raw id {}, which {} does not list (pass the label map it was written with as --label-map)",
                labels[i] & 0xFFFF,
                space.source()
            ),
        });
    }
    Ok(())
}

/// Scores the `NAME.label` files of `predictions` against those of `labels` (module docs);
/// `on_scan` is called after each scan with its name.
pub fn evaluate_label_dirs(
    predictions: &Path,
    labels: &Path,
    space: &LabelSpace,
    mut on_scan: impl FnMut(&str),
) -> Result<FolderScores> {
    let names = list_stems(labels, ".label")?;
    if names.is_empty() {
        return Err(Error::Input {
            path: labels.to_path_buf(),
            reason: "no `.label` file to score against".into(),
        });
    }
    let mut eval = IouEval::new(space.num_classes(), &space.ignored())?;
    for name in &names {
        let truth_path = labels.join(format!("{name}.label"));
        let pred_path = predictions.join(format!("{name}.label"));
        if !pred_path.exists() {
            return Err(Error::Input {
                path: pred_path,
                reason: format!(
                    "missing: the ground truth {} has no prediction",
                    truth_path.display()
                ),
            });
        }
        let truth = read_labels(&truth_path, None)?;
        let pred = read_labels(&pred_path, None)?;
        if pred.len() != truth.len() {
            return Err(Error::Input {
                path: pred_path,
                reason: format!(
                    "{} labels, but the ground truth {} has {} (a prediction of another scan?)",
                    pred.len(),
                    truth_path.display(),
                    truth.len()
                ),
            });
        }
        check_listed(&truth, space, &truth_path, "ground truth")?;
        check_listed(&pred, space, &pred_path, "prediction")?;
        let p: Vec<u32> = pred.iter().map(|&r| space.train_id(r)).collect();
        let t: Vec<u32> = truth.iter().map(|&r| space.train_id(r)).collect();
        eval.add(&p, &t)?;
        on_scan(name);
    }
    Ok(FolderScores {
        scores: eval.scores(),
        class_names: space.classes().into_iter().map(|c| c.name).collect(),
        scans: names.len(),
        label_map: space.source().to_string(),
    })
}
