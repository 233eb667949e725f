#pragma once
// LoRA (low-rank adaptation) of the UNet's attention projections: each adapted Linear computes
//   W x + b + scale * up(down(x)),  down: r x in, up: out x r, scale = alpha / r
// (through Linear::lora_down / lora_up), and the adapters can be merged into W. Files are diffusers' LoRA
// safetensors as StableDiffusionXLPipeline.save_lora_weights writes them for a PEFT-adapted UNet:
//   unet.<module>.lora_A.weight (down), unet.<module>.lora_B.weight (up), e.g. module
//   "down_blocks.1.attentions.0.transformer_blocks.0.attn2.to_q", and the "__metadata__" entry
//   "lora_adapter_metadata" (JSON: "unet.r", "unet.lora_alpha", "unet.target_modules", optional
//   "unet.alpha_pattern"). Without that entry alpha equals each module's rank (scale 1), as diffusers
//   loads such files. Text-encoder adapters, kohya-style files (lora_unet_*, lora_down/lora_up), DoRA and
//   LoRA biases are refused by name.
// New adapters (create) go on the cross-attention layers only (attn2 of every transformer block), as the
// paper's scene adaptation places them. A file attaches whatever attention projections it holds, self-
// attention (attn1) included: third-party LoRAs are often trained that way, and refusing them would only
// stop them from loading, not make them follow the paper.
#include <map>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "common/safetensors.h"
#include "diffusion_worker/sdxl/unet.h"

namespace gaps::sdxl {

struct LoraConfig {
  int64_t rank = 4;
  double alpha = 4;  // scale = alpha / rank
  // Projections of every cross-attention layer that get an adapter (suffixes of their diffusers names).
  std::vector<std::string> targets = {"to_q", "to_k", "to_v", "to_out.0"};
};

class UNetLora {
 public:
  struct Adapter {
    std::string module;   // diffusers name of the adapted Linear
    at::Tensor down, up;  // r x in, out x r, float32; shared with the UNet's Linear while attached
    double alpha = 0;     // scale = alpha / rank
    double scale() const { return alpha / static_cast<double>(down.size(0)); }
  };

  // New adapters on every target projection of the cross-attention layers, attached to unet: down ~
  // U(-1/sqrt(in), 1/sqrt(in)) (PEFT's kaiming-uniform init) from seed, up = 0, so the UNet's output is
  // unchanged until they are trained.
  static absl::StatusOr<UNetLora> create(UNet2DCondition& unet, const LoraConfig& config, uint64_t seed);
  // Reads a LoRA file and attaches all its adapters, on self- or cross-attention, to unet (left untouched on
  // error). Errors name the file and every missing, mis-shaped or unknown tensor.
  static absl::StatusOr<UNetLora> load(const std::string& path, UNet2DCondition& unet);
  static absl::StatusOr<UNetLora> from_tensors(const TensorMap& tensors, const SafetensorsMetadata& metadata,
                                               UNet2DCondition& unet, const std::string& source);
  // Writes the adapters (float32) in the format load() and diffusers' load_lora_weights read.
  absl::Status save(const std::string& path) const;
  // The same file's bytes, and adapters attached from them (what one worker hands another); errors name source.
  absl::StatusOr<std::string> to_bytes() const;
  static absl::StatusOr<UNetLora> from_bytes(std::string bytes, UNet2DCondition& unet, const std::string& source);

  // down and up of every adapter, in module-name order: the trainable parameters.
  std::vector<at::Tensor> parameters() const;
  const std::vector<Adapter>& adapters() const { return adapters_; }

  // W += scale * up @ down on every adapted layer of unet, which then runs without the adapters. A host copy
  // of every W it changes is kept first, so that unmerge_from can restore them bit for bit (subtracting
  // again would leave half-precision rounding behind with every scene). With `base_copies` (module -> that
  // copy, page-locked for a GPU's weights) the copies are taken from there and only the missing ones made:
  // the base weights never change, so a pipeline that merges scene after scene copies them once.
  using BaseCopies = std::map<std::string, at::Tensor>;
  void merge_into(UNet2DCondition& unet, BaseCopies* base_copies = nullptr);
  // Restores the weights merge_into changed; nothing to do when it was not merged.
  void unmerge_from(UNet2DCondition& unet);
  bool merged() const { return !base_weights_.empty(); }
  // Removes the adapters from unet (its base weights are unchanged).
  void detach_from(UNet2DCondition& unet) const;

 private:
  void attach_to(UNet2DCondition& unet) const;
  // The tensors and the PEFT configuration save() writes.
  DecodedSafetensors as_safetensors() const;

  std::vector<Adapter> adapters_;
  std::map<std::string, at::Tensor> base_weights_;  // module -> W before merge_into (CPU)
};

}  // namespace gaps::sdxl
