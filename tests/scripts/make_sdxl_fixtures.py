#!/usr/bin/env python3
"""Builds the tiny random-weight SDXL fixtures of tests/fixtures/sdxl_tiny/ with PyPI's diffusers.

Requirements (not needed by CI, which only reads the committed fixtures):
    ~/.cache/gaps/venv/bin/pip install diffusers transformers accelerate
Usage:
    ~/.cache/gaps/venv/bin/python tests/scripts/make_sdxl_fixtures.py [OUT_DIR]

OUT_DIR (default tests/fixtures/sdxl_tiny) receives
  model/        a diffusers-layout SDXL folder (model_index.json, unet, vae, text_encoder, text_encoder_2,
                tokenizer, tokenizer_2, scheduler), fp32 safetensors, SDXL architecture at tiny sizes;
  reference/    inputs and outputs of each component's forward, two steps of each scheduler per timestep
                spacing, noising at an img2img start step, and img2img at strength 0.5 with a fixed seed
                (2 of 4 Euler steps; 3 of 6 DDIM and DPM-Solver++ steps), as safetensors (plus
                tokenizer.json: prompts and their token ids).
The tokenizer vocabulary is built here (byte-level symbols plus the merges learned from a few sentences),
since the real CLIP vocabulary is not downloaded.
"""
import collections
import json
import os
import sys

import torch

import diffusers
import transformers
from diffusers import (AutoencoderKL, DDIMScheduler, DPMSolverMultistepScheduler, EulerDiscreteScheduler,
                       StableDiffusionXLImg2ImgPipeline, UNet2DConditionModel)
from transformers import CLIPTextConfig, CLIPTextModel, CLIPTextModelWithProjection, CLIPTokenizer

from reference_tensors import reference_saver

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = sys.argv[1] if len(sys.argv) > 1 else os.path.join(HERE, "..", "fixtures", "sdxl_tiny")
MODEL = os.path.join(OUT, "model")
REF = os.path.join(OUT, "reference")
save = reference_saver(REF)

CORPUS = [
    "a photo of a fern in a garden", "a bonsai tree on a wooden table", "a high quality photo of a room",
    "photorealistic, sharp details, natural light", "the quick brown fox jumps over the lazy dog",
    "a painting of a red house near the river", "leaves, plants and flowers in the sunlight",
]


def bytes_to_unicode():
    # The printable stand-ins of GPT-2/CLIP byte-level BPE, one per byte value.
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + \
        list(range(ord("®"), ord("ÿ") + 1))
    cs = bs[:]
    n = 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return dict(zip(bs, [chr(c) for c in cs]))


def build_vocab(num_merges):
    """A CLIP-style vocabulary: bytes, bytes + '</w>', merges learned greedily from CORPUS, specials."""
    symbols = list(bytes_to_unicode().values())
    vocab = symbols + [s + "</w>" for s in symbols]
    words = collections.Counter(w for line in CORPUS for w in line.lower().replace(",", " ,").split())
    splits = {w: [c for c in w[:-1]] + [w[-1] + "</w>"] for w in words}
    merges = []
    for _ in range(num_merges):
        pairs = collections.Counter()
        for w, parts in splits.items():
            for a, b in zip(parts, parts[1:]):
                pairs[(a, b)] += words[w]
        if not pairs:
            break
        best = max(pairs.items(), key=lambda kv: (kv[1], kv[0]))[0]
        merges.append(best)
        vocab.append(best[0] + best[1])
        for w, parts in splits.items():
            out, i = [], 0
            while i < len(parts):
                if i + 1 < len(parts) and (parts[i], parts[i + 1]) == best:
                    out.append(parts[i] + parts[i + 1])
                    i += 2
                else:
                    out.append(parts[i])
                    i += 1
            splits[w] = out
    vocab += ["<|startoftext|>", "<|endoftext|>"]
    return {tok: i for i, tok in enumerate(vocab)}, merges


def write_tokenizer(folder, vocab, merges, pad_token):
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, "vocab.json"), "w") as f:
        json.dump(vocab, f)
    with open(os.path.join(folder, "merges.txt"), "w") as f:
        f.write("#version: 0.2\n")
        for a, b in merges:
            f.write(f"{a} {b}\n")
    tok = CLIPTokenizer(os.path.join(folder, "vocab.json"), os.path.join(folder, "merges.txt"),
                        pad_token=pad_token, model_max_length=77)
    tok.save_pretrained(folder)
    return CLIPTokenizer.from_pretrained(folder)


def main():
    torch.manual_seed(0)
    os.makedirs(REF, exist_ok=True)
    vocab, merges = build_vocab(200)
    tokenizer = write_tokenizer(os.path.join(MODEL, "tokenizer"), vocab, merges, "<|endoftext|>")
    tokenizer_2 = write_tokenizer(os.path.join(MODEL, "tokenizer_2"), vocab, merges, "!")
    bos, eos = vocab["<|startoftext|>"], vocab["<|endoftext|>"]

    def clip_config(act, layers):
        return CLIPTextConfig(vocab_size=len(vocab), hidden_size=32, intermediate_size=37, num_hidden_layers=layers,
                              num_attention_heads=4, max_position_embeddings=77, hidden_act=act,
                              projection_dim=32, bos_token_id=bos, eos_token_id=eos, pad_token_id=1)

    # SDXL: CLIP ViT-L (quick_gelu) and OpenCLIP bigG (gelu) with a projection of the pooled output.
    text_encoder = CLIPTextModel(clip_config("quick_gelu", 3)).eval()
    text_encoder_2 = CLIPTextModelWithProjection(clip_config("gelu", 4)).eval()

    unet = UNet2DConditionModel(
        sample_size=8, in_channels=4, out_channels=4, layers_per_block=2, block_out_channels=(16, 32),
        down_block_types=("DownBlock2D", "CrossAttnDownBlock2D"),
        up_block_types=("CrossAttnUpBlock2D", "UpBlock2D"), norm_num_groups=8,
        attention_head_dim=(2, 4), use_linear_projection=True, transformer_layers_per_block=(1, 2),
        cross_attention_dim=64, addition_embed_type="text_time", addition_time_embed_dim=8,
        projection_class_embeddings_input_dim=6 * 8 + 32).eval()
    vae = AutoencoderKL(
        in_channels=3, out_channels=3, latent_channels=4, block_out_channels=(16, 32),
        down_block_types=("DownEncoderBlock2D",) * 2, up_block_types=("UpDecoderBlock2D",) * 2,
        layers_per_block=2, norm_num_groups=8, sample_size=32, scaling_factor=0.13025,
        force_upcast=True).eval()
    # Random (not zero) init everywhere, so zero-initialised layers (e.g. conv_out) are exercised too.
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for model in (unet, vae, text_encoder, text_encoder_2):
            for name, p in model.named_parameters():
                if name.endswith("weight") and p.ndim == 1 and "norm" in name:
                    p.copy_(1 + 0.1 * torch.randn(p.shape, generator=g))
                else:
                    p.copy_(torch.randn(p.shape, generator=g) / max(1, p[0].numel()) ** 0.5)

    scheduler = EulerDiscreteScheduler(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear",
                                       num_train_timesteps=1000, steps_offset=1, timestep_spacing="leading",
                                       prediction_type="epsilon")
    pipe = StableDiffusionXLImg2ImgPipeline(vae=vae, text_encoder=text_encoder, text_encoder_2=text_encoder_2,
                                            tokenizer=tokenizer, tokenizer_2=tokenizer_2, unet=unet,
                                            scheduler=scheduler, requires_aesthetics_score=False,
                                            force_zeros_for_empty_prompt=True)
    pipe.save_pretrained(MODEL, safe_serialization=True)

    with torch.no_grad():
        # Tokenizer.
        prompts = ["a photo of a fern in a garden", "Bonsai, on a Wooden table!!  42 fox's",
                   "", "unseen words: zebra quokka"]
        tokens = {"prompts": prompts,
                  "tokenizer": [tokenizer(p, padding="max_length", max_length=77, truncation=True).input_ids
                                for p in prompts],
                  "tokenizer_2": [tokenizer_2(p, padding="max_length", max_length=77, truncation=True).input_ids
                                  for p in prompts]}
        with open(os.path.join(REF, "tokenizer.json"), "w") as f:
            json.dump(tokens, f)

        # Text encoders.
        ids1 = torch.tensor(tokens["tokenizer"][:2])
        ids2 = torch.tensor(tokens["tokenizer_2"][:2])
        o1 = text_encoder(ids1, output_hidden_states=True)
        o2 = text_encoder_2(ids2, output_hidden_states=True)
        save("text_encoder", {"input_ids": ids1, "penultimate": o1.hidden_states[-2],
                              "last_hidden_state": o1.last_hidden_state, "pooled": o1.pooler_output})
        save("text_encoder_2", {"input_ids": ids2, "penultimate": o2.hidden_states[-2],
                                "last_hidden_state": o2.last_hidden_state, "text_embeds": o2.text_embeds})

        # VAE (encoder moments, decoder image).
        image = torch.rand(2, 3, 32, 24, generator=g) * 2 - 1
        moments = vae.encoder(image)
        moments = vae.quant_conv(moments)
        latents = torch.randn(2, 4, 4, 3, generator=g)
        decoded = vae.decode(latents).sample
        save("vae", {"image": image, "moments": moments, "latents": latents, "decoded": decoded})

        # UNet with text_time conditioning.
        sample = torch.randn(2, 4, 8, 6, generator=g)
        timestep = torch.tensor([999.0, 421.0])
        context = torch.randn(2, 7, 64, generator=g)
        text_embeds = torch.randn(2, 32, generator=g)
        time_ids = torch.tensor([[64.0, 48.0, 0.0, 0.0, 64.0, 48.0], [1024.0, 768.0, 8.0, 16.0, 1024.0, 1024.0]])
        out = unet(sample, timestep, encoder_hidden_states=context,
                   added_cond_kwargs={"text_embeds": text_embeds, "time_ids": time_ids}).sample
        save("unet", {"sample": sample, "timestep": timestep, "encoder_hidden_states": context,
                      "text_embeds": text_embeds, "time_ids": time_ids, "out": out})

        # One step of each scheduler, per spacing, with its timestep and sigma tables.
        sched_ref = {}
        x = torch.randn(1, 4, 4, 3, generator=g)
        eps = torch.randn(1, 4, 4, 3, generator=g)
        eps2 = torch.randn(1, 4, 4, 3, generator=g)
        sched_ref["x"], sched_ref["eps"], sched_ref["eps2"] = x, eps, eps2
        base = dict(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", num_train_timesteps=1000,
                    steps_offset=1)
        kinds = {"euler": EulerDiscreteScheduler, "ddim": DDIMScheduler,
                 "dpmpp2m": lambda **kw: DPMSolverMultistepScheduler(algorithm_type="dpmsolver++", solver_order=2,
                                                                     **kw)}
        for kind, make in kinds.items():
            for spacing in ("leading", "trailing", "linspace"):
                s = make(timestep_spacing=spacing, **base)
                s.set_timesteps(10)
                key = f"{kind}_{spacing}"
                sched_ref[key + "_timesteps"] = s.timesteps.to(torch.float64)
                if hasattr(s, "sigmas"):
                    sched_ref[key + "_sigmas"] = s.sigmas.to(torch.float64)
                xs = x.clone()
                if kind == "euler":
                    xs = s.scale_model_input(xs, s.timesteps[0])
                    sched_ref[key + "_scaled_input"] = xs
                    xs = x.clone()
                # Two steps, so the multistep solver's second-order update is covered.
                step1 = s.step(eps, s.timesteps[0], x).prev_sample
                step2 = s.step(eps2, s.timesteps[1], step1).prev_sample
                sched_ref[key + "_step1"] = step1
                sched_ref[key + "_step2"] = step2
        save("schedulers", {k: v.float() if k.endswith(("step1", "step2", "x", "eps", "eps2", "input")) else v
                            for k, v in sched_ref.items()})
        # Noise at a strength's start step (the img2img entry point).
        s = EulerDiscreteScheduler(timestep_spacing="leading", **base)
        s.set_timesteps(4)
        noise = torch.randn(1, 4, 4, 3, generator=g)
        noisy = s.add_noise(x, noise, s.timesteps[2:3])
        save("add_noise", {"x": x, "noise": noise, "timestep": s.timesteps[2:3].float(), "noisy": noisy})

        # 2-step img2img: 4 scheduled steps at strength 0.5, CFG 5, seed 1234, two images.
        init_image = torch.rand(2, 3, 32, 24, generator=g)
        out = pipe(prompt=["a photo of a fern in a garden", "a bonsai tree"], image=init_image,
                   strength=0.5, num_inference_steps=4, guidance_scale=5.0,
                   generator=torch.Generator().manual_seed(1234), output_type="pt").images
        save("img2img", {"image": init_image, "out": out})
        # The same with the other schedulers built from the folder's config (diffusers' from_config), 6
        # scheduled steps at strength 0.5: 3 run, so DPM-Solver++ takes second-order steps.
        for kind, cls in (("ddim", DDIMScheduler), ("dpmpp2m", DPMSolverMultistepScheduler)):
            pipe.scheduler = cls.from_config(scheduler.config)
            out = pipe(prompt=["a photo of a fern in a garden", "a bonsai tree"], image=init_image,
                       strength=0.5, num_inference_steps=6, guidance_scale=5.0,
                       generator=torch.Generator().manual_seed(1234), output_type="pt").images
            save("img2img_" + kind, {"image": init_image, "out": out})
        pipe.scheduler = scheduler
        with open(os.path.join(REF, "img2img.json"), "w") as f:
            json.dump({"prompts": ["a photo of a fern in a garden", "a bonsai tree"], "strength": 0.5,
                       "num_inference_steps": 4, "guidance_scale": 5.0, "seed": 1234,
                       "diffusers": diffusers.__version__, "transformers": transformers.__version__,
                       "torch": torch.__version__}, f, indent=1)


if __name__ == "__main__":
    main()
