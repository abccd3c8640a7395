//! The whole convolution as one op: the columns of one sample at a time, a tile of output rows at a
//! time, and one `gemm` product per tile, forward and backward; samples in parallel when there are
//! at least as many as threads, per-thread scratch of one tile.

use candle_core::{CpuStorage, CustomOp2, CustomOp3, Layout, Shape, Tensor};
use rayon::prelude::*;

use super::im2col::{Im2Col, Im2ColSpec, im2col};
use super::matmul::{matmul_abt, matmul_into};
use super::{on_cpu_f32, slice_f32, with_f32, zeros};
use crate::error::{Result, shape_err};

thread_local! {
    /// This thread's scratch for the fused convolution (one tile of a sample's columns and their
    /// gradient, at most 2 x [`TILE_FLOATS`](super::im2col::TILE_FLOATS)), kept between calls at the size of the largest seen: every element is written before
    /// it is read, so it is never zero-filled again (that fill cost about 9 % of a training step).
    static CONV_SCRATCH: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Runs `f` on two scratch slices of `len` elements each: this thread's (see `CONV_SCRATCH`), or
/// fresh ones if they are in use further up this thread's stack.
fn with_scratch<R>(len: usize, f: impl FnOnce(&mut [f32], &mut [f32]) -> R) -> R {
    CONV_SCRATCH.with(|cell| match cell.try_borrow_mut() {
        Ok(mut buf) => {
            if buf.len() < 2 * len {
                buf.resize(2 * len, 0.0);
            }
            let (a, b) = buf[..2 * len].split_at_mut(len);
            f(a, b)
        }
        Err(_) => {
            let mut buf = vec![0f32; 2 * len];
            let (a, b) = buf.split_at_mut(len);
            f(a, b)
        }
    })
}

/// A convolution as one op: for each sample, the im2col of [`Im2Col`] into one reused buffer and
/// one matrix product (`gemm`), forward and backward (weight gradient accumulated over the batch
/// in place). Compared with [`im2col`] followed by candle's `matmul`, the `C kh kw`-row column
/// matrix of the whole batch never exists, nor its gradient, which candle's backward would
/// zero-fill and add to: the backward pass rebuilds the columns one sample at a time.
#[derive(Debug, Clone, Copy)]
pub(super) struct Conv2dGemm {
    pub(super) cols: Im2Col,
    /// Forces one of the two paths (tests); `None` chooses by the batch and the thread count.
    pub(super) parallel: Option<bool>,
    /// Forces the output rows per column tile (tests); `None`: as many as fit
    /// [`TILE_FLOATS`](super::im2col::TILE_FLOATS).
    pub(super) tile_rows: Option<usize>,
}

/// Shapes of a [`Conv2dGemm`] call.
#[derive(Debug, Clone, Copy)]
pub(super) struct ConvDims {
    b: usize,
    c: usize,
    h: usize,
    w: usize,
    out_c: usize,
    /// `C kh kw`: the columns' rows.
    k: usize,
    /// `H_o W_o`: output pixels per channel.
    n: usize,
    pub(super) ho: usize,
    pub(super) wo: usize,
}

impl Conv2dGemm {
    pub(super) fn dims(&self, x: &[usize], weight: &[usize]) -> candle_core::Result<ConvDims> {
        let spec = self.cols.spec;
        let (&[b, c, h, w], &[out_c, wc, kh, kw]) = (x, weight) else {
            candle_core::bail!("convolution: input {x:?} or weight {weight:?} is not 4-d")
        };
        if wc != c || (kh, kw) != spec.kernel {
            candle_core::bail!(
                "convolution: weight {weight:?} does not fit input {x:?} and {spec:?}"
            )
        }
        let Some((ho, wo)) = spec.out_size(h, w) else {
            candle_core::bail!("convolution: {spec:?} does not fit a {h}x{w} input")
        };
        Ok(ConvDims {
            b,
            c,
            h,
            w,
            out_c,
            k: c * kh * kw,
            n: ho * wo,
            ho,
            wo,
        })
    }

    /// Whether the samples run in parallel, each with single-threaded products (when there are
    /// at least as many samples as threads), rather than one after another with each product
    /// spread over the threads: measured on 2 cores at batch 8, the thread hand-offs inside every
    /// product cost more than they gain (`cargo xtask bench-model`, BENCHMARKS.md).
    fn samples_in_parallel(&self, d: &ConvDims) -> bool {
        self.parallel.unwrap_or_else(|| {
            let threads = rayon::current_num_threads();
            threads > 1 && d.b >= threads
        })
    }

    /// Output rows per column tile, and the scratch floats of one column buffer.
    fn tiling(&self, d: &ConvDims) -> (usize, usize) {
        let rows = self.tile_rows.map_or_else(
            || self.cols.tile_rows(d.k, d.ho, d.wo),
            |r| r.clamp(1, d.ho.max(1)),
        );
        (rows, self.cols.scratch_len(d.k, rows * d.wo))
    }

    /// The output-row ranges of the column tiles.
    fn tiles(&self, d: &ConvDims) -> impl Iterator<Item = std::ops::Range<usize>> + use<> {
        let (rows, ho) = (self.tiling(d).0, d.ho);
        (0..ho).step_by(rows).map(move |oy| oy..(oy + rows).min(ho))
    }

    /// One sample's output `[out, H_o W_o]` (`col`: a scratch buffer of one tile).
    fn forward_sample(
        &self,
        d: &ConvDims,
        (x, weight, bias): (&[f32], &[f32], Option<&[f32]>),
        dst: &mut [f32],
        col: &mut [f32],
        threaded: bool,
    ) -> candle_core::Result<()> {
        let ConvDims {
            h,
            w,
            out_c,
            k,
            n,
            wo,
            ..
        } = *d;
        if let Some(bias) = bias {
            for (row, &v) in dst.chunks_mut(n).zip(bias) {
                row.fill(v);
            }
        }
        // computed transposed, outᵀ (N x O) = colᵀ (N x K) · Wᵀ (K x O): the big operand is then
        // column-major, which `gemm` reads in place instead of packing a copy of it
        if self.cols.is_identity() {
            return matmul_into(
                (dst, 1, n),
                (n, out_c, k),
                bias.is_some(),
                (x, 1, n),
                (weight, 1, k),
                threaded,
            );
        }
        for oys in self.tiles(d) {
            let (p0, tn) = (oys.start * wo, oys.len() * wo);
            let col = &mut col[..k * tn];
            self.cols.fill_sample(col, x, (h, w), oys, threaded);
            matmul_into(
                (&mut dst[p0..], 1, n),
                (tn, out_c, k),
                bias.is_some(),
                (col, 1, tn),
                (weight, 1, k),
                threaded,
            )?;
        }
        Ok(())
    }

    fn forward(
        &self,
        d: ConvDims,
        x: &[f32],
        weight: &[f32],
        bias: Option<&[f32]>,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let out = self.forward_vec(d, x, weight, bias)?;
        Ok((
            CpuStorage::F32(out),
            Shape::from((d.b, d.out_c, d.ho, d.wo)),
        ))
    }

    /// The output `[B, out, H_o, W_o]` as a plain vector.
    pub(super) fn forward_vec(
        &self,
        d: ConvDims,
        x: &[f32],
        weight: &[f32],
        bias: Option<&[f32]>,
    ) -> candle_core::Result<Vec<f32>> {
        let ConvDims {
            b,
            c,
            h,
            w,
            out_c,
            n,
            ..
        } = d;
        let mut out = zeros(b * out_c * n);
        let plane = c * h * w;
        if out.is_empty() || plane == 0 {
            return Ok(out);
        }
        let scratch = self.tiling(&d).1;
        if self.samples_in_parallel(&d) {
            out.par_chunks_mut(out_c * n)
                .zip(x.par_chunks(plane))
                .try_for_each(|(dst, xb)| {
                    with_scratch(scratch, |col, _| {
                        self.forward_sample(&d, (xb, weight, bias), dst, col, false)
                    })
                })?;
        } else {
            with_scratch(scratch, |col, _| {
                for (dst, xb) in out.chunks_mut(out_c * n).zip(x.chunks(plane)) {
                    self.forward_sample(&d, (xb, weight, bias), dst, col, true)?;
                }
                Ok::<_, candle_core::Error>(())
            })?;
        }
        Ok(out)
    }

    /// One sample's share of the gradients: its input gradient `dx` (zeroed), its own weight
    /// gradient `dw` and bias gradient `db` (summed over the batch afterwards, in batch order).
    #[allow(clippy::too_many_arguments)]
    fn backward_sample(
        &self,
        d: &ConvDims,
        (x, weight, g): (&[f32], &[f32], &[f32]),
        (dx, dw, db): (&mut [f32], &mut [f32], &mut [f32]),
        col: &mut [f32],
        dcol: &mut [f32],
        threaded: bool,
    ) -> candle_core::Result<()> {
        let ConvDims {
            h,
            w,
            out_c,
            k,
            n,
            wo,
            ..
        } = *d;
        for (acc, row) in db.iter_mut().zip(g.chunks(n)) {
            *acc = row.iter().sum::<f32>();
        }
        // dcolᵀ (N x K) = gᵀ (N x O) · W (O x K), transposed as in the forward
        let dcol_into = |dst: &mut [f32], g: &[f32], tn: usize| {
            matmul_into(
                (dst, 1, tn),
                (tn, k, out_c),
                false,
                (g, 1, n),
                (weight, k, 1),
                threaded,
            )
        };
        if self.cols.is_identity() {
            // dW (O x K) = g (O x N) · xᵀ: rows of g against rows of x, both in place; a 1x1
            // convolution's dcol is dx itself
            matmul_abt(dw, (g, n), (x, n), (out_c, k, n), false, threaded)?;
            return dcol_into(dx, g, n);
        }
        for (t, oys) in self.tiles(d).enumerate() {
            let (p0, tn) = (oys.start * wo, oys.len() * wo);
            let (col, dcol) = (&mut col[..k * tn], &mut dcol[..k * tn]);
            self.cols.fill_sample(col, x, (h, w), oys.clone(), threaded);
            // dW (O x K) += g_tile (O x tile) · col_tileᵀ, both read in place
            matmul_abt(
                dw,
                (&g[p0..], n),
                (col, tn),
                (out_c, k, tn),
                t > 0,
                threaded,
            )?;
            dcol_into(dcol, &g[p0..], tn)?;
            self.cols.scatter_sample(dcol, dx, (h, w), oys, threaded);
        }
        Ok(())
    }

    /// Gradients of input, weight and (when `with_bias`) bias. Each sample's weight and bias
    /// gradients are summed in batch order, so the result does not depend on the thread count.
    fn backward(
        &self,
        x: &Tensor,
        weight: &Tensor,
        grad: &Tensor,
        with_bias: bool,
    ) -> candle_core::Result<(Tensor, Tensor, Option<Tensor>)> {
        let d = self.dims(x.dims(), weight.dims())?;
        // the input and the weights are read in place (no copies: this runs once per convolution
        // in every training step)
        let (dx, dw, db) = with_f32(x, "convolution input", |xs| {
            with_f32(weight, "convolution weight", |ws| {
                with_f32(grad, "convolution gradient", |g| {
                    self.backward_slices(&d, xs, ws, g)
                })
            })
        })?;
        let dev = x.device();
        let dx = Tensor::from_vec(dx, (d.b, d.c, d.h, d.w), dev)?;
        let dw = Tensor::from_vec(dw, weight.dims(), dev)?;
        let db = if with_bias {
            Some(Tensor::from_vec(db, d.out_c, dev)?)
        } else {
            None
        };
        Ok((dx, dw, db))
    }

    /// [`Self::backward`] on slices: `(dx, dw, db)` for input `xs`, weights `ws` and output
    /// gradient `g` (`db` is the bias gradient whether or not there is a bias).
    pub(super) fn backward_slices(
        &self,
        d: &ConvDims,
        xs: &[f32],
        ws: &[f32],
        g: &[f32],
    ) -> candle_core::Result<(Vec<f32>, Vec<f32>, Vec<f32>)> {
        let ConvDims {
            b,
            c,
            h,
            w,
            out_c,
            k,
            n,
            ..
        } = *d;
        let plane = c * h * w;
        if g.len() != b * out_c * n || xs.len() != b * plane || ws.len() != out_c * k {
            candle_core::bail!(
                "convolution: gradient of {} values, input of {}, weights of {} for {d:?}",
                g.len(),
                xs.len(),
                ws.len()
            )
        }
        let mut dx = zeros(b * plane);
        let mut dw_parts = vec![0f32; b * out_c * k];
        let mut db_parts = vec![0f32; b * out_c];
        if !(dx.is_empty() || g.is_empty() || dw_parts.is_empty()) {
            let (dws, dbs) = (out_c * k, out_c);
            let scratch = self.tiling(d).1;
            if self.samples_in_parallel(d) {
                dx.par_chunks_mut(plane)
                    .zip(dw_parts.par_chunks_mut(dws))
                    .zip(db_parts.par_chunks_mut(dbs))
                    .zip(xs.par_chunks(plane).zip(g.par_chunks(out_c * n)))
                    .try_for_each(|(((dxb, dwb), dbb), (xb, gb))| {
                        with_scratch(scratch, |col, dcol| {
                            self.backward_sample(d, (xb, ws, gb), (dxb, dwb, dbb), col, dcol, false)
                        })
                    })?;
            } else {
                with_scratch(scratch, |col, dcol| {
                    for (((dxb, dwb), dbb), (xb, gb)) in dx
                        .chunks_mut(plane)
                        .zip(dw_parts.chunks_mut(dws))
                        .zip(db_parts.chunks_mut(dbs))
                        .zip(xs.chunks(plane).zip(g.chunks(out_c * n)))
                    {
                        self.backward_sample(d, (xb, ws, gb), (dxb, dwb, dbb), col, dcol, true)?;
                    }
                    Ok::<_, candle_core::Error>(())
                })?;
            }
        }
        let sum_parts = |parts: &[f32], len: usize| -> Vec<f32> {
            let mut acc = vec![0f32; len];
            for part in parts.chunks(len.max(1)) {
                for (a, v) in acc.iter_mut().zip(part) {
                    *a += v;
                }
            }
            acc
        };
        Ok((
            dx,
            sum_parts(&dw_parts, out_c * k),
            sum_parts(&db_parts, out_c),
        ))
    }
}

impl CustomOp2 for Conv2dGemm {
    fn name(&self) -> &'static str {
        "veila-conv2d"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let d = self.dims(l1.dims(), l2.dims())?;
        let x = slice_f32(s1, l1, "convolution input")?;
        let weight = slice_f32(s2, l2, "convolution weight")?;
        self.forward(d, x, weight, None)
    }

    fn bwd(
        &self,
        x: &Tensor,
        weight: &Tensor,
        _res: &Tensor,
        grad_res: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let (dx, dw, _) = self.backward(x, weight, grad_res, false)?;
        Ok((Some(dx), Some(dw)))
    }
}

impl CustomOp3 for Conv2dGemm {
    fn name(&self) -> &'static str {
        "veila-conv2d-bias"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let d = self.dims(l1.dims(), l2.dims())?;
        if l3.dims() != [d.out_c] {
            candle_core::bail!("convolution: bias {:?}, expected [{}]", l3.dims(), d.out_c)
        }
        let x = slice_f32(s1, l1, "convolution input")?;
        let weight = slice_f32(s2, l2, "convolution weight")?;
        let bias = slice_f32(s3, l3, "convolution bias")?;
        self.forward(d, x, weight, Some(bias))
    }

    fn bwd(
        &self,
        x: &Tensor,
        weight: &Tensor,
        _bias: &Tensor,
        _res: &Tensor,
        grad_res: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (dx, dw, db) = self.backward(x, weight, grad_res, true)?;
        Ok((Some(dx), Some(dw), db))
    }
}

/// A `kh x kw` convolution of `x: [B, C, H, W]` with `weight: [out, C, kh, kw]` and `bias: [out]`,
/// padded and strided as `spec` says (`spec.kernel` and `spec.ones_row` are ignored: the kernel
/// comes from the weights), output `[B, out, H_o, W_o]`: as one op on CPU f32 tensors (the
/// columns and one `gemm` per sample, forward and backward), as [`im2col`] and a matrix product
/// otherwise.
pub fn conv2d(
    x: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    spec: Im2ColSpec,
) -> Result<Tensor> {
    let (b, c, h, w) = x.dims4()?;
    let (out_c, wc, kh, kw) = weight.dims4()?;
    // the weights follow the activations' dtype (mixed precision: f32 master weights, half
    // activations; the cast is differentiable, and free when the dtypes agree)
    let weight = &weight.to_dtype(x.dtype())?;
    let bias = bias.map(|b| b.to_dtype(x.dtype())).transpose()?;
    let bias = bias.as_ref();
    let spec = Im2ColSpec {
        kernel: (kh, kw),
        ones_row: false,
        ..spec
    };
    let Some((ho, wo)) = spec.out_size(h, w) else {
        return Err(shape_err(
            "convolution input",
            format!("[B, {wc}, H, W] that a {kh}x{kw} kernel with {spec:?} fits"),
            x.dims(),
        ));
    };
    if wc != c {
        return Err(shape_err(
            "convolution input",
            format!("[B, {wc}, H, W]"),
            x.dims(),
        ));
    }
    if let Some(bias) = bias
        && bias.dims() != [out_c]
    {
        return Err(shape_err(
            "convolution bias",
            format!("[{out_c}]"),
            bias.dims(),
        ));
    }
    let fused = on_cpu_f32(x) && on_cpu_f32(weight) && bias.is_none_or(on_cpu_f32);
    if fused {
        let op = Conv2dGemm {
            cols: Im2Col { spec },
            parallel: None,
            tile_rows: None,
        };
        let (x, weight) = (x.contiguous()?, weight.contiguous()?);
        return Ok(match bias {
            Some(bias) => x.apply_op3(&weight, &bias.contiguous()?, op)?,
            None => x.apply_op2(&weight, op)?,
        });
    }
    conv2d_reference(x, weight, bias, spec, (b, ho, wo))
}

/// [`conv2d`] from candle ops ([`im2col`], then one matrix product with the bias as an extra
/// row of ones): any device, differentiable.
pub fn conv2d_reference(
    x: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    spec: Im2ColSpec,
    (b, ho, wo): (usize, usize, usize),
) -> Result<Tensor> {
    let (out_c, c, kh, kw) = weight.dims4()?;
    let spec = Im2ColSpec {
        kernel: (kh, kw),
        ones_row: bias.is_some(),
        ..spec
    };
    let col = im2col(x, spec)?;
    let mut wm = weight.reshape((out_c, c * kh * kw))?;
    if let Some(bias) = bias {
        wm = Tensor::cat(&[&wm, &bias.reshape((out_c, 1))?], 1)?;
    }
    Ok(wm
        .unsqueeze(0)?
        .broadcast_matmul(&col)?
        .reshape((b, out_c, ho, wo))?)
}

#[cfg(test)]
mod tests {
    use candle_core::Device;

    use super::*;
    use crate::fused::pattern;

    #[test]
    fn both_convolution_paths_give_the_same_bits() {
        // samples in parallel (single-threaded products) and one after another (threaded
        // products): the outputs and all three gradients are bit-identical, which is what makes a
        // training run independent of the thread count
        let dev = Device::Cpu;
        let spec = Im2ColSpec {
            kernel: (3, 3),
            stride: (1, 2),
            pad_h: 1,
            pad_w: 1,
            ring: true,
            ones_row: false,
        };
        let x = Tensor::from_vec(pattern(3 * 4 * 6 * 10, 0.37), (3, 4, 6, 10), &dev).unwrap();
        let w = Tensor::from_vec(pattern(5 * 4 * 9, 0.11), (5, 4, 3, 3), &dev).unwrap();
        let b = Tensor::from_vec(pattern(5, 0.7), 5, &dev).unwrap();
        let run = |parallel: bool| -> Vec<Vec<f32>> {
            let op = Conv2dGemm {
                cols: Im2Col { spec },
                parallel: Some(parallel),
                tile_rows: None,
            };
            let y = x.apply_op3(&w, &b, op).unwrap();
            let g = Tensor::from_vec(pattern(y.elem_count(), 0.53), y.dims(), &dev).unwrap();
            let (dx, dw, db) = op.backward(&x, &w, &g, true).unwrap();
            [y, dx, dw, db.unwrap()]
                .iter()
                .map(|t| t.flatten_all().unwrap().to_vec1::<f32>().unwrap())
                .collect()
        };
        let (a, b) = (run(true), run(false));
        for (i, (a, b)) in a.iter().zip(&b).enumerate() {
            let same =
                a.len() == b.len() && a.iter().zip(b).all(|(p, q)| p.to_bits() == q.to_bits());
            assert!(same, "output {i} differs between the two paths");
        }
        assert!(
            a[2].iter().any(|v| *v != 0.0),
            "the weight gradient is all zero"
        );
    }

    #[test]
    fn column_tiles_give_the_whole_layers_convolution() {
        // the columns filled and scattered a few output rows at a time (1, 2 and 4 of 6 rows: equal
        // tiles, and a short last one) against one tile of the whole layer: the same output and
        // gradients, up to the order in which the weight gradient sums the tiles
        let dev = Device::Cpu;
        for (spec, (h, w)) in [
            (
                Im2ColSpec {
                    kernel: (3, 3),
                    stride: (1, 2),
                    pad_h: 1,
                    pad_w: 1,
                    ring: true,
                    ones_row: false,
                },
                (6, 10),
            ),
            (
                Im2ColSpec {
                    kernel: (3, 3),
                    stride: (2, 2),
                    pad_h: 1,
                    pad_w: 1,
                    ring: false,
                    ones_row: false,
                },
                (11, 8),
            ),
        ] {
            let x = Tensor::from_vec(pattern(2 * 4 * h * w, 0.37), (2, 4, h, w), &dev).unwrap();
            let wt = Tensor::from_vec(pattern(5 * 4 * 9, 0.11), (5, 4, 3, 3), &dev).unwrap();
            let b = Tensor::from_vec(pattern(5, 0.7), 5, &dev).unwrap();
            let run = |tile_rows: usize, parallel: bool| -> Vec<Vec<f32>> {
                let op = Conv2dGemm {
                    cols: Im2Col { spec },
                    parallel: Some(parallel),
                    tile_rows: Some(tile_rows),
                };
                let y = x.apply_op3(&wt, &b, op).unwrap();
                let g = Tensor::from_vec(pattern(y.elem_count(), 0.53), y.dims(), &dev).unwrap();
                let (dx, dw, db) = op.backward(&x, &wt, &g, true).unwrap();
                [y, dx, dw, db.unwrap()]
                    .iter()
                    .map(|t| t.flatten_all().unwrap().to_vec1::<f32>().unwrap())
                    .collect()
            };
            let whole = run(usize::MAX, false);
            let ho = spec.out_size(h, w).unwrap().0;
            for rows in [1, 2, 4] {
                assert!(rows < ho, "{rows} rows make more than one tile of {ho}");
                for parallel in [false, true] {
                    let tiled = run(rows, parallel);
                    for (i, (a, b)) in tiled.iter().zip(&whole).enumerate() {
                        assert_eq!(a.len(), b.len());
                        let scale = b.iter().fold(1f32, |m, v| m.max(v.abs()));
                        for (p, q) in a.iter().zip(b) {
                            assert!(
                                (p - q).abs() <= 1e-5 * scale,
                                "{spec:?}, {rows} rows a tile, output {i}: {p} against {q}"
                            );
                        }
                    }
                }
            }
        }
    }
}
