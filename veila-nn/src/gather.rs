//! GCMA's bilinear gather as one op: `out[b, n, :] = sum_c w_c[n] · src[b, idx_c[n], :]` over the
//! four corners `c` of each epipolar sample, whole channel rows at a time.
//!
//! Built from candle ops the gather is four `index_select`s, four broadcast products and three
//! sums, each a `[B, N, C]` tensor that the graph keeps until the backward pass: at the paper's
//! level 0 about ten times the size of its output. Here the forward pass writes the output
//! directly and keeps nothing but the corner table (shared with the geometry), and the backward
//! pass scatters the gradient back into the source rows.
//!
//! On the CPU in f32 it runs as a kernel over the rayon pool. Every other device and dtype runs
//! the candle composition ([`bilinear_gather_reference`]) without a graph, as one node whose
//! backward pass is the scatter in candle ops ([`crate::recompute::with_backward`]), so that
//! neither its intermediates nor those of their gradients are kept there either.

use std::sync::Arc;

use candle_core::{CpuStorage, CustomOp1, DType, Layout, Shape, Tensor};
use rayon::prelude::*;

use crate::error::{Error, Result};

/// The four bilinear corners of `n` samples: row indices into the source and their weights.
#[derive(Debug, Clone)]
pub struct GatherTaps {
    idx: [Vec<u32>; 4],
    w: [Vec<f32>; 4],
    idx_t: [Tensor; 4],
    w_t: [Tensor; 4],
    /// The largest corner index (checked against the source's rows on every call).
    max_index: Option<u32>,
}

impl GatherTaps {
    /// Corners `idx[c][n]` (row indices) with weights `w[c][n]`; the tensors live on `device`.
    pub fn new(idx: [Vec<u32>; 4], w: [Vec<f32>; 4], device: &candle_core::Device) -> Result<Self> {
        let n = idx[0].len();
        if idx.iter().any(|v| v.len() != n) || w.iter().any(|v| v.len() != n) {
            return Err(Error::Config(
                "bilinear gather: the four corners differ in length".into(),
            ));
        }
        let to_t = |i: usize| -> Result<(Tensor, Tensor)> {
            Ok((
                Tensor::from_vec(idx[i].clone(), n, device)?,
                Tensor::from_vec(w[i].clone(), n, device)?,
            ))
        };
        let (a, b, c, d) = (to_t(0)?, to_t(1)?, to_t(2)?, to_t(3)?);
        let max_index = idx.iter().flat_map(|v| v.iter().copied()).max();
        Ok(Self {
            max_index,
            idx_t: [a.0, b.0, c.0, d.0],
            w_t: [a.1, b.1, c.1, d.1],
            idx,
            w,
        })
    }

    /// Number of samples `n`.
    pub fn len(&self) -> usize {
        self.idx[0].len()
    }

    /// Whether there are no samples.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The corner indices as `[n]` u32 tensors.
    pub fn index_tensors(&self) -> &[Tensor; 4] {
        &self.idx_t
    }

    /// The corner weights as `[n]` f32 tensors.
    pub fn weight_tensors(&self) -> &[Tensor; 4] {
        &self.w_t
    }

    fn max_index(&self) -> Option<u32> {
        self.max_index
    }
}

struct Gather {
    taps: Arc<GatherTaps>,
}

/// `(B, M, C)` of a contiguous 3-d f32 CPU source, checked against the taps.
fn source<'a>(
    taps: &GatherTaps,
    s: &'a CpuStorage,
    l: &Layout,
) -> candle_core::Result<(&'a [f32], usize, usize, usize)> {
    let CpuStorage::F32(v) = s else {
        candle_core::bail!("bilinear gather: expected an f32 source")
    };
    let Some((a, b)) = l.contiguous_offsets() else {
        candle_core::bail!("bilinear gather: expected a contiguous source")
    };
    let (bs, m, c) = l.shape().dims3()?;
    if taps.max_index().is_some_and(|i| i as usize >= m) {
        candle_core::bail!("bilinear gather: a corner index is past the source's {m} rows")
    }
    Ok((&v[a..b], bs, m, c))
}

impl CustomOp1 for Gather {
    fn name(&self) -> &'static str {
        "veila-bilinear-gather"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> candle_core::Result<(CpuStorage, Shape)> {
        let t = &*self.taps;
        let (src, bs, m, c) = source(t, s, l)?;
        let n = t.len();
        let mut out = vec![0f32; bs * n * c];
        if c > 0 {
            out.par_chunks_mut(c)
                .with_min_len(64)
                .enumerate()
                .for_each(|(row, dst)| {
                    let (b, k) = (row / n, row % n);
                    for corner in 0..4 {
                        let w = t.w[corner][k];
                        if w != 0.0 {
                            let at = (b * m + t.idx[corner][k] as usize) * c;
                            for (d, s) in dst.iter_mut().zip(&src[at..at + c]) {
                                *d += w * s;
                            }
                        }
                    }
                });
        }
        Ok((CpuStorage::F32(out), Shape::from((bs, n, c))))
    }

    fn bwd(
        &self,
        arg: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<Option<Tensor>> {
        let t = &*self.taps;
        let (bs, m, c) = arg.dims3()?;
        let n = t.len();
        let g = grad
            .to_dtype(DType::F32)?
            .contiguous()?
            .flatten_all()?
            .to_vec1::<f32>()?;
        // each task owns a block of channels of every source row: no two tasks write one value
        let block = c
            .div_ceil(rayon::current_num_threads().max(1))
            .clamp(1, c.max(1));
        let blocks: Vec<(usize, Vec<f32>)> = (0..c.div_ceil(block.max(1)))
            .into_par_iter()
            .map(|j| {
                let (lo, hi) = (j * block, ((j + 1) * block).min(c));
                let w = hi - lo;
                let mut acc = vec![0f32; bs * m * w];
                for b in 0..bs {
                    for k in 0..n {
                        let go = &g[(b * n + k) * c + lo..(b * n + k) * c + hi];
                        for corner in 0..4 {
                            let wt = t.w[corner][k];
                            if wt != 0.0 {
                                let at = (b * m + t.idx[corner][k] as usize) * w;
                                for (a, x) in acc[at..at + w].iter_mut().zip(go) {
                                    *a += wt * x;
                                }
                            }
                        }
                    }
                }
                (lo, acc)
            })
            .collect();
        let mut out = vec![0f32; bs * m * c];
        for (lo, acc) in blocks {
            let w = acc.len() / (bs * m).max(1);
            for (row, vals) in acc.chunks(w.max(1)).enumerate() {
                out[row * c + lo..row * c + lo + vals.len()].copy_from_slice(vals);
            }
        }
        Ok(Some(
            Tensor::from_vec(out, (bs, m, c), arg.device())?.to_dtype(arg.dtype())?,
        ))
    }
}

/// The candle composition of [`bilinear_gather`]: the test oracle, and the forward pass of every
/// device but the CPU in f32 (whose backward pass is a scatter, `bilinear_scatter`).
pub fn bilinear_gather_reference(src: &Tensor, taps: &GatherTaps) -> Result<Tensor> {
    let n = taps.len();
    let mut acc: Option<Tensor> = None;
    for corner in 0..4 {
        let sel = src.index_select(&taps.idx_t[corner], 1)?;
        let wt = taps.w_t[corner].to_dtype(src.dtype())?.reshape((1, n, 1))?;
        let term = sel.broadcast_mul(&wt)?;
        acc = Some(match acc {
            None => term,
            Some(a) => (a + term)?,
        });
    }
    acc.ok_or_else(|| Error::Config("internal: no bilinear taps".into()))
}

/// `[B, M, C]` source rows to `[B, n, C]` samples, each the weighted sum of its four corner rows.
pub fn bilinear_gather(src: &Tensor, taps: &Arc<GatherTaps>) -> Result<Tensor> {
    let (_, m, _) = src.dims3()?;
    if taps.max_index().is_some_and(|i| i as usize >= m) {
        return Err(Error::Config(format!(
            "bilinear gather: a corner index is past the source's {m} rows"
        )));
    }
    if crate::fused::takes_kernels(src) {
        return Ok(src.contiguous()?.apply_op1(Gather { taps: taps.clone() })?);
    }
    let t = taps.clone();
    crate::recompute::with_backward(
        &[src],
        |s| bilinear_gather_reference(s[0], taps),
        Arc::new(move |s: &[&Tensor], g: &Tensor| Ok(vec![Some(bilinear_scatter(s[0], &t, g)?)])),
    )
}

/// The gradient of [`bilinear_gather`] with respect to its source `src: [B, M, C]` for the
/// output's gradient `grad: [B, n, C]`: each sample's gradient, times each corner's weight, added
/// into that corner's row (`index_add`). What it keeps at once is the gradient, one weighted copy
/// of it and the source-sized sum; the composition's own backward pass kept its four selections,
/// products and partial sums, about ten times the output (at the paper's level 0, the largest
/// part of a training step's peak on the path GPUs run).
fn bilinear_scatter(src: &Tensor, taps: &GatherTaps, grad: &Tensor) -> Result<Tensor> {
    let n = taps.len();
    let mut acc = src.zeros_like()?;
    for corner in 0..4 {
        let wt = taps.w_t[corner]
            .to_dtype(grad.dtype())?
            .reshape((1, n, 1))?;
        acc = acc.index_add(&taps.idx_t[corner], &grad.broadcast_mul(&wt)?, 1)?;
    }
    Ok(acc)
}
