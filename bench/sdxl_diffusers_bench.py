#!/usr/bin/env python3
"""diffusers side of the SDXL speed comparison with bench/sdxl_bench.cpp (same cases, same weights).

Times diffusers' UNet2DConditionModel step (batch 2, fp16) at 1024x1024 and at 504x378 padded to
504x384, and StableDiffusionXLImg2ImgPipeline (30-step schedule, strength 0.5, guidance 5) at both sizes,
on the random-weight SDXL folder that `sdxl_bench --write_model` writes. One JSON line per measurement,
with peak GPU memory (torch.cuda.max_memory_allocated).

Requirements (not part of scripts/setup.sh): pip install diffusers transformers accelerate
Usage: python bench/sdxl_diffusers_bench.py --model_dir DIR [--runs 10] [--json results.jsonl]
       (--device cpu --dtype float32 runs the same code on the CPU, for a smoke test on a tiny model)
"""
import argparse
import time

import torch
import diffusers
from diffusers import StableDiffusionXLImg2ImgPipeline

from diffusers_timing import json_lines, reset_peak, sync, time_ms

SIZES = [("1024x1024", 1024, 1024, 1024, 1024), ("504x378", 504, 378, 504, 384)]


def peak_gib(device):
    return torch.cuda.max_memory_allocated() / 2**30 if device.type == "cuda" else None


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--model_dir", default="/tmp/gaps_sdxl_random")
    ap.add_argument("--dtype", default="float16", choices=["float16", "bfloat16", "float32"])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--img2img_runs", type=int, default=3)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--strength", type=float, default=0.5)
    ap.add_argument("--guidance", type=float, default=5.0)
    ap.add_argument("--sizes", default="", help="override, e.g. 32x24:32x24 (view:run size)")
    ap.add_argument("--json", default="")
    args = ap.parse_args()
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("sdxl_diffusers_bench: no CUDA device found")
    dtype = getattr(torch, args.dtype)
    sizes = SIZES
    if args.sizes:
        sizes = []
        for item in args.sizes.split(","):
            view, run = item.split(":")
            (w, h), (rw, rh) = (map(int, view.split("x")), map(int, run.split("x")))
            sizes.append((view, w, h, rw, rh))

    emit = json_lines(args.json)

    common = {"bench": "sdxl", "impl": "diffusers", "diffusers": diffusers.__version__, "torch": torch.__version__,
              "dtype": args.dtype,
              "gpu": torch.cuda.get_device_name(0) if device.type == "cuda" else "cpu"}
    reset_peak(device)
    t0 = time.perf_counter()
    pipe = StableDiffusionXLImg2ImgPipeline.from_pretrained(args.model_dir, torch_dtype=dtype).to(device)
    pipe.set_progress_bar_config(disable=True)
    sync(device)
    emit({**common, "case": "load", "seconds": time.perf_counter() - t0, "gpu_memory_gib": peak_gib(device)})

    unet = pipe.unet
    text_dim = unet.config.cross_attention_dim
    pooled_dim = pipe.text_encoder_2.config.projection_dim
    with torch.inference_mode():
        for name, w, h, rw, rh in sizes:
            torch.manual_seed(3)
            sample = torch.randn(2, 4, rh // 8, rw // 8, device=device, dtype=dtype)
            timestep = torch.tensor(500.0, device=device)
            context = torch.randn(2, 77, text_dim, device=device, dtype=dtype)
            text_embeds = torch.randn(2, pooled_dim, device=device, dtype=dtype)
            time_ids = torch.tensor([[rh, rw, 0, 0, rh, rw]] * 2, device=device, dtype=dtype)
            reset_peak(device)
            out = {}

            def step():
                out["x"] = unet(sample, timestep, encoder_hidden_states=context,
                                added_cond_kwargs={"text_embeds": text_embeds, "time_ids": time_ids}).sample

            med, best = time_ms(device, 3, args.runs, step)
            emit({**common, "case": "unet_step", "size": name, "run_size": [rw, rh], "latent": [rw // 8, rh // 8],
                  "batch": 2, "runs": args.runs, "eager_ms": med, "eager_min_ms": best,
                  "output_finite": bool(torch.isfinite(out["x"]).all()), "peak_gpu_memory_gib": peak_gib(device)})

        for name, w, h, rw, rh in sizes:
            torch.manual_seed(4)
            view = torch.rand(1, 3, h, w)
            image = torch.nn.functional.pad(view, (0, rw - w, 0, rh - h), mode="replicate")
            reset_peak(device)

            def run():
                pipe(prompt="a photo of a fern in a garden", image=image, strength=args.strength,
                     num_inference_steps=args.steps, guidance_scale=args.guidance,
                     generator=torch.Generator().manual_seed(1234), output_type="pt")

            med, best = time_ms(device, 1, args.img2img_runs, run)
            emit({**common, "case": "img2img", "size": name, "run_size": [rw, rh], "steps": args.steps,
                  "strength": args.strength, "unet_steps": int(args.steps * args.strength),
                  "guidance": args.guidance, "ms": med, "min_ms": best, "peak_gpu_memory_gib": peak_gib(device)})


if __name__ == "__main__":
    main()
