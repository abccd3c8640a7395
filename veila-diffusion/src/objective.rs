//! The diffusion process as a whole: schedule + parameterisation + time input + loss weighting,
//! forward noising and the training loss.
//!
//! Three training objectives share this interface ([`Objective`]), so that one trainer and one
//! sampler serve every method the benchmark compares:
//!
//! * [`Objective::Diffusion`]: Gaussian diffusion on [`DiffusionConfig::schedule`], predicting ε, `v`
//!   or `x₀` ([`DiffusionConfig::prediction`]), weighted by [`DiffusionConfig::loss_weighting`].
//! * [`Objective::RectifiedFlow`]: flow matching on straight paths (as in R2Flow):
//!   `x_t = (1 − t)·x₀ + t·ε`, the network predicts the velocity `ε − x₀`, training times are
//!   logit-normal; sampling integrates the ODE from `t = 1` to `0` with Euler steps.
//! * [`Objective::Regression`]: no noise at all: the network sees zeros at `t = 1` and predicts `x₀`
//!   with an L1 loss, i.e. the per-pixel conditional median. Sampling is one forward pass. It is the
//!   mean network of residual ("corrective") diffusion and the zero-step end of the trade-off.

use candle_core::{Device, Tensor};
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::denoiser::{CondDropout, Denoiser, time_tensor};
use crate::error::{Error, Result, invalid};
use crate::noise::randn;
use crate::prediction::{LossWeighting, Prediction, TimeInput};
use crate::schedule::{NoiseLevel, NoiseSchedule, ScheduleConfig, TrainLevels};

/// Serializable description of a diffusion process (store it next to the model weights).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiffusionConfig {
    /// The noise schedule.
    pub schedule: ScheduleConfig,
    /// What the network predicts.
    #[serde(default)]
    pub prediction: Prediction,
    /// What time value the network is fed.
    #[serde(default)]
    pub time_input: TimeInput,
    /// Loss weighting over noise levels.
    #[serde(default)]
    pub loss_weighting: LossWeighting,
    /// What is trained: Gaussian diffusion (the default), rectified flow or one-pass regression.
    /// The schedule, prediction and weighting above apply to [`Objective::Diffusion`] only.
    #[serde(default, skip_serializing_if = "Objective::is_diffusion")]
    pub objective: Objective,
    /// Which noise levels training draws ([`Objective::Diffusion`] only).
    #[serde(default, skip_serializing_if = "TrainLevels::is_uniform_time")]
    pub train_levels: TrainLevels,
}

impl DiffusionConfig {
    /// Whether a network trained under `self` computes what one trained under `other` does: the
    /// same schedule, prediction, time input and objective. The loss weighting and the training
    /// levels only decide where training spends its updates (a weighting over levels by two
    /// names), so a checkpoint resumes under others: a run may go on with a new level
    /// distribution. Whether a run *should* is the caller's rule (the recipes' run records ask for
    /// identical settings).
    pub fn same_network(&self, other: &Self) -> bool {
        self.schedule == other.schedule
            && self.prediction == other.prediction
            && self.time_input == other.time_input
            && self.objective == other.objective
    }
}

/// The training objective (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Objective {
    /// Gaussian diffusion with the config's schedule, prediction and loss weighting.
    #[default]
    Diffusion,
    /// Rectified flow: `x_t = (1 − t)·x₀ + t·ε`, velocity target `ε − x₀`, training times
    /// `t = sigmoid(logit_mean + logit_std·n)`, `n ~ N(0, 1)`.
    RectifiedFlow {
        /// Mean of the logit-normal training-time density (0: centred on `t = 0.5`).
        logit_mean: f64,
        /// Its standard deviation (1 as in Stable Diffusion 3).
        logit_std: f64,
    },
    /// One-pass regression of `x₀` (L1), fed zeros at `t = 1`.
    Regression,
}

impl Objective {
    /// Whether this is [`Objective::Diffusion`].
    pub fn is_diffusion(&self) -> bool {
        matches!(self, Self::Diffusion)
    }

    /// Rectified flow with the logit-normal(0, 1) time density.
    pub fn rectified_flow() -> Self {
        Self::RectifiedFlow {
            logit_mean: 0.0,
            logit_std: 1.0,
        }
    }

    /// A short name (`diffusion`, `rectified_flow`, `regression`).
    pub fn name(&self) -> &'static str {
        match self {
            Self::Diffusion => "diffusion",
            Self::RectifiedFlow { .. } => "rectified_flow",
            Self::Regression => "regression",
        }
    }
}

/// Flow times are kept inside `[FLOW_T_MIN, 1 − FLOW_T_MIN]` in training so that the equivalent
/// log-SNR stays finite.
pub const FLOW_T_MIN: f64 = 1e-5;

/// The noise level with the same signal-to-noise ratio as rectified-flow time `t`
/// (`SNR = ((1 − t)/t)²`), for the bookkeeping that speaks in levels (loss statistics, time inputs).
pub fn flow_level(t: f64) -> NoiseLevel {
    let t = t.clamp(FLOW_T_MIN, 1.0 - FLOW_T_MIN);
    NoiseLevel::from_log_snr(t, 2.0 * ((1.0 - t) / t).ln())
}

impl Default for DiffusionConfig {
    /// R2DM-like default: continuous cosine log-SNR schedule, ε-prediction, `t ∈ [0, 1]` input,
    /// min-SNR-5 weighting.
    fn default() -> Self {
        Self {
            schedule: ScheduleConfig::cosine_logsnr(),
            prediction: Prediction::Epsilon,
            time_input: TimeInput::default(),
            loss_weighting: LossWeighting::MinSnr { gamma: 5.0 },
            objective: Objective::Diffusion,
            train_levels: TrainLevels::UniformTime,
        }
    }
}

/// A built diffusion process.
#[derive(Debug, Clone, PartialEq)]
pub struct Diffusion {
    config: DiffusionConfig,
    schedule: NoiseSchedule,
}

/// The result of [`Diffusion::training_loss`].
#[derive(Debug, Clone)]
pub struct LossOutput {
    /// Scalar weighted MSE (differentiable).
    pub loss: Tensor,
    /// The noise level drawn for each sample.
    pub levels: Vec<NoiseLevel>,
    /// Which samples had their conditioning dropped.
    pub dropped: Vec<bool>,
}

/// The model's prediction at one level, converted to both forms.
#[derive(Debug, Clone)]
pub struct Denoised {
    /// `x̂_0`, clipped if requested.
    pub x0: Tensor,
    /// `ε̂`, consistent with `x0` (recomputed after clipping).
    pub eps: Tensor,
}

/// The largest `time_input.scale`. The network multiplies it by its own `time.input_scale`, whose
/// bound is the same (the network crate's `config::MAX_TIME_INPUT_SCALE`; the application layer
/// asserts the two agree, since this core does not name the network crate).
pub const MAX_TIME_INPUT_SCALE: f64 = 1e5;

impl Diffusion {
    /// Builds and validates a diffusion process.
    pub fn new(config: DiffusionConfig) -> Result<Self> {
        let schedule = NoiseSchedule::new(&config.schedule)?;
        if let LossWeighting::MinSnr { gamma } = config.loss_weighting
            && !(gamma.is_finite() && gamma > 0.0)
        {
            return Err(invalid(
                "loss_weighting.gamma",
                format!("must be finite and > 0, got {gamma}"),
            ));
        }
        if let Objective::RectifiedFlow {
            logit_mean,
            logit_std,
        } = config.objective
            && !(logit_mean.is_finite() && logit_std.is_finite() && logit_std >= 0.0)
        {
            return Err(invalid(
                "objective.logit_mean/logit_std",
                format!("need finite values and logit_std >= 0, got {logit_mean}, {logit_std}"),
            ));
        }
        config.train_levels.validate()?;
        let max = MAX_TIME_INPUT_SCALE;
        if let TimeInput::Scaled { scale } = config.time_input
            && !(scale.is_finite() && scale > 0.0 && scale <= max)
        {
            return Err(invalid(
                "time_input.scale",
                format!("must be above 0 and at most {max}, got {scale}"),
            ));
        }
        Ok(Self { config, schedule })
    }

    /// The configuration.
    pub fn config(&self) -> &DiffusionConfig {
        &self.config
    }

    /// The schedule.
    pub fn schedule(&self) -> &NoiseSchedule {
        &self.schedule
    }

    /// The parameterisation.
    pub fn prediction(&self) -> Prediction {
        self.config.prediction
    }

    /// The `[B]` f32 time tensor fed to the network for `levels`.
    pub fn model_time(&self, levels: &[NoiseLevel], device: &Device) -> Result<Tensor> {
        let v: Vec<f64> = levels
            .iter()
            .map(|l| self.config.time_input.value(l))
            .collect();
        Ok(time_tensor(&v, device)?)
    }

    /// The level a network time value stands for (inverse of [`Self::model_time`]).
    pub fn level_of_model_time(&self, value: f64) -> NoiseLevel {
        self.config.time_input.level(value, &self.schedule)
    }

    /// Forward process `x_t = α·x_0 + σ·ε` with one level per sample.
    pub fn q_sample(&self, x0: &Tensor, eps: &Tensor, levels: &[NoiseLevel]) -> Result<Tensor> {
        let (a, s) = per_sample_alpha_sigma(levels, x0)?;
        Ok((x0.broadcast_mul(&a)? + eps.broadcast_mul(&s)?)?)
    }

    /// Runs the network at one level for the whole batch and converts its output to `(x̂_0, ε̂)`.
    ///
    /// With `guidance = Some((scale, uncond))` the output is `uncond_out + scale·(cond_out − uncond_out)`
    /// where `uncond` is the null conditioning (see [`Conditioning`](crate::Conditioning)). `clip_x0` clamps `x̂_0` to
    /// `[-c, c]` and recomputes `ε̂` from it.
    pub fn denoise<D: Denoiser>(
        &self,
        model: &D,
        x_t: &Tensor,
        level: &NoiseLevel,
        cond: Option<&D::Cond>,
        guidance: Option<(f64, &D::Cond)>,
        clip_x0: Option<f64>,
    ) -> Result<Denoised> {
        if level.is_clean() {
            return Err(invalid(
                "level",
                "the network is never evaluated on clean data (sigma = 0)",
            ));
        }
        let b = x_t.dim(0)?;
        let t = self.model_time(&vec![*level; b], x_t.device())?;
        let mut out = model.forward(x_t, &t, cond)?;
        if let Some((scale, uncond)) = guidance
            && scale != 1.0
        {
            let out_u = model.forward(x_t, &t, Some(uncond))?;
            out = crate::denoiser::guide(&out_u, &out, scale)?;
        }
        if out.shape() != x_t.shape() {
            return Err(Error::Shape {
                what: "denoiser output",
                expected: format!("{:?}", x_t.dims()),
                got: format!("{:?}", out.dims()),
            });
        }
        let alpha = scalar(level.alpha(), x_t)?;
        let sigma = scalar(level.sigma(), x_t)?;
        let pred = self.config.prediction;
        let x0 = pred.x0_from_output(x_t, &out, &alpha, &sigma)?;
        match clip_x0 {
            Some(c) => {
                let x0 = x0.clamp(-c as f32, c as f32)?;
                let eps = crate::prediction::eps_from_x0(x_t, &x0, &alpha, &sigma)?;
                Ok(Denoised { x0, eps })
            }
            None => {
                let eps = pred.eps_from_output(x_t, &out, &alpha, &sigma)?;
                Ok(Denoised { x0, eps })
            }
        }
    }

    /// The training loss of `model` on clean data `x0` (see [`Self::training_loss_weighted`]).
    pub fn training_loss<D: Denoiser, R: Rng + ?Sized>(
        &self,
        model: &D,
        x0: &Tensor,
        cond: Option<&D::Cond>,
        cond_dropout: Option<CondDropout>,
        rng: &mut R,
    ) -> Result<LossOutput> {
        self.training_loss_weighted(model, x0, None, cond, cond_dropout, rng)
    }

    /// The training loss of `model` on clean data `x0` under the config's [`Objective`]: one noise
    /// level (or flow time) per sample, fresh noise, optional condition dropout.
    ///
    /// * Diffusion: the weighted MSE between the output and the prediction target.
    /// * Rectified flow: the MSE between the output and the velocity `ε − x₀`.
    /// * Regression: the mean absolute error between the output (on zeros at `t = 1`) and `x₀`.
    ///
    /// `weight` (broadcastable to `x0`, ≥ 0) weighs every element of the error, e.g. 0 where a
    /// target value does not matter; each sample's error is divided by its weight sum, so a
    /// sample's loss is a weighted mean.
    pub fn training_loss_weighted<D: Denoiser, R: Rng + ?Sized>(
        &self,
        model: &D,
        x0: &Tensor,
        weight: Option<&Tensor>,
        cond: Option<&D::Cond>,
        cond_dropout: Option<CondDropout>,
        rng: &mut R,
    ) -> Result<LossOutput> {
        let b = x0.dim(0)?;
        if b == 0 {
            return Err(invalid("x0", "empty batch"));
        }
        let objective = self.config.objective;
        let levels: Vec<NoiseLevel> = match objective {
            Objective::Diffusion => (0..b)
                .map(|_| self.config.train_levels.draw(&self.schedule, rng))
                .collect(),
            Objective::RectifiedFlow {
                logit_mean,
                logit_std,
            } => (0..b)
                .map(|_| {
                    let n: f64 = rng.sample(rand_distr::StandardNormal);
                    let t = 1.0 / (1.0 + (-(logit_mean + logit_std * n)).exp());
                    flow_level(t)
                })
                .collect(),
            Objective::Regression => vec![flow_level(1.0); b],
        };
        let (cond_used, dropped) = match (cond, cond_dropout) {
            (Some(c), Some(d)) if d.prob > 0.0 => {
                let (c, m) = d.apply(c, b, rng)?;
                (Some(c), m)
            }
            _ => (None, vec![false; b]),
        };
        let cond_ref = cond_used.as_ref().or(cond);
        let (input, target, t) = match objective {
            Objective::Diffusion => {
                let eps = randn(rng, x0.dims(), x0.device())?.to_dtype(x0.dtype())?;
                let x_t = self.q_sample(x0, &eps, &levels)?;
                let (alpha, sigma) = per_sample_alpha_sigma(&levels, x0)?;
                let target = self.config.prediction.target(x0, &eps, &alpha, &sigma)?;
                (x_t, target, self.model_time(&levels, x0.device())?)
            }
            Objective::RectifiedFlow { .. } => {
                let eps = randn(rng, x0.dims(), x0.device())?.to_dtype(x0.dtype())?;
                let ts: Vec<f64> = levels.iter().map(|l| l.t).collect();
                let t_b = per_sample(&ts, x0)?;
                let one_minus = per_sample(&ts.iter().map(|t| 1.0 - t).collect::<Vec<_>>(), x0)?;
                let x_t = (x0.broadcast_mul(&one_minus)? + eps.broadcast_mul(&t_b)?)?;
                let target = (&eps - x0)?;
                (x_t, target, self.flow_time(&ts, x0.device())?)
            }
            Objective::Regression => (
                x0.zeros_like()?,
                x0.clone(),
                self.flow_time(&vec![1.0; b], x0.device())?,
            ),
        };
        let out = model.forward(&input, &t, cond_ref)?;
        if out.shape() != x0.shape() {
            return Err(Error::Shape {
                what: "denoiser output",
                expected: format!("{:?}", x0.dims()),
                got: format!("{:?}", out.dims()),
            });
        }
        let diff = (out - target)?;
        let err = match objective {
            Objective::Regression => diff.abs()?,
            _ => diff.sqr()?,
        };
        let per_sample = match weight {
            None => err.flatten_from(1)?.mean(1)?,
            Some(w) => {
                let w = w.broadcast_as(x0.shape())?.to_dtype(err.dtype())?;
                let num = (err * &w)?.flatten_from(1)?.sum(1)?;
                let den = w.flatten_from(1)?.sum(1)?.clamp(1e-6f32, f32::MAX)?;
                (num / den)?
            }
        }; // [B]
        let w: Vec<f32> = match objective {
            Objective::Diffusion => levels
                .iter()
                .map(|l| self.config.loss_weighting.weight(l, self.config.prediction) as f32)
                .collect(),
            _ => vec![1.0; b],
        };
        let w = Tensor::from_vec(w, b, x0.device())?.to_dtype(per_sample.dtype())?;
        let loss = (per_sample * w)?.mean_all()?;
        Ok(LossOutput {
            loss,
            levels,
            dropped,
        })
    }

    /// The network's time input for rectified-flow times `ts` (`t` itself with
    /// [`TimeInput::Unit`], `t · scale` with [`TimeInput::Scaled`], the equivalent log-SNR with
    /// [`TimeInput::LogSnr`]).
    pub fn flow_time(&self, ts: &[f64], device: &Device) -> Result<Tensor> {
        let v: Vec<f64> = ts
            .iter()
            .map(|&t| self.config.time_input.value(&flow_level(t)))
            .collect();
        Ok(time_tensor(&v, device)?)
    }
}

/// A `[B, 1, …, 1]` tensor of per-sample values with the dtype and device of `like`.
fn per_sample(values: &[f64], like: &Tensor) -> Result<Tensor> {
    let mut shape = vec![1usize; like.rank()];
    shape[0] = values.len();
    let v: Vec<f32> = values.iter().map(|&x| x as f32).collect();
    Ok(Tensor::from_vec(v, shape, like.device())?.to_dtype(like.dtype())?)
}

/// `[B, 1, …, 1]` tensors of α and σ (f64 → dtype of `like`).
pub(crate) fn per_sample_alpha_sigma(
    levels: &[NoiseLevel],
    like: &Tensor,
) -> Result<(Tensor, Tensor)> {
    let b = like.dim(0)?;
    if levels.len() != b {
        return Err(Error::Shape {
            what: "levels",
            expected: format!("{b} (batch size)"),
            got: levels.len().to_string(),
        });
    }
    let mut shape = vec![1usize; like.rank()];
    shape[0] = b;
    let a: Vec<f32> = levels.iter().map(|l| l.alpha() as f32).collect();
    let s: Vec<f32> = levels.iter().map(|l| l.sigma() as f32).collect();
    let a = Tensor::from_vec(a, shape.clone(), like.device())?.to_dtype(like.dtype())?;
    let s = Tensor::from_vec(s, shape, like.device())?.to_dtype(like.dtype())?;
    Ok((a, s))
}

/// A rank-0 tensor with the dtype and device of `like`.
pub(crate) fn scalar(v: f64, like: &Tensor) -> Result<Tensor> {
    Ok(Tensor::new(v as f32, like.device())?.to_dtype(like.dtype())?)
}

#[cfg(test)]
mod tests;
