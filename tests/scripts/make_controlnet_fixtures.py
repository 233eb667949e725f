#!/usr/bin/env python3
"""Builds the tiny random-weight SDXL ControlNet fixture of tests/fixtures/sdxl_controlnet_tiny/ with PyPI's
diffusers, matching the tiny SDXL model of tests/fixtures/sdxl_tiny (made by make_sdxl_fixtures.py).

Requirements (not needed by CI, which only reads the committed fixtures):
    ~/.cache/gaps/venv/bin/pip install diffusers transformers accelerate
Usage:
    ~/.cache/gaps/venv/bin/python tests/scripts/make_controlnet_fixtures.py [OUT_DIR]

OUT_DIR (default tests/fixtures/sdxl_controlnet_tiny) receives
  controlnet/   a diffusers ControlNetModel folder (config.json, diffusion_pytorch_model.safetensors in
                float16): ControlNetModel.from_unet of the tiny UNet with a 2-level conditioning embedding
                (the tiny VAE's latent factor is 2), then every weight re-drawn at random (zero convolutions
                included, so they contribute) and rounded to float16; the references are computed in
                float32 from those rounded weights;
  reference/    controlnet.safetensors: one ControlNet forward (inputs, every down-block residual and the
                mid residual at conditioning scale 0.7); unet_controlled.safetensors: the tiny UNet's output
                with those residuals; img2img_controlnet.safetensors (+ .json): StableDiffusionXLControlNet-
                Img2ImgPipeline on the tiny SDXL folder, 2 of 4 Euler steps, guidance 5, conditioning scale
                0.8, seed 1234.
"""
import json
import os
import sys

import torch

import diffusers
import transformers
from diffusers import ControlNetModel, StableDiffusionXLControlNetImg2ImgPipeline, StableDiffusionXLImg2ImgPipeline

from reference_tensors import reference_saver

HERE = os.path.dirname(os.path.abspath(__file__))
SDXL = os.path.join(HERE, "..", "fixtures", "sdxl_tiny", "model")
OUT = sys.argv[1] if len(sys.argv) > 1 else os.path.join(HERE, "..", "fixtures", "sdxl_controlnet_tiny")
REF = os.path.join(OUT, "reference")
save = reference_saver(REF)


def main():
    os.makedirs(REF, exist_ok=True)
    base = StableDiffusionXLImg2ImgPipeline.from_pretrained(SDXL, torch_dtype=torch.float32)
    unet = base.unet.eval()
    controlnet = ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=(8, 16)).eval()
    g = torch.Generator().manual_seed(2)
    with torch.no_grad():
        for name, p in controlnet.named_parameters():
            if name.endswith("weight") and p.ndim == 1 and "norm" in name:
                p.copy_(1 + 0.1 * torch.randn(p.shape, generator=g))
            else:
                p.copy_(torch.randn(p.shape, generator=g) / max(1, p[0].numel()) ** 0.5)
            p.copy_(p.half().float())  # the stored float16 values, exactly
    controlnet.half().save_pretrained(os.path.join(OUT, "controlnet"), safe_serialization=True)
    controlnet.float()

    with torch.no_grad():
        sample = torch.randn(2, 4, 8, 6, generator=g)
        timestep = torch.tensor([999.0, 421.0])
        context = torch.randn(2, 7, 64, generator=g)
        text_embeds = torch.randn(2, 32, generator=g)
        time_ids = torch.tensor([[16.0, 12.0, 0.0, 0.0, 16.0, 12.0], [1024.0, 768.0, 8.0, 16.0, 1024.0, 1024.0]])
        cond = torch.rand(2, 3, 16, 12, generator=g)
        added = {"text_embeds": text_embeds, "time_ids": time_ids}
        down, mid = controlnet(sample, timestep, encoder_hidden_states=context, controlnet_cond=cond,
                               conditioning_scale=0.7, added_cond_kwargs=added, return_dict=False)
        ref = {"sample": sample, "timestep": timestep, "encoder_hidden_states": context, "text_embeds": text_embeds,
               "time_ids": time_ids, "controlnet_cond": cond, "conditioning_scale": torch.tensor([0.7]), "mid": mid}
        ref.update({f"down_{i}": d for i, d in enumerate(down)})
        save("controlnet", ref)
        out = unet(sample, timestep, encoder_hidden_states=context, added_cond_kwargs=added,
                   down_block_additional_residuals=down, mid_block_additional_residual=mid).sample
        save("unet_controlled", {"out": out})

        pipe = StableDiffusionXLControlNetImg2ImgPipeline(
            vae=base.vae, text_encoder=base.text_encoder, text_encoder_2=base.text_encoder_2,
            tokenizer=base.tokenizer, tokenizer_2=base.tokenizer_2, unet=unet, controlnet=controlnet,
            scheduler=base.scheduler, requires_aesthetics_score=False, force_zeros_for_empty_prompt=True,
            add_watermarker=False)
        setup = {"prompts": ["a photo of a fern in a garden", "a bonsai tree"], "strength": 0.5,
                 "num_inference_steps": 4, "guidance_scale": 5.0, "controlnet_conditioning_scale": 0.8,
                 "seed": 1234}
        init_image = torch.rand(2, 3, 32, 24, generator=g)
        control_image = torch.rand(2, 3, 32, 24, generator=g)
        out = pipe(prompt=setup["prompts"], image=init_image, control_image=control_image,
                   strength=setup["strength"], num_inference_steps=setup["num_inference_steps"],
                   guidance_scale=setup["guidance_scale"],
                   controlnet_conditioning_scale=setup["controlnet_conditioning_scale"],
                   generator=torch.Generator().manual_seed(setup["seed"]), output_type="pt").images
        save("img2img_controlnet", {"image": init_image, "control_image": control_image, "out": out})
        setup.update({"diffusers": diffusers.__version__, "transformers": transformers.__version__,
                      "torch": torch.__version__})
        with open(os.path.join(REF, "img2img_controlnet.json"), "w") as f:
            json.dump(setup, f, indent=1)


if __name__ == "__main__":
    main()
