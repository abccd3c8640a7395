//! The scaled residual sum `(a + b) * s`.

use candle_core::{CpuStorage, CustomOp1, CustomOp2, Layout, Shape, Tensor};
use rayon::prelude::*;

use super::{GRAIN, on_cpu_f32, slice_f32};
use crate::error::{Result, shape_err};

#[derive(Debug, Clone, Copy)]
struct AddScaled {
    scale: f32,
}

impl CustomOp2 for AddScaled {
    fn name(&self) -> &'static str {
        "veila-add-scaled"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let a = slice_f32(s1, l1, "add_scaled lhs")?;
        let b = slice_f32(s2, l2, "add_scaled rhs")?;
        if l1.shape() != l2.shape() {
            candle_core::bail!(
                "add_scaled: shapes {:?} and {:?} differ",
                l1.shape(),
                l2.shape()
            )
        }
        let s = self.scale;
        // collected, not written into a zero-filled buffer: every value is new
        let dst: Vec<f32> = a
            .par_iter()
            .zip(b)
            .with_min_len(GRAIN)
            .map(|(a, b)| (a + b) * s)
            .collect();
        Ok((CpuStorage::F32(dst), l1.shape().clone()))
    }

    fn bwd(
        &self,
        _a: &Tensor,
        _b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let g = grad
            .contiguous()?
            .apply_op1_no_bwd(&Scale { scale: self.scale })?;
        Ok((Some(g.clone()), Some(g)))
    }
}

#[derive(Debug, Clone, Copy)]
struct Scale {
    scale: f32,
}

impl CustomOp1 for Scale {
    fn name(&self) -> &'static str {
        "veila-scale"
    }

    fn cpu_fwd(
        &self,
        storage: &CpuStorage,
        layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let a = slice_f32(storage, layout, "scale input")?;
        Ok((
            CpuStorage::F32(scaled(a, self.scale)),
            layout.shape().clone(),
        ))
    }
}

/// `(a + b) * scale` (same shapes): the scaled residual connection.
pub fn add_scaled(a: &Tensor, b: &Tensor, scale: f64) -> Result<Tensor> {
    if a.dims() != b.dims() {
        return Err(shape_err(
            "add_scaled rhs",
            format!("{:?}", a.dims()),
            b.dims(),
        ));
    }
    if on_cpu_f32(a) && on_cpu_f32(b) {
        return Ok(a.contiguous()?.apply_op2(
            &b.contiguous()?,
            AddScaled {
                scale: scale as f32,
            },
        )?);
    }
    #[cfg(feature = "cuda")]
    if super::cuda::takes_kernels(a) && a.dtype() == b.dtype() && a.device().same_device(b.device())
    {
        return Ok(a.contiguous()?.apply_op2(
            &b.contiguous()?,
            super::cuda::AddScaledCuda {
                scale: scale as f32,
            },
        )?);
    }
    Ok(((a + b)? * scale)?)
}

/// `a * s`, collected over the rayon pool.
pub(super) fn scaled(a: &[f32], s: f32) -> Vec<f32> {
    a.par_iter().with_min_len(GRAIN).map(|v| v * s).collect()
}
