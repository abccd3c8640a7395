// Runs the kernels of `veila-nn/src/fused/cuda/kernels.cu` on the host (see emu.h) for
// `tests/it/cuda_emu.rs`: `harness OP DIR` reads `DIR/args.txt` and the raw little-endian inputs
// `DIR/NAME.bin`, launches the kernels as `fused/cuda.rs` does, and writes `DIR/NAME.out`.
//   gn_DT          args B C N G eps silu; x scale shift g (DT) -> y stats dx (DT), dscale dshift (f32)
//   add_scaled_DT  args total s; a b (DT) -> y (DT)
//   adamw          args nslots n_0 .. n_{k-1}; p g m v (f32, the slots one after another),
//                  scalars (the 10 f32 of AdamScalars) -> p m v (f32)
#include "emu.h"

#include "../../src/fused/cuda/kernels.cu"

#include <cstdio>
#include <fstream>
#include <iostream>
#include <stdexcept>
#include <string>

template <typename T> static std::vector<T> load(const std::string &dir, const char *name) {
    std::ifstream f(dir + "/" + name + ".bin", std::ios::binary);
    if (!f) throw std::runtime_error(std::string("missing input ") + name);
    std::vector<char> bytes((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
    std::vector<T> v(bytes.size() / sizeof(T));
    std::memcpy(v.data(), bytes.data(), v.size() * sizeof(T));
    return v;
}

template <typename T>
static void save(const std::string &dir, const char *name, const std::vector<T> &v) {
    std::ofstream f(dir + "/" + name + ".out", std::ios::binary);
    f.write(reinterpret_cast<const char *>(v.data()), v.size() * sizeof(T));
}

static unsigned blocks_for(int64_t items) { return (unsigned)((items + VEILA_NT - 1) / VEILA_NT); }

template <typename T>
static void run_gn(const std::string &dir, std::istream &args,
                   void (*k_stats)(const T *, float *, int64_t, float),
                   void (*k_fwd)(const T *, const float *, const T *, const T *, T *, int64_t, int64_t,
                                 int64_t, int),
                   void (*k_red)(const T *, const T *, const float *, const T *, const T *, float *,
                                 int64_t, int64_t, int64_t, int),
                   void (*k_grp)(const T *, const float *, float *, int64_t, int64_t, int64_t),
                   void (*k_dx)(const T *, const T *, const float *, const T *, const T *,
                                const float *, T *, int64_t, int64_t, int64_t, int)) {
    int64_t b, c, n, groups;
    float eps;
    int silu;
    args >> b >> c >> n >> groups >> eps >> silu;
    const int64_t cg = c / groups, total = b * c * n, bc = b * c, bg = b * groups;
    auto x = load<T>(dir, "x"), scale = load<T>(dir, "scale"), shift = load<T>(dir, "shift"),
         g = load<T>(dir, "g");
    std::vector<float> stats(2 * bg), gss(2 * bc), sums(2 * bg);
    std::vector<T> y(total), dx(total);
    // a grid smaller than the data for the grid-stride kernels, as on a GPU with few SMs
    const unsigned small = blocks_for(total) > 3 ? 3 : blocks_for(total);
    emu_launch(k_stats, (unsigned)bg, VEILA_NT, x.data(), stats.data(), cg * n, eps);
    emu_launch(k_fwd, small, VEILA_NT, x.data(), (const float *)stats.data(), scale.data(),
               shift.data(), y.data(), total, n, cg, silu);
    emu_launch(k_red, (unsigned)bc, VEILA_NT, x.data(), g.data(), (const float *)stats.data(),
               scale.data(), shift.data(), gss.data(), bc, n, cg, silu);
    emu_launch(k_grp, blocks_for(bg), VEILA_NT, scale.data(), (const float *)gss.data(),
               sums.data(), bc, bg, cg);
    emu_launch(k_dx, small, VEILA_NT, x.data(), g.data(), (const float *)stats.data(),
               scale.data(), shift.data(), (const float *)sums.data(), dx.data(), total, n, cg,
               silu);
    save(dir, "y", y);
    save(dir, "stats", stats);
    save(dir, "dx", dx);
    save(dir, "dscale", std::vector<float>(gss.begin(), gss.begin() + bc));
    save(dir, "dshift", std::vector<float>(gss.begin() + bc, gss.end()));
}

template <typename T>
static void run_add_scaled(const std::string &dir, std::istream &args,
                           void (*k)(const T *, const T *, T *, int64_t, float)) {
    int64_t total;
    float s;
    args >> total >> s;
    auto a = load<T>(dir, "a"), b = load<T>(dir, "b");
    std::vector<T> y(total);
    emu_launch(k, blocks_for(total) > 2 ? 2 : blocks_for(total), VEILA_NT, a.data(), b.data(),
               y.data(), total, s);
    save(dir, "y", y);
}

static void run_adamw(const std::string &dir, std::istream &args) {
    int nslots;
    args >> nslots;
    std::vector<int64_t> sizes(nslots);
    for (auto &n : sizes) args >> n;
    auto p = load<float>(dir, "p"), g = load<float>(dir, "g"), m = load<float>(dir, "m"),
         v = load<float>(dir, "v"), sc = load<float>(dir, "scalars");
    if (sc.size() != sizeof(AdamScalars) / sizeof(float)) throw std::runtime_error("scalars");
    AdamScalars c;
    std::memcpy(&c, sc.data(), sizeof c);
    std::vector<AdamSlot> slots;
    std::vector<int64_t> first{0};
    int64_t off = 0;
    for (int64_t n : sizes) {
        slots.push_back({p.data() + off, g.data() + off, m.data() + off, v.data() + off, n});
        first.push_back(first.back() + (n + VEILA_ADAM_CHUNK - 1) / VEILA_ADAM_CHUNK);
        off += n;
    }
    emu_launch(veila_adamw_f32, (unsigned)first.back(), VEILA_NT, (const AdamSlot *)slots.data(),
               (const int64_t *)first.data(), nslots, c);
    save(dir, "p", p);
    save(dir, "m", m);
    save(dir, "v", v);
}

int main(int argc, char **argv) {
    if (argc != 3) {
        std::fprintf(stderr, "usage: harness OP DIR\n");
        return 2;
    }
    const std::string op = argv[1], dir = argv[2];
    std::ifstream args(dir + "/args.txt");
    try {
#define GN(SUF, T)                                                                                 \
    if (op == "gn_" #SUF) {                                                                        \
        run_gn<T>(dir, args, veila_gn_stats_##SUF, veila_gn_fwd_##SUF, veila_gn_bwd_reduce_##SUF,  \
                  veila_gn_bwd_group_##SUF, veila_gn_bwd_dx_##SUF);                                \
        return 0;                                                                                  \
    }                                                                                              \
    if (op == "add_scaled_" #SUF) {                                                                \
        run_add_scaled<T>(dir, args, veila_add_scaled_##SUF);                                      \
        return 0;                                                                                  \
    }
        GN(f32, float)
        GN(bf16, __nv_bfloat16)
        GN(f16, __half)
        if (op == "adamw") {
            run_adamw(dir, args);
            return 0;
        }
    } catch (const std::exception &e) {
        std::fprintf(stderr, "harness %s: %s\n", op.c_str(), e.what());
        return 1;
    }
    std::fprintf(stderr, "harness: unknown op %s\n", op.c_str());
    return 2;
}
