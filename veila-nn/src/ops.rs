//! Low-level tensor operations shared by the denoiser blocks.
//!
//! Everything here works on candle tensors, is differentiable (built from ops candle can backpropagate
//! through) and runs on any device.

use candle_core::{D, DType, Device, Tensor};
use candle_nn::{Init, VarBuilder};

use crate::error::{Result, shape_err};
pub use crate::fused::{Im2ColSpec, im2col};

/// Pads `[B, C, H, W]` by `pad_w` columns on each side *circularly* (the azimuth axis wraps around a
/// spinning LiDAR) and by `pad_h` rows of zeros on top and bottom (the vertical field of view does not
/// wrap).
///
/// Built from `narrow` + `cat`, so it backpropagates. `pad_w` may not exceed `W`.
pub fn ring_pad(x: &Tensor, pad_h: usize, pad_w: usize) -> Result<Tensor> {
    let (_, _, _, w) = x.dims4()?;
    let x = if pad_w > 0 {
        if pad_w > w {
            return Err(shape_err(
                "ring_pad input",
                format!("width >= {pad_w} (the circular padding)"),
                x.dims(),
            ));
        }
        let left = x.narrow(3, w - pad_w, pad_w)?;
        let right = x.narrow(3, 0, pad_w)?;
        Tensor::cat(&[&left, x, &right], 3)?
    } else {
        x.clone()
    };
    Ok(if pad_h > 0 {
        x.pad_with_zeros(2, pad_h, pad_h)?
    } else {
        x
    })
}

/// A 2-D convolution whose input is padded with [`ring_pad`] (circular in W, zeros in H), followed by a
/// convolution with padding 0. Weights `weight: [out, in, k, k]` and `bias: [out]`, as `candle_nn::Conv2d`.
#[derive(Debug, Clone)]
pub struct RingConv2d {
    weight: Tensor,
    bias: Option<Tensor>,
    kernel: usize,
    stride: usize,
    span: tracing::Span,
}

impl RingConv2d {
    /// A `k x k` convolution (k odd) with the candle default initialisation (Kaiming normal weights,
    /// uniform bias), weights under `vb` as `weight` and `bias`.
    pub fn new(
        in_c: usize,
        out_c: usize,
        kernel: usize,
        stride: usize,
        vb: VarBuilder<'_>,
    ) -> Result<Self> {
        let ws = vb.get_with_hints(
            (out_c, in_c, kernel, kernel),
            "weight",
            candle_nn::init::DEFAULT_KAIMING_NORMAL,
        )?;
        let bound = 1.0 / ((in_c * kernel * kernel) as f64).sqrt();
        let bs = vb.get_with_hints(
            out_c,
            "bias",
            Init::Uniform {
                lo: -bound,
                up: bound,
            },
        )?;
        Self::from_weights(ws, Some(bs), stride)
    }

    /// Builds from explicit weights (`[out, in, k, k]`, `k` odd).
    pub fn from_weights(weight: Tensor, bias: Option<Tensor>, stride: usize) -> Result<Self> {
        let (_, _, kh, kw) = weight.dims4()?;
        if kh != kw || kh % 2 == 0 || stride == 0 {
            return Err(shape_err(
                "ring conv weight",
                "[out, in, k, k] with odd k and stride >= 1",
                weight.dims(),
            ));
        }
        Ok(Self {
            weight,
            bias,
            kernel: kh,
            stride,
            span: tracing::span!(tracing::Level::TRACE, "ring_conv"),
        })
    }

    /// Weights `[out, in, k, k]` and bias `[out]`.
    pub(crate) fn weights(&self) -> (&Tensor, Option<&Tensor>) {
        (&self.weight, self.bias.as_ref())
    }

    /// The im2col geometry of [`Self::forward`] (ring padding in width, zeros in height).
    pub(crate) fn spec(&self) -> Im2ColSpec {
        let p = self.kernel / 2;
        Im2ColSpec {
            kernel: (self.kernel, self.kernel),
            stride: (self.stride, self.stride),
            pad_h: p,
            pad_w: p,
            ring: true,
            ones_row: false,
        }
    }

    /// `[B, in, H, W] -> [B, out, ceil(H/stride), ceil(W/stride)]` (for odd kernels).
    ///
    /// Runs as one im2col ([`crate::fused::im2col`], padding included) and one matrix product.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let _enter = self.span.enter();
        conv2d_im2col(x, &self.weight, self.bias.as_ref(), self.spec())
    }
}

/// Every `stride`-th of `n` entries along `dim`, starting at `start`: `t[.., start + stride * i, ..]`
/// for `i < n` (entries past the end read as zero). Built from `narrow`, `pad_with_zeros` and
/// `reshape`, so it backpropagates.
fn strided_narrow(t: &Tensor, dim: usize, start: usize, n: usize, stride: usize) -> Result<Tensor> {
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

/// A `k x k` convolution with no further padding of the already padded input `xp: [B, C, Hp, Wp]`
/// (weights `[out, C, k, k]`, bias `[out]`), output `[B, out, (Hp - k) / stride + 1, (Wp - k) / stride + 1]`.
///
/// Runs as an explicit im2col (`k^2` shifted, strided views concatenated along channels) and one
/// matrix product. Its backward pass is made of slices, concatenations and matrix products, which is
/// an order of magnitude faster on the CPU than candle's `conv2d` backward (a naive transposed
/// convolution); the forward pass is about twice as fast as candle's CPU `conv2d` too.
pub fn conv2d_padded(
    xp: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    stride: usize,
) -> Result<Tensor> {
    conv2d_padded_hw(xp, weight, bias, stride, stride)
}

/// [`conv2d_padded`] with separate row and column strides (RangeNet++ downsamples columns only),
/// output `[B, out, (Hp - k) / stride_h + 1, (Wp - k) / stride_w + 1]`.
pub fn conv2d_padded_hw(
    xp: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    stride_h: usize,
    stride_w: usize,
) -> Result<Tensor> {
    let (b, c, hp, wp) = xp.dims4()?;
    let (out_c, wc, kh, kw) = weight.dims4()?;
    if wc != c || kh > hp || kw > wp || stride_h == 0 || stride_w == 0 {
        return Err(shape_err(
            "conv2d_padded input",
            format!("[B, {wc}, >= {kh}, >= {kw}] (strides {stride_h} x {stride_w} >= 1)"),
            xp.dims(),
        ));
    }
    let ho = (hp - kh) / stride_h + 1;
    let wo = (wp - kw) / stride_w + 1;
    let y = if kh == 1 && kw == 1 {
        let xs = strided_narrow(&strided_narrow(xp, 2, 0, ho, stride_h)?, 3, 0, wo, stride_w)?;
        // the weights in the activations' dtype; add_bias takes the bias as it is
        let wm = weight.to_dtype(xp.dtype())?.reshape((1, out_c, c))?;
        wm.broadcast_matmul(&xs.reshape((b, c, ho * wo))?)?
            .reshape((b, out_c, ho, wo))?
    } else {
        return conv2d_im2col(
            xp,
            weight,
            bias,
            Im2ColSpec {
                kernel: (kh, kw),
                stride: (stride_h, stride_w),
                pad_h: 0,
                pad_w: 0,
                ring: false,
                ones_row: false,
            },
        );
    };
    Ok(match bias {
        Some(bias) => add_bias(&y, &bias.reshape((1, bias.dim(0)?, 1, 1))?)?,
        None => y,
    })
}

/// `y + bias` (broadcast) in `y`'s dtype. For half-precision `y` the sum runs in f32, so that the
/// bias gradient (a sum over every position of the batch) is accumulated in f32 rather than in
/// 8 significant bits.
pub fn add_bias(y: &Tensor, bias: &Tensor) -> Result<Tensor> {
    if crate::fused::is_half(y.dtype()) {
        let sum = y
            .to_dtype(DType::F32)?
            .broadcast_add(&bias.to_dtype(DType::F32)?)?;
        return Ok(sum.to_dtype(y.dtype())?);
    }
    Ok(y.broadcast_add(&bias.to_dtype(y.dtype())?)?)
}

/// A zero-padded convolution through [`conv2d_padded`]: the same result as candle's
/// `x.conv2d(weight, padding, stride, 1, 1)` (+ bias), with a fast backward pass.
pub fn conv2d_zero_pad(
    x: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    padding: usize,
    stride: usize,
) -> Result<Tensor> {
    let (_, _, kh, kw) = weight.dims4()?;
    if kh == 1 && kw == 1 && padding == 0 {
        return conv2d_padded(x, weight, bias, stride);
    }
    conv2d_im2col(
        x,
        weight,
        bias,
        Im2ColSpec {
            kernel: (kh, kw),
            stride: (stride, stride),
            pad_h: padding,
            pad_w: padding,
            ring: false,
            ones_row: false,
        },
    )
}

/// A `kh x kw` convolution of `x: [B, C, H, W]` (weights `[out, C, kh, kw]`, bias `[out]`) with the
/// padding and strides of `spec`: [`crate::fused::conv2d`] (one op on the CPU: the columns of one
/// sample at a time and one matrix product each, forward and backward; im2col and a matrix product
/// elsewhere). `spec.kernel` and `spec.ones_row` are taken from the weights and the bias.
///
/// Where the CPU kernels do not run (GPUs, half precision) and a graph is being built, the im2col
/// composition is one node recomputed in the backward pass a tile of output rows at a time (a
/// tile's columns at most 4 Mi values, [`conv2d_lean_tiles`]): the graph keeps the input and the
/// output, not the columns (about `27 C N` values per 3x3 convolution otherwise).
pub fn conv2d_im2col(
    x: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    spec: Im2ColSpec,
) -> Result<Tensor> {
    if crate::fused::takes_kernels(x) {
        return crate::fused::conv2d(x, weight, bias, spec);
    }
    let tracked = x.track_op() || weight.track_op() || bias.is_some_and(Tensor::track_op);
    if tracked {
        return conv2d_lean_tiles(x, weight, bias, spec, None);
    }
    // No graph (sampling, or a checkpointed block's forward pass): tiles too, so that the
    // columns never exceed UNTRACKED_TILE_FLOATS values, whatever the batch and the grid.
    let (b, c, _, _) = x.dims4()?;
    let (_, _, kh, kw) = weight.dims4()?;
    let wo = spec.out_size(x.dim(2)?, x.dim(3)?).map_or(1, |(_, wo)| wo);
    let rows = UNTRACKED_TILE_FLOATS / (b * c * kh * kw * wo).max(1);
    conv2d_lean_tiles(x, weight, bias, spec, Some(rows.max(1)))
}

/// The most values of im2col columns an untracked convolution builds at once (256 MiB of f32):
/// larger tiles than a tracked one's, whose backward pass builds a tile's gradient too, because
/// this is the sampling path and fewer, larger products run faster.
const UNTRACKED_TILE_FLOATS: usize = 1 << 26;

/// [`conv2d_im2col`]'s lean path on any device: output rows in tiles of `tile_rows` (default: as
/// many as keep a tile's columns within 4 Mi values), one graph node whose backward pass
/// recomputes and back-propagates one tile at a time.
/// Public for tests and for measuring what a tile size costs.
pub fn conv2d_lean_tiles(
    x: &Tensor,
    weight: &Tensor,
    bias: Option<&Tensor>,
    spec: Im2ColSpec,
    tile_rows: Option<usize>,
) -> Result<Tensor> {
    let (b, c, h, w) = x.dims4()?;
    let (_, _, kh, kw) = weight.dims4()?;
    let spec = Im2ColSpec {
        kernel: (kh, kw),
        ones_row: false,
        ..spec
    };
    let Some((ho, wo)) = spec.out_size(h, w) else {
        return Err(crate::error::shape_err(
            "convolution input",
            format!("a plane the {spec:?} fits"),
            x.dims(),
        ));
    };
    let per_row = (b * c * kh * kw * wo).max(1);
    let rows = tile_rows
        .unwrap_or(crate::fused::TILE_FLOATS / per_row)
        .clamp(1, ho.max(1));
    let conv = move |t: &[&Tensor]| crate::fused::conv2d(t[0], t[1], t.get(2).copied(), spec);
    let inputs: Vec<&Tensor> = std::iter::once(x).chain([weight]).chain(bias).collect();
    if rows >= ho {
        return lean(&inputs, conv);
    }
    let (sh, pad_h) = (spec.stride.0, spec.pad_h);
    let mut tiles: Vec<std::sync::Arc<crate::recompute::BlockFn>> =
        Vec::with_capacity(ho.div_ceil(rows));
    for oy0 in (0..ho).step_by(rows) {
        let oy1 = (oy0 + rows).min(ho);
        // input rows [lo, hi) of the padded plane that these output rows read, as rows of `x`
        // plus the zero rows above and below it
        let lo = (oy0 * sh) as isize - pad_h as isize;
        let hi = ((oy1 - 1) * sh + kh) as isize - pad_h as isize;
        let (top, bottom) = ((-lo).max(0) as usize, (hi - h as isize).max(0) as usize);
        let (r0, r1) = (lo.max(0) as usize, (hi.min(h as isize)) as usize);
        let tile_spec = Im2ColSpec { pad_h: 0, ..spec };
        tiles.push(std::sync::Arc::new(move |t: &[&Tensor]| {
            let rows = t[0]
                .narrow(2, r0, r1 - r0)?
                .pad_with_zeros(2, top, bottom)?;
            crate::fused::conv2d(&rows, t[1], t.get(2).copied(), tile_spec)
        }));
    }
    // one node for the whole layer: the graph keeps its input and its output once (a node per
    // tile and their concatenation kept the output twice)
    crate::recompute::checkpoint_pieces(
        &inputs,
        Vec::new(),
        &crate::recompute::RecomputeTape::new(),
        tiles,
        2,
    )
}

/// `op(inputs)` recomputed in the backward pass (one to three inputs): the graph keeps the inputs
/// (an activation, weights, per-sample scales), not the op's intermediates. Every input that takes
/// part in the graph gets its gradient.
fn lean(
    inputs: &[&Tensor],
    op: impl Fn(&[&Tensor]) -> Result<Tensor> + Send + Sync + 'static,
) -> Result<Tensor> {
    crate::recompute::checkpoint(
        inputs,
        Vec::new(),
        &crate::recompute::RecomputeTape::new(),
        std::sync::Arc::new(op),
    )
}

/// GroupNorm with a per-sample `scale`, `shift: [B, C]` and an optional SiLU
/// ([`crate::fused::group_norm_act`]). Where the CPU kernels do not run and a graph is being built,
/// it is one node whose backward pass recomputes the normalisation and applies its gradient by
/// hand ([`crate::fused::group_norm_act_grad`]; on a GPU both passes are CUDA kernels): the graph
/// keeps `x`, not the normalisation's chain of about six `C N` intermediates, and its backward
/// pass builds no graph of its own.
/// Statistics of half-precision inputs are f32.
fn group_norm_act(
    x: &Tensor,
    scale: &Tensor,
    shift: &Tensor,
    groups: usize,
    eps: f64,
    silu: bool,
) -> Result<Tensor> {
    let tracked = x.track_op() || scale.track_op() || shift.track_op();
    if crate::fused::takes_kernels(x) || !tracked {
        return crate::fused::group_norm_act(x, scale, shift, groups, eps, silu);
    }
    crate::recompute::with_backward(
        &[x, scale, shift],
        |t| crate::fused::group_norm_act(t[0], t[1], t[2], groups, eps, silu),
        std::sync::Arc::new(move |t: &[&Tensor], g: &Tensor| {
            let (gx, gs, gt) =
                crate::fused::group_norm_act_grad(t[0], t[1], t[2], groups, eps, silu, g)?;
            Ok(vec![Some(gx), Some(gs), Some(gt)])
        }),
    )
}

/// Runs a `candle_nn::Conv2d` through [`conv2d_zero_pad`] (same weights, padding and stride, fast
/// backward); dilated or grouped convolutions fall back to the module's own `forward`.
pub fn conv2d_module(conv: &candle_nn::Conv2d, x: &Tensor) -> Result<Tensor> {
    let cfg = conv.config();
    if cfg.dilation != 1 || cfg.groups != 1 || cfg.cudnn_fwd_algo.is_some() {
        return Ok(candle_core::Module::forward(conv, x)?);
    }
    conv2d_zero_pad(x, conv.weight(), conv.bias(), cfg.padding, cfg.stride)
}

/// Nearest-neighbour upsampling by an integer `factor` (`[B, C, H, W] -> [B, C, factor H, factor W]`)
/// through a broadcast, whose backward pass is a sum (candle's `upsample_nearest2d` backward runs a
/// grouped convolution, one group per channel, which is slow on the CPU).
pub fn upsample_nearest(x: &Tensor, factor: usize) -> Result<Tensor> {
    crate::fused::upsample_nearest(x, factor)
}

/// A 1x1 convolution as a per-pixel linear map, weights `weight: [out, in, 1, 1]`, `bias: [out]`
/// (the layout of `candle_nn::Conv2d` / PyTorch `nn.Conv2d(k=1)`).
#[derive(Debug, Clone)]
pub struct Conv1x1 {
    weight: Tensor,
    bias: Option<Tensor>,
}

impl Conv1x1 {
    /// Default (Kaiming normal) initialisation.
    pub fn new(in_c: usize, out_c: usize, bias: bool, vb: VarBuilder<'_>) -> Result<Self> {
        Self::with_init(
            in_c,
            out_c,
            bias,
            candle_nn::init::DEFAULT_KAIMING_NORMAL,
            vb,
        )
    }

    /// Zero-initialised weights and bias (the "zero convolution" of ControlNet-style residual branches).
    pub fn zeros(in_c: usize, out_c: usize, vb: VarBuilder<'_>) -> Result<Self> {
        let weight = vb.get_with_hints((out_c, in_c, 1, 1), "weight", Init::Const(0.0))?;
        let bias = vb.get_with_hints(out_c, "bias", Init::Const(0.0))?;
        Ok(Self {
            weight,
            bias: Some(bias),
        })
    }

    fn with_init(
        in_c: usize,
        out_c: usize,
        bias: bool,
        init: Init,
        vb: VarBuilder<'_>,
    ) -> Result<Self> {
        let weight = vb.get_with_hints((out_c, in_c, 1, 1), "weight", init)?;
        let bias = if bias {
            let bound = 1.0 / (in_c as f64).sqrt();
            Some(vb.get_with_hints(
                out_c,
                "bias",
                Init::Uniform {
                    lo: -bound,
                    up: bound,
                },
            )?)
        } else {
            None
        };
        Ok(Self { weight, bias })
    }

    /// Weights `[out, in, 1, 1]` and bias `[out]`.
    pub(crate) fn weights(&self) -> (&Tensor, Option<&Tensor>) {
        (&self.weight, self.bias.as_ref())
    }

    /// `[B, in, ...spatial] -> [B, out, ...spatial]` (any number of trailing spatial dims).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let dims = x.dims().to_vec();
        if dims.len() < 2 {
            return Err(shape_err("conv1x1 input", "[B, C, ...]", &dims));
        }
        let (b, c) = (dims[0], dims[1]);
        let n: usize = dims[2..].iter().product();
        let (out_c, in_c) = (self.weight.dim(0)?, self.weight.dim(1)?);
        if c != in_c {
            return Err(shape_err(
                "conv1x1 input",
                format!("[B, {in_c}, ...]"),
                &dims,
            ));
        }
        let mut out_dims = dims;
        out_dims[1] = out_c;
        if crate::fused::takes_kernels(x) {
            // one fused op (bias inside, input read in place): the product below builds a
            // batch-broadcast weight and a `[1, out, 1]` bias broadcast, whose backward passes
            // are candle's single-threaded strided sums (about a tenth of a training step)
            let y = crate::fused::conv2d(
                &x.reshape((b, c, n, 1))?,
                &self.weight,
                self.bias.as_ref(),
                Im2ColSpec::POINTWISE,
            )?;
            return Ok(y.reshape(out_dims)?);
        }
        let w = self.weight.to_dtype(x.dtype())?.reshape((1, out_c, in_c))?;
        let y = w.broadcast_matmul(&x.reshape((b, c, n))?)?;
        let y = match &self.bias {
            Some(bias) => add_bias(&y, &bias.reshape((1, out_c, 1))?)?,
            None => y,
        };
        Ok(y.reshape(out_dims)?)
    }
}

/// Interpolation matrix `[out, in]` of PyTorch's 1-D linear resize with `align_corners=False`
/// (the size-given form of `F.interpolate(mode="bilinear")`, `antialias=False`).
///
/// For output index `i` the source coordinate is `(i + 0.5) * in / out - 0.5`, clamped below at 0;
/// the two neighbours are `floor(src)` and `min(floor(src) + 1, in - 1)`.
pub fn linear_resize_matrix(in_len: usize, out_len: usize) -> Vec<f32> {
    let mut m = vec![0f32; out_len * in_len];
    if in_len == 0 || out_len == 0 {
        return m;
    }
    let scale = in_len as f64 / out_len as f64;
    for i in 0..out_len {
        let src = ((i as f64 + 0.5) * scale - 0.5).max(0.0);
        let i0 = (src.floor() as usize).min(in_len - 1);
        let i1 = (i0 + 1).min(in_len - 1);
        let l1 = src - i0 as f64;
        let l0 = 1.0 - l1;
        m[i * in_len + i0] += l0 as f32;
        m[i * in_len + i1] += l1 as f32;
    }
    m
}

/// Bilinear resize of `[B, C, H, W]` to `[B, C, out_h, out_w]`, matching PyTorch
/// `F.interpolate(x, size=(out_h, out_w), mode="bilinear", align_corners=False)` (no antialiasing).
///
/// Implemented as two matrix products with the separable interpolation matrices of
/// [`linear_resize_matrix`], so it is differentiable and runs on any device. Same size is a no-op.
pub fn bilinear_resize(x: &Tensor, out_h: usize, out_w: usize) -> Result<Tensor> {
    let (b, c, h, w) = x.dims4()?;
    if (h, w) == (out_h, out_w) {
        return Ok(x.clone());
    }
    if h == 0 || w == 0 || out_h == 0 || out_w == 0 {
        return Err(shape_err(
            "bilinear_resize",
            "non-empty input and output sizes",
            &[b, c, h, w],
        ));
    }
    let dev = x.device();
    let dtype = x.dtype();
    let mw = Tensor::from_vec(linear_resize_matrix(w, out_w), (out_w, w), dev)?.to_dtype(dtype)?;
    let mh = Tensor::from_vec(linear_resize_matrix(h, out_h), (out_h, h), dev)?.to_dtype(dtype)?;
    // [B*C*H, W] x [W, out_w]
    let y = x.reshape((b * c * h, w))?.matmul(&mw.t()?)?;
    // [B*C, H, out_w] -> mh [out_h, H] x ...
    let y = y.reshape((b * c, h, out_w))?;
    let y = mh.unsqueeze(0)?.broadcast_matmul(&y)?;
    Ok(y.reshape((b, c, out_h, out_w))?)
}

/// Softmax over the last dimension with log-weights and a validity mask, stable for huge logits.
///
/// Computes `a_k = valid_k * w_k * exp(s_k) / sum_j valid_j * w_j * exp(s_j)` as
/// `exp(s'_k - max_valid s')` with `s' = clamp(s, ±1e38) + log_w` on valid entries only, so the largest
/// term is exactly 1 whenever any entry is valid (no overflow, no underflow of the denominator). Rows with
/// no valid entry give all zeros, never NaN.
///
/// * `logits`: `[..., K]`
/// * `log_w`: broadcastable to `logits`; finite on valid entries (anything on invalid ones)
/// * `valid`: broadcastable to `logits`, `u8` (1 = valid)
pub fn masked_softmax_last_dim(logits: &Tensor, log_w: &Tensor, valid: &Tensor) -> Result<Tensor> {
    if crate::fused::is_half(logits.dtype()) {
        // in f32: the -3e38 mask does not fit f16, and bf16's sums lose the small weights
        let a = masked_softmax_last_dim(
            &logits.to_dtype(DType::F32)?,
            &log_w.to_dtype(DType::F32)?,
            valid,
        )?;
        return Ok(a.to_dtype(logits.dtype())?);
    }
    let log_w = &log_w.to_dtype(logits.dtype())?;
    const BIG: f64 = 1e38;
    let shape = logits.shape().clone();
    let dtype = logits.dtype();
    let valid = valid.broadcast_as(shape.clone())?;
    let s = logits.clamp(-BIG, BIG)?.broadcast_add(log_w)?;
    let neg = Tensor::full(-3.0e38f32, shape.clone(), logits.device())?.to_dtype(dtype)?;
    let zero = Tensor::zeros(shape.clone(), dtype, logits.device())?;
    let s_valid = valid.where_cond(&s, &neg)?;
    let m = s_valid.max_keepdim(D::Minus1)?;
    // rows without any valid entry have m = -3e38; replace by 0 so that s - m stays finite
    let any = m.gt(-1.0e38)?;
    let m = any.where_cond(&m, &m.zeros_like()?)?;
    let z = s_valid.broadcast_sub(&m)?;
    // exp of invalid entries is exp(-3e38 - m) = 0 (or masked below when m is hugely negative)
    let e = valid.where_cond(&z.exp()?, &zero)?;
    let denom = e.sum_keepdim(D::Minus1)?;
    // denominators are >= 1 on rows with a valid entry and 0 otherwise
    let denom = denom.maximum(1e-30)?;
    Ok(e.broadcast_div(&denom)?)
}

/// Sinusoidal embedding of a per-sample scalar (diffusion time, step index or log-SNR), `[B] -> [B, dim]`.
///
/// `emb = [cos(scale * t * f_j), sin(scale * t * f_j)]`, `f_j = exp(-ln(max_period) * j / (dim/2))`,
/// `j = 0 .. dim/2` (the DDPM / ADM convention). `dim` must be even.
pub fn sinusoidal_embedding(t: &Tensor, dim: usize, max_period: f64, scale: f64) -> Result<Tensor> {
    if !dim.is_multiple_of(2) || dim == 0 {
        return Err(crate::Error::Config(format!(
            "time embedding dim must be even and > 0, got {dim}"
        )));
    }
    let b = match t.dims() {
        [b] => *b,
        other => return Err(shape_err("timestep", "[B]", other)),
    };
    let half = dim / 2;
    let freqs: Vec<f32> = (0..half)
        .map(|j| (-(max_period.ln()) * j as f64 / half as f64).exp() as f32)
        .collect();
    let freqs = Tensor::from_vec(freqs, (1, half), t.device())?;
    let args = (t
        .to_dtype(DType::F32)?
        .affine(scale, 0.0)?
        .reshape((b, 1))?)
    .broadcast_mul(&freqs)?;
    Ok(Tensor::cat(&[args.cos()?, args.sin()?], 1)?)
}

/// `x W^T + b` of a `candle_nn::Linear` in `x`'s dtype: the weights are cast to it first
/// (mixed precision: f32 master weights, half activations; free when the dtypes agree).
pub fn linear(layer: &candle_nn::Linear, x: &Tensor) -> Result<Tensor> {
    use candle_core::Module;
    let dt = x.dtype();
    if layer.weight().dtype() == dt {
        return Ok(layer.forward(x)?);
    }
    let y = candle_nn::Linear::new(layer.weight().to_dtype(dt)?, None).forward(x)?;
    match layer.bias() {
        Some(b) => add_bias(&y, b),
        None => Ok(y),
    }
}

/// Swish / SiLU.
pub fn silu(x: &Tensor) -> Result<Tensor> {
    Ok(candle_nn::ops::silu(x)?)
}

/// Group normalisation `[B, C, ...]` with learned `weight`/`bias` (`vb`), PyTorch `nn.GroupNorm` names.
pub fn group_norm(groups: usize, channels: usize, vb: VarBuilder<'_>) -> Result<GroupNorm> {
    if groups == 0 || !channels.is_multiple_of(groups) {
        return Err(crate::Error::Config(format!(
            "group norm: {channels} channels are not divisible into {groups} groups (at {})",
            vb.prefix()
        )));
    }
    let weight = vb.get_with_hints(channels, "weight", Init::Const(1.0))?;
    let bias = vb.get_with_hints(channels, "bias", Init::Const(0.0))?;
    Ok(GroupNorm {
        weight,
        bias,
        groups,
        eps: 1e-5,
    })
}

/// GroupNorm (PyTorch `nn.GroupNorm` semantics and weight names, epsilon 1e-5), with fused variants
/// that apply SiLU and a per-sample modulation in the same pass ([`crate::fused::group_norm_act`]).
#[derive(Debug, Clone)]
pub struct GroupNorm {
    weight: Tensor,
    bias: Tensor,
    groups: usize,
    eps: f64,
}

impl GroupNorm {
    /// Number of groups.
    pub fn groups(&self) -> usize {
        self.groups
    }

    /// Variance epsilon.
    pub(crate) fn eps(&self) -> f64 {
        self.eps
    }

    /// The affine weight and bias (the trainable tensors).
    pub(crate) fn params(&self) -> [&Tensor; 2] {
        [&self.weight, &self.bias]
    }

    /// The affine weights broadcast to `[B, C]` (scale, shift).
    pub(crate) fn affine(&self, b: usize) -> Result<(Tensor, Tensor)> {
        let c = self.weight.dim(0)?;
        Ok((
            self.weight
                .unsqueeze(0)?
                .broadcast_as((b, c))?
                .contiguous()?,
            self.bias.unsqueeze(0)?.broadcast_as((b, c))?.contiguous()?,
        ))
    }

    /// `GroupNorm(x)` for `x: [B, C, ...]`.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (sc, sh) = self.affine(x.dim(0)?)?;
        group_norm_act(x, &sc, &sh, self.groups, self.eps, false)
    }

    /// `SiLU(GroupNorm(x))`.
    pub fn forward_silu(&self, x: &Tensor) -> Result<Tensor> {
        let (sc, sh) = self.affine(x.dim(0)?)?;
        group_norm_act(x, &sc, &sh, self.groups, self.eps, true)
    }

    /// `SiLU(GroupNorm(x) * (1 + scale) + shift)` with per-sample `scale`, `shift: [B, C]` (AdaGN / FiLM).
    pub fn forward_modulated_silu(
        &self,
        x: &Tensor,
        scale: &Tensor,
        shift: &Tensor,
    ) -> Result<Tensor> {
        let (sc, sh) = self.modulated_affine(scale, shift)?;
        group_norm_act(x, &sc, &sh, self.groups, self.eps, true)
    }

    /// The per-sample `[B, C]` scale and shift of [`Self::forward_modulated_silu`].
    pub(crate) fn modulated_affine(
        &self,
        scale: &Tensor,
        shift: &Tensor,
    ) -> Result<(Tensor, Tensor)> {
        // (xhat w + b)(1 + s) + t = xhat [w (1 + s)] + [b (1 + s) + t], in the weights' dtype
        // (f32 master weights under mixed precision; group_norm_act casts as it needs)
        let dt = self.weight.dtype();
        let one_s = (scale.to_dtype(dt)? + 1.0)?;
        let sc = one_s.broadcast_mul(&self.weight.unsqueeze(0)?)?;
        let sh = (one_s.broadcast_mul(&self.bias.unsqueeze(0)?)? + shift.to_dtype(dt)?)?;
        Ok((sc, sh))
    }
}

/// Largest group count `<= max_groups` that divides `channels` (at least 1). The scan stops at
/// `channels` (no larger count divides it), so a huge `max_groups` from a config costs nothing.
pub fn groups_for(channels: usize, max_groups: usize) -> usize {
    (1..=max_groups.min(channels).max(1))
        .rev()
        .find(|g| channels.is_multiple_of(*g))
        .unwrap_or(1)
}

/// A `[1, C, H, W]` tensor from a channel-major `Vec<f32>`.
pub(crate) fn image_tensor(
    data: Vec<f32>,
    c: usize,
    h: usize,
    w: usize,
    dev: &Device,
) -> Result<Tensor> {
    Ok(Tensor::from_vec(data, (1, c, h, w), dev)?)
}
