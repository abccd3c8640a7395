//! Multi-threaded CPU kernels for the denoiser's hot spots, as candle custom ops.
//!
//! candle's CPU backend builds GroupNorm out of about a dozen separate passes over memory (twice that
//! backward), and an im2col convolution out of `cat`s of shifted views whose backward adds up
//! zero-padded copies; the training step spent most of its time there (issue 19).
//! The ops here do the same arithmetic in one pass each, spread over the rayon pool:
//!
//! * [`im2col`]: padding (circular or zero in width, zero in height), strides and the im2col of a
//!   `k x k` convolution in one copy, with a `col2im` backward;
//! * [`conv2d`]: a whole convolution, the columns of one sample at a time and one `gemm` product
//!   (candle's matrix-product crate) per sample, forward and backward, so neither the columns of the
//!   batch nor their gradient exist as tensors;
//! * [`group_norm_act`]: GroupNorm with a per-sample, per-channel scale and shift (the affine weights,
//!   and the FiLM / AdaGN modulation of the time embedding folded in) and an optional SiLU, forward and
//!   backward;
//! * [`add_scaled`]: the scaled residual sum `(a + b) * s`;
//! * [`res_block`]: a whole residual block (the ops above, composed, with a hand-written backward), so
//!   candle's backward handles one gradient for it instead of one per layer.
//!
//! Each public function dispatches: F32 tensors on the CPU take the kernels, every other device or dtype
//! runs the plain candle composition (the `*_reference` functions), which is also what the tests compare
//! against, gradients included.

use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, DType, Layout, Shape, Tensor};
use rayon::prelude::*;

use crate::error::{Result, shape_err};

/// Environment variable that, when set to `1`, turns the kernels off (every op runs its candle
/// composition): for before/after measurements in one binary (`cargo xtask bench-model`).
pub const REFERENCE_OPS_ENV: &str = "VEILA_NN_REFERENCE_OPS";

/// bf16 or f16: the dtypes whose normalisations and softmaxes run in f32 (mixed precision).
pub fn is_half(dtype: DType) -> bool {
    matches!(dtype, DType::BF16 | DType::F16)
}

/// Whether the CPU kernels are on (they are unless [`REFERENCE_OPS_ENV`] is `1`; read once).
pub fn kernels_enabled() -> bool {
    static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ON.get_or_init(|| std::env::var(REFERENCE_OPS_ENV).map_or(true, |v| v != "1"))
}

/// Whether `t` takes the CPU kernels of this module (an f32 tensor on the CPU, kernels on).
pub fn takes_kernels(t: &Tensor) -> bool {
    on_cpu_f32(t)
}

/// Whether `t` takes the CPU kernels of this module.
fn on_cpu_f32(t: &Tensor) -> bool {
    t.device().is_cpu() && t.dtype() == DType::F32 && kernels_enabled()
}

/// The contiguous `f32` slice of a CPU storage.
fn slice_f32<'a>(s: &'a CpuStorage, l: &Layout, what: &str) -> candle_core::Result<&'a [f32]> {
    let CpuStorage::F32(v) = s else {
        candle_core::bail!("{what}: expected an f32 tensor")
    };
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&v[a..b]),
        None => candle_core::bail!("{what}: expected a contiguous tensor"),
    }
}

/// A fresh contiguous copy of a CPU f32 tensor's data (only used in backward passes).
fn tensor_f32(t: &Tensor, what: &str) -> candle_core::Result<Vec<f32>> {
    let t = t.contiguous()?;
    let (s, l) = t.storage_and_layout();
    match &*s {
        candle_core::Storage::Cpu(c) => Ok(slice_f32(c, l, what)?.to_vec()),
        _ => candle_core::bail!("{what}: the fused kernels run on the CPU only"),
    }
}

/// Runs `f` on the contiguous `f32` data of the CPU tensor `t`.
fn with_f32<R>(
    t: &Tensor,
    what: &str,
    f: impl FnOnce(&[f32]) -> candle_core::Result<R>,
) -> candle_core::Result<R> {
    let t = t.contiguous()?;
    let (s, l) = t.storage_and_layout();
    match &*s {
        candle_core::Storage::Cpu(c) => f(slice_f32(c, l, what)?),
        _ => candle_core::bail!("{what}: the fused kernels run on the CPU only"),
    }
}

/// Minimum elements per rayon task: below this the split costs more than it saves.
const GRAIN: usize = 16 * 1024;

/// `n` zeros, written over the rayon pool when `n` is large: the big activation and gradient
/// buffers of a training step, zero-filled on the calling thread, kept one core idle for about
/// 5 % of the step.
fn zeros(n: usize) -> Vec<f32> {
    if n < 4 * GRAIN {
        return vec![0f32; n];
    }
    let mut v = Vec::with_capacity(n);
    v.par_extend(rayon::iter::repeat_n(0f32, n));
    v
}

fn min_len(chunk: usize) -> usize {
    (GRAIN / chunk.max(1)).max(1)
}

/// Defines the `#[inline(always)]` kernel `$kernel` and, after `dispatch`, `$name`, which runs it
/// compiled for the widest vector unit the CPU has (AVX-512, else AVX2, else the baseline SSE2 the
/// crate is built for), and `$at`, which runs it at a given level (for tests): the kernel is
/// inlined into one function per level with those target features, so its loops vectorise 16 or
/// 8 lanes wide instead of 4. The kernels keep their own lane structure and never use `mul_add`,
/// so every level computes the same IEEE operations in the same order: results are bit-identical
/// across CPUs (tests compare the levels).
macro_rules! multiversion {
    (
        $(#[$kdoc:meta])*
        fn $kernel:ident($($arg:ident: $ty:ty),* $(,)?) $body:block
        $(#[$doc:meta])*
        dispatch $name:ident / $at:ident;
    ) => {
        $(#[$kdoc])*
        #[inline(always)]
        #[allow(clippy::too_many_arguments)]
        fn $kernel($($arg: $ty),*) $body

        $(#[$doc])*
        #[allow(clippy::too_many_arguments)]
        fn $name($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                $at(simd_level(), $($arg),*)
            }
            #[cfg(not(target_arch = "x86_64"))]
            {
                $kernel($($arg),*)
            }
        }

        /// The kernel at a given vector level (which the caller must have checked the CPU has).
        #[cfg(target_arch = "x86_64")]
        #[allow(clippy::too_many_arguments)]
        fn $at(level: SimdLevel, $($arg: $ty),*) {
            #[target_feature(enable = "avx2,fma,avx512f")]
            #[allow(clippy::too_many_arguments)]
            fn avx512($($arg: $ty),*) {
                $kernel($($arg),*)
            }
            #[target_feature(enable = "avx2,fma")]
            #[allow(clippy::too_many_arguments)]
            fn avx2($($arg: $ty),*) {
                $kernel($($arg),*)
            }
            match level {
                // SAFETY: `level` came from `simd_level` (or a test that checked the CPU), so
                // the CPU has these features.
                #[allow(unsafe_code)]
                SimdLevel::Avx512 => unsafe { avx512($($arg),*) },
                #[allow(unsafe_code)]
                SimdLevel::Avx2 => unsafe { avx2($($arg),*) },
                SimdLevel::Baseline => $kernel($($arg),*),
            }
        }
    };
}

#[cfg(target_arch = "x86_64")]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum SimdLevel {
    Avx512,
    Avx2,
    Baseline,
}

/// The CPU's vector level (AVX-512 and AVX2 levels include FMA), detected once (`VEILA_NN_SIMD=baseline|avx2` caps it, for tests and
/// comparisons).
#[cfg(target_arch = "x86_64")]
fn simd_level() -> SimdLevel {
    static LEVEL: std::sync::OnceLock<SimdLevel> = std::sync::OnceLock::new();
    *LEVEL.get_or_init(|| {
        let cap = std::env::var("VEILA_NN_SIMD").unwrap_or_default();
        if cap != "baseline"
            && cap != "avx2"
            && std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma")
        {
            SimdLevel::Avx512
        } else if cap != "baseline"
            && std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma")
        {
            SimdLevel::Avx2
        } else {
            SimdLevel::Baseline
        }
    })
}

// ---------------------------------------------------------------------------------------------
// im2col

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
struct Im2Col {
    spec: Im2ColSpec,
}

impl Im2Col {
    /// Fills one output row (`ho * wo` values) for channel plane `plane` (`h * w`) at kernel tap
    /// `(ky, kx)`.
    fn fill_row(&self, row: &mut [f32], plane: &[f32], h: usize, w: usize, ky: usize, kx: usize) {
        let s = &self.spec;
        let (sh, sw) = s.stride;
        let (ho, wo) = s.out_size(h, w).unwrap_or((0, 0));
        for oy in 0..ho {
            let out = &mut row[oy * wo..(oy + 1) * wo];
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

    /// Adds one gradient row back into the channel plane (the transpose of `Im2Col::fill_row`).
    #[inline(always)]
    fn scatter_row(
        &self,
        row: &[f32],
        plane: &mut [f32],
        h: usize,
        w: usize,
        ky: usize,
        kx: usize,
    ) {
        let s = &self.spec;
        let (sh, sw) = s.stride;
        let (ho, wo) = s.out_size(h, w).unwrap_or((0, 0));
        for oy in 0..ho {
            let g = &row[oy * wo..(oy + 1) * wo];
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
                        self.fill_col_row(r, row, &x[bi * c * h * w..(bi + 1) * c * h * w], h, w);
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
                    self.inner.scatter_plane(ci, plane, sample, (h, w, n));
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

// ---------------------------------------------------------------------------------------------
// convolution: im2col + gemm, one sample at a time

/// `dst (m x n) = [dst +] lhs (m x k) · rhs (k x n)` with `gemm` (candle's own matrix-product
/// crate), every matrix given as `(slice, row stride, column stride)`; `accumulate` adds to `dst`,
/// `threaded` spreads the product over candle's thread count (the result is the same either way:
/// `gemm` splits the output, not the sum). The strides are checked against the slices, so the call
/// is in bounds.
fn matmul_into(
    dst: (&mut [f32], usize, usize),
    (m, n, k): (usize, usize, usize),
    accumulate: bool,
    lhs: (&[f32], usize, usize),
    rhs: (&[f32], usize, usize),
    threaded: bool,
) -> candle_core::Result<()> {
    fn fits(len: usize, rows: usize, cols: usize, rs: usize, cs: usize) -> bool {
        rows == 0 || cols == 0 || (rows - 1) * rs + (cols - 1) * cs < len
    }
    let (d, d_rs, d_cs) = dst;
    if !fits(d.len(), m, n, d_rs, d_cs)
        || !fits(lhs.0.len(), m, k, lhs.1, lhs.2)
        || !fits(rhs.0.len(), k, n, rhs.1, rhs.2)
    {
        candle_core::bail!("matmul_into: a matrix does not fit its slice ({m}x{k} · {k}x{n})")
    }
    if m == 0 || n == 0 {
        return Ok(());
    }
    if k == 0 {
        if !accumulate {
            for i in 0..m {
                for j in 0..n {
                    d[i * d_rs + j * d_cs] = 0.0;
                }
            }
        }
        return Ok(());
    }
    // rayon's count, not `candle_core::utils::get_num_threads()`: candle 0.11 reads
    // `/proc/cpuinfo` on every call of that unless RAYON_NUM_THREADS is set
    let threads = rayon::current_num_threads();
    let parallelism = if threaded && threads > 1 {
        gemm::Parallelism::Rayon(threads)
    } else {
        gemm::Parallelism::None
    };
    // SAFETY: `fits` checked that every element the three strided matrices address lies inside its
    // slice; `dst` is borrowed mutably and does not alias `lhs` or `rhs`.
    #[allow(unsafe_code)]
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            d.as_mut_ptr(),
            d_cs as isize,
            d_rs as isize,
            accumulate,
            lhs.0.as_ptr(),
            lhs.2 as isize,
            lhs.1 as isize,
            rhs.0.as_ptr(),
            rhs.2 as isize,
            rhs.1 as isize,
            if accumulate { 1.0 } else { 0.0 },
            1.0,
            false,
            false,
            false,
            parallelism,
        );
    }
    Ok(())
}

/// `dst (m x nb, row-major) = a (m x len) · bᵀ` for `b (nb x len)`, both row-major: every output
/// is a dot product of two contiguous rows. This is the weight gradient of a convolution (`g ·
/// colᵀ`, summed over the pixels), for which `gemm` first copies both operands into packed panels
/// (a transposing gather of the whole column matrix: most of that product's time, and more with
/// AVX-512's wider panels); here the rows are read in place, 4 x 3 outputs at a time in vector
/// accumulators (`pulp`: AVX-512, AVX2 + FMA or scalar, chosen at run time; fused multiply-adds
/// where the CPU has them, so the last bits depend on the CPU, as `gemm`'s do).
struct Abt<'a> {
    dst: &'a mut [f32],
    a: &'a [f32],
    b: &'a [f32],
    m: usize,
    nb: usize,
    len: usize,
}

impl pulp::WithSimd for Abt<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let Abt {
            dst,
            a,
            b,
            m,
            nb,
            len,
        } = self;
        let span = |i: usize| i * len..(i + 1) * len;
        let dot = |x: &[f32], y: &[f32]| -> f32 {
            let (xs, xt) = S::as_simd_f32s(x);
            let (ys, yt) = S::as_simd_f32s(y);
            let mut acc = simd.splat_f32s(0.0);
            for (p, q) in xs.iter().zip(ys) {
                acc = simd.mul_add_f32s(*p, *q, acc);
            }
            let mut t = simd.reduce_sum_f32s(acc);
            for (p, q) in xt.iter().zip(yt) {
                t += p * q;
            }
            t
        };
        for i in (0..m).step_by(4) {
            for j in (0..nb).step_by(3) {
                if i + 4 > m || j + 3 > nb {
                    for ii in i..(i + 4).min(m) {
                        for jj in j..(j + 3).min(nb) {
                            dst[ii * nb + jj] = dot(&a[span(ii)], &b[span(jj)]);
                        }
                    }
                    continue;
                }
                let ar = |r: usize| S::as_simd_f32s(&a[span(i + r)]);
                let br = |q: usize| S::as_simd_f32s(&b[span(j + q)]);
                let ((a0, a0t), (a1, a1t), (a2, a2t), (a3, a3t)) = (ar(0), ar(1), ar(2), ar(3));
                let ((b0, b0t), (b1, b1t), (b2, b2t)) = (br(0), br(1), br(2));
                let z = simd.splat_f32s(0.0);
                let (mut c00, mut c01, mut c02) = (z, z, z);
                let (mut c10, mut c11, mut c12) = (z, z, z);
                let (mut c20, mut c21, mut c22) = (z, z, z);
                let (mut c30, mut c31, mut c32) = (z, z, z);
                for ((((x0, x1), x2), x3), ((y0, y1), y2)) in a0
                    .iter()
                    .zip(a1)
                    .zip(a2)
                    .zip(a3)
                    .zip(b0.iter().zip(b1).zip(b2))
                {
                    c00 = simd.mul_add_f32s(*x0, *y0, c00);
                    c01 = simd.mul_add_f32s(*x0, *y1, c01);
                    c02 = simd.mul_add_f32s(*x0, *y2, c02);
                    c10 = simd.mul_add_f32s(*x1, *y0, c10);
                    c11 = simd.mul_add_f32s(*x1, *y1, c11);
                    c12 = simd.mul_add_f32s(*x1, *y2, c12);
                    c20 = simd.mul_add_f32s(*x2, *y0, c20);
                    c21 = simd.mul_add_f32s(*x2, *y1, c21);
                    c22 = simd.mul_add_f32s(*x2, *y2, c22);
                    c30 = simd.mul_add_f32s(*x3, *y0, c30);
                    c31 = simd.mul_add_f32s(*x3, *y1, c31);
                    c32 = simd.mul_add_f32s(*x3, *y2, c32);
                }
                let acc = [
                    [c00, c01, c02],
                    [c10, c11, c12],
                    [c20, c21, c22],
                    [c30, c31, c32],
                ];
                let (at, bt) = ([a0t, a1t, a2t, a3t], [b0t, b1t, b2t]);
                for r in 0..4 {
                    for q in 0..3 {
                        let mut t = simd.reduce_sum_f32s(acc[r][q]);
                        for (p, v) in at[r].iter().zip(bt[q]) {
                            t += p * v;
                        }
                        dst[(i + r) * nb + j + q] = t;
                    }
                }
            }
        }
    }
}

/// [`Abt`] on the CPU's widest vector unit; with `threaded`, blocks of output rows are
/// spread over rayon's threads (each output is one thread's, so the result does not depend on
/// the thread count).
fn matmul_abt(
    dst: &mut [f32],
    a: &[f32],
    b: &[f32],
    (m, nb, len): (usize, usize, usize),
    threaded: bool,
) -> candle_core::Result<()> {
    if dst.len() != m * nb || a.len() < m * len || b.len() < nb * len {
        candle_core::bail!(
            "matmul_abt: a matrix does not fit its slice ({m}x{len} · ({nb}x{len})ᵀ)"
        )
    }
    fn run(dst: &mut [f32], a: &[f32], b: &[f32], (m, nb, len): (usize, usize, usize)) {
        pulp::Arch::new().dispatch(Abt {
            dst,
            a,
            b,
            m,
            nb,
            len,
        });
    }
    const ROWS: usize = 4;
    if threaded && rayon::current_num_threads() > 1 && m > ROWS && nb > 0 {
        dst.par_chunks_mut(ROWS * nb)
            .zip(a.par_chunks(ROWS * len))
            .for_each(|(d, a)| run(d, a, b, (d.len() / nb, nb, len)));
    } else {
        run(dst, a, b, (m, nb, len));
    }
    Ok(())
}

impl Im2Col {
    /// Whether the column matrix of a sample is its planes as they are (a 1x1 kernel, stride 1,
    /// no padding): the convolution then reads the input in place and writes the input gradient
    /// directly, with no column buffer.
    fn is_identity(&self) -> bool {
        Im2ColSpec {
            ring: false,
            ..self.spec
        } == Im2ColSpec::POINTWISE
    }

    /// Scratch floats per column buffer for a `k x n` column matrix (none for [`Self::is_identity`]).
    fn scratch_len(&self, k: usize, n: usize) -> usize {
        if self.is_identity() { 0 } else { k * n }
    }

    /// The `[C kh kw, H_o W_o]` column matrix of one sample (`x`: its `C` planes of `h x w`).
    /// Fills row `r` (below `C kh kw`) of one sample's column matrix from that sample's planes `x`.
    fn fill_col_row(&self, r: usize, row: &mut [f32], x: &[f32], h: usize, w: usize) {
        let (kh, kw) = self.spec.kernel;
        let (ci, tap) = (r / (kh * kw), r % (kh * kw));
        self.fill_row(
            row,
            &x[ci * h * w..(ci + 1) * h * w],
            h,
            w,
            tap / kw,
            tap % kw,
        );
    }

    /// Adds channel `ci`'s rows of one sample's column gradient `dcol` (`n` values a row) into that
    /// channel's plane.
    #[inline(always)]
    fn scatter_plane(
        &self,
        ci: usize,
        plane: &mut [f32],
        dcol: &[f32],
        (h, w, n): (usize, usize, usize),
    ) {
        let (kh, kw) = self.spec.kernel;
        for tap in 0..kh * kw {
            let r = ci * kh * kw + tap;
            self.scatter_row(&dcol[r * n..(r + 1) * n], plane, h, w, tap / kw, tap % kw);
        }
    }

    fn fill_sample(
        &self,
        col: &mut [f32],
        x: &[f32],
        (h, w, n): (usize, usize, usize),
        parallel: bool,
    ) {
        if n == 0 {
            return;
        }
        let fill = |(r, row): (usize, &mut [f32])| self.fill_col_row(r, row, x, h, w);
        if parallel {
            col.par_chunks_mut(n)
                .with_min_len(min_len(n))
                .enumerate()
                .for_each(fill);
        } else {
            col.chunks_mut(n).enumerate().for_each(fill);
        }
    }

    /// Adds the column-matrix gradient `dcol` of one sample back into its planes `dx` (zeroed).
    fn scatter_sample(
        &self,
        dcol: &[f32],
        dx: &mut [f32],
        (h, w, n): (usize, usize, usize),
        parallel: bool,
    ) {
        if h * w == 0 {
            return;
        }
        let (kh, kw) = self.spec.kernel;
        let kk = kh * kw;
        let scatter =
            |(ci, plane): (usize, &mut [f32])| self.scatter_plane(ci, plane, dcol, (h, w, n));
        if parallel {
            dx.par_chunks_mut(h * w)
                .with_min_len(min_len(h * w * kk))
                .enumerate()
                .for_each(scatter);
        } else {
            scatter_planes_simd(self, dcol, dx, h, w, n);
        }
    }
}

multiversion! {
    /// One sample's col2im on one thread: every channel's plane in turn.
    fn scatter_planes(cols: &Im2Col, dcol: &[f32], dx: &mut [f32], h: usize, w: usize, n: usize) {
        for (ci, plane) in dx.chunks_mut(h * w).enumerate() {
            cols.scatter_plane(ci, plane, dcol, (h, w, n));
        }
    }

    /// [`scatter_planes`] on the CPU's widest vector unit (its adds vectorise; same bits on
    /// every level).
    dispatch scatter_planes_simd / scatter_planes_at;
}

thread_local! {
    /// This thread's scratch for the fused convolution (one sample's columns and their gradient),
    /// kept between calls at the size of the largest layer seen: every element is written before
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
struct Conv2dGemm {
    cols: Im2Col,
    /// Forces one of the two paths (tests); `None` chooses by the batch and the thread count.
    parallel: Option<bool>,
}

/// Shapes of a [`Conv2dGemm`] call.
#[derive(Debug, Clone, Copy)]
struct ConvDims {
    b: usize,
    c: usize,
    h: usize,
    w: usize,
    out_c: usize,
    /// `C kh kw`: the columns' rows.
    k: usize,
    /// `H_o W_o`: output pixels per channel.
    n: usize,
    ho: usize,
    wo: usize,
}

impl Conv2dGemm {
    fn dims(&self, x: &[usize], weight: &[usize]) -> candle_core::Result<ConvDims> {
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

    /// One sample's output `[out, H_o W_o]` (`col`: a scratch buffer of `k * n`).
    fn forward_sample(
        &self,
        d: &ConvDims,
        (x, weight, bias): (&[f32], &[f32], Option<&[f32]>),
        dst: &mut [f32],
        col: &mut [f32],
        threaded: bool,
    ) -> candle_core::Result<()> {
        let ConvDims {
            h, w, out_c, k, n, ..
        } = *d;
        let col: &[f32] = if self.cols.is_identity() {
            x
        } else {
            self.cols.fill_sample(col, x, (h, w, n), threaded);
            col
        };
        if let Some(bias) = bias {
            for (row, &v) in dst.chunks_mut(n).zip(bias) {
                row.fill(v);
            }
        }
        // computed transposed, outᵀ (N x O) = colᵀ (N x K) · Wᵀ (K x O): the big operand is then
        // column-major, which `gemm` reads in place instead of packing a copy of it
        matmul_into(
            (dst, 1, n),
            (n, out_c, k),
            bias.is_some(),
            (col, 1, n),
            (weight, 1, k),
            threaded,
        )
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
    fn forward_vec(
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
            k,
            n,
            ..
        } = d;
        let mut out = zeros(b * out_c * n);
        let plane = c * h * w;
        if out.is_empty() || plane == 0 {
            return Ok(out);
        }
        if self.samples_in_parallel(&d) {
            out.par_chunks_mut(out_c * n)
                .zip(x.par_chunks(plane))
                .try_for_each(|(dst, xb)| {
                    with_scratch(self.cols.scratch_len(k, n), |col, _| {
                        self.forward_sample(&d, (xb, weight, bias), dst, col, false)
                    })
                })?;
        } else {
            with_scratch(self.cols.scratch_len(k, n), |col, _| {
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
            h, w, out_c, k, n, ..
        } = *d;
        let identity = self.cols.is_identity();
        let col: &[f32] = if identity {
            x
        } else {
            self.cols.fill_sample(col, x, (h, w, n), threaded);
            col
        };
        // dW (O x K) = g (O x N) · colᵀ (N x K): rows of g against rows of col, both in place
        matmul_abt(dw, g, col, (out_c, k, n), threaded)?;
        // dcol (K x N) = Wᵀ (K x O) · g (O x N), transposed as in the forward:
        // dcolᵀ (N x K) = gᵀ (N x O) · W (O x K); a 1x1 convolution's dcol is dx itself
        let dcol_into = |dst: &mut [f32]| {
            matmul_into(
                (dst, 1, n),
                (n, k, out_c),
                false,
                (g, 1, n),
                (weight, k, 1),
                threaded,
            )
        };
        if identity {
            dcol_into(dx)?;
        } else {
            dcol_into(dcol)?;
            self.cols.scatter_sample(dcol, dx, (h, w, n), threaded);
        }
        for (acc, row) in db.iter_mut().zip(g.chunks(n)) {
            *acc = row.iter().sum::<f32>();
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
    fn backward_slices(
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
            let scratch = self.cols.scratch_len(k, n);
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

// ---------------------------------------------------------------------------------------------
// GroupNorm + scale/shift + SiLU

#[derive(Debug, Clone, Copy)]
struct GroupNormAct {
    groups: usize,
    eps: f64,
    silu: bool,
}

/// `(B, C, N)` of a `[B, C, ...]` shape.
fn bcn(shape: &Shape) -> candle_core::Result<(usize, usize, usize)> {
    let d = shape.dims();
    if d.len() < 2 {
        candle_core::bail!("group norm: expected [B, C, ...], got {d:?}")
    }
    Ok((d[0], d[1], d[2..].iter().product()))
}

/// Lanes of the blocked sums below: 8 independent f32 accumulators, which the compiler turns into
/// vector adds (a single running sum cannot be vectorised without reordering it).
const LANES: usize = 8;
/// Elements summed in f32 lanes before they are added to the f64 total.
const BLOCK: usize = 64;

/// `Σ f(x_i)` over `x`: f32 lanes within blocks of [`BLOCK`] elements, f64 across blocks.
#[inline(always)]
fn blocked_sum(x: &[f32], f: impl Fn(f32) -> f32) -> f64 {
    let mut total = 0f64;
    let mut blocks = x.chunks_exact(BLOCK);
    for b in &mut blocks {
        let mut lane = [0f32; LANES];
        for c in b.chunks_exact(LANES) {
            for j in 0..LANES {
                lane[j] += f(c[j]);
            }
        }
        total += lane.iter().map(|v| f64::from(*v)).sum::<f64>();
    }
    total
        + blocks
            .remainder()
            .iter()
            .map(|v| f64::from(f(*v)))
            .sum::<f64>()
}

/// Mean and `1 / sqrt(var + eps)` of a group (two passes; f32 lanes within blocks, f64 across).
fn group_stats(x: &[f32], eps: f64) -> (f32, f32) {
    let n = x.len().max(1) as f64;
    let mean = blocked_sum(x, |v| v) / n;
    let m = mean as f32;
    let var = blocked_sum(x, |v| (v - m) * (v - m)) / n;
    (m, (1.0 / (var + eps).sqrt()) as f32)
}

/// `e^x` in plain f32 arithmetic (no libm call, so the loops around it vectorise): `x = n ln 2 + r`
/// with `|r| <= ln 2 / 2` (Cody-Waite split of ln 2), a degree-6 Taylor polynomial for `e^r`
/// (truncation below 1.3e-7 relative), and `2^n` from its exponent bits. `x` is clamped to
/// `[-87, 88]`, the normal f32 range; NaN stays NaN. A unit test bounds the error against f64.
#[inline(always)]
fn exp_f32(x: f32) -> f32 {
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // 1.5 * 2^23: adding it rounds to an integer, which then sits in the low mantissa bits
    const ROUND: f32 = 12_582_912.0;
    let x = x.clamp(-87.0, 88.0);
    let t = x * std::f32::consts::LOG2_E + ROUND;
    let n = t - ROUND;
    let r = x - n * LN2_HI - n * LN2_LO;
    let p = 1.0
        + r * (1.0
            + r * (0.5
                + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0))))));
    let ni = (t.to_bits() as i32).wrapping_sub(0x4B40_0000);
    p * f32::from_bits(((ni + 127) << 23) as u32)
}

/// The logistic function through [`exp_f32`], for loops that vectorise (the forward pass).
#[inline(always)]
fn sigmoid(z: f32) -> f32 {
    1.0 / (1.0 + exp_f32(-z))
}

multiversion! {
    /// One group of one sample: `out = act(xhat * sc + sh)` for its `sc.len()` channels of `n`.
    fn gn_forward_group(
        out: &mut [f32],
        xs: &[f32],
        sc: &[f32],
        sh: &[f32],
        n: usize,
        eps: f64,
        silu: bool,
    ) {
        let (mean, rstd) = group_stats(xs, eps);
        for ci in 0..sc.len() {
            let a = sc[ci] * rstd;
            let bb = sh[ci] - mean * a;
            let (o, xi) = (&mut out[ci * n..(ci + 1) * n], &xs[ci * n..(ci + 1) * n]);
            if silu {
                for (o, v) in o.iter_mut().zip(xi) {
                    let z = v * a + bb;
                    *o = z * sigmoid(z);
                }
            } else {
                for (o, v) in o.iter_mut().zip(xi) {
                    *o = v * a + bb;
                }
            }
        }
    }

    /// [`gn_forward_group`] on the CPU's widest vector unit.
    dispatch gn_forward_simd / gn_forward_at;
}

/// One channel of the backward pass 1: `d = dxhat` and the sums `[Σ dz xhat, Σ dz, Σ dxhat,
/// Σ dxhat xhat]`, in f32 lanes within blocks of [`BLOCK`] (f64 across blocks) so the loop
/// vectorises.
#[inline(always)]
fn gn_backward_channel<const SILU: bool>(
    d: &mut [f32],
    x: &[f32],
    g: &[f32],
    (mean, rstd): (f32, f32),
    (s, t): (f32, f32),
) -> [f64; 4] {
    #[inline(always)]
    fn elem<const SILU: bool>(
        v: f32,
        g: f32,
        mean: f32,
        rstd: f32,
        s: f32,
        t: f32,
    ) -> (f32, f32, f32) {
        let xh = (v - mean) * rstd;
        let dz = if SILU {
            let z = xh * s + t;
            let sg = sigmoid(z);
            g * sg * (1.0 + z * (1.0 - sg))
        } else {
            g
        };
        (xh, dz, dz * s)
    }
    let mut tot = [0f64; 4];
    let n = d.len();
    let done = n - n % BLOCK;
    for ((db, xb), gb) in d[..done]
        .chunks_exact_mut(BLOCK)
        .zip(x[..done].chunks_exact(BLOCK))
        .zip(g[..done].chunks_exact(BLOCK))
    {
        let (mut l0, mut l1, mut l2, mut l3) =
            ([0f32; LANES], [0f32; LANES], [0f32; LANES], [0f32; LANES]);
        for ((dc, xc), gc) in db
            .chunks_exact_mut(LANES)
            .zip(xb.chunks_exact(LANES))
            .zip(gb.chunks_exact(LANES))
        {
            for j in 0..LANES {
                let (xh, dz, dxh) = elem::<SILU>(xc[j], gc[j], mean, rstd, s, t);
                dc[j] = dxh;
                l0[j] += dz * xh;
                l1[j] += dz;
                l2[j] += dxh;
                l3[j] += dxh * xh;
            }
        }
        for (t, l) in tot.iter_mut().zip([l0, l1, l2, l3]) {
            *t += l.iter().map(|v| f64::from(*v)).sum::<f64>();
        }
    }
    for k in done..n {
        let (xh, dz, dxh) = elem::<SILU>(x[k], g[k], mean, rstd, s, t);
        d[k] = dxh;
        for (t, p) in tot.iter_mut().zip([dz * xh, dz, dxh, dxh * xh]) {
            *t += f64::from(p);
        }
    }
    tot
}

multiversion! {
    /// One group of one sample, backward: `dxs` gets the input gradient, `dsc`/`dsh` the scale and
    /// shift gradients of its channels. Pass 1 ([`gn_backward_channel`]) writes `dxhat` and the
    /// sums; pass 2 turns `dxhat` into `dx`.
    fn gn_backward_group(
        dxs: &mut [f32],
        xs: &[f32],
        gs: &[f32],
        dsc: &mut [f32],
        dsh: &mut [f32],
        scs: &[f32],
        shs: &[f32],
        n: usize,
        eps: f64,
        silu: bool,
    ) {
        let (mean, rstd) = group_stats(xs, eps);
        let (mut sum_d, mut sum_dx) = (0f64, 0f64);
        for ci in 0..scs.len() {
            let r = ci * n..(ci + 1) * n;
            let (d, x, g) = (&mut dxs[r.clone()], &xs[r.clone()], &gs[r]);
            let st = (scs[ci], shs[ci]);
            let tot = if silu {
                gn_backward_channel::<true>(d, x, g, (mean, rstd), st)
            } else {
                gn_backward_channel::<false>(d, x, g, (mean, rstd), st)
            };
            dsc[ci] = tot[0] as f32;
            dsh[ci] = tot[1] as f32;
            sum_d += tot[2];
            sum_dx += tot[3];
        }
        // pass 2: dx = rstd (dxhat - mean(dxhat) - xhat mean(dxhat xhat))
        let m = xs.len().max(1) as f64;
        let (md, mdx) = ((sum_d / m) as f32, (sum_dx / m) as f32);
        for (d, v) in dxs.iter_mut().zip(xs) {
            let xh = (v - mean) * rstd;
            *d = rstd * (*d - md - xh * mdx);
        }
    }

    /// [`gn_backward_group`] on the CPU's widest vector unit.
    dispatch gn_backward_simd / gn_backward_at;
}

impl GroupNormAct {
    /// `act(GroupNorm(x) * scale + shift)` of `x: [B, C, N]` (contiguous) with `scale`, `shift:
    /// [B, C]`, `C` divisible by the group count; groups of all samples in parallel.
    fn forward_slices(
        &self,
        x: &[f32],
        scale: &[f32],
        shift: &[f32],
        (c, n): (usize, usize),
    ) -> Vec<f32> {
        let cg = c / self.groups;
        let mut dst = zeros(x.len());
        if cg * n > 0 {
            dst.par_chunks_mut(cg * n)
                .zip(x.par_chunks(cg * n))
                .zip(scale.par_chunks(cg).zip(shift.par_chunks(cg)))
                .for_each(|((out, xs), (sc, sh))| {
                    gn_forward_simd(out, xs, sc, sh, n, self.eps, self.silu)
                });
        }
        dst
    }

    /// Gradients `(dx, dscale, dshift)` of [`Self::forward_slices`] for the output gradient `g`.
    fn backward_slices(
        &self,
        x: &[f32],
        scale: &[f32],
        shift: &[f32],
        g: &[f32],
        (c, n): (usize, usize),
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let cg = c / self.groups;
        let mut dx = zeros(x.len());
        let mut dscale = vec![0f32; scale.len()];
        let mut dshift = vec![0f32; shift.len()];
        if cg * n > 0 {
            dx.par_chunks_mut(cg * n)
                .zip(x.par_chunks(cg * n).zip(g.par_chunks(cg * n)))
                .zip(dscale.par_chunks_mut(cg).zip(dshift.par_chunks_mut(cg)))
                .zip(scale.par_chunks(cg).zip(shift.par_chunks(cg)))
                .for_each(|(((dxs, (xs, gs)), (dsc, dsh)), (scs, shs))| {
                    gn_backward_simd(dxs, xs, gs, dsc, dsh, scs, shs, n, self.eps, self.silu)
                });
        }
        (dx, dscale, dshift)
    }

    fn check(
        &self,
        (b, c, _): (usize, usize, usize),
        l2: &Layout,
        l3: &Layout,
    ) -> candle_core::Result<()> {
        if self.groups == 0 || !c.is_multiple_of(self.groups) {
            candle_core::bail!("group norm: {c} channels in {} groups", self.groups)
        }
        if l2.shape().dims() != [b, c] || l3.shape().dims() != [b, c] {
            candle_core::bail!(
                "group norm: scale {:?} and shift {:?} must be [{b}, {c}]",
                l2.shape(),
                l3.shape()
            )
        }
        Ok(())
    }
}

impl CustomOp3 for GroupNormAct {
    fn name(&self) -> &'static str {
        "veila-group-norm-act"
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
        let (b, c, n) = bcn(l1.shape())?;
        self.check((b, c, n), l2, l3)?;
        let x = slice_f32(s1, l1, "group norm input")?;
        let scale = slice_f32(s2, l2, "group norm scale")?;
        let shift = slice_f32(s3, l3, "group norm shift")?;
        let dst = self.forward_slices(x, scale, shift, (c, n));
        Ok((CpuStorage::F32(dst), l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        scale: &Tensor,
        shift: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (b, c, n) = bcn(x.shape())?;
        let sc = tensor_f32(scale, "group norm scale")?;
        let sh = tensor_f32(shift, "group norm shift")?;
        let (dx, dscale, dshift) = with_f32(x, "group norm input", |xv| {
            with_f32(grad, "group norm gradient", |gv| {
                Ok(self.backward_slices(xv, &sc, &sh, gv, (c, n)))
            })
        })?;
        let dev = x.device();
        Ok((
            Some(Tensor::from_vec(dx, x.shape(), dev)?),
            Some(Tensor::from_vec(dscale, (b, c), dev)?),
            Some(Tensor::from_vec(dshift, (b, c), dev)?),
        ))
    }
}

/// `act(GroupNorm(x) * scale + shift)` for `x: [B, C, ...]`, per-sample, per-channel `scale` and
/// `shift` (`[B, C]`), `groups` groups, variance epsilon `eps`, `act` SiLU when `silu` (identity
/// otherwise). GroupNorm itself has no affine weights here: fold them into `scale` and `shift`.
pub fn group_norm_act(
    x: &Tensor,
    scale: &Tensor,
    shift: &Tensor,
    groups: usize,
    eps: f64,
    silu: bool,
) -> Result<Tensor> {
    let dims = x.dims();
    if dims.len() < 2 || groups == 0 || !dims[1].is_multiple_of(groups) {
        return Err(shape_err(
            "group norm input",
            format!("[B, C, ...] with C divisible by {groups}"),
            dims,
        ));
    }
    let bc = [dims[0], dims[1]];
    if scale.dims() != bc || shift.dims() != bc {
        return Err(shape_err(
            "group norm scale/shift",
            format!("{bc:?}"),
            scale.dims(),
        ));
    }
    if is_half(x.dtype()) {
        // statistics of half-precision activations in f32, the result back in their dtype
        let f = |t: &Tensor| t.to_dtype(DType::F32);
        let y = group_norm_act(&f(x)?, &f(scale)?, &f(shift)?, groups, eps, silu)?;
        return Ok(y.to_dtype(x.dtype())?);
    }
    let (scale, shift) = (&scale.to_dtype(x.dtype())?, &shift.to_dtype(x.dtype())?);
    if on_cpu_f32(x) && on_cpu_f32(scale) && on_cpu_f32(shift) {
        return Ok(x.contiguous()?.apply_op3(
            &scale.contiguous()?,
            &shift.contiguous()?,
            GroupNormAct { groups, eps, silu },
        )?);
    }
    group_norm_act_reference(x, scale, shift, groups, eps, silu)
}

/// [`group_norm_act`] from candle ops (the formula of `candle_nn::GroupNorm`): any device.
pub fn group_norm_act_reference(
    x: &Tensor,
    scale: &Tensor,
    shift: &Tensor,
    groups: usize,
    eps: f64,
    silu: bool,
) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let (b, c) = (dims[0], dims[1]);
    let xr = x.reshape((b, groups, ()))?;
    let m = xr.dim(2)? as f64;
    let mean = (xr.sum_keepdim(2)? / m)?;
    let xc = xr.broadcast_sub(&mean)?;
    let var = (xc.sqr()?.sum_keepdim(2)? / m)?;
    let xn = xc
        .broadcast_div(&(var + eps)?.sqrt()?)?
        .reshape(dims.as_slice())?;
    let mut bshape = vec![1; dims.len()];
    bshape[0] = b;
    bshape[1] = c;
    let y = xn
        .broadcast_mul(&scale.reshape(bshape.as_slice())?)?
        .broadcast_add(&shift.reshape(bshape.as_slice())?)?;
    Ok(if silu { candle_nn::ops::silu(&y)? } else { y })
}

// ---------------------------------------------------------------------------------------------
// scaled residual sum

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
    Ok(((a + b)? * scale)?)
}

// ---------------------------------------------------------------------------------------------
// residual block

/// The parameters of one [`res_block`] call, as the block's layers hold them.
#[derive(Debug, Clone, Copy)]
pub struct ResBlockParams<'a> {
    /// GroupNorm 1's per-sample scale and shift, `[B, C_in]` each (its affine weights folded in).
    pub norm1: (&'a Tensor, &'a Tensor),
    /// Convolution 1: weights `[C_out, C_in, k, k]` and bias `[C_out]`.
    pub conv1: (&'a Tensor, Option<&'a Tensor>),
    /// GroupNorm 2's per-sample scale and shift, `[B, C_out]` each (time modulation folded in).
    pub norm2: (&'a Tensor, &'a Tensor),
    /// Convolution 2: weights `[C_out, C_out, k, k]` and bias `[C_out]`.
    pub conv2: (&'a Tensor, Option<&'a Tensor>),
    /// The skip's 1x1 convolution `[C_out, C_in, 1, 1]` and bias, when the channel count changes.
    pub skip: Option<(&'a Tensor, Option<&'a Tensor>)>,
}

/// Group counts, epsilon, residual scale and convolution geometry of one [`res_block`].
#[derive(Debug, Clone, Copy)]
pub struct ResBlockSpec {
    /// GroupNorm 1's group count (divides `C_in`).
    pub groups1: usize,
    /// GroupNorm 2's group count (divides `C_out`).
    pub groups2: usize,
    /// Both GroupNorms' variance epsilon.
    pub eps: f64,
    /// Factor on the residual sum.
    pub scale: f64,
    /// Both convolutions' padding and stride (the kernel comes from the weights; stride 1 and
    /// size-preserving padding, so the skip adds up).
    pub conv: Im2ColSpec,
}

/// What the forward pass of [`ResBlockOp`] keeps for its backward pass.
struct ResBlockSaved {
    /// `SiLU(GN1(x))`, convolution 1's input.
    a1: Vec<f32>,
    /// Convolution 1's output, GroupNorm 2's input.
    h1: Vec<f32>,
    /// `SiLU(GN2(h1))`, convolution 2's input.
    a2: Vec<f32>,
}

/// A residual block as one op: `(skip(x) + conv2(SiLU(GN2(conv1(SiLU(GN1(x))))))) * scale`, from
/// the kernels above, with the small per-sample and weight tensors packed into two flat inputs.
/// candle's backward pass zero-fills and adds a gradient for every edge of its graph; as one node
/// the block has one such edge instead of six, and its intermediate activations live here.
struct ResBlockOp {
    spec: ResBlockSpec,
    /// `(C_in, C_out, k)`.
    channels: (usize, usize, usize),
    conv: Conv2dGemm,
    skip: Option<Conv2dGemm>,
    /// Which of conv 1, conv 2 and the skip have a bias.
    biases: [bool; 3],
    saved: std::sync::Mutex<Option<ResBlockSaved>>,
}

/// Offsets of the packed weights: `[w1, b1?, w2, b2?, ws?, bs?]`.
struct ResBlockLayout {
    w1: std::ops::Range<usize>,
    b1: Option<std::ops::Range<usize>>,
    w2: std::ops::Range<usize>,
    b2: Option<std::ops::Range<usize>>,
    ws: Option<std::ops::Range<usize>>,
    bs: Option<std::ops::Range<usize>>,
    len: usize,
}

impl ResBlockOp {
    fn layout(&self) -> ResBlockLayout {
        let (ci, co, k) = self.channels;
        let mut at = 0;
        let mut take = |len: usize| {
            let r = at..at + len;
            at += len;
            r
        };
        let w1 = take(co * ci * k * k);
        let b1 = self.biases[0].then(|| take(co));
        let w2 = take(co * co * k * k);
        let b2 = self.biases[1].then(|| take(co));
        let ws = self.skip.map(|_| take(co * ci));
        let bs = (self.skip.is_some() && self.biases[2]).then(|| take(co));
        ResBlockLayout {
            w1,
            b1,
            w2,
            b2,
            ws,
            bs,
            len: at,
        }
    }

    /// `(B, H, W)` of the input, checked against the packed inputs' lengths.
    fn check(
        &self,
        x: &[usize],
        small: usize,
        weights: usize,
    ) -> candle_core::Result<(usize, usize, usize)> {
        let (ci, co, _) = self.channels;
        let &[b, c, h, w] = x else {
            candle_core::bail!("residual block: input {x:?} is not 4-d")
        };
        if c != ci || small != 2 * b * (ci + co) || weights != self.layout().len {
            candle_core::bail!(
                "residual block: input {x:?}, {small} per-sample and {weights} weight values for {:?}",
                self.channels
            )
        }
        Ok((b, h, w))
    }

    fn conv_dims(
        &self,
        (b, h, w): (usize, usize, usize),
    ) -> candle_core::Result<(ConvDims, ConvDims, Option<ConvDims>)> {
        let (ci, co, k) = self.channels;
        let d1 = self.conv.dims(&[b, ci, h, w], &[co, ci, k, k])?;
        let d2 = self.conv.dims(&[b, co, h, w], &[co, co, k, k])?;
        let ds = self
            .skip
            .map(|s| s.dims(&[b, ci, h, w], &[co, ci, 1, 1]))
            .transpose()?;
        if (d1.ho, d1.wo) != (h, w) {
            candle_core::bail!(
                "residual block: {:?} changes the size {h}x{w}",
                self.spec.conv
            )
        }
        Ok((d1, d2, ds))
    }

    fn norm(&self, groups: usize) -> GroupNormAct {
        GroupNormAct {
            groups,
            eps: self.spec.eps,
            silu: true,
        }
    }
}

impl CustomOp3 for ResBlockOp {
    fn name(&self) -> &'static str {
        "veila-res-block"
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
        let x = slice_f32(s1, l1, "residual block input")?;
        let small = slice_f32(s2, l2, "residual block norms")?;
        let wts = slice_f32(s3, l3, "residual block weights")?;
        let (b, h, w) = self.check(l1.dims(), small.len(), wts.len())?;
        let (ci, co, _) = self.channels;
        let (d1, d2, ds) = self.conv_dims((b, h, w))?;
        let n = h * w;
        let lay = self.layout();
        let (sc1, rest) = small.split_at(b * ci);
        let (sh1, rest) = rest.split_at(b * ci);
        let (sc2, sh2) = rest.split_at(b * co);
        let a1 = self
            .norm(self.spec.groups1)
            .forward_slices(x, sc1, sh1, (ci, n));
        let h1 = self
            .conv
            .forward_vec(d1, &a1, &wts[lay.w1], lay.b1.map(|r| &wts[r]))?;
        let a2 = self
            .norm(self.spec.groups2)
            .forward_slices(&h1, sc2, sh2, (co, n));
        let mut out = self
            .conv
            .forward_vec(d2, &a2, &wts[lay.w2], lay.b2.map(|r| &wts[r]))?;
        let skip = match (self.skip, ds, lay.ws) {
            (Some(conv), Some(d), Some(ws)) => {
                Some(conv.forward_vec(d, x, &wts[ws], lay.bs.map(|r| &wts[r]))?)
            }
            _ => None,
        };
        let skip: &[f32] = skip.as_deref().unwrap_or(x);
        let s = self.spec.scale as f32;
        out.par_chunks_mut(GRAIN)
            .zip(skip.par_chunks(GRAIN))
            .for_each(|(o, k)| {
                for (o, k) in o.iter_mut().zip(k) {
                    *o = (k + *o) * s;
                }
            });
        *self
            .saved
            .lock()
            .map_err(|_| candle_core::Error::Msg("residual block: poisoned".into()))? =
            Some(ResBlockSaved { a1, h1, a2 });
        Ok((CpuStorage::F32(out), Shape::from((b, co, h, w))))
    }

    fn bwd(
        &self,
        x: &Tensor,
        small: &Tensor,
        weights: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let guard = self
            .saved
            .lock()
            .map_err(|_| candle_core::Error::Msg("residual block: poisoned".into()))?;
        let Some(saved) = guard.as_ref() else {
            candle_core::bail!("residual block: backward pass before a forward pass")
        };
        let (b, h, w) = self.check(x.dims(), small.elem_count(), weights.elem_count())?;
        let (ci, co, _) = self.channels;
        let (d1, d2, ds) = self.conv_dims((b, h, w))?;
        let n = h * w;
        let lay = self.layout();
        let sm = tensor_f32(small, "residual block norms")?;
        let wts = tensor_f32(weights, "residual block weights")?;
        let (sc1, rest) = sm.split_at(b * ci);
        let (sh1, rest) = rest.split_at(b * ci);
        let (sc2, sh2) = rest.split_at(b * co);
        let s = self.spec.scale as f32;
        let (dx, dsmall, dw) = with_f32(x, "residual block input", |xs| {
            with_f32(grad, "residual block gradient", |g| {
                // both branches of the sum get g * scale
                let gs = scaled(g, s);
                let mut dw = vec![0f32; lay.len];
                // a convolution's weight and bias gradients into their places in `dw`
                let mut put = |w: std::ops::Range<usize>,
                               b: Option<std::ops::Range<usize>>,
                               (dwv, dbv): (Vec<f32>, Vec<f32>)| {
                    dw[w].copy_from_slice(&dwv);
                    if let Some(r) = b {
                        dw[r].copy_from_slice(&dbv);
                    }
                };
                let (da2, dw2, db2) =
                    self.conv
                        .backward_slices(&d2, &saved.a2, &wts[lay.w2.clone()], &gs)?;
                put(lay.w2.clone(), lay.b2.clone(), (dw2, db2));
                let (dh1, dsc2, dsh2) = self.norm(self.spec.groups2).backward_slices(
                    &saved.h1,
                    sc2,
                    sh2,
                    &da2,
                    (co, n),
                );
                let (da1, dw1, db1) =
                    self.conv
                        .backward_slices(&d1, &saved.a1, &wts[lay.w1.clone()], &dh1)?;
                put(lay.w1.clone(), lay.b1.clone(), (dw1, db1));
                let (mut dx, dsc1, dsh1) =
                    self.norm(self.spec.groups1)
                        .backward_slices(xs, sc1, sh1, &da1, (ci, n));
                // the skip's share of dx
                match (self.skip, ds, lay.ws.clone()) {
                    (Some(conv), Some(d), Some(r)) => {
                        let (dxs, dws, dbs) = conv.backward_slices(&d, xs, &wts[r.clone()], &gs)?;
                        put(r, lay.bs.clone(), (dws, dbs));
                        add_into(&mut dx, &dxs);
                    }
                    _ => add_into(&mut dx, &gs),
                }
                let dsmall = [dsc1, dsh1, dsc2, dsh2].concat();
                Ok((dx, dsmall, dw))
            })
        })?;
        let dev = x.device();
        Ok((
            Some(Tensor::from_vec(dx, x.shape(), dev)?),
            Some(Tensor::from_vec(dsmall, small.shape(), dev)?),
            Some(Tensor::from_vec(dw, weights.shape(), dev)?),
        ))
    }
}

/// `a * s`, collected over the rayon pool.
fn scaled(a: &[f32], s: f32) -> Vec<f32> {
    a.par_iter().with_min_len(GRAIN).map(|v| v * s).collect()
}

/// `acc += v`, elementwise over the rayon pool.
fn add_into(acc: &mut [f32], v: &[f32]) {
    acc.par_chunks_mut(GRAIN)
        .zip(v.par_chunks(GRAIN))
        .for_each(|(a, v)| {
            for (a, v) in a.iter_mut().zip(v) {
                *a += v;
            }
        });
}

/// A residual block `(skip(x) + conv2(SiLU(GN2(conv1(SiLU(GN1(x))))))) * scale` as one op on CPU
/// f32 tensors (`skip` is a 1x1 convolution when given, the identity otherwise); `None` when a
/// tensor is not CPU f32 or the kernels are off (then compose the layers instead). The GroupNorms'
/// scales and shifts are per sample (`[B, C]`), with their affine weights and any modulation
/// folded in, as in [`group_norm_act`]. Same arithmetic as that composition, kernel for kernel.
pub fn res_block(x: &Tensor, p: ResBlockParams<'_>, spec: ResBlockSpec) -> Result<Option<Tensor>> {
    let mut all = vec![
        x, p.norm1.0, p.norm1.1, p.norm2.0, p.norm2.1, p.conv1.0, p.conv2.0,
    ];
    all.extend(p.conv1.1);
    all.extend(p.conv2.1);
    if let Some((w, b)) = p.skip {
        all.push(w);
        all.extend(b);
    }
    if !all.iter().all(|t| on_cpu_f32(t)) {
        return Ok(None);
    }
    let (b, ci, _, _) = x.dims4()?;
    let (co, wc, kh, kw) = p.conv1.0.dims4()?;
    if wc != ci || kh != kw || p.conv2.0.dims() != [co, co, kh, kw] {
        return Err(shape_err(
            "residual block weights",
            format!("[C_out, {ci}, k, k] and [C_out, C_out, k, k]"),
            p.conv1.0.dims(),
        ));
    }
    if spec.groups1 == 0
        || spec.groups2 == 0
        || !ci.is_multiple_of(spec.groups1)
        || !co.is_multiple_of(spec.groups2)
    {
        return Err(shape_err(
            "residual block input",
            format!(
                "channels divisible by {} and {}",
                spec.groups1, spec.groups2
            ),
            x.dims(),
        ));
    }
    for (t, want) in [
        (p.norm1.0, [b, ci]),
        (p.norm1.1, [b, ci]),
        (p.norm2.0, [b, co]),
        (p.norm2.1, [b, co]),
    ] {
        if t.dims() != want {
            return Err(shape_err(
                "residual block scale/shift",
                format!("{want:?}"),
                t.dims(),
            ));
        }
    }
    for bias in [p.conv1.1, p.conv2.1, p.skip.and_then(|s| s.1)]
        .into_iter()
        .flatten()
    {
        if bias.dims() != [co] {
            return Err(shape_err(
                "residual block bias",
                format!("[{co}]"),
                bias.dims(),
            ));
        }
    }
    match p.skip {
        Some((sw, _)) if sw.dims() != [co, ci, 1, 1] => {
            return Err(shape_err(
                "residual block skip",
                format!("[{co}, {ci}, 1, 1]"),
                sw.dims(),
            ));
        }
        None if ci != co => {
            return Err(shape_err(
                "residual block skip",
                format!("a [{co}, {ci}, 1, 1] projection"),
                &[],
            ));
        }
        _ => {}
    }
    let flat = |t: &Tensor| t.flatten_all();
    let small = Tensor::cat(
        &[
            flat(p.norm1.0)?,
            flat(p.norm1.1)?,
            flat(p.norm2.0)?,
            flat(p.norm2.1)?,
        ],
        0,
    )?;
    let mut parts = vec![flat(p.conv1.0)?];
    parts.extend(p.conv1.1.cloned());
    parts.push(flat(p.conv2.0)?);
    parts.extend(p.conv2.1.cloned());
    if let Some((sw, sb)) = p.skip {
        parts.push(flat(sw)?);
        parts.extend(sb.cloned());
    }
    let weights = Tensor::cat(&parts, 0)?;
    let op = ResBlockOp {
        spec,
        channels: (ci, co, kh),
        conv: Conv2dGemm {
            cols: Im2Col {
                spec: Im2ColSpec {
                    kernel: (kh, kw),
                    ones_row: false,
                    ..spec.conv
                },
            },
            parallel: None,
        },
        skip: p.skip.map(|_| Conv2dGemm {
            cols: Im2Col {
                spec: Im2ColSpec::POINTWISE,
            },
            parallel: None,
        }),
        biases: [
            p.conv1.1.is_some(),
            p.conv2.1.is_some(),
            p.skip.is_some_and(|s| s.1.is_some()),
        ],
        saved: std::sync::Mutex::new(None),
    };
    Ok(Some(x.contiguous()?.apply_op3(&small, &weights, op)?))
}

// ---------------------------------------------------------------------------------------------
// nearest-neighbour upsampling

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

#[cfg(test)]
mod exp_tests {
    use super::exp_f32;

    #[test]
    fn exp_f32_is_within_3e7_of_f64_exp_over_the_f32_range() {
        let mut worst = 0f64;
        let mut x = -87.0f32;
        while x <= 88.0 {
            let want = f64::from(x).exp();
            let got = f64::from(exp_f32(x));
            worst = worst.max(((got - want) / want).abs());
            x += 0.000_37 * (1.0 + x.abs());
        }
        assert!(worst < 3e-7, "max relative error {worst:e}");
        assert_eq!(exp_f32(0.0), 1.0);
        assert!(exp_f32(f32::NAN).is_nan());
        // clamped, not overflowing or flushing to zero
        assert!(exp_f32(1000.0).is_finite() && exp_f32(-1000.0) > 0.0);
    }
}

#[cfg(test)]
mod tests {
    use candle_core::Device;

    use super::*;

    /// A fixed pattern of `n` values in about [-1, 1].
    fn pattern(n: usize, f: f32) -> Vec<f32> {
        (0..n).map(|i| (i as f32 * f).sin()).collect()
    }

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

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn group_norm_kernels_give_the_same_bits_on_every_vector_unit() {
        // the kernels inlined into AVX-512 / AVX2 functions against the baseline build: same
        // operations in the same order, so the same bits (on a CPU without these units the
        // wider paths are skipped)
        // 2 channels of 203 values: 3 whole blocks and a remainder
        let (cg, n) = (2, 203);
        let x = pattern(cg * n, 0.37);
        let g = pattern(cg * n, 0.53);
        let (sc, sh) = (vec![1.3f32, 0.7], vec![-0.2f32, 0.4]);
        for silu in [true, false] {
            let run = |level: SimdLevel| -> Vec<f32> {
                let mut out = vec![0f32; cg * n];
                let mut dx = vec![0f32; cg * n];
                let (mut dsc, mut dsh) = (vec![0f32; cg], vec![0f32; cg]);
                gn_forward_at(level, &mut out, &x, &sc, &sh, n, 1e-5, silu);
                gn_backward_at(
                    level, &mut dx, &x, &g, &mut dsc, &mut dsh, &sc, &sh, n, 1e-5, silu,
                );
                [out, dx, dsc, dsh].concat()
            };
            let base = run(SimdLevel::Baseline);
            assert!(base.iter().all(|v| v.is_finite()) && base.iter().any(|v| *v != 0.0));
            #[cfg(target_arch = "x86_64")]
            {
                let same =
                    |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(p, q)| p.to_bits() == q.to_bits());
                if std::arch::is_x86_feature_detected!("avx2") {
                    let wide = run(SimdLevel::Avx2);
                    assert!(same(&base, &wide), "AVX2 path differs (silu {silu})");
                }
                if std::arch::is_x86_feature_detected!("avx512f")
                    && std::arch::is_x86_feature_detected!("avx2")
                {
                    let wide = run(SimdLevel::Avx512);
                    assert!(same(&base, &wide), "AVX-512 path differs (silu {silu})");
                }
            }
        }
    }

    #[test]
    fn matmul_abt_matches_an_f64_reference_on_every_vector_unit() {
        // whole 4 x 3 blocks, partial blocks in both directions, rows with a lane remainder
        for (m, nb, len) in [(8, 9, 64), (6, 7, 37), (1, 1, 5), (16, 144, 1000)] {
            let a = pattern(m * len, 0.37);
            let b = pattern(nb * len, 0.11);
            let want: Vec<f64> = (0..m * nb)
                .map(|ij| {
                    let (i, j) = (ij / nb, ij % nb);
                    (0..len)
                        .map(|p| f64::from(a[i * len + p]) * f64::from(b[j * len + p]))
                        .sum()
                })
                .collect();
            let scale = want.iter().fold(0f64, |s, v| s.max(v.abs())).max(1.0);
            let check = |got: &[f32], what: &str| {
                for (g, w) in got.iter().zip(&want) {
                    assert!(
                        (f64::from(*g) - w).abs() <= 1e-5 * scale,
                        "{what} {m}x{nb}x{len}: {g} against {w}"
                    );
                }
            };
            for threaded in [false, true] {
                let mut dst = vec![f32::NAN; m * nb];
                matmul_abt(&mut dst, &a, &b, (m, nb, len), threaded).unwrap();
                check(&dst, "dispatched");
            }
            let mut scalar = vec![f32::NAN; m * nb];
            pulp::Simd::vectorize(
                pulp::Scalar::new(),
                Abt {
                    dst: &mut scalar,
                    a: &a,
                    b: &b,
                    m,
                    nb,
                    len,
                },
            );
            check(&scalar, "scalar");
        }
        let mut small = vec![0f32; 4];
        assert!(matmul_abt(&mut small, &[0.0; 3], &[0.0; 6], (2, 2, 3), false).is_err());
    }
}
