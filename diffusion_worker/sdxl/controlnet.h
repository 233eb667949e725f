#pragma once
// diffusers ControlNetModel as SDXL ControlNets configure it: a copy of the UNet's input half (time and
// text_time embeddings, conv_in, down blocks, mid block; UNet2DCondition::load_input_half) whose conv_in
// output gets the conditioning image's embedding (controlnet_cond_embedding: conv_in, pairs of 3x3 convs
// with the second of each pair strided, conv_out, SiLU between them) added, and one 1x1 "zero
// convolution" per skip connection (controlnet_down_blocks) and for the mid block (controlnet_mid_block).
// The residuals, times the conditioning scale, go to UNetInputs::down_block_residuals / mid_block_residual
// (eq. controlnet of the paper).
#include <optional>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include <nlohmann/json.hpp>
#include "absl/status/statusor.h"
#include "diffusion_worker/sdxl/layers.h"
#include "diffusion_worker/sdxl/unet.h"

namespace gaps::sdxl {

struct ControlNetConfig {
  UNetConfig unet;  // the input half it copies (no up blocks)
  int64_t conditioning_channels = 3;
  std::vector<int64_t> conditioning_embedding_out_channels;  // one per level of the conditioning embedding
  bool bgr = false;  // controlnet_conditioning_channel_order "bgr": the image's channels are flipped first
  // Factor from the conditioning image's size to the latent size: 2^(levels - 1).
  int64_t downscale() const { return int64_t{1} << (conditioning_embedding_out_channels.size() - 1); }
  // Rejects what is not implemented (global_pool_conditions, class embeddings, other mid blocks, ...).
  static absl::StatusOr<ControlNetConfig> from_json(const nlohmann::json& config);
};

struct ControlNetResiduals {
  std::vector<at::Tensor> down;  // one per UNet skip connection
  at::Tensor mid;
};

class ControlNet {
 public:
  static absl::StatusOr<ControlNet> load(const ControlNetConfig& config, TensorMap weights, at::TensorOptions options,
                                         const std::string& source);
  // A ControlNetModel folder: config.json and its *.safetensors (variant "fp16": *.fp16.safetensors).
  static absl::StatusOr<ControlNet> load_folder(const std::string& dir, at::TensorOptions options,
                                                const std::string& variant = "");
  // inputs: as for the UNet (sample, timestep, encoder_hidden_states, text_embeds, time_ids); image:
  // B x conditioning_channels x H x W with H x W = the latent size times config().downscale(), in the
  // model's dtype (SDXL depth ControlNets take [0, 1]); scale: one per batch entry, or one for all.
  // Guess mode is not implemented: the residuals are scaled uniformly, as diffusers does without it.
  ControlNetResiduals forward(const UNetInputs& inputs, const at::Tensor& image, const at::Tensor& scale) const;

  const ControlNetConfig& config() const { return config_; }
  // An error naming the mismatch when these residuals do not fit unet (channels, blocks, embeddings).
  absl::Status check_compatible(const UNetConfig& unet) const;

 private:
  ControlNetConfig config_;
  std::optional<UNet2DCondition> trunk_;
  Conv2d cond_in_, cond_out_;
  std::vector<Conv2d> cond_blocks_;
  std::vector<Conv2d> zero_convs_;
  Conv2d zero_conv_mid_;
};

}  // namespace gaps::sdxl
