//! Panoramic Feature Coherence: global multi-head self-attention over every position of the deepest
//! U-Net level, with GroupNorm before it and a residual around it (equation 11).

use candle_core::{D, DType, Tensor};
use candle_nn::VarBuilder;

use crate::config::PfcConfig;
use crate::error::{Error, Result};
use crate::ops::{Conv1x1, group_norm, groups_for};

/// `R_bar = SelfAttention(GroupNorm(R)) + R` over all `H x W` positions of a `[B, C, H, W]` map.
///
/// Weights: `norm.{weight,bias}`, `qkv.{weight,bias}` (`[3C, C, 1, 1]`, queries then keys then values,
/// head-major inside each), `proj.{weight,bias}` (`[C, C, 1, 1]`). There is no positional encoding, so
/// the block is equivariant to any permutation of positions (in particular azimuth rolls).
#[derive(Debug, Clone)]
pub struct Pfc {
    norm: crate::ops::GroupNorm,
    qkv: Conv1x1,
    proj: Conv1x1,
    num_heads: usize,
    channels: usize,
    span: tracing::Span,
}

impl Pfc {
    /// Builds the block for `channels` channels.
    pub fn new(
        cfg: &PfcConfig,
        channels: usize,
        max_groups: usize,
        vb: VarBuilder<'_>,
    ) -> Result<Self> {
        if cfg.num_heads == 0 || !channels.is_multiple_of(cfg.num_heads) {
            return Err(Error::Config(format!(
                "pfc: {} heads do not divide {channels} channels",
                cfg.num_heads
            )));
        }
        Ok(Self {
            norm: group_norm(groups_for(channels, max_groups), channels, vb.pp("norm"))?,
            qkv: Conv1x1::new(channels, 3 * channels, true, vb.pp("qkv"))?,
            proj: Conv1x1::new(channels, channels, true, vb.pp("proj"))?,
            num_heads: cfg.num_heads,
            channels,
            span: tracing::span!(tracing::Level::TRACE, "pfc"),
        })
    }

    /// `[B, C, H, W] -> [B, C, H, W]`.
    /// The trainable tensors (for activation checkpointing).
    pub(crate) fn params(&self) -> Vec<Tensor> {
        let mut out: Vec<Tensor> = self.norm.params().into_iter().cloned().collect();
        crate::recompute::push_weights(&mut out, self.qkv.weights());
        crate::recompute::push_weights(&mut out, self.proj.weights());
        out
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let _enter = self.span.enter();
        let (b, c, h, w) = x.dims4()?;
        let n = h * w;
        let heads = self.num_heads;
        let dh = self.channels / heads;
        let qkv = self
            .qkv
            .forward(&self.norm.forward(x)?)?
            .reshape((b, 3, heads, dh, n))?;
        let q = qkv.narrow(1, 0, 1)?.reshape((b * heads, dh, n))?;
        let k = qkv.narrow(1, 1, 1)?.reshape((b * heads, dh, n))?;
        let v = qkv.narrow(1, 2, 1)?.reshape((b * heads, dh, n))?;
        // logits [B*h, N_q, N_k]
        let logits =
            (q.transpose(1, 2)?.contiguous()?.matmul(&k.contiguous()?)? / (dh as f64).sqrt())?;
        // the softmax of half-precision logits in f32
        let attn = if crate::fused::is_half(logits.dtype()) {
            candle_nn::ops::softmax(&logits.to_dtype(DType::F32)?, D::Minus1)?
                .to_dtype(logits.dtype())?
        } else {
            candle_nn::ops::softmax(&logits, D::Minus1)?
        };
        // out [B*h, dh, N_q] = v [dh, N_k] x attn^T [N_k, N_q]
        let out = v
            .contiguous()?
            .matmul(&attn.transpose(1, 2)?.contiguous()?)?;
        let out = self.proj.forward(&out.reshape((b, c, h, w))?)?;
        Ok((x + out)?)
    }
}
