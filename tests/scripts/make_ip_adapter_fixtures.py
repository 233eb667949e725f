#!/usr/bin/env python3
"""Builds the tiny random-weight IP-Adapter fixtures of tests/fixtures/ip_adapter_tiny/ with PyPI's
diffusers and transformers, for the SDXL model of tests/fixtures/sdxl_tiny/ (make_sdxl_fixtures.py).

Requirements (not needed by CI, which only reads the committed fixtures):
    ~/.cache/gaps/venv/bin/pip install diffusers transformers accelerate
Usage:
    ~/.cache/gaps/venv/bin/python tests/scripts/make_ip_adapter_fixtures.py [OUT_DIR]

OUT_DIR (default tests/fixtures/ip_adapter_tiny) receives
  image_encoder/            a transformers CLIPVisionModelWithProjection folder (config.json,
                            model.safetensors) at tiny sizes (32 x 32 input, 8 x 8 patches, gelu);
  ip_adapter.safetensors    IP-Adapter weights in diffusers' single-file layout (image_proj.proj/norm,
                            ip_adapter.<1, 3, 5, ...>.to_k_ip/to_v_ip for the UNet's cross-attention layers);
  reference/                encoder.safetensors: two reference images (H x W x 3 in [0, 1], 8-bit
                            values), their pixel_values after diffusers' default CLIPImageProcessor and
                            the encoder's image_embeds (and pooled, last_hidden_state);
                            projection.safetensors: the projected image tokens of those embeddings and
                            of zeros (the negative image prompt);
                            unet.safetensors: one UNet forward with the adapter at scale 0.5;
                            img2img.safetensors (+ img2img.json): a 2-of-4-step img2img run of two
                            images with ip_adapter_image (the first reference), scale 0.5, guidance 5
                            and seed 1234.
"""
import json
import os
import sys

import numpy as np
import torch
from PIL import Image
from safetensors.torch import save_file

import diffusers
import transformers
from diffusers import StableDiffusionXLImg2ImgPipeline
from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection

from reference_tensors import reference_saver

HERE = os.path.dirname(os.path.abspath(__file__))
SDXL_MODEL = os.path.join(HERE, "..", "fixtures", "sdxl_tiny", "model")
OUT = sys.argv[1] if len(sys.argv) > 1 else os.path.join(HERE, "..", "fixtures", "ip_adapter_tiny")
REF = os.path.join(OUT, "reference")
save = reference_saver(REF)
SCALE = 0.5


def randomize(module, g):
    # Random (not default-initialised) weights everywhere, scaled by fan-in; norms near one.
    with torch.no_grad():
        for name, p in module.named_parameters():
            if name.endswith("weight") and p.ndim == 1 and "norm" in name:
                p.copy_(1 + 0.1 * torch.randn(p.shape, generator=g))
            else:
                p.copy_(torch.randn(p.shape, generator=g) / max(1, p[0].numel()) ** 0.5)


def ip_adapter_state_dict(unet, image_embed_dim, g):
    """diffusers' single-file IP-Adapter layout for this UNet: attention layers numbered in the order of
    unet.attn_processors, the cross-attention (attn2) layers taking the odd numbers 1, 3, 5, ..."""
    cross = unet.config.cross_attention_dim
    sd = {"image_proj.proj.weight": torch.randn(4 * cross, image_embed_dim, generator=g) / image_embed_dim ** 0.5,
          "image_proj.proj.bias": 0.1 * torch.randn(4 * cross, generator=g),
          "image_proj.norm.weight": 1 + 0.1 * torch.randn(cross, generator=g),
          "image_proj.norm.bias": 0.1 * torch.randn(cross, generator=g)}
    key_id = 1
    modules = dict(unet.named_modules())
    for name in unet.attn_processors:
        if name.endswith("attn1.processor"):
            continue
        hidden = modules[name[: -len(".processor")]].to_k.out_features
        for kv in ("to_k_ip", "to_v_ip"):
            sd[f"ip_adapter.{key_id}.{kv}.weight"] = torch.randn(hidden, cross, generator=g) / cross ** 0.5
        key_id += 2
    return sd


def main():
    os.makedirs(REF, exist_ok=True)
    g = torch.Generator().manual_seed(7)
    pipe = StableDiffusionXLImg2ImgPipeline.from_pretrained(SDXL_MODEL)
    pipe.set_progress_bar_config(disable=True)

    config = CLIPVisionConfig(hidden_size=32, intermediate_size=37, num_hidden_layers=3, num_attention_heads=4,
                              image_size=32, patch_size=8, projection_dim=24, hidden_act="gelu",
                              layer_norm_eps=1e-5)
    encoder = CLIPVisionModelWithProjection(config).eval()
    randomize(encoder, g)
    encoder.save_pretrained(os.path.join(OUT, "image_encoder"), safe_serialization=True)
    save_file(ip_adapter_state_dict(pipe.unet, config.projection_dim, g), os.path.join(OUT, "ip_adapter.safetensors"))

    # diffusers' loader: the image encoder from image_encoder/, a default CLIPImageProcessor at the
    # encoder's image size, decoupled cross-attention processors in every attn2, the image projection.
    pipe.load_ip_adapter(OUT, subfolder="", weight_name="ip_adapter.safetensors", image_encoder_folder="image_encoder")
    pipe.set_ip_adapter_scale(SCALE)
    unet = pipe.unet

    # Two 8-bit reference images: 48 x 64 (shortest side and center crop) and 40 x 40.
    refs = [torch.randint(0, 256, (48, 64, 3), generator=g, dtype=torch.uint8),
            torch.randint(0, 256, (40, 40, 3), generator=g, dtype=torch.uint8)]
    pil_refs = [Image.fromarray(r.numpy()) for r in refs]
    with torch.no_grad():
        pixel_values = [pipe.feature_extractor(p, return_tensors="pt").pixel_values for p in pil_refs]
        outputs = [encoder(pv) for pv in pixel_values]
        save("encoder", {"image_0": refs[0].float() / 255, "image_1": refs[1].float() / 255,
                         "pixel_values_0": pixel_values[0], "pixel_values_1": pixel_values[1],
                         "image_embeds": torch.cat([o.image_embeds for o in outputs]),
                         "last_hidden_state": torch.cat([o.last_hidden_state for o in outputs])})
        image_embeds = torch.cat([o.image_embeds for o in outputs])  # 2 x 24

        projection = unet.encoder_hid_proj.image_projection_layers[0]
        save("projection", {"image_embeds": image_embeds, "tokens": projection(image_embeds),
                            "negative_tokens": projection(torch.zeros_like(image_embeds))})

        # One UNet forward with the adapter: image_embeds per adapter as B x images x E.
        sample = torch.randn(2, 4, 8, 6, generator=g)
        timestep = torch.tensor([999.0, 421.0])
        context = torch.randn(2, 7, 64, generator=g)
        text_embeds = torch.randn(2, 32, generator=g)
        time_ids = torch.tensor([[64.0, 48.0, 0.0, 0.0, 64.0, 48.0], [1024.0, 768.0, 8.0, 16.0, 1024.0, 1024.0]])
        out = unet(sample, timestep, encoder_hidden_states=context,
                   added_cond_kwargs={"text_embeds": text_embeds, "time_ids": time_ids,
                                      "image_embeds": [image_embeds[:, None]]}).sample
        pipe.set_ip_adapter_scale(0.0)
        out_without = unet(sample, timestep, encoder_hidden_states=context,
                           added_cond_kwargs={"text_embeds": text_embeds, "time_ids": time_ids,
                                              "image_embeds": [image_embeds[:, None]]}).sample
        pipe.set_ip_adapter_scale(SCALE)
        assert (out - out_without).abs().max() > 1e-3, "the adapter must change the UNet's output"
        save("unet", {"sample": sample, "timestep": timestep, "encoder_hidden_states": context,
                      "text_embeds": text_embeds, "time_ids": time_ids, "image_embeds": image_embeds, "out": out})

        # 2-step img2img (strength 0.5 of 4 Euler steps, guidance 5, seed 1234) of two images, both with the
        # first reference image (the pipeline repeats one image prompt for every prompt of the batch; a
        # list of images would be several references for every image, not one per image).
        prompts = ["a photo of a fern in a garden", "a bonsai tree"]
        init_image = torch.rand(2, 3, 32, 24, generator=g)
        run = dict(prompt=prompts, image=init_image, strength=0.5, num_inference_steps=4, guidance_scale=5.0,
                   output_type="pt")
        out = pipe(ip_adapter_image=pil_refs[0], generator=torch.Generator().manual_seed(1234), **run).images
        # The same through explicit embeddings, negative (zero embedding) first: the negative prompt of
        # guidance is the projection of zeros.
        explicit = torch.cat([torch.zeros_like(image_embeds[:1]), image_embeds[:1]])[:, None]
        out_explicit = pipe(ip_adapter_image_embeds=[explicit], generator=torch.Generator().manual_seed(1234),
                            **run).images
        assert (out - out_explicit).abs().max() < 1e-5, (out - out_explicit).abs().max()
        pipe.set_ip_adapter_scale(0.0)
        out_without = pipe(ip_adapter_image=pil_refs[0], generator=torch.Generator().manual_seed(1234), **run).images
        assert (out - out_without).abs().max() > 1e-3, "the adapter must change the image"
        save("img2img", {"image": init_image, "out": out})
        with open(os.path.join(REF, "img2img.json"), "w") as f:
            json.dump({"prompts": prompts, "strength": 0.5, "num_inference_steps": 4, "guidance_scale": 5.0,
                       "seed": 1234, "ip_adapter_scale": SCALE, "diffusers": diffusers.__version__,
                       "transformers": transformers.__version__, "torch": torch.__version__}, f, indent=1)


if __name__ == "__main__":
    main()
