//! GroupNorm + per-sample scale/shift + SiLU, forward and backward, per vector unit.

use candle_core::{CpuStorage, CustomOp3, DType, Layout, Shape, Tensor};
use rayon::prelude::*;

use super::{compute_dtype, is_half, on_cpu_f32, slice_f32, tensor_f32, with_f32, zeros};
use crate::error::{Result, shape_err};

#[derive(Debug, Clone, Copy)]
pub(super) struct GroupNormAct {
    pub(super) groups: usize,
    pub(super) eps: f64,
    pub(super) silu: bool,
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
    pub(super) fn forward_slices(
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
    pub(super) fn backward_slices(
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

/// Checks the shapes [`group_norm_act`] and its gradient take: `x: [B, C, ...]` with `C` divisible
/// by `groups`, `scale` and `shift` `[B, C]`.
fn check_args(x: &Tensor, scale: &Tensor, shift: &Tensor, groups: usize) -> Result<()> {
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
    Ok(())
}

/// `x - mean` per group (`[B, groups, M]`) and the group's `sqrt(var + eps)` (`[B, groups, 1]`),
/// the biased variance as `candle_nn::GroupNorm` computes it.
fn centred_and_std(x: &Tensor, groups: usize, eps: f64) -> Result<(Tensor, Tensor)> {
    let xr = x.reshape((x.dim(0)?, groups, ()))?;
    let m = xr.dim(2)? as f64;
    let mean = (xr.sum_keepdim(2)? / m)?;
    let xc = xr.broadcast_sub(&mean)?;
    let var = (xc.sqr()?.sum_keepdim(2)? / m)?;
    Ok((xc, (var + eps)?.sqrt()?))
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
    check_args(x, scale, shift, groups)?;
    #[cfg(feature = "cuda")]
    if super::cuda::takes_kernels(x) && on_one_device(x, scale, shift) {
        return super::cuda::group_norm_act(x, scale, shift, groups, eps, silu);
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
    let (xc, std) = centred_and_std(x, groups, eps)?;
    let xn = xc.broadcast_div(&std)?.reshape(dims.as_slice())?;
    let mut bshape = vec![1; dims.len()];
    bshape[0] = b;
    bshape[1] = c;
    let y = xn
        .broadcast_mul(&scale.reshape(bshape.as_slice())?)?
        .broadcast_add(&shift.reshape(bshape.as_slice())?)?;
    Ok(if silu { candle_nn::ops::silu(&y)? } else { y })
}

/// Whether `scale` and `shift` are on `x`'s device (the CUDA kernels take them in `x`'s dtype).
#[cfg(feature = "cuda")]
fn on_one_device(x: &Tensor, scale: &Tensor, shift: &Tensor) -> bool {
    scale.device().same_device(x.device()) && shift.device().same_device(x.device())
}

/// The gradients of [`group_norm_act`] (`x`, `scale`, `shift`) for the output's gradient `grad`,
/// recomputing the normalisation from `x`: what a backward pass needs without keeping the forward
/// pass's chain. On a GPU with the `cuda` feature, four kernels (statistics, per-channel sums,
/// per-group sums, one elementwise pass); elsewhere [`group_norm_act_grad_reference`].
pub fn group_norm_act_grad(
    x: &Tensor,
    scale: &Tensor,
    shift: &Tensor,
    groups: usize,
    eps: f64,
    silu: bool,
    grad: &Tensor,
) -> Result<(Tensor, Tensor, Tensor)> {
    #[cfg(feature = "cuda")]
    if super::cuda::takes_kernels(x)
        && on_one_device(x, scale, shift)
        && grad.device().same_device(x.device())
    {
        check_grad_args(x, scale, shift, groups, grad)?;
        return super::cuda::group_norm_act_grad(x, scale, shift, groups, eps, silu, grad);
    }
    // (the reference checks the arguments itself)
    group_norm_act_grad_reference(x, scale, shift, groups, eps, silu, grad)
}

fn check_grad_args(
    x: &Tensor,
    scale: &Tensor,
    shift: &Tensor,
    groups: usize,
    grad: &Tensor,
) -> Result<()> {
    check_args(x, scale, shift, groups)?;
    if grad.dims() != x.dims() {
        return Err(shape_err(
            "group norm gradient",
            format!("{:?}, the input's shape", x.dims()),
            grad.dims(),
        ));
    }
    Ok(())
}

/// [`group_norm_act_grad`] from candle ops (any device). It holds about five `x`-sized tensors at
/// once (the incoming gradient, `x̂`, the SiLU's derivative and two products), each dropped as
/// soon as it is used; the composition's own backward pass kept its six intermediates and a
/// gradient for each. Half-precision inputs are computed in f32 and the gradients returned in
/// their dtypes.
pub fn group_norm_act_grad_reference(
    x: &Tensor,
    scale: &Tensor,
    shift: &Tensor,
    groups: usize,
    eps: f64,
    silu: bool,
    grad: &Tensor,
) -> Result<(Tensor, Tensor, Tensor)> {
    check_grad_args(x, scale, shift, groups, grad)?;
    let dims = x.dims().to_vec();
    let (b, c) = (dims[0], dims[1]);
    let dt = compute_dtype(x.dtype());
    let (s, t) = (scale.to_dtype(dt)?, shift.to_dtype(dt)?);
    let g = grad.to_dtype(dt)?;
    // x̂ and 1 / sigma per group, as the forward pass computed them
    let (xc, std) = centred_and_std(&x.to_dtype(dt)?, groups, eps)?;
    let m = xc.dim(2)? as f64;
    let rstd = std.recip()?;
    let xhat = xc.broadcast_mul(&rstd)?.reshape((b, c, ()))?;
    drop(xc);
    let (s3, t3) = (s.reshape((b, c, 1))?, t.reshape((b, c, 1))?);
    let g = g.reshape((b, c, ()))?;
    // through the SiLU: d silu(a) / da = sig(a) (1 + a (1 - sig(a)))
    let ga = if silu {
        let a = xhat.broadcast_mul(&s3)?.broadcast_add(&t3)?;
        let sig = candle_nn::ops::sigmoid(&a)?;
        let d = ((&a * (1.0 - &sig)?)? + 1.0)?;
        drop(a);
        let d = (d * sig)?;
        (g * d)?
    } else {
        g
    };
    let g_shift = ga.sum(2)?;
    let g_scale = (&ga * &xhat)?.sum(2)?;
    let gx = ga.broadcast_mul(&s3)?.reshape((b, groups, ()))?;
    drop(ga);
    let xhat = xhat.reshape((b, groups, ()))?;
    let m1 = (gx.sum_keepdim(2)? / m)?;
    let m2 = ((&gx * &xhat)?.sum_keepdim(2)? / m)?;
    let gx = gx.broadcast_sub(&m1)?;
    let gx = (gx - xhat.broadcast_mul(&m2)?)?;
    drop(xhat);
    let gx = gx.broadcast_mul(&rstd)?.reshape(dims.as_slice())?;
    Ok((
        gx.to_dtype(x.dtype())?,
        g_scale.to_dtype(scale.dtype())?,
        g_shift.to_dtype(shift.dtype())?,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    #[cfg(target_arch = "x86_64")]
    use crate::fused::{SimdLevel, pattern};

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
}
