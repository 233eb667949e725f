#pragma once
// transformers CLIPVisionModelWithProjection, the image encoder of IP-Adapter (CLIP ViT-H/14 for
// ip-adapter_sdxl_vit-h, OpenCLIP ViT-bigG/14 for ip-adapter_sdxl), and CLIPImageProcessor's preprocessing
// with the settings diffusers' load_ip_adapter gives it (shortest side and center crop to the encoder's
// image_size, bicubic with antialiasing, rescale, CLIP mean and std).
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include <nlohmann/json.hpp>
#include "absl/status/statusor.h"
#include "diffusion_worker/sdxl/clip_encoder.h"
#include "diffusion_worker/sdxl/layers.h"

namespace gaps::sdxl {

struct ClipVisionConfig : ClipEncoderConfig {
  int64_t image_size = 224, patch_size = 32, num_channels = 3, projection_dim = 512;
  // A CLIPVisionConfig, or a full CLIPConfig whose "vision_config" it reads.
  static absl::StatusOr<ClipVisionConfig> from_json(const nlohmann::json& config);
};

struct ClipVisionOutput {
  at::Tensor last_hidden_state;  // B x (1 + patches) x D, before the post-layernorm
  at::Tensor pooled;             // B x D, post_layernorm of the class token
  at::Tensor image_embeds;       // B x P, visual_projection(pooled)
};

class ClipVisionEncoder {
 public:
  // A transformers folder: config.json and model.safetensors (or sharded *.safetensors).
  static absl::StatusOr<ClipVisionEncoder> load_folder(const std::string& folder, at::TensorOptions options);
  static absl::StatusOr<ClipVisionEncoder> load(const ClipVisionConfig& config, TensorMap weights,
                                                at::TensorOptions options, const std::string& source);
  // pixel_values: B x 3 x image_size x image_size, already preprocessed.
  ClipVisionOutput forward(const at::Tensor& pixel_values) const;
  // CLIPImageProcessor: image H x W x 3 in [0, 1] (any device) -> 1 x 3 x image_size x image_size float32
  // on the CPU. The image is first quantised to 8 bits, as the processor sees a PIL image: the shortest
  // side is resized to image_size with antialiased bicubic on the 8-bit values (rounded back to 8 bits),
  // the center image_size square is cropped, and (x / 255 - mean) / std is taken per channel.
  absl::StatusOr<at::Tensor> preprocess(const at::Tensor& image) const;
  // preprocess + forward of each image: image_embeds B x P in the encoder's dtype, on its device.
  absl::StatusOr<at::Tensor> embed(const std::vector<at::Tensor>& images) const;

  const ClipVisionConfig& config() const { return config_; }

 private:
  static absl::StatusOr<ClipVisionEncoder> build(const ClipVisionConfig& config, WeightLoader& w);

  ClipVisionConfig config_;
  at::Tensor class_embedding_, position_embedding_, patch_embedding_;  // the patch conv has no bias
  LayerNorm pre_layernorm_, post_layernorm_;
  ClipEncoder encoder_;
  Linear visual_projection_;
};

}  // namespace gaps::sdxl
