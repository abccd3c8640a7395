#!/usr/bin/env python3
"""Convert official RangeNet++ / SpareNet PointNet weights into a Veila feature-net bundle.

UNTESTED: the official weights were not available when this was written. The tensor names of
veila-nn's RangeNet (DarkNet presets) and PointNet (sparenet preset) were chosen to equal the
PyTorch state-dict names, so the conversion is a rename-free copy that drops `num_batches_tracked`
and any decoder / segmentation-head tensors. `veila eval --feature-nets OUT` then reports a clear
mismatch (missing / unexpected / mis-shaped tensors by name) if an assumption below is wrong.

    pip install torch safetensors
    python3 xtask/scripts/convert_feature_nets.py \
        --rangenet darknet53-1024/backbone --arch darknet53 --cols 1024 \
        --pointnet cls_model_39.pth --out feature-nets-official

Inputs:
  --rangenet  the `backbone` file of a RangeNet++ archive (darknet21, darknet53, darknet53-1024,
              darknet53-512 from PRBonn/lidar-bonnetal): a pickled module or state dict.
  --pointnet  SpareNet's `Frechet/cls_model_39.pth` (pointnet.pytorch `PointNetCls`, 16 classes).

Remember: even with these weights, Veila's FRD / FPD use different feature layers than R2DM
(global average of the deepest encoder map; max-pooled global PointNet feature), so values are
still not comparable with published numbers.
"""
import argparse
import hashlib
import json
import os

import torch
from safetensors.torch import save_file

RANGENET_MEAN = [12.12, 10.88, 0.23, -1.04, 0.21]
RANGENET_STD = [12.32, 11.47, 6.91, 0.86, 0.16]
BLOCKS = {"darknet21": [1, 1, 2, 2, 1], "darknet53": [1, 2, 8, 8, 4]}


def state_dict(path):
    obj = torch.load(path, map_location="cpu", weights_only=False)
    if hasattr(obj, "state_dict"):
        obj = obj.state_dict()
    if isinstance(obj, dict) and "model_state_dict" in obj:
        obj = obj["model_state_dict"]
    return obj


def clean(sd, keep):
    out = {}
    for k, v in sd.items():
        k = k[len("module."):] if k.startswith("module.") else k
        if k.endswith("num_batches_tracked") or not keep(k):
            continue
        out[k] = v.detach().float().contiguous()
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rangenet", required=True)
    ap.add_argument("--arch", choices=sorted(BLOCKS), default="darknet53")
    ap.add_argument("--cols", type=int, default=1024)
    ap.add_argument("--pointnet", required=True)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)

    # the backbone only: stem (conv1, bn1) and the encoder stages enc1..enc5
    rn = clean(state_dict(a.rangenet),
               lambda k: k.startswith(("conv1.", "bn1.", "enc")))
    save_file(rn, os.path.join(a.out, "rangenet.safetensors"))
    rcfg = {
        "name": f"rangenet-{a.arch}",
        "stem_channels": 32,
        "stages": [{"channels": c, "blocks": b}
                   for c, b in zip([64, 128, 256, 512, 1024], BLOCKS[a.arch])],
        "num_classes": None,
        "head_channels": 32,
        "input_mean": RANGENET_MEAN,
        "input_std": RANGENET_STD,
        # HDL-64E, uniform rows, as veila_geom::LidarSensor::hdl64e() with the archive's width
        "sensor": {"rows": 64, "cols": a.cols, "fov_up_deg": 3.0, "fov_down_deg": -25.0,
                   "min_range_m": 0.5, "max_range_m": 120.0, "beams": {"kind": "uniform"}},
        "leaky_slope": 0.1,
        "bn_eps": 1e-5,
        "bn_momentum": 0.01,
    }
    pn = clean(state_dict(a.pointnet), lambda k: True)
    save_file(pn, os.path.join(a.out, "pointnet.safetensors"))
    pcfg = {
        "name": "pointnet-sparenet",
        "mlp": [64, 128, 1024],
        "head": [512, 256],
        "num_classes": 16,
        "batch_norm": True,
        "input_transform": True,
        "point_scale": 1.0 / 80.0,
        "num_points": None,
        "sample_seed": 0,
        "bn_eps": 1e-5,
        "bn_momentum": 0.1,
    }
    for name, cfg in [("rangenet.json", rcfg), ("pointnet.json", pcfg)]:
        with open(os.path.join(a.out, name), "w") as f:
            json.dump(cfg, f, indent=2)
            f.write("\n")
    files = {}
    for name in ["rangenet.json", "rangenet.safetensors", "pointnet.json", "pointnet.safetensors"]:
        with open(os.path.join(a.out, name), "rb") as f:
            files[name] = hashlib.sha256(f.read()).hexdigest()
    manifest = {"format": 1, "name": "official",
                "description": f"converted from {a.rangenet} ({a.arch}) and {a.pointnet}",
                "files": files}
    with open(os.path.join(a.out, "manifest.json"), "w") as f:
        json.dump(manifest, f, indent=2)
        f.write("\n")


if __name__ == "__main__":
    main()
