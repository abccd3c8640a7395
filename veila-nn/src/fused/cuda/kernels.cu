// CUDA kernels of `veila_nn::fused` (the GPU side of the CPU kernels in the Rust files next door).
//
// Built to PTX by veila-nn's build script when the `cuda` feature is on (`nvcc --ptx`, compute
// capability from CUDA_COMPUTE_CAP; `cargo xtask build-cuda` sets both), loaded once per device
// by `fused/cuda.rs`. The same file also compiles as C++ on the host with `emu.h` (one OS thread
// per CUDA thread, blocks one after another): `tests/it/cuda_emu.rs` runs it there against the
// candle compositions, so the kernels' arithmetic is tested on machines without a GPU.
//
// Rules that keep the emulation faithful: reductions go through shared memory and
// `__syncthreads()` (no warp shuffles), every kernel takes its block size from VEILA_NT, and
// floating-point operations whose rounding the tests compare bit for bit use the `__f*_rn`
// intrinsics (no fused multiply-add).
//
// Layouts: activations `[B, C, N]` contiguous (N the pixels), per-sample scale and shift `[B, C]`,
// GroupNorm statistics `[B * G, 2]` (mean, 1 / sqrt(var + eps)) in f32 whatever the dtype.

#ifndef VEILA_EMU
#include <cuda_bf16.h>
#include <cuda_fp16.h>
#include <stdint.h>
#endif

#define VEILA_NT 256

__device__ __forceinline__ float to_f(float x) { return x; }
__device__ __forceinline__ float to_f(__half x) { return __half2float(x); }
__device__ __forceinline__ float to_f(__nv_bfloat16 x) { return __bfloat162float(x); }

template <typename T> __device__ __forceinline__ T from_f(float x);
template <> __device__ __forceinline__ float from_f<float>(float x) { return x; }
template <> __device__ __forceinline__ __half from_f<__half>(float x) { return __float2half_rn(x); }
template <> __device__ __forceinline__ __nv_bfloat16 from_f<__nv_bfloat16>(float x) {
    return __float2bfloat16_rn(x);
}

// The sum of `v` over the block (every thread gets it). `sh` holds VEILA_NT doubles.
__device__ __forceinline__ double block_sum(double v, double *sh) {
    const int t = threadIdx.x;
    sh[t] = v;
    __syncthreads();
    for (int s = VEILA_NT / 2; s > 0; s >>= 1) {
        if (t < s) sh[t] += sh[t + s];
        __syncthreads();
    }
    const double r = sh[0];
    __syncthreads();
    return r;
}

__device__ __forceinline__ float sigmoidf(float a) { return 1.0f / (1.0f + expf(-a)); }

// ---- GroupNorm + per-sample scale/shift + optional SiLU -----------------------------------------

// One block per (sample, group): the group's `m` values start at `x + block * m`. Two passes in
// double (mean, then the centred sum of squares): no cancellation for large offsets.
template <typename T>
__device__ void gn_stats(const T *x, float *stats, int64_t m, float eps) {
    __shared__ double sh[VEILA_NT];
    const T *xs = x + (int64_t)blockIdx.x * m;
    double s = 0.0;
    for (int64_t i = threadIdx.x; i < m; i += VEILA_NT) s += (double)to_f(xs[i]);
    const double mean = block_sum(s, sh) / (double)m;
    double q = 0.0;
    for (int64_t i = threadIdx.x; i < m; i += VEILA_NT) {
        const double d = (double)to_f(xs[i]) - mean;
        q += d * d;
    }
    const double var = block_sum(q, sh) / (double)m;
    if (threadIdx.x == 0) {
        stats[2 * blockIdx.x] = (float)mean;
        stats[2 * blockIdx.x + 1] = (float)(1.0 / sqrt(var + (double)eps));
    }
}

// y = act((x - mean) rstd scale + shift), grid-stride over all `total` values; `cg` channels per
// group, so the group of channel row `bc = b C + c` is `bc / cg`.
template <typename T>
__device__ void gn_fwd(const T *x, const float *stats, const T *scale, const T *shift, T *y,
                       int64_t total, int64_t n, int64_t cg, int silu) {
    for (int64_t i = (int64_t)blockIdx.x * VEILA_NT + threadIdx.x; i < total;
         i += (int64_t)gridDim.x * VEILA_NT) {
        const int64_t bc = i / n;
        const int64_t grp = bc / cg;
        const float xh = (to_f(x[i]) - stats[2 * grp]) * stats[2 * grp + 1];
        float a = xh * to_f(scale[bc]) + to_f(shift[bc]);
        if (silu) a = a * sigmoidf(a);
        y[i] = from_f<T>(a);
    }
}

// The gradient through the SiLU (or none) at x̂ for the output gradient g.
__device__ __forceinline__ float gn_gz(float xh, float s, float t, float g, int silu) {
    if (!silu) return g;
    const float a = xh * s + t;
    const float sg = sigmoidf(a);
    return g * (sg * (1.0f + a * (1.0f - sg)));
}

// One block per channel row `bc`: dscale = sum gz x̂, dshift = sum gz (into gss[bc], gss[BC + bc]).
template <typename T>
__device__ void gn_bwd_reduce(const T *x, const T *g, const float *stats, const T *scale,
                              const T *shift, float *gss, int64_t bcount, int64_t n, int64_t cg,
                              int silu) {
    __shared__ double sh[VEILA_NT];
    const int64_t bc = blockIdx.x;
    const int64_t grp = bc / cg;
    const float mean = stats[2 * grp], rstd = stats[2 * grp + 1];
    const float s = to_f(scale[bc]), t = to_f(shift[bc]);
    const T *xs = x + bc * n;
    const T *gs = g + bc * n;
    double ds = 0.0, dt = 0.0;
    for (int64_t i = threadIdx.x; i < n; i += VEILA_NT) {
        const float xh = (to_f(xs[i]) - mean) * rstd;
        const float gz = gn_gz(xh, s, t, to_f(gs[i]), silu);
        ds += (double)gz * (double)xh;
        dt += (double)gz;
    }
    ds = block_sum(ds, sh);
    dt = block_sum(dt, sh);
    if (threadIdx.x == 0) {
        gss[bc] = (float)ds;
        gss[bcount + bc] = (float)dt;
    }
}

// One thread per (sample, group): sums[2 grp] = sum_c scale_c dshift_c, sums[2 grp + 1] =
// sum_c scale_c dscale_c over the group's `cg` channels (the group means of the gradient of x̂ and
// of its product with x̂, times the group size).
template <typename T>
__device__ void gn_bwd_group(const T *scale, const float *gss, float *sums, int64_t bcount,
                             int64_t groups_total, int64_t cg) {
    const int64_t grp = (int64_t)blockIdx.x * VEILA_NT + threadIdx.x;
    if (grp >= groups_total) return;
    double s1 = 0.0, s2 = 0.0;
    for (int64_t c = 0; c < cg; ++c) {
        const int64_t bc = grp * cg + c;
        const double s = (double)to_f(scale[bc]);
        s1 += s * (double)gss[bcount + bc];
        s2 += s * (double)gss[bc];
    }
    sums[2 * grp] = (float)s1;
    sums[2 * grp + 1] = (float)s2;
}

// dx = rstd (gz scale - (S1 + x̂ S2) / M), grid-stride; M = cg n values per group.
template <typename T>
__device__ void gn_bwd_dx(const T *x, const T *g, const float *stats, const T *scale,
                          const T *shift, const float *sums, T *dx, int64_t total, int64_t n,
                          int64_t cg, int silu) {
    const float inv_m = 1.0f / (float)(cg * n);
    for (int64_t i = (int64_t)blockIdx.x * VEILA_NT + threadIdx.x; i < total;
         i += (int64_t)gridDim.x * VEILA_NT) {
        const int64_t bc = i / n;
        const int64_t grp = bc / cg;
        const float rstd = stats[2 * grp + 1];
        const float xh = (to_f(x[i]) - stats[2 * grp]) * rstd;
        const float s = to_f(scale[bc]);
        const float gz = gn_gz(xh, s, to_f(shift[bc]), to_f(g[i]), silu);
        dx[i] = from_f<T>(rstd * (gz * s - (sums[2 * grp] + xh * sums[2 * grp + 1]) * inv_m));
    }
}

// ---- the scaled residual sum (a + b) s -------------------------------------------------------------

template <typename T>
__device__ void add_scaled(const T *a, const T *b, T *y, int64_t total, float s) {
    for (int64_t i = (int64_t)blockIdx.x * VEILA_NT + threadIdx.x; i < total;
         i += (int64_t)gridDim.x * VEILA_NT) {
        y[i] = from_f<T>((to_f(a[i]) + to_f(b[i])) * s);
    }
}

#define VEILA_GN_KERNELS(T, SUF)                                                                   \
    extern "C" __global__ void veila_gn_stats_##SUF(const T *x, float *stats, int64_t m,          \
                                                    float eps) {                                  \
        gn_stats<T>(x, stats, m, eps);                                                             \
    }                                                                                              \
    extern "C" __global__ void veila_gn_fwd_##SUF(const T *x, const float *stats, const T *scale, \
                                                  const T *shift, T *y, int64_t total, int64_t n,  \
                                                  int64_t cg, int silu) {                          \
        gn_fwd<T>(x, stats, scale, shift, y, total, n, cg, silu);                                  \
    }                                                                                              \
    extern "C" __global__ void veila_gn_bwd_reduce_##SUF(                                          \
        const T *x, const T *g, const float *stats, const T *scale, const T *shift, float *gss,    \
        int64_t bcount, int64_t n, int64_t cg, int silu) {                                         \
        gn_bwd_reduce<T>(x, g, stats, scale, shift, gss, bcount, n, cg, silu);                     \
    }                                                                                              \
    extern "C" __global__ void veila_gn_bwd_group_##SUF(const T *scale, const float *gss,          \
                                                        float *sums, int64_t bcount,               \
                                                        int64_t groups_total, int64_t cg) {        \
        gn_bwd_group<T>(scale, gss, sums, bcount, groups_total, cg);                               \
    }                                                                                              \
    extern "C" __global__ void veila_gn_bwd_dx_##SUF(                                              \
        const T *x, const T *g, const float *stats, const T *scale, const T *shift,                \
        const float *sums, T *dx, int64_t total, int64_t n, int64_t cg, int silu) {                \
        gn_bwd_dx<T>(x, g, stats, scale, shift, sums, dx, total, n, cg, silu);                     \
    }                                                                                              \
    extern "C" __global__ void veila_add_scaled_##SUF(const T *a, const T *b, T *y,                \
                                                      int64_t total, float s) {                    \
        add_scaled<T>(a, b, y, total, s);                                                          \
    }

VEILA_GN_KERNELS(float, f32)
VEILA_GN_KERNELS(__nv_bfloat16, bf16)
VEILA_GN_KERNELS(__half, f16)

// ---- AdamW over many tensors in one launch -------------------------------------------------------

// One parameter tensor of the update: all f32, `n` values each.
struct AdamSlot {
    float *p;
    const float *g;
    float *m;
    float *v;
    int64_t n;
};

// Scalars of one step, each rounded to f32 from the f64 the host computed (as candle's
// `tensor * f64` rounds its factor), so the update is bit-identical to candle-nn's AdamW.
struct AdamScalars {
    float grad_scale; // 1 = none
    float beta1, one_minus_beta1, beta2, one_minus_beta2;
    float scale_m, scale_v; // 1 / (1 - beta^t)
    float decay;            // 1 - lr weight_decay
    float lr, eps;
};

// Block `blockIdx.x` updates chunk `blockIdx.x - first[k]` (VEILA_ADAM_CHUNK values) of slot k,
// where first[k] <= blockIdx.x < first[k + 1] (`first` has nslots + 1 entries).
#define VEILA_ADAM_CHUNK 4096

extern "C" __global__ void veila_adamw_f32(const AdamSlot *slots, const int64_t *first, int nslots,
                                           AdamScalars c) {
    const int64_t blk = blockIdx.x;
    int lo = 0, hi = nslots; // first[lo] <= blk < first[hi]
    while (hi - lo > 1) {
        const int mid = (lo + hi) / 2;
        if (first[mid] <= blk) lo = mid;
        else hi = mid;
    }
    const AdamSlot s = slots[lo];
    const int64_t start = (blk - first[lo]) * VEILA_ADAM_CHUNK;
    int64_t end = start + VEILA_ADAM_CHUNK;
    if (end > s.n) end = s.n;
    for (int64_t i = start + threadIdx.x; i < end; i += VEILA_NT) {
        float g = s.g[i];
        if (c.grad_scale != 1.0f) g = __fmul_rn(g, c.grad_scale);
        // candle-nn's order: m' = m b1 + g (1 - b1); v' = v b2 + g^2 (1 - b2)
        const float m = __fadd_rn(__fmul_rn(s.m[i], c.beta1), __fmul_rn(g, c.one_minus_beta1));
        const float v = __fadd_rn(__fmul_rn(s.v[i], c.beta2),
                                  __fmul_rn(__fmul_rn(g, g), c.one_minus_beta2));
        const float m_hat = __fmul_rn(m, c.scale_m);
        const float v_hat = __fmul_rn(v, c.scale_v);
        const float adj = __fdiv_rn(m_hat, __fadd_rn(__fsqrt_rn(v_hat), c.eps));
        s.p[i] = __fsub_rn(__fmul_rn(s.p[i], c.decay), __fmul_rn(adj, c.lr));
        s.m[i] = m;
        s.v[i] = v;
    }
}
