//! Training a [`Bundle`](super::Bundle)'s networks on in-memory examples: the denoiser and the mean network of
//! residual diffusion ([`fit_denoiser`], with [`DenoiserTraining`] computing the frozen encoder
//! features once per example), the whole generative part of a bundle ([`fit_bundle`]), and the small
//! CNN encoders ([`train_small_cnn`]). [`super::recipe`] strings these into the one training recipe
//! the binaries share.
//!
//! Everything is seeded: the same inputs and seed give the same weights.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use veila_geom::PinholeCamera;
use veila_nn::encoders::kind::AnyEncoder;
use veila_nn::encoders::small_cnn::{SmallCnn, SmallCnnConfig, SmallCnnLossConfig};
use veila_nn::{Denoiser as Net, GcmaGeometry};

use super::bundle::{BundleConfig, ResidualConfig};
use super::dataset::{EncoderExample, ExampleSource, Examples, Order, Prefetcher, Rigs};
pub use super::dataset::{TrainExample, TrainView};
use super::generate::{ViewFeatures, encode_views};
use super::nn::{NetCond, VeilaDenoiser};
use crate::error::{Error, Result};
use crate::objective::Diffusion;
use crate::sampler::{Sampler, SamplerConfig};
use crate::trainer::distributed::{Parallel, ProcessGroup};
use crate::trainer::{
    AdamW, Batch, BatchSource, FitSummary, ParamsAdamW, TrainConfig, TrainObserver, Trainer,
};

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
    let mut sums = ResidualSums::new(enc.num_channels());
    for (x, m) in x0.iter().zip(means) {
        sums.add(enc, x, m, hw);
    }
    sums.scale()
}

/// Running sums of squared residuals per channel (see [`residual_scale`]).
struct ResidualSums {
    sum: Vec<f64>,
    count: Vec<f64>,
}

impl ResidualSums {
    fn new(c: usize) -> Self {
        Self {
            sum: vec![0.0; c],
            count: vec![0.0; c],
        }
    }

    fn add(&mut self, enc: &crate::RangeEncoding, x: &[f32], m: &[f32], hw: usize) {
        let w = regression_weight(enc, x, hw);
        let r = raw_residual(enc, x, m, hw);
        for ch in 0..self.sum.len() {
            for p in ch * hw..(ch + 1) * hw {
                if w[p] > 0.0 {
                    self.sum[ch] += f64::from(r[p]) * f64::from(r[p]);
                    self.count[ch] += 1.0;
                }
            }
        }
    }

    fn scale(&self) -> Vec<f32> {
        self.sum
            .iter()
            .zip(&self.count)
            .map(|(s, n)| ((s / n.max(1.0)).sqrt() as f32).max(1e-3))
            .collect()
    }
}

/// Training state of one network of a bundle: the targets (and for residual diffusion the mean
/// predictions, for regression the loss weights), the frozen encoder features, the GCMA geometry
/// of every camera (built the first time it appears; samples of different rigs share a batch,
/// each attending with its own), batches drawn by a seeded shuffle that is a pure function of the
/// step (so resumed runs match uninterrupted ones).
///
/// [`Self::new`] takes examples in memory and computes everything once per example;
/// [`Self::streaming`] reads the examples of each batch from an [`ExampleSource`] (a loader
/// thread reads ahead) and runs the frozen networks per batch. The two give the same batches.
#[derive(Debug)]
pub struct DenoiserTraining {
    store: Store,
    /// The geometry of each camera, when the network has GCMA.
    rigs: Option<Rigs>,
    epipolar: veila_geom::EpipolarConfig,
    device: Device,
    order: Order,
}

#[derive(Debug)]
enum Store {
    Memory {
        features: Vec<ViewFeatures>,
        /// Every example's cameras, one per view.
        rigs: Vec<Vec<PinholeCamera>>,
        x0: Vec<Tensor>,
        means: Option<Vec<Tensor>>,
        weights: Option<Vec<Tensor>>,
    },
    Stream(Box<Streamed>),
}

/// What [`DenoiserTraining::streaming`] needs per batch.
#[derive(Debug)]
struct Streamed {
    prefetch: Prefetcher,
    config: BundleConfig,
    semantic: Option<AnyEncoder>,
    depth: Option<AnyEncoder>,
    stage: Stage,
    /// The frozen mean network and the residual scale (residual denoiser).
    residual: Option<(MeanPredictor, Vec<f32>)>,
    conditional: bool,
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
                let views = ex
                    .views(num_views(net))
                    .map_err(|e| Error::Data(format!("example {i}: {e}")))?;
                features.push(encode_views(config, semantic, depth, &views, device)?);
            }
        }
        Ok(Self {
            store: Store::Memory {
                features,
                rigs: examples.iter().map(|e| e.rig(num_views(net))).collect(),
                x0,
                means: residual.is_some().then_some(mean_t),
                weights: (stage == Stage::Mean).then_some(weights),
            },
            rigs: has_gcma(net).then(Rigs::new),
            epipolar: config.epipolar,
            device: device.clone(),
            order: Order {
                n: examples.len(),
                batch: batch_size,
                seed,
                shard: None,
            },
        })
    }

    /// Training state that reads each batch's examples from `source` (a loader thread reads
    /// `prefetch` batches ahead) and runs the frozen encoders, and for a residual denoiser the
    /// frozen mean network with `mean_weights`, on every batch: memory does not grow with the
    /// set. `config.residual.scale` must already be set for a residual denoiser
    /// ([`residual_scale_of`]).
    #[allow(clippy::too_many_arguments)]
    pub fn streaming(
        config: &BundleConfig,
        semantic: Option<&AnyEncoder>,
        depth: Option<&AnyEncoder>,
        net: &Net,
        source: Arc<dyn ExampleSource>,
        stage: Stage,
        mean_weights: Option<&HashMap<String, Tensor>>,
        batch_size: usize,
        seed: u64,
        prefetch: usize,
        device: &Device,
    ) -> Result<Self> {
        if source.is_empty() || batch_size == 0 {
            return Err(Error::Data(
                "training needs at least one example and a batch size of at least 1".into(),
            ));
        }
        let conditional = net.is_conditional();
        let residual = match (stage, &config.residual) {
            (Stage::Denoiser, Some(r)) => {
                let w = mean_weights.ok_or_else(|| {
                    Error::Data(
                        "a residual denoiser trains on the mean network's predictions: pass its weights"
                            .into(),
                    )
                })?;
                Some((MeanPredictor::new(config, w, device)?, r.scale.clone()))
            }
            (Stage::Mean, None) => {
                return Err(Error::Data(
                    "this bundle has no mean network (not residual diffusion)".into(),
                ));
            }
            _ => None,
        };
        let n = source.len();
        Ok(Self {
            store: Store::Stream(Box::new(Streamed {
                prefetch: Prefetcher::new(source, prefetch),
                config: config.clone(),
                semantic: semantic.cloned(),
                depth: depth.cloned(),
                stage,
                residual,
                conditional,
            })),
            rigs: has_gcma(net).then(Rigs::new),
            epipolar: config.epipolar,
            device: device.clone(),
            order: Order {
                n,
                batch: batch_size,
                seed,
                shard: None,
            },
        })
    }

    /// Number of examples.
    pub fn len(&self) -> usize {
        self.order.n
    }

    /// Whether there are no examples.
    pub fn is_empty(&self) -> bool {
        self.order.n == 0
    }

    /// The GCMA geometry of the first camera seen (`None` before the first batch, or without
    /// GCMA).
    pub fn geometry(&self) -> Option<&GcmaGeometry> {
        self.rigs.as_ref().and_then(Rigs::first)
    }

    /// The condition of a batch whose samples have the camera rigs `cameras` (one camera per
    /// view): every rig's geometry (built once), each sample attending with its own.
    fn condition<'g>(
        &'g self,
        net: &Net,
        input: &veila_nn::ConditionInput,
        cameras: &[&[PinholeCamera]],
    ) -> Result<veila_nn::PreparedCondition<'g>> {
        rig_condition(
            net,
            self.rigs.as_ref(),
            input,
            cameras,
            &self.epipolar,
            &self.device,
        )
    }

    /// Indices of the examples of update `step`: epoch-wise seeded shuffles.
    pub fn indices(&self, step: u64) -> Vec<usize> {
        self.order.indices(step)
    }

    /// Makes [`Self::batch`] return only `group`'s share of each global batch (data-parallel
    /// training: every rank draws the same global batch and takes its own disjoint part).
    pub fn set_shard(&mut self, group: &ProcessGroup) -> Result<()> {
        if self.order.batch < group.world_size {
            return Err(Error::Data(format!(
                "a global batch of {} cannot be shared by {} ranks (each needs at least one example)",
                self.order.batch, group.world_size
            )));
        }
        self.order.shard = Some(group.clone());
        Ok(())
    }

    /// The batch of update `step` for `net` (the condition fusion runs here, inside the graph, so
    /// CACM is trained); with [`Self::set_shard`], this rank's share of it.
    pub fn batch<'g>(&'g self, net: &Net, step: u64) -> Result<Batch<NetCond<'g>>> {
        let idx = self.order.local(step);
        self.batch_range(net, step, &idx, 0..idx.len())
    }

    /// Part `part` of `parts` of [`Self::batch`] (gradient accumulation): contiguous parts of
    /// this rank's examples whose sizes differ by at most one.
    pub fn batch_part<'g>(
        &'g self,
        net: &Net,
        step: u64,
        part: usize,
        parts: usize,
    ) -> Result<Batch<NetCond<'g>>> {
        let idx = self.order.local(step);
        let (start, len) = crate::trainer::part_range(idx.len(), part, parts)?;
        self.batch_range(net, step, &idx, start..start + len)
    }

    /// The batch of the examples `idx[range]` of update `step`.
    fn batch_range<'g>(
        &'g self,
        net: &Net,
        step: u64,
        idx: &[usize],
        range: std::ops::Range<usize>,
    ) -> Result<Batch<NetCond<'g>>> {
        match &self.store {
            Store::Memory {
                features,
                rigs,
                x0,
                means,
                weights,
            } => {
                let idx = &idx[range];
                let pick = |v: &[Tensor]| -> Result<Tensor> {
                    Ok(Tensor::cat(
                        &idx.iter().map(|&i| v[i].clone()).collect::<Vec<_>>(),
                        0,
                    )?)
                };
                let x0 = pick(x0)?;
                let image = if features.is_empty() {
                    None
                } else {
                    let items: Vec<&ViewFeatures> = idx.iter().map(|&i| &features[i]).collect();
                    let input = ViewFeatures::cat(&items)?;
                    let cams: Vec<&[PinholeCamera]> = idx.iter().map(|&i| &rigs[i][..]).collect();
                    Some(self.condition(net, &input, &cams)?)
                };
                let mean = means.as_deref().map(pick).transpose()?;
                let weight = weights.as_deref().map(pick).transpose()?;
                let cond = (image.is_some() || mean.is_some()).then_some(NetCond { image, mean });
                Ok(Batch { x0, cond, weight })
            }
            Store::Stream(st) => {
                let examples = st.prefetch.examples(&self.order, step)?;
                self.stream_batch(st, net, &examples[range])
            }
        }
    }

    /// A batch of `examples` read by the loader: targets, mean predictions and features
    /// computed now.
    fn stream_batch<'g>(
        &'g self,
        st: &Streamed,
        net: &Net,
        examples: &[TrainExample],
    ) -> Result<Batch<NetCond<'g>>> {
        let config = &st.config;
        let (h, w) = (config.denoiser.height(), config.denoiser.width());
        let c = config.channels();
        let b = examples.len();
        for ex in examples {
            if ex.x0.len() != c * h * w {
                return Err(Error::Shape {
                    what: "training example",
                    expected: format!("{c} x {h} x {w} values"),
                    got: format!("{} values", ex.x0.len()),
                });
            }
        }
        let dev = &self.device;
        let nv = num_views(net);
        // the frozen encoders run once per batch: the mean network and the denoiser share them
        let input = if st.conditional {
            Some(encode_examples(
                config,
                st.semantic.as_ref(),
                st.depth.as_ref(),
                examples,
                nv,
                dev,
            )?)
        } else {
            None
        };
        let (x0, mean) = match &st.residual {
            Some((predictor, scale)) => {
                let mu = predictor.predict_encoded(input.as_ref(), examples)?;
                let mut r = Vec::with_capacity(b * c * h * w);
                for (ex, m) in examples.iter().zip(&mu) {
                    r.extend(residual_target(&config.encoding, &ex.x0, m, scale, h * w));
                }
                let m: Vec<f32> = mu.concat();
                (
                    Tensor::from_vec(r, (b, c, h, w), dev)?,
                    Some(Tensor::from_vec(m, (b, c, h, w), dev)?),
                )
            }
            None => {
                let x: Vec<f32> = examples.iter().flat_map(|e| e.x0.iter().copied()).collect();
                (Tensor::from_vec(x, (b, c, h, w), dev)?, None)
            }
        };
        let weight = if st.stage == Stage::Mean {
            let wt: Vec<f32> = examples
                .iter()
                .flat_map(|e| regression_weight(&config.encoding, &e.x0, h * w))
                .collect();
            Some(Tensor::from_vec(wt, (b, c, h, w), dev)?)
        } else {
            None
        };
        let image = match &input {
            Some(input) => {
                let rigs: Vec<Vec<PinholeCamera>> = examples.iter().map(|e| e.rig(nv)).collect();
                let cams: Vec<&[PinholeCamera]> = rigs.iter().map(|r| &r[..]).collect();
                Some(self.condition(net, input, &cams)?)
            }
            None => None,
        };
        let cond = (image.is_some() || mean.is_some()).then_some(NetCond { image, mean });
        Ok(Batch { x0, cond, weight })
    }
}

/// [`DenoiserTraining`] as the trainer's [`BatchSource`], with the network whose condition fusion
/// the batches run.
struct TrainingSource<'a> {
    data: &'a DenoiserTraining,
    net: &'a Net,
}

impl<'a> BatchSource<NetCond<'a>> for TrainingSource<'a> {
    fn batch(&mut self, step: u64) -> Result<Batch<NetCond<'a>>> {
        self.data.batch(self.net, step)
    }

    fn batch_part(&mut self, step: u64, part: usize, parts: usize) -> Result<Batch<NetCond<'a>>> {
        self.data.batch_part(self.net, step, part, parts)
    }
}

/// How many camera views `net` takes (1 when unconditional).
fn num_views(net: &Net) -> usize {
    net.config()
        .conditioning
        .as_ref()
        .map_or(1, |c| c.num_views.max(1))
}

/// Whether `net` has GCMA (and so needs the cameras' geometry).
fn has_gcma(net: &Net) -> bool {
    net.config()
        .conditioning
        .as_ref()
        .is_some_and(|c| c.gcma.is_some())
}

/// What [`fit_denoiser`] trains on and how.
#[derive(Debug, Clone, Copy)]
pub struct DenoiserFit<'a> {
    /// Frozen `E_s` (when the config uses semantic cues).
    pub semantic: Option<&'a AnyEncoder>,
    /// Frozen `E_d` (when the config uses depth cues).
    pub depth: Option<&'a AnyEncoder>,
    /// The training examples (any cameras), in memory or streamed.
    pub examples: Examples<'a>,
    /// Which network of the bundle is trained.
    pub stage: Stage,
    /// For the residual denoiser on examples in memory: the mean network's prediction of every
    /// example ([`predict_means`]).
    pub means: Option<&'a [Vec<f32>]>,
    /// For the residual denoiser on streamed examples: the mean network's weights (it predicts
    /// each batch).
    pub mean_weights: Option<&'a HashMap<String, Tensor>>,
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
    let mut data = match fit.examples {
        Examples::Memory(examples) => DenoiserTraining::new(
            config,
            fit.semantic,
            fit.depth,
            &net,
            examples,
            fit.stage,
            fit.means,
            fit.batch_size,
            fit.train.seed,
            device,
        )?,
        Examples::Stream { source, prefetch } => DenoiserTraining::streaming(
            config,
            fit.semantic,
            fit.depth,
            &net,
            source.clone(),
            fit.stage,
            fit.mean_weights,
            fit.batch_size,
            fit.train.seed,
            prefetch,
            device,
        )?,
    };
    if let Some(p) = fit.parallel {
        data.set_shard(p.group())?;
    }
    let world = fit.parallel.map_or(1, |p| p.group().world_size);
    let parts = fit.train.grad_accum_steps as usize;
    if parts > fit.batch_size / world {
        return Err(Error::Data(format!(
            "grad_accum_steps {parts} splits each rank's share of the batch ({} of {} over {world} rank(s)) \
             into more parts than it has examples",
            fit.batch_size / world,
            fit.batch_size
        )));
    }
    // the batches run the condition fusion through a clone that shares the trained variables
    let batch_net = net.clone();
    let mut net = net;
    net.set_activation_checkpointing(fit.train.activation_checkpointing);
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
    let mut source = TrainingSource {
        data: &data,
        net: &batch_net,
    };
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
    /// The training examples (any cameras), in memory or streamed.
    pub examples: Examples<'a>,
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
    /// Initial mean-network weights, likewise (fine-tuning a residual bundle: without them its
    /// mean network starts from its seeded initialisation).
    pub mean_init: Option<&'a HashMap<String, Tensor>>,
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
                mean_weights: None,
                batch_size: fit.batch_size,
                train: tc,
                checkpoint_dir: &dir,
                init: fit.mean_init,
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
        let (means, scale) = match fit.examples {
            Examples::Memory(examples) => {
                let means = predict_means(
                    config,
                    fit.semantic,
                    fit.depth,
                    &out.ema_weights,
                    examples,
                    16,
                    device,
                )?;
                let (h, w) = (config.denoiser.height(), config.denoiser.width());
                let x0: Vec<Vec<f32>> = examples.iter().map(|e| e.x0.clone()).collect();
                let scale = residual_scale(&config.encoding, &x0, &means, h * w);
                (Some(means), scale)
            }
            Examples::Stream { source, .. } => {
                let scale = residual_scale_of(
                    config,
                    fit.semantic,
                    fit.depth,
                    &out.ema_weights,
                    source.as_ref(),
                    16,
                    device,
                )?;
                (None, scale)
            }
        };
        if let Some(r) = config.residual.as_mut() {
            r.scale = scale;
        }
        seconds[0] = t.elapsed().as_secs_f64();
        (Some(out), means)
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
            mean_weights: mean.as_ref().map(|m: &DenoiserFitOutcome| &m.ema_weights),
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

/// The frozen mean network of a residual bundle: its one-pass prediction of a batch of examples
/// (what the residual denoiser's targets subtract and what it is conditioned on).
pub struct MeanPredictor {
    config: BundleConfig,
    net: Net,
    diffusion: Diffusion,
    /// The geometry of each camera, when the mean network has GCMA.
    rigs: Option<Rigs>,
    device: Device,
}

impl std::fmt::Debug for MeanPredictor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MeanPredictor").finish_non_exhaustive()
    }
}

impl MeanPredictor {
    /// The mean network of `config` with `weights` (the GCMA geometry of each camera is built
    /// when it first appears).
    pub fn new(
        config: &BundleConfig,
        weights: &HashMap<String, Tensor>,
        device: &Device,
    ) -> Result<Self> {
        let (cfg, diffusion) = stage_config(config, Stage::Mean)?;
        let net = Net::new(
            &cfg,
            VarBuilder::from_tensors(weights.clone(), DType::F32, device),
        )?;
        Ok(Self {
            config: config.clone(),
            rigs: has_gcma(&net).then(Rigs::new),
            net,
            diffusion: Diffusion::new(diffusion)?,
            device: device.clone(),
        })
    }

    /// The prediction (encoded, `channels * rows * cols` values) of each of `examples`, in one
    /// batch.
    pub fn predict(
        &self,
        semantic: Option<&AnyEncoder>,
        depth: Option<&AnyEncoder>,
        examples: &[TrainExample],
    ) -> Result<Vec<Vec<f32>>> {
        let input = if self.net.is_conditional() && !examples.is_empty() {
            let nv = num_views(&self.net);
            Some(encode_examples(
                &self.config,
                semantic,
                depth,
                examples,
                nv,
                &self.device,
            )?)
        } else {
            None
        };
        self.predict_encoded(input.as_ref(), examples)
    }

    /// [`Self::predict`] from the examples' frozen encoder features already computed
    /// ([`encode_examples`]; `None` for an unconditional network).
    fn predict_encoded(
        &self,
        input: Option<&veila_nn::ConditionInput>,
        examples: &[TrainExample],
    ) -> Result<Vec<Vec<f32>>> {
        if examples.is_empty() {
            return Ok(Vec::new());
        }
        let cfg = self.net.config();
        let (h, w) = (cfg.height(), cfg.width());
        let c = self.config.channels();
        let sampler = Sampler::new(
            &self.diffusion,
            SamplerConfig {
                steps: 1,
                guidance_scale: 1.0,
                ..self.config.sampler.clone()
            },
        )?;
        let image = match (self.net.is_conditional(), input) {
            (true, Some(input)) => {
                let nv = num_views(&self.net);
                let rigs: Vec<Vec<PinholeCamera>> = examples.iter().map(|e| e.rig(nv)).collect();
                let cams: Vec<&[PinholeCamera]> = rigs.iter().map(|r| &r[..]).collect();
                Some(rig_condition(
                    &self.net,
                    self.rigs.as_ref(),
                    input,
                    &cams,
                    &self.config.epipolar,
                    &self.device,
                )?)
            }
            (true, None) => {
                return Err(Error::Data(
                    "the mean network is image-conditioned: it needs the examples' features".into(),
                ));
            }
            (false, _) => None,
        };
        let cond = NetCond { image, mean: None };
        let model = VeilaDenoiser::new(self.net.clone());
        let zeros = Tensor::zeros((examples.len(), c, h, w), DType::F32, &self.device)?;
        // the one-pass regression from zeros draws no noise; a fixed stream keeps it so anyway
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mu = sampler.sample_from(&model, zeros, Some(&cond), &mut rng, |_| {})?;
        (0..examples.len())
            .map(|i| Ok(mu.get(i)?.flatten_all()?.to_vec1::<f32>()?))
            .collect()
    }
}

/// The frozen encoders' features of `examples` (their first `views` camera views), as one batch.
fn encode_examples(
    config: &BundleConfig,
    semantic: Option<&AnyEncoder>,
    depth: Option<&AnyEncoder>,
    examples: &[TrainExample],
    views: usize,
    device: &Device,
) -> Result<veila_nn::ConditionInput> {
    let feats = examples
        .iter()
        .map(|ex| encode_views(config, semantic, depth, &ex.views(views)?, device))
        .collect::<Result<Vec<_>>>()?;
    let refs: Vec<&ViewFeatures> = feats.iter().collect();
    ViewFeatures::cat(&refs)
}

/// `input` prepared for `net`, each sample attending with the GCMA geometry of its rig
/// (`cameras[b]`, one camera per view), built the first time the rig appears in `rigs`
/// (`None`: the network has no GCMA).
fn rig_condition<'g>(
    net: &Net,
    rigs: Option<&'g Rigs>,
    input: &veila_nn::ConditionInput,
    cameras: &[&[PinholeCamera]],
    epipolar: &veila_geom::EpipolarConfig,
    device: &Device,
) -> Result<veila_nn::PreparedCondition<'g>> {
    let Some(rigs) = rigs else {
        return Ok(net.prepare_condition(input, None)?);
    };
    let geoms = cameras
        .iter()
        .map(|c| rigs.get(c, || Ok(net.geometry(c, epipolar, device)?)))
        .collect::<Result<Vec<_>>>()?;
    Ok(net.prepare_condition_per_sample(input, &geoms)?)
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
    let predictor = MeanPredictor::new(config, mean_weights, device)?;
    let mut out = Vec::with_capacity(examples.len());
    for chunk in examples.chunks(batch_size.max(1)) {
        out.extend(predictor.predict(semantic, depth, chunk)?);
    }
    Ok(out)
}

/// [`residual_scale`] of a streamed set: one pass over `source` in chunks of `batch_size`, the
/// mean network (`mean_weights`) predicting each chunk; memory bounded by the chunk.
pub fn residual_scale_of(
    config: &BundleConfig,
    semantic: Option<&AnyEncoder>,
    depth: Option<&AnyEncoder>,
    mean_weights: &HashMap<String, Tensor>,
    source: &dyn ExampleSource,
    batch_size: usize,
    device: &Device,
) -> Result<Vec<f32>> {
    if source.is_empty() {
        return Err(Error::Data(
            "the residual scale needs at least one example".into(),
        ));
    }
    let predictor = MeanPredictor::new(config, mean_weights, device)?;
    let (h, w) = (config.denoiser.height(), config.denoiser.width());
    let c = config.channels();
    let mut sums = ResidualSums::new(c);
    let n = source.len();
    let step = batch_size.max(1);
    for start in (0..n).step_by(step) {
        let chunk = (start..(start + step).min(n))
            .map(|i| source.example(i))
            .collect::<Result<Vec<_>>>()?;
        let means = predictor.predict(semantic, depth, &chunk)?;
        for (ex, m) in chunk.iter().zip(&means) {
            sums.add(&config.encoding, &ex.x0, m, h * w);
        }
    }
    Ok(sums.scale())
}

/// What one encoder training step did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EncoderStep {
    /// Steps done.
    pub step: usize,
    /// Total loss of the batch.
    pub loss: f32,
}

/// Image augmentation of encoder training (issue 18): a random crop-and-zoom with the targets
/// resampled alike, then the photometric pipeline of [`veila_data::augment`] (exposure,
/// vignetting, blur, white balance, noise, colour jitter, JPEG). Depth targets are divided by the
/// zoom `s`: an object zoomed `s` times looks as it would `s` times nearer through the training
/// camera, and the encoder keeps answering for that camera's focal length.
///
/// The example's camera (when it has one) follows the crop: the cropped intrinsics
/// ([`veila_data::augment::CropZoom::camera`]) with the camera frame scaled by `1 / s`, the same
/// "s times nearer" as the depth targets, so that a ground prior computed from it
/// ([`veila_nn::encoders::ground`]) agrees with them: the flat ground's depth through the
/// returned camera is the true one divided by `s`, at the pixels where the crop put it.
///
/// Each example of each update draws its own parameters from `(seed, update, slot)`, so a run is
/// reproducible and the same image is augmented differently every time it is drawn.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EncoderAugment {
    /// Photometric ranges and probabilities.
    pub photometric: veila_data::augment::Photometric,
    /// Crop-and-zoom probability and zoom range.
    pub crop_zoom: veila_data::augment::CropZoomRange,
}

impl EncoderAugment {
    /// Augments one `h x w` example in place with the parameters drawn from `seed`.
    pub fn apply(&self, ex: &mut EncoderExample, (h, w): (usize, usize), seed: u64) -> Result<()> {
        let img = veila_data::augment::rgb_image_from_raw(
            w as u32,
            h as u32,
            std::mem::take(&mut ex.rgb),
        )?;
        let crop = self.crop_zoom.draw(w as u32, h as u32, seed)?;
        let img = if crop != veila_data::augment::CropZoom::identity(w as u32, h as u32) {
            if let Some(cam) = ex.camera.as_mut() {
                let cropped = crop.camera(cam)?;
                *cam = PinholeCamera {
                    cam_from_lidar: glam::Mat4::from_scale(glam::Vec3::splat(1.0 / crop.scale))
                        * cropped.cam_from_lidar,
                    ..cropped
                };
            }
            if let Some(l) = ex.labels.as_mut() {
                *l = crop.resample_nearest(l, w as u32, h as u32)?;
            }
            if !ex.depth_m.is_empty() {
                let inv = 1.0 / crop.scale;
                ex.depth_m = crop
                    .resample_nearest(&ex.depth_m, w as u32, h as u32)?
                    .into_iter()
                    .map(|d| d * inv)
                    .collect();
            }
            crop.resample_rgb(&img)?
        } else {
            img
        };
        ex.rgb = self
            .photometric
            .augment(&img, seed ^ 0x6a09_e667_f3bc_c909)?
            .into_raw();
        Ok(())
    }
}

fn augment_seed(seed: u64, step: usize, slot: usize) -> u64 {
    let mut z = seed
        ^ (step as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (slot as u64).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Trains a [`SmallCnn`] on images with per-pixel targets: `images[i]` is `h * w * 3` RGB bytes,
/// `labels[i]` (class ids of the learning map) and/or `depth_m[i]` (metres, 0 = no ground truth)
/// `h * w` values, `cameras[i]` the image's camera (needed when `cfg` has the ground prior,
/// ignored otherwise). AdamW with a cosine learning rate, seeded batches; returns the network and its
/// `VarMap`. With `augment`, every drawn example is augmented first ([`EncoderAugment`]).
/// [`train_small_cnn_from`] reads the examples on demand instead.
#[allow(clippy::too_many_arguments)]
pub fn train_small_cnn(
    cfg: &SmallCnnConfig,
    images: &[Vec<u8>],
    labels: Option<&[Vec<u32>]>,
    depth_m: Option<&[Vec<f32>]>,
    cameras: Option<&[PinholeCamera]>,
    hw: (usize, usize),
    steps: usize,
    batch_size: usize,
    lr: f64,
    seed: u64,
    augment: Option<&EncoderAugment>,
    device: &Device,
    on_step: impl FnMut(EncoderStep),
) -> Result<(SmallCnn, VarMap)> {
    if let Some(c) = cameras
        && c.len() != images.len()
    {
        return Err(Error::Data(format!(
            "encoder training: {} images but {} cameras",
            images.len(),
            c.len()
        )));
    }
    let get = |i: usize| -> Result<EncoderExample> {
        Ok(EncoderExample {
            rgb: images[i].clone(),
            camera: cameras.map(|c| c[i]),
            labels: labels.map(|l| l[i].clone()),
            depth_m: depth_m.map(|d| d[i].clone()).unwrap_or_default(),
        })
    };
    train_small_cnn_from(
        cfg,
        images.len(),
        &get,
        (labels.is_some(), depth_m.is_some()),
        hw,
        steps,
        batch_size,
        lr,
        seed,
        augment,
        device,
        on_step,
    )
}

/// [`train_small_cnn`] on `n` examples read by `get` when a batch needs them (bounded memory);
/// `(labels, depth)` says which targets the loss uses. The same examples give the same weights.
#[allow(clippy::too_many_arguments)]
pub fn train_small_cnn_from(
    cfg: &SmallCnnConfig,
    n: usize,
    get: &dyn Fn(usize) -> Result<EncoderExample>,
    (use_labels, use_depth): (bool, bool),
    (h, w): (usize, usize),
    steps: usize,
    batch_size: usize,
    lr: f64,
    seed: u64,
    augment: Option<&EncoderAugment>,
    device: &Device,
    mut on_step: impl FnMut(EncoderStep),
) -> Result<(SmallCnn, VarMap)> {
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
        let mut batch = idx.iter().map(|&i| get(i)).collect::<Result<Vec<_>>>()?;
        if let Some(a) = augment {
            for (slot, e) in batch.iter_mut().enumerate() {
                a.apply(e, (h, w), augment_seed(seed, step, slot))?;
            }
        }
        // colours, and the ground prior of each (augmented) example's camera when configured
        let imgs = batch
            .iter()
            .map(|e| Ok(cfg.input_tensor(&e.rgb, h, w, e.camera.as_ref(), device)?))
            .collect::<Result<Vec<_>>>()?;
        let image = Tensor::cat(&imgs, 0)?;
        // random horizontal flips (targets flipped with the image)
        let flip = rng.random_bool(0.5);
        let image = if flip { flip_w(&image)? } else { image };
        let lab = if use_labels {
            let mut rows: Vec<u32> = Vec::with_capacity(batch_size * h * w);
            for e in &batch {
                let l = e.labels.as_ref().ok_or_else(|| {
                    Error::Data(
                        "the semantic encoder needs per-pixel train ids: an example has none"
                            .into(),
                    )
                })?;
                rows.extend_from_slice(l);
            }
            let t = Tensor::from_vec(rows, (batch_size, h, w), device)?;
            Some(if flip { flip_w(&t)? } else { t })
        } else {
            None
        };
        let dep = if use_depth {
            let rows: Vec<f32> = batch
                .iter()
                .flat_map(|e| e.depth_m.iter().copied())
                .collect();
            let t = Tensor::from_vec(rows, (batch_size, h, w), device)?;
            Some(if flip { flip_w(&t)? } else { t })
        } else {
            None
        };
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
