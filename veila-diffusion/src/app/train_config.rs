//! The training config of `veila train` (`[data]`, `[model]`, `[train]`, `[output]`), as serde
//! structs any format can fill (the binary reads TOML), and what it gives: the [`BundleConfig`] a
//! run trains ([`TrainFile::bundle_config`]) and the [`RecipeSettings`] it trains with
//! ([`TrainSection::recipe_settings`]).
//!
//! ```toml
//! [data]
//! shards = "data/kitti-shards"     # folder with manifest.json (relative to this file)
//! # max_frames = 2000              # use the first N samples only
//! # verify = true                  # check every shard's sha256 against the manifest
//! # unify_cameras = false          # true: give every sample the first one's camera (approximation)
//! # stream = false                 # true: read the shards batch by batch (any dataset size)
//! # prefetch = 4                   # batches read ahead when streaming
//!
//! [model]
//! variant = "full"                 # full, unconditional, no-cacm, no-gcma, no-pfc, semantic-only, depth-only
//! # method = "residual"            # eps, v, residual (default), flow, regression
//! # bundle = "models/default/bundle.json"  # start from a bundle config instead of the CPU default
//! # encoders_from = "models/default"       # reuse trained encoders instead of training them
//! # image_height = 96              # camera input size of the encoders
//! # image_width = 320
//! # semantic_encoder = "segformer-b0"     # a pretrained encoder by kind instead of a small CNN:
//! # semantic_weights = "weights/segformer-b0/model.safetensors"   # its Hugging Face file
//! # depth_encoder = "depth-anything-v2-small"
//! # depth_weights = "weights/da2-small/model.safetensors"
//! # views = 1                      # cameras per sample (3: the paper's front, front-left, front-right)
//! # ground_prior = false           # true: the small-CNN encoders also take the flat-ground depth
//! #                                #   from each image's calibration (LiDAR 1.73 m above the ground)
//! # depth_features = false         # true: the small-CNN depth encoder's own depth reading is one
//! #                                #   more channel of its feature maps (same weights)
//! # base_channels = 16             # the U-Nets' width: R2DM's is 64 (a GPU's), the CPU default 16
//! # channel_mults = [1, 2, 2, 4]   # width multiplier of each U-Net level
//! # res_blocks = 1                 # residual blocks per level
//! # ray_freqs = 4                  # octaves of each pixel's ray-direction Fourier features
//! # loss_weighting = "min-snr"     # or "uniform": every noise level alike in the loss
//! # clean_share = 0.25             # share of training draws at the clean levels (fine texture)
//! # range_weight = 1.0             # a return's loss weight ((r + 1) / 11)^P: far errors count more
//!
//! [train]
//! steps = 1000                     # denoiser steps
//! # mean_steps = 1000              # mean-network steps of the residual method (default: steps)
//! batch = 4
//! lr = 1e-3
//! seed = 0
//! encoder_steps = 250
//! checkpoint_every = 250
//! # grad_accum_steps = 1           # run each batch in this many parts (activation memory of one part)
//! # precision = "f32"              # or "bf16": mixed precision (bf16 activations, f32 weights; GPUs)
//! # activation_checkpointing = "none"   # or "block": recompute each block in the backward pass
//! # [train.encoder_augment]        # augment the encoders' training images (crop-zoom, colour,
//! # crop_zoom = { p = 0.5, scale = [1.0, 1.3] }   #  blur, noise, JPEG; veila_data::augment)
//!
//! [output]
//! dir = "runs/my-model"            # OUTPUT/checkpoints, OUTPUT/bundle
//! ```

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use veila_nn::encoders::kind::EncoderKind;

use super::bundle::{BundleConfig, EncoderSpec, Method, NetworkKnobs, Variant, sha256_hex};
use super::encoder_train::EncoderAugment;
use super::recipe::RecipeSettings;
use crate::error::{Error, Result};
use crate::trainer::Precision;

/// The config file.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainFile {
    /// `[data]`: the shards.
    pub data: DataSection,
    /// `[model]`: what is trained.
    #[serde(default)]
    pub model: ModelSection,
    /// `[train]`: steps, batches, rates.
    #[serde(default)]
    pub train: TrainSection,
    /// `[output]`: where checkpoints and the bundle go.
    pub output: OutputSection,
}

/// `[data]`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DataSection {
    /// Folder with `manifest.json` and the shards.
    pub shards: PathBuf,
    /// Use only the first this many samples.
    #[serde(default)]
    pub max_frames: Option<usize>,
    /// Check every shard against the manifest's sha256 before training.
    #[serde(default = "yes")]
    pub verify: bool,
    /// Train every sample with the first sample's camera, an approximation (by default every
    /// sample's own camera is used: the geometric attention of each camera is built once and
    /// samples of several rigs share a batch).
    #[serde(default)]
    pub unify_cameras: bool,
    /// Read the samples from the shards batch by batch (a loader thread reads ahead) and run the
    /// frozen encoders per batch, instead of loading every sample and its features into memory:
    /// for datasets of any size, at the cost of encoding each batch.
    #[serde(default)]
    pub stream: bool,
    /// Batches the loader reads ahead when streaming.
    #[serde(default = "d_prefetch")]
    pub prefetch: usize,
}

fn d_prefetch() -> usize {
    4
}

fn yes() -> bool {
    true
}

/// `[model]`.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelSection {
    /// Model variant of `BundleConfig::cpu_default` (default `full`).
    #[serde(default)]
    pub variant: Option<String>,
    /// Generative method (`eps`, `v`, `residual`, `flow`, `regression`; default: the CPU
    /// default's).
    #[serde(default)]
    pub method: Option<String>,
    /// A `bundle.json` to start from instead of the CPU default.
    #[serde(default)]
    pub bundle: Option<PathBuf>,
    /// Reuse the encoders of this bundle folder.
    #[serde(default)]
    pub encoders_from: Option<PathBuf>,
    /// Start the networks from this bundle folder's weights wherever names and shapes match
    /// (fine-tuning): its denoiser's, and its mean network's for a residual model. An
    /// unconditional bundle gives a conditional model its whole U-Net; the camera's GCMA layers
    /// are new and start at zero, so before its first update the model draws what the
    /// unconditional one drew. A bundle of which fewer than half the tensors fit is refused.
    #[serde(default)]
    pub init_from: Option<PathBuf>,
    /// Name written into the bundle.
    #[serde(default)]
    pub name: Option<String>,
    /// Camera input height of the encoders.
    #[serde(default)]
    pub image_height: Option<usize>,
    /// Camera input width of the encoders.
    #[serde(default)]
    pub image_width: Option<usize>,
    /// The semantic encoder by kind (`small-cnn`, `segformer-b0` .. `segformer-b5`,
    /// `depth-anything-v2-{small,base,large}`, `dinov2-{s,b,l}`); default: the config's.
    #[serde(default)]
    pub semantic_encoder: Option<String>,
    /// The pretrained semantic encoder's `model.safetensors`.
    #[serde(default)]
    pub semantic_weights: Option<PathBuf>,
    /// The depth encoder by kind, as `semantic_encoder`.
    #[serde(default)]
    pub depth_encoder: Option<String>,
    /// The pretrained depth encoder's `model.safetensors`.
    #[serde(default)]
    pub depth_weights: Option<PathBuf>,
    /// Camera views per sample (the paper's table 8: 1 or 3); the shards must carry as many
    /// cameras per sample (`veila convert --camera CAM_FRONT,CAM_FRONT_LEFT,...`).
    #[serde(default)]
    pub views: Option<usize>,
    /// The flat-ground prior as an input channel of the small-CNN encoders (`true`), or none
    /// (`false`); default: the config's (none for the CPU default).
    #[serde(default)]
    pub ground_prior: Option<bool>,
    /// The small-CNN depth encoder's depth reading as one more channel of its feature maps
    /// (`true`), or not (`false`); default: the config's (off for the CPU default).
    #[serde(default)]
    pub depth_features: Option<bool>,
    /// Width of the U-Nets' first level (default: the config's; the CPU default's is 16).
    #[serde(default)]
    pub base_channels: Option<usize>,
    /// Width multipliers of the U-Net levels, one per level (default: the config's).
    #[serde(default)]
    pub channel_mults: Option<Vec<usize>>,
    /// Residual blocks per U-Net level (default: the config's).
    #[serde(default)]
    pub res_blocks: Option<usize>,
    /// Octaves of the Fourier features of each pixel's ray direction fed to the U-Nets (default:
    /// the config's; the CPU default's is 4).
    #[serde(default)]
    pub ray_freqs: Option<usize>,
    /// How the noise levels weigh in the loss: `min-snr` (min-SNR-5) or `uniform` (every level
    /// alike in the prediction's MSE); default: the config's.
    #[serde(default)]
    pub loss_weighting: Option<String>,
    /// The share of training draws at the clean levels, where a sample's fine texture forms
    /// (`TrainLevels::clean_share`, within `[0, 1]`); default: the config's (uniform time).
    #[serde(default)]
    pub clean_share: Option<f64>,
    /// The power of the range weight in the denoiser's loss, 0 to 2
    /// (`BundleConfig::range_weight`); default: every pixel alike.
    #[serde(default)]
    pub range_weight: Option<f64>,
}

/// `[train]`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainSection {
    /// Denoiser steps.
    #[serde(default = "d_steps")]
    pub steps: u64,
    /// Global batch.
    #[serde(default = "d_batch")]
    pub batch: usize,
    /// Learning rate of the two networks.
    #[serde(default = "d_lr")]
    pub lr: f64,
    /// Seed of initialisation, batches and noise.
    #[serde(default)]
    pub seed: u64,
    /// Updates of each encoder.
    #[serde(default = "d_encoder_steps")]
    pub encoder_steps: usize,
    /// Batch of the encoders' training.
    #[serde(default = "d_encoder_batch")]
    pub encoder_batch: usize,
    /// Learning rate of the encoders.
    #[serde(default = "d_encoder_lr")]
    pub encoder_lr: f64,
    /// Steps between checkpoints.
    #[serde(default = "d_checkpoint_every")]
    pub checkpoint_every: u64,
    /// Checkpoints kept.
    #[serde(default = "d_keep")]
    pub keep_checkpoints: usize,
    /// EMA decay of the shipped weights.
    #[serde(default = "d_ema")]
    pub ema_decay: f64,
    /// Condition dropout for classifier-free guidance (default 0.1 for conditional models).
    #[serde(default)]
    pub cond_drop_prob: Option<f64>,
    /// Steps of the residual method's mean network (default: `steps`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mean_steps: Option<u64>,
    /// Gradient accumulation: each update runs its batch in this many parts (default 1: none).
    /// The batch stays the global one; each part's activations are freed before the next.
    #[serde(default = "d_one", skip_serializing_if = "is_one")]
    pub grad_accum_steps: u64,
    /// Image augmentation of the encoders' training (`[train.encoder_augment]`, any key of
    /// `veila_data::augment::Photometric` under `photometric`, `p` / `scale` under `crop_zoom`;
    /// absent: none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub encoder_augment: Option<EncoderAugment>,
    /// The activations' precision of the two networks' training: `f32` (default) or `bf16`
    /// (mixed precision on f32 master weights; for GPUs).
    #[serde(default, skip_serializing_if = "is_f32")]
    pub precision: Precision,
    /// Activation checkpointing of the denoiser and the mean network: `none` (default) or
    /// `block` (each residual block, GCMA and PFC layer recomputed in the backward pass: the same
    /// gradients, less memory, one more forward pass; `veila bench --activation-checkpointing`
    /// measures both).
    #[serde(default, skip_serializing_if = "is_no_checkpointing")]
    pub activation_checkpointing: crate::trainer::ActivationCheckpointing,
}

fn is_no_checkpointing(a: &crate::trainer::ActivationCheckpointing) -> bool {
    *a == crate::trainer::ActivationCheckpointing::None
}

fn is_f32(p: &Precision) -> bool {
    *p == Precision::F32
}

fn d_one() -> u64 {
    1
}
fn is_one(v: &u64) -> bool {
    *v == 1
}

fn d_steps() -> u64 {
    1000
}
fn d_batch() -> usize {
    4
}
fn d_lr() -> f64 {
    1e-3
}
fn d_encoder_steps() -> usize {
    250
}
fn d_encoder_batch() -> usize {
    8
}
fn d_encoder_lr() -> f64 {
    2e-3
}
fn d_checkpoint_every() -> u64 {
    250
}
fn d_keep() -> usize {
    2
}
fn d_ema() -> f64 {
    0.995
}

impl Default for TrainSection {
    fn default() -> Self {
        TrainSection {
            steps: d_steps(),
            batch: d_batch(),
            lr: d_lr(),
            seed: 0,
            encoder_steps: d_encoder_steps(),
            encoder_batch: d_encoder_batch(),
            encoder_lr: d_encoder_lr(),
            checkpoint_every: d_checkpoint_every(),
            keep_checkpoints: d_keep(),
            ema_decay: d_ema(),
            cond_drop_prob: None,
            mean_steps: None,
            grad_accum_steps: 1,
            encoder_augment: None,
            precision: Precision::F32,
            activation_checkpointing: crate::trainer::ActivationCheckpointing::None,
        }
    }
}

impl TrainSection {
    /// The recipe's settings (condition dropout 0.1 unless set).
    pub fn recipe_settings(&self) -> RecipeSettings {
        RecipeSettings {
            seed: self.seed,
            steps: self.steps,
            mean_steps: self.mean_steps,
            batch: self.batch,
            lr: self.lr,
            ema_decay: self.ema_decay,
            cond_drop_prob: self.cond_drop_prob.unwrap_or(0.1),
            checkpoint_every: self.checkpoint_every,
            keep_checkpoints: self.keep_checkpoints,
            encoder_steps: self.encoder_steps,
            encoder_batch: self.encoder_batch,
            encoder_lr: self.encoder_lr,
            grad_accum_steps: self.grad_accum_steps,
            encoder_augment: self.encoder_augment,
            precision: self.precision,
            activation_checkpointing: self.activation_checkpointing,
        }
    }
}

/// `[output]`.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutputSection {
    /// Output folder: `checkpoints/` and `bundle/` go inside.
    pub dir: PathBuf,
}

/// Written to `OUTPUT/checkpoints/run.json`: a rerun resumes only with the same settings.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunFingerprint {
    /// The bundle config trained.
    pub bundle: BundleConfig,
    /// `[train]` as JSON.
    pub train: serde_json::Value,
    /// sha256 of the shards' `manifest.json`.
    pub data_manifest_sha256: String,
    /// Samples trained on.
    pub samples: usize,
    /// `[model] encoders_from`, when set.
    pub encoders_from: Option<String>,
    /// `[model] init_from`, when set (absent from the run records of runs without it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub init_from: Option<String>,
}

/// The error of a config value: the config file and what is wrong.
fn bad(config_path: &Path, reason: impl Into<String>) -> Error {
    Error::Input {
        path: config_path.to_path_buf(),
        reason: reason.into(),
    }
}

/// The largest `[train] batch` and `encoder_batch`.
pub const MAX_BATCH: usize = 4096;
/// The largest `[train] steps` and `encoder_steps`.
pub const MAX_STEPS: u64 = 100_000_000;
/// The largest `[data] prefetch` (batches held ahead of the trainer).
pub const MAX_PREFETCH: usize = 64;
/// The largest encoder input side, `[model] image_height` / `image_width`, in pixels.
pub const MAX_IMAGE_SIDE: usize = 4096;

impl TrainFile {
    /// Makes the config's relative paths relative to the config file `config_path`, and checks
    /// the `[train]` and `[data]` values (errors name the file).
    pub fn resolve_and_check(&mut self, config_path: &Path) -> Result<()> {
        let base = config_path
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        let resolve = |p: &Path| {
            if p.is_absolute() {
                p.to_path_buf()
            } else {
                base.join(p)
            }
        };
        self.data.shards = resolve(&self.data.shards);
        self.output.dir = resolve(&self.output.dir);
        let m = &mut self.model;
        m.bundle = m.bundle.as_deref().map(resolve);
        m.encoders_from = m.encoders_from.as_deref().map(resolve);
        m.init_from = m.init_from.as_deref().map(resolve);
        m.semantic_weights = m.semantic_weights.as_deref().map(resolve);
        m.depth_weights = m.depth_weights.as_deref().map(resolve);
        let t = &self.train;
        let bad_train = |what: &str| bad(config_path, format!("[train] {what}"));
        if t.steps == 0 {
            return Err(bad_train("steps must be at least 1"));
        }
        if t.batch == 0 || t.encoder_batch == 0 {
            return Err(bad_train("batch and encoder_batch must be at least 1"));
        }
        if !(t.lr.is_finite() && t.lr > 0.0 && t.encoder_lr.is_finite() && t.encoder_lr > 0.0) {
            return Err(bad_train("lr and encoder_lr must be finite and > 0"));
        }
        if t.checkpoint_every == 0 {
            return Err(bad_train("checkpoint_every must be at least 1"));
        }
        if t.grad_accum_steps == 0 || t.grad_accum_steps as usize > t.batch {
            return Err(bad_train(&format!(
                "grad_accum_steps must be in 1..=batch ({}), got {}",
                t.batch, t.grad_accum_steps
            )));
        }
        if !(0.0..1.0).contains(&t.ema_decay) {
            return Err(bad_train("ema_decay must be in [0, 1)"));
        }
        if let Some(p) = t.cond_drop_prob
            && !(0.0..=1.0).contains(&p)
        {
            return Err(bad_train("cond_drop_prob must be in [0, 1]"));
        }
        if self.data.max_frames == Some(0) {
            return Err(bad(config_path, "[data] max_frames must be at least 1"));
        }
        // sizes that become allocations: bounded before anything is built
        if t.batch > MAX_BATCH || t.encoder_batch > MAX_BATCH {
            return Err(bad_train(&format!(
                "batch and encoder_batch must be at most {MAX_BATCH}"
            )));
        }
        if t.steps > MAX_STEPS || t.encoder_steps as u64 > MAX_STEPS {
            return Err(bad_train(&format!(
                "steps and encoder_steps must be at most {MAX_STEPS}"
            )));
        }
        if !(1..=MAX_PREFETCH).contains(&self.data.prefetch) {
            return Err(bad(
                config_path,
                format!("[data] prefetch must be in 1..={MAX_PREFETCH}"),
            ));
        }
        for (what, v) in [
            ("image_height", self.model.image_height),
            ("image_width", self.model.image_width),
        ] {
            if let Some(v) = v
                && !(8..=MAX_IMAGE_SIDE).contains(&v)
            {
                return Err(bad(
                    config_path,
                    format!("[model] {what} must be in 8..={MAX_IMAGE_SIDE}, got {v}"),
                ));
            }
        }
        Ok(())
    }

    /// The bundle config the run trains (`config_path`: the config file, which errors name).
    pub fn bundle_config(&self, config_path: &Path) -> Result<BundleConfig> {
        let m = &self.model;
        let bad = |reason: String| bad(config_path, reason);
        let mut cfg = match (&m.bundle, &m.variant) {
            (Some(_), Some(_)) => {
                return Err(bad(
                    "[model] give either `variant` or `bundle`, not both".into()
                ));
            }
            (Some(p), None) => {
                // the error names the config and its field too: the path came from there
                let from_field = |e: &dyn std::fmt::Display| bad(format!("[model] bundle: {e}"));
                let text = veila_data::read_capped::read_metadata(
                    p,
                    veila_data::read_capped::MAX_JSON_METADATA_BYTES,
                    "a bundle.json",
                )
                .map_err(|e| from_field(&e))?;
                let mut c: BundleConfig = serde_json::from_slice(&text)
                    .map_err(|e| from_field(&format!("{}: not a bundle.json: {e}", p.display())))?;
                c.provenance = serde_json::Value::Null;
                // its pretrained weights lie in its folder (it may be a downloaded bundle's):
                // checked there now, and named by an absolute path from here on
                for (field, spec) in [
                    ("semantic_encoder", &mut c.semantic_encoder),
                    ("depth_encoder", &mut c.depth_encoder),
                ] {
                    let Some(spec) = spec.as_mut().filter(|s| s.kind.is_pretrained()) else {
                        continue;
                    };
                    let Some(w) = spec.weights.clone() else {
                        continue;
                    };
                    let found = match spec.resolve_weights_from(p, field)? {
                        Some(f) => f,
                        None => p.parent().unwrap_or(Path::new(".")).join(w),
                    };
                    spec.weights = Some(std::path::absolute(&found).unwrap_or(found));
                }
                c
            }
            (None, v) => {
                let variant: Variant = v
                    .as_deref()
                    .unwrap_or("full")
                    .parse()
                    .map_err(|e: String| bad(format!("[model] {e}")))?;
                BundleConfig::cpu_default(variant)
            }
        };
        // a bundle.json keeps its own method unless one is named; the CPU default takes the
        // default method
        let method = match (&m.method, &m.bundle) {
            (Some(name), _) => Some(
                name.parse::<Method>()
                    .map_err(|e: String| bad(format!("[model] {e}")))?,
            ),
            (None, None) => Some(Method::DEFAULT),
            (None, Some(_)) => None,
        };
        if let Some(method) = method {
            cfg = cfg.with_method(method);
        }
        if let Some(name) = &m.name {
            cfg.name = name.clone();
        }
        if m.image_height.is_some() || m.image_width.is_some() {
            cfg.image_height = m.image_height.unwrap_or(cfg.image_height);
            cfg.image_width = m.image_width.unwrap_or(cfg.image_width);
            if cfg.image_height < 32 || cfg.image_width < 32 {
                return Err(bad(
                    "[model] image_height and image_width must be at least 32".into(),
                ));
            }
            if let Some(c) = cfg.denoiser.conditioning.as_mut() {
                c.feature_sizes =
                    veila_nn::ConditioningConfig::pyramid_sizes(cfg.image_height, cfg.image_width);
            }
        }
        if m.semantic_encoder.is_some()
            || m.depth_encoder.is_some()
            || m.semantic_weights.is_some()
            || m.depth_weights.is_some()
        {
            let semantic = encoder_spec(
                "semantic",
                m.semantic_encoder.as_deref(),
                m.semantic_weights.as_deref(),
                cfg.semantic_encoder.as_ref(),
                config_path,
            )?;
            let depth = encoder_spec(
                "depth",
                m.depth_encoder.as_deref(),
                m.depth_weights.as_deref(),
                cfg.depth_encoder.as_ref(),
                config_path,
            )?;
            if cfg.denoiser.conditioning.is_none() {
                return Err(bad(
                    "[model] names encoders, but the model is unconditional".into(),
                ));
            }
            cfg.set_encoders(semantic, depth)
                .map_err(|e| bad(format!("[model] encoders: {e}")))?;
        }
        if let Some(on) = m.ground_prior {
            let prior = on.then(veila_nn::encoders::ground::GroundPrior::default);
            if cfg.set_ground_prior(prior) == 0 && on {
                return Err(bad(
                    "[model] ground_prior needs a small-cnn encoder (pretrained encoders take colours only)"
                        .into(),
                ));
            }
        }
        if let Some(on) = m.depth_features {
            cfg.set_depth_features(on)
                .map_err(|e| bad(format!("[model] depth_features: {e}")))?;
        }
        let loss_weighting = m
            .loss_weighting
            .as_deref()
            .map(str::parse)
            .transpose()
            .map_err(|e: String| bad(format!("[model] {e}")))?;
        cfg.set_network(&NetworkKnobs {
            base_channels: m.base_channels,
            channel_mults: m.channel_mults.clone(),
            res_blocks: m.res_blocks,
            ray_freqs: m.ray_freqs,
            loss_weighting,
            clean_share: m.clean_share,
            range_weight: m.range_weight,
        })
        .map_err(|e| bad(format!("[model] {e}")))?;
        if let Some(views) = m.views {
            if !(1..=6).contains(&views) {
                return Err(bad("[model] views must be 1 to 6".into()));
            }
            let Some(c) = cfg.denoiser.conditioning.as_mut() else {
                return Err(bad("[model] views, but the model is unconditional".into()));
            };
            c.num_views = views;
            if let Some(c) = cfg
                .residual
                .as_mut()
                .and_then(|r| r.mean_net.conditioning.as_mut())
            {
                c.num_views = views;
            }
        }
        cfg.denoiser
            .validate()
            .map_err(|e| bad(format!("[model] gives an invalid denoiser: {e}")))?;
        Ok(cfg)
    }
}

/// One encoder of `[model]`: `kind` (default: the config's), with `weights` for pretrained kinds
/// (hashed here, so the bundle records which file it was trained with).
fn encoder_spec(
    which: &str,
    kind: Option<&str>,
    weights: Option<&Path>,
    current: Option<&EncoderSpec>,
    config_path: &Path,
) -> Result<Option<EncoderSpec>> {
    let bad = |reason: String| bad(config_path, format!("[model] {which}_encoder: {reason}"));
    let kind: Option<EncoderKind> = match kind {
        Some(k) => Some(k.parse().map_err(|e: String| bad(e))?),
        None => current.map(|c| c.kind),
    };
    let Some(kind) = kind else {
        if weights.is_some() {
            return Err(bad(format!("`{which}_weights` without an encoder")));
        }
        return Ok(None);
    };
    if !kind.is_pretrained() {
        if weights.is_some() {
            return Err(bad(format!(
                "a small-cnn is trained here; `{which}_weights` is for pretrained kinds"
            )));
        }
        let config = current
            .and_then(|c| c.small_cnn_config().cloned())
            .unwrap_or_default();
        return Ok(Some(EncoderSpec::small_cnn(config)));
    }
    let Some(path) = weights else {
        if let Some(c) = current.filter(|c| c.kind == kind) {
            return Ok(Some(c.clone()));
        }
        return Err(bad(format!(
            "`{kind}` needs `{which}_weights`, the path of `model.safetensors` from {}",
            kind.hub_repo().unwrap_or("-")
        )));
    };
    // a regular file under the weights cap, checked before anything is read
    let bytes = veila_nn::checkpoint::read_weights_file(path).map_err(|e| {
        let hint = match &e {
            veila_nn::Error::Io { .. } => format!(
                " (download `model.safetensors` of {} from the Hugging Face Hub)",
                kind.hub_repo().unwrap_or("-")
            ),
            _ => String::new(),
        };
        bad(format!("cannot read {}{hint}: {e}", path.display()))
    })?;
    // check it now rather than after the data is loaded
    kind.load_pretrained(
        &bytes,
        path,
        candle_core::DType::F32,
        &candle_core::Device::Cpu,
    )
    .map_err(|e| bad(e.to_string()))?;
    let path = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
    Ok(Some(EncoderSpec::pretrained(
        kind,
        path,
        Some(sha256_hex(&bytes)),
    )))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(model: serde_json::Value) -> Result<BundleConfig> {
        let file: TrainFile = serde_json::from_value(serde_json::json!({
            "data": {"shards": "shards"},
            "model": model,
            "train": {},
            "output": {"dir": "out"},
        }))
        .map_err(|e| bad(Path::new("train.toml"), e.to_string()))?;
        file.bundle_config(Path::new("train.toml"))
    }

    fn depth_channels(c: &BundleConfig) -> Vec<usize> {
        c.denoiser
            .conditioning
            .as_ref()
            .map(|k| k.depth_channels.clone())
            .unwrap_or_default()
    }

    #[test]
    fn depth_features_widen_the_depth_conditioning_and_refusals_name_the_file() {
        let plain = config(serde_json::json!({})).unwrap();
        assert_eq!(
            config(serde_json::json!({"depth_features": false})).unwrap(),
            plain
        );
        let on = config(serde_json::json!({"depth_features": true})).unwrap();
        let widened: Vec<usize> = depth_channels(&plain).iter().map(|c| c + 1).collect();
        assert_eq!(depth_channels(&on), widened);
        let mean = on.residual.as_ref().unwrap().mean_net.conditioning.as_ref();
        assert_eq!(mean.unwrap().depth_channels, widened);
        // a model without a depth encoder cannot have it
        let err = config(serde_json::json!({"variant": "semantic-only", "depth_features": true}))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("train.toml") && err.contains("depth_features"),
            "{err}"
        );
    }

    #[test]
    #[cfg(feature = "sim")] // the other door, the simulator's recipe
    fn both_doors_size_the_networks_and_place_the_updates_alike() {
        use crate::app::sim_recipe::SimRecipe;
        use crate::prediction::LossWeighting;
        let knobs = serde_json::json!({
            "method": "residual",
            "base_channels": 24,
            "channel_mults": [1, 2, 4, 8],
            "res_blocks": 2,
            "ray_freqs": 6,
            "loss_weighting": "uniform",
            "clean_share": 0.25,
            "range_weight": 1.0,
        });
        let veila_train = config(knobs).unwrap();
        let d = &veila_train.denoiser;
        assert_eq!(
            (d.base_channels, &d.channel_mults, d.num_res_blocks),
            (24, &vec![1, 2, 4, 8], 2)
        );
        // the residual method's mean network is sized alike, and keeps its own input
        let mean = &veila_train.residual.as_ref().unwrap().mean_net;
        assert_eq!(
            (mean.base_channels, &mean.channel_mults, mean.num_res_blocks),
            (24, &vec![1, 2, 4, 8], 2)
        );
        assert_eq!(mean.in_channels * 2, d.in_channels);
        for net in [d, mean] {
            assert_eq!(net.ray_features.map(|e| e.num_freqs), Some(6));
        }
        assert_eq!(veila_train.diffusion.loss_weighting, LossWeighting::Uniform);
        assert_eq!(
            veila_train.diffusion.train_levels,
            crate::TrainLevels::clean_share(0.25)
        );
        assert_eq!(veila_train.range_weight, Some(1.0));
        // `train-default` with the same knobs trains the same networks
        let recipe = SimRecipe {
            method: Method::Residual,
            base_channels: Some(24),
            channel_mults: Some(vec![1, 2, 4, 8]),
            res_blocks: Some(2),
            ray_freqs: Some(6),
            loss_weighting: Some(LossWeighting::Uniform),
            clean_share: Some(0.25),
            range_weight: Some(1.0),
            ..SimRecipe::shipped()
        };
        let sim = recipe.bundle_config().unwrap();
        assert_eq!(sim.denoiser, veila_train.denoiser);
        assert_eq!(sim.residual, veila_train.residual);
        assert_eq!(sim.diffusion, veila_train.diffusion);
        assert_eq!(sim.range_weight, veila_train.range_weight);
        // nothing given keeps the config's, and min-snr is the CPU default's
        let plain = config(serde_json::json!({})).unwrap();
        assert_eq!(
            config(serde_json::json!({"loss_weighting": "min-snr"})).unwrap(),
            plain
        );
        assert_ne!(plain.denoiser, veila_train.denoiser);
        // refusals name the file and the field
        for (model, needle) in [
            (
                serde_json::json!({"loss_weighting": "snr"}),
                "loss weighting `snr`",
            ),
            (serde_json::json!({"clean_share": 1.5}), "share"),
            (serde_json::json!({"range_weight": 2.5}), "range_weight"),
            (serde_json::json!({"range_weight": -0.5}), "range_weight"),
            (serde_json::json!({"base_channels": 0}), "base_channels"),
            (
                serde_json::json!({"base_channels": 1_000_000}),
                "base_channels",
            ),
            (serde_json::json!({"res_blocks": 1000}), "num_res_blocks"),
            (
                serde_json::json!({"ray_freqs": 40}),
                "at most 32 frequencies",
            ),
            // every level within its width limit, the whole far past 2^30 weights
            (
                serde_json::json!({"base_channels": 4096, "channel_mults": [1, 2, 4, 4]}),
                "limit of 1073741824",
            ),
            // 32 rows cannot halve six times
            (
                serde_json::json!({"channel_mults": [1, 1, 1, 1, 1, 1, 1]}),
                "channel_mults",
            ),
        ] {
            let e = config(model.clone()).unwrap_err().to_string();
            assert!(
                e.contains("train.toml") && e.contains(needle),
                "{model}: {e}"
            );
        }
    }
}
