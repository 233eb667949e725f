#!/usr/bin/env python3
"""How much arithmetic one pseudo-view of the sdxl backend is, and what fraction of a GPU's tensor throughput the
timed runs reach: counts the floating-point operations of the SDXL base UNet, the depth ControlNet (diffusers'
ControlNetModel.from_unet, as bench/make_random_generator_weights.py builds it) and the VAE's encoder and decoder
at one view size with PyTorch's FlopCounterMode on meta tensors (no weights, no GPU; matrix products,
convolutions and attention, 2 operations per multiply-add), then divides each generator_bench img2img row's work
by its time.

Per view: the VAE encodes it, the UNet and the ControlNet run its `unet_steps` steps on a batch of 2 when guidance
doubles it, the VAE decodes it. Left out, so that the count is a lower bound: the IP-Adapter's image encoder and
its extra attention, GroupNorm/LayerNorm and other elementwise work.

  python3 bench/generator_flops.py --size 504x378 --rows bench/results/generator_strength03_gpu_...jsonl \
      --ceiling_tflops 723.6
Needs diffusers (and transformers) in the Python environment.
"""
import argparse
import json
import sys

import torch
from torch.utils.flop_counter import FlopCounterMode

SDXL_UNET = dict(act_fn="silu", addition_embed_type="text_time", addition_embed_type_num_heads=64,
                 addition_time_embed_dim=256, attention_head_dim=[5, 10, 20], block_out_channels=[320, 640, 1280],
                 cross_attention_dim=2048,
                 down_block_types=["DownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D"], in_channels=4,
                 layers_per_block=2, norm_num_groups=32, out_channels=4, projection_class_embeddings_input_dim=2816,
                 sample_size=128, transformer_layers_per_block=[1, 2, 10],
                 up_block_types=["CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "UpBlock2D"], use_linear_projection=True)
SDXL_VAE = dict(block_out_channels=[128, 256, 512, 512], down_block_types=["DownEncoderBlock2D"] * 4,
                up_block_types=["UpDecoderBlock2D"] * 4, in_channels=3, out_channels=3, latent_channels=4,
                layers_per_block=2, norm_num_groups=32, sample_size=1024, act_fn="silu")


def counted(fn):
    with FlopCounterMode(display=False) as counter:
        fn()
    return counter.get_total_flops()


def per_view_flops(width, height, cfg):
    from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
    f = 8
    h, w = -(-height // f) * f, -(-width // f) * f  # padded to the latent factor, as the backend runs it
    b = 2 if cfg else 1
    with torch.device("meta"):
        unet = UNet2DConditionModel(**SDXL_UNET).half()
        controlnet = ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=(16, 32, 96, 256),
                                               load_weights_from_unet=False).half()
        vae = AutoencoderKL(**SDXL_VAE)
        sample = torch.empty(b, 4, h // f, w // f, dtype=torch.half)
        t = torch.tensor([500] * b)
        context = torch.empty(b, 77, 2048, dtype=torch.half)
        added = {"text_embeds": torch.empty(b, 1280, dtype=torch.half), "time_ids": torch.empty(b, 6, dtype=torch.half)}
        control = torch.empty(b, 3, h, w, dtype=torch.half)
        image = torch.empty(1, 3, h, w)
        latent = torch.empty(1, 4, h // f, w // f)
    return {
        "run_size": [w, h],
        "unet_step": counted(lambda: unet(sample, t, context, added_cond_kwargs=added)),
        "controlnet_step": counted(lambda: controlnet(sample, t, context, controlnet_cond=control,
                                                      added_cond_kwargs=added)),
        "vae_encode": counted(lambda: vae.encode(image)),
        "vae_decode": counted(lambda: vae.decode(latent)),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="504x378", help="view size WxH")
    ap.add_argument("--no_guidance", action="store_true", help="guidance scale <= 1 (no doubled batch)")
    ap.add_argument("--rows", help="generator_bench JSON lines: each img2img row's achieved rate")
    ap.add_argument("--ceiling_tflops", type=float, help="the GPU's measured dense fp16 matrix-product rate")
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    flops = per_view_flops(width, height, not args.no_guidance)
    step = flops["unet_step"] + flops["controlnet_step"]
    vae = flops["vae_encode"] + flops["vae_decode"]
    print(json.dumps({"bench": "generator_flops", "size": args.size, "guidance": not args.no_guidance,
                      **{k: v / 1e12 if isinstance(v, int) else v for k, v in flops.items()},
                      "unit": "TFLOP", "step_with_controlnet": step / 1e12, "vae_per_view": vae / 1e12}))
    if not args.rows:
        return
    for line in open(args.rows):
        row = json.loads(line)
        if not row.get("case", "").startswith("img2img") or row.get("size") != args.size:
            continue
        work = row["unet_steps"] * (step if row.get("controlnet_scale") else flops["unet_step"]) + vae
        rate = work / (row["ms_per_view"] / 1e3) / 1e12
        out = {"case": row["case"], "batch": row["batch"], "unet_steps": row["unet_steps"],
               "cuda_graphs": row.get("cuda_graphs"), "commit": row.get("commit"), "ms_per_view": row["ms_per_view"],
               "tflop_per_view": work / 1e12, "achieved_tflops": round(rate, 1)}
        if args.ceiling_tflops:
            out["fraction_of_ceiling"] = round(rate / args.ceiling_tflops, 3)
        print(json.dumps(out))


if __name__ == "__main__":
    sys.exit(main())
