//! The network interface the samplers and the trainer are written against.

use candle_core::{DType, Tensor};
use rand::Rng;

/// A denoising network: maps a noisy batch, the per-sample time value and an optional conditioning
/// to the chosen [`Prediction`](crate::Prediction) (ε, v or x₀), with the same shape as `x_t`.
///
/// `t` is a `[B]` f32 tensor whose values come from [`TimeInput`](crate::TimeInput) (e.g. `1000·t`
/// or the log-SNR). `cond = None` means "no conditioning at all" (an unconditional model); the
/// *unconditional branch* of classifier-free guidance instead uses
/// [`Conditioning::drop_samples`], exactly as condition dropout does during training.
pub trait Denoiser {
    /// The conditioning the network takes (camera features, a tensor, or `()` for none).
    type Cond: Conditioning;

    /// Runs the network.
    fn forward(
        &self,
        x_t: &Tensor,
        t: &Tensor,
        cond: Option<&Self::Cond>,
    ) -> candle_core::Result<Tensor>;

    /// Completes the gradients of a backward pass through this network: a network that recomputes
    /// activations in its backward pass adds its parameters' gradients here. The trainer calls
    /// it after every `backward()`; the default adds nothing.
    fn finish_backward(
        &self,
        _grads: &mut candle_core::backprop::GradStore,
    ) -> candle_core::Result<()> {
        Ok(())
    }
}

impl<D: Denoiser + ?Sized> Denoiser for &D {
    type Cond = D::Cond;
    fn forward(
        &self,
        x_t: &Tensor,
        t: &Tensor,
        cond: Option<&Self::Cond>,
    ) -> candle_core::Result<Tensor> {
        (**self).forward(x_t, t, cond)
    }
    fn finish_backward(
        &self,
        grads: &mut candle_core::backprop::GradStore,
    ) -> candle_core::Result<()> {
        (**self).finish_backward(grads)
    }
}

impl<D: Denoiser + ?Sized> Denoiser for Box<D> {
    type Cond = D::Cond;
    fn forward(
        &self,
        x_t: &Tensor,
        t: &Tensor,
        cond: Option<&Self::Cond>,
    ) -> candle_core::Result<Tensor> {
        (**self).forward(x_t, t, cond)
    }
    fn finish_backward(
        &self,
        grads: &mut candle_core::backprop::GradStore,
    ) -> candle_core::Result<()> {
        (**self).finish_backward(grads)
    }
}

/// Mixed precision: runs `inner` on its input cast to `dtype` (bf16 on a GPU) and returns the
/// prediction in the input's dtype. The network's weights stay where they are (f32 master
/// weights while training): veila-nn's layers cast them to the activations' dtype at use, run
/// their normalisations and softmaxes in f32, and the gradients flow back through the casts.
/// With `dtype` equal to the input's, this is `inner` itself.
#[derive(Debug, Clone, Copy)]
pub struct Autocast<D> {
    /// The wrapped network.
    pub inner: D,
    /// The activations' dtype.
    pub dtype: DType,
}

impl<D: Denoiser> Denoiser for Autocast<D> {
    type Cond = D::Cond;
    fn forward(
        &self,
        x_t: &Tensor,
        t: &Tensor,
        cond: Option<&Self::Cond>,
    ) -> candle_core::Result<Tensor> {
        if x_t.dtype() == self.dtype {
            return self.inner.forward(x_t, t, cond);
        }
        self.inner
            .forward(&x_t.to_dtype(self.dtype)?, t, cond)?
            .to_dtype(x_t.dtype())
    }
    fn finish_backward(
        &self,
        grads: &mut candle_core::backprop::GradStore,
    ) -> candle_core::Result<()> {
        self.inner.finish_backward(grads)
    }
}

/// A conditioning that can be replaced by the "null" conditioning per sample, for condition dropout
/// during training and the unconditional branch of classifier-free guidance.
pub trait Conditioning: Sized {
    /// Returns a copy where every sample `i` with `drop[i] == true` carries the null conditioning.
    /// `drop.len()` is the batch size.
    fn drop_samples(&self, drop: &[bool]) -> candle_core::Result<Self>;
}

/// No conditioning.
impl Conditioning for () {
    fn drop_samples(&self, _drop: &[bool]) -> candle_core::Result<Self> {
        Ok(())
    }
}

/// A batch-first tensor; the null conditioning is all zeros.
impl Conditioning for Tensor {
    fn drop_samples(&self, drop: &[bool]) -> candle_core::Result<Self> {
        let b = self.dim(0)?;
        if drop.len() != b {
            candle_core::bail!(
                "drop_samples: mask of length {} for a batch of {b}",
                drop.len()
            )
        }
        let keep: Vec<f32> = drop.iter().map(|&d| if d { 0.0 } else { 1.0 }).collect();
        let mut shape = vec![1usize; self.rank()];
        shape[0] = b;
        let keep = Tensor::from_vec(keep, shape, self.device())?.to_dtype(self.dtype())?;
        self.broadcast_mul(&keep)
    }
}

impl<A: Conditioning, B: Conditioning> Conditioning for (A, B) {
    fn drop_samples(&self, drop: &[bool]) -> candle_core::Result<Self> {
        Ok((self.0.drop_samples(drop)?, self.1.drop_samples(drop)?))
    }
}

impl<C: Conditioning> Conditioning for Vec<C> {
    fn drop_samples(&self, drop: &[bool]) -> candle_core::Result<Self> {
        self.iter().map(|c| c.drop_samples(drop)).collect()
    }
}

/// Per-sample condition dropout for classifier-free guidance training (Ho & Salimans 2022).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CondDropout {
    /// Probability of replacing a sample's conditioning with the null conditioning (e.g. 0.1).
    pub prob: f64,
}

impl CondDropout {
    /// Draws the per-sample drop mask (one uniform draw per sample, always, so the RNG stream does
    /// not depend on the outcome).
    pub fn sample_mask<R: Rng + ?Sized>(&self, batch: usize, rng: &mut R) -> Vec<bool> {
        (0..batch)
            .map(|_| rng.random::<f64>() < self.prob)
            .collect()
    }

    /// Applies dropout to `cond`, returning the new conditioning and the mask.
    pub fn apply<C: Conditioning, R: Rng + ?Sized>(
        &self,
        cond: &C,
        batch: usize,
        rng: &mut R,
    ) -> candle_core::Result<(C, Vec<bool>)> {
        let mask = self.sample_mask(batch, rng);
        Ok((cond.drop_samples(&mask)?, mask))
    }
}

/// Classifier-free guidance: `uncond + scale · (cond − uncond)`. `scale = 1` returns `cond`,
/// `scale = 0` returns `uncond`.
pub fn guide(uncond: &Tensor, cond: &Tensor, scale: f64) -> candle_core::Result<Tensor> {
    if scale == 1.0 {
        return Ok(cond.clone());
    }
    uncond + ((cond - uncond)? * scale)?
}

/// A `[B]` f32 time tensor from per-sample values.
pub(crate) fn time_tensor(
    values: &[f64],
    device: &candle_core::Device,
) -> candle_core::Result<Tensor> {
    Tensor::from_vec(
        values.iter().map(|&v| v as f32).collect::<Vec<f32>>(),
        values.len(),
        device,
    )?
    .to_dtype(DType::F32)
}
