//! `veila train --config CONFIG.toml`: trains a model bundle on converted training shards
//! (`cargo xtask convert`).
//!
//! The image encoders are trained first (or taken from another bundle), with sparse supervision
//! from the LiDAR: each return of a shard's range image is projected into the camera image, giving
//! a metric depth and, when the shards carry train ids, a semantic class at that pixel. Then the
//! denoiser is trained on the frozen encoder features. The run is resumable: the trained encoders
//! and the denoiser checkpoints live in `OUTPUT/checkpoints`, and rerunning the same config picks
//! up the newest checkpoint (the result is bit-identical to an uninterrupted run). The finished
//! bundle is written to `OUTPUT/bundle` (verified by reading it back). Every update appends a line
//! to `OUTPUT/train_log.jsonl` (stage, step, loss, learning rate, samples/s).
//!
//! Data-parallel: started by a launcher as several processes (torchrun's `RANK` / `WORLD_SIZE` /
//! `LOCAL_RANK` / `MASTER_ADDR` / `MASTER_PORT`, or Slurm's `SLURM_PROCID` / `SLURM_NTASKS` /
//! `SLURM_LOCALID` with `MASTER_ADDR` / `MASTER_PORT` exported), the ranks meet at rank 0 over TCP
//! ([`crate::dist`]), each trains on its share of every global batch of `[train] batch`, the
//! gradients are averaged before each update, and rank 0 alone writes checkpoints, the log and the
//! bundle (the other ranks log to `train_log.rank-N.jsonl`). The output folder must be shared.
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
//! # [train.encoder_augment]        # augment the encoders' training images (crop-zoom, colour,
//! # crop_zoom = { p = 0.5, scale = [1.0, 1.3] }   #  blur, noise, JPEG; veila_data::augment)
//!
//! [output]
//! dir = "runs/my-model"            # OUTPUT/checkpoints, OUTPUT/bundle
//! ```

use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use serde::{Deserialize, Serialize};
use veila_data::shard::{Manifest, read_shard};
use veila_diffusion::app::bundle::{Bundle, BundleConfig, EncoderSpec, Variant, sha256_hex};
use veila_diffusion::app::{
    Encoder, EncoderData, EncoderEvent, EncoderSource, ExampleSource, Examples, RecipeInput,
    RecipeSettings, Stage, TrainExample, run_recipe,
};
use veila_diffusion::trainer::distributed::{Parallel, ProcessGroup};
use veila_diffusion::{Precision, StepStats, TrainObserver};
use veila_geom::{ProjectionOptions, Projector, RayTable};
use veila_nn::encoders::kind::EncoderKind;

use crate::train_data::{Prepared, ShardSource, prepare_sample};
use crate::{model, progress};

/// Arguments of `veila train`.
#[derive(Debug, Args)]
pub(crate) struct TrainArgs {
    /// Training config (TOML: `[data]` shards, `[model]` variant, `[train]` steps, batch, lr, seed,
    /// encoder_steps, checkpoint_every, `[output]` dir); relative paths are relative to this file.
    #[arg(long, value_name = "CONFIG.toml")]
    config: PathBuf,
    /// Stop after this many training steps of this run, the mean network's and the denoiser's
    /// together (a checkpoint is written; rerun the same command to continue).
    #[arg(long, value_name = "N")]
    stop_after: Option<u64>,
}

/// The config file.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct TrainFile {
    data: DataSection,
    #[serde(default)]
    model: ModelSection,
    #[serde(default)]
    train: TrainSection,
    output: OutputSection,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct DataSection {
    /// Folder with `manifest.json` and the shards.
    shards: PathBuf,
    /// Use only the first this many samples.
    #[serde(default)]
    max_frames: Option<usize>,
    /// Check every shard against the manifest's sha256 before training.
    #[serde(default = "yes")]
    verify: bool,
    /// Train every sample with the first sample's camera, an approximation (by default every
    /// sample's own camera is used: the geometric attention of each camera is built once and
    /// samples of several rigs share a batch).
    #[serde(default)]
    unify_cameras: bool,
    /// Read the samples from the shards batch by batch (a loader thread reads ahead) and run the
    /// frozen encoders per batch, instead of loading every sample and its features into memory:
    /// for datasets of any size, at the cost of encoding each batch.
    #[serde(default)]
    stream: bool,
    /// Batches the loader reads ahead when streaming.
    #[serde(default = "d_prefetch")]
    prefetch: usize,
}

fn d_prefetch() -> usize {
    4
}

fn yes() -> bool {
    true
}

#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct ModelSection {
    /// Model variant of `BundleConfig::cpu_default` (default `full`).
    #[serde(default)]
    variant: Option<String>,
    /// Generative method (`eps`, `v`, `residual`, `flow`, `regression`; default: the CPU
    /// default's).
    #[serde(default)]
    method: Option<String>,
    /// A `bundle.json` to start from instead of the CPU default.
    #[serde(default)]
    bundle: Option<PathBuf>,
    /// Reuse the encoders of this bundle folder.
    #[serde(default)]
    encoders_from: Option<PathBuf>,
    /// Name written into the bundle.
    #[serde(default)]
    name: Option<String>,
    /// Camera input height of the encoders.
    #[serde(default)]
    image_height: Option<usize>,
    /// Camera input width of the encoders.
    #[serde(default)]
    image_width: Option<usize>,
    /// The semantic encoder by kind (`small-cnn`, `segformer-b0` .. `segformer-b5`,
    /// `depth-anything-v2-{small,base,large}`, `dinov2-{s,b,l}`); default: the config's.
    #[serde(default)]
    semantic_encoder: Option<String>,
    /// The pretrained semantic encoder's `model.safetensors`.
    #[serde(default)]
    semantic_weights: Option<PathBuf>,
    /// The depth encoder by kind, as `semantic_encoder`.
    #[serde(default)]
    depth_encoder: Option<String>,
    /// The pretrained depth encoder's `model.safetensors`.
    #[serde(default)]
    depth_weights: Option<PathBuf>,
    /// Camera views per sample (the paper's table 8: 1 or 3); the shards must carry as many
    /// cameras per sample (`cargo xtask convert --camera CAM_FRONT,CAM_FRONT_LEFT,...`).
    #[serde(default)]
    views: Option<usize>,
    /// The flat-ground prior as an input channel of the small-CNN encoders (`true`), or none
    /// (`false`); default: the config's (none for the CPU default).
    #[serde(default)]
    ground_prior: Option<bool>,
    /// The small-CNN depth encoder's depth reading as one more channel of its feature maps
    /// (`true`), or not (`false`); default: the config's (off for the CPU default).
    #[serde(default)]
    depth_features: Option<bool>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct TrainSection {
    #[serde(default = "d_steps")]
    steps: u64,
    #[serde(default = "d_batch")]
    batch: usize,
    #[serde(default = "d_lr")]
    lr: f64,
    #[serde(default)]
    seed: u64,
    #[serde(default = "d_encoder_steps")]
    encoder_steps: usize,
    #[serde(default = "d_encoder_batch")]
    encoder_batch: usize,
    #[serde(default = "d_encoder_lr")]
    encoder_lr: f64,
    #[serde(default = "d_checkpoint_every")]
    checkpoint_every: u64,
    #[serde(default = "d_keep")]
    keep_checkpoints: usize,
    #[serde(default = "d_ema")]
    ema_decay: f64,
    /// Condition dropout for classifier-free guidance (default 0.1 for conditional models).
    #[serde(default)]
    cond_drop_prob: Option<f64>,
    /// Steps of the residual method's mean network (default: `steps`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    mean_steps: Option<u64>,
    /// Gradient accumulation: each update runs its batch in this many parts (default 1: none).
    /// The batch stays the global one; each part's activations are freed before the next.
    #[serde(default = "d_one", skip_serializing_if = "is_one")]
    grad_accum_steps: u64,
    /// Image augmentation of the encoders' training (`[train.encoder_augment]`, any key of
    /// `veila_data::augment::Photometric` under `photometric`, `p` / `scale` under `crop_zoom`;
    /// absent: none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    encoder_augment: Option<veila_diffusion::app::EncoderAugment>,
    /// The activations' precision of the two networks' training: `f32` (default) or `bf16`
    /// (mixed precision on f32 master weights; for GPUs).
    #[serde(default, skip_serializing_if = "is_f32")]
    precision: Precision,
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
        }
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct OutputSection {
    /// Output folder: `checkpoints/` and `bundle/` go inside.
    dir: PathBuf,
}

/// Written to `OUTPUT/checkpoints/run.json`: a rerun resumes only with the same settings.
#[derive(Debug, Clone, PartialEq, Serialize)]
struct RunFingerprint {
    bundle: BundleConfig,
    train: serde_json::Value,
    data_manifest_sha256: String,
    samples: usize,
    encoders_from: Option<String>,
}

const ENCODER_DIR: &str = "encoders";

fn read_config(path: &Path) -> Result<TrainFile> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read", path.display()))?;
    let mut cfg: TrainFile = toml::from_str(&text)
        .map_err(|e| anyhow::anyhow!("{}: not a valid training config: {e}", path.display()))?;
    let base = path
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
    cfg.data.shards = resolve(&cfg.data.shards);
    cfg.output.dir = resolve(&cfg.output.dir);
    cfg.model.bundle = cfg.model.bundle.as_deref().map(resolve);
    cfg.model.encoders_from = cfg.model.encoders_from.as_deref().map(resolve);
    cfg.model.semantic_weights = cfg.model.semantic_weights.as_deref().map(resolve);
    cfg.model.depth_weights = cfg.model.depth_weights.as_deref().map(resolve);
    let t = &cfg.train;
    let bad = |what: &str| anyhow::anyhow!("{}: [train] {what}", path.display());
    if t.steps == 0 {
        return Err(bad("steps must be at least 1"));
    }
    if t.batch == 0 || t.encoder_batch == 0 {
        return Err(bad("batch and encoder_batch must be at least 1"));
    }
    if !(t.lr.is_finite() && t.lr > 0.0 && t.encoder_lr.is_finite() && t.encoder_lr > 0.0) {
        return Err(bad("lr and encoder_lr must be finite and > 0"));
    }
    if t.checkpoint_every == 0 {
        return Err(bad("checkpoint_every must be at least 1"));
    }
    if t.grad_accum_steps == 0 || t.grad_accum_steps as usize > t.batch {
        return Err(bad(&format!(
            "grad_accum_steps must be in 1..=batch ({}), got {}",
            t.batch, t.grad_accum_steps
        )));
    }
    if !(0.0..1.0).contains(&t.ema_decay) {
        return Err(bad("ema_decay must be in [0, 1)"));
    }
    if let Some(p) = t.cond_drop_prob
        && !(0.0..=1.0).contains(&p)
    {
        return Err(bad("cond_drop_prob must be in [0, 1]"));
    }
    if cfg.data.max_frames == Some(0) {
        return Err(anyhow::anyhow!(
            "{}: [data] max_frames must be at least 1",
            path.display()
        ));
    }
    Ok(cfg)
}

/// The bundle config the run trains.
fn bundle_config(file: &TrainFile, config_path: &Path) -> Result<BundleConfig> {
    let m = &file.model;
    let mut cfg = match (&m.bundle, &m.variant) {
        (Some(_), Some(_)) => bail!(
            "{}: [model] give either `variant` or `bundle`, not both",
            config_path.display()
        ),
        (Some(p), None) => {
            let text = std::fs::read(p).with_context(|| format!("{}: cannot read", p.display()))?;
            let mut c: BundleConfig = serde_json::from_slice(&text)
                .with_context(|| format!("{}: not a bundle.json", p.display()))?;
            c.provenance = serde_json::Value::Null;
            c
        }
        (None, v) => {
            let variant: Variant = v
                .as_deref()
                .unwrap_or("full")
                .parse()
                .map_err(|e: String| anyhow::anyhow!("{}: [model] {e}", config_path.display()))?;
            BundleConfig::cpu_default(variant)
        }
    };
    // a bundle.json keeps its own method unless one is named; the CPU default takes the
    // default method
    let method = match (&m.method, &m.bundle) {
        (Some(name), _) => Some(
            name.parse::<veila_diffusion::app::bundle::Method>()
                .map_err(|e: String| anyhow::anyhow!("{}: [model] {e}", config_path.display()))?,
        ),
        (None, None) => Some(veila_diffusion::app::bundle::Method::DEFAULT),
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
            bail!(
                "{}: [model] image_height and image_width must be at least 32",
                config_path.display()
            );
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
            bail!(
                "{}: [model] names encoders, but the model is unconditional",
                config_path.display()
            );
        }
        cfg.set_encoders(semantic, depth)
            .with_context(|| format!("{}: [model] encoders", config_path.display()))?;
    }
    if let Some(on) = m.ground_prior {
        let prior = on.then(veila_nn::encoders::ground::GroundPrior::default);
        if cfg.set_ground_prior(prior) == 0 && on {
            bail!(
                "{}: [model] ground_prior needs a small-cnn encoder (pretrained encoders take colours only)",
                config_path.display()
            );
        }
    }
    if let Some(on) = m.depth_features {
        cfg.set_depth_features(on)
            .with_context(|| format!("{}: [model] depth_features", config_path.display()))?;
    }
    if let Some(views) = m.views {
        if !(1..=6).contains(&views) {
            bail!("{}: [model] views must be 1 to 6", config_path.display());
        }
        let Some(c) = cfg.denoiser.conditioning.as_mut() else {
            bail!(
                "{}: [model] views, but the model is unconditional",
                config_path.display()
            );
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
    cfg.denoiser.validate().with_context(|| {
        format!(
            "{}: [model] gives an invalid denoiser",
            config_path.display()
        )
    })?;
    Ok(cfg)
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
    let at = || format!("{}: [model] {which}_encoder", config_path.display());
    let kind: Option<EncoderKind> = match kind {
        Some(k) => Some(
            k.parse()
                .map_err(|e: String| anyhow::anyhow!("{}: {e}", at()))?,
        ),
        None => current.map(|c| c.kind),
    };
    let Some(kind) = kind else {
        if weights.is_some() {
            bail!("{}: `{which}_weights` without an encoder", at());
        }
        return Ok(None);
    };
    if !kind.is_pretrained() {
        if weights.is_some() {
            bail!(
                "{}: a small-cnn is trained here; `{which}_weights` is for pretrained kinds",
                at()
            );
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
        bail!(
            "{}: `{kind}` needs `{which}_weights`, the path of `model.safetensors` from {}",
            at(),
            kind.hub_repo().unwrap_or("-")
        );
    };
    let bytes = std::fs::read(path).with_context(|| {
        format!(
            "{}: cannot read {} (download `model.safetensors` of {} from the Hugging Face Hub)",
            at(),
            path.display(),
            kind.hub_repo().unwrap_or("-")
        )
    })?;
    // check it now rather than after the data is loaded
    kind.load_pretrained(
        &bytes,
        path,
        candle_core::DType::F32,
        &candle_core::Device::Cpu,
    )
    .with_context(at)?;
    let path = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
    Ok(Some(EncoderSpec::pretrained(
        kind,
        path,
        Some(sha256_hex(&bytes)),
    )))
}

struct Progress {
    bar: indicatif::ProgressBar,
    ema_loss: Option<f64>,
    stop_after: Option<u64>,
    /// Steps run by this invocation, over all stages.
    run: std::rc::Rc<std::cell::Cell<u64>>,
    stage: Stage,
    /// `OUTPUT/train_log.jsonl`, appended to (a resumed run continues it).
    log: std::rc::Rc<TrainLog>,
}

/// `OUTPUT/train_log.jsonl`: one JSON object per update (stage, step, loss, learning rate,
/// samples/s), flushed per line, so a killed run keeps every step it logged.
struct TrainLog {
    path: PathBuf,
    file: std::cell::RefCell<std::io::LineWriter<std::fs::File>>,
    failed: std::cell::Cell<bool>,
}

/// The log file's name inside `[output] dir`.
const TRAIN_LOG: &str = "train_log.jsonl";

impl TrainLog {
    fn open(path: PathBuf) -> Result<Self> {
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .with_context(|| format!("{}: cannot open the training log", path.display()))?;
        Ok(TrainLog {
            path,
            file: std::cell::RefCell::new(std::io::LineWriter::new(file)),
            failed: std::cell::Cell::new(false),
        })
    }

    fn step(&self, stage: Stage, s: &StepStats) {
        use std::io::Write;
        let line = serde_json::json!({
            "stage": match stage {
                Stage::Mean => "mean",
                Stage::Denoiser => "denoiser",
            },
            "step": s.step,
            "loss": s.loss.is_finite().then_some(s.loss),
            "lr": s.lr,
            "samples_per_s": s.samples_per_sec,
            "step_s": s.step_secs,
        });
        if writeln!(self.file.borrow_mut(), "{line}").is_err() && !self.failed.replace(true) {
            tracing::warn!("{}: cannot write the training log", self.path.display());
        }
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        self.bar.finish_and_clear();
    }
}

impl<M: veila_diffusion::Denoiser> TrainObserver<M> for Progress {
    fn on_step(&mut self, s: &StepStats) -> ControlFlow<()> {
        if s.loss.is_finite() {
            self.ema_loss = Some(match self.ema_loss {
                None => s.loss,
                Some(e) => 0.98 * e + 0.02 * s.loss,
            });
        }
        self.run.set(self.run.get() + 1);
        self.log.step(self.stage, s);
        self.bar.set_position(s.step);
        self.bar.set_message(format!(
            "loss {:.4} (avg {:.4}) lr {:.2e} {:.2} s/step",
            s.loss,
            self.ema_loss.unwrap_or(f64::NAN),
            s.lr,
            s.step_secs
        ));
        match self.stop_after {
            Some(n) if self.run.get() >= n => ControlFlow::Break(()),
            _ => ControlFlow::Continue(()),
        }
    }
}

fn stage_name(stage: Stage) -> &'static str {
    match stage {
        Stage::Mean => "mean network",
        Stage::Denoiser => "denoiser",
    }
}

fn print_denoiser_summary(d: &veila_diffusion::app::DenoiserFitOutcome, steps: u64, secs: f64) {
    let s = &d.summary;
    println!(
        "  denoiser: {} steps this run (now at {} of {steps}), mean loss {}, {} skipped, {secs:.1} s",
        s.steps_run,
        s.final_step,
        s.mean_loss_text(),
        s.skipped
    );
}

fn encoder_name(which: Encoder) -> &'static str {
    match which {
        Encoder::Semantic => "semantic",
        Encoder::Depth => "depth",
    }
}

pub(crate) fn run(args: TrainArgs) -> Result<()> {
    let t_all = Instant::now();
    let file = read_config(&args.config)?;
    let mut cfg = bundle_config(&file, &args.config)?;
    let device = model::device()?;
    let t = &file.train;
    if t.precision == Precision::Bf16 && device.is_cpu() {
        eprintln!(
            "note: precision = \"bf16\" on the CPU runs slower than f32 (candle's CPU backend has \
             no bf16 convolution or matrix kernels); it is meant for GPUs (--device cuda)"
        );
    }
    // data-parallel when a launcher (torchrun, srun) started several of us
    let group = ProcessGroup::from_env()?;
    let parallel = if group.world_size > 1 {
        if t.batch < group.world_size {
            bail!(
                "{}: [train] batch {} is smaller than the {} ranks (the batch is the global one, shared by the ranks)",
                args.config.display(),
                t.batch,
                group.world_size
            );
        }
        let tcp = crate::dist::TcpGroup::connect(&group, std::time::Duration::from_secs(300))?;
        // on GPUs of an NCCL build the gradients go over NCCL (the TCP group only bootstraps it)
        #[cfg(feature = "nccl")]
        let comm: Box<dyn veila_diffusion::trainer::distributed::Communicator> = if device.is_cuda()
        {
            let mut tcp = tcp;
            Box::new(crate::dist_nccl::NcclGroup::connect(&device, &mut tcp)?)
        } else {
            Box::new(tcp)
        };
        #[cfg(not(feature = "nccl"))]
        let comm: Box<dyn veila_diffusion::trainer::distributed::Communicator> = Box::new(tcp);
        eprintln!(
            "train: rank {} of {} (local rank {})",
            group.rank, group.world_size, group.local_rank
        );
        Some(Parallel::new(group.clone(), comm)?)
    } else {
        None
    };

    // 1. data
    let shards = &file.data.shards;
    let manifest_path = shards.join("manifest.json");
    if !manifest_path.exists() {
        bail!(
            "{}: no manifest.json: [data] shards must be a folder written by `cargo xtask convert`",
            shards.display()
        );
    }
    let manifest = Manifest::read(&manifest_path)?;
    if manifest.count == 0 {
        bail!("{}: the manifest lists no samples", manifest_path.display());
    }
    if file.data.verify {
        manifest.verify(shards)?;
    }
    let want = file
        .data
        .max_frames
        .unwrap_or(manifest.count)
        .min(manifest.count);
    // the camera is needed by conditional models and to train encoders
    let needs_camera = cfg.denoiser.conditioning.is_some()
        || (file.model.encoders_from.is_none()
            && (cfg.semantic_encoder.is_some() || cfg.depth_encoder.is_some()));
    let conditional = cfg.denoiser.conditioning.is_some();
    let mut prepared: Vec<Prepared> = Vec::new();
    let mut stream: Option<Arc<dyn ExampleSource>> = None;
    let mut first_has_labels = false;
    if file.data.stream {
        let source = ShardSource::new(
            shards,
            &manifest,
            want,
            &cfg,
            needs_camera,
            conditional,
            file.data.unify_cameras,
        )?;
        first_has_labels = source.first_sample()?.train_ids.is_some();
        stream = Some(Arc::new(source));
    } else {
        let projector = Projector::new(&cfg.denoiser.sensor, ProjectionOptions::default())?;
        let shard_rays = RayTable::new(&manifest.sensor)?;
        let bar = progress::bar(want as u64, "loading");
        prepared.reserve(want);
        'outer: for entry in &manifest.shards {
            let path = shards.join(&entry.file);
            let shard = read_shard(&path)?;
            if shard.sensor != manifest.sensor {
                bail!(
                    "{}: the shard's sensor differs from the manifest's",
                    path.display()
                );
            }
            for s in &shard.samples {
                if prepared.len() == want {
                    break 'outer;
                }
                prepared.push(prepare_sample(
                    s,
                    &shard.sensor,
                    &shard_rays,
                    &cfg,
                    &projector,
                    &path,
                    needs_camera,
                )?);
                bar.inc(1);
            }
        }
        bar.finish_and_clear();
        if conditional && file.data.unify_cameras {
            let first = prepared[0].camera;
            for p in &mut prepared {
                p.camera = first;
            }
        }
    }
    let samples = stream.as_ref().map_or(prepared.len(), |s| s.len());
    println!(
        "train: {} samples from {}{} ({} sensor {}x{} -> model grid {}x{}), model `{}`",
        samples,
        shards.display(),
        if stream.is_some() {
            format!(", streamed (prefetch {})", file.data.prefetch)
        } else {
            String::new()
        },
        manifest.dataset,
        manifest.sensor.rows,
        manifest.sensor.cols,
        cfg.denoiser.sensor.rows,
        cfg.denoiser.sensor.cols,
        cfg.name
    );

    // 2. resumability: the run's fingerprint
    let out = &file.output.dir;
    let ck_dir = out.join("checkpoints");
    std::fs::create_dir_all(&ck_dir)
        .with_context(|| format!("{}: cannot create", ck_dir.display()))?;
    let manifest_bytes = std::fs::read(&manifest_path)
        .with_context(|| format!("{}: cannot read", manifest_path.display()))?;
    let fingerprint = RunFingerprint {
        bundle: cfg.clone(),
        train: serde_json::to_value(t)?,
        data_manifest_sha256: sha256_hex(&manifest_bytes),
        samples,
        encoders_from: file
            .model
            .encoders_from
            .as_ref()
            .map(|p| p.display().to_string()),
    };
    // one writer per run folder; a killed earlier run's partial files go, checkpoints stay
    let _run_lock = if group.is_main() {
        Some(crate::staging::lock_train_run(out, &ck_dir)?)
    } else {
        None
    };
    if group.is_main() {
        veila_diffusion::claim_checkpoint_dir(&ck_dir, &fingerprint).with_context(|| {
            format!(
                "{}: model, [train] or data changed since these checkpoints; use another [output] dir",
                out.display()
            )
        })?;
    }
    if let Some(p) = &parallel {
        // the others wait for rank 0's claim (and learn whether it failed: a zero sum)
        let mut ok = [1f32];
        p.communicator().all_reduce_sum(&mut ok)?;
        if ok[0] < group.world_size as f32 {
            bail!("rank {}: another rank failed to start", group.rank);
        }
    }

    // 3. encoders and 4. networks: the shared recipe
    let settings = RecipeSettings {
        seed: t.seed,
        steps: t.steps,
        mean_steps: t.mean_steps,
        batch: t.batch,
        lr: t.lr,
        ema_decay: t.ema_decay,
        cond_drop_prob: t.cond_drop_prob.unwrap_or(0.1),
        checkpoint_every: t.checkpoint_every,
        keep_checkpoints: t.keep_checkpoints,
        encoder_steps: t.encoder_steps,
        encoder_batch: t.encoder_batch,
        encoder_lr: t.encoder_lr,
        grad_accum_steps: t.grad_accum_steps,
        encoder_augment: t.encoder_augment,
        precision: t.precision,
    };
    let mean_steps = settings.mean_steps();
    let enc_dir = ck_dir.join(ENCODER_DIR);
    let images: Vec<Vec<u8>> = prepared.iter().map(|p| p.rgb.clone()).collect();
    let depths: Vec<Vec<f32>> = prepared.iter().map(|p| p.depth_m.clone()).collect();
    let cameras: Vec<veila_geom::PinholeCamera> = prepared.iter().map(|p| p.camera).collect();
    let labels: Option<Vec<Vec<u32>>> = prepared.iter().map(|p| p.labels.clone()).collect();
    let encoders = match &file.model.encoders_from {
        Some(dir) => EncoderSource::Bundle(dir),
        None => {
            if cfg
                .semantic_encoder
                .as_ref()
                .is_some_and(|e| e.small_cnn_config().is_some())
                && (if stream.is_some() {
                    !first_has_labels
                } else {
                    labels.is_none()
                })
            {
                bail!(
                    "{}: the shards carry no semantic train ids (`label`), so the semantic encoder cannot be trained: \
                     convert with a label map (SemanticKITTI) or set [model] encoders_from = \"models/default\"",
                    shards.display()
                );
            }
            EncoderSource::Train {
                data: match &stream {
                    Some(source) => EncoderData::Stream(source),
                    None => EncoderData::Memory {
                        images: &images,
                        labels: labels.as_deref(),
                        depth_m: &depths,
                        cameras: Some(&cameras),
                    },
                },
                dir: &enc_dir,
            }
        }
    };
    let examples: Vec<TrainExample> = prepared
        .into_iter()
        .map(|p| TrainExample {
            rgb: p.rgb,
            camera: p.camera,
            x0: p.x0,
            extra_views: p.extra_views,
        })
        .collect();
    let t_den = Instant::now();
    let mut encoder_note = String::new();
    let mut enc_bar: Option<indicatif::ProgressBar> = None;
    let run = std::rc::Rc::new(std::cell::Cell::new(0u64));
    let log_path = if group.is_main() {
        out.join(TRAIN_LOG)
    } else {
        out.join(format!("train_log.rank-{}.jsonl", group.rank))
    };
    let log = std::rc::Rc::new(TrainLog::open(log_path)?);
    let outcome = run_recipe(
        &mut cfg,
        RecipeInput {
            encoders,
            examples: match &stream {
                Some(source) => Examples::Stream {
                    source,
                    prefetch: file.data.prefetch.max(1),
                },
                None => (&examples).into(),
            },
            work_dir: &ck_dir,
            init: None,
            mean_init: None,
            parallel: parallel.as_ref(),
        },
        &settings,
        &device,
        |event| match event {
            EncoderEvent::Reused(which, _) => {
                encoder_note.push_str(&format!("{} resumed; ", encoder_name(which)))
            }
            EncoderEvent::Step(which, s, total) => {
                let bar =
                    enc_bar.get_or_insert_with(|| progress::bar(total as u64, encoder_name(which)));
                bar.set_position(s.step as u64);
                bar.set_message(format!("loss {:.4}", s.loss));
            }
            EncoderEvent::Trained(which, last) => {
                if let Some(bar) = enc_bar.take() {
                    bar.finish_and_clear();
                }
                encoder_note.push_str(&format!(
                    "{}: final batch loss {last:.4}; ",
                    encoder_name(which)
                ));
            }
        },
        |stage, p, step| {
            println!(
                "  {}: resumed from {} (step {step})",
                stage_name(stage),
                p.display()
            )
        },
        |stage, total| Progress {
            bar: progress::bar(total, stage_name(stage)),
            ema_loss: None,
            stop_after: args.stop_after,
            run: run.clone(),
            stage,
            log: log.clone(),
        },
    )
    .with_context(|| match &file.model.encoders_from {
        Some(dir) => format!("[model] encoders_from: loading {}", dir.display()),
        None => format!("training with checkpoints in {}", ck_dir.display()),
    })?;
    if let Some(dir) = &file.model.encoders_from {
        encoder_note = format!("from {}", dir.display());
    }
    let enc_secs = outcome.encoder_seconds;
    if !encoder_note.is_empty() {
        println!("  encoders: {}", encoder_note.trim_end_matches("; "));
    }
    let den_secs = t_den.elapsed().as_secs_f64() - enc_secs;
    if let Some(m) = &outcome.fit.mean {
        println!(
            "  mean network: {} steps this run (now at {} of {mean_steps}), mean loss {}, {:.1} s",
            m.summary.steps_run,
            m.summary.final_step,
            m.summary.mean_loss_text(),
            outcome.fit.seconds[0]
        );
    }
    let den = match &outcome.fit.denoiser {
        Some(d) if d.step >= t.steps => d,
        Some(d) => {
            print_denoiser_summary(d, t.steps, outcome.fit.seconds[1]);
            println!(
                "stopped at step {} of {}; checkpoint in {}: rerun `veila train --config {}` to continue",
                d.step,
                t.steps,
                ck_dir.display(),
                args.config.display()
            );
            return Ok(());
        }
        None => {
            let at = outcome.fit.mean.as_ref().map_or(0, |m| m.step);
            println!(
                "stopped the mean network at step {at} of {mean_steps}; checkpoint in {}: rerun `veila train --config {}` to continue",
                ck_dir.join("mean").display(),
                args.config.display()
            );
            return Ok(());
        }
    };
    print_denoiser_summary(den, t.steps, outcome.fit.seconds[1]);
    if !group.is_main() {
        println!("rank {}: done; rank 0 writes the bundle", group.rank);
        return Ok(());
    }
    let summary = den.summary.clone();
    let weights = outcome.into_weights();

    // 5. the bundle
    cfg.provenance = serde_json::json!({
        "trained_by": "veila train",
        "config": args.config.display().to_string(),
        "data": shards.display().to_string(),
        "dataset": manifest.dataset,
        "data_manifest_sha256": fingerprint.data_manifest_sha256,
        "samples": fingerprint.samples,
        "encoders_from": fingerprint.encoders_from,
        "train": fingerprint.train,
        "ranks": group.world_size,
        "final_mean_loss_this_run": summary.mean_loss,
        "seconds_this_run": {
            "encoders": enc_secs.round(),
            "denoiser": den_secs.round(),
        },
    });
    let bundle_dir = out.join("bundle");
    Bundle::save(&bundle_dir, &cfg, &weights)?;
    Bundle::from_dir(&bundle_dir, &device)
        .with_context(|| format!("re-reading {}", bundle_dir.display()))?;
    println!(
        "wrote {} in {:.0} s ({} denoiser parameters); generate with `veila generate --checkpoint {} ...`",
        bundle_dir.display(),
        t_all.elapsed().as_secs_f64(),
        veila_nn::checkpoint::parameter_count(&cfg.denoiser)?,
        bundle_dir.display()
    );
    if let Some(mib) = peak_host_mib() {
        println!("peak host memory: {mib:.0} MiB");
    }
    Ok(())
}

/// The process's peak resident set (`VmHWM` of `/proc/self/status`, Linux) in MiB.
fn peak_host_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(model: &str) -> Result<BundleConfig> {
        let text = format!(
            "[data]\nshards = \"shards\"\n\n[model]\n{model}\n\n[train]\n\n[output]\ndir = \"out\"\n"
        );
        let file: TrainFile = toml::from_str(&text)?;
        bundle_config(&file, Path::new("train.toml"))
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
        let plain = config("").unwrap();
        assert_eq!(config("depth_features = false").unwrap(), plain);
        let on = config("depth_features = true").unwrap();
        let widened: Vec<usize> = depth_channels(&plain).iter().map(|c| c + 1).collect();
        assert_eq!(depth_channels(&on), widened);
        let mean = on.residual.as_ref().unwrap().mean_net.conditioning.as_ref();
        assert_eq!(mean.unwrap().depth_channels, widened);
        // a model without a depth encoder cannot have it
        let err = config("variant = \"semantic-only\"\ndepth_features = true")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("train.toml") && err.contains("depth_features"),
            "{err}"
        );
    }
}
