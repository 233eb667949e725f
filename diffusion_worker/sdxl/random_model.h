#pragma once
// Writes a diffusers-layout SDXL folder with the real SDXL base architecture (UNet 2.6B parameters, VAE,
// CLIP ViT-L and OpenCLIP bigG text encoders) and seeded random weights, for speed measurements without
// downloading the model. Loadable by SdxlPipeline and by diffusers' from_pretrained alike.
#include <cstdint>
#include <string>

#include <nlohmann/json.hpp>
#include "absl/status/status.h"

namespace gaps::sdxl {

// The component configs (config.json contents) of an SDXL folder.
struct SdxlConfigs {
  nlohmann::json unet, vae, text_encoder, text_encoder_2, scheduler;
  // The published SDXL base 1.0 configs.
  static SdxlConfigs base();
};

// Writes folder (created if needed): model_index.json, every component's config and random weights
// (normal with std 1/sqrt(fan-in) for matrices and kernels, std 0.02 for embeddings, 1 for norm scales,
// 0 for biases; drawn from a CPU generator seeded with seed) stored as dtype_name ("float16",
// "bfloat16" or "float32"), and a byte-level CLIP tokenizer (no merges) with the real special-token ids.
// Text-encoder tensors get transformers' "text_model." prefix (the layout of the released checkpoints).
absl::Status write_random_sdxl_model(const std::string& folder, const SdxlConfigs& configs, uint64_t seed,
                                     const std::string& dtype_name);

}  // namespace gaps::sdxl
