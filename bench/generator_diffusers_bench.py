#!/usr/bin/env python3
"""diffusers side of bench/generator_bench.cpp: the same pseudo-view and inpainting cases on the same random
weights, settings, inputs and timing method (medians of --runs after --warmup, CUDA-synchronised).

  img2img_controlnet_lora     StableDiffusionXLControlNetImg2ImgPipeline with the LoRA (load_lora_weights;
                              needs peft, else the case is reported as skipped)
  img2img_controlnet_ip       the same pipeline after load_ip_adapter (ViT-H image encoder), scale 0.5,
                              without the LoRA
  img2img_controlnet_ip_lora  with both (needs peft)
  inpaint                     StableDiffusionInpaintPipeline (SD2 inpainting, the folder's DDIM scheduler),
                              from pure noise under the same mask
  worker_peak                 torch.cuda.max_memory_allocated with the SDXL pipeline (ControlNet, IP-Adapter,
                              LoRA) and the inpainting pipeline loaded together, over the cases run with them
All img2img cases: 30-step schedule at strength 0.6, guidance 5, ControlNet scale 1, one image, seed 1234;
sizes 504x378 (padded, replicated, to 504x384) and 1024x1024.

Requirements (not part of scripts/setup.sh): pip install diffusers transformers accelerate [peft]
Usage: python bench/generator_diffusers_bench.py --sdxl_dir SDXL --weights_dir W [--json out.jsonl]
       (--device cpu --dtype float32 runs the same code on the CPU, for the --tiny weights)
"""
import argparse
import importlib.util
import os

import numpy as np
import torch
from PIL import Image

import diffusers
from diffusers import ControlNetModel, StableDiffusionInpaintPipeline, StableDiffusionXLControlNetImg2ImgPipeline

from diffusers_timing import json_lines, reset_peak, sync, time_ms

PROMPT = "a photo of a fern in a garden"
IP_WEIGHTS = "ip-adapter_sdxl_vit-h.safetensors"


def parse_size(text, factor):
    w, h = (int(v) for v in text.split("x"))
    return text, w, h, -(-w // factor) * factor, -(-h // factor) * factor


def view_inputs(size, seed):
    """The render (padded), its control image, the reference view and the inpainting mask, as
    generator_bench draws them."""
    name, w, h, rw, rh = size
    torch.manual_seed(seed)
    pad = (0, rw - w, 0, rh - h)
    image = torch.nn.functional.pad(torch.rand(1, 3, h, w), pad, mode="replicate")
    control = torch.nn.functional.pad(torch.rand(1, 1, h, w).expand(1, 3, h, w), pad, mode="replicate")
    reference = torch.rand(h, w, 3)
    mask = torch.zeros(1, 1, rh, rw)
    mask[..., rw * 3 // 4:] = 1
    mask[..., : rh // 4, : rw // 4] = 1
    return image, control, reference, mask


peaks = []  # every case's peak since the last peaks.clear()


def peak_mib(device):
    peaks.append(torch.cuda.max_memory_allocated() / 2**20 if device.type == "cuda" else None)
    return peaks[-1]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sdxl_dir", default="/tmp/gaps_sdxl_random")
    ap.add_argument("--weights_dir", default="/tmp/gaps_generator_random")
    ap.add_argument("--dtype", default="float16", choices=["float16", "bfloat16", "float32"])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--sizes", default="504x378,1024x1024")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--strength", type=float, default=0.6)
    ap.add_argument("--guidance", type=float, default=5.0)
    ap.add_argument("--control_scale", type=float, default=1.0)
    ap.add_argument("--ip_scale", type=float, default=0.5)
    ap.add_argument("--inpaint_steps", type=int, default=30)
    ap.add_argument("--inpaint_guidance", type=float, default=7.5)
    ap.add_argument("--commit", default="")
    ap.add_argument("--json", default="")
    args = ap.parse_args()
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("generator_diffusers_bench: no CUDA device found")
    dtype = getattr(torch, args.dtype)
    w = args.weights_dir
    lora_dir = os.path.join(w, "lora")
    has_peft = importlib.util.find_spec("peft") is not None

    emit = json_lines(args.json)

    common = {"bench": "generator", "impl": "diffusers", "diffusers": diffusers.__version__,
              "torch": torch.__version__, "dtype": args.dtype, "commit": args.commit,
              "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"}

    reset_peak(device)
    controlnet = ControlNetModel.from_pretrained(os.path.join(w, "controlnet"), torch_dtype=dtype)
    pipe = StableDiffusionXLControlNetImg2ImgPipeline.from_pretrained(
        args.sdxl_dir, controlnet=controlnet, torch_dtype=dtype, add_watermarker=False).to(device)
    pipe.set_progress_bar_config(disable=True)
    factor = pipe.vae_scale_factor
    sizes = [parse_size(s, factor) for s in args.sizes.split(",")]

    def time_img2img(case, image_prompt):
        for size in sizes:
            image, control, reference, _ = view_inputs(size, 4)
            extra = {}
            if image_prompt:
                extra["ip_adapter_image"] = Image.fromarray((reference * 255).round().to(torch.uint8).numpy())
            reset_peak(device)
            out = {}

            def run():
                out["x"] = pipe(prompt=PROMPT, image=image, control_image=control, strength=args.strength,
                                num_inference_steps=args.steps, guidance_scale=args.guidance,
                                controlnet_conditioning_scale=args.control_scale,
                                generator=torch.Generator().manual_seed(1234), output_type="pt", **extra).images

            med, best = time_ms(device, args.warmup, args.runs, run)
            emit({**common, "case": case, "size": size[0], "run_size": [size[3], size[4]], "steps": args.steps,
                  "strength": args.strength, "unet_steps": int(args.steps * args.strength),
                  "guidance": args.guidance, "controlnet_scale": args.control_scale,
                  "ip_adapter_scale": args.ip_scale if image_prompt else None, "lora": "lora" in case,
                  "runs": args.runs, "ms": med, "min_ms": best,
                  "output_finite": bool(torch.isfinite(out["x"]).all()), "peak_mib": peak_mib(device)})

    def lora_case(case, image_prompt):
        if not has_peft:
            for size in sizes:
                emit({**common, "case": case, "size": size[0], "skipped": "diffusers' LoRA loading needs peft, "
                      "which is not installed"})
            return False
        pipe.load_lora_weights(lora_dir, weight_name="pytorch_lora_weights.safetensors")
        time_img2img(case, image_prompt)
        return True

    # The pipelines run under torch.no_grad (their __call__), as the LibTorch side runs without autograd.
    if lora_case("img2img_controlnet_lora", False):
        pipe.unload_lora_weights()
    pipe.load_ip_adapter(os.path.join(w, "ip_adapter"), subfolder="", weight_name=IP_WEIGHTS,
                         image_encoder_folder="image_encoder")
    pipe.set_ip_adapter_scale(args.ip_scale)
    inpaint = StableDiffusionInpaintPipeline.from_pretrained(os.path.join(w, "sd2_inpaint"), torch_dtype=dtype,
                                                             safety_checker=None, requires_safety_checker=False)
    inpaint = inpaint.to(device)
    inpaint.set_progress_bar_config(disable=True)
    sync(device)
    loaded = torch.cuda.memory_allocated() / 2**20 if device.type == "cuda" else None
    emit({**common, "case": "load_all", "components": ["sdxl", "controlnet", "ip_adapter", "image_encoder",
                                                       "sd2_inpaint"], "allocated_mib": loaded})
    reset_peak(device)
    peaks.clear()
    time_img2img("img2img_controlnet_ip", True)
    lora_case("img2img_controlnet_ip_lora", True)
    for size in sizes:
        image, _, _, mask = view_inputs(size, 6)
        reset_peak(device)
        out = {}

        def run():
            out["x"] = inpaint(prompt=PROMPT, image=image, mask_image=mask, height=size[4], width=size[3],
                               strength=1.0, num_inference_steps=args.inpaint_steps,
                               guidance_scale=args.inpaint_guidance,
                               generator=torch.Generator().manual_seed(1234), output_type="pt").images

        med, best = time_ms(device, args.warmup, args.runs, run)
        emit({**common, "case": "inpaint", "size": size[0], "run_size": [size[3], size[4]],
              "steps": args.inpaint_steps, "strength": 1.0, "guidance": args.inpaint_guidance,
              "masked_fraction": float(mask.mean()), "runs": args.runs, "ms": med, "min_ms": best,
              "output_finite": bool(torch.isfinite(out["x"]).all()), "peak_mib": peak_mib(device)})
    components = ["sdxl", "controlnet", "ip_adapter", "image_encoder"] + (["lora"] if has_peft else []) + ["sd2_inpaint"]
    # Each case resets the peak: the phase's peak is the largest of theirs.
    emit({**common, "case": "worker_peak", "components": components, "sizes": args.sizes, "loaded_mib": loaded,
          "peak_mib": max(peaks) if peaks and None not in peaks else None})


if __name__ == "__main__":
    main()
