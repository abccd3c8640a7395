#!/usr/bin/env python3
"""PyTorch yardstick for the Veila denoiser (issues 19 and 45). Run by hand, not by CI.

Builds `veila_nn::Denoiser` in PyTorch -- the whole network: ray features, time embedding, the
residual U-Net, the condition fusion (CACM or its ablations), GCMA at its levels on candle's own
epipolar geometry tensors, PFC -- from safetensors weights with the checkpoint's own parameter
names (strict: every stored tensor used, none missing), checks that its output equals candle's on
the fixed input that `cargo xtask bench-model --export DIR` wrote, and times PyTorch eager on the
same network.

    cargo xtask bench-model --export target/ys                     # the small unconditional network
    cargo xtask bench-model --network paper --export target/ys-paper   # DenoiserConfig::paper()
    cargo xtask bench-model --network bundled --export target/ys-bundled   # models/default
    python3 xtask/scripts/torch_yardstick.py target/ys-paper --batch 1,2 [--json]

Without `--batch` it prints the figures of `bench-model` (forward at batch 1 and 8, one training step
at batch 8, medians, in this process). With `--batch 1,2` it measures one training step (the
condition fusion, forward, MSE loss, backward, AdamW, as `veila bench` times candle) per batch and
`--precision` (f32; bf16: autocast), each in a fresh subprocess: the median step time and the peak
memory (on the CPU the child's peak RSS from `wait4`, cross-checked with its `VmHWM`; on CUDA
`torch.cuda.max_memory_allocated`), and per-sample memory from consecutive batches
((peak(b2) - peak(b1)) / (b2 - b1)). `--json` prints one JSON object (`rows`, `per_sample`, `check`).

On a GPU: `bench-model --device cuda` (a `build-cuda --xtask` build) and `--device cuda` here; PyTorch
then computes in full f32 like candle unless `--tf32`.

Needs `torch` and `numpy` (`pip install torch numpy safetensors`; the CPU is enough; safetensors is
optional). The output check fails (exit 1) above `--tolerance` (1e-5) relative L2.
"""

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import time


def parser():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("export", help="folder written by `cargo xtask bench-model --export`")
    ap.add_argument("--weights", help="denoiser safetensors (default: EXPORT/weights.safetensors)")
    ap.add_argument("--config", help="denoiser config JSON (default: EXPORT/config.json)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--batch", help="comma-separated training batches to measure, each in a fresh process (e.g. 1,2)")
    ap.add_argument("--precision", default="f32", help="with --batch: comma-separated f32, bf16 (autocast)")
    ap.add_argument("--forward-runs", type=int, default=15)
    ap.add_argument("--train-runs", type=int, default=None, help="timed steps (default 11; 5 with --batch)")
    ap.add_argument("--warmup", type=int, default=2, help="untimed steps before the timed ones")
    ap.add_argument("--tolerance", type=float, default=1e-5, help="largest relative L2 against candle")
    ap.add_argument("--no-check", action="store_true", help="skip the output check (timings only)")
    ap.add_argument("--json", action="store_true", help="print only the JSON object (no lines on stderr)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda (compare with `bench-model --device cuda`)")
    ap.add_argument(
        "--tf32",
        action="store_true",
        help="let cuDNN and cuBLAS round f32 products to TF32 (PyTorch's default for convolutions; "
        "candle computes in full f32, so the output check fails at about 7e-4)",
    )
    ap.add_argument("--check-only", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--child-batch", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--child-precision", help=argparse.SUPPRESS)
    return ap


def common_flags(a):
    """The flags a child process inherits."""
    cmd = ["--threads", str(a.threads), "--device", a.device]
    for opt in ("weights", "config"):
        if getattr(a, opt):
            cmd += [f"--{opt}", getattr(a, opt)]
    if a.tf32:
        cmd.append("--tf32")
    return cmd


def run_child(a, batch, precision):
    """Runs one measured configuration in a fresh process; adds its peak RSS and peak_memory_mib.

    The driver never imports torch, so the child's `ru_maxrss` (which counts the memory of the
    process it was forked from until its exec) is the child's own peak."""
    cmd = [sys.executable, os.path.abspath(__file__), a.export, "--child-batch", str(batch),
           "--child-precision", precision, "--train-runs", str(a.train_runs), "--warmup", str(a.warmup)]
    p = subprocess.Popen(cmd + common_flags(a), stdout=subprocess.PIPE)
    out = p.stdout.read()
    p.stdout.close()
    _, status, ru = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode != 0:
        return {"batch": batch, "precision": precision, "device": a.device, "error": f"child exit {p.returncode}"}
    row = json.loads(out.decode().strip().splitlines()[-1])
    row["peak_rss_mib"] = ru.ru_maxrss / 1024  # Linux: KiB
    if a.device.startswith("cuda"):
        row["peak_memory_mib"] = row["cuda_max_allocated_mib"]
        row["peak_memory_source"] = "torch.cuda.max_memory_allocated"
    else:
        row["peak_memory_mib"] = row["peak_rss_mib"]
        row["peak_memory_source"] = "peak RSS of a fresh process (wait4 ru_maxrss)"
    return row


def per_sample(rows):
    """(peak(b2) - peak(b1)) / (b2 - b1) over consecutive measured batches of each configuration."""
    out = []
    groups = {}
    for r in rows:
        if "error" not in r:
            groups.setdefault((r["network"], r["grid"], r["device"], r["precision"]), []).append(r)
    for (net, grid, dev, prec), rs in groups.items():
        rs = sorted(rs, key=lambda r: r["batch"])
        for r1, r2 in zip(rs, rs[1:]):
            if r2["batch"] > r1["batch"]:
                out.append({
                    "network": net, "grid": grid, "device": dev, "precision": prec,
                    "batches": [r1["batch"], r2["batch"]],
                    "per_sample_memory_mib": (r2["peak_memory_mib"] - r1["peak_memory_mib"]) / (r2["batch"] - r1["batch"]),
                    "per_sample_step_ms": (r2["step_ms"] - r1["step_ms"]) / (r2["batch"] - r1["batch"]),
                })
    return out


def driver(a):
    """`--batch`: the output check, then every (precision, batch) in a fresh process; no torch here."""
    precisions = [p.strip() for p in a.precision.split(",") if p.strip()]
    if not precisions or any(p not in ("f32", "bf16") for p in precisions):
        sys.exit(f"--precision: expected f32 and/or bf16, got {a.precision}")
    try:
        batches = [int(b) for b in a.batch.split(",") if b.strip()]
    except ValueError:
        batches = []
    if not batches or min(batches) < 1:
        sys.exit(f"--batch: expected positive batch sizes, got {a.batch}")
    cmd = [sys.executable, os.path.abspath(__file__), a.export, "--check-only", "--json"]
    if a.no_check:
        cmd.append("--no-check")
    r = subprocess.run(cmd + common_flags(a), stdout=subprocess.PIPE)
    if r.returncode != 0 or not r.stdout.strip():
        sys.exit(f"{a.export}: building the network or the output check failed (exit {r.returncode})")
    out = json.loads(r.stdout.decode().strip().splitlines()[-1])
    rows = []
    for p in precisions:
        for b in batches:
            row = run_child(a, b, p)
            if not a.json:
                print(f"{out['network']} {out['grid']} {p} batch {b}: "
                      + (row.get("error") or f"{row['step_ms']:.0f} ms per step, peak {row['peak_memory_mib']:.0f} MiB"),
                      file=sys.stderr, flush=True)
            rows.append(row)
    out["rows"] = rows
    out["per_sample"] = per_sample(rows)
    if not a.json:
        for s in out["per_sample"]:
            print(f"per sample ({s['network']} {s['grid']} {s['device']} {s['precision']}, batches "
                  f"{s['batches'][0]} -> {s['batches'][1]}): {s['per_sample_memory_mib']:.0f} MiB, "
                  f"{s['per_sample_step_ms']:.0f} ms", file=sys.stderr)
    finish(a, out)


def finish(a, out):
    if not a.json:
        for k, v in out.items():
            if k not in ("rows", "per_sample"):
                print(f"{k:28} {v}", file=sys.stderr)
    print(json.dumps(out), flush=True)
    rel = out.get("output_rel_l2_vs_candle")
    if rel is not None and not rel < a.tolerance and not a.tf32:
        sys.exit(f"PyTorch output differs from candle's: relative L2 {rel:.3g} (tolerance {a.tolerance:g})")
    if any("error" in r for r in out.get("rows", [])):
        sys.exit("a measured configuration failed (see its row)")


if __name__ == "__main__":
    _args = parser().parse_args()
    if _args.train_runs is None:
        _args.train_runs = 5 if _args.batch or _args.child_batch else 11
    if _args.batch and not _args.child_batch and not _args.check_only:
        driver(_args)
        sys.exit(0)

import numpy as np  # noqa: E402 (the driver above runs without them)
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402

try:
    from safetensors.numpy import load_file
except ImportError:  # a machine with torch but without the safetensors package (the GPU machine)

    def load_file(path):
        """The safetensors layout: u64 header length, JSON header, then the raw little-endian data."""
        dtypes = {
            "F32": np.float32,
            "F64": np.float64,
            "F16": np.float16,
            "I64": np.int64,
            "U32": np.uint32,
            "U8": np.uint8,
        }
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


def group_norm(channels, max_groups):
    return torch.nn.GroupNorm(groups_for(channels, max_groups), channels, eps=1e-5)


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
    """veila_nn::ResBlock: GN, SiLU, conv, AdaGN(t), SiLU, conv, plus the (projected) skip, scaled."""

    def __init__(self, cin, cout, temb, groups, scale):
        super().__init__()
        self.norm1 = group_norm(cin, groups)
        self.conv1 = RingConv(cin, cout)
        self.emb = torch.nn.Linear(temb, 2 * cout)
        self.norm2 = group_norm(cout, groups)
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
    """veila_nn::Pfc: multi-head self-attention over every position, GroupNorm before, residual."""

    def __init__(self, ch, heads, groups):
        super().__init__()
        self.norm = group_norm(ch, groups)
        self.qkv = Conv1x1(ch, 3 * ch)
        self.proj = Conv1x1(ch, ch)
        self.heads = heads

    def forward(self, x):
        b, c, h, w = x.shape
        n, dh = h * w, c // self.heads
        qkv = self.qkv(self.norm(x)).reshape(b, 3, self.heads, dh, n)
        q, k, v = (qkv[:, i].reshape(b * self.heads, dh, n) for i in range(3))
        logits = q.transpose(1, 2) @ k / math.sqrt(dh)
        attn = torch.softmax(logits.float(), dim=-1).to(logits.dtype)
        out = (v @ attn.transpose(1, 2)).reshape(b, c, h, w)
        return x + self.proj(out)


def masked_softmax(logits, log_w, valid):
    """veila_nn::ops::masked_softmax_last_dim, in f32: w_k exp(s_k) over the valid entries only."""
    dt = logits.dtype
    s = logits.float().clamp(-1e38, 1e38) + log_w.float()
    s_valid = torch.where(valid, s, torch.full_like(s, -3.0e38))
    m = s_valid.amax(dim=-1, keepdim=True)
    m = torch.where(m > -1e38, m, torch.zeros_like(m))
    e = torch.where(valid, (s_valid - m).exp(), torch.zeros_like(s))
    return (e / e.sum(dim=-1, keepdim=True).clamp_min(1e-30)).to(dt)


class Gcma(torch.nn.Module):
    """veila_nn::Gcma: every range pixel attends to the fused image features at its epipolar samples
    (bilinear taps), queries from the range features plus an MLP of the sample points, the
    depth-aware weights as a log-prior; a zero convolution closes the residual branch."""

    def __init__(self, gcfg, channels, feat_channels, groups):
        super().__init__()
        d = gcfg["attn_dim"]
        pe = gcfg["point_encoding"]
        gdim = 3 * 2 * pe["num_freqs"] + (3 if pe["include_input"] else 0)
        self.norm = group_norm(channels, groups)
        self.q = Conv1x1(channels, d)
        self.kv = Conv1x1(feat_channels, 2 * d, bias=False)
        self.pos = torch.nn.ModuleDict({"0": torch.nn.Linear(gdim, d), "2": torch.nn.Linear(d, d)})
        self.out = Conv1x1(d, channels)
        self.d = d
        self.heads = gcfg["num_heads"]

    def forward(self, r, feat, g, keep):
        b, c, h, w = r.shape
        d, heads = self.d, self.heads
        dh = d // heads
        views, (fh, fw) = g["views"], g["feat_size"]
        active = g["active"]
        p, s = active.numel(), g["samples"]
        kv = self.kv(feat).reshape(b, views, 2 * d, fh * fw).permute(0, 1, 3, 2)
        kv = kv.reshape(b, views * fh * fw, 2 * d)
        taps = None
        for corner in range(4):
            term = kv.index_select(1, g[f"corner_idx.{corner}"]) * g[f"corner_w.{corner}"].to(kv.dtype)[None, :, None]
            taps = term if taps is None else taps + term
        taps = taps.reshape(b, p, s, 2, heads, dh)
        keys, vals = taps[:, :, :, 0], taps[:, :, :, 1]
        qr = self.q(self.norm(r)).reshape(b, d, h * w).index_select(2, active)
        qr = qr.transpose(1, 2).reshape(b, p, 1, heads, dh)
        pos = self.pos["2"](F.silu(self.pos["0"](g["point_features"])))
        q = qr + pos.reshape(1, p, s, heads, dh)
        logits = ((q * keys).sum(-1) / math.sqrt(dh)).transpose(2, 3)  # [B, P, heads, S]
        a = masked_softmax(logits, g["log_w"].reshape(1, p, 1, s), g["valid"].reshape(1, p, 1, s))
        vals = vals.permute(0, 1, 3, 2, 4).reshape(b * p * heads, s, dh)
        out = (a.reshape(b * p * heads, 1, s).to(vals.dtype) @ vals).reshape(b, p, d).transpose(1, 2)
        full = torch.zeros(b, d, h * w, dtype=out.dtype, device=out.device).index_add(2, active, out)
        delta = self.out(full.reshape(b, d, h, w))
        if keep is not None:
            delta = delta * keep.to(delta.dtype).reshape(b, 1, 1, 1)
        return r + delta


def resize_to(x, h, w):
    """veila_nn::ops::bilinear_resize (PyTorch's bilinear, align_corners=False; same size: as is)."""
    if tuple(x.shape[2:]) == (h, w):
        return x
    return F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False)


class ScaleFusion(torch.nn.Module):
    """One scale of veila_nn::ConditionFusion: CACM (equations 4-6) or an ablation's `proj`."""

    def __init__(self, cc, i):
        super().__init__()
        sem, dep, out = cc["semantic_channels"], cc["depth_channels"], cc["cond_channels"][i]
        self.kind = "cacm" if cc["cues"] == "both" and cc["fusion"] == "cacm" else cc["cues"]
        if cc["cues"] == "both" and cc["fusion"] == "concat":
            self.kind = "concat"
        self.size = tuple(cc["feature_sizes"][i])
        self.delta = cc["cacm_delta"]
        if self.kind == "cacm":
            self.proj_s = Conv1x1(sem[i], out)
            self.proj_d = Conv1x1(dep[i], out)
            self.conf_s = torch.nn.Conv2d(out, 1, 3, padding=1)
            self.conf_d = torch.nn.Conv2d(out, 1, 3, padding=1)
        elif self.kind == "concat":
            self.proj = Conv1x1(sem[i] + dep[i], out)
        elif self.kind == "semantic_only":
            self.proj = Conv1x1(sem[i], out)
        elif self.kind == "depth_only":
            self.proj = Conv1x1(dep[i], out)
        else:
            raise ValueError(f"unknown conditioning cues/fusion {cc['cues']}/{cc['fusion']}")

    def forward(self, sem, dep):
        h, w = self.size
        if self.kind == "cacm":
            fs = self.proj_s(sem)
            fd = self.proj_d(resize_to(dep, h, w))
            cs = torch.sigmoid(self.conf_s(fs))
            cd = torch.sigmoid(self.conf_d(fd))
            return (fs * cs + fd * cd) / (cs + cd + self.delta)
        if self.kind == "concat":
            return self.proj(torch.cat([sem, resize_to(dep, h, w)], dim=1))
        if self.kind == "semantic_only":
            return self.proj(sem)
        return self.proj(resize_to(dep, h, w))


class Level(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.res = torch.nn.ModuleList()
        self.gcma = None


GEOMETRY_NAMES = ["active"] + [f"corner_{k}.{c}" for c in range(4) for k in ("idx", "w")] + [
    "log_w",
    "valid",
    "point_features",
]


class Denoiser(torch.nn.Module):
    """veila_nn::Denoiser, with its parameter names. `geometry`: {level: {name: array}} as exported."""

    def __init__(self, cfg, ray_features, geometry=None):
        super().__init__()
        self.cfg = cfg
        base = cfg["base_channels"]
        mults = cfg["channel_mults"]
        nrb = cfg["num_res_blocks"]
        groups = cfg["norm_groups"]
        rs = cfg["residual_scale"]
        temb = 4 * base
        nl = len(mults)
        cc = cfg.get("conditioning")
        gc = cc.get("gcma") if cc else None
        self.cc = cc
        self.register_buffer("ray", ray_features, persistent=False)
        in_c = cfg["in_channels"] + (ray_features.shape[1] if ray_features is not None else 0)
        self.in_conv = RingConv(in_c, base)
        self.time = torch.nn.ModuleDict(
            {"0": torch.nn.Linear(cfg["time"]["dim"], temb), "2": torch.nn.Linear(temb, temb)}
        )
        self.gcma_levels = sorted(set(gc["levels"])) if gc else []
        self.geom_meta = {}
        if gc:
            if geometry is None:
                raise ValueError("a GCMA network needs the exported geometry")
            for lev in self.gcma_levels:
                gl = geometry[lev]
                feat = cc["feature_sizes"][self.scale_for_level(lev)]
                self.geom_meta[lev] = {
                    "views": cc["num_views"],
                    "feat_size": tuple(feat),
                    "samples": gl["log_w"].shape[1] if gl["log_w"].ndim == 2 else 0,
                }
                for name in GEOMETRY_NAMES:
                    a = torch.from_numpy(np.ascontiguousarray(gl[name]))
                    if name == "valid":
                        a = a.bool()
                    elif name == "active" or name.startswith("corner_idx"):
                        a = a.long()
                    self.register_buffer(self.geom_key(lev, name), a, persistent=False)

        def gcma_at(level, decoder, ch):
            if gc and level in gc["levels"] and (not decoder or gc["decoder"]):
                fc = cc["cond_channels"][self.scale_for_level(level)]
                return Gcma(gc, ch, fc, groups)
            return None

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
            L.gcma = gcma_at(lev, False, ch)
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
            L.gcma = gcma_at(lev, True, ch)
            if lev > 0:
                L.upsample = RingConv(ch, ch)
            self.up[str(lev)] = L
        self.out_norm = group_norm(ch, groups)
        self.out_conv = RingConv(ch, cfg["out_channels"])
        if cc:
            self.cond = torch.nn.Module()
            self.cond.fuse = torch.nn.ModuleList([ScaleFusion(cc, i) for i in range(len(cc["feature_sizes"]))])
            # the "w/o GCMA" ablation's global condition
            self.cond.pool = torch.nn.Linear(cc["cond_channels"][-1], temb) if not gc else None

    @staticmethod
    def geom_key(level, name):
        return f"geom_{level}_" + name.replace(".", "_")

    def scale_for_level(self, level):
        return min(level, len(self.cc["feature_sizes"]) - 1)

    def geometry(self, level):
        g = dict(self.geom_meta[level])
        for name in GEOMETRY_NAMES:
            g[name] = getattr(self, self.geom_key(level, name))
        return g

    def time_embedding(self, t):
        tc = self.cfg["time"]
        half = tc["dim"] // 2
        j = torch.arange(half, dtype=torch.float64, device=t.device)
        freqs = torch.exp(-math.log(tc["max_period"]) * j / half).to(torch.float32)
        args = (t.float() * tc["input_scale"])[:, None] * freqs[None]
        return torch.cat([torch.cos(args), torch.sin(args)], dim=1)

    def fuse(self, semantic, depth):
        """The fused conditioning maps F^(i) (Denoiser::prepare_condition)."""
        return [f(s, d) for f, s, d in zip(self.cond.fuse, semantic, depth)]

    def forward(self, x, t, fused=None, keep=None):
        emb = self.time["2"](F.silu(self.time["0"](self.time_embedding(t))))
        b = x.shape[0]
        if fused is not None and self.cond.pool is not None:
            last = fused[-1]
            n, cf = last.shape[:2]
            g = self.cond.pool(last.flatten(2).mean(2).reshape(b, n // b, cf).mean(1))
            if keep is not None:
                g = g * keep.to(g.dtype)[:, None]
            emb = emb + g
        emb = F.silu(emb)

        def gcma(blk, h, level):
            if blk is None or fused is None:
                return h
            return blk(h, fused[self.scale_for_level(level)], self.geometry(level), keep)

        if self.ray is not None:
            x = torch.cat([x, self.ray.to(x.dtype).expand(b, -1, -1, -1)], dim=1)
        h = self.in_conv(x)
        skips = [h]
        for lev, L in enumerate(self.down):
            for j, rb in enumerate(L.res):
                h = rb(h, emb)
                if j + 1 == len(L.res):
                    h = gcma(L.gcma, h, lev)
                skips.append(h)
            if len(L.res) == 0:
                h = gcma(L.gcma, h, lev)
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
            h = gcma(L.gcma, h, lev)
            if hasattr(L, "upsample"):
                h = L.upsample(F.interpolate(h, scale_factor=2, mode="nearest"))
        return self.out_conv(F.silu(self.out_norm(h)))


def load_weights(net, path):
    """Copies every parameter from `path` by its candle name; exits unless the names match exactly."""
    tensors = load_file(path)
    state = net.state_dict()
    missing = sorted(k for k in state if k not in tensors)
    unused = sorted(k for k in tensors if k not in state)
    if missing or unused:
        sys.exit(f"{path}: missing parameters {missing[:5]} ({len(missing)}), unused tensors {unused[:5]} ({len(unused)})")
    with torch.no_grad():
        for k, v in state.items():
            src = torch.from_numpy(tensors[k].astype(np.float32))
            if tuple(src.shape) != tuple(v.shape):
                sys.exit(f"{path}: {k} has shape {tuple(src.shape)}, expected {tuple(v.shape)}")
            v.copy_(src)
    return len(state), len(tensors)


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


def build(a, dev):
    """The network of the export on `dev`: (net, cfg, export info, reference tensors, loaded, stored)."""
    cfg = json.load(open(a.config or f"{a.export}/config.json"))
    info_path = f"{a.export}/export.json"
    info = json.load(open(info_path)) if os.path.exists(info_path) else {"network": "small"}
    ref = load_file(f"{a.export}/reference.safetensors")
    ray = torch.from_numpy(ref["ray_features"]) if "ray_features" in ref else None
    geometry = {}
    for lev in info.get("gcma_levels", []):
        geometry[lev] = {name: ref[f"gcma.{lev}.{name}"] for name in GEOMETRY_NAMES}
    net = Denoiser(cfg, ray, geometry or None)
    used, stored = load_weights(net, a.weights or f"{a.export}/weights.safetensors")
    return net.to(dev), cfg, info, ref, used, stored


def make_inputs(cfg, b, dev, seed=1):
    """Seeded inputs of batch `b`: x, t, the target, the encoder features, keep (all 1)."""
    g = torch.Generator().manual_seed(seed)
    h, w = cfg["sensor"]["rows"], cfg["sensor"]["cols"]
    x = torch.randn(b, cfg["in_channels"], h, w, generator=g)
    t = torch.rand(b, generator=g) * 0.9 + 0.05
    target = torch.randn(b, cfg["out_channels"], h, w, generator=g)
    cc = cfg.get("conditioning")
    sem = dep = keep = None
    if cc:
        n = b * cc["num_views"]
        sem = [torch.randn(n, c, fh, fw, generator=g) for c, (fh, fw) in zip(cc["semantic_channels"], cc["feature_sizes"])]
        dep = [torch.randn(n, c, fh, fw, generator=g) for c, (fh, fw) in zip(cc["depth_channels"], cc["feature_sizes"])]
        if cc["cues"] == "semantic_only":
            dep = [None] * len(sem)
        if cc["cues"] == "depth_only":
            sem = [None] * len(dep)
        sem = [s.to(dev) if s is not None else None for s in sem]
        dep = [d.to(dev) if d is not None else None for d in dep]
        keep = torch.ones(b).to(dev)
    return x.to(dev), t.to(dev), target.to(dev), sem, dep, keep


def conditioned(net, x, t, sem, dep, keep):
    fused = net.fuse(sem, dep) if sem is not None else None
    return net(x, t, fused, keep)


def check(net, ref, dev):
    """Relative L2 of PyTorch's output against candle's on the exported input (and of the fused maps)."""
    x = torch.from_numpy(ref["x"]).to(dev)
    t = torch.from_numpy(ref["t"]).to(dev)
    out = {}
    with torch.no_grad():
        if "keep" in ref:
            n = len([k for k in ref if k.startswith("fused.")])
            def pyramid(cue):
                return [torch.from_numpy(ref[f"{cue}.{i}"]).to(dev) if f"{cue}.{i}" in ref else None for i in range(n)]

            sem, dep = pyramid("semantic"), pyramid("depth")
            fused = net.fuse(sem, dep)
            errs = []
            for i, f in enumerate(fused):
                fr = torch.from_numpy(ref[f"fused.{i}"])
                errs.append((torch.linalg.norm(f.cpu() - fr) / torch.linalg.norm(fr)).item())
            out["fused_rel_l2_vs_candle"] = max(errs)
            y = net(x, t, fused, torch.from_numpy(ref["keep"]).to(dev)).cpu()
        else:
            y = net(x, t).cpu()
    y_ref = torch.from_numpy(ref["y"])
    out["output_rel_l2_vs_candle"] = (torch.linalg.norm(y - y_ref) / torch.linalg.norm(y_ref)).item()
    return out


def train_step_fn(net, inputs, precision, dev):
    x, t, target, sem, dep, keep = inputs
    opt = torch.optim.AdamW(net.parameters(), lr=1e-5)
    bf16 = precision == "bf16"

    def step():
        opt.zero_grad(set_to_none=True)
        with torch.autocast(device_type=dev.type, dtype=torch.bfloat16, enabled=bf16):
            y = conditioned(net, x, t, sem, dep, keep)
        loss = F.mse_loss(y.float(), target)
        loss.backward()
        opt.step()

    return step


def vm_hwm_mib():
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def child(a):
    """One measured configuration in this fresh process; prints one JSON object."""
    dev = torch.device(a.device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    net, cfg, info, _, _, _ = build(a, dev)
    b = a.child_batch
    inputs = make_inputs(cfg, b, dev)
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    step = train_step_fn(net, inputs, a.child_precision, dev)
    ms = median_ms(step, a.train_runs, sync, warmup=a.warmup)
    row = {
        "network": info.get("network", "small"),
        "grid": f"{cfg['sensor']['rows']}x{cfg['sensor']['cols']}",
        "batch": b,
        "device": a.device,
        "precision": a.child_precision,
        "step_ms": ms,
        "train_runs": a.train_runs,
        "vm_hwm_mib": vm_hwm_mib(),
    }
    if dev.type == "cuda":
        row["cuda_max_allocated_mib"] = torch.cuda.max_memory_allocated(dev) / 2**20
        row["cuda_max_reserved_mib"] = torch.cuda.max_memory_reserved(dev) / 2**20
    print(json.dumps(row), flush=True)
    # without the interpreter's teardown, which touches about 100 MiB more than the step itself
    os._exit(0)


def legacy_figures(a, net, cfg, dev, sync):
    """bench-model's figures: forward at batch 1 and 8, one training step at batch 8."""
    in1, in8 = make_inputs(cfg, 1, dev), make_inputs(cfg, 8, dev)
    with torch.no_grad():
        f1 = median_ms(lambda: conditioned(net, *in1[:2], *in1[3:]), a.forward_runs, sync)
        f8 = median_ms(lambda: conditioned(net, *in8[:2], *in8[3:]), a.forward_runs, sync)
    step = train_step_fn(net, in8, "f32", dev)
    cpu0, wall0 = time.process_time(), time.perf_counter()
    tr = median_ms(step, a.train_runs, sync)
    return {
        "forward_b1_ms": f1,
        "forward_b8_ms": f8,
        "train_b8_ms": tr,
        "train_cpu_over_wall": (time.process_time() - cpu0) / (time.perf_counter() - wall0),
    }


def main(a):
    torch.backends.cudnn.allow_tf32 = a.tf32
    torch.backends.cuda.matmul.allow_tf32 = a.tf32
    torch.set_num_threads(a.threads)
    torch.manual_seed(0)
    if a.child_batch:
        return child(a)
    dev = torch.device(a.device)
    # the clock waits for a GPU; a CPU run never touches CUDA
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    net, cfg, info, ref, used, stored = build(a, dev)
    out = {
        "torch": torch.__version__,
        "network": info.get("network", "small"),
        "grid": f"{cfg['sensor']['rows']}x{cfg['sensor']['cols']}",
        "device": a.device,
        "tf32": a.tf32,
        "threads": a.threads,
        "params": sum(p.numel() for p in net.parameters()),
        "weights_loaded": used,
        "weights_stored": stored,
    }
    if not a.no_check:
        out.update(check(net, ref, dev))
    if a.check_only:
        # the driver judges the figure, after the measurements
        print(json.dumps(out), flush=True)
        return
    out.update(legacy_figures(a, net, cfg, dev, sync))
    finish(a, out)


if __name__ == "__main__":
    main(_args)
