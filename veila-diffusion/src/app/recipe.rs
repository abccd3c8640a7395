//! The one training recipe of a bundle, run by both `veila train` (on converted shards) and
//! `cargo xtask train-default` (on simulator frames). Its five stages:
//!
//! 1. the semantic encoder `E_s` and 2. the depth encoder `E_d`, each trained on sparse LiDAR
//!    supervision ([`super::encoder_train::train_small_cnn`]) or taken from another bundle ([`prepare_encoders`]);
//! 3. for residual bundles the mean network (one-pass regression), 4. its predictions of every
//!    example and the residual scale, 5. the denoiser on the frozen encoder features
//!    ([`fit_bundle`]).
//!
//! The binaries only read their data, claim their checkpoint folder, draw progress and write the
//! provenance; the settings ([`RecipeSettings`]) turn into the same [`TrainConfig`]s for both.
//! Every stage is seeded and resumable: trained encoders are kept in a folder and reused, the
//! networks resume from their newest checkpoint.

use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

use candle_core::{DType, Device, Tensor};
use veila_geom::PinholeCamera;
use veila_nn::encoders::kind::AnyEncoder;
use veila_nn::encoders::small_cnn::{SmallCnn, SmallCnnConfig};

use super::bundle::{
    Bundle, BundleConfig, DENOISER_FILE, DEPTH_FILE, EncoderSpec, MEAN_FILE, SEMANTIC_FILE,
};
use super::dataset::{EncoderExample, ExampleSource, Examples};
use super::encoder_train::{EncoderStep, train_small_cnn_from, varmap_tensors};
use super::nn::VeilaDenoiser;
use super::stage::Stage;
use super::train::{BundleFit, BundleFitOutcome, fit_bundle};
use crate::error::{Error, Result};
use crate::trainer::{TrainConfig, TrainObserver};

/// The settings of one run of the recipe.
#[derive(Debug, Clone, PartialEq)]
pub struct RecipeSettings {
    /// Seed of everything (the encoders use `seed ^ 0x5e` and `seed ^ 0xde`, the mean network
    /// `seed ^ 0x3ea`).
    pub seed: u64,
    /// Denoiser updates.
    pub steps: u64,
    /// Mean-network updates of residual bundles (`None`: `steps`).
    pub mean_steps: Option<u64>,
    /// Examples per update (both networks).
    pub batch: usize,
    /// Peak learning rate (both networks; warm-up over 5% of the steps, cosine to 5%).
    pub lr: f64,
    /// EMA decay of the shipped weights.
    pub ema_decay: f64,
    /// Condition dropout of conditional models (classifier-free guidance).
    pub cond_drop_prob: f64,
    /// Updates between checkpoints.
    pub checkpoint_every: u64,
    /// Checkpoints kept.
    pub keep_checkpoints: usize,
    /// Updates of each encoder.
    pub encoder_steps: usize,
    /// Images per encoder update.
    pub encoder_batch: usize,
    /// Peak learning rate of the encoders.
    pub encoder_lr: f64,
    /// Gradient accumulation of the denoiser and the mean network: each update runs its batch in
    /// this many parts ([`TrainConfig::grad_accum_steps`]; 1: none).
    pub grad_accum_steps: u64,
    /// Image augmentation of the encoders' training (`None`: the images as they are).
    pub encoder_augment: Option<super::encoder_train::EncoderAugment>,
    /// The activations' precision of the denoiser's and the mean network's training
    /// ([`TrainConfig::precision`]; the encoders train in f32).
    pub precision: crate::trainer::Precision,
    /// Activation checkpointing of the denoiser's and the mean network's training
    /// ([`TrainConfig::activation_checkpointing`]).
    pub activation_checkpointing: crate::trainer::ActivationCheckpointing,
}

impl RecipeSettings {
    /// Mean-network updates.
    pub fn mean_steps(&self) -> u64 {
        self.mean_steps.unwrap_or(self.steps)
    }

    /// The trainer settings of the denoiser and of the mean network, for a conditional model or
    /// not (unconditional models drop no condition).
    pub fn train_configs(&self, conditional: bool) -> (TrainConfig, TrainConfig) {
        let tc = TrainConfig {
            seed: self.seed,
            lr: self.lr,
            min_lr: self.lr * 0.05,
            warmup_steps: (self.steps / 20).max(1),
            total_steps: self.steps,
            ema_decay: self.ema_decay,
            cond_drop_prob: if conditional {
                self.cond_drop_prob
            } else {
                0.0
            },
            checkpoint_every: Some(self.checkpoint_every.max(1)),
            keep_checkpoints: Some(self.keep_checkpoints.max(1)),
            grad_accum_steps: self.grad_accum_steps.max(1),
            precision: self.precision,
            activation_checkpointing: self.activation_checkpointing,
            ..TrainConfig::default()
        };
        let mean_steps = self.mean_steps();
        let mean_tc = TrainConfig {
            seed: self.seed ^ 0x3ea,
            total_steps: mean_steps,
            warmup_steps: (mean_steps / 20).max(1),
            ..tc.clone()
        };
        (tc, mean_tc)
    }
}

/// One of the two image encoders.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoder {
    /// `E_s`.
    Semantic,
    /// `E_d`.
    Depth,
}

impl Encoder {
    /// Its weight file in a bundle.
    pub fn file(self) -> &'static str {
        match self {
            Encoder::Semantic => SEMANTIC_FILE,
            Encoder::Depth => DEPTH_FILE,
        }
    }

    /// Its name in progress lines: `semantic` or `depth`.
    pub fn name(self) -> &'static str {
        match self {
            Encoder::Semantic => "semantic",
            Encoder::Depth => "depth",
        }
    }

    /// Its field in `bundle.json`.
    pub fn field(self) -> &'static str {
        match self {
            Encoder::Semantic => "semantic_encoder",
            Encoder::Depth => "depth_encoder",
        }
    }

    fn salt(self) -> u64 {
        match self {
            Encoder::Semantic => 0x5e,
            Encoder::Depth => 0xde,
        }
    }

    fn config(self, config: &BundleConfig) -> Option<&EncoderSpec> {
        match self {
            Encoder::Semantic => config.semantic_encoder.as_ref(),
            Encoder::Depth => config.depth_encoder.as_ref(),
        }
    }
}

/// What the encoders train on: the examples' images at the bundle's image size with sparse
/// targets of the same size.
#[derive(Clone, Copy)]
pub enum EncoderData<'a> {
    /// In memory.
    Memory {
        /// RGB bytes, `image_width * image_height * 3` each.
        images: &'a [Vec<u8>],
        /// Train ids (0 = ignored) per pixel; needed by a semantic encoder.
        labels: Option<&'a [Vec<u32>]>,
        /// Metric depth (0 = no ground truth) per pixel.
        depth_m: &'a [Vec<f32>],
        /// Each image's camera; needed by an encoder with the ground prior.
        cameras: Option<&'a [PinholeCamera]>,
    },
    /// Read on demand, batch by batch ([`ExampleSource::encoder_example`]).
    Stream(&'a Arc<dyn ExampleSource>),
}

impl std::fmt::Debug for EncoderData<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            EncoderData::Memory { images, labels, .. } => write!(
                f,
                "EncoderData::Memory({} images, labels: {})",
                images.len(),
                labels.is_some()
            ),
            EncoderData::Stream(s) => write!(f, "EncoderData::Stream({} examples)", s.len()),
        }
    }
}

/// Where the encoders of a run come from.
#[derive(Debug, Clone, Copy)]
pub enum EncoderSource<'a> {
    /// The encoders of this bundle folder (same image size and encoder configs).
    Bundle(&'a Path),
    /// Trained on `data`; the weights are kept in `dir` and a rerun reuses them (their training
    /// is deterministic, so it would give the same weights).
    Train {
        /// The training data.
        data: EncoderData<'a>,
        /// Folder of the trained weights.
        dir: &'a Path,
    },
}

/// What the encoder stages report.
#[derive(Debug, Clone, Copy)]
pub enum EncoderEvent<'a> {
    /// Weights trained by an earlier run were found and reused.
    Reused(Encoder, &'a Path),
    /// One training step of `total`.
    Step(Encoder, EncoderStep, usize),
    /// Training finished; the loss of the last batch.
    Trained(Encoder, f32),
}

/// The frozen encoders of a run and their weights by bundle file name.
#[derive(Debug, Default)]
pub struct Encoders {
    /// `E_s`.
    pub semantic: Option<AnyEncoder>,
    /// `E_d`.
    pub depth: Option<AnyEncoder>,
    /// Weights of the small CNNs by bundle file name (what [`Bundle::save`] takes; pretrained
    /// encoders stay in their own files).
    pub weights: HashMap<&'static str, HashMap<String, Tensor>>,
}

/// A small CNN saved at `path` (a bundle's encoder file, or one this recipe wrote), with its
/// weights by name (what [`Bundle::save`] takes). Read once, as a bundle's weights are: a regular
/// file under veila-nn's cap, checked before reading, then its tensors against the network of `c`
/// (names and shapes, a float dtype, finite, within `MAX_ABS_WEIGHT`) before any is made.
fn read_cnn(
    c: &SmallCnnConfig,
    path: &Path,
    device: &Device,
) -> Result<(SmallCnn, HashMap<String, Tensor>)> {
    let bytes = veila_nn::checkpoint::read_weights_file(path)?;
    let expected = veila_nn::checkpoint::record_tensors(|vb| SmallCnn::new(c, vb).map(drop))?;
    // any float dtype, as a bundle's own encoder files (`load_checked_bytes`), loaded as f32
    let tensors = veila_nn::checkpoint::read_checked_float_bytes(
        &bytes,
        path,
        &expected,
        DType::F32,
        device,
    )?;
    let net = SmallCnn::new(
        c,
        candle_nn::VarBuilder::from_tensors(tensors.clone(), DType::F32, device),
    )?;
    Ok((net, tensors))
}

/// Stages 1 and 2: the encoders `config` asks for, semantic first. Pretrained encoders are read
/// from the files their specs name (paths relative to the working directory); small CNNs come
/// from `source`.
pub fn prepare_encoders(
    config: &BundleConfig,
    source: EncoderSource<'_>,
    settings: &RecipeSettings,
    device: &Device,
    mut on_event: impl FnMut(EncoderEvent<'_>),
) -> Result<Encoders> {
    let mut out = Encoders::default();
    let put = |out: &mut Encoders, which: Encoder, net: AnyEncoder| match which {
        Encoder::Semantic => out.semantic = Some(net),
        Encoder::Depth => out.depth = Some(net),
    };
    let mut small = Vec::new();
    for which in [Encoder::Semantic, Encoder::Depth] {
        let Some(spec) = which.config(config) else {
            continue;
        };
        match spec.small_cnn_config() {
            Some(c) => small.push((which, c)),
            None => {
                // the run's own config names pretrained weights by an absolute path (a training
                // config's, resolved when it was read)
                let net = match spec.weights.as_deref() {
                    Some(w) if w.is_absolute() => spec.load_at(w, which.field(), device)?,
                    _ => spec.load(Path::new("."), which.field(), device)?,
                };
                put(&mut out, which, net);
            }
        }
    }
    if let EncoderSource::Bundle(dir) = source {
        if small.is_empty() {
            return Ok(out);
        }
        let b = Bundle::from_dir(dir, device)?;
        if b.config.image_height != config.image_height
            || b.config.image_width != config.image_width
        {
            return Err(Error::Checkpoint {
                reason: format!(
                    "its encoders take {}x{} images, this model {}x{}",
                    b.config.image_width,
                    b.config.image_height,
                    config.image_width,
                    config.image_height
                ),
                path: dir.to_path_buf(),
            });
        }
        // the depth channel changes what the encoder returns, not its weights
        let weights_of = |c: &SmallCnnConfig| SmallCnnConfig {
            depth_features: false,
            ..c.clone()
        };
        for (which, c) in small {
            if which
                .config(&b.config)
                .and_then(|s| s.small_cnn_config())
                .map(weights_of)
                != Some(weights_of(c))
            {
                return Err(Error::Checkpoint {
                    reason: format!(
                        "its {} does not match this model's encoder config",
                        which.file()
                    ),
                    path: dir.to_path_buf(),
                });
            }
            let path = dir.join(which.file());
            let (net, tensors) = read_cnn(c, &path, device)?;
            out.weights.insert(which.file(), tensors);
            put(&mut out, which, net.into());
        }
        return Ok(out);
    }
    let EncoderSource::Train { data, dir } = source else {
        return Ok(out);
    };
    let hw = (config.image_height, config.image_width);
    for (which, c) in small {
        let saved = dir.join(which.file());
        // anything at the path is reused and so checked (a link to a device or a FIFO is refused
        // by the weights reader, never trained over)
        let (net, tensors) = if saved.symlink_metadata().is_ok() {
            on_event(EncoderEvent::Reused(which, &saved));
            read_cnn(c, &saved, device)?
        } else {
            if let EncoderData::Memory { labels: None, .. } = data
                && c.semantic_head
            {
                return Err(Error::Data(
                    "the semantic encoder needs per-pixel train ids: the data has none".into(),
                ));
            }
            if let EncoderData::Memory { cameras: None, .. } = data
                && c.ground_prior.is_some()
            {
                return Err(Error::Data(format!(
                    "the {} takes the ground prior, which needs each training image's camera: the data has none",
                    which.field()
                )));
            }
            let get_memory;
            let get_stream;
            let (n, get): (usize, &dyn Fn(usize) -> Result<EncoderExample>) = match data {
                EncoderData::Memory {
                    images,
                    labels,
                    depth_m,
                    cameras,
                } => {
                    if let Some(cams) = cameras
                        && cams.len() != images.len()
                    {
                        return Err(Error::Data(format!(
                            "encoder training: {} images but {} cameras",
                            images.len(),
                            cams.len()
                        )));
                    }
                    get_memory = move |i: usize| -> Result<EncoderExample> {
                        Ok(EncoderExample {
                            rgb: images[i].clone(),
                            camera: cameras.map(|c| c[i]),
                            labels: labels.filter(|_| c.semantic_head).map(|l| l[i].clone()),
                            depth_m: if c.depth_head {
                                depth_m[i].clone()
                            } else {
                                Vec::new()
                            },
                        })
                    };
                    (images.len(), &get_memory)
                }
                EncoderData::Stream(source) => {
                    get_stream = move |i: usize| source.encoder_example(i);
                    (source.len(), &get_stream)
                }
            };
            let mut last = f32::NAN;
            let (net, vm) = train_small_cnn_from(
                c,
                n,
                get,
                (c.semantic_head, c.depth_head),
                hw,
                settings.encoder_steps,
                settings.encoder_batch,
                settings.encoder_lr,
                settings.seed ^ which.salt(),
                settings.encoder_augment.as_ref(),
                device,
                |s| {
                    last = s.loss;
                    on_event(EncoderEvent::Step(which, s, settings.encoder_steps));
                },
            )?;
            on_event(EncoderEvent::Trained(which, last));
            let tensors = varmap_tensors(&vm)?;
            let bytes = veila_nn::checkpoint::safetensors_bytes(&tensors, &saved)?;
            std::fs::create_dir_all(dir).map_err(|source| Error::Io {
                action: "creating the encoder folder",
                path: dir.to_path_buf(),
                source,
            })?;
            veila_data::atomic::write_atomic(&saved, &bytes)?;
            (net, tensors)
        };
        out.weights.insert(which.file(), tensors);
        put(&mut out, which, net.into());
    }
    Ok(out)
}

/// What [`run_recipe`] trains on.
#[derive(Debug, Clone, Copy)]
pub struct RecipeInput<'a> {
    /// Where the encoders come from.
    pub encoders: EncoderSource<'a>,
    /// The training examples (any cameras), in memory or streamed.
    pub examples: Examples<'a>,
    /// The networks' checkpoints: the denoiser's here, the mean network's in `mean/`.
    pub work_dir: &'a Path,
    /// Initial denoiser weights wherever names and shapes match (fine-tuning).
    pub init: Option<&'a HashMap<String, Tensor>>,
    /// Initial mean-network weights, likewise (residual bundles).
    pub mean_init: Option<&'a HashMap<String, Tensor>>,
    /// Data-parallel training with the other ranks of the run (`None`: one process). Every rank
    /// runs every stage; the encoders' and the mean network's work is repeated on each (it is
    /// deterministic), the networks' updates are shared. Only rank 0 writes checkpoints; the
    /// caller writes the bundle on rank 0 only.
    pub parallel: Option<&'a crate::trainer::distributed::Parallel>,
}

/// What [`run_recipe`] did.
#[derive(Debug)]
pub struct RecipeOutcome {
    /// The encoders (stages 1 and 2).
    pub encoders: Encoders,
    /// Seconds spent on the encoders.
    pub encoder_seconds: f64,
    /// The networks' runs (stages 3 to 5).
    pub fit: BundleFitOutcome,
}

impl RecipeOutcome {
    /// Whether every stage ran to its last step (an observer may stop a run early).
    pub fn finished(&self, settings: &RecipeSettings) -> bool {
        self.fit
            .denoiser
            .as_ref()
            .is_some_and(|d| d.step >= settings.steps)
    }

    /// Every weight file of the bundle, by file name (the EMA weights of the networks).
    pub fn into_weights(self) -> HashMap<&'static str, HashMap<String, Tensor>> {
        let mut w = self.encoders.weights;
        if let Some(m) = self.fit.mean {
            w.insert(MEAN_FILE, m.ema_weights);
        }
        if let Some(d) = self.fit.denoiser {
            w.insert(DENOISER_FILE, d.ema_weights);
        }
        w
    }
}

/// The whole recipe: encoders ([`prepare_encoders`]), then [`fit_bundle`] (which writes the
/// residual scale into `config`). `on_encoder` hears the encoder stages; `on_resume` and
/// `observer` are [`fit_bundle`]'s.
pub fn run_recipe<O>(
    config: &mut BundleConfig,
    input: RecipeInput<'_>,
    settings: &RecipeSettings,
    device: &Device,
    on_encoder: impl FnMut(EncoderEvent<'_>),
    on_resume: impl FnMut(Stage, &Path, u64),
    observer: impl FnMut(Stage, u64) -> O,
) -> Result<RecipeOutcome>
where
    O: for<'g> TrainObserver<VeilaDenoiser<'g>>,
{
    let t = std::time::Instant::now();
    let encoders =
        prepare_encoders(config, input.encoders, settings, device, on_encoder).map_err(|e| {
            match input.encoders {
                EncoderSource::Bundle(dir) => Error::EncodersFrom {
                    dir: dir.to_path_buf(),
                    source: Box::new(e),
                },
                EncoderSource::Train { .. } => e,
            }
        })?;
    let encoder_seconds = t.elapsed().as_secs_f64();
    let (tc, mean_tc) = settings.train_configs(config.denoiser.conditioning.is_some());
    let fit = fit_bundle(
        config,
        BundleFit {
            semantic: encoders.semantic.as_ref(),
            depth: encoders.depth.as_ref(),
            examples: input.examples,
            batch_size: settings.batch,
            train: &tc,
            mean_train: Some(&mean_tc),
            work_dir: input.work_dir,
            init: input.init,
            mean_init: input.mean_init,
            parallel: input.parallel,
        },
        device,
        on_resume,
        observer,
    )?;
    Ok(RecipeOutcome {
        encoders,
        encoder_seconds,
        fit,
    })
}
