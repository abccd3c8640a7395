//! Nearest-neighbour upsampling by an integer factor, with a block-sum backward.

use candle_core::{CpuStorage, CustomOp1, Layout, Shape, Tensor};
use rayon::prelude::*;

use super::{min_len, on_cpu_f32, slice_f32, zeros};
use crate::error::Result;

#[derive(Debug, Clone, Copy)]
struct UpsampleNearest {
    factor: usize,
}

impl CustomOp1 for UpsampleNearest {
    fn name(&self) -> &'static str {
        "veila-upsample-nearest"
    }

    fn cpu_fwd(
        &self,
        storage: &CpuStorage,
        layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let x = slice_f32(storage, layout, "upsample input")?;
        let (b, c, h, w) = layout.shape().dims4()?;
        let f = self.factor;
        let (ho, wo) = (h * f, w * f);
        let mut dst = zeros(b * c * ho * wo);
        if h * w > 0 {
            dst.par_chunks_mut(ho * wo)
                .zip(x.par_chunks(h * w))
                .with_min_len(min_len(ho * wo))
                .for_each(|(out, plane)| {
                    for y in 0..h {
                        let src = &plane[y * w..(y + 1) * w];
                        let row = &mut out[y * f * wo..(y * f + 1) * wo];
                        for (o, v) in row.chunks_exact_mut(f).zip(src) {
                            o.fill(*v);
                        }
                        for k in 1..f {
                            let (done, rest) = out.split_at_mut((y * f + k) * wo);
                            rest[..wo].copy_from_slice(&done[y * f * wo..(y * f + 1) * wo]);
                        }
                    }
                });
        }
        Ok((CpuStorage::F32(dst), Shape::from((b, c, ho, wo))))
    }

    fn bwd(
        &self,
        _arg: &Tensor,
        _res: &Tensor,
        grad_res: &Tensor,
    ) -> candle_core::Result<Option<Tensor>> {
        Ok(Some(grad_res.contiguous()?.apply_op1_no_bwd(
            &DownsampleSum {
                factor: self.factor,
            },
        )?))
    }
}

/// Sum over `factor x factor` blocks (the backward pass of `UpsampleNearest`).
#[derive(Debug, Clone, Copy)]
struct DownsampleSum {
    factor: usize,
}

impl CustomOp1 for DownsampleSum {
    fn name(&self) -> &'static str {
        "veila-block-sum"
    }

    fn cpu_fwd(
        &self,
        storage: &CpuStorage,
        layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let g = slice_f32(storage, layout, "block-sum input")?;
        let (b, c, ho, wo) = layout.shape().dims4()?;
        let f = self.factor;
        if !ho.is_multiple_of(f) || !wo.is_multiple_of(f) {
            candle_core::bail!("block sum: {ho}x{wo} is not divisible by {f}")
        }
        let (h, w) = (ho / f, wo / f);
        let mut dst = zeros(b * c * h * w);
        if h * w > 0 {
            dst.par_chunks_mut(h * w)
                .zip(g.par_chunks(ho * wo))
                .with_min_len(min_len(ho * wo))
                .for_each(|(out, plane)| {
                    for yo in 0..ho {
                        let row = &plane[yo * wo..(yo + 1) * wo];
                        let o = &mut out[(yo / f) * w..(yo / f + 1) * w];
                        for (d, blk) in o.iter_mut().zip(row.chunks_exact(f)) {
                            *d += blk.iter().sum::<f32>();
                        }
                    }
                });
        }
        Ok((CpuStorage::F32(dst), Shape::from((b, c, h, w))))
    }
}

/// Nearest-neighbour upsampling of `[B, C, H, W]` by an integer `factor` (`>= 1`).
pub fn upsample_nearest(x: &Tensor, factor: usize) -> Result<Tensor> {
    let (b, c, h, w) = x.dims4()?;
    if factor <= 1 {
        return Ok(x.clone());
    }
    if on_cpu_f32(x) {
        return Ok(x.contiguous()?.apply_op1(UpsampleNearest { factor })?);
    }
    Ok(x.reshape((b, c, h, 1, w, 1))?
        .broadcast_as((b, c, h, factor, w, factor))?
        .reshape((b, c, h * factor, w * factor))?)
}
