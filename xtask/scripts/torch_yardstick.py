#!/usr/bin/env python3
"""PyTorch yardstick for the Veila denoiser's CPU speed (issue 19). Run by hand, not by CI.

Builds the unconditional path of `veila_nn::Denoiser` in PyTorch from safetensors weights with the
checkpoint's own parameter names, checks that its output equals candle's on the fixed input that
`cargo xtask bench-model --export DIR` wrote, and times the same three figures as `bench-model`:
forward at batch 1 and 8, and one training step at batch 8 (forward, MSE, backward, AdamW), as medians
with 2 threads by default.

    cargo xtask bench-model --export target/yardstick       # weights, config, input, candle output
    python3 xtask/scripts/torch_yardstick.py target/yardstick [--threads 2] [--json]

On a GPU: `bench-model --device cuda` (a `build-cuda --xtask` build) and `--device cuda` here; PyTorch
then computes in full f32 like candle unless `--tf32`.

Needs `torch`, `numpy` and `safetensors` (`pip install torch numpy safetensors`; the CPU is enough).
Another bundle's denoiser works too: pass `--weights models/default/denoiser.safetensors` and
`--config` with the `denoiser` object of its `bundle.json` (the conditioning branches are skipped);
then the ray features must come from the export (they depend on the sensor only).
"""

import argparse
import json
import math
import statistics
import sys
import time

import numpy as np
import torch
import torch.nn.functional as F

try:
    from safetensors.numpy import load_file
except ImportError:  # a machine with torch but without the safetensors package (the GPU machine)

    def load_file(path):
        """The safetensors layout: u64 header length, JSON header, then the raw little-endian data."""
        dtypes = {"F32": np.float32, "F64": np.float64, "F16": np.float16, "I64": np.int64, "U8": np.uint8}
        with open(path, "rb") as f:
            blob = f.read()
        n = int.from_bytes(blob[:8], "little")
        header = json.loads(blob[8 : 8 + n])
        out = {}
        for name, info in header.items():
            if name == "__metadata__":
                continue
            a, b = info["data_offsets"]
            raw = blob[8 + n + a : 8 + n + b]
            out[name] = np.frombuffer(raw, dtype=dtypes[info["dtype"]]).reshape(info["shape"]).copy()
        return out


def groups_for(channels, max_groups):
    for g in range(max(max_groups, 1), 0, -1):
        if channels % g == 0:
            return g
    return 1


class RingConv(torch.nn.Module):
    """k x k conv, circular padding in width, zeros in height (veila_nn::ops::RingConv2d)."""

    def __init__(self, cin, cout, k=3, stride=1):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(cout, cin, k, k))
        self.bias = torch.nn.Parameter(torch.zeros(cout))
        self.p = k // 2
        self.stride = stride

    def forward(self, x):
        p = self.p
        x = torch.cat([x[..., -p:], x, x[..., :p]], dim=3)
        return F.conv2d(x, self.weight, self.bias, stride=self.stride, padding=(p, 0))


class Conv1x1(torch.nn.Module):
    def __init__(self, cin, cout, bias=True):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(cout, cin, 1, 1))
        self.bias = torch.nn.Parameter(torch.zeros(cout)) if bias else None

    def forward(self, x):
        return F.conv2d(x, self.weight, self.bias)


class ResBlock(torch.nn.Module):
    def __init__(self, cin, cout, temb, groups, scale):
        super().__init__()
        self.norm1 = torch.nn.GroupNorm(groups_for(cin, groups), cin, eps=1e-5)
        self.conv1 = RingConv(cin, cout)
        self.emb = torch.nn.Linear(temb, 2 * cout)
        self.norm2 = torch.nn.GroupNorm(groups_for(cout, groups), cout, eps=1e-5)
        self.conv2 = RingConv(cout, cout)
        self.skip = Conv1x1(cin, cout) if cin != cout else None
        self.cout = cout
        self.scale = scale

    def forward(self, x, emb):
        h = self.conv1(F.silu(self.norm1(x)))
        e = self.emb(emb)[:, :, None, None]
        sc, sh = e[:, : self.cout], e[:, self.cout :]
        h = self.norm2(h) * (1 + sc) + sh
        h = self.conv2(F.silu(h))
        s = self.skip(x) if self.skip is not None else x
        return (s + h) * self.scale


class Pfc(torch.nn.Module):
    def __init__(self, ch, heads, groups):
        super().__init__()
        self.norm = torch.nn.GroupNorm(groups_for(ch, groups), ch, eps=1e-5)
        self.qkv = Conv1x1(ch, 3 * ch)
        self.proj = Conv1x1(ch, ch)
        self.heads = heads

    def forward(self, x):
        b, c, h, w = x.shape
        n, dh = h * w, c // self.heads
        qkv = self.qkv(self.norm(x)).reshape(b, 3, self.heads, dh, n)
        q, k, v = (qkv[:, i].reshape(b * self.heads, dh, n) for i in range(3))
        attn = torch.softmax(q.transpose(1, 2) @ k / math.sqrt(dh), dim=-1)
        out = (v @ attn.transpose(1, 2)).reshape(b, c, h, w)
        return x + self.proj(out)


class Level(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.res = torch.nn.ModuleList()


class Denoiser(torch.nn.Module):
    """The unconditional path of veila_nn::Denoiser, with its parameter names."""

    def __init__(self, cfg, ray_features):
        super().__init__()
        self.cfg = cfg
        base = cfg["base_channels"]
        mults = cfg["channel_mults"]
        nrb = cfg["num_res_blocks"]
        groups = cfg["norm_groups"]
        rs = cfg["residual_scale"]
        temb = 4 * base
        nl = len(mults)
        self.register_buffer("ray", ray_features)
        in_c = cfg["in_channels"] + (ray_features.shape[1] if ray_features is not None else 0)
        self.in_conv = RingConv(in_c, base)
        self.time = torch.nn.ModuleDict(
            {"0": torch.nn.Linear(cfg["time"]["dim"], temb), "2": torch.nn.Linear(temb, temb)}
        )
        skips = [base]
        ch = base
        self.down = torch.nn.ModuleList()
        for lev in range(nl):
            out = base * mults[lev]
            L = Level()
            for _ in range(nrb):
                L.res.append(ResBlock(ch, out, temb, groups, rs))
                ch = out
                skips.append(ch)
            if lev + 1 < nl:
                skips.append(ch)
                L.downsample = RingConv(ch, ch, 3, 2)
            self.down.append(L)
        self.mid = torch.nn.Module()
        self.mid.res = torch.nn.ModuleList(
            [ResBlock(ch, ch, temb, groups, rs), ResBlock(ch, ch, temb, groups, rs)]
        )
        self.mid.pfc = Pfc(ch, cfg["pfc"]["num_heads"], groups) if cfg.get("pfc") else None
        # the decoder's parameter names count levels down from nl-1 (`up.{l}`)
        self.up = torch.nn.ModuleDict()
        for lev in reversed(range(nl)):
            out = base * mults[lev]
            L = Level()
            for _ in range(nrb + 1):
                L.res.append(ResBlock(ch + skips.pop(), out, temb, groups, rs))
                ch = out
            if lev > 0:
                L.upsample = RingConv(ch, ch)
            self.up[str(lev)] = L
        self.out_norm = torch.nn.GroupNorm(groups_for(ch, groups), ch, eps=1e-5)
        self.out_conv = RingConv(ch, cfg["out_channels"])

    def time_embedding(self, t):
        tc = self.cfg["time"]
        half = tc["dim"] // 2
        j = torch.arange(half, dtype=torch.float64, device=t.device)
        freqs = torch.exp(-math.log(tc["max_period"]) * j / half).to(torch.float32)
        args = (t.float() * tc["input_scale"])[:, None] * freqs[None]
        return torch.cat([torch.cos(args), torch.sin(args)], dim=1)

    def forward(self, x, t):
        emb = self.time["2"](F.silu(self.time["0"](self.time_embedding(t))))
        emb = F.silu(emb)
        b = x.shape[0]
        if self.ray is not None:
            x = torch.cat([x, self.ray.expand(b, -1, -1, -1)], dim=1)
        h = self.in_conv(x)
        skips = [h]
        for L in self.down:
            for rb in L.res:
                h = rb(h, emb)
                skips.append(h)
            if hasattr(L, "downsample"):
                h = L.downsample(h)
                skips.append(h)
        h = self.mid.res[0](h, emb)
        if self.mid.pfc is not None:
            h = self.mid.pfc(h)
        h = self.mid.res[1](h, emb)
        for lev in reversed(range(len(self.cfg["channel_mults"]))):
            L = self.up[str(lev)]
            for rb in L.res:
                h = rb(torch.cat([h, skips.pop()], dim=1), emb)
            if hasattr(L, "upsample"):
                h = L.upsample(F.interpolate(h, scale_factor=2, mode="nearest"))
        return self.out_conv(F.silu(self.out_norm(h)))


def torch_name(name):
    # candle names `mid.res.0` / `mid.pfc` and `time.0` map one to one; nothing to rename
    return name


def load_weights(net, path):
    tensors = load_file(path)
    state = net.state_dict()
    missing = [k for k in state if k != "ray" and torch_name(k) not in tensors]
    if missing:
        sys.exit(f"{path}: missing parameters {missing[:5]} ...")
    used = 0
    with torch.no_grad():
        for k, v in state.items():
            if k == "ray":
                continue
            src = torch.from_numpy(tensors[torch_name(k)].astype(np.float32))
            if tuple(src.shape) != tuple(v.shape):
                sys.exit(f"{path}: {k} has shape {tuple(src.shape)}, expected {tuple(v.shape)}")
            v.copy_(src)
            used += 1
    return used, len(tensors)


def median_ms(fn, runs, sync, warmup=2):
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(runs):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("export", help="folder written by `cargo xtask bench-model --export`")
    ap.add_argument("--weights", help="denoiser safetensors (default: EXPORT/weights.safetensors)")
    ap.add_argument("--config", help="denoiser config JSON (default: EXPORT/config.json)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--forward-runs", type=int, default=15)
    ap.add_argument("--train-runs", type=int, default=11)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--device", default="cpu", help="cpu or cuda (compare with `bench-model --device cuda`)")
    ap.add_argument(
        "--tf32",
        action="store_true",
        help="let cuDNN and cuBLAS round f32 products to TF32 (PyTorch's default for convolutions; "
        "candle computes in full f32, so the output check fails at about 7e-4)",
    )
    a = ap.parse_args()
    torch.backends.cudnn.allow_tf32 = a.tf32
    torch.backends.cuda.matmul.allow_tf32 = a.tf32
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    cfg = json.load(open(a.config or f"{a.export}/config.json"))
    ref = load_file(f"{a.export}/reference.safetensors")
    ray = torch.from_numpy(ref["ray_features"]) if "ray_features" in ref else None
    net = Denoiser(cfg, ray)
    used, stored = load_weights(net, a.weights or f"{a.export}/weights.safetensors")
    params = sum(p.numel() for p in net.parameters())
    dev = torch.device(a.device)
    net = net.to(dev)
    # the clock waits for a GPU; a CPU run never touches CUDA
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)

    # 1. same output as candle on the fixed input
    x1 = torch.from_numpy(ref["x"]).to(dev)
    t1 = torch.from_numpy(ref["t"]).to(dev)
    with torch.no_grad():
        y = net(x1, t1).cpu()
    y_ref = torch.from_numpy(ref["y"])
    rel_l2 = (torch.linalg.norm(y - y_ref) / torch.linalg.norm(y_ref)).item()

    # 2. timings (seeded inputs of the same shapes as bench-model)
    g = torch.Generator().manual_seed(1)
    c, h, w = x1.shape[1:]
    x8 = torch.randn(8, c, h, w, generator=g).to(dev)
    t8 = (torch.rand(8, generator=g) * 0.96 + 0.02).to(dev)
    noise = torch.randn(8, c, h, w, generator=g).to(dev)
    with torch.no_grad():
        f1 = median_ms(lambda: net(x1, t1), a.forward_runs, sync)
        f8 = median_ms(lambda: net(x8, t8), a.forward_runs, sync)
    opt = torch.optim.AdamW(net.parameters(), lr=1e-4)

    def step():
        opt.zero_grad(set_to_none=True)
        loss = F.mse_loss(net(x8, t8), noise)
        loss.backward()
        opt.step()

    cpu0, wall0 = time.process_time(), time.perf_counter()
    tr = median_ms(step, a.train_runs, sync)
    cpu_over_wall = (time.process_time() - cpu0) / (time.perf_counter() - wall0)
    out = {
        "torch": torch.__version__,
        "device": a.device,
        "tf32": a.tf32,
        "threads": a.threads,
        "params": params,
        "weights_loaded": used,
        "weights_stored": stored,
        "output_rel_l2_vs_candle": rel_l2,
        "forward_b1_ms": f1,
        "forward_b8_ms": f8,
        "train_b8_ms": tr,
        "train_cpu_over_wall": cpu_over_wall,
    }
    if not a.json:
        for k, v in out.items():
            print(f"{k:28} {v}", file=sys.stderr)
    print(json.dumps(out))
    if not rel_l2 < 1e-4 and not a.tf32:
        sys.exit(f"PyTorch output differs from candle's: relative L2 {rel_l2:.3g}")


if __name__ == "__main__":
    main()
