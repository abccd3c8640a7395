//! Seeded Gaussian noise, drawn on the CPU so results do not depend on the device.

use candle_core::{Device, Tensor};
use rand::Rng;
use rand_distr::StandardNormal;

use crate::error::Result;

/// A standard-normal f32 tensor of `shape`, drawn from `rng` (in row-major order) and moved to `device`.
pub fn randn<R: Rng + ?Sized>(rng: &mut R, shape: &[usize], device: &Device) -> Result<Tensor> {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n)
        .map(|_| rng.sample::<f32, _>(StandardNormal))
        .collect();
    Ok(Tensor::from_vec(v, shape, device)?)
}

/// Standard-normal noise with the shape, dtype and device of `like`.
pub fn randn_like<R: Rng + ?Sized>(rng: &mut R, like: &Tensor) -> Result<Tensor> {
    Ok(randn(rng, like.dims(), like.device())?.to_dtype(like.dtype())?)
}
