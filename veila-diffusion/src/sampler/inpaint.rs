//! RePaint-style inpainting (Lugmayr et al. 2022): completion and scene editing.
//!
//! At every step the known pixels are re-noised to the current level from the known clean image and
//! pasted over the sample, so only the masked region is generated; optional resampling jumps
//! (going back up `jump_length` levels with the forward process and descending again) let the
//! generated region harmonise with the known one.

use candle_core::Tensor;
use serde::{Deserialize, Serialize};

use super::steps::{beta_between, ddim_step, ddpm_step};
use super::{Sampler, SamplerKind};
use crate::denoiser::Denoiser;
use crate::error::{Error, Result, invalid};
use crate::noise::{NoiseSource, randn_like};
use crate::schedule::NoiseLevel;

/// Resampling settings; `jump_n_sample = 1` disables resampling.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RepaintConfig {
    /// How many levels each jump goes back up (RePaint: 10).
    pub jump_length: usize,
    /// How many times each jump segment is traversed (RePaint: 10; 1 = no jumps).
    pub jump_n_sample: usize,
}

impl Default for RepaintConfig {
    fn default() -> Self {
        Self {
            jump_length: 10,
            jump_n_sample: 1,
        }
    }
}

/// The sequence of level indices RePaint visits for `n` sampling levels: index `n` is the noisiest
/// level, `0` clean data. A decrease is a denoising step, an increase a forward re-noising step.
///
/// Jumps start at every index `i = 1 + m·jump_length` with `i + jump_length ≤ n`; each is taken
/// `jump_n_sample − 1` times.
pub fn repaint_schedule(n: usize, cfg: &RepaintConfig) -> Result<Vec<usize>> {
    if cfg.jump_length == 0 || cfg.jump_n_sample == 0 {
        return Err(invalid(
            "repaint",
            "jump_length and jump_n_sample must be at least 1",
        ));
    }
    let mut remaining = vec![0usize; n + 1];
    let mut i = 1;
    while i + cfg.jump_length <= n {
        remaining[i] = cfg.jump_n_sample - 1;
        i += cfg.jump_length;
    }
    let mut seq = vec![n];
    let mut i = n;
    while i > 0 {
        i -= 1;
        seq.push(i);
        if remaining[i] > 0 {
            remaining[i] -= 1;
            for _ in 0..cfg.jump_length {
                i += 1;
                seq.push(i);
            }
        }
    }
    Ok(seq)
}

/// Inpaints: keeps the pixels of `known_x0` where `known_mask` is 1 and generates the rest.
///
/// * `known_x0`: the encoded clean image `[B, C, H, W]`.
/// * `known_mask`: 1 = keep, 0 = generate; any shape that broadcasts to `known_x0`
///   (e.g. `[B, 1, H, W]`), same dtype.
/// * The sampler must be DDPM or DDIM (a multistep solver has no meaning across jumps).
///
/// Returns the clean sample with the known pixels exactly equal to `known_x0`.
pub fn inpaint<D: Denoiser, R: NoiseSource + ?Sized>(
    sampler: &Sampler<'_>,
    model: &D,
    known_x0: &Tensor,
    known_mask: &Tensor,
    cond: Option<&D::Cond>,
    repaint: &RepaintConfig,
    rng: &mut R,
) -> Result<Tensor> {
    if matches!(sampler.config().kind, SamplerKind::DpmSolverPp2M) {
        return Err(invalid("kind", "inpainting needs the ddpm or ddim sampler"));
    }
    if !sampler.diffusion().config().objective.is_diffusion() {
        return Err(invalid(
            "objective",
            "RePaint inpainting needs a Gaussian-diffusion model (not rectified flow or regression)",
        ));
    }
    let mask = known_mask
        .broadcast_as(known_x0.shape())
        .map_err(|_| Error::Shape {
            what: "known_mask",
            expected: format!("broadcastable to {:?}", known_x0.dims()),
            got: format!("{:?}", known_mask.dims()),
        })?;
    let mask = mask.to_dtype(known_x0.dtype())?;
    let inv = mask.affine(-1.0, 1.0)?;
    let b = known_x0.dim(0)?;
    let uncond = sampler.uncond_for(cond, b)?;

    // levels[0] = clean, levels[n] = noisiest.
    let mut levels = vec![NoiseLevel::CLEAN];
    levels.extend(sampler.levels().iter().rev().copied());
    let n = levels.len() - 1;
    let seq = repaint_schedule(n, repaint)?;

    let mut x = randn_like(rng, known_x0)?;
    for w in seq.windows(2) {
        let (cur, next) = (w[0], w[1]);
        let (from, to) = (levels[cur], levels[next]);
        if next < cur {
            let d = sampler.denoise(model, &x, &from, cond, uncond.as_ref())?;
            let unknown = match sampler.config().kind {
                SamplerKind::Ddpm { variance } => {
                    let z = if to.is_clean() {
                        None
                    } else {
                        Some(randn_like(rng, known_x0)?)
                    };
                    ddpm_step(&x, &d, &from, &to, variance, z.as_ref())?
                }
                SamplerKind::Ddim { eta } => {
                    let z = if to.is_clean() || eta == 0.0 {
                        None
                    } else {
                        Some(randn_like(rng, known_x0)?)
                    };
                    ddim_step(&d, &from, &to, eta, z.as_ref())?
                }
                SamplerKind::DpmSolverPp2M => unreachable!("rejected above"),
            };
            let known = if to.is_clean() {
                known_x0.clone()
            } else {
                let z = randn_like(rng, known_x0)?;
                ((known_x0 * to.alpha())? + (z * to.sigma())?)?
            };
            x = (known.mul(&mask)? + unknown.mul(&inv)?)?;
        } else {
            // forward re-noising q(x_next | x_cur), `next` noisier than `cur`
            let beta = beta_between(&to, &from);
            let keep = (0.5 * (to.log_alpha_bar() - from.log_alpha_bar())).exp();
            let z = randn_like(rng, known_x0)?;
            x = ((x * keep)? + (z * beta.sqrt())?)?;
        }
    }
    Ok(x)
}
