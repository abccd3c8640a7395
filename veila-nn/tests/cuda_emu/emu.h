// Host emulation of the CUDA subset `veila-nn/src/fused/cuda/kernels.cu` uses, for testing its
// arithmetic without a GPU: a block's threads are OS threads (`__syncthreads` is a barrier),
// blocks run one after another (so `__shared__` arrays can be function-level statics), and half
// and bfloat16 are 16-bit patterns converted with round-to-nearest-even as CUDA's `_rn`
// intrinsics do. Compile with -ffp-contract=off so `a * b + c` rounds twice, as `__fmul_rn` /
// `__fadd_rn` do on the GPU.
#pragma once
#define VEILA_EMU 1

#include <barrier>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <thread>
#include <vector>

#define __global__
#define __device__
#define __forceinline__ inline
#define __shared__ static

struct dim3 {
    unsigned x = 1, y = 1, z = 1;
};
inline thread_local dim3 threadIdx;
inline thread_local dim3 blockIdx;
inline dim3 blockDim;
inline dim3 gridDim;
inline std::barrier<> *emu_barrier = nullptr;

inline void __syncthreads() { emu_barrier->arrive_and_wait(); }

struct __half {
    uint16_t bits;
};
struct __nv_bfloat16 {
    uint16_t bits;
};

inline float __half2float(__half h) {
    _Float16 f;
    std::memcpy(&f, &h.bits, 2);
    return (float)f;
}
inline __half __float2half_rn(float x) {
    _Float16 f = (_Float16)x; // IEEE conversion: round to nearest, ties to even
    __half h;
    std::memcpy(&h.bits, &f, 2);
    return h;
}
inline float __bfloat162float(__nv_bfloat16 b) {
    uint32_t u = (uint32_t)b.bits << 16;
    float f;
    std::memcpy(&f, &u, 4);
    return f;
}
inline __nv_bfloat16 __float2bfloat16_rn(float x) {
    uint32_t u;
    std::memcpy(&u, &x, 4);
    if ((u & 0x7fffffffu) > 0x7f800000u) return {(uint16_t)((u >> 16) | 0x40u)}; // quiet NaN
    u += 0x7fffu + ((u >> 16) & 1u);
    return {(uint16_t)(u >> 16)};
}

inline float __fadd_rn(float a, float b) { return a + b; }
inline float __fsub_rn(float a, float b) { return a - b; }
inline float __fmul_rn(float a, float b) { return a * b; }
inline float __fdiv_rn(float a, float b) { return a / b; }
inline float __fsqrt_rn(float a) { return std::sqrt(a); }
#include <math.h> // expf
using std::sqrt;

// Runs `kernel(args...)` on `grid` blocks of `block` threads.
template <typename... P, typename... A>
void emu_launch(void (*kernel)(P...), unsigned grid, unsigned block, A... args) {
    gridDim = {grid, 1, 1};
    blockDim = {block, 1, 1};
    for (unsigned b = 0; b < grid; ++b) {
        std::barrier<> bar(block);
        emu_barrier = &bar;
        std::vector<std::thread> threads;
        threads.reserve(block);
        for (unsigned t = 0; t < block; ++t) {
            threads.emplace_back([=] {
                blockIdx = {b, 1, 1};
                threadIdx = {t, 1, 1};
                kernel(((P)args)...);
            });
        }
        for (auto &th : threads) th.join();
    }
    emu_barrier = nullptr;
}
