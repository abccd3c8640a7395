//! AdamW over many parameter tensors in one GPU launch (candle-nn's `AdamW` runs about 14 tensor
//! ops per parameter tensor: some 2,600 launches a step for the paper network).
//!
//! The update is candle-nn's, operation for operation and rounding for rounding (every factor
//! rounded from f64 to f32 as candle's `tensor * f64` rounds it, no fused multiply-add), so a
//! fused step is bit-identical to `candle_nn::AdamW` on the CPU (tested on the host emulation of
//! the kernel, and on a GPU by `cargo xtask check-cuda`).

use candle_core::{Tensor, Var};
use candle_nn::ParamsAdamW;

use crate::error::Result;

/// The scalars of one AdamW step, as the kernel takes them (`AdamScalars` in `kernels.cu`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamScalars {
    /// Factor of every gradient (gradient clipping); exactly 1 for none.
    pub grad_scale: f32,
    pub beta1: f32,
    pub one_minus_beta1: f32,
    pub beta2: f32,
    pub one_minus_beta2: f32,
    /// `1 / (1 - beta1^t)`.
    pub scale_m: f32,
    /// `1 / (1 - beta2^t)`.
    pub scale_v: f32,
    /// `1 - lr weight_decay`.
    pub decay: f32,
    pub lr: f32,
    pub eps: f32,
}

impl AdamScalars {
    /// The scalars of step `step_t` (from 1) with hyper-parameters `p`, each computed in f64 as
    /// candle-nn computes it and rounded to f32.
    pub fn new(p: &ParamsAdamW, step_t: usize, grad_scale: f64) -> Self {
        let t = i32::try_from(step_t).unwrap_or(i32::MAX);
        Self {
            grad_scale: grad_scale as f32,
            beta1: p.beta1 as f32,
            one_minus_beta1: (1.0 - p.beta1) as f32,
            beta2: p.beta2 as f32,
            one_minus_beta2: (1.0 - p.beta2) as f32,
            scale_m: (1.0 / (1.0 - p.beta1.powi(t))) as f32,
            scale_v: (1.0 / (1.0 - p.beta2.powi(t))) as f32,
            decay: (1.0 - p.lr * p.weight_decay) as f32,
            lr: p.lr as f32,
            eps: p.eps as f32,
        }
    }

    /// The ten values in the struct's order (for the host emulation's input file).
    pub fn to_array(&self) -> [f32; 10] {
        [
            self.grad_scale,
            self.beta1,
            self.one_minus_beta1,
            self.beta2,
            self.one_minus_beta2,
            self.scale_m,
            self.scale_v,
            self.decay,
            self.lr,
            self.eps,
        ]
    }
}

/// One parameter tensor of a fused AdamW step: the parameter, its gradient, its two moments.
pub type AdamSlot<'a> = (&'a Var, &'a Tensor, &'a Var, &'a Var);

/// Whether [`adamw_fused`] runs for parameters like `t`: f32 on a CUDA device, built with the
/// `cuda` feature, kernels on (`VEILA_NN_REFERENCE_OPS=1` turns it off).
pub fn adamw_fused_supported(t: &Tensor) -> bool {
    #[cfg(feature = "cuda")]
    {
        t.device().is_cuda() && t.dtype() == candle_core::DType::F32 && super::kernels_enabled()
    }
    #[cfg(not(feature = "cuda"))]
    {
        let _ = t;
        false
    }
}

/// One AdamW step of every slot, in place, in one launch: `m = b1 m + (1 - b1) g`,
/// `v = b2 v + (1 - b2) g^2`, `p = p (1 - lr wd) - lr m̂ / (sqrt(v̂) + eps)` with `g` the gradient
/// times `grad_scale`. `Ok(false)`, changing nothing, where there are no slots or a tensor is not
/// one [`adamw_fused_supported`] takes (the caller then runs the per-tensor update); an error where
/// a slot's four tensors differ in size.
pub fn adamw_fused(slots: &[AdamSlot<'_>], scalars: &AdamScalars) -> Result<bool> {
    let quads: Vec<[&Tensor; 4]> = slots
        .iter()
        .map(|(p, g, m, v)| [p.as_tensor(), *g, m.as_tensor(), v.as_tensor()])
        .collect();
    if quads.is_empty() || !quads.iter().flatten().all(|t| adamw_fused_supported(t)) {
        return Ok(false);
    }
    for (k, q) in quads.iter().enumerate() {
        let n = q[0].elem_count();
        if q.iter().any(|t| t.elem_count() != n) {
            return Err(crate::Error::Config(format!(
                "fused AdamW: slot {k}'s parameter, gradient and moments differ in size"
            )));
        }
    }
    #[cfg(feature = "cuda")]
    {
        super::cuda::adamw(&quads, scalars.to_array())?;
        Ok(true)
    }
    #[cfg(not(feature = "cuda"))]
    {
        // unreachable: nothing is supported without the feature
        let _ = scalars;
        Ok(false)
    }
}
