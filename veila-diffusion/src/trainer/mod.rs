//! Training loop: AdamW, warm-up + cosine learning rate, EMA weights, gradient clipping by global
//! norm, condition dropout, deterministic seeding, atomic checkpoints with exact resume, progress and
//! sample-preview callbacks.
//!
//! The trainer is generic over the model (any [`Denoiser`] whose parameters live in a
//! [`candle_nn::VarMap`]) and over the data ([`BatchSource`], e.g. a closure `step -> Batch`).
//!
//! **Exact resume.** Everything that influences the next update is in the checkpoint: weights, EMA
//! weights, AdamW moments and step counter, the step, and the position of the trainer's ChaCha8
//! stream (which draws timesteps, noise and condition-dropout masks). Data sources get the step
//! number, so a source that is a function of the step (a seeded shuffle per epoch, say) resumes
//! exactly too.
//!
//! # Example
//!
//! A one-parameter "network" trained for a few steps on a step-indexed data source:
//!
//! ```
//! use candle_core::{DType, Device, Tensor};
//! use candle_nn::{VarBuilder, VarMap};
//! use veila_diffusion::{Batch, Denoiser, Diffusion, DiffusionConfig, TrainConfig, Trainer};
//!
//! struct Scale(Tensor);
//! impl Denoiser for Scale {
//!     type Cond = ();
//!     fn forward(&self, x: &Tensor, _t: &Tensor, _c: Option<&()>) -> candle_core::Result<Tensor> {
//!         x.broadcast_mul(&self.0)
//!     }
//! }
//!
//! # fn main() -> veila_diffusion::Result<()> {
//! let varmap = VarMap::new();
//! let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
//! let model = Scale(vb.get_with_hints(1, "scale", candle_nn::Init::Const(0.0))?);
//! let config = TrainConfig { total_steps: 5, warmup_steps: 1, checkpoint_every: None, ..TrainConfig::default() };
//! let mut trainer = Trainer::new(model, varmap, Diffusion::new(DiffusionConfig::default())?, config)?;
//! let mut data = |_step: u64| -> veila_diffusion::Result<Batch<()>> {
//!     Ok(Batch { x0: Tensor::zeros((4, 1, 2, 8), DType::F32, &Device::Cpu)?, cond: None, weight: None })
//! };
//! let summary = trainer.fit(&mut data, None, &mut ())?;
//! assert_eq!((summary.steps_run, trainer.step()), (5, 5));
//! assert!(summary.mean_loss.is_finite());
//! # Ok(())
//! # }
//! ```

mod checkpoint;
pub mod distributed;
mod lr;
mod optim;

pub use checkpoint::{
    CheckpointState, RUN_RECORD_FILE, RngState, TensorFileReader, claim_checkpoint_dir,
    find_latest_checkpoint,
};
pub use lr::LrSchedule;
pub use optim::{AdamSlot, AdamW, FusedAdamW, ParamsAdamW};

use std::collections::HashMap;
use std::ops::ControlFlow;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{Tensor, Var};
use candle_nn::VarMap;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::denoiser::{CondDropout, Denoiser};
use crate::error::{Error, Result, invalid};
use crate::objective::Diffusion;

/// Training hyper-parameters.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    /// Seed of the trainer's RNG (timesteps, noise, dropout masks).
    pub seed: u64,
    /// Peak learning rate.
    pub lr: f64,
    /// Learning rate at the end of the cosine.
    pub min_lr: f64,
    /// Linear warm-up steps.
    pub warmup_steps: u64,
    /// Total number of steps ([`Trainer::fit`] stops there; the cosine ends there).
    pub total_steps: u64,
    /// AdamW β₁.
    pub beta1: f64,
    /// AdamW β₂.
    pub beta2: f64,
    /// AdamW ε.
    pub adam_eps: f64,
    /// AdamW decoupled weight decay.
    pub weight_decay: f64,
    /// EMA decay (e.g. 0.9999 for long runs; 0 disables averaging: EMA = weights).
    pub ema_decay: f64,
    /// Use `min(decay, (1 + n)/(10 + n))` for the n-th update, so early EMA follows the weights.
    pub ema_warmup: bool,
    /// Clip the global gradient norm to this.
    pub grad_clip_norm: Option<f64>,
    /// Per-sample condition dropout probability for classifier-free guidance (0 = off).
    pub cond_drop_prob: f64,
    /// Skip (instead of failing on) steps with a non-finite loss or gradient norm.
    pub skip_non_finite: bool,
    /// Save a checkpoint every this many steps (and at the end) when `fit` gets a directory.
    pub checkpoint_every: Option<u64>,
    /// Keep only the newest this many checkpoints.
    pub keep_checkpoints: Option<usize>,
    /// Call [`TrainObserver::on_preview`] every this many steps.
    pub preview_every: Option<u64>,
    /// Gradient accumulation: every update runs this many forward/backward passes, each on one
    /// part of the batch ([`BatchSource::batch_part`]), and steps on their example-weighted mean
    /// gradient. The update equals one on the whole batch (up to float rounding and the order of
    /// the random draws) at the activation memory of one part. 1: no accumulation.
    #[serde(default = "one")]
    pub grad_accum_steps: u64,
    /// The activations' precision. The weights, their gradients, the optimizer state and the
    /// EMA stay f32 in every mode, so a checkpoint resumes in any mode. Left out of the JSON when
    /// f32, so the run records of runs made before this field existed still match.
    #[serde(default, skip_serializing_if = "Precision::is_f32")]
    pub precision: Precision,
    /// Activation checkpointing of the network's blocks (each block recomputed in the backward pass): `block`
    /// recomputes each block in the backward pass, trading a second forward pass of it for
    /// keeping only its inputs. The gradients are the same. Left out of the JSON when off.
    #[serde(default, skip_serializing_if = "is_no_checkpointing")]
    pub activation_checkpointing: ActivationCheckpointing,
}

fn is_no_checkpointing(a: &ActivationCheckpointing) -> bool {
    *a == ActivationCheckpointing::None
}

/// Whether and where the network recomputes activations in its backward pass (the app layer
/// switches the network; the trainer merges what it leaves through [`Denoiser::finish_backward`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ActivationCheckpointing {
    /// Keep every activation (fastest, most memory).
    #[default]
    None,
    /// Recompute each residual block, GCMA and PFC layer in the backward pass.
    Block,
}

impl ActivationCheckpointing {
    /// The name used in configs and on the command line (`none`, `block`).
    pub fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Block => "block",
        }
    }
}

impl std::str::FromStr for ActivationCheckpointing {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "none" => Ok(Self::None),
            "block" => Ok(Self::Block),
            other => Err(invalid(
                "activation_checkpointing",
                format!("activation checkpointing `{other}`: expected `none` or `block`"),
            )),
        }
    }
}

/// The precision of a training run's forward and backward passes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// f32 throughout.
    #[default]
    F32,
    /// Mixed precision: bf16 activations on f32 master weights ([`crate::denoiser::Autocast`]),
    /// normalisations, softmaxes, bias sums and the loss in f32. bf16 keeps f32's exponent
    /// range, so no loss scaling is needed. Meant for GPUs: candle's CPU backend has no bf16
    /// convolution kernels and widens bf16 matrix products to f32, so on a CPU it is slower
    /// than f32 (it still runs, which is what the tests use).
    Bf16,
}

impl Precision {
    /// Whether this is [`Precision::F32`] (the default).
    pub fn is_f32(&self) -> bool {
        *self == Self::F32
    }

    /// The dtype of the activations.
    pub fn dtype(self) -> candle_core::DType {
        match self {
            Self::F32 => candle_core::DType::F32,
            Self::Bf16 => candle_core::DType::BF16,
        }
    }

    /// The name used in configs and on command lines (`f32`, `bf16`).
    pub fn name(self) -> &'static str {
        match self {
            Self::F32 => "f32",
            Self::Bf16 => "bf16",
        }
    }
}

impl std::str::FromStr for Precision {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "f32" => Ok(Self::F32),
            "bf16" => Ok(Self::Bf16),
            other => Err(invalid(
                "precision",
                format!("`{other}` is not one of f32, bf16"),
            )),
        }
    }
}

fn one() -> u64 {
    1
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            seed: 0,
            lr: 2e-4,
            min_lr: 0.0,
            warmup_steps: 1000,
            total_steps: 100_000,
            beta1: 0.9,
            beta2: 0.999,
            adam_eps: 1e-8,
            weight_decay: 0.0,
            ema_decay: 0.9999,
            ema_warmup: true,
            grad_clip_norm: Some(1.0),
            cond_drop_prob: 0.1,
            skip_non_finite: true,
            checkpoint_every: Some(5000),
            keep_checkpoints: Some(3),
            preview_every: None,
            grad_accum_steps: 1,
            precision: Precision::F32,
            activation_checkpointing: ActivationCheckpointing::None,
        }
    }
}

impl TrainConfig {
    /// Checks the domains.
    pub fn validate(&self) -> Result<()> {
        let pos = |v: f64| v.is_finite() && v > 0.0;
        if !pos(self.lr) {
            return Err(invalid(
                "lr",
                format!("must be finite and > 0, got {}", self.lr),
            ));
        }
        if !(self.min_lr.is_finite() && self.min_lr >= 0.0 && self.min_lr <= self.lr) {
            return Err(invalid(
                "min_lr",
                format!("must be in [0, lr], got {}", self.min_lr),
            ));
        }
        for (name, v) in [("beta1", self.beta1), ("beta2", self.beta2)] {
            if !(0.0..1.0).contains(&v) {
                return Err(invalid(name, format!("must be in [0, 1), got {v}")));
            }
        }
        if !pos(self.adam_eps) {
            return Err(invalid("adam_eps", "must be finite and > 0"));
        }
        if !(self.weight_decay.is_finite() && self.weight_decay >= 0.0) {
            return Err(invalid("weight_decay", "must be finite and >= 0"));
        }
        if !(0.0..1.0).contains(&self.ema_decay) {
            return Err(invalid(
                "ema_decay",
                format!("must be in [0, 1), got {}", self.ema_decay),
            ));
        }
        if let Some(c) = self.grad_clip_norm
            && !pos(c)
        {
            return Err(invalid(
                "grad_clip_norm",
                format!("must be finite and > 0, got {c}"),
            ));
        }
        if !(0.0..=1.0).contains(&self.cond_drop_prob) {
            return Err(invalid("cond_drop_prob", "must be in [0, 1]"));
        }
        if self.checkpoint_every == Some(0) || self.preview_every == Some(0) {
            return Err(invalid(
                "checkpoint_every/preview_every",
                "must be at least 1",
            ));
        }
        if self.grad_accum_steps == 0 {
            return Err(invalid("grad_accum_steps", "must be at least 1"));
        }
        if self.keep_checkpoints == Some(0) {
            return Err(invalid("keep_checkpoints", "must be at least 1"));
        }
        Ok(())
    }

    /// The learning-rate schedule these settings describe.
    pub fn lr_schedule(&self) -> LrSchedule {
        LrSchedule {
            base_lr: self.lr,
            warmup_steps: self.warmup_steps,
            total_steps: self.total_steps,
            min_lr: self.min_lr,
        }
    }
}

/// One training batch.
#[derive(Debug, Clone)]
pub struct Batch<C> {
    /// Encoded clean range images `[B, C, H, W]`.
    pub x0: Tensor,
    /// Conditioning for the batch (`None` for unconditional training).
    pub cond: Option<C>,
    /// Per-element loss weights broadcastable to `x0` (`None`: all 1); see
    /// [`Diffusion::training_loss_weighted`].
    pub weight: Option<Tensor>,
}

/// Where batches come from. `step` is the 0-based index of the update the batch is for; a source
/// that is a pure function of `step` makes resumed runs identical to uninterrupted ones.
pub trait BatchSource<C> {
    /// The batch for update `step`.
    fn batch(&mut self, step: u64) -> Result<Batch<C>>;

    /// Part `part` of `parts` of the batch of update `step` (gradient accumulation,
    /// [`TrainConfig::grad_accum_steps`]): the parts are disjoint and together the whole batch.
    /// The default splits [`Self::batch`] along the batch axis into contiguous parts whose sizes
    /// differ by at most one; it cannot split a conditioning, so conditional sources implement
    /// this themselves.
    fn batch_part(&mut self, step: u64, part: usize, parts: usize) -> Result<Batch<C>> {
        let batch = self.batch(step)?;
        if parts == 1 {
            return Ok(batch);
        }
        if batch.cond.is_some() {
            return Err(invalid(
                "grad_accum_steps",
                "this data source cannot split a conditioned batch into parts; implement BatchSource::batch_part",
            ));
        }
        let b = batch.x0.dim(0)?;
        let (start, len) = part_range(b, part, parts)?;
        let weight = match &batch.weight {
            Some(w) if w.dim(0)? == b && b > 1 => Some(w.narrow(0, start, len)?),
            other => other.clone(),
        };
        Ok(Batch {
            x0: batch.x0.narrow(0, start, len)?,
            cond: None,
            weight,
        })
    }
}

/// The examples `start..start + len` of part `part` of `parts` of a batch of `b`: contiguous
/// parts whose sizes differ by at most one (the first `b % parts` are one longer).
pub fn part_range(b: usize, part: usize, parts: usize) -> Result<(usize, usize)> {
    if parts == 0 || part >= parts || b < parts {
        return Err(invalid(
            "grad_accum_steps",
            format!(
                "part {part} of {parts} of a batch of {b}: every part needs at least one example"
            ),
        ));
    }
    let (q, r) = (b / parts, b % parts);
    Ok((part * q + part.min(r), q + usize::from(part < r)))
}

impl<C, F: FnMut(u64) -> Result<Batch<C>>> BatchSource<C> for F {
    fn batch(&mut self, step: u64) -> Result<Batch<C>> {
        self(step)
    }
}

/// What one update did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepStats {
    /// Number of updates done after this one.
    pub step: u64,
    /// Weighted loss of the batch.
    pub loss: f64,
    /// Learning rate used.
    pub lr: f64,
    /// Global gradient norm before clipping (NaN when the loss was non-finite).
    pub grad_norm: f64,
    /// Whether clipping scaled the gradient.
    pub clipped: bool,
    /// Whether the update was skipped (non-finite loss or gradient).
    pub skipped: bool,
    /// Batch size.
    pub batch_size: usize,
    /// Wall time of this step in seconds (data loading excluded).
    pub step_secs: f64,
    /// Samples per second of this step.
    pub samples_per_sec: f64,
}

/// The loss of a run's updates averaged for progress lines: an exponential moving average
/// (weight 0.02 per update) of the finite losses.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LossAverage(Option<f64>);

impl LossAverage {
    /// The average (NaN before the first finite loss).
    pub fn value(&self) -> f64 {
        self.0.unwrap_or(f64::NAN)
    }

    /// Takes in update `s` and returns its progress line:
    /// `loss L (avg A) lr R S s/step`.
    pub fn line(&mut self, s: &StepStats) -> String {
        if s.loss.is_finite() {
            self.0 = Some(match self.0 {
                None => s.loss,
                Some(e) => 0.98 * e + 0.02 * s.loss,
            });
        }
        format!(
            "loss {:.4} (avg {:.4}) lr {:.2e} {:.2} s/step",
            s.loss,
            self.value(),
            s.lr,
            s.step_secs
        )
    }
}

/// Callbacks from [`Trainer::fit`]; every method has a no-op default.
pub trait TrainObserver<M: Denoiser> {
    /// After every update (draw the progress bar here). Return `Break` to stop early.
    fn on_step(&mut self, _stats: &StepStats) -> ControlFlow<()> {
        ControlFlow::Continue(())
    }

    /// Every `preview_every` steps, with the EMA weights loaded into `model` (restored afterwards).
    fn on_preview(&mut self, _step: u64, _model: &M, _diffusion: &Diffusion) -> Result<()> {
        Ok(())
    }

    /// After a checkpoint was written.
    fn on_checkpoint(&mut self, _step: u64, _path: &Path) {}
}

/// The do-nothing observer.
impl<M: Denoiser> TrainObserver<M> for () {}

/// Summary of a [`Trainer::fit`] call.
#[derive(Debug, Clone, PartialEq)]
pub struct FitSummary {
    /// Updates performed in this call.
    pub steps_run: u64,
    /// The trainer's step afterwards.
    pub final_step: u64,
    /// Mean loss over this call's non-skipped updates (NaN if none).
    pub mean_loss: f64,
    /// Skipped updates in this call.
    pub skipped: u64,
    /// Whether the observer stopped the run.
    pub stopped_early: bool,
    /// Checkpoints written in this call.
    pub checkpoints: Vec<PathBuf>,
    /// The run's training clock afterwards (all resumed runs together).
    pub clock: Clock,
}

impl FitSummary {
    /// [`mean_loss`](Self::mean_loss) for a log line: four decimals, or `-` when this call ran no
    /// update (a run resumed at its last step), instead of NaN.
    pub fn mean_loss_text(&self) -> String {
        if self.steps_run == 0 {
            "- (no update this run)".to_string()
        } else {
            format!("{:.4}", self.mean_loss)
        }
    }
}

/// Wall time a training run has spent in [`Trainer::fit`], carried through its checkpoints.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Clock {
    /// Seconds counted.
    pub seconds: f64,
    /// The step counting began at (0 unless the run began in a build that kept no clock).
    pub from_step: u64,
}

/// The trainer. Owns the model, its `VarMap`, the optimizer, the EMA weights and the RNG.
pub struct Trainer<M: Denoiser> {
    model: M,
    varmap: VarMap,
    diffusion: Diffusion,
    config: TrainConfig,
    names: Vec<String>,
    vars: Vec<Var>,
    ema: Vec<Tensor>,
    opt: AdamW,
    step: u64,
    skipped: u64,
    rng: ChaCha8Rng,
    clock: Clock,
    comm: Option<Box<dyn distributed::Communicator>>,
}

impl<M: Denoiser> std::fmt::Debug for Trainer<M> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Trainer")
            .field("step", &self.step)
            .field("skipped", &self.skipped)
            .field("parameters", &self.names.len())
            .field("config", &self.config)
            .field("diffusion", &self.diffusion)
            .finish_non_exhaustive()
    }
}

impl<M: Denoiser> Trainer<M> {
    /// Creates a trainer. `varmap` must hold `model`'s parameters (build the model with
    /// `VarBuilder::from_varmap(&varmap, ..)`); variables are handled in name order.
    pub fn new(
        model: M,
        varmap: VarMap,
        diffusion: Diffusion,
        config: TrainConfig,
    ) -> Result<Self> {
        config.validate()?;
        let mut named: Vec<(String, Var)> = {
            let data = varmap
                .data()
                .lock()
                .map_err(|_| invalid("varmap", "the VarMap lock is poisoned"))?;
            data.iter().map(|(k, v)| (k.clone(), v.clone())).collect()
        };
        named.retain(|(_, v)| v.dtype().is_float());
        named.sort_by(|a, b| a.0.cmp(&b.0));
        if named.is_empty() {
            return Err(invalid(
                "varmap",
                "holds no float variables; build the model from it first",
            ));
        }
        let names: Vec<String> = named.iter().map(|(n, _)| n.clone()).collect();
        let vars: Vec<Var> = named.iter().map(|(_, v)| v.clone()).collect();
        let ema = vars
            .iter()
            .map(|v| Ok(v.as_tensor().copy()?.detach()))
            .collect::<Result<Vec<_>>>()?;
        let opt = AdamW::new(
            named,
            ParamsAdamW {
                lr: config.lr,
                beta1: config.beta1,
                beta2: config.beta2,
                eps: config.adam_eps,
                weight_decay: config.weight_decay,
            },
        )?;
        let rng = ChaCha8Rng::seed_from_u64(config.seed);
        Ok(Self {
            model,
            varmap,
            diffusion,
            config,
            names,
            vars,
            ema,
            opt,
            step: 0,
            skipped: 0,
            rng,
            clock: Clock::default(),
            comm: None,
        })
    }

    /// Trains data-parallel with the other ranks of `comm` (see [`distributed`]): every update
    /// averages the gradients and the loss over the ranks, so all ranks take the same step, and
    /// the noise of update `s` comes from a ChaCha8 stream seeded by `(seed, s, rank)` (no
    /// generator state to carry, so resumes stay exact). Each rank passes its own share of the
    /// global batch ([`distributed::ProcessGroup::shard`]); only rank 0 writes checkpoints. A
    /// world of one changes nothing.
    pub fn set_communicator(&mut self, comm: Box<dyn distributed::Communicator>) {
        self.comm = (comm.world_size() > 1).then_some(comm);
    }

    /// Runs the optimizer's updates through `fused` where it accepts the parameters
    /// ([`AdamW::set_fused`]; the application layer passes `veila-nn`'s one-launch GPU AdamW).
    pub fn set_fused_adamw(&mut self, fused: Option<std::sync::Arc<FusedAdamW>>) {
        self.opt.set_fused(fused);
    }

    /// This trainer's rank (0 without a communicator).
    pub fn rank(&self) -> usize {
        self.comm.as_ref().map_or(0, |c| c.rank())
    }

    /// The model (current, non-averaged weights).
    pub fn model(&self) -> &M {
        &self.model
    }

    /// The variable map.
    pub fn varmap(&self) -> &VarMap {
        &self.varmap
    }

    /// The diffusion process.
    pub fn diffusion(&self) -> &Diffusion {
        &self.diffusion
    }

    /// The settings.
    pub fn config(&self) -> &TrainConfig {
        &self.config
    }

    /// Replaces the settings (e.g. a longer `total_steps` when continuing a run).
    pub fn set_config(&mut self, config: TrainConfig) -> Result<()> {
        config.validate()?;
        self.config = config;
        Ok(())
    }

    /// Updates done so far.
    pub fn step(&self) -> u64 {
        self.step
    }

    /// Updates skipped so far (non-finite loss or gradient).
    pub fn skipped_steps(&self) -> u64 {
        self.skipped
    }

    /// The run's training clock: wall seconds spent in [`Self::fit`], over every resumed run.
    pub fn clock(&self) -> Clock {
        self.clock
    }

    /// The learning rate the next update will use.
    pub fn next_lr(&self) -> f64 {
        self.config.lr_schedule().lr_at(self.step)
    }

    /// Parameter names, sorted.
    pub fn parameter_names(&self) -> &[String] {
        &self.names
    }

    /// A snapshot (copy) of the current weights by name.
    pub fn weights(&self) -> Result<HashMap<String, Tensor>> {
        self.names
            .iter()
            .zip(&self.vars)
            .map(|(n, v)| Ok((n.clone(), v.as_tensor().copy()?)))
            .collect()
    }

    /// The EMA weights by name (same names as the model's variables: loadable into it directly).
    pub fn ema_weights(&self) -> HashMap<String, Tensor> {
        self.names
            .iter()
            .cloned()
            .zip(self.ema.iter().cloned())
            .collect()
    }

    /// Runs `f` with the EMA weights loaded into the model, restoring the training weights after
    /// (also when `f` fails).
    pub fn with_ema_weights<R>(&self, f: impl FnOnce(&M) -> Result<R>) -> Result<R> {
        let backup = self
            .vars
            .iter()
            .map(|v| Ok(v.as_tensor().copy()?))
            .collect::<Result<Vec<_>>>()?;
        for (v, e) in self.vars.iter().zip(&self.ema) {
            v.set(e)?;
        }
        let out = f(&self.model);
        for (v, b) in self.vars.iter().zip(&backup) {
            v.set(b)?;
        }
        out
    }

    /// One update on `batch`.
    pub fn train_step(&mut self, batch: &Batch<M::Cond>) -> Result<StepStats> {
        let started = Instant::now();
        let _span = tracing::debug_span!("train_step", step = self.step).entered();
        let b = batch.x0.dim(0)?;
        let (lr, dropout) = self.begin_step();
        let (loss_t, loss) = self.batch_loss(batch, dropout)?;
        let grads = if loss.is_finite() {
            let mut grads = loss_t.backward()?;
            self.model.finish_backward(&mut grads)?;
            Some(grads)
        } else {
            None
        };
        self.finish_step(started, b, loss, grads, lr)
    }

    /// One update accumulated over `parts` parts of a batch (see
    /// [`TrainConfig::grad_accum_steps`]): `part(k)` gives part `k`; each part's forward and
    /// backward pass runs and is freed before the next, and the update steps on the mean gradient
    /// weighted by the parts' sizes (the gradient of the whole batch's mean loss). The loss
    /// reported is the whole batch's. One part is [`Self::train_step`].
    pub fn train_step_accumulated(
        &mut self,
        parts: usize,
        mut part: impl FnMut(usize) -> Result<Batch<M::Cond>>,
    ) -> Result<StepStats> {
        if parts <= 1 {
            let batch = part(0)?;
            return self.train_step(&batch);
        }
        let started = Instant::now();
        let _span =
            tracing::debug_span!("train_step_accumulated", step = self.step, parts).entered();
        let (lr, dropout) = self.begin_step();
        let mut sum: Vec<Option<Tensor>> = vec![None; self.vars.len()];
        let (mut total, mut loss_sum, mut finite) = (0usize, 0f64, true);
        for k in 0..parts {
            let batch = part(k)?;
            let b = batch.x0.dim(0)?;
            total += b;
            if !finite {
                continue;
            }
            let (loss_t, loss) = self.batch_loss(&batch, dropout)?;
            if !loss.is_finite() {
                finite = false;
                continue;
            }
            loss_sum += loss * b as f64;
            let mut grads = loss_t.backward()?;
            self.model.finish_backward(&mut grads)?;
            for (acc, v) in sum.iter_mut().zip(&self.vars) {
                if let Some(g) = grads.get(v.as_tensor()) {
                    let g = g.to_dtype(candle_core::DType::F32)?.affine(b as f64, 0.0)?;
                    *acc = Some(match acc.take() {
                        Some(a) => (a + g)?,
                        None => g,
                    });
                }
            }
        }
        let (loss, grads) = if finite {
            let mut store = candle_core::backprop::GradStore::default();
            for (acc, v) in sum.into_iter().zip(&self.vars) {
                if let Some(a) = acc {
                    let mean = a
                        .affine(1.0 / total as f64, 0.0)?
                        .to_dtype(v.as_tensor().dtype())?;
                    store.insert(v.as_tensor(), mean);
                }
            }
            (loss_sum / total as f64, Some(store))
        } else {
            (f64::NAN, None)
        };
        self.finish_step(started, total, loss, grads, lr)
    }

    /// The loss of `batch` (drawing its noise from the trainer's stream), as a tensor and a value.
    fn batch_loss(
        &mut self,
        batch: &Batch<M::Cond>,
        dropout: Option<CondDropout>,
    ) -> Result<(Tensor, f64)> {
        // f32 data in an f32 run: Autocast passes straight through
        let model = crate::denoiser::Autocast {
            inner: &self.model,
            dtype: self.config.precision.dtype(),
        };
        let out = self.diffusion.training_loss_weighted(
            &model,
            &batch.x0,
            batch.weight.as_ref(),
            batch.cond.as_ref(),
            dropout,
            &mut self.rng,
        )?;
        let loss = out
            .loss
            .to_dtype(candle_core::DType::F64)?
            .to_scalar::<f64>()?;
        Ok((out.loss, loss))
    }

    /// The learning rate and condition dropout of the coming update; under a communicator, the
    /// random stream of `(seed, step, rank)`.
    fn begin_step(&mut self) -> (f64, Option<CondDropout>) {
        let lr = self.config.lr_schedule().lr_at(self.step);
        let dropout = (self.config.cond_drop_prob > 0.0).then_some(CondDropout {
            prob: self.config.cond_drop_prob,
        });
        if let Some(c) = &self.comm {
            // a stream per (seed, step, rank): ranks draw different noise, and a resumed rank
            // draws what it would have drawn
            let mut rng = ChaCha8Rng::seed_from_u64(self.config.seed);
            rng.set_stream(((c.rank() as u64) << 40) ^ self.step);
            self.rng = rng;
        }
        (lr, dropout)
    }

    /// Applies the local gradients `grads` of a batch of `b` with loss `loss` (`None` when the
    /// loss was not finite): averaged over the ranks under a communicator, clipped, stepped.
    fn finish_step(
        &mut self,
        started: Instant,
        b: usize,
        loss: f64,
        grads: Option<candle_core::backprop::GradStore>,
        lr: f64,
    ) -> Result<StepStats> {
        let mut stats = StepStats {
            step: self.step + 1,
            loss,
            lr,
            grad_norm: f64::NAN,
            clipped: false,
            skipped: false,
            batch_size: b,
            step_secs: 0.0,
            samples_per_sec: 0.0,
        };
        if self.comm.is_some() {
            self.distributed_update(grads, loss, lr, &mut stats)?;
        } else if let Some(grads) = grads {
            // one device sync for the global norm, not one per parameter
            let mut sums = Vec::with_capacity(self.vars.len());
            for v in &self.vars {
                if let Some(g) = grads.get(v.as_tensor()) {
                    sums.push(g.to_dtype(candle_core::DType::F32)?.sqr()?.sum_all()?);
                }
            }
            let norm = if sums.is_empty() {
                0.0
            } else {
                (Tensor::stack(&sums, 0)?.sum_all()?.to_scalar::<f32>()? as f64).sqrt()
            };
            stats.grad_norm = norm;
            self.apply_update(&grads, norm, lr, &mut stats)?;
        } else {
            stats.skipped = true;
        }
        if stats.skipped {
            if !self.config.skip_non_finite {
                let what = if loss.is_finite() {
                    "gradient norm"
                } else {
                    "loss"
                };
                return Err(Error::NonFinite {
                    what,
                    step: self.step,
                });
            }
            self.skipped += 1;
            tracing::warn!(
                step = self.step,
                loss,
                "skipping update with non-finite loss or gradient"
            );
        }
        self.step += 1;
        stats.step_secs = started.elapsed().as_secs_f64();
        stats.samples_per_sec = b as f64 / stats.step_secs.max(1e-9);
        Ok(stats)
    }

    /// Clips by `norm` and steps the optimizer and the EMA (or marks the update skipped when the
    /// norm is not finite).
    fn apply_update(
        &mut self,
        grads: &candle_core::backprop::GradStore,
        norm: f64,
        lr: f64,
        stats: &mut StepStats,
    ) -> Result<()> {
        if norm.is_finite() {
            let scale = match self.config.grad_clip_norm {
                Some(c) if norm > c => {
                    stats.clipped = true;
                    c / (norm + 1e-6)
                }
                _ => 1.0,
            };
            self.opt.set_learning_rate(lr);
            self.opt.step(grads, scale)?;
            self.update_ema()?;
        } else {
            stats.skipped = true;
        }
        Ok(())
    }

    /// The data-parallel update: every rank contributes its gradients (zeros and a flag when its
    /// loss is not finite) and its loss to one all-reduce, then all apply the same mean gradient.
    fn distributed_update(
        &mut self,
        grads: Option<candle_core::backprop::GradStore>,
        loss: f64,
        lr: f64,
        stats: &mut StepStats,
    ) -> Result<()> {
        let finite = loss.is_finite() && grads.is_some();
        let mut sizes = Vec::with_capacity(self.vars.len());
        let mut flat: Vec<f32> = Vec::new();
        for v in &self.vars {
            let n = v.as_tensor().elem_count();
            sizes.push(n);
            match grads.as_ref().and_then(|g| g.get(v.as_tensor())) {
                Some(g) => flat.extend(
                    g.to_dtype(candle_core::DType::F32)?
                        .flatten_all()?
                        .to_vec1::<f32>()?,
                ),
                None => flat.extend(std::iter::repeat_n(0f32, n)),
            }
        }
        flat.push(if finite { loss as f32 } else { 0.0 });
        flat.push(if finite { 0.0 } else { 1.0 });
        let comm = self
            .comm
            .as_mut()
            .ok_or_else(|| invalid("trainer", "no communicator"))?;
        let world = comm.world_size() as f32;
        comm.all_reduce_sum(&mut flat)?;
        let bad = flat.pop().unwrap_or(0.0);
        let loss_sum = flat.pop().unwrap_or(f32::NAN);
        if bad > 0.0 {
            stats.skipped = true;
            stats.loss = f64::NAN;
            return Ok(());
        }
        stats.loss = (loss_sum / world) as f64;
        let mut store = grads.ok_or_else(|| invalid("trainer", "no gradients"))?;
        let mut at = 0;
        let mut sq = 0f64;
        for (v, &n) in self.vars.iter().zip(&sizes) {
            let mean: Vec<f32> = flat[at..at + n].iter().map(|x| x / world).collect();
            at += n;
            sq += mean.iter().map(|&x| (x as f64) * (x as f64)).sum::<f64>();
            let t = Tensor::from_vec(mean, v.as_tensor().shape(), v.as_tensor().device())?
                .to_dtype(v.as_tensor().dtype())?;
            store.insert(v.as_tensor(), t);
        }
        let norm = sq.sqrt();
        stats.grad_norm = norm;
        self.apply_update(&store, norm, lr, stats)
    }

    fn update_ema(&mut self) -> Result<()> {
        let n = self.opt.step_count() as f64;
        let mut d = self.config.ema_decay;
        if self.config.ema_warmup {
            d = d.min((1.0 + n) / (10.0 + n));
        }
        for (e, v) in self.ema.iter_mut().zip(&self.vars) {
            *e = ((&*e * d)? + (v.as_tensor() * (1.0 - d))?)?.detach();
        }
        Ok(())
    }

    /// Trains until `config.total_steps`, pulling batches from `source`, reporting to `observer`,
    /// previewing every `preview_every` steps and, with `checkpoint_dir`, checkpointing every
    /// `checkpoint_every` steps and at the end.
    pub fn fit<S: BatchSource<M::Cond>, O: TrainObserver<M>>(
        &mut self,
        source: &mut S,
        checkpoint_dir: Option<&Path>,
        observer: &mut O,
    ) -> Result<FitSummary> {
        let mut summary = FitSummary {
            steps_run: 0,
            final_step: self.step,
            mean_loss: f64::NAN,
            skipped: 0,
            stopped_early: false,
            checkpoints: Vec::new(),
            clock: self.clock,
        };
        let mut tick = std::time::Instant::now();
        let mut loss_sum = 0.0;
        let mut loss_n = 0u64;
        let mut last_saved = None;
        let parts = self.config.grad_accum_steps as usize;
        while self.step < self.config.total_steps {
            let stats = if parts > 1 {
                let step = self.step;
                self.train_step_accumulated(parts, |k| source.batch_part(step, k, parts))?
            } else {
                let batch = source.batch(self.step)?;
                self.train_step(&batch)?
            };
            summary.steps_run += 1;
            if stats.skipped {
                summary.skipped += 1;
            } else {
                loss_sum += stats.loss;
                loss_n += 1;
            }
            self.clock.seconds += tick.elapsed().as_secs_f64();
            let flow = observer.on_step(&stats);
            if let Some(every) = self.config.preview_every
                && self.step.is_multiple_of(every)
            {
                let step = self.step;
                let diffusion = self.diffusion.clone();
                self.with_ema_weights(|m| observer.on_preview(step, m, &diffusion))?;
            }
            if let (Some(dir), Some(every)) = (checkpoint_dir, self.config.checkpoint_every)
                && self.step.is_multiple_of(every)
                && self.rank() == 0
            {
                // the checkpoint carries the clock up to its own writing, counted after it
                let t = std::time::Instant::now();
                let p = self.save_checkpoint(dir)?;
                self.clock.seconds += t.elapsed().as_secs_f64();
                observer.on_checkpoint(self.step, &p);
                summary.checkpoints.push(p);
                last_saved = Some(self.step);
            }
            // what observers and previews do (progress, evaluations) is not training time
            tick = std::time::Instant::now();
            if flow.is_break() {
                summary.stopped_early = true;
                break;
            }
        }
        if let Some(dir) = checkpoint_dir
            && last_saved != Some(self.step)
            && summary.steps_run > 0
            && self.rank() == 0
        {
            let p = self.save_checkpoint(dir)?;
            observer.on_checkpoint(self.step, &p);
            summary.checkpoints.push(p);
        }
        summary.final_step = self.step;
        summary.clock = self.clock;
        if loss_n > 0 {
            summary.mean_loss = loss_sum / loss_n as f64;
        }
        Ok(summary)
    }
}

#[cfg(test)]
mod tests;
