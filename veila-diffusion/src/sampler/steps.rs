//! Single-step update rules (pure tensor math, coefficients in f64).

use candle_core::Tensor;

use super::DdpmVariance;
use crate::error::{Result, invalid};
use crate::objective::Denoised;
use crate::schedule::NoiseLevel;

fn check_order(from: &NoiseLevel, to: &NoiseLevel) -> Result<()> {
    if from.is_clean() || to.log_snr.is_nan() || to.log_snr <= from.log_snr {
        return Err(invalid(
            "levels",
            format!(
                "a sampler step must go from a noisy level to a less noisy one (log-SNR {} -> {})",
                from.log_snr, to.log_snr
            ),
        ));
    }
    Ok(())
}

/// `1 − ᾱ_t/ᾱ_s` for `s` less noisy than `t`, without cancellation.
pub(crate) fn beta_between(from: &NoiseLevel, to: &NoiseLevel) -> f64 {
    -(from.log_alpha_bar() - to.log_alpha_bar()).exp_m1()
}

fn lin2(a: &Tensor, ca: f64, b: &Tensor, cb: f64) -> Result<Tensor> {
    Ok(((a * ca)? + (b * cb)?)?)
}

/// One DDPM ancestral step from `from` (`t`) to the less noisy `to` (`s`), using `x̂_0`:
///
/// `x_s = sqrt(ᾱ_s)·β_{t|s}/σ_t² · x̂_0 + sqrt(ᾱ_t/ᾱ_s)·σ_s²/σ_t² · x_t + std · z`,
/// with `β_{t|s} = 1 − ᾱ_t/ᾱ_s` and `std² = β_{t|s}·σ_s²/σ_t²` (posterior) or `β_{t|s}` (beta).
/// `noise = None` takes `z = 0` (always the case for the final step to clean data).
pub fn ddpm_step(
    x_t: &Tensor,
    d: &Denoised,
    from: &NoiseLevel,
    to: &NoiseLevel,
    variance: DdpmVariance,
    noise: Option<&Tensor>,
) -> Result<Tensor> {
    check_order(from, to)?;
    let beta = beta_between(from, to);
    let c_x0 = to.alpha() * beta / from.sigma2;
    let c_xt = (0.5 * (from.log_alpha_bar() - to.log_alpha_bar())).exp() * to.sigma2 / from.sigma2;
    let mean = lin2(&d.x0, c_x0, x_t, c_xt)?;
    match noise {
        Some(z) if !to.is_clean() => {
            let var = match variance {
                DdpmVariance::Posterior => beta * to.sigma2 / from.sigma2,
                DdpmVariance::Beta => beta,
            };
            Ok((mean + (z * var.sqrt())?)?)
        }
        _ => Ok(mean),
    }
}

/// One DDIM step from `from` (`t`) to the less noisy `to` (`s`), using `x̂_0` and `ε̂`:
///
/// `x_s = sqrt(ᾱ_s)·x̂_0 + sqrt(σ_s² − c²)·ε̂ + c·z`, `c = η·sqrt(σ_s²/σ_t² · (1 − ᾱ_t/ᾱ_s))`.
/// `noise = None` takes `z = 0`.
pub fn ddim_step(
    d: &Denoised,
    from: &NoiseLevel,
    to: &NoiseLevel,
    eta: f64,
    noise: Option<&Tensor>,
) -> Result<Tensor> {
    check_order(from, to)?;
    let c2 = eta * eta * to.sigma2 / from.sigma2 * beta_between(from, to);
    let c_eps = (to.sigma2 - c2).max(0.0).sqrt();
    let det = lin2(&d.x0, to.alpha(), &d.eps, c_eps)?;
    match noise {
        Some(z) if c2 > 0.0 => Ok((det + (z * c2.sqrt())?)?),
        _ => Ok(det),
    }
}

/// DPM-Solver++(2M): the multistep second-order solver of the probability-flow ODE in data
/// prediction form. With `λ = log(α/σ)` and `h = λ_s − λ_t`:
///
/// `x_s = (σ_s/σ_t)·x_t − α_s·(e^{−h} − 1)·D`, where `D = x̂_0` on the first step and
/// `D = (1 + 1/(2r))·x̂_0 − 1/(2r)·x̂_0^{prev}`, `r = h_prev/h`, afterwards. The step to clean data
/// returns `x̂_0` (first order, as the final step of DPM-Solver++ always is).
#[derive(Debug, Clone, Default)]
pub struct DpmSolverPp2M {
    prev: Option<(Tensor, f64)>,
}

impl DpmSolverPp2M {
    /// Forgets the history (start of a new trajectory).
    pub fn reset(&mut self) {
        self.prev = None;
    }

    /// One step from `from` to the less noisy `to`, given the model's `x̂_0` at `from`.
    pub fn step(
        &mut self,
        x_t: &Tensor,
        x0: &Tensor,
        from: &NoiseLevel,
        to: &NoiseLevel,
    ) -> Result<Tensor> {
        check_order(from, to)?;
        if to.is_clean() {
            self.prev = None;
            return Ok(x0.clone());
        }
        let lam_t = 0.5 * from.log_snr;
        let lam_s = 0.5 * to.log_snr;
        let h = lam_s - lam_t;
        let d = match &self.prev {
            Some((x0_prev, h_prev)) if *h_prev > 0.0 => {
                let r = h_prev / h;
                lin2(x0, 1.0 + 0.5 / r, x0_prev, -0.5 / r)?
            }
            _ => x0.clone(),
        };
        let ratio = (0.5 * (to.sigma2.ln() - from.sigma2.ln())).exp();
        let c_d = -to.alpha() * (-h).exp_m1();
        let x_s = lin2(x_t, ratio, &d, c_d)?;
        self.prev = Some((x0.clone(), h));
        Ok(x_s)
    }
}
