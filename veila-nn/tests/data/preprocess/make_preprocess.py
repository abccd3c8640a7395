#!/usr/bin/env python3
"""Reference outputs of Pillow's resampling and of the Hugging Face image processors for veila-nn's
preprocessing tests (veila-nn/tests/it/preprocess.rs). Run by hand, never in CI:

    python3 -m venv target/pyvenv
    target/pyvenv/bin/pip install numpy pillow safetensors transformers torch
    target/pyvenv/bin/python veila-nn/tests/data/preprocess/make_preprocess.py

Writes `preprocess.safetensors` next to this file:

* `image`: the fixed test image, `[45, 67, 3]` uint8 (smooth gradients plus noise, so that every
  filter tap matters and rounding is exercised);
* `pil_{filter}_{h}x{w}`: `PIL.Image.resize((w, h), filter, reducing_gap=None)` of it, uint8, for
  downscales, upscales and mixed sizes, `filter` in `bilinear` / `bicubic`;
* `segformer`: `SegformerImageProcessorPil(size={"height": 32, "width": 48})` pixel values
  `[3, 32, 48]` float32 (bilinear, ImageNet mean/std);
* `depth_anything`: `DPTImageProcessorPil` with the Depth-Anything-V2 `-hf` settings (keep aspect
  ratio, multiple of 14, bicubic, ImageNet mean/std) and a 56x56 target instead of 518x518, so the
  file stays small: pixel values `[3, H, W]` float32.

The versions used are written into the file's metadata.
"""
import json
import os

import numpy as np
import PIL
import transformers
from PIL import Image
from safetensors.numpy import save_file
from transformers import DPTImageProcessorPil, SegformerImageProcessorPil

HERE = os.path.dirname(os.path.abspath(__file__))
IMAGENET_MEAN = [0.485, 0.456, 0.406]
IMAGENET_STD = [0.229, 0.224, 0.225]
SIZES = [
    (20, 30), (8, 9), (90, 201), (37, 80), (100, 50), (45, 67), (44, 67), (13, 131),
    (30, 100), (60, 40), (44, 68), (46, 66), (10, 67), (45, 20), (5, 30),
]


def test_image():
    h, w = 45, 67
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    rng = np.random.default_rng(20261124)
    base = np.stack(
        [
            127 + 120 * np.sin(x / 7.0) * np.cos(y / 5.0),
            255 * x / (w - 1),
            255 * (y / (h - 1)) ** 2,
        ],
        axis=-1,
    )
    noisy = base + rng.normal(0, 30, size=base.shape)
    # a few saturated pixels so that clamping is exercised
    noisy[::9, ::11, :] = 255
    noisy[4::9, 5::11, :] = 0
    return np.clip(np.round(noisy), 0, 255).astype(np.uint8)


def main():
    image = test_image()
    out = {"image": image}
    pil = Image.fromarray(image)
    for name, flt in [("bilinear", Image.BILINEAR), ("bicubic", Image.BICUBIC)]:
        for h, w in SIZES:
            out[f"pil_{name}_{h}x{w}"] = np.asarray(pil.resize((w, h), flt, reducing_gap=None))
    seg = SegformerImageProcessorPil(
        size={"height": 32, "width": 48}, image_mean=IMAGENET_MEAN, image_std=IMAGENET_STD
    )
    out["segformer"] = np.asarray(seg(images=image, return_tensors="np")["pixel_values"][0], np.float32)
    dpt = DPTImageProcessorPil(
        size={"height": 56, "width": 56},
        keep_aspect_ratio=True,
        ensure_multiple_of=14,
        resample=Image.BICUBIC,
        do_pad=False,
        image_mean=IMAGENET_MEAN,
        image_std=IMAGENET_STD,
    )
    out["depth_anything"] = np.asarray(dpt(images=image, return_tensors="np")["pixel_values"][0], np.float32)
    out = {k: np.ascontiguousarray(v) for k, v in out.items()}
    meta = {
        "pillow": PIL.__version__,
        "transformers": transformers.__version__,
        "numpy": np.__version__,
        "sizes": json.dumps(SIZES),
    }
    save_file(out, os.path.join(HERE, "preprocess.safetensors"), metadata=meta)
    for k, v in out.items():
        print(k, v.shape, v.dtype)


if __name__ == "__main__":
    main()
