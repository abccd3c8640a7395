//! Semantic segmentation scores as the SemanticKITTI benchmark computes them.
//!
//! Protocol of the official evaluator (PRBonn/semantic-kitti-api, `evaluate_semantics.py` with
//! `auxiliary/np_ioueval.py`'s `iouEval`):
//!
//! * raw labels (the lower 16 bits of a `.label` entry) are mapped to train ids by the
//!   `learning_map` of `semantic-kitti.yaml` (28 raw classes to 0-19), here a [`LearningMap`];
//! * one confusion matrix over every point of every scan, rows the prediction, columns the ground
//!   truth ([`IouEval::add`]);
//! * the columns of the ignored classes (class 0, "unlabeled") are zeroed before scoring, so a point
//!   whose ground truth is ignored never counts, while an ignored class predicted on a labelled point
//!   is a false negative of its true class;
//! * per class `IoU = TP / (TP + FP + FN + 1e-15)` (TP the diagonal, FP the rest of the row, FN the
//!   rest of the column), so a class absent from the ground truth and never predicted scores 0;
//! * mIoU is the mean over every class that is not ignored (19 on SemanticKITTI), and the accuracy
//!   is `sum TP / (sum over included classes of TP + FP + 1e-15)`.
//!
//! Beside the official mean, [`SegmentationScores::miou_present`] averages only the included
//! classes that occur in the ground truth: on a simulator with fewer classes, report both.
//!
//! This crate reads no files: the caller turns `semantic-kitti.yaml` into pairs (with
//! `veila_data`'s label map) and the `.label` files into raw ids.
//!
//! ```
//! use veila_metrics::segmentation::IouEval;
//!
//! let mut eval = IouEval::new(3, &[0])?;
//! // prediction, ground truth; the point with ground truth 0 does not count
//! eval.add(&[1, 1, 2, 0, 2], &[1, 2, 2, 2, 0])?;
//! let s = eval.scores();
//! assert!((s.iou[1] - 0.5).abs() < 1e-12); // TP 1, FP 1 (a 2 predicted as 1)
//! assert!((s.iou[2] - 1.0 / 3.0).abs() < 1e-12); // TP 1, FN 2 (one predicted 1, one predicted 0)
//! assert!((s.miou - (0.5 + 1.0 / 3.0) / 2.0).abs() < 1e-12);
//! # Ok::<(), veila_metrics::Error>(())
//! ```

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// Largest number of classes of an [`IouEval`] (its confusion matrix holds the square).
pub const MAX_CLASSES: usize = 4096;
/// SemanticKITTI's train ids, 0 ("unlabeled") included.
pub const SEMANTIC_KITTI_CLASSES: usize = 20;
/// The `1e-15` the official evaluator adds to every denominator.
pub const EPS: f64 = 1e-15;

/// A map from raw semantic ids (the lower 16 bits of a label) to train ids.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LearningMap {
    table: Vec<u32>,
    num_classes: usize,
}

impl LearningMap {
    /// The map of `(raw id, train id)` pairs; raw ids that no pair names map to 0. Fails when a raw
    /// id exceeds 16 bits, a raw id is named twice with two train ids, or a train id is not below
    /// `num_classes` (itself in `1..=MAX_CLASSES`).
    pub fn from_pairs(
        pairs: impl IntoIterator<Item = (u32, u32)>,
        num_classes: usize,
    ) -> Result<Self> {
        check_classes(num_classes)?;
        let mut table = vec![0u32; 1 << 16];
        let mut set = vec![false; 1 << 16];
        for (raw, train) in pairs {
            let bad = |reason: String| Error::InvalidParameter {
                name: "learning map",
                reason,
            };
            if raw > u32::from(u16::MAX) {
                return Err(bad(format!("raw id {raw} exceeds 16 bits")));
            }
            if train as usize >= num_classes {
                return Err(bad(format!(
                    "raw id {raw} maps to {train}, not below {num_classes} classes"
                )));
            }
            let r = raw as usize;
            if set[r] && table[r] != train {
                return Err(bad(format!(
                    "raw id {raw} maps to both {} and {train}",
                    table[r]
                )));
            }
            table[r] = train;
            set[r] = true;
        }
        Ok(Self { table, num_classes })
    }

    /// The train id of a raw label (its lower 16 bits; the instance bits are dropped).
    pub fn train_id(&self, raw_label: u32) -> u32 {
        self.table[(raw_label & 0xFFFF) as usize]
    }

    /// The number of train ids.
    pub fn num_classes(&self) -> usize {
        self.num_classes
    }
}

fn check_classes(n: usize) -> Result<()> {
    if n == 0 || n > MAX_CLASSES {
        return Err(Error::InvalidParameter {
            name: "num_classes",
            reason: format!("{n} is not in 1..={MAX_CLASSES}"),
        });
    }
    Ok(())
}

/// The official evaluator's confusion matrix (see the module docs).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IouEval {
    n: usize,
    ignore: Vec<usize>,
    /// Row-major `n x n`: `conf[pred * n + truth]`.
    conf: Vec<u64>,
}

impl IouEval {
    /// An empty matrix over `num_classes` classes (in `1..=MAX_CLASSES`) with the `ignore`d ones
    /// (each below `num_classes`).
    pub fn new(num_classes: usize, ignore: &[usize]) -> Result<Self> {
        check_classes(num_classes)?;
        if let Some(&c) = ignore.iter().find(|&&c| c >= num_classes) {
            return Err(Error::InvalidParameter {
                name: "ignore",
                reason: format!("class {c} is not below {num_classes}"),
            });
        }
        let mut ignore = ignore.to_vec();
        ignore.sort_unstable();
        ignore.dedup();
        Ok(Self {
            n: num_classes,
            ignore,
            conf: vec![0; num_classes * num_classes],
        })
    }

    /// SemanticKITTI's: 20 train ids, 0 ignored.
    pub fn semantic_kitti() -> Self {
        Self {
            n: SEMANTIC_KITTI_CLASSES,
            ignore: vec![0],
            conf: vec![0; SEMANTIC_KITTI_CLASSES * SEMANTIC_KITTI_CLASSES],
        }
    }

    /// Number of classes.
    pub fn num_classes(&self) -> usize {
        self.n
    }

    /// Counts one scan: `pred[i]` and `truth[i]` are the train ids of point `i`. Nothing is counted
    /// when the lengths differ or an id is not below the number of classes.
    pub fn add(&mut self, pred: &[u32], truth: &[u32]) -> Result<()> {
        if pred.len() != truth.len() {
            return Err(Error::ShapeMismatch {
                what: "predictions and ground truth".into(),
                expected: format!("{} labels", truth.len()),
                got: format!("{} labels", pred.len()),
            });
        }
        for (what, ids) in [("prediction", pred), ("ground truth", truth)] {
            if let Some(index) = ids.iter().position(|&c| c as usize >= self.n) {
                return Err(Error::LabelSpace {
                    what: what.into(),
                    label: ids[index],
                    index,
                    space: "train",
                    hint: format!("train ids are below {}", self.n),
                });
            }
        }
        for (&p, &t) in pred.iter().zip(truth) {
            self.conf[p as usize * self.n + t as usize] += 1;
        }
        Ok(())
    }

    /// [`IouEval::add`] with the ground truth as raw labels, mapped by `map` (which must have this
    /// matrix's number of classes).
    pub fn add_raw(&mut self, pred: &[u32], truth_raw: &[u32], map: &LearningMap) -> Result<()> {
        if map.num_classes() != self.n {
            return Err(Error::InvalidParameter {
                name: "learning map",
                reason: format!(
                    "maps to {} classes, the evaluator has {}",
                    map.num_classes(),
                    self.n
                ),
            });
        }
        let truth: Vec<u32> = truth_raw.iter().map(|&r| map.train_id(r)).collect();
        self.add(pred, &truth)
    }

    /// Adds another matrix's counts (same classes and ignored classes).
    pub fn merge(&mut self, other: &IouEval) -> Result<()> {
        if other.n != self.n || other.ignore != self.ignore {
            return Err(Error::ShapeMismatch {
                what: "merged evaluator".into(),
                expected: format!("{} classes, ignoring {:?}", self.n, self.ignore),
                got: format!("{} classes, ignoring {:?}", other.n, other.ignore),
            });
        }
        for (a, b) in self.conf.iter_mut().zip(&other.conf) {
            *a += b;
        }
        Ok(())
    }

    /// The raw counts, row-major `conf[pred * n + truth]` (ignored columns not yet zeroed).
    pub fn confusion(&self) -> &[u64] {
        &self.conf
    }

    /// The scores of everything added so far.
    pub fn scores(&self) -> SegmentationScores {
        let n = self.n;
        let mut conf = self.conf.clone();
        for &c in &self.ignore {
            for row in 0..n {
                conf[row * n + c] = 0;
            }
        }
        let tp: Vec<u64> = (0..n).map(|c| conf[c * n + c]).collect();
        let row: Vec<u64> = (0..n)
            .map(|r| conf[r * n..(r + 1) * n].iter().sum())
            .collect();
        let col: Vec<u64> = (0..n)
            .map(|c| (0..n).map(|r| conf[r * n + c]).sum())
            .collect();
        let included: Vec<usize> = (0..n).filter(|c| !self.ignore.contains(c)).collect();
        let iou: Vec<f64> = (0..n)
            .map(|c| {
                let (fp, fn_) = (row[c] - tp[c], col[c] - tp[c]);
                tp[c] as f64 / ((tp[c] + fp + fn_) as f64 + EPS)
            })
            .collect();
        let mean = |classes: &[usize]| {
            if classes.is_empty() {
                0.0
            } else {
                classes.iter().map(|&c| iou[c]).sum::<f64>() / classes.len() as f64
            }
        };
        let present: Vec<usize> = included.iter().copied().filter(|&c| col[c] > 0).collect();
        let total_tp: u64 = tp.iter().sum();
        let total: u64 = included.iter().map(|&c| row[c]).sum();
        SegmentationScores {
            miou: mean(&included),
            miou_present: mean(&present),
            accuracy: total_tp as f64 / (total as f64 + EPS),
            points: col.iter().sum(),
            iou,
            included,
            present,
        }
    }
}

/// The scores of an [`IouEval`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SegmentationScores {
    /// IoU of every class, ignored ones included (as the official evaluator lists them).
    pub iou: Vec<f64>,
    /// Mean IoU over the included classes (the benchmark's mIoU).
    pub miou: f64,
    /// Mean IoU over the included classes present in the ground truth (0 when none is).
    pub miou_present: f64,
    /// Overall accuracy over the points whose ground truth is not ignored.
    pub accuracy: f64,
    /// Points whose ground truth is not ignored.
    pub points: u64,
    /// The classes not ignored.
    pub included: Vec<usize>,
    /// The included classes that occur in the ground truth.
    pub present: Vec<usize>,
}
