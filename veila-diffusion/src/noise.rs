//! Seeded Gaussian noise, drawn on the CPU so results do not depend on the device.

use candle_core::{Device, Tensor};
use rand::Rng;
use rand_distr::StandardNormal;

use crate::error::{Error, Result};

/// A standard-normal f32 tensor of `shape`, drawn from `rng` (in row-major order) and moved to `device`.
pub fn randn<R: Rng + ?Sized>(rng: &mut R, shape: &[usize], device: &Device) -> Result<Tensor> {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n)
        .map(|_| rng.sample::<f32, _>(StandardNormal))
        .collect();
    Ok(Tensor::from_vec(v, shape, device)?)
}

/// Where a sampler's noise comes from: any random generator (one stream for the whole batch) or
/// [`PerSample`] generators.
pub trait NoiseSource {
    /// Standard-normal f32 noise of `shape` (batch first) on `device`.
    fn noise(&mut self, shape: &[usize], device: &Device) -> Result<Tensor>;
}

impl<R: Rng + ?Sized> NoiseSource for R {
    fn noise(&mut self, shape: &[usize], device: &Device) -> Result<Tensor> {
        randn(self, shape, device)
    }
}

/// One generator per sample of a batch: sample `i` of every noise tensor (index `i` of its first
/// dimension) is drawn from generator `i`, so what a sample gets does not depend on how many
/// other samples share its batch. A batch of one draws exactly what its generator alone would.
#[derive(Debug, Clone)]
pub struct PerSample<R>(pub Vec<R>);

impl<R: Rng> NoiseSource for PerSample<R> {
    fn noise(&mut self, shape: &[usize], device: &Device) -> Result<Tensor> {
        if shape.first() != Some(&self.0.len()) {
            return Err(Error::Shape {
                what: "per-sample noise",
                expected: format!("a batch of {}", self.0.len()),
                got: format!("{shape:?}"),
            });
        }
        let per: usize = shape[1..].iter().product();
        let mut v: Vec<f32> = Vec::with_capacity(per * self.0.len());
        for rng in &mut self.0 {
            v.extend((0..per).map(|_| rng.sample::<f32, _>(StandardNormal)));
        }
        Ok(Tensor::from_vec(v, shape, device)?)
    }
}

/// Standard-normal noise with the shape, dtype and device of `like`.
pub fn randn_like<R: NoiseSource + ?Sized>(rng: &mut R, like: &Tensor) -> Result<Tensor> {
    Ok(rng
        .noise(like.dims(), like.device())?
        .to_dtype(like.dtype())?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn a_sample_draws_the_same_noise_whatever_the_batch() {
        let gens = |n: usize| {
            PerSample(
                (0..n as u64)
                    .map(|i| {
                        let mut r = ChaCha8Rng::seed_from_u64(7);
                        r.set_stream(i);
                        r
                    })
                    .collect(),
            )
        };
        let one = gens(1).noise(&[1, 2, 3], &Device::Cpu).unwrap();
        let eight = gens(8).noise(&[8, 2, 3], &Device::Cpu).unwrap();
        let first = eight.narrow(0, 0, 1).unwrap();
        let (a, b) = (
            one.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            first.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
        );
        assert_eq!(a, b);
        // a batch of one is its generator's own stream
        let plain = randn(&mut ChaCha8Rng::seed_from_u64(7), &[1, 2, 3], &Device::Cpu).unwrap();
        assert_eq!(a, plain.flatten_all().unwrap().to_vec1::<f32>().unwrap());
        // the other samples differ from the first
        let second = eight.narrow(0, 1, 1).unwrap().flatten_all().unwrap();
        assert_ne!(a, second.to_vec1::<f32>().unwrap());
        assert!(gens(2).noise(&[3, 1], &Device::Cpu).is_err());
    }
}
