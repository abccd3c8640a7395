//! im2col: padding (circular or zero in width, zero in height), strides and the columns of a `k x k`
//! convolution in one copy, with a col2im backward; and the per-sample column matrices the fused
//! convolution fills and scatters.

use std::ops::Range;

use candle_core::{CpuStorage, CustomOp1, Layout, Shape, Tensor};
use rayon::prelude::*;

use super::{min_len, on_cpu_f32, slice_f32, zeros};
use crate::error::{Result, shape_err};

/// Geometry of an [`im2col`]: kernel, strides, padding and how the width is padded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Im2ColSpec {
    /// Kernel height and width.
    pub kernel: (usize, usize),
    /// Row and column strides (>= 1).
    pub stride: (usize, usize),
    /// Rows of zeros added on top and bottom.
    pub pad_h: usize,
    /// Columns added left and right: copies of the opposite border when `ring`, zeros otherwise.
    pub pad_w: usize,
    /// Circular padding in width (the azimuth of a spinning LiDAR).
    pub ring: bool,
    /// Append one row of ones (so a bias can ride in the matrix product).
    pub ones_row: bool,
}

impl Im2ColSpec {
    /// A 1x1 kernel at stride 1 without padding: a per-pixel linear map, whose column matrix is the
    /// input itself (the fused convolution then reads the input in place).
    pub const POINTWISE: Self = Self {
        kernel: (1, 1),
        stride: (1, 1),
        pad_h: 0,
        pad_w: 0,
        ring: false,
        ones_row: false,
    };

    /// Output `(H_o, W_o)` for an input of `h x w`.
    pub fn out_size(&self, h: usize, w: usize) -> Option<(usize, usize)> {
        let (kh, kw) = self.kernel;
        let (sh, sw) = self.stride;
        let hp = h + 2 * self.pad_h;
        let wp = w + 2 * self.pad_w;
        if kh == 0 || kw == 0 || sh == 0 || sw == 0 || kh > hp || kw > wp {
            return None;
        }
        if self.ring && self.pad_w > w {
            return None;
        }
        Some(((hp - kh) / sh + 1, (wp - kw) / sw + 1))
    }

    fn rows(&self, c: usize) -> usize {
        c * self.kernel.0 * self.kernel.1 + usize::from(self.ones_row)
    }
}

/// For output columns `0..wo` at kernel column `kx`: the source column of each output column in
/// stride-1 runs, as `(out_start, len, Some(src_start) | None for zeros)` segments.
fn col_segments(
    wo: usize,
    w: usize,
    kx: usize,
    pad_w: usize,
    ring: bool,
) -> [(usize, usize, Option<usize>); 3] {
    // stride-1 source column of output column ox is ox + kx - pad_w, in [-pad_w, w + pad_w)
    let off = kx as isize - pad_w as isize;
    let left = if off < 0 { (-off) as usize } else { 0 }.min(wo);
    let mid_end = ((w as isize - off).max(0) as usize).min(wo).max(left);
    let right = wo - mid_end;
    let src = |ix: isize| -> Option<usize> {
        if ring {
            Some(ix.rem_euclid(w as isize) as usize)
        } else {
            None
        }
    };
    [
        (0, left, src(off)),
        (left, mid_end - left, Some((left as isize + off) as usize)),
        (mid_end, right, src(mid_end as isize + off)),
    ]
}

#[derive(Debug, Clone, Copy)]
pub(super) struct Im2Col {
    pub(super) spec: Im2ColSpec,
}

impl Im2Col {
    /// Fills one row of the column matrix (`oys.len() * wo` values: the output rows `oys`) for
    /// channel plane `plane` (`h * w`) at kernel tap `(ky, kx)`.
    #[allow(clippy::too_many_arguments)]
    fn fill_row(
        &self,
        row: &mut [f32],
        plane: &[f32],
        h: usize,
        w: usize,
        ky: usize,
        kx: usize,
        oys: Range<usize>,
    ) {
        let s = &self.spec;
        let (sh, sw) = s.stride;
        let (_, wo) = s.out_size(h, w).unwrap_or((0, 0));
        let first = oys.start;
        for oy in oys {
            let out = &mut row[(oy - first) * wo..(oy - first + 1) * wo];
            let iy = (oy * sh + ky) as isize - s.pad_h as isize;
            if iy < 0 || iy >= h as isize {
                out.fill(0.0);
                continue;
            }
            let src = &plane[iy as usize * w..(iy as usize + 1) * w];
            if sw == 1 {
                for (o0, len, from) in col_segments(wo, w, kx, s.pad_w, s.ring) {
                    if len == 0 {
                        continue;
                    }
                    match from {
                        Some(f) => out[o0..o0 + len].copy_from_slice(&src[f..f + len]),
                        None => out[o0..o0 + len].fill(0.0),
                    }
                }
            } else {
                for (ox, o) in out.iter_mut().enumerate() {
                    let ix = (ox * sw + kx) as isize - s.pad_w as isize;
                    *o = if ix >= 0 && ix < w as isize {
                        src[ix as usize]
                    } else if s.ring {
                        src[ix.rem_euclid(w as isize) as usize]
                    } else {
                        0.0
                    };
                }
            }
        }
    }

    /// Adds one gradient row (the output rows `oys`) back into the channel plane (the transpose
    /// of `Im2Col::fill_row`).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn scatter_row(
        &self,
        row: &[f32],
        plane: &mut [f32],
        h: usize,
        w: usize,
        ky: usize,
        kx: usize,
        oys: Range<usize>,
    ) {
        let s = &self.spec;
        let (sh, sw) = s.stride;
        let (_, wo) = s.out_size(h, w).unwrap_or((0, 0));
        let first = oys.start;
        for oy in oys {
            let g = &row[(oy - first) * wo..(oy - first + 1) * wo];
            let iy = (oy * sh + ky) as isize - s.pad_h as isize;
            if iy < 0 || iy >= h as isize {
                continue;
            }
            let dst = &mut plane[iy as usize * w..(iy as usize + 1) * w];
            if sw == 1 {
                for (o0, len, from) in col_segments(wo, w, kx, s.pad_w, s.ring) {
                    if let Some(f) = from {
                        for (d, v) in dst[f..f + len].iter_mut().zip(&g[o0..o0 + len]) {
                            *d += v;
                        }
                    }
                }
            } else {
                for (ox, v) in g.iter().enumerate() {
                    let ix = (ox * sw + kx) as isize - s.pad_w as isize;
                    if ix >= 0 && ix < w as isize {
                        dst[ix as usize] += v;
                    } else if s.ring {
                        dst[ix.rem_euclid(w as isize) as usize] += v;
                    }
                }
            }
        }
    }
}

impl CustomOp1 for Im2Col {
    fn name(&self) -> &'static str {
        "veila-im2col"
    }

    fn cpu_fwd(
        &self,
        storage: &CpuStorage,
        layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let x = slice_f32(storage, layout, "im2col input")?;
        let (b, c, h, w) = layout.shape().dims4()?;
        let Some((ho, wo)) = self.spec.out_size(h, w) else {
            candle_core::bail!("im2col: {:?} does not fit a {h}x{w} input", self.spec)
        };
        let (kh, kw) = self.spec.kernel;
        let kk = kh * kw;
        let rows = self.spec.rows(c);
        let n = ho * wo;
        let mut dst = zeros(b * rows * n);
        if n > 0 {
            dst.par_chunks_mut(n)
                .with_min_len(min_len(n))
                .enumerate()
                .for_each(|(i, row)| {
                    let (bi, r) = (i / rows, i % rows);
                    if r >= c * kk {
                        row.fill(1.0);
                    } else {
                        let xb = &x[bi * c * h * w..(bi + 1) * c * h * w];
                        self.fill_col_row(r, row, xb, (h, w), 0..ho);
                    }
                });
        }
        Ok((CpuStorage::F32(dst), Shape::from((b, rows, n))))
    }

    fn bwd(
        &self,
        arg: &Tensor,
        _res: &Tensor,
        grad_res: &Tensor,
    ) -> candle_core::Result<Option<Tensor>> {
        let (b, c, h, w) = arg.dims4()?;
        let op = Col2Im {
            inner: *self,
            in_shape: (b, c, h, w),
        };
        Ok(Some(grad_res.contiguous()?.apply_op1_no_bwd(&op)?))
    }
}

/// The transpose of `Im2Col` (its backward pass).
#[derive(Debug, Clone, Copy)]
struct Col2Im {
    inner: Im2Col,
    in_shape: (usize, usize, usize, usize),
}

impl CustomOp1 for Col2Im {
    fn name(&self) -> &'static str {
        "veila-col2im"
    }

    fn cpu_fwd(
        &self,
        storage: &CpuStorage,
        layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let g = slice_f32(storage, layout, "col2im input")?;
        let (b, c, h, w) = self.in_shape;
        let spec = self.inner.spec;
        let (kh, kw) = spec.kernel;
        let kk = kh * kw;
        let rows = spec.rows(c);
        let Some((ho, wo)) = spec.out_size(h, w) else {
            candle_core::bail!("col2im: {spec:?} does not fit a {h}x{w} input")
        };
        let n = ho * wo;
        if layout.shape().dims() != [b, rows, n] {
            candle_core::bail!(
                "col2im: gradient {:?}, expected {:?}",
                layout.shape(),
                [b, rows, n]
            );
        }
        let mut dst = zeros(b * c * h * w);
        if h * w > 0 {
            dst.par_chunks_mut(h * w)
                .with_min_len(min_len(h * w * kk))
                .enumerate()
                .for_each(|(i, plane)| {
                    let (bi, ci) = (i / c, i % c);
                    let sample = &g[bi * rows * n..(bi + 1) * rows * n];
                    self.inner.scatter_plane(ci, plane, sample, (h, w), 0..ho);
                });
        }
        Ok((CpuStorage::F32(dst), Shape::from((b, c, h, w))))
    }
}

/// The im2col of `x: [B, C, H, W]`: `[B, C kh kw (+1), H_o W_o]`, row `c kh kw + ky kw + kx` holding
/// the input at `(oy sh + ky - pad_h, ox sw + kx - pad_w)` (wrapped in width when `ring`, zero outside),
/// and a last row of ones when `spec.ones_row`. The row order matches a `[out, C, kh, kw]` weight
/// reshaped to `[out, C kh kw]`.
pub fn im2col(x: &Tensor, spec: Im2ColSpec) -> Result<Tensor> {
    let (b, c, h, w) = x.dims4()?;
    let Some((ho, wo)) = spec.out_size(h, w) else {
        return Err(shape_err(
            "im2col input",
            format!("a plane the {spec:?} fits"),
            x.dims(),
        ));
    };
    if on_cpu_f32(x) {
        return Ok(x.contiguous()?.apply_op1(Im2Col { spec })?);
    }
    im2col_reference(x, spec, (b, c, ho, wo))
}

/// [`im2col`] from candle ops (narrow, cat, pad, reshape): any device, differentiable.
pub fn im2col_reference(
    x: &Tensor,
    spec: Im2ColSpec,
    (b, c, ho, wo): (usize, usize, usize, usize),
) -> Result<Tensor> {
    let (kh, kw) = spec.kernel;
    let (sh, sw) = spec.stride;
    let (_, _, _, w) = x.dims4()?;
    let xw = if spec.pad_w > 0 {
        if spec.ring {
            let left = x.narrow(3, w - spec.pad_w, spec.pad_w)?;
            let right = x.narrow(3, 0, spec.pad_w)?;
            Tensor::cat(&[&left, x, &right], 3)?
        } else {
            x.pad_with_zeros(3, spec.pad_w, spec.pad_w)?
        }
    } else {
        x.clone()
    };
    let xp = if spec.pad_h > 0 {
        xw.pad_with_zeros(2, spec.pad_h, spec.pad_h)?
    } else {
        xw
    };
    let mut taps = Vec::with_capacity(kh * kw);
    for ky in 0..kh {
        let rows = strided(&xp, 2, ky, ho, sh)?;
        for kx in 0..kw {
            taps.push(strided(&rows, 3, kx, wo, sw)?.unsqueeze(2)?);
        }
    }
    // [B, C, kh*kw, Ho, Wo] -> [B, C*kh*kw, Ho*Wo]
    let col = Tensor::stack(&taps, 2)?
        .squeeze(3)?
        .reshape((b, c * kh * kw, ho * wo))?;
    Ok(if spec.ones_row {
        let ones = Tensor::ones((b, 1, ho * wo), x.dtype(), x.device())?;
        Tensor::cat(&[&col, &ones], 1)?
    } else {
        col
    })
}

/// `t[.., start + stride * i, ..]` for `i < n` along `dim` (entries past the end read as zero).
fn strided(t: &Tensor, dim: usize, start: usize, n: usize, stride: usize) -> Result<Tensor> {
    if stride == 1 {
        return Ok(t.narrow(dim, start, n)?);
    }
    let len = t.dim(dim)?;
    let want = n * stride;
    let avail = len.saturating_sub(start).min(want);
    let mut s = t.narrow(dim, start, avail)?;
    if avail < want {
        s = s.pad_with_zeros(dim, 0, want - avail)?;
    }
    let mut shape = s.dims().to_vec();
    shape[dim] = n;
    shape.insert(dim + 1, stride);
    let s = s.reshape(shape.as_slice())?.narrow(dim + 1, 0, 1)?;
    Ok(s.squeeze(dim + 1)?)
}

impl Im2Col {
    /// Whether the column matrix of a sample is its planes as they are (a 1x1 kernel, stride 1,
    /// no padding): the convolution then reads the input in place and writes the input gradient
    /// directly, with no column buffer.
    pub(super) fn is_identity(&self) -> bool {
        Im2ColSpec {
            ring: false,
            ..self.spec
        } == Im2ColSpec::POINTWISE
    }

    /// Output rows per column tile of a convolution whose column matrix has `k` rows: as many
    /// whole output rows as fit [`TILE_FLOATS`], at least one. Filling and scattering the columns
    /// tile by tile bounds the scratch of a convolution by the tile, not by the layer: one sample's
    /// full column matrix is `k` times its `H_o W_o` pixels (`9 C` for a 3x3 kernel: 432 MiB at
    /// the paper network's 64 x 1024 level with 192 input channels, per thread).
    pub(super) fn tile_rows(&self, k: usize, ho: usize, wo: usize) -> usize {
        (TILE_FLOATS / (k * wo).max(1)).clamp(1, ho.max(1))
    }

    /// Scratch floats per column buffer for tiles of `tile_n` output pixels (none for
    /// [`Self::is_identity`]).
    pub(super) fn scratch_len(&self, k: usize, tile_n: usize) -> usize {
        if self.is_identity() { 0 } else { k * tile_n }
    }

    /// Fills row `r` (below `C kh kw`) of one sample's column matrix, for the output rows `oys`,
    /// from that sample's planes `x`.
    fn fill_col_row(
        &self,
        r: usize,
        row: &mut [f32],
        x: &[f32],
        (h, w): (usize, usize),
        oys: Range<usize>,
    ) {
        let (kh, kw) = self.spec.kernel;
        let (ci, tap) = (r / (kh * kw), r % (kh * kw));
        self.fill_row(
            row,
            &x[ci * h * w..(ci + 1) * h * w],
            h,
            w,
            tap / kw,
            tap % kw,
            oys,
        );
    }

    /// Adds channel `ci`'s rows of one sample's column gradient `dcol` (the output rows `oys`,
    /// `oys.len() * W_o` values a row) into that channel's plane.
    #[inline(always)]
    fn scatter_plane(
        &self,
        ci: usize,
        plane: &mut [f32],
        dcol: &[f32],
        (h, w): (usize, usize),
        oys: Range<usize>,
    ) {
        let (kh, kw) = self.spec.kernel;
        let wo = self.spec.out_size(h, w).map_or(0, |(_, wo)| wo);
        let n = oys.len() * wo;
        for tap in 0..kh * kw {
            let r = ci * kh * kw + tap;
            let row = &dcol[r * n..(r + 1) * n];
            self.scatter_row(row, plane, h, w, tap / kw, tap % kw, oys.clone());
        }
    }

    /// Fills one sample's column matrix for the output rows `oys` (`C kh kw` rows of
    /// `oys.len() * W_o` values) from its planes `x`.
    pub(super) fn fill_sample(
        &self,
        col: &mut [f32],
        x: &[f32],
        (h, w): (usize, usize),
        oys: Range<usize>,
        parallel: bool,
    ) {
        let wo = self.spec.out_size(h, w).map_or(0, |(_, wo)| wo);
        let n = oys.len() * wo;
        if n == 0 {
            return;
        }
        let fill =
            |(r, row): (usize, &mut [f32])| self.fill_col_row(r, row, x, (h, w), oys.clone());
        if parallel {
            col.par_chunks_mut(n)
                .with_min_len(min_len(n))
                .enumerate()
                .for_each(fill);
        } else {
            col.chunks_mut(n).enumerate().for_each(fill);
        }
    }

    /// Adds the column-matrix gradient `dcol` of one sample's output rows `oys` back into its
    /// planes `dx`.
    pub(super) fn scatter_sample(
        &self,
        dcol: &[f32],
        dx: &mut [f32],
        (h, w): (usize, usize),
        oys: Range<usize>,
        parallel: bool,
    ) {
        if h * w == 0 || oys.is_empty() {
            return;
        }
        let (kh, kw) = self.spec.kernel;
        let kk = kh * kw;
        let scatter = |(ci, plane): (usize, &mut [f32])| {
            self.scatter_plane(ci, plane, dcol, (h, w), oys.clone())
        };
        if parallel {
            dx.par_chunks_mut(h * w)
                .with_min_len(min_len(h * w * kk))
                .enumerate()
                .for_each(scatter);
        } else {
            scatter_planes_simd(self, dcol, dx, h, w, oys);
        }
    }
}

/// The most floats of one column tile of the fused convolution (16 MiB; see
/// [`Im2Col::tile_rows`]). The products over a tile are still large (a 64 x 1024 level with 64
/// input channels takes 7 output rows, 7,168 pixels, at once).
pub(crate) const TILE_FLOATS: usize = 1 << 22;

multiversion! {
    /// One sample's col2im on one thread: every channel's plane in turn.
    fn scatter_planes(cols: &Im2Col, dcol: &[f32], dx: &mut [f32], h: usize, w: usize, oys: Range<usize>) {
        for (ci, plane) in dx.chunks_mut(h * w).enumerate() {
            cols.scatter_plane(ci, plane, dcol, (h, w), oys.clone());
        }
    }

    /// [`scatter_planes`] on the CPU's widest vector unit (its adds vectorise; same bits on
    /// every level).
    dispatch scatter_planes_simd / scatter_planes_at;
}
