//! LiDAR semantic segmentation with the range-view segmenter of `veila_nn::segmenter`: what
//! `veila segment train`, `predict` and `eval` run.
//!
//! * [`labels`]: raw ids and train ids ([`LabelSpace`]: SemanticKITTI's built-in learning map
//!   or a label-map file), the classes a model records ([`SegClass`]) and their check.
//! * [`model`]: the model folder ([`SegmenterModel`]: `segmenter.json`, `segmenter.safetensors`,
//!   a bundle's sha256 manifest), and prediction: a scan projected on the model's grid, the
//!   network's pixel classes carried to every point by RangeNet++'s kNN clean-up.
//! * [`frames`]: scans on a segmenter's grid ([`GridScan`]), labelled training frames
//!   ([`SegFrame`]) with their augmentation, batches and class weights.
//! * [`config`]: the TOML config of `veila segment train` ([`SegTrainFile`]).
//! * [`train`]: the training loop with exact resume ([`fit_segmenter`]).
//! * [`shards`]: converted shards as training frames; `sim` (feature `sim`): simulator frames
//!   with their ground truth.
//! * [`eval`]: prediction folders scored against ground-truth folders ([`evaluate_label_dirs`]).
//!
//! [`load_training_data`] and [`train_from_file`] are the recipe of `veila segment train`.

pub mod config;
pub mod eval;
pub mod frames;
pub mod labels;
pub mod model;
pub mod shards;
#[cfg(feature = "sim")]
pub mod sim;
pub mod train;

use std::ops::ControlFlow;

use candle_core::Device;
use veila_geom::{ProjectionOptions, Projector};

pub use config::{SegPreset, SegTrainFile};
pub use eval::{FolderScores, evaluate_label_dirs};
pub use frames::{ClassWeighting, GridScan, SegFrame, class_counts, class_weights};
pub use labels::{LabelSpace, SegClass, check_classes};
pub use model::{SegmenterModel, SegmenterModelConfig};
pub use train::{HeldOutScan, SegEvent, SegFitOutcome, SegTrainSettings, fit_segmenter};

use crate::error::{Error, Result};

/// The training data of a config: frames, held-out scans, the label space, and what identifies
/// the data for the checkpoint folder.
#[derive(Debug)]
pub struct SegData {
    /// The training frames.
    pub frames: Vec<SegFrame>,
    /// The held-out scans (simulator frames; empty for shards).
    pub held_out: Vec<HeldOutScan>,
    /// The classes.
    pub labels: LabelSpace,
    /// What identifies the data.
    pub fingerprint: serde_json::Value,
}

/// Reads or simulates the data `file` trains on (frames held in memory); `on_item` is called
/// after each simulated scene or shard sample.
pub fn load_training_data(file: &SegTrainFile, on_item: &(dyn Fn() + Sync)) -> Result<SegData> {
    let d = &file.data;
    let labels = LabelSpace::read_or_built_in(d.label_map.as_deref())?;
    let model = file.model_config(&labels)?;
    let projector = Projector::new(&model.sensor, ProjectionOptions::default())?;
    let net = &model.network;
    if let Some(dir) = &d.shards {
        let (frames, manifest) = shards::shard_frames(
            dir,
            d.max_frames,
            &labels,
            d.label_map.is_some(),
            &projector,
            net,
            on_item,
        )?;
        let manifest_bytes = veila_data::read_capped::read_metadata(
            &dir.join("manifest.json"),
            veila_data::read_capped::MAX_JSON_METADATA_BYTES,
            "a shard manifest",
        )?;
        return Ok(SegData {
            fingerprint: serde_json::json!({
                "shards_manifest_sha256": veila_nn::checkpoint::sha256_hex(&manifest_bytes),
                "dataset": manifest.dataset,
                "frames": frames.len(),
                "label_map": labels.source(),
            }),
            frames,
            held_out: Vec::new(),
            labels,
        });
    }
    simulated_data(file, labels, &projector, net, on_item)
}

#[cfg(feature = "sim")]
fn simulated_data(
    file: &SegTrainFile,
    labels: LabelSpace,
    projector: &Projector,
    net: &veila_nn::segmenter::SegmenterConfig,
    on_item: &(dyn Fn() + Sync),
) -> Result<SegData> {
    let d = &file.data;
    let Some(list) = &d.scenes else {
        return Err(Error::Data("[data] has neither scenes nor shards".into()));
    };
    let frames = sim::simulated_frames(
        list,
        d.scene_count,
        d.frames_per_scene,
        projector,
        net,
        on_item,
    )?;
    let held_out = match &d.held_out_scenes {
        Some(h) if d.held_out_count > 0 => {
            sim::simulated_held_out(h, d.held_out_count, projector, net, on_item)?
        }
        _ => Vec::new(),
    };
    let list_sha = |p: &std::path::Path| -> Result<String> {
        let bytes = veila_data::read_capped::read_metadata(
            p,
            veila_data::read_capped::MAX_CONFIG_BYTES,
            "a scene list",
        )?;
        Ok(veila_nn::checkpoint::sha256_hex(&bytes))
    };
    Ok(SegData {
        fingerprint: serde_json::json!({
            "scenes": list.display().to_string(),
            "scenes_sha256": list_sha(list)?,
            "scene_count": d.scene_count,
            "frames_per_scene": d.frames_per_scene,
        }),
        frames,
        held_out,
        labels,
    })
}

#[cfg(not(feature = "sim"))]
fn simulated_data(
    file: &SegTrainFile,
    _: LabelSpace,
    _: &Projector,
    _: &veila_nn::segmenter::SegmenterConfig,
    _: &(dyn Fn() + Sync),
) -> Result<SegData> {
    Err(Error::Input {
        path: file.data.scenes.clone().unwrap_or_default(),
        reason: "simulator frames need veila-diffusion's `sim` feature".into(),
    })
}

/// What [`train_from_file`] ends with: the model's config (provenance filled in) and the run.
#[derive(Debug)]
pub struct SegTrained {
    /// The model's config.
    pub config: SegmenterModelConfig,
    /// The run.
    pub outcome: SegFitOutcome,
    /// The loss weight of each class.
    pub class_weights: Vec<f32>,
}

/// Trains the segmenter of `file` on `data` (checkpoints in `OUTPUT/checkpoints`, resumed from
/// the newest), reporting through `on_event` ([`fit_segmenter`]).
pub fn train_from_file(
    file: &SegTrainFile,
    data: &SegData,
    device: &Device,
    on_event: impl FnMut(SegEvent<'_>) -> ControlFlow<()>,
) -> Result<SegTrained> {
    let mut config = file.model_config(&data.labels)?;
    let ignored = data.labels.ignored();
    let counts = class_counts(&data.frames, config.network.num_classes);
    let weights = class_weights(&counts, file.train.class_weights, &ignored);
    let settings = file.train.settings();
    let ck_dir = file.output.dir.join("checkpoints");
    let outcome = fit_segmenter(
        &train::SegTrainInput {
            model: &config,
            frames: &data.frames,
            class_weights: &weights,
            ignored: &ignored,
            held_out: &data.held_out,
            ck_dir: &ck_dir,
            data: data.fingerprint.clone(),
        },
        &settings,
        device,
        on_event,
    )?;
    config.provenance = serde_json::json!({
        "trained_by": "veila segment train",
        "data": data.fingerprint,
        "frames": data.frames.len(),
        "class_pixels": counts,
        "class_weights": file.train.class_weights,
        "train": settings,
        "steps_done": outcome.step,
        "train_seconds": outcome.train_seconds.round(),
        "held_out": outcome.held_out.as_ref().map(|s| serde_json::json!({
            "scans": data.held_out.len(),
            "miou": s.miou,
            "miou_present": s.miou_present,
            "accuracy": s.accuracy,
            "iou": s.iou,
            "present": s.present,
        })),
    });
    Ok(SegTrained {
        config,
        outcome,
        class_weights: weights,
    })
}
