//! Training a [`Bundle`](super::Bundle)'s generative networks on examples: the denoiser and the
//! mean network of residual diffusion ([`fit_denoiser`], with [`DenoiserTraining`] computing the
//! frozen encoder features once per example in memory or per batch when streamed), and the whole
//! generative part of a bundle ([`fit_bundle`]). The residual targets and the frozen mean network
//! are [`super::mean`]; the small CNN encoders' training is [`super::encoder_train`].
//! [`super::recipe`] strings these into the one training recipe the binaries share.
//!
//! Everything is seeded: the same inputs and seed give the same weights.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarMap;
use veila_geom::PinholeCamera;
use veila_nn::encoders::kind::AnyEncoder;
use veila_nn::{Denoiser as Net, GcmaGeometry};

use super::bundle::BundleConfig;
use super::dataset::{ExampleSource, Examples, Order, Prefetcher, Rigs};
pub use super::dataset::{TrainExample, TrainView};
use super::generate::{ViewFeatures, encode_views};
use super::mean::{
    MeanPredictor, loss_weight, predict_means, residual_scale, residual_scale_of, residual_target,
};
use super::nn::{NetCond, VeilaDenoiser};
use super::stage::{Stage, encode_examples, has_gcma, num_views, rig_condition, stage_config};
use crate::error::{Error, Result};
use crate::objective::Diffusion;
use crate::trainer::distributed::{Parallel, ProcessGroup};
use crate::trainer::{Batch, BatchSource, FitSummary, TrainConfig, TrainObserver, Trainer};

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
            if let Some(wt) = loss_weight(config, stage, &ex.x0, h * w) {
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
                weights: (!weights.is_empty()).then_some(weights),
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
        let weight = examples
            .iter()
            .map(|e| loss_weight(config, st.stage, &e.x0, h * w))
            .collect::<Option<Vec<_>>>()
            .map(|wt| Tensor::from_vec(wt.concat(), (b, c, h, w), dev))
            .transpose()?;
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
        // another model's weights (another width, say) would otherwise leave the run at its
        // seeded start without a word: a fine-tune takes most of what it is given
        if 2 * initialised < init.len() {
            return Err(Error::InvalidConfig {
                field: "init",
                reason: format!(
                    "only {initialised} of the {} tensors given to start the {} from fit it by name and \
                     shape: they are another model's",
                    init.len(),
                    fit.stage.name()
                ),
            });
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
    net.set_recompute_blocks(
        fit.train.activation_checkpointing == crate::trainer::ActivationCheckpointing::Block,
    );
    let mut trainer = Trainer::new(
        VeilaDenoiser::new(net),
        varmap,
        Diffusion::new(diffusion)?,
        fit.train.clone(),
    )?;
    trainer.set_fused_adamw(Some(crate::app::nn::fused_adamw()));
    if let Some(p) = fit.parallel {
        trainer.set_communicator(p.communicator());
    }
    let resumed: Option<PathBuf> =
        trainer.resume_latest(fit.checkpoint_dir, super::nn::read_checkpoint_tensors)?;
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
