#!/usr/bin/env python3
"""Builds the tiny random-weight Depth-Anything fixtures of tests/fixtures/depth_anything_tiny/ with PyPI's
transformers.

Requirements (not needed by CI, which only reads the committed fixtures):
    ~/.cache/gaps/venv/bin/pip install transformers
Usage:
    ~/.cache/gaps/venv/bin/python tests/scripts/make_depth_anything_fixtures.py [OUT_DIR]

OUT_DIR (default tests/fixtures/depth_anything_tiny) receives
  model/        a transformers-layout DepthAnythingForDepthEstimation folder (config.json, model.safetensors in
                fp32, preprocessor_config.json): a 4-layer DINOv2 backbone of width 32 with non-trivial layer
                scales and a DPT neck and head of widths 8..32, every weight drawn at random;
  reference/    for two images whose sides are not multiples of 14 (one enlarged, one reduced by the
                processor): the uint8 image, the processor's pixel_values, the backbone's feature maps, the raw
                predicted depth and the depth post-processed back to the image size, as safetensors
                (reference/<name>.safetensors), plus reference/versions.json.
"""
import json
import math
import os
import sys

import numpy as np
import torch
from safetensors.torch import save_file

import transformers
from transformers import AutoImageProcessor, DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config
from transformers.image_utils import IMAGENET_DEFAULT_MEAN, IMAGENET_DEFAULT_STD
from transformers.models.dpt.image_processing_dpt import DPTImageProcessor

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = sys.argv[1] if len(sys.argv) > 1 else os.path.join(HERE, "..", "fixtures", "depth_anything_tiny")
MODEL = os.path.join(OUT, "model")
REF = os.path.join(OUT, "reference")

# (name, height, width): both sides off the multiples of 14; the processor's target is 70 x 70.
IMAGES = [("enlarged", 45, 61), ("reduced", 100, 77)]


def tiny_config():
    backbone = Dinov2Config(hidden_size=32, num_hidden_layers=4, num_attention_heads=2, mlp_ratio=2, image_size=56,
                            patch_size=14, out_indices=[1, 2, 3, 4], reshape_hidden_states=False,
                            layerscale_value=0.7)
    return DepthAnythingConfig(backbone_config=backbone, reassemble_hidden_size=32, reassemble_factors=[4, 2, 1, 0.5],
                               neck_hidden_sizes=[8, 16, 24, 32], fusion_hidden_size=8, head_hidden_size=8)


def randomize(model, generator):
    """Every parameter drawn at random, at magnitudes that keep activations of order one, so that any
    mistake in any part of the forward shows in the output."""
    with torch.no_grad():
        for name, p in model.named_parameters():
            noise = torch.randn(p.shape, generator=generator)
            if name.endswith("lambda1"):
                p.copy_(0.6 + 0.2 * noise)
            elif "norm" in name and name.endswith("weight"):
                p.copy_(1.0 + 0.2 * noise)
            elif name.endswith("bias") or "token" in name or "position_embeddings" in name:
                p.copy_(0.2 * noise if p.dim() == 1 else 0.5 * noise)
            else:
                fan_in = p[0].numel() if p.dim() > 1 else p.numel()
                p.copy_(noise / math.sqrt(fan_in))
        # Most of the relative depth above the final ReLU, some of it below (so the ReLU matters).
        model.head.conv3.bias.fill_(-0.6)


def test_image(height, width, seed):
    """A smooth pattern plus noise, as uint8 H x W x 3."""
    g = torch.Generator().manual_seed(seed)
    y = torch.linspace(0, 1, height)[:, None, None]
    x = torch.linspace(0, 1, width)[None, :, None]
    phase = torch.tensor([0.0, 1.0, 2.0])[None, None, :]
    base = 0.5 + 0.35 * torch.sin(6 * x + 4 * y + phase) * torch.cos(3 * y - phase)
    img = base + 0.1 * torch.randn(height, width, 3, generator=g)
    return (img.clamp(0, 1) * 255).round().to(torch.uint8)


def main():
    torch.manual_seed(0)
    model = DepthAnythingForDepthEstimation(tiny_config()).eval()
    randomize(model, torch.Generator().manual_seed(1))
    # Depth-Anything's processor settings (ImageNet mean and std, aspect kept, multiples of 14, bicubic) at a
    # small target size.
    DPTImageProcessor(size={"height": 70, "width": 70}, keep_aspect_ratio=True, ensure_multiple_of=14, resample=3,
                      do_pad=False, image_mean=IMAGENET_DEFAULT_MEAN,
                      image_std=IMAGENET_DEFAULT_STD).save_pretrained(MODEL)
    model.save_pretrained(MODEL, safe_serialization=True)
    processor = AutoImageProcessor.from_pretrained(MODEL)  # what users of the folder get
    os.makedirs(REF, exist_ok=True)

    for index, (name, height, width) in enumerate(IMAGES):
        image = test_image(height, width, seed=10 + index)
        inputs = processor(images=image.numpy(), return_tensors="pt")
        with torch.no_grad():
            out = model(**inputs)
            features = model.backbone(inputs["pixel_values"]).feature_maps
        post = processor.post_process_depth_estimation(out, target_sizes=[(height, width)])[0]["predicted_depth"]
        depth = out.predicted_depth
        positive = (depth > 0).float().mean().item()
        assert 0.6 < positive < 0.97, f"{name}: {positive:.2f} of the depth is above the ReLU"
        tensors = {"image": image.contiguous(), "pixel_values": inputs["pixel_values"].contiguous(),
                   "predicted_depth": depth.contiguous(), "post_processed_depth": post.contiguous()}
        for i, f in enumerate(features):
            tensors[f"feature_map.{i}"] = f.contiguous()
        save_file(tensors, os.path.join(REF, f"{name}.safetensors"))
        print(name, tuple(image.shape), "->", tuple(inputs["pixel_values"].shape), "depth range",
              depth.min().item(), depth.max().item(), f"positive {positive:.2f}")

    # The native 4 x 4 patch grid (position embeddings used as stored), a batch of two, random pixel values.
    pixel_values = torch.randn(2, 3, 56, 56, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        depth = model(pixel_values=pixel_values).predicted_depth
    save_file({"pixel_values": pixel_values, "predicted_depth": depth.contiguous()},
              os.path.join(REF, "native_grid_batch.safetensors"))

    # The same weights with the metric head (sigmoid times max_depth) on the first image's pixel values.
    metric_config = tiny_config()
    metric_config.depth_estimation_type = "metric"
    metric_config.max_depth = 5
    metric = DepthAnythingForDepthEstimation(metric_config).eval()
    metric.load_state_dict(model.state_dict())
    first = processor(images=test_image(IMAGES[0][1], IMAGES[0][2], seed=10).numpy(), return_tensors="pt")
    with torch.no_grad():
        depth = metric(**first).predicted_depth
    save_file({"pixel_values": first["pixel_values"].contiguous(), "predicted_depth": depth.contiguous()},
              os.path.join(REF, "metric.safetensors"))

    with open(os.path.join(REF, "versions.json"), "w") as f:
        json.dump({"transformers": transformers.__version__, "torch": torch.__version__, "numpy": np.__version__,
                   "images": {name: [h, w] for name, h, w in IMAGES}}, f, indent=2)
        f.write("\n")


if __name__ == "__main__":
    main()
