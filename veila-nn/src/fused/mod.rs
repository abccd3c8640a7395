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
//! Each public function dispatches: F32 tensors on the CPU take the kernels; with the `cuda` feature,
//! GroupNorm + scale/shift + SiLU and the scaled residual sum take CUDA kernels on a GPU (f32, bf16,
//! f16; `cuda/kernels.cu`, see `cuda.rs`), and so does [`adamw_fused`], AdamW over all parameters in
//! one launch; every other device, op or dtype runs the plain candle composition (the `*_reference`
//! functions), which is also what the tests compare against, gradients included.
//! [`REFERENCE_OPS_ENV`] turns every kernel off, CPU and GPU.
//!
//! One file per op: `im2col.rs` (and the column matrices the convolution reuses), `matmul.rs` (the
//! matrix products, on `gemm` and `pulp`), `conv.rs`, `group_norm.rs`, `add_scaled.rs`,
//! `res_block.rs`, `upsample.rs` and `adamw.rs`; `cuda.rs` launches the CUDA kernels; this file
//! holds what they share (the dispatch tests, slices of CPU storage, zero-filled buffers, and the
//! vector-level dispatch of the kernels).

use candle_core::{CpuStorage, DType, Layout, Tensor};
use rayon::prelude::*;

/// Environment variable that, when set to `1`, turns the kernels off (every op runs its candle
/// composition): for before/after measurements in one binary (`cargo xtask bench-model`).
pub const REFERENCE_OPS_ENV: &str = "VEILA_NN_REFERENCE_OPS";

/// bf16 or f16: the dtypes whose normalisations and softmaxes run in f32 (mixed precision).
pub fn is_half(dtype: DType) -> bool {
    matches!(dtype, DType::BF16 | DType::F16)
}

/// The dtype normalisations, softmaxes and hand-written gradients compute in for `dtype`: f32 for
/// bf16 and f16, the dtype itself otherwise.
pub fn compute_dtype(dtype: DType) -> DType {
    if is_half(dtype) { DType::F32 } else { dtype }
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
                $at($crate::fused::simd_level(), $($arg),*)
            }
            #[cfg(not(target_arch = "x86_64"))]
            {
                $kernel($($arg),*)
            }
        }

        /// The kernel at a given vector level (which the caller must have checked the CPU has).
        #[cfg(target_arch = "x86_64")]
        #[allow(clippy::too_many_arguments)]
        fn $at(level: $crate::fused::SimdLevel, $($arg: $ty),*) {
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
                $crate::fused::SimdLevel::Avx512 => unsafe { avx512($($arg),*) },
                #[allow(unsafe_code)]
                $crate::fused::SimdLevel::Avx2 => unsafe { avx2($($arg),*) },
                $crate::fused::SimdLevel::Baseline => $kernel($($arg),*),
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

mod adamw;
mod add_scaled;
mod conv;
// kernel launches and device buffers are `unsafe` in cudarc; each block says why it holds
#[cfg(feature = "cuda")]
#[allow(unsafe_code)]
mod cuda;
mod group_norm;
mod im2col;
mod matmul;
mod res_block;
mod upsample;

pub use adamw::{AdamScalars, AdamSlot, adamw_fused, adamw_fused_supported};
pub use add_scaled::add_scaled;
pub use conv::{conv2d, conv2d_reference};
pub use group_norm::{
    group_norm_act, group_norm_act_grad, group_norm_act_grad_reference, group_norm_act_reference,
};
pub(crate) use im2col::TILE_FLOATS;
pub use im2col::{Im2ColSpec, im2col, im2col_reference};
pub use res_block::{ResBlockParams, ResBlockSpec, res_block};
pub use upsample::upsample_nearest;

/// A fixed pattern of `n` values in about [-1, 1] (the unit tests' inputs).
#[cfg(test)]
fn pattern(n: usize, f: f32) -> Vec<f32> {
    (0..n).map(|i| (i as f32 * f).sin()).collect()
}
