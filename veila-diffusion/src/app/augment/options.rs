//! The benchmark's options and the job its work folder records.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use super::data::LABELLED_LIST_SEED;
use crate::app::bundle::Bundle;
use crate::app::segment::{ClassWeighting, SegTrainSettings};
use crate::error::{Result, invalid};
use crate::sampler::SamplerConfig;

/// The options of one run (`cargo xtask bench-augment`'s flags). Paths are relative to `root`
/// (or absolute).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AugmentOptions {
    /// The workspace: the scene lists are found in it.
    pub root: PathBuf,
    /// The conditional bundle that generates.
    pub model: PathBuf,
    /// The first frames of the bundle's training list: the ones it trained on, skipped by the
    /// split, and the retrieval database.
    pub pool_frames: usize,
    /// Frames of the split (after the pool).
    pub split_frames: usize,
    /// Held-out frames of the test list.
    pub test_frames: usize,
    /// Labelled fractions of the split.
    pub fractions: Vec<f64>,
    /// Training seeds (every row at every one).
    pub seeds: Vec<u64>,
    /// Each run's training (its `seed` is replaced by each training seed).
    pub train: SegTrainSettings,
    /// How each run weighs the classes of its training frames.
    pub class_weighting: ClassWeighting,
    /// The sampler of the generated scans (none: the bundle's).
    pub sampler: Option<SamplerConfig>,
    /// The work folder (scans, checkpoints, results).
    pub work: PathBuf,
    /// The report's folder.
    pub out: PathBuf,
    /// The command line the report states.
    pub command: String,
}

impl AugmentOptions {
    /// The job as the work folder records it: what its results depend on.
    pub(super) fn job(&self, bundle: &Bundle, sampler: &SamplerConfig) -> serde_json::Value {
        serde_json::json!({
            "format": "veila-bench-augment/1",
            "bundle_manifest_sha256": bundle.manifest_sha256,
            "sampler": sampler,
            "pool_frames": self.pool_frames,
            "split_frames": self.split_frames,
            "test_frames": self.test_frames,
            "train": SegTrainSettings { seed: 0, ..self.train.clone() },
            "class_weighting": self.class_weighting,
            "labelled_list_seed": LABELLED_LIST_SEED,
        })
    }

    pub(super) fn check(&self) -> Result<()> {
        if self.split_frames < 2 || self.test_frames == 0 {
            return Err(invalid(
                "split_frames",
                "the split needs 2 frames or more and the test set 1 or more",
            ));
        }
        if self.fractions.is_empty() || self.seeds.is_empty() {
            return Err(invalid("fractions", "no fraction or no seed"));
        }
        if let Some(f) = self.fractions.iter().find(|f| !(**f > 0.0 && **f < 1.0)) {
            return Err(invalid(
                "fractions",
                format!("{f} is not a fraction strictly between 0 and 1"),
            ));
        }
        self.train.validate()
    }
}

/// `fraction` in percent, as the names and the report write it.
pub fn pct(fraction: f64) -> String {
    let p = fraction * 100.0;
    if (p - p.round()).abs() < 1e-9 {
        format!("{}", p.round())
    } else {
        format!("{p}")
    }
}
