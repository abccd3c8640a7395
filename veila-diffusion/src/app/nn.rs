//! The Veila denoiser from `veila-nn` as a [`Denoiser`].
//!
//! [`VeilaDenoiser`] wraps [`veila_nn::Denoiser`]; its conditioning is the
//! [`PreparedCondition`] that `veila_nn::Denoiser::prepare_condition` builds once per image (CACM
//! output and GCMA geometry), so the image encoders and the fusion run once per sample, not once per
//! step. Condition dropout and the unconditional branch of classifier-free guidance go through the
//! condition's per-sample `keep` factor (0 = drop), which the network defines to give exactly its
//! unconditional output.
//!
//! For residual ("corrective") diffusion the condition also carries the mean network's prediction
//! ([`NetCond::mean`]), which is concatenated to the noisy input as extra channels and is never
//! dropped: guidance and condition dropout act on the image only.
//!
//! The network multiplies its time input by `TimeEmbeddingConfig::input_scale` (1000 in the
//! presets), so pair the presets with [`TimeInput::Unit`](crate::TimeInput::Unit) (the default).

use std::marker::PhantomData;

use candle_core::{Device, Tensor};
use veila_nn::{GcmaGeometry, PreparedCondition};

use crate::denoiser::{Conditioning, Denoiser};

/// The Veila U-Net as a [`Denoiser`]; `'g` is the lifetime of the GCMA geometry that prepared
/// conditions borrow.
#[derive(Debug, Clone)]
pub struct VeilaDenoiser<'g> {
    net: veila_nn::Denoiser,
    _geometry: PhantomData<&'g GcmaGeometry>,
}

impl<'g> VeilaDenoiser<'g> {
    /// Wraps a network.
    pub fn new(net: veila_nn::Denoiser) -> Self {
        Self {
            net,
            _geometry: PhantomData,
        }
    }

    /// The wrapped network.
    pub fn net(&self) -> &veila_nn::Denoiser {
        &self.net
    }

    /// Unwraps the network.
    pub fn into_inner(self) -> veila_nn::Denoiser {
        self.net
    }
}

fn to_candle(e: veila_nn::Error) -> candle_core::Error {
    match e {
        veila_nn::Error::Candle(c) => c,
        other => candle_core::Error::Msg(other.to_string()),
    }
}

/// What [`VeilaDenoiser`] is conditioned on: the prepared image condition and, for residual
/// diffusion, the mean network's prediction `[B, C, H, W]` (concatenated to the input channels).
#[derive(Debug, Clone)]
pub struct NetCond<'g> {
    /// The image condition (`None`: the network's unconditional branch).
    pub image: Option<PreparedCondition<'g>>,
    /// The mean prediction of residual diffusion (`None` for direct diffusion).
    pub mean: Option<Tensor>,
}

impl<'g> From<PreparedCondition<'g>> for NetCond<'g> {
    fn from(image: PreparedCondition<'g>) -> Self {
        Self {
            image: Some(image),
            mean: None,
        }
    }
}

impl<'g> Denoiser for VeilaDenoiser<'g> {
    type Cond = NetCond<'g>;

    fn forward(
        &self,
        x_t: &Tensor,
        t: &Tensor,
        cond: Option<&Self::Cond>,
    ) -> candle_core::Result<Tensor> {
        let (image, mean) = match cond {
            Some(c) => (c.image.as_ref(), c.mean.as_ref()),
            None => (None, None),
        };
        match mean {
            Some(m) => {
                // the mean in the input's dtype (mixed precision runs x_t in bf16)
                let x = Tensor::cat(&[x_t, &m.to_dtype(x_t.dtype())?], 1)?;
                self.net.forward(&x, t, image).map_err(to_candle)
            }
            None => self.net.forward(x_t, t, image).map_err(to_candle),
        }
    }

    fn finish_backward(
        &self,
        grads: &mut candle_core::backprop::GradStore,
    ) -> candle_core::Result<()> {
        match self.net.recompute_tape() {
            Some(tape) => tape.merge_into(grads).map_err(to_candle),
            None => Ok(()),
        }
    }
}

impl Conditioning for NetCond<'_> {
    fn drop_samples(&self, drop: &[bool]) -> candle_core::Result<Self> {
        Ok(Self {
            image: self
                .image
                .as_ref()
                .map(|c| c.drop_samples(drop))
                .transpose()?,
            mean: self.mean.clone(),
        })
    }
}

impl Conditioning for PreparedCondition<'_> {
    fn drop_samples(&self, drop: &[bool]) -> candle_core::Result<Self> {
        let b = self.batch();
        if drop.len() != b {
            candle_core::bail!(
                "drop_samples: mask of length {} for a batch of {b}",
                drop.len()
            )
        }
        let device = match (&self.keep, self.fused.first()) {
            (Some(k), _) => k.device().clone(),
            (None, Some(f)) => f.device().clone(),
            (None, None) => Device::Cpu,
        };
        let mask: Vec<f32> = drop.iter().map(|&d| if d { 0.0 } else { 1.0 }).collect();
        let mask = Tensor::from_vec(mask, b, &device)?;
        let keep = match &self.keep {
            Some(k) => k.mul(&mask.to_dtype(k.dtype())?)?,
            None => mask,
        };
        Ok(self.clone().with_keep(Some(keep)))
    }
}

#[cfg(test)]
mod tests;

/// `veila-nn`'s AdamW over every parameter in one GPU launch
/// ([`veila_nn::fused::adamw_fused`], the per-tensor update's roundings) as the trainer's fused
/// update ([`crate::trainer::AdamW::set_fused`]): it runs where every parameter is an f32 tensor on
/// a GPU of a `cuda` build, and declines elsewhere.
pub fn fused_adamw() -> std::sync::Arc<crate::trainer::FusedAdamW> {
    std::sync::Arc::new(
        |slots: &[crate::trainer::AdamSlot<'_>],
         params: &candle_nn::ParamsAdamW,
         step_t: usize,
         grad_scale: f64|
         -> candle_core::Result<bool> {
            let scalars = veila_nn::fused::AdamScalars::new(params, step_t, grad_scale);
            veila_nn::fused::adamw_fused(slots, &scalars)
                .map_err(|e| candle_core::Error::Msg(e.to_string()))
        },
    )
}

/// The trainer's checkpoint reader ([`crate::trainer::TensorFileReader`]) with the checks a model
/// bundle's weights get, by `veila-nn`'s one weights reader: a regular file under its size cap
/// (checked before reading), its tensors exactly `expected` by name and shape, of a float dtype,
/// finite and within [`veila_nn::weights::MAX_ABS_WEIGHT`], before any tensor is made; then
/// converted to `dtype` on `device`.
pub fn read_checkpoint_tensors(
    path: &std::path::Path,
    expected: &std::collections::BTreeMap<String, Vec<usize>>,
    dtype: candle_core::DType,
    device: &Device,
) -> crate::Result<std::collections::HashMap<String, Tensor>> {
    let bad = |reason: String| crate::Error::Checkpoint {
        reason,
        path: path.to_path_buf(),
    };
    let bytes = veila_nn::checkpoint::read_weights_file(path).map_err(|e| match e {
        veila_nn::Error::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            bad("file missing".into())
        }
        e => e.into(),
    })?;
    veila_nn::checkpoint::read_checked_float_bytes(&bytes, path, expected, dtype, device).map_err(
        |e| match e {
            veila_nn::Error::CheckpointMismatch { report, .. } => bad(mismatch_reason(&report)),
            veila_nn::Error::SafeTensors { message, .. } => {
                bad(format!("reading safetensors: {message}"))
            }
            e => e.into(),
        },
    )
}

/// A tensor report in the words of a training checkpoint (every name, the file's shape first).
fn mismatch_reason(r: &veila_nn::TensorReport) -> String {
    let mis_shaped: Vec<String> = r
        .mis_shaped
        .iter()
        .map(|(n, model, file)| format!("{n} {file:?} (model {model:?})"))
        .collect();
    format!(
        "tensors do not match the model: missing [{}], unexpected [{}], mis-shaped [{}]",
        r.missing.join(", "),
        r.unexpected.join(", "),
        mis_shaped.join(", ")
    )
}
