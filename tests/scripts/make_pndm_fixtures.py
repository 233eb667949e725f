#!/usr/bin/env python3
"""Records diffusers' PNDMScheduler (PLMS steps, skip_prk_steps=True, as Stable Diffusion 2's folders ship
it) for the parity test of diffusion_worker/sdxl/schedulers.* (tests/sdxl_schedulers_test.cpp).

Requirements (not needed by CI, which only reads the committed fixture):
    ~/.cache/gaps/venv/bin/pip install diffusers
Usage:
    ~/.cache/gaps/venv/bin/python tests/scripts/make_pndm_fixtures.py [OUT_FILE]

OUT_FILE (default tests/fixtures/pndm/pndm.safetensors) receives, for each timestep spacing (leading,
trailing, linspace) and set_alpha_to_one (false, as SD2, and true): the schedule of 5 steps (6 timesteps:
PLMS repeats the second) and the samples after each of its steps, run from the sample "x" with the model
outputs "eps0".."eps5" (every branch of the linear multistep update); plus DDPM noising at step 2 of the
leading schedule.
"""
import os
import sys

import torch
from safetensors.torch import save_file

import diffusers
from diffusers import PNDMScheduler

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = sys.argv[1] if len(sys.argv) > 1 else os.path.join(HERE, "..", "fixtures", "pndm", "pndm.safetensors")
STEPS = 5


def main():
    g = torch.Generator().manual_seed(0)
    ref = {"x": torch.randn(1, 4, 4, 3, generator=g)}
    for k in range(STEPS + 1):
        ref[f"eps{k}"] = torch.randn(1, 4, 4, 3, generator=g)
    ref["noise"] = torch.randn(1, 4, 4, 3, generator=g)
    base = dict(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", num_train_timesteps=1000,
                steps_offset=1, skip_prk_steps=True)
    for spacing in ("leading", "trailing", "linspace"):
        for alpha_to_one in (False, True):
            s = PNDMScheduler(timestep_spacing=spacing, set_alpha_to_one=alpha_to_one, **base)
            s.set_timesteps(STEPS)
            key = f"{spacing}_{'one' if alpha_to_one else 'first'}"
            ref[key + "_timesteps"] = s.timesteps.to(torch.float64)
            sample = ref["x"].clone()
            for k, t in enumerate(s.timesteps):
                sample = s.step(ref[f"eps{k}"], t, sample).prev_sample
                ref[f"{key}_step{k}"] = sample.clone()
    s = PNDMScheduler(timestep_spacing="leading", **base)
    s.set_timesteps(STEPS)
    ref["noisy_timestep"] = s.timesteps[2:3].to(torch.float64)
    ref["noisy"] = s.add_noise(ref["x"], ref["noise"], s.timesteps[2:3])
    os.makedirs(os.path.dirname(OUT), exist_ok=True)
    save_file({k: v.contiguous() for k, v in ref.items()}, OUT, metadata={"diffusers": diffusers.__version__})


if __name__ == "__main__":
    main()
