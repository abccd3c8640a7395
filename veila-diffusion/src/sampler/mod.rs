//! Samplers: DDPM (ancestral), DDIM (η), DPM-Solver++(2M), with classifier-free guidance, and
//! RePaint-style inpainting ([`inpaint`]).
//!
//! Every sampler walks a list of noise levels from [`NoiseSchedule::sampling_levels`](crate::NoiseSchedule::sampling_levels)
//! (noisiest first) and ends on clean data; the per-step update rules are public pure functions
//! ([`ddpm_step`], [`ddim_step`], [`DpmSolverPp2M`]) so they can be tested and reused. All
//! coefficients are computed in `f64` from log-SNRs; the tensors stay in the model's dtype.

mod inpaint;
mod steps;

pub use inpaint::{RepaintConfig, inpaint, repaint_schedule};
pub use steps::{DpmSolverPp2M, ddim_step, ddpm_step};

use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::denoiser::{Conditioning, Denoiser};
use crate::error::{Result, invalid};
use crate::noise::{NoiseSource, randn_like};
use crate::objective::{Denoised, Diffusion, Objective, flow_level};
use crate::schedule::{NoiseLevel, Spacing};

/// Variance of DDPM's ancestral step from level `t` to the less noisy level `s`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DdpmVariance {
    /// The true posterior variance `β̃ = β_{t|s}·σ_s²/σ_t²` ("fixed small").
    #[default]
    Posterior,
    /// `β_{t|s} = 1 − ᾱ_t/ᾱ_s` ("fixed large").
    Beta,
}

/// Which update rule to use.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum SamplerKind {
    /// Ancestral sampling from the posterior `q(x_s | x_t, x̂_0)` (Ho et al. 2020); works on any
    /// sub-sequence of levels.
    Ddpm {
        /// Step variance.
        #[serde(default)]
        variance: DdpmVariance,
    },
    /// DDIM (Song et al. 2021): `η = 0` is deterministic, `η = 1` equals DDPM's posterior step.
    Ddim {
        /// Stochasticity `η ∈ [0, 1]` (larger values are allowed and add more noise).
        eta: f64,
    },
    /// DPM-Solver++(2M) (Lu et al. 2022): deterministic second-order multistep solver in the data
    /// prediction form; good samples in 10–25 steps.
    DpmSolverPp2M,
}

impl SamplerKind {
    /// How reports name the update rule: `DDPM`, `DDIM (η = 0)`, `DPM-Solver++(2M)`.
    pub fn title(&self) -> String {
        match self {
            SamplerKind::Ddpm { .. } => "DDPM".into(),
            SamplerKind::Ddim { eta } => format!("DDIM (η = {eta})"),
            SamplerKind::DpmSolverPp2M => "DPM-Solver++(2M)".into(),
        }
    }
}

/// The short label of logs and records: `ddpm`, `ddim (eta 0)`, `dpm-solver++(2m)`.
impl std::fmt::Display for SamplerKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SamplerKind::Ddpm { .. } => f.write_str("ddpm"),
            SamplerKind::Ddim { eta } => write!(f, "ddim (eta {eta})"),
            SamplerKind::DpmSolverPp2M => f.write_str("dpm-solver++(2m)"),
        }
    }
}

/// A sampler as a command line, a config or a benchmark names it. [`SamplerName::ALL`] is the one
/// list of samplers: the CLI's and xtask's `--sampler` choices are built from it (and a test of
/// each door checks that they are). A new sampler is a [`SamplerKind`], a variant here and its
/// arm in [`SamplerName::config`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SamplerName {
    /// Ancestral DDPM (stochastic).
    Ddpm,
    /// DDIM with `eta = 0` (deterministic).
    Ddim,
    /// DPM-Solver++(2M) (deterministic, good in 10-25 steps).
    Dpm,
}

impl SamplerName {
    /// Every sampler, in the order help texts list them.
    pub const ALL: [SamplerName; 3] = [SamplerName::Ddpm, SamplerName::Ddim, SamplerName::Dpm];

    /// The command-line name: `ddpm`, `ddim`, `dpm`.
    pub fn as_str(self) -> &'static str {
        match self {
            SamplerName::Ddpm => "ddpm",
            SamplerName::Ddim => "ddim",
            SamplerName::Dpm => "dpm",
        }
    }

    /// One line for a `--help` text.
    pub fn help(self) -> &'static str {
        match self {
            SamplerName::Ddpm => "ancestral DDPM (stochastic)",
            SamplerName::Ddim => "DDIM with eta = 0 (deterministic)",
            SamplerName::Dpm => "DPM-Solver++(2M) (deterministic, good in 10-25 steps)",
        }
    }

    /// The sampler with `steps` steps and no guidance: `ddpm` is [`SamplerConfig::ddpm`], `ddim`
    /// [`SamplerConfig::ddim`] with `eta = 0`, `dpm` [`SamplerConfig::dpm_solver_pp_2m`].
    pub fn config(self, steps: usize) -> SamplerConfig {
        match self {
            SamplerName::Ddpm => SamplerConfig::ddpm(steps),
            SamplerName::Ddim => SamplerConfig::ddim(steps, 0.0),
            SamplerName::Dpm => SamplerConfig::dpm_solver_pp_2m(steps),
        }
    }

    /// [`config`](Self::config) with the guidance scale `guidance` (a benchmark's `--sampler` and
    /// `--steps` with a bundle's guidance).
    pub fn guided(self, steps: usize, guidance: f64) -> SamplerConfig {
        SamplerConfig {
            guidance_scale: guidance,
            ..self.config(steps)
        }
    }
}

impl std::fmt::Display for SamplerName {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for SamplerName {
    type Err = crate::Error;

    fn from_str(name: &str) -> Result<Self> {
        SamplerName::ALL
            .into_iter()
            .find(|n| n.as_str() == name)
            .ok_or_else(|| {
                let names: Vec<&str> = SamplerName::ALL.map(SamplerName::as_str).into();
                invalid(
                    "sampler",
                    format!("`{name}` is not one of {}", names.join(", ")),
                )
            })
    }
}

/// The most sampler steps (network evaluations per branch) a [`SamplerConfig`] may ask for,
/// whether from a command-line flag, a config or a bundle's `sampler.steps`: far beyond any useful
/// count (the samplers converge in 10-50), and it bounds the time a typo or a hostile file can
/// cost.
pub const MAX_STEPS: usize = 1000;

/// The largest classifier-free guidance scale a [`SamplerConfig`] may have (flag, config or a
/// bundle's `sampler.guidance_scale`; the smallest is 0, the unconditional branch alone). Scales
/// beyond ~10 only amplify the difference of the two branches into saturated garbage (1e300 gave
/// an empty scan).
pub const MAX_GUIDANCE: f64 = 20.0;

/// Sampler settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SamplerConfig {
    /// Update rule.
    pub kind: SamplerKind,
    /// Number of network evaluations (per conditioning branch).
    pub steps: usize,
    /// Placement of the levels.
    #[serde(default)]
    pub spacing: Spacing,
    /// Classifier-free guidance scale `s` (`1` = no guidance, the unconditional branch is skipped).
    #[serde(default = "one")]
    pub guidance_scale: f64,
    /// Clamp `x̂_0` to `[-c, c]` at every step (data are encoded to `[-1, 1]`, so `Some(1.0)`).
    /// A residual bundle clamps its data, `μ + s·r̂₀`, to `[-c, c]`: each pixel's residual gets its
    /// own interval ([`Sampler::with_x0_bounds`]).
    #[serde(default = "clip_one")]
    pub clip_x0: Option<f64>,
    /// Where a draw starts. `None`: from pure noise at the noisiest level. `Some(t)`, `t` in
    /// `(0, 1]`: from `α_t·μ + σ_t·ε` at level `t`, where `μ` is the scan a bundle's prior mean
    /// network predicts from the image (Come-Closer-Diffuse-Faster, Chung et al. 2022), then down
    /// the sampler's levels below `t` ([`Sampler::sample_from_level`]). Only for a bundle with a
    /// prior (`prior` in its `bundle.json`; the application's generation reads this field, and
    /// [`Sampler::sample_from`] itself always starts at its first level); `1` is the same as pure
    /// noise. Lower starts follow the image more closely, cost fewer steps and keep less of the
    /// model's own texture.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_t: Option<f64>,
}

fn one() -> f64 {
    1.0
}

fn clip_one() -> Option<f64> {
    Some(1.0)
}

/// One line for logs and summaries: `ddpm x 16 steps, guidance 1`, and where a prior's draw
/// starts, `dpm-solver++(2m) x 16 steps, guidance 1.5, from the mean network's scan at t = 0.2`.
impl std::fmt::Display for SamplerConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} x {} steps, guidance {}",
            self.kind, self.steps, self.guidance_scale
        )?;
        if let Some(t) = self.start_t {
            write!(f, ", from the mean network's scan at t = {t}")?;
        }
        Ok(())
    }
}

impl SamplerConfig {
    /// DDPM with `steps` steps and the posterior variance.
    pub fn ddpm(steps: usize) -> Self {
        Self::with_kind(
            SamplerKind::Ddpm {
                variance: DdpmVariance::Posterior,
            },
            steps,
        )
    }

    /// DDIM with `steps` steps and stochasticity `eta`.
    pub fn ddim(steps: usize, eta: f64) -> Self {
        Self::with_kind(SamplerKind::Ddim { eta }, steps)
    }

    /// DPM-Solver++(2M) with `steps` steps and trailing spacing (the more accurate choice at
    /// 20–100 steps in this crate's benchmark; [`Spacing::LogSnr`] converges at second order
    /// asymptotically and can be better at 10 steps).
    pub fn dpm_solver_pp_2m(steps: usize) -> Self {
        Self::with_kind(SamplerKind::DpmSolverPp2M, steps)
    }

    fn with_kind(kind: SamplerKind, steps: usize) -> Self {
        Self {
            kind,
            steps,
            spacing: Spacing::Trailing,
            guidance_scale: 1.0,
            clip_x0: Some(1.0),
            start_t: None,
        }
    }

    /// Checks the settings: at most [`MAX_STEPS`] steps (0 is left to the caller: it is valid
    /// only for a residual bundle's mean network alone, which [`Sampler::new`] is not), a guidance
    /// scale from 0 to [`MAX_GUIDANCE`], a finite `eta >= 0`, a finite `clip_x0 > 0` and a `start_t`
    /// in `(0, 1]`.
    pub fn validate(&self) -> Result<()> {
        if self.steps > MAX_STEPS {
            return Err(invalid(
                "steps",
                format!(
                    "{} is more than the limit of {MAX_STEPS} (must be between 1 and {MAX_STEPS})",
                    self.steps
                ),
            ));
        }
        let g = self.guidance_scale;
        if !(g.is_finite() && (0.0..=MAX_GUIDANCE).contains(&g)) {
            return Err(invalid(
                "guidance_scale",
                format!("{g} is not a number between 0 and {MAX_GUIDANCE} (1 = no guidance)"),
            ));
        }
        if let SamplerKind::Ddim { eta } = self.kind
            && !(eta.is_finite() && eta >= 0.0)
        {
            return Err(invalid(
                "eta",
                format!("must be finite and >= 0, got {eta}"),
            ));
        }
        if let Some(c) = self.clip_x0
            && !(c.is_finite() && c > 0.0)
        {
            return Err(invalid(
                "clip_x0",
                format!("must be finite and > 0, got {c}"),
            ));
        }
        if let Some(t) = self.start_t
            && !(t.is_finite() && t > 0.0 && t <= 1.0)
        {
            return Err(invalid(
                "start_t",
                format!("must be a level in (0, 1] (1 = pure noise), got {t}"),
            ));
        }
        Ok(())
    }
}

/// What a sampler reports after each step.
#[derive(Debug)]
pub struct StepInfo<'a> {
    /// Step index, `0..total`.
    pub index: usize,
    /// Number of steps.
    pub total: usize,
    /// Level before the step.
    pub from: NoiseLevel,
    /// Level after the step.
    pub to: NoiseLevel,
    /// The sample after the step.
    pub x: &'a Tensor,
    /// The model's clean estimate at `from`.
    pub x0: &'a Tensor,
}

/// A sampler bound to a diffusion process.
#[derive(Debug, Clone)]
pub struct Sampler<'a> {
    diffusion: &'a Diffusion,
    config: SamplerConfig,
    levels: Vec<NoiseLevel>,
    /// Rectified flow / regression: the times `t` of the steps (1 first).
    flow_times: Vec<f64>,
    /// Per-element bounds of `x̂₀` that replace the symmetric `clip_x0` (see
    /// [`Sampler::with_x0_bounds`]).
    x0_bounds: Option<(Tensor, Tensor)>,
}

impl<'a> Sampler<'a> {
    /// Validates `config` and precomputes the levels.
    pub fn new(diffusion: &'a Diffusion, config: SamplerConfig) -> Result<Self> {
        config.validate()?;
        if config.steps == 0 {
            return Err(invalid(
                "steps",
                "must be at least 1 (0 steps, the mean network alone, is for a bundle with one)",
            ));
        }
        let (levels, flow_times) = match diffusion.config().objective {
            Objective::Diffusion => (
                diffusion
                    .schedule()
                    .sampling_levels(config.steps, config.spacing)?,
                Vec::new(),
            ),
            Objective::RectifiedFlow { .. } => {
                let n = config.steps;
                let times: Vec<f64> = (0..n).map(|i| 1.0 - i as f64 / n as f64).collect();
                (times.iter().map(|&t| flow_level(t)).collect(), times)
            }
            Objective::Regression => (vec![flow_level(1.0)], vec![1.0]),
        };
        Ok(Self {
            diffusion,
            config,
            levels,
            flow_times,
            x0_bounds: None,
        })
    }

    /// Clamps `x̂₀` between `lo` and `hi` (element-wise, broadcast to the sample's shape) at
    /// every step, in place of the symmetric `[-clip_x0, clip_x0]`; `ε̂` is recomputed from the
    /// clamped `x̂₀`. For a model of a transformed variable, such as a residual diffusion's
    /// `(x₀ − μ) / s`, whose data bound `[-c, c]` is a different interval at every pixel:
    /// `lo = (−c − μ) / s`, `hi = (c − μ) / s`. Clamping the transformed variable to `[-c, c]`
    /// instead would cut its tails, which hold the edges the mean network blurs.
    pub fn with_x0_bounds(mut self, lo: Tensor, hi: Tensor) -> Self {
        self.x0_bounds = Some((lo, hi));
        self
    }

    /// `x̂₀` clamped by the bounds or `clip_x0` (`true` when anything was applied).
    fn clamp_x0(&self, x0: Tensor) -> Result<(Tensor, bool)> {
        Ok(match (&self.x0_bounds, self.config.clip_x0) {
            (Some((lo, hi)), _) => (x0.broadcast_maximum(lo)?.broadcast_minimum(hi)?, true),
            (None, Some(c)) => (x0.clamp(-c as f32, c as f32)?, true),
            (None, None) => (x0, false),
        })
    }

    /// The settings.
    pub fn config(&self) -> &SamplerConfig {
        &self.config
    }

    /// The process this sampler runs.
    pub fn diffusion(&self) -> &Diffusion {
        self.diffusion
    }

    /// The levels the network is evaluated at, noisiest first (clean data follows the last one).
    pub fn levels(&self) -> &[NoiseLevel] {
        &self.levels
    }

    /// Draws `x_T ~ N(0, I)` of `shape` from `rng` and samples.
    pub fn sample<D: Denoiser, R: NoiseSource + ?Sized>(
        &self,
        model: &D,
        shape: &[usize],
        device: &Device,
        cond: Option<&D::Cond>,
        rng: &mut R,
    ) -> Result<Tensor> {
        let x_t = rng.noise(shape, device)?;
        self.sample_from(model, x_t, cond, rng, |_| {})
    }

    /// Samples starting from a given `x_T` (at [`Self::levels`]`[0]`), calling `on_step` after each step.
    pub fn sample_from<D: Denoiser, R: NoiseSource + ?Sized>(
        &self,
        model: &D,
        x_t: Tensor,
        cond: Option<&D::Cond>,
        rng: &mut R,
        on_step: impl FnMut(&StepInfo<'_>),
    ) -> Result<Tensor> {
        let _span = tracing::debug_span!("sample", steps = self.levels.len()).entered();
        if !self.diffusion.config().objective.is_diffusion() {
            let uncond = self.uncond_for(cond, x_t.dim(0)?)?;
            return self.sample_flow(model, x_t, cond, uncond.as_ref(), on_step);
        }
        self.sample_levels(model, x_t, &self.levels, cond, rng, on_step)
    }

    /// Samples from `x_t` at `start`, a level of this process ([`crate::NoiseSchedule::level`]
    /// of its schedule), instead of from pure noise: the network is evaluated at `start`, then at
    /// each of [`Self::levels`] below it, then the sample is clean. SDEdit's partial resampling
    /// (Meng et al., 2022) from `x_t = α·x₀ + σ·ε` ([`Diffusion::q_sample`]), and `--restart`
    /// of the `denoise_probe` example: where along the levels a draw's fine texture is made.
    /// A multistep solver starts afresh at `start` (its first step is first order). Diffusion
    /// objectives only: rectified flow and regression have no levels to start from.
    pub fn sample_from_level<D: Denoiser, R: NoiseSource + ?Sized>(
        &self,
        model: &D,
        x_t: Tensor,
        start: NoiseLevel,
        cond: Option<&D::Cond>,
        rng: &mut R,
        on_step: impl FnMut(&StepInfo<'_>),
    ) -> Result<Tensor> {
        let objective = &self.diffusion.config().objective;
        if !objective.is_diffusion() {
            return Err(invalid(
                "start",
                format!(
                    "sampling from a level needs a diffusion objective, this process is {}",
                    objective.name()
                ),
            ));
        }
        if !(start.t > 0.0 && start.t <= 1.0 && start.sigma2 > 0.0) {
            return Err(invalid(
                "start",
                format!(
                    "must be a noisy level, with t in (0, 1], got t = {}",
                    start.t
                ),
            ));
        }
        let levels: Vec<NoiseLevel> = std::iter::once(start)
            .chain(self.levels.iter().copied().filter(|l| l.t < start.t))
            .collect();
        let _span = tracing::debug_span!("sample", steps = levels.len()).entered();
        self.sample_levels(model, x_t, &levels, cond, rng, on_step)
    }

    /// The diffusion samplers' loop over `levels` (noisiest first), from `x_t` at `levels[0]`.
    fn sample_levels<D: Denoiser, R: NoiseSource + ?Sized>(
        &self,
        model: &D,
        x_t: Tensor,
        levels: &[NoiseLevel],
        cond: Option<&D::Cond>,
        rng: &mut R,
        mut on_step: impl FnMut(&StepInfo<'_>),
    ) -> Result<Tensor> {
        let uncond = self.uncond_for(cond, x_t.dim(0)?)?;
        let mut x = x_t;
        let mut solver = DpmSolverPp2M::default();
        let n = levels.len();
        for i in 0..n {
            let from = levels[i];
            let to = levels.get(i + 1).copied().unwrap_or(NoiseLevel::CLEAN);
            let d = self.denoise(model, &x, &from, cond, uncond.as_ref())?;
            x = match self.config.kind {
                SamplerKind::Ddpm { variance } => {
                    let z = if to.is_clean() {
                        None
                    } else {
                        Some(randn_like(rng, &x)?)
                    };
                    ddpm_step(&x, &d, &from, &to, variance, z.as_ref())?
                }
                SamplerKind::Ddim { eta } => {
                    let z = if to.is_clean() || eta == 0.0 {
                        None
                    } else {
                        Some(randn_like(rng, &x)?)
                    };
                    ddim_step(&d, &from, &to, eta, z.as_ref())?
                }
                SamplerKind::DpmSolverPp2M => solver.step(&x, &d.x0, &from, &to)?,
            };
            on_step(&StepInfo {
                index: i,
                total: n,
                from,
                to,
                x: &x,
                x0: &d.x0,
            });
        }
        Ok(x)
    }

    /// The null conditioning used for the unconditional branch, when guidance is on.
    /// Rectified flow: Euler steps of the ODE `dx/dt = v` from `t = 1` to `0` (every sampler kind;
    /// no noise is drawn). With `clip_x0` the step goes through the clamped `x̂₀ = x − t·v`:
    /// `x' = (1 − t')·x̂₀ + t'·ε̂` with `ε̂ = (x − (1 − t)·x̂₀)/t`, which is the plain Euler step when
    /// nothing is clamped. Regression: one pass on zeros at `t = 1`, the output is the result.
    fn sample_flow<D: Denoiser>(
        &self,
        model: &D,
        x_t: Tensor,
        cond: Option<&D::Cond>,
        uncond: Option<&D::Cond>,
        mut on_step: impl FnMut(&StepInfo<'_>),
    ) -> Result<Tensor> {
        let b = x_t.dim(0)?;
        let regression = matches!(self.diffusion.config().objective, Objective::Regression);
        let mut x = if regression { x_t.zeros_like()? } else { x_t };
        let n = self.flow_times.len();
        for i in 0..n {
            let t = self.flow_times[i];
            let t_next = self.flow_times.get(i + 1).copied().unwrap_or(0.0);
            let tt = self.diffusion.flow_time(&vec![t; b], x.device())?;
            let mut out = model.forward(&x, &tt, cond)?;
            if let Some(u) = uncond {
                let out_u = model.forward(&x, &tt, Some(u))?;
                out = crate::denoiser::guide(&out_u, &out, self.config.guidance_scale)?;
            }
            if out.shape() != x.shape() {
                return Err(crate::error::Error::Shape {
                    what: "denoiser output",
                    expected: format!("{:?}", x.dims()),
                    got: format!("{:?}", out.dims()),
                });
            }
            let x0 = if regression { out } else { (&x - (&out * t)?)? };
            let (x0, clipped) = self.clamp_x0(x0)?;
            x = if regression || t_next == 0.0 {
                x0.clone()
            } else {
                let eps = if clipped {
                    ((&x - (&x0 * (1.0 - t))?)? / t)?
                } else {
                    (&x + (&out_velocity(&x, &x0, t)? * (1.0 - t))?)?
                };
                ((&x0 * (1.0 - t_next))? + (eps * t_next)?)?
            };
            let to = if t_next == 0.0 {
                NoiseLevel::CLEAN
            } else {
                flow_level(t_next)
            };
            on_step(&StepInfo {
                index: i,
                total: n,
                from: flow_level(t),
                to,
                x: &x,
                x0: &x0,
            });
        }
        Ok(x)
    }

    pub(crate) fn uncond_for<C: Conditioning>(
        &self,
        cond: Option<&C>,
        batch: usize,
    ) -> Result<Option<C>> {
        match cond {
            Some(c) if self.config.guidance_scale != 1.0 => {
                Ok(Some(c.drop_samples(&vec![true; batch])?))
            }
            _ => Ok(None),
        }
    }

    pub(crate) fn denoise<D: Denoiser>(
        &self,
        model: &D,
        x: &Tensor,
        level: &NoiseLevel,
        cond: Option<&D::Cond>,
        uncond: Option<&D::Cond>,
    ) -> Result<Denoised> {
        let guidance = uncond.map(|u| (self.config.guidance_scale, u));
        // the symmetric clip is the process's own; per-element bounds are applied here
        let symmetric = match self.x0_bounds {
            None => self.config.clip_x0,
            Some(_) => None,
        };
        let d = self
            .diffusion
            .denoise(model, x, level, cond, guidance, symmetric)?;
        if self.x0_bounds.is_none() {
            return Ok(d);
        }
        let (x0, _) = self.clamp_x0(d.x0)?;
        let alpha = crate::objective::scalar(level.alpha(), x)?;
        let sigma = crate::objective::scalar(level.sigma(), x)?;
        let eps = crate::prediction::eps_from_x0(x, &x0, &alpha, &sigma)?;
        Ok(Denoised { x0, eps })
    }
}

/// The velocity `v = (x − x̂₀)/t` that produced `x̂₀` from `x` at flow time `t > 0`.
fn out_velocity(x: &Tensor, x0: &Tensor, t: f64) -> Result<Tensor> {
    Ok(((x - x0)? / t)?)
}

#[cfg(test)]
mod tests;
