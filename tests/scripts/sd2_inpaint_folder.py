"""Writes a diffusers StableDiffusionInpaintPipeline folder with stabilityai/stable-diffusion-2-inpainting's
scheduler and tokenizer files around given models. Shared by make_inpaint_fixtures.py (the tiny test
fixture) and bench/make_random_generator_weights.py (the benchmark's random SD2 inpainting), so that both
folders have the layout the LibTorch loader reads."""
import os
import shutil

from diffusers import DDIMScheduler, StableDiffusionInpaintPipeline


def sd2_ddim_scheduler():
    """DDIM on SD2's betas (the published folder ships PNDM with the same betas)."""
    return DDIMScheduler(beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", num_train_timesteps=1000,
                         steps_offset=1, clip_sample=False, set_alpha_to_one=False, timestep_spacing="leading",
                         prediction_type="epsilon")


def save_sd2_inpaint_folder(folder, vae, text_encoder, unet, tokenizer, tokenizer_dir):
    """Saves the pipeline (safetensors) with a DDIM scheduler and returns it. tokenizer_dir is the folder
    the tokenizer was read from: its BPE files are copied, since transformers 5 saves only tokenizer.json and
    the LibTorch tokenizer reads vocab.json and merges.txt."""
    pipe = StableDiffusionInpaintPipeline(vae=vae, text_encoder=text_encoder, tokenizer=tokenizer, unet=unet,
                                          scheduler=sd2_ddim_scheduler(), safety_checker=None, feature_extractor=None,
                                          requires_safety_checker=False)
    pipe.save_pretrained(folder, safe_serialization=True)
    for name in ("vocab.json", "merges.txt"):
        shutil.copy(os.path.join(tokenizer_dir, name), os.path.join(folder, "tokenizer", name))
    return pipe
