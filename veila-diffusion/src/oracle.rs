//! Analytic denoisers for validating samplers: when the data are i.i.d. Gaussian per pixel,
//! `x_0 ~ N(μ, s²)`, the optimal denoiser and the probability-flow ODE have closed forms.
//!
//! With `x_t = α·x_0 + σ·ε`: `E[x_0 | x_t] = μ + α·s²/(α²·s² + σ²)·(x_t − α·μ)`, the marginal is
//! `N(α·μ, α²·s² + σ²)`, and the probability-flow ODE keeps the standardised value
//! `(x_t − α·μ)/sqrt(α²·s² + σ²)` constant, so its exact solution from `x_T` is
//! `x_0 = μ + s·(x_T − α_T·μ)/sqrt(α_T²·s² + σ_T²)`.
//!
//! When the data are a finite set of points `x_1 … x_K` drawn uniformly ([`EmpiricalOracle`]), the
//! optimal denoiser is the posterior-weighted mean of the points, with weights
//! `softmax_k(−‖x_t − α·x_k‖² / (2σ²))`. A sampler driven by it must end on the points themselves,
//! all of them reachable: a multimodal check that the Gaussian case cannot make (its mean and its
//! samples are one mode), and the ideal network of a model trained on `K` frames.

use candle_core::{DType, Tensor};

use crate::denoiser::Denoiser;
use crate::error::{Result, invalid};
use crate::objective::Diffusion;
use crate::prediction::Prediction;
use crate::schedule::NoiseLevel;

/// The Bayes-optimal denoiser for `x_0 ~ N(mean, std²)` i.i.d. per element, answering in the
/// diffusion's parameterisation.
#[derive(Debug, Clone)]
pub struct GaussianOracle {
    mean: f64,
    std: f64,
    diffusion: Diffusion,
}

impl GaussianOracle {
    /// A new oracle; `std` must be positive.
    pub fn new(mean: f64, std: f64, diffusion: Diffusion) -> Result<Self> {
        if !(mean.is_finite() && std.is_finite() && std > 0.0) {
            return Err(invalid(
                "std",
                format!("need finite mean and std > 0, got {mean}, {std}"),
            ));
        }
        Ok(Self {
            mean,
            std,
            diffusion,
        })
    }

    /// Data mean `μ`.
    pub fn mean(&self) -> f64 {
        self.mean
    }

    /// Data standard deviation `s`.
    pub fn std(&self) -> f64 {
        self.std
    }

    /// `(a, b)` with `E[x_0 | x_t] = a + b·x_t` at `level`.
    pub fn posterior_mean_coeffs(&self, level: &NoiseLevel) -> (f64, f64) {
        let (a, s2) = (level.alpha(), self.std * self.std);
        let b = a * s2 / (level.alpha_bar * s2 + level.sigma2);
        (self.mean - b * a * self.mean, b)
    }

    /// The exact probability-flow ODE solution at clean data from `x_T` at `level_t` (f64, per element).
    pub fn pf_ode_solution(&self, x_t: f64, level_t: &NoiseLevel) -> f64 {
        let a = level_t.alpha();
        let scale = (level_t.alpha_bar * self.std * self.std + level_t.sigma2).sqrt();
        self.mean + self.std * (x_t - a * self.mean) / scale
    }
}

impl Denoiser for GaussianOracle {
    type Cond = ();

    fn forward(&self, x_t: &Tensor, t: &Tensor, _cond: Option<&()>) -> candle_core::Result<Tensor> {
        let b = x_t.dim(0)?;
        let tv = t.to_dtype(DType::F64)?.to_vec1::<f64>()?;
        if tv.len() != b {
            candle_core::bail!("oracle: {} time values for a batch of {b}", tv.len())
        }
        let mut shape = vec![1usize; x_t.rank()];
        shape[0] = b;
        let (mut k0s, mut k1s) = (Vec::with_capacity(b), Vec::with_capacity(b));
        let (mu, s2) = (self.mean, self.std * self.std);
        for &v in &tv {
            let level = self.diffusion.level_of_model_time(v);
            let (al, si) = (level.alpha(), level.sigma());
            let d = level.alpha_bar * s2 + level.sigma2;
            // output = k0 + k1·x_t for every parameterisation, written without cancellation
            let (k0, k1) = match self.diffusion.prediction() {
                Prediction::Sample => (mu * level.sigma2 / d, al * s2 / d),
                Prediction::Epsilon => (-al * mu * si / d, si / d),
                Prediction::V => (-mu * si / d, al * si * (1.0 - s2) / d),
            };
            k0s.push(k0 as f32);
            k1s.push(k1 as f32);
        }
        let k0 = Tensor::from_vec(k0s, shape.clone(), x_t.device())?.to_dtype(x_t.dtype())?;
        let k1 = Tensor::from_vec(k1s, shape, x_t.device())?.to_dtype(x_t.dtype())?;
        x_t.broadcast_mul(&k1)?.broadcast_add(&k0)
    }
}

/// The Bayes-optimal denoiser for `x_0` drawn uniformly from a finite set of points (every sample
/// of a batch has the points' shape), answering in the diffusion's parameterisation. Gaussian
/// diffusion only ([`Objective::Diffusion`](crate::Objective::Diffusion)).
#[derive(Debug, Clone)]
pub struct EmpiricalOracle {
    points: Vec<Vec<f64>>,
    diffusion: Diffusion,
}

impl EmpiricalOracle {
    /// A new oracle over `points`: at least one, all of one non-zero length, all finite.
    pub fn new(points: Vec<Vec<f64>>, diffusion: Diffusion) -> Result<Self> {
        let Some(d) = points.first().map(Vec::len) else {
            return Err(invalid("points", "need at least one point"));
        };
        if d == 0
            || points
                .iter()
                .any(|p| p.len() != d || p.iter().any(|v| !v.is_finite()))
        {
            return Err(invalid(
                "points",
                "need points of one non-zero length with finite values",
            ));
        }
        if !diffusion.config().objective.is_diffusion() {
            return Err(invalid(
                "diffusion",
                "the oracle answers Gaussian diffusion only",
            ));
        }
        Ok(Self { points, diffusion })
    }

    /// The points.
    pub fn points(&self) -> &[Vec<f64>] {
        &self.points
    }

    /// `E[x_0 | x_t]` at `level` for one flattened sample (f64, log-sum-exp stable).
    pub fn posterior_mean(&self, x_t: &[f64], level: &NoiseLevel) -> Vec<f64> {
        let (a, s2) = (level.alpha(), level.sigma2.max(f64::MIN_POSITIVE));
        let logits: Vec<f64> = self
            .points
            .iter()
            .map(|p| {
                let d2: f64 = p
                    .iter()
                    .zip(x_t)
                    .map(|(&x0, &x)| (x - a * x0).powi(2))
                    .sum();
                -d2 / (2.0 * s2)
            })
            .collect();
        let top = logits.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let w: Vec<f64> = logits.iter().map(|l| (l - top).exp()).collect();
        let total: f64 = w.iter().sum();
        let mut mean = vec![0.0; x_t.len()];
        for (p, wk) in self.points.iter().zip(&w) {
            for (m, &v) in mean.iter_mut().zip(p) {
                *m += wk / total * v;
            }
        }
        mean
    }
}

impl Denoiser for EmpiricalOracle {
    type Cond = ();

    fn forward(&self, x_t: &Tensor, t: &Tensor, _cond: Option<&()>) -> candle_core::Result<Tensor> {
        let b = x_t.dim(0)?;
        let d = self.points[0].len();
        if x_t.elem_count() != b * d {
            candle_core::bail!(
                "oracle: samples of {} values, points of {d}",
                x_t.elem_count() / b.max(1)
            )
        }
        let tv = t.to_dtype(DType::F64)?.to_vec1::<f64>()?;
        if tv.len() != b {
            candle_core::bail!("oracle: {} time values for a batch of {b}", tv.len())
        }
        let xs = x_t.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?;
        let mut out = Vec::with_capacity(b * d);
        for (i, &v) in tv.iter().enumerate() {
            let level = self.diffusion.level_of_model_time(v);
            let x = &xs[i * d..(i + 1) * d];
            let x0 = self.posterior_mean(x, &level);
            let (al, si) = (level.alpha(), level.sigma());
            out.extend(
                x.iter()
                    .zip(&x0)
                    .map(|(&x, &m)| match self.diffusion.prediction() {
                        Prediction::Sample => m,
                        Prediction::Epsilon => (x - al * m) / si,
                        Prediction::V => (al * x - m) / si,
                    }),
            );
        }
        Tensor::from_vec(out, x_t.shape(), x_t.device())?.to_dtype(x_t.dtype())
    }
}
