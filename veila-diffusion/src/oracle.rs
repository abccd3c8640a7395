//! Analytic denoisers for validating samplers: when the data are i.i.d. Gaussian per pixel,
//! `x_0 ~ N(μ, s²)`, the optimal denoiser and the probability-flow ODE have closed forms.
//!
//! With `x_t = α·x_0 + σ·ε`: `E[x_0 | x_t] = μ + α·s²/(α²·s² + σ²)·(x_t − α·μ)`, the marginal is
//! `N(α·μ, α²·s² + σ²)`, and the probability-flow ODE keeps the standardised value
//! `(x_t − α·μ)/sqrt(α²·s² + σ²)` constant, so its exact solution from `x_T` is
//! `x_0 = μ + s·(x_T − α_T·μ)/sqrt(α_T²·s² + σ_T²)`.

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
