//! The diffusion process as a whole: schedule + parameterisation + time input + loss weighting,
//! forward noising and the training loss.

use candle_core::{Device, Tensor};
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::denoiser::{CondDropout, Denoiser, time_tensor};
use crate::error::{Error, Result, invalid};
use crate::noise::randn;
use crate::prediction::{LossWeighting, Prediction, TimeInput};
use crate::schedule::{NoiseLevel, NoiseSchedule, ScheduleConfig};

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
        if let TimeInput::Scaled { scale } = config.time_input
            && !(scale.is_finite() && scale > 0.0)
        {
            return Err(invalid(
                "time_input.scale",
                format!("must be finite and > 0, got {scale}"),
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

    /// The training loss of one batch: draws one level per sample, the noise and (with
    /// `cond_dropout`) the per-sample condition drop mask from `rng`, and returns the weighted MSE
    /// between the network output and the target of the configured parameterisation.
    ///
    /// The RNG is consumed in a fixed order (levels, drop mask, noise), so a seeded RNG gives
    /// bit-identical losses.
    pub fn training_loss<D: Denoiser, R: Rng + ?Sized>(
        &self,
        model: &D,
        x0: &Tensor,
        cond: Option<&D::Cond>,
        cond_dropout: Option<CondDropout>,
        rng: &mut R,
    ) -> Result<LossOutput> {
        let b = x0.dim(0)?;
        if b == 0 {
            return Err(invalid("x0", "empty batch"));
        }
        let levels: Vec<NoiseLevel> = (0..b)
            .map(|_| self.schedule.sample_train_level(rng))
            .collect();
        let (cond_used, dropped) = match (cond, cond_dropout) {
            (Some(c), Some(d)) if d.prob > 0.0 => {
                let (c, m) = d.apply(c, b, rng)?;
                (Some(c), m)
            }
            _ => (None, vec![false; b]),
        };
        let cond_ref = cond_used.as_ref().or(cond);
        let eps = randn(rng, x0.dims(), x0.device())?.to_dtype(x0.dtype())?;
        let x_t = self.q_sample(x0, &eps, &levels)?;
        let t = self.model_time(&levels, x0.device())?;
        let out = model.forward(&x_t, &t, cond_ref)?;
        if out.shape() != x0.shape() {
            return Err(Error::Shape {
                what: "denoiser output",
                expected: format!("{:?}", x0.dims()),
                got: format!("{:?}", out.dims()),
            });
        }
        let (alpha, sigma) = per_sample_alpha_sigma(&levels, x0)?;
        let target = self.config.prediction.target(x0, &eps, &alpha, &sigma)?;
        let per_sample = (out - target)?.sqr()?.flatten_from(1)?.mean(1)?; // [B]
        let w: Vec<f32> = levels
            .iter()
            .map(|l| self.config.loss_weighting.weight(l, self.config.prediction) as f32)
            .collect();
        let w = Tensor::from_vec(w, b, x0.device())?.to_dtype(per_sample.dtype())?;
        let loss = (per_sample * w)?.mean_all()?;
        Ok(LossOutput {
            loss,
            levels,
            dropped,
        })
    }
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
