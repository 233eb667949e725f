#include "diffusion_worker/sdxl/clip_vision_encoder.h"

#include <algorithm>
#include <utility>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/model_folder.h"

namespace gaps::sdxl {
namespace {

// transformers' OPENAI_CLIP_MEAN / OPENAI_CLIP_STD, the defaults of CLIPImageProcessor.
constexpr float kClipMean[3] = {0.48145466f, 0.4578275f, 0.40821073f};
constexpr float kClipStd[3] = {0.26862954f, 0.26130258f, 0.27577711f};

}  // namespace

absl::StatusOr<ClipVisionConfig> ClipVisionConfig::from_json(const nlohmann::json& config) {
  const bool nested = config.contains("vision_config") && config["vision_config"].is_object();
  const nlohmann::json& j = nested ? config["vision_config"] : config;
  ClipVisionConfig c;
  GAPS_RETURN_IF_ERROR(c.read_json(j, "CLIP vision config"));
  GAPS_ASSIGN_OR_RETURN(c.image_size, config_value<int64_t>(j, "image_size", c.image_size));
  GAPS_ASSIGN_OR_RETURN(c.patch_size, config_value<int64_t>(j, "patch_size", c.patch_size));
  GAPS_ASSIGN_OR_RETURN(c.num_channels, config_value<int64_t>(j, "num_channels", c.num_channels));
  GAPS_ASSIGN_OR_RETURN(c.projection_dim, config_value<int64_t>(j, "projection_dim", c.projection_dim));
  // A CLIPConfig keeps the shared projection size at its top level.
  if (nested) {
    GAPS_ASSIGN_OR_RETURN(c.projection_dim, config_value<int64_t>(config, "projection_dim", c.projection_dim));
  }
  if (c.num_channels != 3) return absl::InvalidArgumentError("CLIP vision config: only RGB input (num_channels 3)");
  if (c.patch_size < 1 || c.image_size % c.patch_size != 0 || c.projection_dim < 1) {
    return absl::InvalidArgumentError(absl::StrCat("CLIP vision config: image_size ", c.image_size,
                                                   " must be a multiple of patch_size ", c.patch_size,
                                                   " and projection_dim positive"));
  }
  return c;
}

absl::StatusOr<ClipVisionEncoder> ClipVisionEncoder::load_folder(const std::string& folder, at::TensorOptions options) {
  GAPS_ASSIGN_OR_RETURN(nlohmann::json json, read_json_file(folder + "/config.json"));
  auto config = ClipVisionConfig::from_json(json);
  if (!config.ok()) return absl::Status(config.status().code(), absl::StrCat(folder, ": ", config.status().message()));
  GAPS_ASSIGN_OR_RETURN(TensorMap weights, read_folder_weights(folder));
  return load(*config, std::move(weights), options, folder);
}

absl::StatusOr<ClipVisionEncoder> ClipVisionEncoder::load(const ClipVisionConfig& config, TensorMap weights,
                                                          at::TensorOptions options, const std::string& source) {
  weights.erase("vision_model.embeddings.position_ids");  // a buffer some checkpoints carry, not a weight
  WeightLoader w(source, std::move(weights), options);
  GAPS_ASSIGN_OR_RETURN(ClipVisionEncoder e, build(config, w));
  GAPS_RETURN_IF_ERROR(w.finish());
  return e;
}

absl::StatusOr<ClipVisionEncoder> ClipVisionEncoder::build(const ClipVisionConfig& c, WeightLoader& w) {
  ClipVisionEncoder e;
  e.config_ = c;
  const int64_t d = c.hidden_size, grid = c.image_size / c.patch_size;
  e.class_embedding_ = w.take("vision_model.embeddings.class_embedding", {d});
  e.patch_embedding_ =
      w.take("vision_model.embeddings.patch_embedding.weight", {d, c.num_channels, c.patch_size, c.patch_size});
  e.position_embedding_ = w.take("vision_model.embeddings.position_embedding.weight", {grid * grid + 1, d});
  // "pre_layrnorm" is transformers' own spelling of the parameter.
  e.pre_layernorm_ = LayerNorm::load(w, "vision_model.pre_layrnorm", d, c.layer_norm_eps);
  e.encoder_ = ClipEncoder::load(w, "vision_model.encoder.", c);
  e.post_layernorm_ = LayerNorm::load(w, "vision_model.post_layernorm", d, c.layer_norm_eps);
  e.visual_projection_ = Linear::load(w, "visual_projection", d, c.projection_dim, /*with_bias=*/false);
  return e;
}

ClipVisionOutput ClipVisionEncoder::forward(const at::Tensor& pixel_values) const {
  const at::Tensor pixels = pixel_values.to(patch_embedding_.device(), patch_embedding_.scalar_type());
  const int64_t batch = pixels.size(0), d = config_.hidden_size;
  const at::Tensor patches =
      at::conv2d(pixels, patch_embedding_, {}, {config_.patch_size, config_.patch_size}).flatten(2).transpose(1, 2);
  at::Tensor x =
      at::cat({class_embedding_.view({1, 1, d}).expand({batch, 1, d}), patches}, 1) + position_embedding_.unsqueeze(0);
  ClipVisionOutput out;
  out.last_hidden_state = encoder_.forward(pre_layernorm_(x), /*causal=*/false);
  out.pooled = post_layernorm_(out.last_hidden_state.select(1, 0));
  out.image_embeds = visual_projection_(out.pooled);
  return out;
}

absl::StatusOr<at::Tensor> ClipVisionEncoder::preprocess(const at::Tensor& image) const {
  if (!image.defined() || image.dim() != 3 || image.size(2) != 3 || image.size(0) < 1 || image.size(1) < 1) {
    return absl::InvalidArgumentError("CLIP image preprocessing: the image must be H x W x 3");
  }
  const int64_t size = config_.image_size, height = image.size(0), width = image.size(1);
  at::Tensor pixels = (image.to(at::kCPU, at::kFloat).clamp(0, 1) * 255).round().to(at::kByte);
  pixels = pixels.permute({2, 0, 1}).unsqueeze(0).contiguous();
  // Shortest side to `size`, the other int(size * long / short) (transformers' get_resize_output_image_size).
  const int64_t short_side = std::min(height, width), long_side = std::max(height, width);
  const auto scaled_long = static_cast<int64_t>(static_cast<double>(size * long_side) / short_side);
  const int64_t new_h = width <= height ? scaled_long : size, new_w = width <= height ? size : scaled_long;
  if (new_h != height || new_w != width) {
    // torchvision resizes 8-bit images natively on the CPU (rounded back to 8 bits).
    pixels = at::_upsample_bicubic2d_aa(pixels, {new_h, new_w}, /*align_corners=*/false);
  }
  const auto top = static_cast<int64_t>((new_h - size) / 2.0), left = static_cast<int64_t>((new_w - size) / 2.0);
  pixels = pixels.slice(2, top, top + size).slice(3, left, left + size).to(at::kFloat);
  // Rescale and normalise fused as transformers does: (x - 255 mean) / (255 std), in float32.
  const at::Tensor mean = at::tensor(at::ArrayRef<float>(kClipMean, 3)) * 255.0;
  const at::Tensor std = at::tensor(at::ArrayRef<float>(kClipStd, 3)) * 255.0;
  return ((pixels - mean.view({1, 3, 1, 1})) / std.view({1, 3, 1, 1})).contiguous();
}

absl::StatusOr<at::Tensor> ClipVisionEncoder::embed(const std::vector<at::Tensor>& images) const {
  if (images.empty()) return absl::InvalidArgumentError("CLIP image encoder: no images");
  std::vector<at::Tensor> pixels;
  for (const at::Tensor& image : images) {
    GAPS_ASSIGN_OR_RETURN(at::Tensor one, preprocess(image));
    pixels.push_back(std::move(one));
  }
  return forward(at::cat(pixels)).image_embeds;
}

}  // namespace gaps::sdxl
