//! Training a [`Bundle`](super::Bundle)'s networks on in-memory examples: the denoiser and the mean network of
//! residual diffusion ([`fit_denoiser`], with [`DenoiserTraining`] computing the frozen encoder
//! features once per example), the whole generative part of a bundle ([`fit_bundle`]), and the small
//! CNN encoders ([`train_small_cnn`]). [`super::recipe`] strings these into the one training recipe
//! the binaries share.
//!
//! Everything is seeded: the same inputs and seed give the same weights.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use veila_geom::PinholeCamera;
use veila_nn::encoders::kind::AnyEncoder;
use veila_nn::encoders::small_cnn::{SmallCnn, SmallCnnConfig, SmallCnnLossConfig};
use veila_nn::{Denoiser as Net, GcmaGeometry};

use super::bundle::{BundleConfig, ResidualConfig};
use super::generate::{CameraView, ViewFeatures, encode_views, image_tensor};
use super::nn::{NetCond, VeilaDenoiser};
use crate::error::{Error, Result};
use crate::objective::Diffusion;
use crate::sampler::{Sampler, SamplerConfig};
use crate::trainer::distributed::{Parallel, ProcessGroup};
use crate::trainer::{AdamW, Batch, FitSummary, ParamsAdamW, TrainConfig, TrainObserver, Trainer};

/// One training example: a camera image at the bundle's size, its camera, and the encoded clean
/// range image (`in_channels * rows * cols` values, row-major per channel).
#[derive(Debug, Clone)]
pub struct TrainExample {
    /// RGB bytes at the bundle image size.
    pub rgb: Vec<u8>,
    /// The camera of that image.
    pub camera: PinholeCamera,
    /// Encoded range image.
    pub x0: Vec<f32>,
}

/// Which network of a bundle a training run fits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// The denoiser (`config.denoiser` with `config.diffusion`). For a residual bundle every
    /// example needs its mean prediction ([`DenoiserFit::means`]) and the targets become the
    /// scaled residuals ([`residual_target`]).
    Denoiser,
    /// The mean network of a residual bundle (`residual.mean_net`, one-pass regression), with
    /// the range and intensity of dropped rays left out of the loss ([`regression_weight`]).
    Mean,
}

/// Per-element loss weights of a regression target: 1 on the ray-drop channel everywhere, and on
/// the range and intensity channels only where the target has a return (a dropped ray has no
/// range to predict).
pub fn regression_weight(enc: &crate::RangeEncoding, x0: &[f32], hw: usize) -> Vec<f32> {
    let c = enc.num_channels();
    let mut w = vec![1.0f32; c * hw];
    if let Some(dc) = enc.raydrop_channel() {
        for p in 0..hw {
            if x0[dc * hw + p] <= enc.raydrop_threshold {
                for ch in 0..c {
                    if ch != dc {
                        w[ch * hw + p] = 0.0;
                    }
                }
            }
        }
    }
    w
}

/// The raw residual `x₀ − μ` of residual diffusion: where the target has no return, its range and
/// intensity are taken to be the mean's (they are not decoded), so only the ray-drop channel
/// carries a residual there.
pub fn raw_residual(enc: &crate::RangeEncoding, x0: &[f32], mean: &[f32], hw: usize) -> Vec<f32> {
    let w = regression_weight(enc, x0, hw);
    x0.iter()
        .zip(mean)
        .zip(&w)
        .map(|((x, m), w)| if *w > 0.0 { x - m } else { 0.0 })
        .collect()
}

/// The training target of a residual denoiser: [`raw_residual`] divided by the per-channel scale.
pub fn residual_target(
    enc: &crate::RangeEncoding,
    x0: &[f32],
    mean: &[f32],
    scale: &[f32],
    hw: usize,
) -> Vec<f32> {
    let mut r = raw_residual(enc, x0, mean, hw);
    for (ch, s) in scale.iter().enumerate() {
        for v in &mut r[ch * hw..(ch + 1) * hw] {
            *v /= s;
        }
    }
    r
}

/// The per-channel residual scale: the root mean square of [`raw_residual`] over the examples,
/// counted on returns for range and intensity and everywhere for ray drop (at least 1e-3).
pub fn residual_scale(
    enc: &crate::RangeEncoding,
    x0: &[Vec<f32>],
    means: &[Vec<f32>],
    hw: usize,
) -> Vec<f32> {
    let c = enc.num_channels();
    let mut sum = vec![0f64; c];
    let mut count = vec![0f64; c];
    for (x, m) in x0.iter().zip(means) {
        let w = regression_weight(enc, x, hw);
        let r = raw_residual(enc, x, m, hw);
        for ch in 0..c {
            for p in ch * hw..(ch + 1) * hw {
                if w[p] > 0.0 {
                    sum[ch] += f64::from(r[p]) * f64::from(r[p]);
                    count[ch] += 1.0;
                }
            }
        }
    }
    (0..c)
        .map(|ch| ((sum[ch] / count[ch].max(1.0)).sqrt() as f32).max(1e-3))
        .collect()
}

/// Training state of one network of a bundle on in-memory examples: frozen encoder features
/// computed once, one GCMA geometry for the rig (all examples must share the camera), the targets
/// (and for residual diffusion the mean predictions and for regression the loss weights) as
/// tensors, batches drawn by a seeded shuffle that is a pure function of the step (so resumed
/// runs match uninterrupted ones).
#[derive(Debug)]
pub struct DenoiserTraining {
    features: Vec<ViewFeatures>,
    x0: Vec<Tensor>,
    means: Option<Vec<Tensor>>,
    weights: Option<Vec<Tensor>>,
    geometry: Option<GcmaGeometry>,
    batch_size: usize,
    seed: u64,
    shard: Option<ProcessGroup>,
}

impl DenoiserTraining {
    /// Computes the frozen features of every example. `net` is the network being trained (its
    /// config decides the cues and the geometry); `stage` and `means` decide the targets (see
    /// [`Stage`]).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        config: &BundleConfig,
        semantic: Option<&AnyEncoder>,
        depth: Option<&AnyEncoder>,
        net: &Net,
        examples: &[TrainExample],
        stage: Stage,
        means: Option<&[Vec<f32>]>,
        batch_size: usize,
        seed: u64,
        device: &Device,
    ) -> Result<Self> {
        if examples.is_empty() || batch_size == 0 {
            return Err(Error::Data(
                "training needs at least one example and a batch size of at least 1".into(),
            ));
        }
        let (h, w) = (config.denoiser.height(), config.denoiser.width());
        let c = config.channels();
        let camera = examples[0].camera;
        let conditional = net.is_conditional();
        let residual = match (stage, &config.residual) {
            (Stage::Denoiser, Some(r)) => {
                let m = means.ok_or_else(|| {
                    Error::Data(
                        "a residual denoiser trains on the mean network's predictions: pass them"
                            .into(),
                    )
                })?;
                if m.len() != examples.len() {
                    return Err(Error::Data(format!(
                        "{} mean predictions for {} examples",
                        m.len(),
                        examples.len()
                    )));
                }
                Some((m, r.scale.clone()))
            }
            (Stage::Mean, None) => {
                return Err(Error::Data(
                    "this bundle has no mean network (not residual diffusion)".into(),
                ));
            }
            _ => None,
        };
        let mut features = Vec::with_capacity(examples.len());
        let mut x0 = Vec::with_capacity(examples.len());
        let mut mean_t = Vec::new();
        let mut weights = Vec::new();
        for (i, ex) in examples.iter().enumerate() {
            if ex.x0.len() != c * h * w {
                return Err(Error::Shape {
                    what: "training example",
                    expected: format!("{c} x {h} x {w} values"),
                    got: format!("example {i}: {} values", ex.x0.len()),
                });
            }
            if ex.camera != camera && conditional {
                return Err(Error::Data(format!(
                    "example {i} has another camera than example 0; one training run takes one camera rig"
                )));
            }
            match &residual {
                Some((m, scale)) => {
                    let mi = &m[i];
                    if mi.len() != c * h * w {
                        return Err(Error::Shape {
                            what: "mean prediction",
                            expected: format!("{c} x {h} x {w} values"),
                            got: format!("example {i}: {} values", mi.len()),
                        });
                    }
                    let r = residual_target(&config.encoding, &ex.x0, mi, scale, h * w);
                    x0.push(Tensor::from_vec(r, (1, c, h, w), device)?);
                    mean_t.push(Tensor::from_slice(mi, (1, c, h, w), device)?);
                }
                None => x0.push(Tensor::from_slice(&ex.x0, (1, c, h, w), device)?),
            }
            if stage == Stage::Mean {
                let wt = regression_weight(&config.encoding, &ex.x0, h * w);
                weights.push(Tensor::from_vec(wt, (1, c, h, w), device)?);
            }
            if conditional {
                let view = CameraView {
                    rgb: &ex.rgb,
                    camera: &ex.camera,
                };
                features.push(encode_views(config, semantic, depth, &[view], device)?);
            }
        }
        let geometry = match &net.config().conditioning {
            Some(cc) if cc.gcma.is_some() => {
                Some(net.geometry(&[camera], &config.epipolar, device)?)
            }
            _ => None,
        };
        Ok(Self {
            features,
            x0,
            means: residual.is_some().then_some(mean_t),
            weights: (stage == Stage::Mean).then_some(weights),
            geometry,
            batch_size,
            seed,
            shard: None,
        })
    }

    /// Number of examples.
    pub fn len(&self) -> usize {
        self.x0.len()
    }

    /// Whether there are no examples.
    pub fn is_empty(&self) -> bool {
        self.x0.is_empty()
    }

    /// The GCMA geometry of the rig.
    pub fn geometry(&self) -> Option<&GcmaGeometry> {
        self.geometry.as_ref()
    }

    /// Indices of the examples of update `step`: epoch-wise seeded shuffles.
    pub fn indices(&self, step: u64) -> Vec<usize> {
        let n = self.x0.len();
        let b = self.batch_size;
        let start = step as usize * b;
        // one seeded shuffle per epoch, built once for the (at most a few) epochs the batch spans
        let mut perm: Option<(usize, Vec<usize>)> = None;
        (start..start + b)
            .map(|k| {
                let epoch = k / n;
                if perm.as_ref().is_none_or(|(e, _)| *e != epoch) {
                    let mut p: Vec<usize> = (0..n).collect();
                    let mut rng = ChaCha8Rng::seed_from_u64(
                        self.seed ^ (epoch as u64).wrapping_mul(0x9E37_79B9),
                    );
                    p.shuffle(&mut rng);
                    perm = Some((epoch, p));
                }
                perm.as_ref().map_or(0, |(_, p)| p[k % n])
            })
            .collect()
    }

    /// Makes [`Self::batch`] return only `group`'s share of each global batch (data-parallel
    /// training: every rank draws the same global batch and takes its own disjoint part).
    pub fn set_shard(&mut self, group: &ProcessGroup) -> Result<()> {
        if self.batch_size < group.world_size {
            return Err(Error::Data(format!(
                "a global batch of {} cannot be shared by {} ranks (each needs at least one example)",
                self.batch_size, group.world_size
            )));
        }
        self.shard = Some(group.clone());
        Ok(())
    }

    /// The batch of update `step` for `net` (the condition fusion runs here, inside the graph, so
    /// CACM is trained); with [`Self::set_shard`], this rank's share of it.
    pub fn batch<'g>(&'g self, net: &Net, step: u64) -> Result<Batch<NetCond<'g>>> {
        let all = self.indices(step);
        let idx = match &self.shard {
            Some(g) => g.shard(&all).to_vec(),
            None => all,
        };
        let pick = |v: &[Tensor]| -> Result<Tensor> {
            Ok(Tensor::cat(
                &idx.iter().map(|&i| v[i].clone()).collect::<Vec<_>>(),
                0,
            )?)
        };
        let x0 = pick(&self.x0)?;
        let image = if self.features.is_empty() {
            None
        } else {
            let items: Vec<&ViewFeatures> = idx.iter().map(|&i| &self.features[i]).collect();
            let input = ViewFeatures::cat(&items)?;
            Some(net.prepare_condition(&input, self.geometry.as_ref())?)
        };
        let mean = self.means.as_deref().map(pick).transpose()?;
        let weight = self.weights.as_deref().map(pick).transpose()?;
        let cond = (image.is_some() || mean.is_some()).then_some(NetCond { image, mean });
        Ok(Batch { x0, cond, weight })
    }
}

/// What [`fit_denoiser`] trains on and how.
#[derive(Debug, Clone, Copy)]
pub struct DenoiserFit<'a> {
    /// Frozen `E_s` (when the config uses semantic cues).
    pub semantic: Option<&'a AnyEncoder>,
    /// Frozen `E_d` (when the config uses depth cues).
    pub depth: Option<&'a AnyEncoder>,
    /// The training examples (one camera rig).
    pub examples: &'a [TrainExample],
    /// Which network of the bundle is trained.
    pub stage: Stage,
    /// For the residual denoiser: the mean network's prediction of every example
    /// ([`predict_means`]).
    pub means: Option<&'a [Vec<f32>]>,
    /// Examples per update.
    pub batch_size: usize,
    /// Optimiser, schedule, EMA, dropout and checkpoint settings; its seed also seeds the
    /// initialisation and the batch order.
    pub train: &'a TrainConfig,
    /// Where checkpoints go; the newest one there is resumed.
    pub checkpoint_dir: &'a Path,
    /// Start from these weights wherever names and shapes match (fine-tuning); the rest keeps its
    /// seeded initialisation.
    pub init: Option<&'a HashMap<String, Tensor>>,
    /// Data-parallel training with the other ranks of this run (`None`: one process). Every rank
    /// trains on its share of each global batch of `batch_size`; only rank 0 writes checkpoints.
    pub parallel: Option<&'a Parallel>,
}

/// What [`fit_denoiser`] did.
#[derive(Debug)]
pub struct DenoiserFitOutcome {
    /// The `fit` call's summary (steps run in this call, mean loss, ...).
    pub summary: FitSummary,
    /// The trainer's step afterwards (less than `total_steps` when the observer stopped early).
    pub step: u64,
    /// Number of tensors taken from [`DenoiserFit::init`].
    pub initialised: usize,
    /// The EMA weights, by name (what a bundle ships).
    pub ema_weights: HashMap<String, Tensor>,
}

/// The network config and process of one training stage of `config`.
pub fn stage_config(
    config: &BundleConfig,
    stage: Stage,
) -> Result<(veila_nn::DenoiserConfig, crate::DiffusionConfig)> {
    match stage {
        Stage::Denoiser => Ok((config.denoiser.clone(), config.diffusion.clone())),
        Stage::Mean => {
            let r = config.residual.as_ref().ok_or_else(|| {
                Error::Data("this bundle has no mean network (not residual diffusion)".into())
            })?;
            Ok((r.mean_net.clone(), ResidualConfig::mean_diffusion()))
        }
    }
}

/// Trains one network of `config` on in-memory examples: a seeded network (optionally started
/// from `fit.init`), frozen encoder features via [`DenoiserTraining`], the [`Trainer`] with its
/// checkpoints in `fit.checkpoint_dir`. A checkpoint already there is resumed first (`on_resume`
/// gets its path and step), so an interrupted run continues exactly.
pub fn fit_denoiser<O>(
    config: &BundleConfig,
    fit: DenoiserFit<'_>,
    device: &Device,
    on_resume: impl FnOnce(&Path, u64),
    observer: &mut O,
) -> Result<DenoiserFitOutcome>
where
    O: for<'g> TrainObserver<VeilaDenoiser<'g>>,
{
    let (net_cfg, diffusion) = stage_config(config, fit.stage)?;
    let varmap = VarMap::new();
    let net = Net::new(
        &net_cfg,
        veila_nn::seeded_var_builder(&varmap, fit.train.seed, DType::F32, device),
    )?;
    let mut initialised = 0;
    if let Some(init) = fit.init {
        let data = varmap
            .data()
            .lock()
            .map_err(|_| Error::Data("the VarMap lock is poisoned".into()))?;
        for (name, var) in data.iter() {
            if let Some(t) = init.get(name)
                && t.dims() == var.dims()
            {
                var.set(t)?;
                initialised += 1;
            }
        }
    }
    let mut data = DenoiserTraining::new(
        config,
        fit.semantic,
        fit.depth,
        &net,
        fit.examples,
        fit.stage,
        fit.means,
        fit.batch_size,
        fit.train.seed,
        device,
    )?;
    if let Some(p) = fit.parallel {
        data.set_shard(p.group())?;
    }
    // the batches run the condition fusion through a clone that shares the trained variables
    let batch_net = net.clone();
    let mut trainer = Trainer::new(
        VeilaDenoiser::new(net),
        varmap,
        Diffusion::new(diffusion)?,
        fit.train.clone(),
    )?;
    if let Some(p) = fit.parallel {
        trainer.set_communicator(p.communicator());
    }
    let resumed: Option<PathBuf> = trainer.resume_latest(fit.checkpoint_dir)?;
    if let Some(p) = &resumed {
        on_resume(p, trainer.step());
    }
    let mut source = |step: u64| data.batch(&batch_net, step);
    let summary = trainer.fit(&mut source, Some(fit.checkpoint_dir), observer)?;
    Ok(DenoiserFitOutcome {
        summary,
        step: trainer.step(),
        initialised,
        ema_weights: trainer.ema_weights(),
    })
}

/// What [`fit_bundle`] trains: the whole training recipe of a bundle's generative part.
#[derive(Debug, Clone, Copy)]
pub struct BundleFit<'a> {
    /// Frozen `E_s` (when the config uses semantic cues).
    pub semantic: Option<&'a AnyEncoder>,
    /// Frozen `E_d` (when the config uses depth cues).
    pub depth: Option<&'a AnyEncoder>,
    /// The training examples (one camera rig).
    pub examples: &'a [TrainExample],
    /// Examples per update.
    pub batch_size: usize,
    /// Settings of the denoiser's run.
    pub train: &'a TrainConfig,
    /// Settings of the mean network's run (residual bundles; `None`: the denoiser's).
    pub mean_train: Option<&'a TrainConfig>,
    /// Checkpoints: the denoiser's go here, the mean network's into its `mean/` subfolder.
    pub work_dir: &'a Path,
    /// Initial denoiser weights wherever names and shapes match (fine-tuning).
    pub init: Option<&'a HashMap<String, Tensor>>,
    /// Data-parallel training (see [`DenoiserFit::parallel`]).
    pub parallel: Option<&'a Parallel>,
}

/// What [`fit_bundle`] did.
#[derive(Debug)]
pub struct BundleFitOutcome {
    /// The denoiser's run (`None` when an observer stopped the mean network's run early: the
    /// denoiser needs the finished mean network).
    pub denoiser: Option<DenoiserFitOutcome>,
    /// The mean network's run (residual bundles).
    pub mean: Option<DenoiserFitOutcome>,
    /// Seconds spent in each run, mean network first (0 when absent).
    pub seconds: [f64; 2],
}

/// The training recipe every command shares: for a residual bundle the mean network first
/// (one-pass regression), then its predictions of every example, the residual scale (written
/// into `config.residual`), then the denoiser on the residuals; otherwise the denoiser alone.
/// Every run resumes from its checkpoints in `fit.work_dir`. `observer(stage, total_steps)` makes
/// the observer of each run; `on_resume` hears of every resumed checkpoint.
pub fn fit_bundle<O>(
    config: &mut BundleConfig,
    fit: BundleFit<'_>,
    device: &Device,
    mut on_resume: impl FnMut(Stage, &Path, u64),
    mut observer: impl FnMut(Stage, u64) -> O,
) -> Result<BundleFitOutcome>
where
    O: for<'g> TrainObserver<VeilaDenoiser<'g>>,
{
    let mut seconds = [0.0; 2];
    let (mean, means) = if config.residual.is_some() {
        let t = std::time::Instant::now();
        let tc = fit.mean_train.unwrap_or(fit.train);
        let dir = fit.work_dir.join("mean");
        let mut obs = observer(Stage::Mean, tc.total_steps);
        let out = fit_denoiser(
            config,
            DenoiserFit {
                semantic: fit.semantic,
                depth: fit.depth,
                examples: fit.examples,
                stage: Stage::Mean,
                means: None,
                batch_size: fit.batch_size,
                train: tc,
                checkpoint_dir: &dir,
                init: None,
                parallel: fit.parallel,
            },
            device,
            |p, s| on_resume(Stage::Mean, p, s),
            &mut obs,
        )?;
        if out.step < tc.total_steps {
            seconds[0] = t.elapsed().as_secs_f64();
            return Ok(BundleFitOutcome {
                denoiser: None,
                mean: Some(out),
                seconds,
            });
        }
        let means = predict_means(
            config,
            fit.semantic,
            fit.depth,
            &out.ema_weights,
            fit.examples,
            16,
            device,
        )?;
        let (h, w) = (config.denoiser.height(), config.denoiser.width());
        let x0: Vec<Vec<f32>> = fit.examples.iter().map(|e| e.x0.clone()).collect();
        let scale = residual_scale(&config.encoding, &x0, &means, h * w);
        if let Some(r) = config.residual.as_mut() {
            r.scale = scale;
        }
        seconds[0] = t.elapsed().as_secs_f64();
        (Some(out), Some(means))
    } else {
        (None, None)
    };
    let t = std::time::Instant::now();
    let mut obs = observer(Stage::Denoiser, fit.train.total_steps);
    let denoiser = fit_denoiser(
        config,
        DenoiserFit {
            semantic: fit.semantic,
            depth: fit.depth,
            examples: fit.examples,
            stage: Stage::Denoiser,
            means: means.as_deref(),
            batch_size: fit.batch_size,
            train: fit.train,
            checkpoint_dir: fit.work_dir,
            init: fit.init,
            parallel: fit.parallel,
        },
        device,
        |p, s| on_resume(Stage::Denoiser, p, s),
        &mut obs,
    )?;
    seconds[1] = t.elapsed().as_secs_f64();
    Ok(BundleFitOutcome {
        denoiser: Some(denoiser),
        mean,
        seconds,
    })
}

/// The mean network's one-pass prediction (encoded, `channels * rows * cols` values) for every
/// example, in batches of `batch_size`: what a residual denoiser trains on.
pub fn predict_means(
    config: &BundleConfig,
    semantic: Option<&AnyEncoder>,
    depth: Option<&AnyEncoder>,
    mean_weights: &HashMap<String, Tensor>,
    examples: &[TrainExample],
    batch_size: usize,
    device: &Device,
) -> Result<Vec<Vec<f32>>> {
    let (cfg, diffusion) = stage_config(config, Stage::Mean)?;
    let net = Net::new(
        &cfg,
        VarBuilder::from_tensors(mean_weights.clone(), DType::F32, device),
    )?;
    let (h, w) = (cfg.height(), cfg.width());
    let c = config.channels();
    let diffusion = Diffusion::new(diffusion)?;
    let sampler = Sampler::new(
        &diffusion,
        SamplerConfig {
            steps: 1,
            guidance_scale: 1.0,
            ..config.sampler.clone()
        },
    )?;
    let geometry = match &cfg.conditioning {
        Some(cc) if cc.gcma.is_some() && !examples.is_empty() => {
            Some(net.geometry(&[examples[0].camera], &config.epipolar, device)?)
        }
        _ => None,
    };
    let model = VeilaDenoiser::new(net.clone());
    let mut out = Vec::with_capacity(examples.len());
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    for chunk in examples.chunks(batch_size.max(1)) {
        let image = if net.is_conditional() {
            let feats = chunk
                .iter()
                .map(|ex| {
                    encode_views(
                        config,
                        semantic,
                        depth,
                        &[CameraView {
                            rgb: &ex.rgb,
                            camera: &ex.camera,
                        }],
                        device,
                    )
                })
                .collect::<Result<Vec<_>>>()?;
            let refs: Vec<&ViewFeatures> = feats.iter().collect();
            Some(net.prepare_condition(&ViewFeatures::cat(&refs)?, geometry.as_ref())?)
        } else {
            None
        };
        let cond = NetCond { image, mean: None };
        let zeros = Tensor::zeros((chunk.len(), c, h, w), DType::F32, device)?;
        let mu = sampler.sample_from(&model, zeros, Some(&cond), &mut rng, |_| {})?;
        for i in 0..chunk.len() {
            out.push(mu.get(i)?.flatten_all()?.to_vec1::<f32>()?);
        }
    }
    Ok(out)
}

/// What one encoder training step did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EncoderStep {
    /// Steps done.
    pub step: usize,
    /// Total loss of the batch.
    pub loss: f32,
}

/// Trains a [`SmallCnn`] on images with per-pixel targets: `images[i]` is `h * w * 3` RGB bytes,
/// `labels[i]` (class ids of the learning map) and/or `depth_m[i]` (metres, 0 = no ground truth)
/// `h * w` values. AdamW with a cosine learning rate, seeded batches; returns the network and its
/// `VarMap`.
#[allow(clippy::too_many_arguments)]
pub fn train_small_cnn(
    cfg: &SmallCnnConfig,
    images: &[Vec<u8>],
    labels: Option<&[Vec<u32>]>,
    depth_m: Option<&[Vec<f32>]>,
    (h, w): (usize, usize),
    steps: usize,
    batch_size: usize,
    lr: f64,
    seed: u64,
    device: &Device,
    mut on_step: impl FnMut(EncoderStep),
) -> Result<(SmallCnn, VarMap)> {
    let n = images.len();
    if n == 0 || batch_size == 0 {
        return Err(Error::Data(
            "encoder training needs images and a batch size".into(),
        ));
    }
    let varmap = VarMap::new();
    let net = SmallCnn::new(
        cfg,
        veila_nn::seeded_var_builder(&varmap, seed, DType::F32, device),
    )?;
    let vars: Vec<(String, candle_core::Var)> = {
        let data = varmap
            .data()
            .lock()
            .map_err(|_| Error::Data("the VarMap lock is poisoned".into()))?;
        let mut v: Vec<_> = data.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        v.sort_by(|a, b| a.0.cmp(&b.0));
        v
    };
    let mut opt = AdamW::new(
        vars,
        ParamsAdamW {
            lr,
            weight_decay: 1e-4,
            ..ParamsAdamW::default()
        },
    )?;
    let loss_cfg = SmallCnnLossConfig::default();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    for step in 0..steps {
        let progress = step as f64 / steps.max(1) as f64;
        opt.set_learning_rate(lr * 0.5 * (1.0 + (std::f64::consts::PI * progress).cos()));
        let idx: Vec<usize> = (0..batch_size).map(|_| rng.random_range(0..n)).collect();
        let imgs = idx
            .iter()
            .map(|&i| image_tensor(&images[i], h, w, device))
            .collect::<Result<Vec<_>>>()?;
        let image = Tensor::cat(&imgs, 0)?;
        // random horizontal flips (targets flipped with the image)
        let flip = rng.random_bool(0.5);
        let image = if flip { flip_w(&image)? } else { image };
        let lab = labels
            .map(|l| -> Result<Tensor> {
                let rows: Vec<u32> = idx.iter().flat_map(|&i| l[i].iter().copied()).collect();
                let t = Tensor::from_vec(rows, (batch_size, h, w), device)?;
                if flip { flip_w(&t) } else { Ok(t) }
            })
            .transpose()?;
        let dep = depth_m
            .map(|d| -> Result<Tensor> {
                let rows: Vec<f32> = idx.iter().flat_map(|&i| d[i].iter().copied()).collect();
                let t = Tensor::from_vec(rows, (batch_size, h, w), device)?;
                if flip { flip_w(&t) } else { Ok(t) }
            })
            .transpose()?;
        let loss = net.loss(&image, lab.as_ref(), dep.as_ref(), &loss_cfg)?;
        let grads = loss.total.backward()?;
        opt.step(&grads, 1.0)?;
        on_step(EncoderStep {
            step: step + 1,
            loss: loss.total.to_dtype(DType::F32)?.to_scalar::<f32>()?,
        });
    }
    Ok((net, varmap))
}

/// Reverses the last axis.
fn flip_w(t: &Tensor) -> Result<Tensor> {
    let w = t.dim(t.rank() - 1)?;
    let idx: Vec<u32> = (0..w as u32).rev().collect();
    let idx = Tensor::from_vec(idx, w, t.device())?;
    Ok(t.index_select(&idx, t.rank() - 1)?)
}

/// The tensors of a `VarMap` by name (for [`Bundle::save`](crate::app::Bundle::save)).
pub fn varmap_tensors(varmap: &VarMap) -> Result<HashMap<String, Tensor>> {
    let data = varmap
        .data()
        .lock()
        .map_err(|_| Error::Data("the VarMap lock is poisoned".into()))?;
    Ok(data
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().clone()))
        .collect())
}
