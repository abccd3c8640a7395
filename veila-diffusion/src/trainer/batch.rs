//! What the trainer trains on: [`Batch`]es from a [`BatchSource`], whole or in parts.

use candle_core::Tensor;

use crate::error::{Result, invalid};

/// One training batch.
#[derive(Debug, Clone)]
pub struct Batch<C> {
    /// Encoded clean range images `[B, C, H, W]`.
    pub x0: Tensor,
    /// Conditioning for the batch (`None` for unconditional training).
    pub cond: Option<C>,
    /// Per-element loss weights broadcastable to `x0` (`None`: all 1); see
    /// [`Diffusion::training_loss_weighted`](crate::objective::Diffusion::training_loss_weighted).
    pub weight: Option<Tensor>,
}

/// Where batches come from. `step` is the 0-based index of the update the batch is for; a source
/// that is a pure function of `step` makes resumed runs identical to uninterrupted ones.
pub trait BatchSource<C> {
    /// The batch for update `step`.
    fn batch(&mut self, step: u64) -> Result<Batch<C>>;

    /// Part `part` of `parts` of the batch of update `step` (gradient accumulation,
    /// [`TrainConfig::grad_accum_steps`](super::TrainConfig::grad_accum_steps)): the parts are disjoint and together the whole batch.
    /// The default splits [`Self::batch`] along the batch axis into contiguous parts whose sizes
    /// differ by at most one; it cannot split a conditioning, so conditional sources implement
    /// this themselves.
    fn batch_part(&mut self, step: u64, part: usize, parts: usize) -> Result<Batch<C>> {
        let batch = self.batch(step)?;
        if parts == 1 {
            return Ok(batch);
        }
        if batch.cond.is_some() {
            return Err(invalid(
                "grad_accum_steps",
                "this data source cannot split a conditioned batch into parts; implement BatchSource::batch_part",
            ));
        }
        let b = batch.x0.dim(0)?;
        let (start, len) = part_range(b, part, parts)?;
        let weight = match &batch.weight {
            Some(w) if w.dim(0)? == b && b > 1 => Some(w.narrow(0, start, len)?),
            other => other.clone(),
        };
        Ok(Batch {
            x0: batch.x0.narrow(0, start, len)?,
            cond: None,
            weight,
        })
    }
}

/// The examples `start..start + len` of part `part` of `parts` of a batch of `b`: contiguous
/// parts whose sizes differ by at most one (the first `b % parts` are one longer).
pub fn part_range(b: usize, part: usize, parts: usize) -> Result<(usize, usize)> {
    if parts == 0 || part >= parts || b < parts {
        return Err(invalid(
            "grad_accum_steps",
            format!(
                "part {part} of {parts} of a batch of {b}: every part needs at least one example"
            ),
        ));
    }
    let (q, r) = (b / parts, b % parts);
    Ok((part * q + part.min(r), q + usize::from(part < r)))
}

impl<C, F: FnMut(u64) -> Result<Batch<C>>> BatchSource<C> for F {
    fn batch(&mut self, step: u64) -> Result<Batch<C>> {
        self(step)
    }
}
