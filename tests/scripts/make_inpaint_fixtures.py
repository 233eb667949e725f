#!/usr/bin/env python3
"""Builds the tiny random-weight Stable Diffusion 2 inpainting fixtures of tests/fixtures/sd2_inpaint_tiny/.

Requirements (not needed by CI, which only reads the committed fixtures):
    ~/.cache/gaps/venv/bin/pip install diffusers transformers accelerate
Usage:
    ~/.cache/gaps/venv/bin/python tests/scripts/make_inpaint_fixtures.py [OUT_DIR]

OUT_DIR (default tests/fixtures/sd2_inpaint_tiny) receives
  model/      a diffusers-layout StableDiffusionInpaintPipeline folder with the options of
              stabilityai/stable-diffusion-2-inpainting at tiny sizes: a UNet with 9 input channels (latents,
              mask, masked-image latents), a per-block attention_head_dim list and linear projections, no
              added embedding; a CLIPTextModel with gelu; a VAE; the CLIP tokenizer of
              tests/fixtures/sdxl_tiny (pad token "!", as SD2's); a DDIM scheduler;
  reference/  the UNet's forward for fixed inputs, the prompt embeddings (last hidden state), and inpainting
              runs with guidance and a fixed seed: 2 DDIM steps and 2 Euler steps at strength 1, 3 of 4
              DDIM steps at strength 0.75, and PNDM (skip_prk_steps, SD2's) with 4 steps at strength 1 and
              0.75, as safetensors (plus inpaint.json with the prompts and settings).
"""
import json
import os
import sys

import torch

import diffusers
import transformers
from diffusers import AutoencoderKL, DDIMScheduler, EulerDiscreteScheduler, PNDMScheduler, UNet2DConditionModel
from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

from reference_tensors import reference_saver
from sd2_inpaint_folder import save_sd2_inpaint_folder

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = sys.argv[1] if len(sys.argv) > 1 else os.path.join(HERE, "..", "fixtures", "sd2_inpaint_tiny")
MODEL = os.path.join(OUT, "model")
REF = os.path.join(OUT, "reference")
save = reference_saver(REF)
SDXL_TOKENIZER = os.path.join(HERE, "..", "fixtures", "sdxl_tiny", "model", "tokenizer_2")


def main():
    torch.manual_seed(0)
    os.makedirs(REF, exist_ok=True)
    tokenizer = CLIPTokenizer.from_pretrained(SDXL_TOKENIZER)
    bos, eos = tokenizer.bos_token_id, tokenizer.eos_token_id
    text_encoder = CLIPTextModel(CLIPTextConfig(
        vocab_size=len(tokenizer), hidden_size=32, intermediate_size=37, num_hidden_layers=2, num_attention_heads=4,
        max_position_embeddings=77, hidden_act="gelu", bos_token_id=bos, eos_token_id=eos, pad_token_id=1)).eval()
    # SD2's layout: cross-attention blocks first, a plain block last, attention_head_dim as a per-block
    # list (diffusers reads it as the number of heads), linear projections in the transformers.
    unet = UNet2DConditionModel(
        sample_size=8, in_channels=9, out_channels=4, layers_per_block=2, block_out_channels=(8, 16),
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"), up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        norm_num_groups=4, attention_head_dim=[2, 4], use_linear_projection=True, cross_attention_dim=32).eval()
    vae = AutoencoderKL(
        in_channels=3, out_channels=3, latent_channels=4, block_out_channels=(8, 16),
        down_block_types=("DownEncoderBlock2D",) * 2, up_block_types=("UpDecoderBlock2D",) * 2,
        layers_per_block=1, norm_num_groups=4, sample_size=16, scaling_factor=0.18215).eval()
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for model in (unet, vae, text_encoder):
            for name, p in model.named_parameters():
                if name.endswith("weight") and p.ndim == 1 and "norm" in name:
                    p.copy_(1 + 0.1 * torch.randn(p.shape, generator=g))
                else:
                    p.copy_(torch.randn(p.shape, generator=g) / max(1, p[0].numel()) ** 0.5)
    pipe = save_sd2_inpaint_folder(MODEL, vae, text_encoder, unet, tokenizer, SDXL_TOKENIZER)
    scheduler = pipe.scheduler

    prompts = ["a photo of a fern in a garden", "a bonsai tree"]
    with torch.no_grad():
        sample = torch.randn(2, 9, 8, 6, generator=g)
        timestep = torch.tensor([999.0, 421.0])
        context = torch.randn(2, 7, 32, generator=g)
        out = unet(sample, timestep, encoder_hidden_states=context).sample
        save("unet", {"sample": sample, "timestep": timestep, "encoder_hidden_states": context, "out": out})

        cond, uncond = pipe.encode_prompt(prompts, "cpu", 1, True, None)
        save("prompt_embeds", {"cond": cond, "uncond": uncond})

        image = torch.rand(2, 3, 16, 16, generator=g)
        # A soft mask: the pipeline binarises it at 0.5.
        mask = torch.zeros(2, 1, 16, 16)
        mask[0, :, 3:11, 5:14] = 0.8
        mask[0, :, 12:, :4] = 0.4  # below 0.5: kept
        mask[1, :, :6, :] = 1.0
        mask[1, :, 9:13, 2:7] = 0.6
        # PNDM as SD2's folders configure it (skip_prk_steps); 4 steps are 5 UNet calls (PLMS repeats one).
        runs = {"ddim": (DDIMScheduler, 2, 1.0), "euler": (EulerDiscreteScheduler, 2, 1.0),
                "ddim_strength": (DDIMScheduler, 4, 0.75), "pndm": (PNDMScheduler, 4, 1.0),
                "pndm_strength": (PNDMScheduler, 4, 0.75)}
        settings = {"prompts": prompts, "guidance_scale": 5.0, "seed": 1234, "runs": {},
                    "diffusers": diffusers.__version__, "transformers": transformers.__version__,
                    "torch": torch.__version__}
        for name, (cls, steps, strength) in runs.items():
            pipe.scheduler = (cls.from_config(scheduler.config, skip_prk_steps=True) if cls is PNDMScheduler
                              else cls.from_config(scheduler.config))
            result = pipe(prompt=prompts, image=image, mask_image=mask, height=16, width=16, strength=strength,
                          num_inference_steps=steps, guidance_scale=5.0,
                          generator=torch.Generator().manual_seed(1234), output_type="pt").images
            save("inpaint_" + name, {"image": image, "mask": mask, "out": result})
            settings["runs"][name] = {"scheduler": cls.__name__, "steps": steps, "strength": strength}
        # One generator per image (diffusers' generator list).
        pipe.scheduler = DDIMScheduler.from_config(scheduler.config)
        result = pipe(prompt=prompts, image=image, mask_image=mask, height=16, width=16, strength=1.0,
                      num_inference_steps=2, guidance_scale=5.0,
                      generator=[torch.Generator().manual_seed(7), torch.Generator().manual_seed(8)],
                      output_type="pt").images
        save("inpaint_seed_list", {"image": image, "mask": mask, "out": result})
        settings["runs"]["seed_list"] = {"scheduler": "DDIMScheduler", "steps": 2, "strength": 1.0, "seeds": [7, 8]}
        with open(os.path.join(REF, "inpaint.json"), "w") as f:
            json.dump(settings, f, indent=1)


if __name__ == "__main__":
    main()
