//! What the network predicts, what time value it sees, and how the loss is weighted over noise levels.
//!
//! With `x_t = α·x_0 + σ·ε` and `α² + σ² = 1`:
//!
//! | parameterisation | target | `x̂_0` | `ε̂` |
//! |---|---|---|---|
//! | [`Prediction::Epsilon`] | `ε` | `(x_t − σ·ε̂) / α` | output |
//! | [`Prediction::V`] | `v = α·ε − σ·x_0` | `α·x_t − σ·v̂` | `σ·x_t + α·v̂` |
//! | [`Prediction::Sample`] | `x_0` | output | `(x_t − α·x̂_0) / σ` |
//!
//! All three conversions are affine in the network output with coefficients that depend only on
//! `x_t`, `α` and `σ`, so classifier-free guidance gives the same result in any of them.

use candle_core::Tensor;
use serde::{Deserialize, Serialize};

use crate::error::Result;
use crate::schedule::{NoiseLevel, NoiseSchedule};

/// The network's output parameterisation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Prediction {
    /// The noise `ε` (DDPM; the paper's objective, eq. 3).
    #[default]
    Epsilon,
    /// The velocity `v = α·ε − σ·x_0` (Salimans & Ho 2022).
    V,
    /// The clean sample `x_0`.
    Sample,
}

impl Prediction {
    /// The regression target for `x_0` and noise `eps`; `alpha`, `sigma` broadcast against them
    /// (shape `[B, 1, 1, 1]` or scalar).
    pub fn target(
        &self,
        x0: &Tensor,
        eps: &Tensor,
        alpha: &Tensor,
        sigma: &Tensor,
    ) -> Result<Tensor> {
        Ok(match self {
            Self::Epsilon => eps.clone(),
            Self::Sample => x0.clone(),
            Self::V => (eps.broadcast_mul(alpha)? - x0.broadcast_mul(sigma)?)?,
        })
    }

    /// `x̂_0` from the model output. For [`Prediction::Epsilon`] this divides by `α`, which is positive
    /// on every level a schedule produces (never exactly 0).
    pub fn x0_from_output(
        &self,
        x_t: &Tensor,
        out: &Tensor,
        alpha: &Tensor,
        sigma: &Tensor,
    ) -> Result<Tensor> {
        Ok(match self {
            Self::Epsilon => (x_t - out.broadcast_mul(sigma)?)?.broadcast_div(alpha)?,
            Self::V => (x_t.broadcast_mul(alpha)? - out.broadcast_mul(sigma)?)?,
            Self::Sample => out.clone(),
        })
    }

    /// `ε̂` from the model output. For [`Prediction::Sample`] this divides by `σ`, which is positive on
    /// every level the samplers evaluate the model at (never the clean level).
    pub fn eps_from_output(
        &self,
        x_t: &Tensor,
        out: &Tensor,
        alpha: &Tensor,
        sigma: &Tensor,
    ) -> Result<Tensor> {
        Ok(match self {
            Self::Epsilon => out.clone(),
            Self::V => (x_t.broadcast_mul(sigma)? + out.broadcast_mul(alpha)?)?,
            Self::Sample => (x_t - out.broadcast_mul(alpha)?)?.broadcast_div(sigma)?,
        })
    }
}

/// `ε` from `x_t` and `x̂_0`: `(x_t − α·x̂_0) / σ` (σ must be positive).
pub fn eps_from_x0(x_t: &Tensor, x0: &Tensor, alpha: &Tensor, sigma: &Tensor) -> Result<Tensor> {
    Ok((x_t - x0.broadcast_mul(alpha)?)?.broadcast_div(sigma)?)
}

/// `x_0` from `x_t` and `ε̂`: `(x_t − σ·ε̂) / α` (α must be positive).
pub fn x0_from_eps(x_t: &Tensor, eps: &Tensor, alpha: &Tensor, sigma: &Tensor) -> Result<Tensor> {
    Ok((x_t - eps.broadcast_mul(sigma)?)?.broadcast_div(alpha)?)
}

/// `ε` from `x_t` and `v̂`: `σ·x_t + α·v̂`.
pub fn eps_from_v(x_t: &Tensor, v: &Tensor, alpha: &Tensor, sigma: &Tensor) -> Result<Tensor> {
    Ok((x_t.broadcast_mul(sigma)? + v.broadcast_mul(alpha)?)?)
}

/// `x_0` from `x_t` and `v̂`: `α·x_t − σ·v̂`.
pub fn x0_from_v(x_t: &Tensor, v: &Tensor, alpha: &Tensor, sigma: &Tensor) -> Result<Tensor> {
    Ok((x_t.broadcast_mul(alpha)? - v.broadcast_mul(sigma)?)?)
}

/// `v = α·ε − σ·x_0`.
pub fn v_from_x0_eps(x0: &Tensor, eps: &Tensor, alpha: &Tensor, sigma: &Tensor) -> Result<Tensor> {
    Ok((eps.broadcast_mul(alpha)? - x0.broadcast_mul(sigma)?)?)
}

/// The time value the network is fed for a noise level (one per sample).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum TimeInput {
    /// `t ∈ [0, 1]`.
    Unit,
    /// `t · scale` (e.g. 1000: the DDPM step index for a 1000-step schedule).
    Scaled {
        /// Multiplier.
        scale: f64,
    },
    /// The log-SNR `λ` (variational-diffusion style).
    LogSnr,
}

impl Default for TimeInput {
    /// [`TimeInput::Unit`]: what the `veila-nn` presets expect (they scale it by 1000 themselves).
    fn default() -> Self {
        Self::Unit
    }
}

impl TimeInput {
    /// The value fed to the network for `level`.
    pub fn value(&self, level: &NoiseLevel) -> f64 {
        match self {
            Self::Unit => level.t,
            Self::Scaled { scale } => level.t * scale,
            Self::LogSnr => level.log_snr,
        }
    }

    /// Recovers the level from a value produced by [`Self::value`] (used by analytic denoisers).
    pub fn level(&self, value: f64, schedule: &NoiseSchedule) -> NoiseLevel {
        match self {
            Self::Unit => schedule.level(value),
            Self::Scaled { scale } => schedule.level(value / scale),
            Self::LogSnr => match schedule {
                NoiseSchedule::Continuous(_) => NoiseLevel::from_log_snr(f64::NAN, value),
                NoiseSchedule::Discrete(_) => schedule.level_of_log_snr(value),
            },
        }
    }
}

/// Per-noise-level loss weight.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum LossWeighting {
    /// Every level weighs the same in the chosen parameterisation's MSE (DDPM's "simple" loss).
    #[default]
    Uniform,
    /// Min-SNR-γ (Hang et al. 2023): the x₀-space weight `min(SNR, γ)` expressed in the chosen
    /// parameterisation (`/SNR` for ε, `/(SNR + 1)` for v).
    MinSnr {
        /// Truncation `γ` (5 in the paper).
        gamma: f64,
    },
}

impl LossWeighting {
    /// The names the training doors take (`train-default --loss-weighting`, `veila train`'s
    /// `[model] loss_weighting`): `min-snr` (min-SNR-5) and `uniform`.
    pub const NAMES: [&'static str; 2] = ["min-snr", "uniform"];

    /// The weight for a sample at `level` under `prediction`.
    pub fn weight(&self, level: &NoiseLevel, prediction: Prediction) -> f64 {
        let Self::MinSnr { gamma } = *self else {
            return 1.0;
        };
        let l = level.log_snr;
        let snr_below = l < gamma.ln();
        match prediction {
            // min(snr, γ)/snr = min(1, γ/snr)
            Prediction::Epsilon => {
                if snr_below {
                    1.0
                } else {
                    gamma * (-l).exp()
                }
            }
            // min(snr, γ)/(snr + 1) = sigmoid(λ) or γ·sigmoid(−λ)
            Prediction::V => {
                if snr_below {
                    level.alpha_bar
                } else {
                    gamma * level.sigma2
                }
            }
            Prediction::Sample => {
                if snr_below {
                    l.exp()
                } else {
                    gamma
                }
            }
        }
    }
}

impl std::str::FromStr for LossWeighting {
    type Err = String;
    /// [`LossWeighting::NAMES`]: `min-snr` is min-SNR-5, `uniform` every level alike.
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "min-snr" => Ok(Self::MinSnr { gamma: 5.0 }),
            "uniform" => Ok(Self::Uniform),
            _ => Err(format!(
                "unknown loss weighting `{s}` (one of: {})",
                Self::NAMES.join(", ")
            )),
        }
    }
}

#[cfg(test)]
mod tests;
