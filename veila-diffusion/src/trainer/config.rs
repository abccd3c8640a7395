//! The trainer's configuration ([`TrainConfig`], with [`Precision`] and
//! [`ActivationCheckpointing`]) and its checks.

use serde::{Deserialize, Serialize};

use super::LrSchedule;
use crate::error::{Error, Result, invalid};

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
    /// Total number of steps ([`Trainer::fit`](super::Trainer::fit) stops there; the cosine ends there).
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
    /// Call [`TrainObserver::on_preview`](super::TrainObserver::on_preview) every this many steps.
    pub preview_every: Option<u64>,
    /// Gradient accumulation: every update runs this many forward/backward passes, each on one
    /// part of the batch ([`BatchSource::batch_part`](super::BatchSource::batch_part)), and steps on their example-weighted mean
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
/// switches the network; the trainer merges what it leaves through [`Denoiser::finish_backward`](crate::denoiser::Denoiser::finish_backward)).
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
