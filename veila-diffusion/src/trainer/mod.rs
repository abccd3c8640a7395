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

mod batch;
mod checkpoint;
mod config;
pub mod distributed;
mod lr;
mod optim;
mod progress;

pub use batch::{Batch, BatchSource, part_range};
pub use checkpoint::{
    CheckpointState, EMA_FILE, RUN_RECORD_FILE, RngState, TensorFileReader, claim_checkpoint_dir,
    find_latest_checkpoint,
};
// the segmenter's checkpoints (`app::segment`) are written with the trainer's file helpers
#[cfg(feature = "app")]
pub(crate) use checkpoint::{
    MODEL_FILE, OPT_FILE, STATE_FILE, read_state_json, save_tensors, write_checkpoint_dir,
    write_state_json,
};
pub use config::{ActivationCheckpointing, Precision, TrainConfig};
pub use lr::LrSchedule;
pub use optim::{AdamSlot, AdamW, FusedAdamW, ParamsAdamW};
pub use progress::{Clock, FitSummary, LossAverage, StepStats, TrainObserver};

use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

use candle_core::{Tensor, Var};
use candle_nn::VarMap;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::denoiser::{CondDropout, Denoiser};
use crate::error::{Error, Result, invalid};
use crate::objective::Diffusion;

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
