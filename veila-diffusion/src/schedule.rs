//! Noise schedules of the variance-preserving process `x_t = α_t · x_0 + σ_t · ε`, `α_t² + σ_t² = 1`.
//!
//! Every schedule is described on the time axis `t ∈ [0, 1]` (`t = 0` is clean data) and evaluated in
//! `f64` through its log signal-to-noise ratio `λ = log(α² / σ²)`, so that `α²` and `σ² = 1 − α²` are
//! both accurate near `t → 0` and `t → 1` (neither is computed as a difference of nearly equal numbers).
//!
//! * [`ScheduleConfig::Linear`]: DDPM's linear betas on `T` discrete steps.
//! * [`ScheduleConfig::Cosine`]: Nichol & Dhariwal's cosine `ᾱ` on `T` discrete steps, betas clipped
//!   at `max_beta` (computed in floating point; candle-transformers' `betas_for_alpha_bar` divides
//!   integers and returns `[0, …, 0, 0.999]`).
//! * [`ScheduleConfig::CosineLogSnr`]: the continuous-time cosine schedule in log-SNR form,
//!   `λ(t) = −2 log tan(a·t + b) + shift`, with `λ(0) = logsnr_max` and `λ(1) = logsnr_min`, so `ᾱ`
//!   never reaches exactly 0 or 1.
//!
//! A discrete schedule with `T` steps lives on the grid `t_k = k / T`, `k = 1..=T`; [`NoiseSchedule::level`]
//! rounds other times to the nearest grid point.

use serde::{Deserialize, Serialize};

use crate::error::{Result, invalid};

/// Serializable choice of schedule.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum ScheduleConfig {
    /// Linear betas from `beta_start` to `beta_end` over `num_timesteps` (DDPM: 1e-4, 0.02, 1000).
    Linear {
        /// Number of discrete steps `T`.
        num_timesteps: usize,
        /// First beta.
        beta_start: f64,
        /// Last beta.
        beta_end: f64,
    },
    /// Nichol & Dhariwal's cosine schedule over `num_timesteps` (s = 0.008, max_beta = 0.999).
    Cosine {
        /// Number of discrete steps `T`.
        num_timesteps: usize,
        /// Offset `s` that keeps β small near `t = 0`.
        s: f64,
        /// Betas are clipped to at most this.
        max_beta: f64,
    },
    /// Continuous cosine log-SNR schedule with clipping.
    CosineLogSnr {
        /// `λ(1)`, the lowest log-SNR (e.g. −20).
        logsnr_min: f64,
        /// `λ(0)`, the highest log-SNR (e.g. 20).
        logsnr_max: f64,
        /// Added to `λ` (resolution shift, e.g. `2·ln(64 / width)`; 0 for none).
        shift: f64,
    },
}

impl ScheduleConfig {
    /// DDPM's linear schedule: 1000 steps, betas from 1e-4 to 0.02.
    pub fn ddpm_linear() -> Self {
        Self::Linear {
            num_timesteps: 1000,
            beta_start: 1e-4,
            beta_end: 0.02,
        }
    }

    /// Improved-DDPM cosine schedule: 1000 steps, s = 0.008, betas clipped at 0.999.
    pub fn cosine() -> Self {
        Self::Cosine {
            num_timesteps: 1000,
            s: 0.008,
            max_beta: 0.999,
        }
    }

    /// Continuous cosine log-SNR schedule clipped to `[-20, 20]`, no shift.
    pub fn cosine_logsnr() -> Self {
        Self::CosineLogSnr {
            logsnr_min: -20.0,
            logsnr_max: 20.0,
            shift: 0.0,
        }
    }
}

/// A point on the noise axis with all the quantities the samplers and losses need (all `f64`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NoiseLevel {
    /// Time in `[0, 1]`; `0` is clean data.
    pub t: f64,
    /// `λ = log(ᾱ / (1 − ᾱ))`; `+∞` for clean data.
    pub log_snr: f64,
    /// `ᾱ = α²`.
    pub alpha_bar: f64,
    /// `1 − ᾱ = σ²`, computed without cancellation.
    pub sigma2: f64,
}

impl NoiseLevel {
    /// Clean data: `α = 1`, `σ = 0`, `λ = +∞`.
    pub const CLEAN: NoiseLevel = NoiseLevel {
        t: 0.0,
        log_snr: f64::INFINITY,
        alpha_bar: 1.0,
        sigma2: 0.0,
    };

    /// Builds a level from its log-SNR (`λ = +∞` gives clean data, `λ = −∞` pure noise).
    pub fn from_log_snr(t: f64, log_snr: f64) -> Self {
        Self {
            t,
            log_snr,
            alpha_bar: sigmoid(log_snr),
            sigma2: sigmoid(-log_snr),
        }
    }

    /// Builds a level from `log ᾱ ≤ 0` (accurate for ᾱ near 1 and near 0).
    pub fn from_log_alpha_bar(t: f64, log_alpha_bar: f64) -> Self {
        let alpha_bar = log_alpha_bar.exp();
        let sigma2 = -log_alpha_bar.exp_m1();
        Self {
            t,
            log_snr: log_alpha_bar - sigma2.ln(),
            alpha_bar,
            sigma2,
        }
    }

    /// Signal scale `α = sqrt(ᾱ)`.
    pub fn alpha(&self) -> f64 {
        self.alpha_bar.sqrt()
    }

    /// Noise scale `σ = sqrt(1 − ᾱ)`.
    pub fn sigma(&self) -> f64 {
        self.sigma2.sqrt()
    }

    /// `log ᾱ = −softplus(−λ)` (0 for clean data), accurate when ᾱ is close to 1.
    pub fn log_alpha_bar(&self) -> f64 {
        -softplus(-self.log_snr)
    }

    /// Signal-to-noise ratio `ᾱ / (1 − ᾱ)` (`+∞` for clean data).
    pub fn snr(&self) -> f64 {
        self.log_snr.exp()
    }

    /// Whether this is clean data (`σ = 0`).
    pub fn is_clean(&self) -> bool {
        self.sigma2 == 0.0
    }
}

/// Numerically stable logistic function.
pub(crate) fn sigmoid(x: f64) -> f64 {
    if x >= 0.0 {
        1.0 / (1.0 + (-x).exp())
    } else {
        let e = x.exp();
        e / (1.0 + e)
    }
}

/// Numerically stable `log(1 + e^x)`.
pub(crate) fn softplus(x: f64) -> f64 {
    if x > 0.0 {
        x + (-x).exp().ln_1p()
    } else {
        x.exp().ln_1p()
    }
}

/// A discrete schedule: betas `β_1..β_T` and `log ᾱ_k = Σ_{j≤k} log(1 − β_j)`.
#[derive(Debug, Clone, PartialEq)]
pub struct DiscreteSchedule {
    betas: Vec<f64>,
    log_alpha_bar: Vec<f64>,
}

impl DiscreteSchedule {
    /// Builds a schedule from betas; every beta must be finite and in `(0, 1)`.
    pub fn from_betas(betas: Vec<f64>) -> Result<Self> {
        if betas.is_empty() {
            return Err(invalid("num_timesteps", "must be at least 1"));
        }
        if let Some((k, b)) = betas
            .iter()
            .enumerate()
            .find(|(_, b)| !(b.is_finite() && **b > 0.0 && **b < 1.0))
        {
            return Err(invalid(
                "betas",
                format!("beta[{k}] = {b} is not in (0, 1)"),
            ));
        }
        let mut acc = 0.0f64;
        let log_alpha_bar = betas
            .iter()
            .map(|b| {
                acc += (-b).ln_1p();
                acc
            })
            .collect();
        Ok(Self {
            betas,
            log_alpha_bar,
        })
    }

    /// DDPM's linear schedule.
    pub fn linear(num_timesteps: usize, beta_start: f64, beta_end: f64) -> Result<Self> {
        if num_timesteps == 0 {
            return Err(invalid("num_timesteps", "must be at least 1"));
        }
        let n = num_timesteps;
        let betas = (0..n)
            .map(|i| {
                if n == 1 {
                    beta_start
                } else {
                    beta_start + (beta_end - beta_start) * i as f64 / (n - 1) as f64
                }
            })
            .collect();
        Self::from_betas(betas)
    }

    /// Nichol & Dhariwal's cosine schedule: `ᾱ(k) = f(k) / f(0)`, `f(k) = cos²((k/T + s)/(1 + s) · π/2)`,
    /// `β_k = min(1 − ᾱ(k)/ᾱ(k−1), max_beta)`.
    pub fn cosine(num_timesteps: usize, s: f64, max_beta: f64) -> Result<Self> {
        if num_timesteps == 0 {
            return Err(invalid("num_timesteps", "must be at least 1"));
        }
        if !(s.is_finite() && s >= 0.0) {
            return Err(invalid("s", format!("must be finite and >= 0, got {s}")));
        }
        if !(max_beta > 0.0 && max_beta < 1.0) {
            return Err(invalid(
                "max_beta",
                format!("must be in (0, 1), got {max_beta}"),
            ));
        }
        let t_total = num_timesteps as f64;
        let f = |k: usize| {
            let u = (k as f64 / t_total + s) / (1.0 + s) * std::f64::consts::FRAC_PI_2;
            u.cos().powi(2)
        };
        let betas = (1..=num_timesteps)
            .map(|k| (1.0 - f(k) / f(k - 1)).clamp(0.0, max_beta).max(1e-12))
            .collect();
        Self::from_betas(betas)
    }

    /// Number of steps `T`.
    pub fn num_timesteps(&self) -> usize {
        self.betas.len()
    }

    /// The betas `β_1..β_T` (index `k − 1`).
    pub fn betas(&self) -> &[f64] {
        &self.betas
    }

    /// The level at grid index `k` (`0` is clean data, `T` the noisiest); `k` is clamped to `T`.
    pub fn level_at_index(&self, k: usize) -> NoiseLevel {
        if k == 0 {
            return NoiseLevel::CLEAN;
        }
        let k = k.min(self.num_timesteps());
        NoiseLevel::from_log_alpha_bar(
            k as f64 / self.num_timesteps() as f64,
            self.log_alpha_bar[k - 1],
        )
    }
}

/// Continuous cosine log-SNR schedule `λ(t) = −2 log tan(a·t + b) + shift`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CosineLogSnr {
    a: f64,
    b: f64,
    shift: f64,
    logsnr_min: f64,
    logsnr_max: f64,
}

impl CosineLogSnr {
    /// Validated constructor; the clipping range is applied before the shift.
    pub fn new(logsnr_min: f64, logsnr_max: f64, shift: f64) -> Result<Self> {
        if !(logsnr_min.is_finite() && logsnr_max.is_finite() && logsnr_min < logsnr_max) {
            return Err(invalid(
                "logsnr_min/logsnr_max",
                format!("need finite logsnr_min < logsnr_max, got {logsnr_min}, {logsnr_max}"),
            ));
        }
        if !(shift.is_finite()) {
            return Err(invalid("shift", "must be finite"));
        }
        let b = (-0.5 * logsnr_max).exp().atan();
        let a = (-0.5 * logsnr_min).exp().atan() - b;
        Ok(Self {
            a,
            b,
            shift,
            logsnr_min,
            logsnr_max,
        })
    }

    /// `λ(t)` for `t` clamped to `[0, 1]`.
    pub fn log_snr(&self, t: f64) -> f64 {
        let t = t.clamp(0.0, 1.0);
        let l = -2.0 * (self.a * t + self.b).tan().ln();
        l.clamp(self.logsnr_min, self.logsnr_max) + self.shift
    }

    /// Inverse of [`Self::log_snr`] (`λ` clamped to the schedule's range).
    pub fn time_of_log_snr(&self, log_snr: f64) -> f64 {
        let l = (log_snr - self.shift).clamp(self.logsnr_min, self.logsnr_max);
        (((-0.5 * l).exp().atan() - self.b) / self.a).clamp(0.0, 1.0)
    }
}

/// A ready-to-use schedule (built from a [`ScheduleConfig`]).
#[derive(Debug, Clone, PartialEq)]
pub enum NoiseSchedule {
    /// `T` discrete steps.
    Discrete(DiscreteSchedule),
    /// Continuous time.
    Continuous(CosineLogSnr),
}

impl NoiseSchedule {
    /// Builds and validates a schedule.
    pub fn new(cfg: &ScheduleConfig) -> Result<Self> {
        Ok(match *cfg {
            ScheduleConfig::Linear {
                num_timesteps,
                beta_start,
                beta_end,
            } => Self::Discrete(DiscreteSchedule::linear(
                num_timesteps,
                beta_start,
                beta_end,
            )?),
            ScheduleConfig::Cosine {
                num_timesteps,
                s,
                max_beta,
            } => Self::Discrete(DiscreteSchedule::cosine(num_timesteps, s, max_beta)?),
            ScheduleConfig::CosineLogSnr {
                logsnr_min,
                logsnr_max,
                shift,
            } => Self::Continuous(CosineLogSnr::new(logsnr_min, logsnr_max, shift)?),
        })
    }

    /// `Some(T)` for a discrete schedule.
    pub fn num_timesteps(&self) -> Option<usize> {
        match self {
            Self::Discrete(d) => Some(d.num_timesteps()),
            Self::Continuous(_) => None,
        }
    }

    /// The noise level at time `t ∈ [0, 1]` (clamped). Discrete schedules round to the nearest grid
    /// point `k / T` and give clean data for `k = 0`; the continuous schedule is never exactly clean
    /// (`λ(0) = logsnr_max`), use [`NoiseLevel::CLEAN`] for that.
    pub fn level(&self, t: f64) -> NoiseLevel {
        let t = if t.is_nan() { 1.0 } else { t.clamp(0.0, 1.0) };
        match self {
            Self::Discrete(d) => {
                let k = (t * d.num_timesteps() as f64).round() as usize;
                d.level_at_index(k)
            }
            Self::Continuous(c) => NoiseLevel::from_log_snr(t, c.log_snr(t)),
        }
    }

    /// `ᾱ(t)`.
    pub fn alpha_bar(&self, t: f64) -> f64 {
        self.level(t).alpha_bar
    }

    /// `σ(t) = sqrt(1 − ᾱ(t))`.
    pub fn sigma(&self, t: f64) -> f64 {
        self.level(t).sigma()
    }

    /// `λ(t)`.
    pub fn log_snr(&self, t: f64) -> f64 {
        self.level(t).log_snr
    }

    /// The level nearest (in log-SNR) to `log_snr`, among the grid for discrete schedules.
    pub fn level_of_log_snr(&self, log_snr: f64) -> NoiseLevel {
        match self {
            Self::Discrete(d) => {
                // log-SNR decreases strictly with k: binary search, then pick the nearer neighbour.
                let n = d.num_timesteps();
                let (mut lo, mut hi) = (1usize, n);
                while lo < hi {
                    let mid = (lo + hi) / 2;
                    if d.level_at_index(mid).log_snr > log_snr {
                        lo = mid + 1;
                    } else {
                        hi = mid;
                    }
                }
                let k = lo;
                if k > 1
                    && (d.level_at_index(k - 1).log_snr - log_snr).abs()
                        < (d.level_at_index(k).log_snr - log_snr).abs()
                {
                    d.level_at_index(k - 1)
                } else {
                    d.level_at_index(k)
                }
            }
            Self::Continuous(c) => {
                let t = c.time_of_log_snr(log_snr);
                NoiseLevel::from_log_snr(t, c.log_snr(t))
            }
        }
    }

    /// Draws a training time: uniform over `{1/T, …, 1}` (discrete) or `[0, 1)` (continuous).
    pub fn sample_train_level<R: rand::Rng + ?Sized>(&self, rng: &mut R) -> NoiseLevel {
        match self {
            Self::Discrete(d) => d.level_at_index(rng.random_range(1..=d.num_timesteps())),
            Self::Continuous(c) => {
                let t: f64 = rng.random();
                NoiseLevel::from_log_snr(t, c.log_snr(t))
            }
        }
    }

    /// The `steps` sampling levels, noisiest first, not including the final clean level.
    pub fn sampling_levels(&self, steps: usize, spacing: Spacing) -> Result<Vec<NoiseLevel>> {
        if steps == 0 {
            return Err(invalid("steps", "must be at least 1"));
        }
        match self {
            Self::Discrete(d) => {
                let t_total = d.num_timesteps();
                if steps > t_total {
                    return Err(invalid(
                        "steps",
                        format!("{steps} sampling steps exceed the schedule's {t_total} timesteps"),
                    ));
                }
                let ks: Vec<usize> = match spacing {
                    Spacing::Trailing => (0..steps)
                        .map(|i| {
                            (t_total as f64 - i as f64 * t_total as f64 / steps as f64).round()
                                as usize
                        })
                        .collect(),
                    Spacing::Leading => {
                        let stride = t_total / steps;
                        (0..steps).rev().map(|j| j * stride + 1).collect()
                    }
                    Spacing::Linspace => (0..steps)
                        .map(|i| {
                            if steps == 1 {
                                t_total
                            } else {
                                (t_total as f64
                                    - i as f64 * (t_total - 1) as f64 / (steps - 1) as f64)
                                    .round() as usize
                            }
                        })
                        .collect(),
                    Spacing::LogSnr => {
                        let hi = d.level_at_index(t_total).log_snr;
                        let lo = d.level_at_index(1).log_snr;
                        let mut ks: Vec<usize> = (0..steps)
                            .map(|i| {
                                let f = if steps == 1 {
                                    0.0
                                } else {
                                    i as f64 / (steps - 1) as f64
                                };
                                let l = self.level_of_log_snr(hi + f * (lo - hi));
                                (l.t * t_total as f64).round() as usize
                            })
                            .collect();
                        ks.dedup();
                        ks
                    }
                };
                Ok(ks
                    .into_iter()
                    .map(|k| d.level_at_index(k.clamp(1, t_total)))
                    .collect())
            }
            Self::Continuous(c) => {
                let ts: Vec<f64> = match spacing {
                    Spacing::Trailing | Spacing::Leading | Spacing::Linspace => {
                        (0..steps).map(|i| 1.0 - i as f64 / steps as f64).collect()
                    }
                    Spacing::LogSnr => {
                        let hi = c.log_snr(1.0);
                        let lo = c.log_snr(LOGSNR_SPACING_T_END);
                        (0..steps)
                            .map(|i| {
                                let f = if steps == 1 {
                                    0.0
                                } else {
                                    i as f64 / (steps - 1) as f64
                                };
                                c.time_of_log_snr(hi + f * (lo - hi))
                            })
                            .collect()
                    }
                };
                Ok(ts
                    .into_iter()
                    .map(|t| NoiseLevel::from_log_snr(t, c.log_snr(t)))
                    .collect())
            }
        }
    }
}

/// Which noise levels training draws (each draw is one sample's level).
///
/// Uniform time on the cosine schedule puts almost no draws at the clean end: with `λ` clipped
/// to ±20, a draw lands above `λ = 10` (σ below 0.007) about 1 time in 200. Images do not miss
/// those levels (their finest detail is an 8-bit step, σ ≈ 0.004); a range image does, because
/// its fine texture (a ground ring's centimetres at tens of metres) is 1e-4 to 1e-3 in the
/// encoding, and a sample's texture forms exactly there. [`TrainLevels::CleanShare`] gives those
/// levels a share of the draws of their own. Either choice trains the same model in the limit:
/// the draw density is a loss weighting over levels (Kingma and Gao 2023).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum TrainLevels {
    /// [`NoiseSchedule::sample_train_level`]: `t` uniform (a uniform index on a discrete
    /// schedule).
    #[default]
    UniformTime,
    /// A `share` of the draws uniform in log-SNR over `[log_snr_min, log_snr_max]` (the clean
    /// levels), the rest uniform in time.
    CleanShare {
        /// The share of draws at the clean levels, in `[0, 1]`.
        share: f64,
        /// The noisiest of them, as a log-SNR.
        log_snr_min: f64,
        /// The cleanest of them, as a log-SNR.
        log_snr_max: f64,
    },
}

impl TrainLevels {
    /// [`TrainLevels::CleanShare`] over `λ ∈ [6, 18]`, σ from 0.05 down to 1.2e-4: where the
    /// texture of a range image's log-range encoding lives.
    pub fn clean_share(share: f64) -> Self {
        Self::CleanShare {
            share,
            log_snr_min: 6.0,
            log_snr_max: 18.0,
        }
    }

    /// Whether this is [`TrainLevels::UniformTime`] (the default, left out of a saved config).
    pub fn is_uniform_time(&self) -> bool {
        matches!(self, Self::UniformTime)
    }

    /// Checks the share and the range.
    pub fn validate(&self) -> Result<()> {
        if let Self::CleanShare {
            share,
            log_snr_min,
            log_snr_max,
        } = *self
        {
            if !(0.0..=1.0).contains(&share) {
                return Err(invalid(
                    "train_levels.share",
                    format!("must be in [0, 1], got {share}"),
                ));
            }
            if !(log_snr_min.is_finite() && log_snr_max.is_finite() && log_snr_min < log_snr_max) {
                return Err(invalid(
                    "train_levels.log_snr_min/log_snr_max",
                    format!(
                        "need finite log_snr_min < log_snr_max, got {log_snr_min}, {log_snr_max}"
                    ),
                ));
            }
        }
        Ok(())
    }

    /// Draws one training level of `schedule` (a clean-level draw is the schedule's level
    /// nearest to the drawn log-SNR, within the schedule's own range).
    pub fn draw<R: rand::Rng + ?Sized>(&self, schedule: &NoiseSchedule, rng: &mut R) -> NoiseLevel {
        match *self {
            Self::UniformTime => schedule.sample_train_level(rng),
            Self::CleanShare {
                share,
                log_snr_min,
                log_snr_max,
            } => {
                if rng.random::<f64>() < share {
                    let u: f64 = rng.random();
                    schedule.level_of_log_snr(log_snr_min + u * (log_snr_max - log_snr_min))
                } else {
                    schedule.sample_train_level(rng)
                }
            }
        }
    }
}

/// Time at which [`Spacing::LogSnr`] ends on a continuous schedule (DPM-Solver's `t_ε = 1e-3`).
pub const LOGSNR_SPACING_T_END: f64 = 1e-3;

/// How sampling levels are placed on the schedule.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Spacing {
    /// `t_i = 1 − i/N`: starts at the noisiest level (Lin et al. 2024, recommended).
    #[default]
    Trailing,
    /// DDIM's original `k = j·⌊T/N⌋ + 1`: never visits the noisiest level exactly.
    Leading,
    /// `N` points spread evenly over `[1/T, 1]` including both ends.
    Linspace,
    /// Uniform in log-SNR from the noisiest level to the least noisy one (`k = 1` on a discrete
    /// schedule, `t = 1e-3` on a continuous one), so the final jump to clean data is negligible
    /// (suits DPM-Solver++). Discrete schedules may return fewer than `N` levels when grid points
    /// coincide.
    LogSnr,
}

impl Spacing {
    /// Every spacing, in the order help texts list them: the one list the doors' `--spacing`
    /// choices are built from.
    pub const ALL: [Spacing; 4] = [
        Spacing::Trailing,
        Spacing::Leading,
        Spacing::Linspace,
        Spacing::LogSnr,
    ];

    /// The name a command line, a config and a bundle use (`trailing`, `leading`, `linspace`,
    /// `log_snr`: the serialized name).
    pub fn as_str(self) -> &'static str {
        match self {
            Spacing::Trailing => "trailing",
            Spacing::Leading => "leading",
            Spacing::Linspace => "linspace",
            Spacing::LogSnr => "log_snr",
        }
    }

    /// One line of help for the name.
    pub fn help(self) -> &'static str {
        match self {
            Spacing::Trailing => "t = 1 - i/N: the last step jumps to clean data from t = 1/N",
            Spacing::Leading => "DDIM's original grid (never the noisiest level)",
            Spacing::Linspace => "N points over [1/T, 1], both ends included",
            Spacing::LogSnr => {
                "uniform in log-SNR down to t = 1e-3: the last steps refine the fine texture"
            }
        }
    }
}

impl std::fmt::Display for Spacing {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for Spacing {
    type Err = crate::Error;

    fn from_str(name: &str) -> Result<Self> {
        Spacing::ALL
            .into_iter()
            .find(|s| s.as_str() == name)
            .ok_or_else(|| {
                let names: Vec<&str> = Spacing::ALL.map(Spacing::as_str).into();
                invalid(
                    "spacing",
                    format!("`{name}` is not one of {}", names.join(", ")),
                )
            })
    }
}

#[cfg(test)]
mod tests;
