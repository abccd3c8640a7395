#!/usr/bin/env python3
"""PyTorch yardstick of `veila_nn::segmenter::Segmenter` (issue 56). Run by hand, not by CI.

Builds the segmenter of `SegmenterConfig::tiny()` in PyTorch from the module docs of
`veila-nn/src/segmenter/mod.rs` (not from candle code), draws every tensor by its candle name with
a seeded numpy generator (BatchNorm statistics and affine parameters too, so that the inference
path is not the identity), loads them strictly (every name used, none missing), runs a fixed input
with empty pixels, and writes, next to this script:

* `tiny_config.json`: the config (serde form of `SegmenterConfig`);
* `tiny_weights.safetensors`: the weights by candle name;
* `tiny_io.safetensors`: `input` [2, 6, 16, 64], `logits_eval` (BatchNorm on running statistics)
  and `logits_train` (BatchNorm on batch statistics), all float32, computed in float64.

The Rust test `veila-nn/tests/it/segmenter.rs` loads the weights into candle's network and must
match both outputs within 1e-5 relative L2.

    python3 -m venv venv && venv/bin/pip install torch numpy safetensors
    venv/bin/python veila-nn/tests/data/segmenter/segmenter_yardstick.py
"""

import json
import os

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from safetensors.numpy import save_file

HERE = os.path.dirname(os.path.abspath(__file__))

CFG = {
    "name": "seg-tiny",
    "rows": 16,
    "cols": 64,
    "num_classes": 5,
    "stem_channels": 4,
    "stages": [
        {"channels": 6, "blocks": 1, "stride": [1, 1]},
        {"channels": 8, "blocks": 2, "stride": [2, 2]},
        {"channels": 8, "blocks": 1, "stride": [1, 2]},
    ],
    "head_channels": 6,
    "input_mean": [12.12, 10.88, 0.23, -1.04, 0.21],
    "input_std": [12.32, 11.47, 6.91, 0.86, 0.16],
    "leaky_slope": 0.1,
    "bn_eps": 1e-5,
    "bn_momentum": 0.01,
}
IN_CHANNELS = 6


class CBA(nn.Module):
    """Conv (no bias; 3x3 wraps the columns, zero-pads the rows) + BatchNorm (+ LeakyReLU)."""

    def __init__(self, cin, cout, k, stride, act):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, k, stride=tuple(stride), padding=0, bias=False)
        self.bn = nn.BatchNorm2d(cout, eps=CFG["bn_eps"], momentum=CFG["bn_momentum"])
        self.k, self.act = k, act

    def forward(self, x):
        p = self.k // 2
        if p:
            x = F.pad(x, (p, p, 0, 0), mode="circular")
            x = F.pad(x, (0, 0, p, p))
        y = self.bn(self.conv(x))
        return F.leaky_relu(y, CFG["leaky_slope"]) if self.act else y


class Block(nn.Module):
    """ResNet basic block with the names conv1/bn1, conv2/bn2, down.{conv,bn}."""

    def __init__(self, cin, cout, stride):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride=tuple(stride), bias=False)
        self.bn1 = nn.BatchNorm2d(cout, eps=CFG["bn_eps"], momentum=CFG["bn_momentum"])
        self.conv2 = nn.Conv2d(cout, cout, 3, bias=False)
        self.bn2 = nn.BatchNorm2d(cout, eps=CFG["bn_eps"], momentum=CFG["bn_momentum"])
        self.down = CBA(cin, cout, 1, stride, False) if (cin != cout or list(stride) != [1, 1]) else None

    @staticmethod
    def ring(x):
        return F.pad(F.pad(x, (1, 1, 0, 0), mode="circular"), (0, 0, 1, 1))

    def forward(self, x):
        s = CFG["leaky_slope"]
        y = F.leaky_relu(self.bn1(self.conv1(self.ring(x))), s)
        y = self.bn2(self.conv2(self.ring(y)))
        skip = self.down(x) if self.down is not None else x
        return F.leaky_relu(y + skip, s)


class Segmenter(nn.Module):
    def __init__(self):
        super().__init__()
        sc, hc = CFG["stem_channels"], CFG["head_channels"]
        self.stem = nn.ModuleList([CBA(IN_CHANNELS, sc, 3, [1, 1], True), CBA(sc, sc, 3, [1, 1], True)])
        c, concat = sc, sc
        self.stage_names = []
        for i, st in enumerate(CFG["stages"]):
            blocks = nn.Module()
            for j in range(st["blocks"]):
                cin, stride = (c, st["stride"]) if j == 0 else (st["channels"], [1, 1])
                setattr(blocks, f"block{j}", Block(cin, st["channels"], stride))
            setattr(self, f"stage{i + 1}", blocks)
            self.stage_names.append((f"stage{i + 1}", st["blocks"]))
            c = st["channels"]
            concat += c
        self.head = nn.Module()
        self.head.fuse1 = CBA(concat, hc, 3, [1, 1], True)
        self.head.fuse2 = CBA(hc, hc, 3, [1, 1], True)
        self.head.classifier = nn.Conv2d(hc, CFG["num_classes"], 1, bias=True)

    def forward(self, x):
        rows, cols = x.shape[2], x.shape[3]
        h = self.stem[1](self.stem[0](x))
        levels = [h]
        for name, n in self.stage_names:
            for j in range(n):
                h = getattr(getattr(self, name), f"block{j}")(h)
            levels.append(F.interpolate(h, size=(rows, cols), mode="bilinear", align_corners=False))
        f = self.head.fuse2(self.head.fuse1(torch.cat(levels, 1)))
        return self.head.classifier(f)


def draw_weights(model, rng):
    """Every tensor of the state dict (bar num_batches_tracked), drawn by name."""
    out = {}
    for name, t in model.state_dict().items():
        if name.endswith("num_batches_tracked"):
            continue
        shape = tuple(t.shape)
        if name.endswith("running_var"):
            v = rng.uniform(0.5, 2.0, shape)
        elif name.endswith("running_mean") or name.endswith("bias"):
            v = rng.normal(0.0, 0.2, shape)
        elif name.endswith("bn.weight") or ".bn" in name and name.endswith("weight"):
            v = rng.uniform(0.5, 1.5, shape)
        else:  # convolution weights
            fan_in = int(np.prod(shape[1:]))
            v = rng.normal(0.0, np.sqrt(2.0 / fan_in), shape)
        out[name] = v.astype(np.float32)
    return out


def main():
    rng = np.random.default_rng(56)
    torch.manual_seed(0)
    model = Segmenter().double()
    weights = draw_weights(model, rng)
    state = {k: torch.from_numpy(v.astype(np.float64)) for k, v in weights.items()}
    missing, unexpected = model.load_state_dict(state, strict=False)
    missing = [m for m in missing if not m.endswith("num_batches_tracked")]
    assert not missing and not unexpected, (missing, unexpected)

    b, rows, cols = 2, CFG["rows"], CFG["cols"]
    x = rng.normal(0.0, 1.0, (b, IN_CHANNELS, rows, cols))
    mask = (rng.uniform(size=(b, rows, cols)) > 0.2).astype(np.float64)
    x[:, :5] *= mask[:, None]
    x[:, 5] = mask
    x = x.astype(np.float32)
    xt = torch.from_numpy(x.astype(np.float64))

    model.eval()
    with torch.no_grad():
        logits_eval = model(xt).numpy().astype(np.float32)
    model.train()
    with torch.no_grad():
        logits_train = model(xt).numpy().astype(np.float32)

    save_file(weights, os.path.join(HERE, "tiny_weights.safetensors"))
    save_file(
        {"input": x, "logits_eval": logits_eval, "logits_train": logits_train},
        os.path.join(HERE, "tiny_io.safetensors"),
    )
    with open(os.path.join(HERE, "tiny_config.json"), "w") as f:
        json.dump(CFG, f, indent=2)
        f.write("\n")
    n_params = sum(v.size for k, v in weights.items() if "running" not in k)
    print(f"{len(weights)} tensors, {n_params} trainable parameters; logits {logits_eval.shape}")


if __name__ == "__main__":
    main()
