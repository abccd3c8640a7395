//! `veila segment`: LiDAR semantic segmentation with the range-view segmenter
//! (`veila_diffusion::app::segment`): `train` a segmenter from a TOML config, `predict` point
//! labels of KITTI scans (`NAME.bin` in, SemanticKITTI `NAME.label` out), `eval` a folder of
//! predictions against ground truth as the SemanticKITTI API does. This module holds the
//! arguments, progress and output; the work is the library's.

mod eval;
mod predict;
mod train;

use anyhow::Result;
use clap::Subcommand;

/// The subcommands of `veila segment`.
#[derive(Debug, Subcommand)]
pub(crate) enum SegmentCmd {
    /// Train a segmenter from a TOML config (simulator frames with their ground truth, or shards
    /// converted with a label map); resumable: rerunning the same config continues from the
    /// newest checkpoint, with the result of an uninterrupted run.
    Train(train::TrainArgs),
    /// Label every point of every `NAME.bin` (KITTI layout) of a folder: `NAME.label`
    /// (SemanticKITTI format, raw ids) in the output folder. Default model: the bundled segmenter.
    Predict(predict::PredictArgs),
    /// Score a folder of predicted `.label` files against a folder of ground truth, as the
    /// SemanticKITTI API does: per-class IoU, mIoU, the mean over the classes present, accuracy.
    Eval(eval::EvalArgs),
}

pub(crate) fn run(cmd: SegmentCmd) -> Result<()> {
    match cmd {
        SegmentCmd::Train(a) => train::run(a),
        SegmentCmd::Predict(a) => predict::run(a),
        SegmentCmd::Eval(a) => eval::run(a),
    }
}
