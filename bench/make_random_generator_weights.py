#!/usr/bin/env python3
"""Random-weight models, at the published architectures, for every component of the sdxl backend that
`generator_bench --write_model` (the SDXL base folder) does not write, in the layouts the loaders of
diffusion_worker/ and diffusers both read. Weights are seeded random values (std 1/sqrt(fan-in) for
matrices and kernels, 0.02 for embeddings, 1 and 0 for norm scales and biases), stored as fp16 safetensors.

OUT receives
  controlnet/                    diffusers ControlNetModel: ControlNetModel.from_unet of the SDXL UNet's
                                 config with conditioning_embedding_out_channels (16, 32, 96, 256), the
                                 config of diffusers/controlnet-depth-sdxl-1.0;
  ip_adapter/ip-adapter_sdxl_vit-h.safetensors
                                 h94/IP-Adapter sdxl_models/ip-adapter_sdxl_vit-h: image projection of a
                                 1024-d CLIP embedding to 4 tokens of 2048, to_k_ip/to_v_ip per attn2 layer;
  ip_adapter/image_encoder/      its CLIPVisionModelWithProjection, ViT-H/14 (hidden 1280, 32 layers, 16
                                 heads, MLP 5120, patch 14, image 224, projection 1024, gelu);
  lora/pytorch_lora_weights.safetensors
                                 rank-4 LoRA (alpha 4) on to_q/to_k/to_v/to_out.0 of every UNet
                                 cross-attention (attn2) layer, diffusers/PEFT layout, as the backend's
                                 LoRA training saves;
  sd2_inpaint/                   stabilityai/stable-diffusion-2-inpainting: UNet (in_channels 9,
                                 cross_attention_dim 1024, attention_head_dim [5, 10, 20, 20], linear
                                 projections), OpenCLIP ViT-H text encoder as CLIPTextModel (hidden 1024,
                                 23 layers, 16 heads, MLP 4096, gelu), the SD VAE, the SDXL folder's
                                 tokenizer_2 (pad "!", as SD2's) and a DDIM scheduler on SD2's betas (the
                                 published folder ships PNDM; DDIM as when the recorded timings were taken);
  depth_anything/                depth-anything/Depth-Anything-V2-Small-hf: DINOv2-S/14 backbone (hidden 384,
                                 12 layers, 6 heads), DPT neck [48, 96, 192, 384], fusion 64, head 32, and
                                 its DPTImageProcessor settings (518, keep aspect, multiple of 14, bicubic).
  done.json                      written last; a folder with it is complete and is not written again.

--tiny writes the same components at tiny sizes (for the tiny SDXL of tests/fixtures/sdxl_tiny) in float32
on the CPU, for a smoke test of the benchmark programs.

Requirements (not part of scripts/setup.sh): pip install diffusers transformers accelerate
Usage: python bench/make_random_generator_weights.py --sdxl_dir SDXL --out OUT [--tiny] [--device cuda]
"""
import argparse
import json
import os
import sys
import time

import torch
from accelerate import init_empty_weights
from safetensors.torch import save_file

import diffusers
import transformers
from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
from transformers import (CLIPTextConfig, CLIPTextModel, CLIPTokenizer, CLIPVisionConfig,
                          CLIPVisionModelWithProjection, DepthAnythingConfig, DepthAnythingForDepthEstimation,
                          Dinov2Config)
from transformers.image_utils import IMAGENET_DEFAULT_MEAN, IMAGENET_DEFAULT_STD
from transformers.models.dpt.image_processing_dpt import DPTImageProcessor

# The SD2 inpainting folder is written as the tiny test fixture's is.
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests", "scripts"))
from sd2_inpaint_folder import save_sd2_inpaint_folder  # noqa: E402

LORA_TARGETS = ["to_q", "to_k", "to_v", "to_out.0"]


def randomize(model, g):
    """Every parameter redrawn: fan-in-scaled normals for Linear/Conv weights, 0.02 for embeddings and
    free parameters (class tokens, position embeddings), norms 1 and 0, biases 0, layer scales 1."""
    with torch.no_grad():
        for module in model.modules():
            for name, p in module.named_parameters(recurse=False):
                if isinstance(module, (torch.nn.LayerNorm, torch.nn.GroupNorm)):
                    p.fill_(1.0 if name == "weight" else 0.0)
                elif name == "bias":
                    p.zero_()
                elif isinstance(module, torch.nn.Embedding):
                    p.normal_(0, 0.02, generator=g)
                elif isinstance(module, (torch.nn.Linear, torch.nn.Conv2d, torch.nn.ConvTranspose2d)):
                    fan_in = p[0].numel() if not isinstance(module, torch.nn.ConvTranspose2d) else p.shape[0] * p[0, 0].numel()
                    p.normal_(0, fan_in ** -0.5, generator=g)
                elif name.startswith("lambda"):
                    p.fill_(1.0)
                else:
                    p.normal_(0, 0.02, generator=g)
    return model


def save_tensors(path, tensors, dtype, metadata=None):
    """A single-file checkpoint in the components' dtype (safetensors takes contiguous CPU tensors)."""
    save_file({k: v.to(dtype).cpu().contiguous() for k, v in tensors.items()}, path, metadata=metadata)


def meta_unet(sdxl_dir):
    with init_empty_weights():
        return UNet2DConditionModel.from_config(UNet2DConditionModel.load_config(os.path.join(sdxl_dir, "unet")))


def write_controlnet(out, unet, tiny, dtype, device, g):
    # 2^(levels - 1) must be the VAE's latent factor: 8 for SDXL, 2 for the tiny model.
    channels = (8, 16) if tiny else (16, 32, 96, 256)
    with torch.device(device):
        controlnet = ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=channels,
                                               load_weights_from_unet=False)
    randomize(controlnet, g).to(dtype).save_pretrained(os.path.join(out, "controlnet"), safe_serialization=True)


def write_ip_adapter(out, unet, tiny, dtype, device, g):
    if tiny:
        config = CLIPVisionConfig(hidden_size=32, intermediate_size=37, num_hidden_layers=3, num_attention_heads=4,
                                  image_size=32, patch_size=8, projection_dim=24, hidden_act="gelu",
                                  layer_norm_eps=1e-5)
    else:
        config = CLIPVisionConfig(hidden_size=1280, intermediate_size=5120, num_hidden_layers=32,
                                  num_attention_heads=16, image_size=224, patch_size=14, projection_dim=1024,
                                  hidden_act="gelu", layer_norm_eps=1e-5)
    with torch.device(device):
        encoder = CLIPVisionModelWithProjection(config)
    folder = os.path.join(out, "ip_adapter")
    randomize(encoder, g).to(dtype).save_pretrained(os.path.join(folder, "image_encoder"), safe_serialization=True)
    # diffusers' single-file layout: attention layers numbered in unet.attn_processors order, the
    # cross-attention (attn2) ones taking 1, 3, 5, ...
    cross, embed = unet.config.cross_attention_dim, config.projection_dim
    tensors = {"image_proj.proj.weight": torch.randn(4 * cross, embed, generator=g, device=device) * embed ** -0.5,
               "image_proj.proj.bias": torch.zeros(4 * cross, device=device),
               "image_proj.norm.weight": torch.ones(cross, device=device),
               "image_proj.norm.bias": torch.zeros(cross, device=device)}
    modules = dict(unet.named_modules())
    key = 1
    for name in unet.attn_processors:
        if name.endswith("attn1.processor"):
            continue
        hidden = modules[name[: -len(".processor")]].to_k.out_features
        for kv in ("to_k_ip", "to_v_ip"):
            tensors[f"ip_adapter.{key}.{kv}.weight"] = torch.randn(hidden, cross, generator=g, device=device) * cross ** -0.5
        key += 2
    save_tensors(os.path.join(folder, "ip-adapter_sdxl_vit-h.safetensors"), tensors, dtype)


def write_lora(out, unet, dtype, device, g, rank=4):
    tensors = {}
    for name, module in unet.named_modules():
        if any(name.endswith(".attn2." + t) for t in LORA_TARGETS):
            down = torch.randn(rank, module.in_features, generator=g, device=device) * module.in_features ** -0.5
            up = torch.randn(module.out_features, rank, generator=g, device=device) * 0.01
            tensors[f"unet.{name}.lora_A.weight"] = down
            tensors[f"unet.{name}.lora_B.weight"] = up
    metadata = {"lora_adapter_metadata": json.dumps(
        {"unet.r": rank, "unet.lora_alpha": rank, "unet.target_modules": LORA_TARGETS})}
    os.makedirs(os.path.join(out, "lora"), exist_ok=True)
    save_tensors(os.path.join(out, "lora", "pytorch_lora_weights.safetensors"), tensors, dtype, metadata)


def write_sd2_inpaint(out, sdxl_dir, tiny, dtype, device, g):
    tokenizer_dir = os.path.join(sdxl_dir, "tokenizer_2")
    tokenizer = CLIPTokenizer.from_pretrained(tokenizer_dir)
    text = dict(vocab_size=len(tokenizer), max_position_embeddings=77, hidden_act="gelu", layer_norm_eps=1e-5,
                bos_token_id=tokenizer.bos_token_id, eos_token_id=tokenizer.eos_token_id, pad_token_id=1)
    if tiny:
        text.update(hidden_size=32, intermediate_size=37, num_hidden_layers=2, num_attention_heads=4)
        unet_config = dict(sample_size=8, block_out_channels=(8, 16), down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
                           up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"), norm_num_groups=4,
                           attention_head_dim=[2, 4], cross_attention_dim=32)
        vae_config = dict(block_out_channels=(8, 16), down_block_types=("DownEncoderBlock2D",) * 2,
                          up_block_types=("UpDecoderBlock2D",) * 2, layers_per_block=1, norm_num_groups=4,
                          sample_size=16)
    else:
        text.update(hidden_size=1024, intermediate_size=4096, num_hidden_layers=23, num_attention_heads=16,
                    projection_dim=512)
        unet_config = dict(sample_size=64, block_out_channels=(320, 640, 1280, 1280),
                           down_block_types=("CrossAttnDownBlock2D",) * 3 + ("DownBlock2D",),
                           up_block_types=("UpBlock2D",) + ("CrossAttnUpBlock2D",) * 3, norm_num_groups=32,
                           attention_head_dim=[5, 10, 20, 20], cross_attention_dim=1024)
        vae_config = dict(block_out_channels=(128, 256, 512, 512), down_block_types=("DownEncoderBlock2D",) * 4,
                          up_block_types=("UpDecoderBlock2D",) * 4, layers_per_block=2, norm_num_groups=32,
                          sample_size=768)
    with torch.device(device):
        text_encoder = CLIPTextModel(CLIPTextConfig(**text))
        unet = UNet2DConditionModel(in_channels=9, out_channels=4, layers_per_block=2, use_linear_projection=True,
                                    act_fn="silu", flip_sin_to_cos=True, freq_shift=0, **unet_config)
        vae = AutoencoderKL(in_channels=3, out_channels=3, latent_channels=4, act_fn="silu", scaling_factor=0.18215,
                            **vae_config)
    for model in (text_encoder, unet, vae):
        randomize(model, g).to(dtype)
    save_sd2_inpaint_folder(os.path.join(out, "sd2_inpaint"), vae, text_encoder, unet, tokenizer, tokenizer_dir)


def write_depth_anything(out, tiny, dtype, device, g):
    if tiny:
        backbone = Dinov2Config(hidden_size=32, num_hidden_layers=4, num_attention_heads=2, mlp_ratio=2, image_size=56,
                                patch_size=14, out_indices=[1, 2, 3, 4], reshape_hidden_states=False)
        config = DepthAnythingConfig(backbone_config=backbone, reassemble_hidden_size=32,
                                     reassemble_factors=[4, 2, 1, 0.5], neck_hidden_sizes=[8, 16, 24, 32],
                                     fusion_hidden_size=8, head_hidden_size=8)
        size = 70
    else:
        backbone = Dinov2Config(hidden_size=384, num_hidden_layers=12, num_attention_heads=6, mlp_ratio=4,
                                image_size=518, patch_size=14, out_indices=[3, 6, 9, 12], reshape_hidden_states=False)
        config = DepthAnythingConfig(backbone_config=backbone, reassemble_hidden_size=384,
                                     reassemble_factors=[4, 2, 1, 0.5], neck_hidden_sizes=[48, 96, 192, 384],
                                     fusion_hidden_size=64, head_hidden_size=32, head_in_index=-1,
                                     depth_estimation_type="relative")
        size = 518
    with torch.device(device):
        model = DepthAnythingForDepthEstimation(config)
    folder = os.path.join(out, "depth_anything")
    randomize(model, g).to(dtype).save_pretrained(folder, safe_serialization=True)
    DPTImageProcessor(size={"height": size, "width": size}, keep_aspect_ratio=True, ensure_multiple_of=14,
                      resample=3, do_pad=False, image_mean=IMAGENET_DEFAULT_MEAN,
                      image_std=IMAGENET_DEFAULT_STD).save_pretrained(folder)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--sdxl_dir", required=True, help="the SDXL folder generator_bench --write_model wrote")
    ap.add_argument("--out", required=True)
    ap.add_argument("--tiny", action="store_true", help="tiny sizes, float32 (for the tiny SDXL test model)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if os.path.exists(os.path.join(args.out, "done.json")):
        print(f"make_random_generator_weights: {args.out} is complete; not written again")
        return
    if not os.path.exists(os.path.join(args.sdxl_dir, "unet", "config.json")):
        raise SystemExit(f"make_random_generator_weights: {args.sdxl_dir} holds no SDXL UNet config "
                         "(write it first with generator_bench --write_model)")
    dtype = torch.float32 if args.tiny else torch.float16
    device = torch.device(args.device)
    g = torch.Generator(device=device).manual_seed(args.seed)
    os.makedirs(args.out, exist_ok=True)
    unet = meta_unet(args.sdxl_dir)
    t0 = time.perf_counter()
    steps = [("controlnet", lambda: write_controlnet(args.out, unet, args.tiny, dtype, device, g)),
             ("ip_adapter", lambda: write_ip_adapter(args.out, unet, args.tiny, dtype, device, g)),
             ("lora", lambda: write_lora(args.out, unet, dtype, device, g)),
             ("sd2_inpaint", lambda: write_sd2_inpaint(args.out, args.sdxl_dir, args.tiny, dtype, device, g)),
             ("depth_anything", lambda: write_depth_anything(args.out, args.tiny, dtype, device, g))]
    seconds = {}
    for name, write in steps:
        start = time.perf_counter()
        write()
        seconds[name] = round(time.perf_counter() - start, 2)
        print(f"make_random_generator_weights: {name} in {seconds[name]} s", flush=True)
        if device.type == "cuda":
            torch.cuda.empty_cache()
    with open(os.path.join(args.out, "done.json"), "w") as f:
        json.dump({"tiny": args.tiny, "seed": args.seed, "dtype": str(dtype), "seconds": seconds,
                   "total_seconds": round(time.perf_counter() - t0, 2), "diffusers": diffusers.__version__,
                   "transformers": transformers.__version__, "torch": torch.__version__}, f, indent=1)


if __name__ == "__main__":
    main()
