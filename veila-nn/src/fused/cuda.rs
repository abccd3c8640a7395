//! The CUDA side of the fused ops: the kernels of `cuda/kernels.cu` (PTX made by the build script
//! when the `cuda` feature is on) as candle custom ops, saving for backward what the CPU kernels
//! save (the input, not the normalisation's chain).
//!
//! * GroupNorm + per-sample scale/shift + optional SiLU, forward (statistics, then one elementwise
//!   pass) and gradient (statistics, per-channel sums, per-group sums, one elementwise pass), for
//!   f32, bf16 and f16 with f32 statistics;
//! * the scaled residual sum `(a + b) s` in one pass;
//! * AdamW over every parameter in one launch (candle-nn's update is about 14 launches per
//!   parameter tensor), bit-identical to candle-nn's on the CPU.
//!
//! The kernels' arithmetic is tested without a GPU (`tests/it/cuda_emu.rs` runs `kernels.cu` on
//! the host); `cargo xtask check-cuda` compares these ops with the candle compositions on a GPU.

use candle_core::backend::BackendStorage;
use candle_core::cuda_backend::cudarc::driver::{
    CudaSlice, DevicePtr, DeviceRepr, LaunchConfig, PushKernelArg,
};
use candle_core::cuda_backend::{CudaDType, WrapErr};
use candle_core::{
    CudaDevice, CudaStorage, CustomOp1, CustomOp2, CustomOp3, DType, Layout, Shape, Storage, Tensor,
};

use crate::error::Result;

/// The PTX of `cuda/kernels.cu`.
const PTX: &str = include_str!(concat!(env!("OUT_DIR"), "/veila_kernels.ptx"));
/// Name of the loaded module in candle's per-device cache.
const MODULE: &str = "veila_fused";
/// Threads per block (`VEILA_NT` in the kernels).
const NT: u32 = 256;
/// Values per block of the AdamW kernel (`VEILA_ADAM_CHUNK`).
const ADAM_CHUNK: usize = 4096;
/// At most this many blocks for the grid-stride kernels (16 per SM of an H100 / H200).
const MAX_BLOCKS: usize = 132 * 16;

/// `$op.run::<T>(args)` for the element type `T` of `$dtype` (f32, bf16 or f16); an error naming
/// `$name` for any other dtype.
macro_rules! by_dtype {
    ($dtype:expr, $name:literal, $op:ident.run($($arg:expr),*)) => {
        match $dtype {
            DType::F32 => $op.run::<f32>($($arg),*),
            DType::BF16 => $op.run::<half::bf16>($($arg),*),
            DType::F16 => $op.run::<half::f16>($($arg),*),
            d => Err(candle_core::Error::Msg(format!("{}: no {d:?} version", $name))),
        }
    };
}

/// Whether `t` takes the CUDA kernels: on a CUDA device, f32 / bf16 / f16, kernels on
/// ([`super::REFERENCE_OPS_ENV`] turns these off too).
pub fn takes_kernels(t: &Tensor) -> bool {
    t.device().is_cuda()
        && matches!(t.dtype(), DType::F32 | DType::BF16 | DType::F16)
        && super::kernels_enabled()
}

fn suffix(dtype: DType) -> candle_core::Result<&'static str> {
    Ok(match dtype {
        DType::F32 => "f32",
        DType::BF16 => "bf16",
        DType::F16 => "f16",
        d => candle_core::bail!("veila CUDA kernels: no {d:?} version"),
    })
}

fn blocks(n: usize) -> LaunchConfig {
    LaunchConfig {
        grid_dim: (n.max(1) as u32, 1, 1),
        block_dim: (NT, 1, 1),
        shared_mem_bytes: 0,
    }
}

fn grid_stride(total: usize) -> LaunchConfig {
    blocks(total.div_ceil(NT as usize).clamp(1, MAX_BLOCKS))
}

/// The contiguous data of `s` from the layout's offset.
fn view<'a, T: CudaDType + DeviceRepr>(
    s: &'a CudaStorage,
    l: &Layout,
    what: &str,
) -> candle_core::Result<candle_core::cuda_backend::cudarc::driver::CudaView<'a, T>> {
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(s.as_cuda_slice::<T>()?.slice(a..b)),
        None => candle_core::bail!("{what}: expected a contiguous tensor"),
    }
}

/// Runs `f` on the CUDA storage and layout of `t` (contiguous).
fn with_storage<R>(
    t: &Tensor,
    what: &str,
    f: impl FnOnce(&CudaStorage, &Layout) -> candle_core::Result<R>,
) -> candle_core::Result<R> {
    let (s, l) = t.storage_and_layout();
    match &*s {
        Storage::Cuda(c) => f(c, l),
        _ => candle_core::bail!("{what}: expected a CUDA tensor"),
    }
}

// ---- GroupNorm ---------------------------------------------------------------------------------------

/// Sizes of one GroupNorm call: `b` samples, `c` channels of `n` values, `cg` channels per group.
#[derive(Debug, Clone, Copy)]
struct GnDims {
    b: usize,
    c: usize,
    n: usize,
    cg: usize,
}

impl GnDims {
    fn new(shape: &Shape, groups: usize) -> candle_core::Result<Self> {
        let dims = shape.dims();
        if dims.len() < 2 || groups == 0 || !dims[1].is_multiple_of(groups) {
            candle_core::bail!("group norm: {dims:?} in {groups} groups")
        }
        Ok(Self {
            b: dims[0],
            c: dims[1],
            n: dims[2..].iter().product(),
            cg: dims[1] / groups,
        })
    }
    fn total(&self) -> usize {
        self.b * self.c * self.n
    }
    fn bc(&self) -> usize {
        self.b * self.c
    }
    fn bg(&self) -> usize {
        self.bc() / self.cg
    }
}

/// Launches the statistics kernel: `[B G, 2]` (mean, 1 / sqrt(var + eps)) in f32.
fn gn_stats<T: CudaDType + DeviceRepr>(
    dev: &CudaDevice,
    x: &candle_core::cuda_backend::cudarc::driver::CudaView<'_, T>,
    d: GnDims,
    eps: f64,
    sfx: &str,
) -> candle_core::Result<CudaSlice<f32>> {
    let mut stats = dev.alloc_zeros::<f32>(2 * d.bg())?;
    let f = dev.get_or_load_custom_func(&format!("veila_gn_stats_{sfx}"), MODULE, PTX)?;
    let (m, eps) = ((d.cg * d.n) as i64, eps as f32);
    let mut b = f.builder();
    b.arg(x);
    b.arg(&mut stats);
    b.arg(&m);
    b.arg(&eps);
    // SAFETY: the arguments match the kernel's signature; `stats` holds 2 B G values.
    unsafe { b.launch(blocks(d.bg())) }.w()?;
    Ok(stats)
}

/// `act(GroupNorm(x) scale + shift)` on the GPU; inputs `(x, scale, shift)`, all of one dtype.
#[derive(Debug, Clone, Copy)]
struct GroupNormActCuda {
    groups: usize,
    eps: f64,
    silu: bool,
}

impl GroupNormActCuda {
    #[allow(clippy::too_many_arguments)]
    fn run<T: CudaDType + DeviceRepr>(
        &self,
        (s1, l1): (&CudaStorage, &Layout),
        (s2, l2): (&CudaStorage, &Layout),
        (s3, l3): (&CudaStorage, &Layout),
    ) -> candle_core::Result<CudaStorage> {
        let dev = s1.device();
        let sfx = suffix(s1.dtype())?;
        let d = GnDims::new(l1.shape(), self.groups)?;
        let x = view::<T>(s1, l1, "group norm input")?;
        let scale = view::<T>(s2, l2, "group norm scale")?;
        let shift = view::<T>(s3, l3, "group norm shift")?;
        let stats = gn_stats(dev, &x, d, self.eps, sfx)?;
        // SAFETY: every value is written by the kernel below.
        let mut y = unsafe { dev.alloc::<T>(d.total()) }?;
        let f = dev.get_or_load_custom_func(&format!("veila_gn_fwd_{sfx}"), MODULE, PTX)?;
        let (total, n, cg, silu) = (d.total() as i64, d.n as i64, d.cg as i64, self.silu as i32);
        let mut b = f.builder();
        b.arg(&x);
        b.arg(&stats);
        b.arg(&scale);
        b.arg(&shift);
        b.arg(&mut y);
        b.arg(&total);
        b.arg(&n);
        b.arg(&cg);
        b.arg(&silu);
        // SAFETY: the arguments match the kernel's signature and sizes.
        unsafe { b.launch(grid_stride(d.total())) }.w()?;
        Ok(CudaStorage::wrap_cuda_slice(y, dev.clone()))
    }
}

impl CustomOp3 for GroupNormActCuda {
    fn name(&self) -> &'static str {
        "veila-group-norm-act-cuda"
    }

    fn cpu_fwd(
        &self,
        _: &candle_core::CpuStorage,
        _: &Layout,
        _: &candle_core::CpuStorage,
        _: &Layout,
        _: &candle_core::CpuStorage,
        _: &Layout,
    ) -> candle_core::Result<(candle_core::CpuStorage, Shape)> {
        candle_core::bail!("veila-group-norm-act-cuda runs on CUDA tensors only")
    }

    fn cuda_fwd(
        &self,
        s1: &CudaStorage,
        l1: &Layout,
        s2: &CudaStorage,
        l2: &Layout,
        s3: &CudaStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CudaStorage, Shape)> {
        let a = ((s1, l1), (s2, l2), (s3, l3));
        let out = by_dtype!(
            s1.dtype(),
            "veila-group-norm-act-cuda",
            self.run(a.0, a.1, a.2)
        )?;
        Ok((out, l1.shape().clone()))
    }

    fn bwd(
        &self,
        x: &Tensor,
        scale: &Tensor,
        shift: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (dx, ds, dt) =
            group_norm_act_grad(x, scale, shift, self.groups, self.eps, self.silu, grad)
                .map_err(|e| candle_core::Error::Msg(e.to_string()))?;
        Ok((Some(dx), Some(ds), Some(dt)))
    }
}

/// The gradient of [`GroupNormActCuda`], applied to `x` with the output gradient and the
/// scale/shift held here. `Sums` returns `[dscale (B C), dshift (B C), stats (2 B G)]` in f32;
/// `Input` (given those) returns dx in the input's dtype.
#[derive(Debug, Clone)]
struct GroupNormActGradCuda {
    groups: usize,
    eps: f64,
    silu: bool,
    grad: Tensor,
    scale: Tensor,
    shift: Tensor,
    /// `None`: the `Sums` pass; `Some(sums)`: the `Input` pass.
    sums: Option<Tensor>,
}

impl GroupNormActGradCuda {
    fn run<T: CudaDType + DeviceRepr>(
        &self,
        s1: &CudaStorage,
        l1: &Layout,
    ) -> candle_core::Result<CudaStorage> {
        let dev = s1.device();
        let sfx = suffix(s1.dtype())?;
        let d = GnDims::new(l1.shape(), self.groups)?;
        let x = view::<T>(s1, l1, "group norm input")?;
        with_storage(&self.grad, "group norm gradient", |sg, lg| {
            with_storage(&self.scale, "group norm scale", |ss, ls| {
                with_storage(&self.shift, "group norm shift", |st, lt| {
                    let g = view::<T>(sg, lg, "group norm gradient")?;
                    let scale = view::<T>(ss, ls, "group norm scale")?;
                    let shift = view::<T>(st, lt, "group norm shift")?;
                    let (total, n, cg) = (d.total() as i64, d.n as i64, d.cg as i64);
                    let (bc, bg, silu) = (d.bc() as i64, d.bg() as i64, self.silu as i32);
                    match &self.sums {
                        None => {
                            // dscale, dshift and the statistics in one f32 buffer
                            let stats = gn_stats(dev, &x, d, self.eps, sfx)?;
                            let mut out = dev.alloc_zeros::<f32>(2 * d.bc() + 2 * d.bg())?;
                            let f = dev.get_or_load_custom_func(
                                &format!("veila_gn_bwd_reduce_{sfx}"),
                                MODULE,
                                PTX,
                            )?;
                            let mut b = f.builder();
                            b.arg(&x);
                            b.arg(&g);
                            b.arg(&stats);
                            b.arg(&scale);
                            b.arg(&shift);
                            b.arg(&mut out);
                            b.arg(&bc);
                            b.arg(&n);
                            b.arg(&cg);
                            b.arg(&silu);
                            // SAFETY: arguments match the kernel; `out` holds 2 B C values first.
                            unsafe { b.launch(blocks(d.bc())) }.w()?;
                            {
                                let mut tail = out.slice_mut(2 * d.bc()..);
                                dev.cuda_stream().memcpy_dtod(&stats, &mut tail).w()?;
                            }
                            Ok(CudaStorage::wrap_cuda_slice(out, dev.clone()))
                        }
                        Some(sums) => with_storage(sums, "group norm sums", |sp, lp| {
                            let packed = view::<f32>(sp, lp, "group norm sums")?;
                            let gss = packed.slice(..2 * d.bc());
                            let stats = packed.slice(2 * d.bc()..);
                            let mut group_sums = dev.alloc_zeros::<f32>(2 * d.bg())?;
                            let f = dev.get_or_load_custom_func(
                                &format!("veila_gn_bwd_group_{sfx}"),
                                MODULE,
                                PTX,
                            )?;
                            let mut b = f.builder();
                            b.arg(&scale);
                            b.arg(&gss);
                            b.arg(&mut group_sums);
                            b.arg(&bc);
                            b.arg(&bg);
                            b.arg(&cg);
                            // SAFETY: arguments match the kernel; one thread per group.
                            unsafe { b.launch(blocks(d.bg().div_ceil(NT as usize))) }.w()?;
                            // SAFETY: every value is written by the kernel below.
                            let mut dx = unsafe { dev.alloc::<T>(d.total()) }?;
                            let f = dev.get_or_load_custom_func(
                                &format!("veila_gn_bwd_dx_{sfx}"),
                                MODULE,
                                PTX,
                            )?;
                            let mut b = f.builder();
                            b.arg(&x);
                            b.arg(&g);
                            b.arg(&stats);
                            b.arg(&scale);
                            b.arg(&shift);
                            b.arg(&group_sums);
                            b.arg(&mut dx);
                            b.arg(&total);
                            b.arg(&n);
                            b.arg(&cg);
                            b.arg(&silu);
                            // SAFETY: arguments match the kernel and its sizes.
                            unsafe { b.launch(grid_stride(d.total())) }.w()?;
                            Ok(CudaStorage::wrap_cuda_slice(dx, dev.clone()))
                        }),
                    }
                })
            })
        })
    }
}

impl CustomOp1 for GroupNormActGradCuda {
    fn name(&self) -> &'static str {
        "veila-group-norm-act-grad-cuda"
    }

    fn cpu_fwd(
        &self,
        _: &candle_core::CpuStorage,
        _: &Layout,
    ) -> candle_core::Result<(candle_core::CpuStorage, Shape)> {
        candle_core::bail!("veila-group-norm-act-grad-cuda runs on CUDA tensors only")
    }

    fn cuda_fwd(&self, s1: &CudaStorage, l1: &Layout) -> candle_core::Result<(CudaStorage, Shape)> {
        let out = by_dtype!(
            s1.dtype(),
            "veila-group-norm-act-grad-cuda",
            self.run(s1, l1)
        )?;
        let shape = match self.sums {
            None => {
                let d = GnDims::new(l1.shape(), self.groups)?;
                Shape::from(2 * d.bc() + 2 * d.bg())
            }
            Some(_) => l1.shape().clone(),
        };
        Ok((out, shape))
    }
}

/// [`super::group_norm_act`] on the GPU (`x`, `scale`, `shift` on one CUDA device; `scale` and
/// `shift` are taken in `x`'s dtype, the f32 master weights of mixed precision rounded to it).
/// The node keeps its three inputs for its gradient ([`group_norm_act_grad`]).
pub(super) fn group_norm_act(
    x: &Tensor,
    scale: &Tensor,
    shift: &Tensor,
    groups: usize,
    eps: f64,
    silu: bool,
) -> Result<Tensor> {
    let dt = x.dtype();
    Ok(x.contiguous()?.apply_op3(
        &scale.to_dtype(dt)?.contiguous()?,
        &shift.to_dtype(dt)?.contiguous()?,
        GroupNormActCuda { groups, eps, silu },
    )?)
}

/// [`super::group_norm_act_grad`] on the GPU: `(dx, dscale, dshift)`, dscale and dshift summed in
/// f32 and returned in their own dtypes.
pub(super) fn group_norm_act_grad(
    x: &Tensor,
    scale: &Tensor,
    shift: &Tensor,
    groups: usize,
    eps: f64,
    silu: bool,
    grad: &Tensor,
) -> Result<(Tensor, Tensor, Tensor)> {
    let (b, c) = (x.dim(0)?, x.dim(1)?);
    let x = x.contiguous()?;
    let mut op = GroupNormActGradCuda {
        groups,
        eps,
        silu,
        grad: grad.to_dtype(x.dtype())?.contiguous()?,
        scale: scale.to_dtype(x.dtype())?.contiguous()?,
        shift: shift.to_dtype(x.dtype())?.contiguous()?,
        sums: None,
    };
    let sums = x.apply_op1_no_bwd(&op)?;
    let dscale = sums.narrow(0, 0, b * c)?.reshape((b, c))?;
    let dshift = sums.narrow(0, b * c, b * c)?.reshape((b, c))?;
    op.sums = Some(sums.clone());
    let dx = x.apply_op1_no_bwd(&op)?;
    Ok((
        dx,
        dscale.to_dtype(scale.dtype())?,
        dshift.to_dtype(shift.dtype())?,
    ))
}

// ---- (a + b) s ----------------------------------------------------------------------------------------

/// `(a + b) s` in one pass (same shapes and dtypes); its gradient is `g s` for both.
#[derive(Debug, Clone, Copy)]
pub(super) struct AddScaledCuda {
    pub scale: f32,
}

impl AddScaledCuda {
    fn run<T: CudaDType + DeviceRepr>(
        &self,
        (s1, l1): (&CudaStorage, &Layout),
        (s2, l2): (&CudaStorage, &Layout),
    ) -> candle_core::Result<CudaStorage> {
        let dev = s1.device();
        let sfx = suffix(s1.dtype())?;
        let a = view::<T>(s1, l1, "add_scaled lhs")?;
        let b = view::<T>(s2, l2, "add_scaled rhs")?;
        let total = l1.shape().elem_count();
        // SAFETY: every value is written by the kernel below.
        let mut y = unsafe { dev.alloc::<T>(total) }?;
        let f = dev.get_or_load_custom_func(&format!("veila_add_scaled_{sfx}"), MODULE, PTX)?;
        let total_i = total as i64;
        let mut bld = f.builder();
        bld.arg(&a);
        bld.arg(&b);
        bld.arg(&mut y);
        bld.arg(&total_i);
        bld.arg(&self.scale);
        // SAFETY: arguments match the kernel and its sizes.
        unsafe { bld.launch(grid_stride(total)) }.w()?;
        Ok(CudaStorage::wrap_cuda_slice(y, dev.clone()))
    }
}

impl CustomOp2 for AddScaledCuda {
    fn name(&self) -> &'static str {
        "veila-add-scaled-cuda"
    }

    fn cpu_fwd(
        &self,
        _: &candle_core::CpuStorage,
        _: &Layout,
        _: &candle_core::CpuStorage,
        _: &Layout,
    ) -> candle_core::Result<(candle_core::CpuStorage, Shape)> {
        candle_core::bail!("veila-add-scaled-cuda runs on CUDA tensors only")
    }

    fn cuda_fwd(
        &self,
        s1: &CudaStorage,
        l1: &Layout,
        s2: &CudaStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CudaStorage, Shape)> {
        if l1.shape() != l2.shape() || s1.dtype() != s2.dtype() {
            candle_core::bail!("add_scaled: {:?} and {:?} differ", l1.shape(), l2.shape())
        }
        let a = ((s1, l1), (s2, l2));
        let out = by_dtype!(s1.dtype(), "veila-add-scaled-cuda", self.run(a.0, a.1))?;
        Ok((out, l1.shape().clone()))
    }

    fn bwd(
        &self,
        _a: &Tensor,
        _b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let g = (grad * f64::from(self.scale))?;
        Ok((Some(g.clone()), Some(g)))
    }
}

// ---- AdamW ----------------------------------------------------------------------------------------------

/// The ten f32 scalars of one step (`AdamScalars` in `kernels.cu` and in `adamw.rs`).
#[repr(C)]
#[derive(Debug, Clone, Copy)]
struct AdamScalarsC([f32; 10]);

// SAFETY: `#[repr(C)]` over ten f32: the layout of the kernel's struct of ten floats.
unsafe impl DeviceRepr for AdamScalarsC {}

/// One AdamW step of `slots` (parameter, its gradient, first and second moment; all f32 on one
/// CUDA device, checked by the caller) in one launch, in place.
pub(super) fn adamw(slots: &[[&Tensor; 4]], scalars: [f32; 10]) -> Result<()> {
    let Some(first) = slots.first() else {
        return Ok(());
    };
    let candle_core::Device::Cuda(dev) = first[0].device() else {
        return Err(crate::Error::Config(
            "fused AdamW: the CUDA path got a tensor off the GPU".into(),
        ));
    };
    let stream = dev.cuda_stream();
    let grads = slots
        .iter()
        .map(|s| s[1].contiguous())
        .collect::<candle_core::Result<Vec<_>>>()?;
    // read guards on every storage for the whole launch: the kernel writes through raw pointers
    // into the parameters and moments, in order on candle's one stream
    let guards: Vec<_> = slots
        .iter()
        .zip(&grads)
        .flat_map(|(s, g)| {
            [
                s[0].storage_and_layout(),
                g.storage_and_layout(),
                s[2].storage_and_layout(),
                s[3].storage_and_layout(),
            ]
        })
        .collect();
    let mut table: Vec<u64> = Vec::with_capacity(5 * slots.len());
    let mut first_chunk: Vec<i64> = Vec::with_capacity(slots.len() + 1);
    first_chunk.push(0);
    let mut syncs = Vec::with_capacity(guards.len());
    for (k, quad) in guards.chunks(4).enumerate() {
        let n = slots[k][0].elem_count();
        for (s, l) in quad {
            let Storage::Cuda(cs) = &**s else {
                return Err(crate::Error::Config(
                    "fused AdamW: a tensor is not on the GPU".into(),
                ));
            };
            if l.shape().elem_count() != n || !l.is_contiguous() {
                return Err(crate::Error::Config(format!(
                    "fused AdamW: slot {k} has tensors of {} and {n} values",
                    l.shape().elem_count()
                )));
            }
            let slice = cs.as_cuda_slice::<f32>()?;
            let (ptr, sync) = slice.device_ptr(&stream);
            table.push(ptr + 4 * l.start_offset() as u64);
            syncs.push(sync);
        }
        table.push(n as u64);
        first_chunk.push(first_chunk[k] + n.div_ceil(ADAM_CHUNK) as i64);
    }
    let total_blocks = *first_chunk.last().unwrap_or(&0) as usize;
    if total_blocks == 0 {
        return Ok(());
    }
    let table_dev = stream.clone_htod(&table).w()?;
    let first_dev = stream.clone_htod(&first_chunk).w()?;
    let f = dev.get_or_load_custom_func("veila_adamw_f32", MODULE, PTX)?;
    let nslots = slots.len() as i32;
    let mut b = f.builder();
    b.arg(&table_dev);
    b.arg(&first_dev);
    b.arg(&nslots);
    let c = AdamScalarsC(scalars);
    b.arg(&c);
    // SAFETY: the table holds `nslots` (p, g, m, v, n) records of live f32 buffers of n values
    // each (checked above, kept alive by `guards`); `first` their chunk offsets.
    unsafe { b.launch(blocks(total_blocks)) }.w()?;
    drop(syncs);
    drop(guards);
    Ok(())
}
