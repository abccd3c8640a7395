#!/usr/bin/env python3
"""Reference outputs of the Hugging Face SegFormer and Depth-Anything-V2 models for veila-nn's
encoder parity tests (veila-nn/tests/it/encoder_parity.rs). Run by hand, never in CI.

Setup (CPU wheels into a venv under the worktree's target/):

    python3 -m venv target/pyvenv
    target/pyvenv/bin/pip install torch --index-url https://download.pytorch.org/whl/cpu
    target/pyvenv/bin/pip install transformers safetensors numpy pillow

Small random configs (committed, a few hundred kB; the Rust tests read these):

    target/pyvenv/bin/python veila-nn/tests/data/encoder_parity/make_parity.py

Real architecture configs (DINOv2-S/14 + Depth-Anything-V2-Small head, SegFormer-B0 and -B2,
random weights, hundreds of MB: written outside the repository, never committed):

    target/pyvenv/bin/python veila-nn/tests/data/encoder_parity/make_parity.py --real /tmp/veila-parity
    VEILA_ENCODER_PARITY_DIR=/tmp/veila-parity cargo test --release -p veila-nn --test it encoder_parity::

Each model gives two files: `<name>.safetensors` (the weights, Hugging Face names) and
`<name>_io.safetensors` (`pixel_values` [1, 3, H, W] and the outputs: `stage{i}` the four
multi-scale encoder features, `logits` for SegFormer, `depth` for Depth-Anything). The small configs'
files also hold an end-to-end reference: `pipeline_image` (45 x 67 uint8 RGB) through the
reference processor (`*ImageProcessorPil`), the model and the post-processing back to the image size
(`pipeline_labels` from `post_process_semantic_segmentation`, `pipeline_depth` from
`post_process_depth_estimation`). All weights are
drawn from a fixed seed, with noise added to Hugging Face's initialisation so that LayerNorm and
BatchNorm parameters and running statistics are not the trivial 1/0.
"""
import argparse
import json
import os
import shutil
import tempfile

import torch
from safetensors.torch import save_file
from transformers import (
    DepthAnythingConfig,
    DepthAnythingForDepthEstimation,
    Dinov2Config,
    SegformerConfig,
    SegformerForSemanticSegmentation,
)

HERE = os.path.dirname(os.path.abspath(__file__))


def perturb(model, seed):
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=g))
        for name, b in model.named_buffers():
            if name.endswith("running_mean"):
                b.copy_(0.1 * torch.randn(b.shape, generator=g))
            elif name.endswith("running_var"):
                b.copy_(0.5 + torch.rand(b.shape, generator=g))
    model.eval()


def save_weights(model, path):
    """Saves with `save_pretrained`, which writes the checkpoint (Hub) tensor names: transformers 5
    renames some modules in memory (`linear_c` -> `linear_projections`, `attention.attention.query`
    -> `attention.q_proj`) and maps the names back when saving."""
    with tempfile.TemporaryDirectory() as tmp:
        model.save_pretrained(tmp, safe_serialization=True)
        shutil.copyfile(os.path.join(tmp, "model.safetensors"), path)


IMAGENET_MEAN = [0.485, 0.456, 0.406]
IMAGENET_STD = [0.229, 0.224, 0.225]


def pipeline_image(seed, h=45, w=67):
    """A fixed uint8 RGB image for the end-to-end pipeline references."""
    import numpy as np

    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    base = np.stack([127 + 100 * np.sin(x / 6.0), 255 * x / (w - 1), 255 * y / (h - 1)], axis=-1)
    return np.clip(np.round(base + rng.normal(0, 25, base.shape)), 0, 255).astype(np.uint8)


def segformer(name, cfg, height, width, out_dir, seed, pipeline=False):
    torch.manual_seed(seed)
    model = SegformerForSemanticSegmentation(cfg)
    perturb(model, seed + 1)
    g = torch.Generator().manual_seed(seed + 2)
    x = torch.randn(1, 3, height, width, generator=g)
    with torch.no_grad():
        out = model(pixel_values=x, output_hidden_states=True)
    io = {"pixel_values": x}
    for i, h in enumerate(out.hidden_states):
        io[f"stage{i}"] = h.contiguous()
    io["logits"] = out.logits.contiguous()
    if pipeline:
        # processor (resize to the model size, bilinear), model, post-processing to the image size
        from transformers import SegformerImageProcessorPil

        image = pipeline_image(seed + 3)
        proc = SegformerImageProcessorPil(
            size={"height": height, "width": width}, image_mean=IMAGENET_MEAN, image_std=IMAGENET_STD
        )
        pv = proc(images=image, return_tensors="pt").pixel_values
        with torch.no_grad():
            o = model(pixel_values=pv)
        labels = proc.post_process_semantic_segmentation(o, target_sizes=[image.shape[:2]])[0]
        io["pipeline_image"] = torch.from_numpy(image).contiguous()
        io["pipeline_labels"] = labels.to(torch.int64).contiguous()
    save_weights(model, os.path.join(out_dir, f"{name}.safetensors"))
    save_file(io, os.path.join(out_dir, f"{name}_io.safetensors"))
    return {k: list(v.shape) for k, v in io.items()}


def depth_anything(name, cfg, height, width, out_dir, seed, pipeline=False):
    torch.manual_seed(seed)
    model = DepthAnythingForDepthEstimation(cfg)
    perturb(model, seed + 1)
    g = torch.Generator().manual_seed(seed + 2)
    x = torch.randn(1, 3, height, width, generator=g)
    captured = {}

    def hook(_module, _inputs, output):
        captured["reassembled"] = [o.detach().clone() for o in output]

    handle = model.neck.reassemble_stage.register_forward_hook(hook)
    with torch.no_grad():
        out = model(pixel_values=x)
    handle.remove()
    io = {"pixel_values": x}
    for i, h in enumerate(captured["reassembled"]):
        io[f"stage{i}"] = h.contiguous()
    io["depth"] = out.predicted_depth.contiguous()
    if pipeline:
        # the -hf processor settings with a target of the model's size and its patch multiple
        from transformers import DPTImageProcessorPil

        image = pipeline_image(seed + 3)
        proc = DPTImageProcessorPil(
            size={"height": height, "width": width},
            keep_aspect_ratio=True,
            ensure_multiple_of=cfg.patch_size,
            resample=3,
            do_pad=False,
            image_mean=IMAGENET_MEAN,
            image_std=IMAGENET_STD,
        )
        pv = proc(images=image, return_tensors="pt").pixel_values
        with torch.no_grad():
            o = model(pixel_values=pv)
        depth = proc.post_process_depth_estimation(o, target_sizes=[image.shape[:2]])[0]["predicted_depth"]
        io["pipeline_image"] = torch.from_numpy(image).contiguous()
        io["pipeline_depth"] = depth.contiguous()
    save_weights(model, os.path.join(out_dir, f"{name}.safetensors"))
    save_file(io, os.path.join(out_dir, f"{name}_io.safetensors"))
    return {k: list(v.shape) for k, v in io.items()}


# Input sizes (height, width) for the processor's output-size rule: KITTI, nuScenes, exact and
# non-integer scales, and widths that land on a tie (x.5 multiples of 14, rounded half to even).
PROCESSOR_SIZES = [
    (375, 1242), (376, 1241), (370, 1226), (900, 1600), (518, 518), (100, 50), (1000, 3000),
    (64, 64), (259, 259), (7, 7), (518, 21), (518, 35), (518, 49), (600, 20), (1242, 375),
]


def processor_sizes(out_dir):
    """Output sizes of the Depth-Anything-V2 `-hf` processor settings (DPTImageProcessor, 518 x 518,
    keep_aspect_ratio, ensure_multiple_of 14, bicubic) for PROCESSOR_SIZES."""
    import numpy as np
    from transformers import DPTImageProcessorPil as DPTImageProcessor

    proc = DPTImageProcessor(
        do_resize=True,
        size={"height": 518, "width": 518},
        keep_aspect_ratio=True,
        ensure_multiple_of=14,
        resample=3,
        do_pad=False,
    )
    rows = []
    for h, w in PROCESSOR_SIZES:
        out = proc(images=np.zeros((h, w, 3), dtype=np.uint8), return_tensors="pt").pixel_values
        rows.append({"input": [h, w], "output": list(out.shape[-2:])})
    with open(os.path.join(out_dir, "depth_anything_processor_sizes.json"), "w") as f:
        json.dump(rows, f, indent=1)
        f.write("\n")
    return rows


def small(out_dir):
    info = {}
    info["depth_anything_processor_sizes"] = processor_sizes(out_dir)
    seg = SegformerConfig(
        num_channels=3,
        num_encoder_blocks=4,
        depths=[1, 2, 1, 1],
        sr_ratios=[4, 2, 2, 1],
        hidden_sizes=[8, 16, 24, 32],
        patch_sizes=[7, 3, 3, 3],
        strides=[4, 2, 2, 2],
        num_attention_heads=[1, 2, 3, 4],
        mlp_ratios=[2, 2, 3, 4],
        hidden_act="gelu",
        decoder_hidden_size=16,
        num_labels=5,
        layer_norm_eps=1e-6,
    )
    # 72 x 52: non-square, not a multiple of 32 (odd stage sizes exercise the padding and upsampling)
    info["segformer_small"] = segformer("segformer_small", seg, 72, 52, out_dir, 1400, pipeline=True)
    backbone = Dinov2Config(
        hidden_size=16,
        num_hidden_layers=4,
        num_attention_heads=2,
        mlp_ratio=2,
        patch_size=4,
        image_size=32,
        layerscale_value=0.5,
        out_indices=[1, 2, 3, 4],
        apply_layernorm=True,
        reshape_hidden_states=False,
    )
    da = DepthAnythingConfig(
        backbone_config=backbone,
        patch_size=4,
        reassemble_hidden_size=16,
        reassemble_factors=[4, 2, 1, 0.5],
        neck_hidden_sizes=[4, 8, 12, 16],
        fusion_hidden_size=8,
        head_hidden_size=4,
        depth_estimation_type="relative",
        max_depth=1,
    )
    # 24 x 44 pixels: a 6 x 11 patch grid against the stored 8 x 8 position grid (shrink one side,
    # grow the other) so that position-embedding resampling is exercised.
    info["depth_anything_small"] = depth_anything(
        "depth_anything_small", da, 24, 44, out_dir, 1410, pipeline=True
    )
    return info


def real(out_dir):
    os.makedirs(out_dir, exist_ok=True)
    info = {}
    backbone = Dinov2Config(
        hidden_size=384,
        num_hidden_layers=12,
        num_attention_heads=6,
        mlp_ratio=4,
        patch_size=14,
        image_size=518,
        layerscale_value=1.0,
        out_indices=[3, 6, 9, 12],
        apply_layernorm=True,
        reshape_hidden_states=False,
    )
    da = DepthAnythingConfig(
        backbone_config=backbone,
        patch_size=14,
        reassemble_hidden_size=384,
        reassemble_factors=[4, 2, 1, 0.5],
        neck_hidden_sizes=[48, 96, 192, 384],
        fusion_hidden_size=64,
        head_hidden_size=32,
        depth_estimation_type="relative",
        max_depth=1,
    )
    # KITTI-like aspect after the Depth-Anything processor: short side 518, width a multiple of 14
    info["depth_anything_v2_small"] = depth_anything("depth_anything_v2_small", da, 518, 1708, out_dir, 2400)
    b0 = SegformerConfig(hidden_sizes=[32, 64, 160, 256], depths=[2, 2, 2, 2], decoder_hidden_size=256, num_labels=19)
    info["segformer_b0"] = segformer("segformer_b0", b0, 512, 1024, out_dir, 2410)
    b2 = SegformerConfig(hidden_sizes=[64, 128, 320, 512], depths=[3, 4, 6, 3], decoder_hidden_size=768, num_labels=19)
    info["segformer_b2"] = segformer("segformer_b2", b2, 512, 1024, out_dir, 2420)
    return info


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--real", metavar="DIR", help="write the real-architecture files to DIR (outside the repository)")
    args = ap.parse_args()
    torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))
    if args.real:
        out_dir = args.real
        info = real(out_dir)
    else:
        out_dir = HERE
        info = small(out_dir)
    import transformers

    info["versions"] = {"torch": torch.__version__, "transformers": transformers.__version__}
    with open(os.path.join(out_dir, "shapes.json"), "w") as f:
        json.dump(info, f, indent=1, sort_keys=True)
        f.write("\n")
    print(json.dumps(info, indent=1, sort_keys=True))


if __name__ == "__main__":
    main()
