#!/usr/bin/env python3
"""Builds the tiny random-weight LoRA fixtures of tests/fixtures/lora_tiny/ for the UNet of
tests/fixtures/sdxl_tiny (make_sdxl_fixtures.py) and the ControlNet of tests/fixtures/sdxl_controlnet_tiny
(make_controlnet_fixtures.py).

Requirements (not needed by CI, which only reads the committed fixtures):
    ~/.cache/gaps/venv/bin/pip install diffusers transformers accelerate
Usage:
    ~/.cache/gaps/venv/bin/python tests/scripts/make_lora_fixtures.py [OUT_DIR]

The LoRA file is written by diffusers' StableDiffusionXLPipeline.save_lora_weights (the PEFT layout that
load_lora_weights reads: unet.<module>.lora_A.weight / lora_B.weight and the lora_adapter_metadata
entry). diffusers' load_lora_weights needs the peft package, which the project's environment does not
install, so the references apply the adapters as PEFT's LoRA Linear computes them,
W x + b + (alpha / r) * B(A x), through forward hooks on the UNet's attention projections.

OUT_DIR (default tests/fixtures/lora_tiny) receives
  pytorch_lora_weights.safetensors  rank-4 adapters on to_q, to_k, to_v, to_out.0 of every attention layer,
                                    random A and B, lora_alpha 8 (scale 2) except
                                    mid_block...attn1.to_q at alpha 2 (alpha_pattern);
  reference/unet_lora.safetensors   the UNet forward of sdxl_tiny/reference/unet.safetensors' inputs with
                                    the adapters (out);
  reference/train_step.safetensors  one denoising-loss step: latents x0, noise, timesteps, context and added
                                    conditioning; x_t = DDPMScheduler.add_noise(x0, noise, t) of the tiny
                                    model's scheduler config; the loss mean((eps_theta(x_t) - noise)^2), the
                                    gradient of every adapter tensor (grad.<key>) and every adapter tensor
                                    after one torch.optim.Adam step (lr 1e-3, after.<key>);
  reference/train_step_controlled.safetensors  the same loss and gradients with the tiny ControlNet's
                                    residuals (control image, conditioning scale 0.8) added to the UNet.
"""
import json
import os
import sys

import torch
import torch.nn.functional as F

import diffusers
from diffusers import ControlNetModel, DDPMScheduler, StableDiffusionXLPipeline, UNet2DConditionModel
from safetensors.torch import load_file

from reference_tensors import reference_saver

HERE = os.path.dirname(os.path.abspath(__file__))
FIXTURES = os.path.join(HERE, "..", "fixtures")
SDXL = os.path.join(FIXTURES, "sdxl_tiny", "model")
CONTROLNET = os.path.join(FIXTURES, "sdxl_controlnet_tiny", "controlnet")
OUT = sys.argv[1] if len(sys.argv) > 1 else os.path.join(FIXTURES, "lora_tiny")
REF = os.path.join(OUT, "reference")
save = reference_saver(REF)
RANK, ALPHA = 4, 8.0
PATTERN_MODULE, PATTERN_ALPHA = "mid_block.attentions.0.transformer_blocks.0.attn1.to_q", 2.0
PROJECTIONS = ("to_q", "to_k", "to_v", "to_out.0")


def projection_modules(unet):
    modules = {}
    for name, module in unet.named_modules():
        if name.endswith(".attn1") or name.endswith(".attn2"):
            for p in PROJECTIONS:
                modules[f"{name}.{p}"] = module.get_submodule(p)
    return modules


def random_lora(modules, g):
    lora = {}
    for name, linear in sorted(modules.items()):
        lora[f"{name}.lora_A.weight"] = torch.randn(RANK, linear.in_features, generator=g) / linear.in_features ** 0.5
        lora[f"{name}.lora_B.weight"] = 0.3 * torch.randn(linear.out_features, RANK, generator=g) / RANK ** 0.5
    return lora


def attach(modules, lora):
    """PEFT's LoRA Linear forward, as hooks: output + scale * B(A x)."""
    handles = []
    for name, linear in modules.items():
        a, b = lora[f"{name}.lora_A.weight"], lora[f"{name}.lora_B.weight"]
        scale = (PATTERN_ALPHA if name == PATTERN_MODULE else ALPHA) / RANK
        handles.append(linear.register_forward_hook(
            lambda mod, inputs, out, a=a, b=b, scale=scale: out + scale * F.linear(F.linear(inputs[0], a), b)))
    return handles


def denoising_loss(unet, x0, noise, t, cond, scheduler, controlnet=None, control_image=None):
    x_t = scheduler.add_noise(x0, noise, t)
    residuals = {}
    if controlnet is not None:
        with torch.no_grad():
            down, mid = controlnet(x_t, t, encoder_hidden_states=cond["context"], controlnet_cond=control_image,
                                   conditioning_scale=0.8, added_cond_kwargs=cond["added"], return_dict=False)
        residuals = {"down_block_additional_residuals": down, "mid_block_additional_residual": mid}
    pred = unet(x_t, t, encoder_hidden_states=cond["context"], added_cond_kwargs=cond["added"], **residuals).sample
    return F.mse_loss(pred.float(), noise.float(), reduction="mean")


def main():
    os.makedirs(REF, exist_ok=True)
    unet = UNet2DConditionModel.from_pretrained(SDXL, subfolder="unet", torch_dtype=torch.float32).eval()
    unet.requires_grad_(False)
    scheduler = DDPMScheduler.from_pretrained(SDXL, subfolder="scheduler")
    modules = projection_modules(unet)
    g = torch.Generator().manual_seed(7)
    lora = random_lora(modules, g)
    metadata = {"r": RANK, "lora_alpha": ALPHA, "alpha_pattern": {PATTERN_MODULE: PATTERN_ALPHA},
                "target_modules": sorted(modules), "init_lora_weights": True}
    StableDiffusionXLPipeline.save_lora_weights(OUT, unet_lora_layers=lora, unet_lora_adapter_metadata=metadata)
    lora = {k[len("unet."):]: v for k, v in load_file(os.path.join(OUT, "pytorch_lora_weights.safetensors")).items()}
    handles = attach(modules, lora)

    inputs = load_file(os.path.join(FIXTURES, "sdxl_tiny", "reference", "unet.safetensors"))
    added = {"text_embeds": inputs["text_embeds"], "time_ids": inputs["time_ids"]}
    with torch.no_grad():
        out = unet(inputs["sample"], inputs["timestep"], encoder_hidden_states=inputs["encoder_hidden_states"],
                   added_cond_kwargs=added).sample
    save("unet_lora", {"out": out})

    x0 = torch.randn(2, 4, 8, 6, generator=g)
    noise = torch.randn(2, 4, 8, 6, generator=g)
    t = torch.tensor([37, 803])
    cond = {"context": inputs["encoder_hidden_states"], "added": added}
    batch = {"x0": x0, "noise": noise, "timesteps": t.float(), "encoder_hidden_states": cond["context"], **added}
    params = {k: v.requires_grad_(True) for k, v in lora.items()}

    loss = denoising_loss(unet, x0, noise, t, cond, scheduler)
    loss.backward()
    record = dict(batch, loss=loss.reshape(1))
    record.update({f"grad.{k}": p.grad.clone() for k, p in params.items()})
    optimizer = torch.optim.Adam(list(params.values()), lr=1e-3)
    optimizer.step()
    record.update({f"after.{k}": p.detach().clone() for k, p in params.items()})
    save("train_step", record)

    with torch.no_grad():  # back to the saved adapters
        saved = load_file(os.path.join(OUT, "pytorch_lora_weights.safetensors"))
        for k, p in params.items():
            p.copy_(saved[f"unet.{k}"])
            p.grad = None
    controlnet = ControlNetModel.from_pretrained(CONTROLNET, torch_dtype=torch.float32).eval()
    control_image = torch.rand(2, 3, 16, 12, generator=g)
    loss = denoising_loss(unet, x0, noise, t, cond, scheduler, controlnet, control_image)
    loss.backward()
    record = dict(batch, loss=loss.reshape(1), control_image=control_image, conditioning_scale=torch.tensor([0.8]))
    record.update({f"grad.{k}": p.grad.clone() for k, p in params.items()})
    save("train_step_controlled", record)
    for h in handles:
        h.remove()
    with open(os.path.join(REF, "versions.json"), "w") as f:
        json.dump({"diffusers": diffusers.__version__, "torch": torch.__version__.split("+")[0]}, f, indent=2)


if __name__ == "__main__":
    main()
