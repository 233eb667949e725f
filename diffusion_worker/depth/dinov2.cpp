#include "diffusion_worker/depth/dinov2.h"

#include <cmath>
#include <utility>

#include <ATen/ATen.h>
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_replace.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/model_folder.h"

namespace gaps::depth {
namespace {

using sdxl::config_value;
using sdxl::join_name;

// image_size and patch_size are an int or a [height, width] pair; only square ones are supported.
absl::StatusOr<int64_t> square_size(const nlohmann::json& config, const std::string& key, int64_t fallback) {
  if (!config.contains(key) || config[key].is_null()) return fallback;
  const nlohmann::json& value = config[key];
  if (value.is_number_integer()) return value.get<int64_t>();
  if (value.is_array() && value.size() == 2 && value[0].is_number_integer() && value[0] == value[1]) {
    return value[0].get<int64_t>();
  }
  return absl::UnimplementedError(
      absl::StrCat("DINOv2 config: ", key, " ", value.dump(), " is not supported (a single size or a square pair)"));
}

// out_indices, else out_features ("stem" is stage 0, "stageN" stage N), else the last stage (the default
// of transformers' backbone configs).
absl::StatusOr<std::vector<int64_t>> stage_indices(const nlohmann::json& config, int64_t num_layers) {
  std::vector<int64_t> indices;
  if (config.contains("out_indices") && !config["out_indices"].is_null()) {
    GAPS_ASSIGN_OR_RETURN(indices, config_value<std::vector<int64_t>>(config, "out_indices", {}));
  } else if (config.contains("out_features") && !config["out_features"].is_null()) {
    GAPS_ASSIGN_OR_RETURN(const auto names, config_value<std::vector<std::string>>(config, "out_features", {}));
    for (const auto& name : names) {
      int64_t stage = 0;
      if (name != "stem" && !(absl::StartsWith(name, "stage") && absl::SimpleAtoi(name.substr(5), &stage))) {
        return absl::InvalidArgumentError(absl::StrCat("DINOv2 config: out_features entry '", name, "' is no stage"));
      }
      indices.push_back(stage);
    }
  } else {
    indices = {num_layers};
  }
  for (size_t i = 0; i < indices.size(); ++i) {
    // Negative indices count from the end, as in transformers' stage lists.
    if (indices[i] < 0) indices[i] += num_layers + 1;
    if (indices[i] < 0 || indices[i] > num_layers || (i > 0 && indices[i] <= indices[i - 1])) {
      return absl::InvalidArgumentError(absl::StrCat("DINOv2 config: out_indices [", absl::StrJoin(indices, ", "),
                                                     "] must be increasing stages in 0..", num_layers));
    }
  }
  if (indices.empty()) return absl::InvalidArgumentError("DINOv2 config: out_indices is empty");
  return indices;
}

}  // namespace

absl::StatusOr<Dinov2Config> Dinov2Config::from_json(const nlohmann::json& j) {
  Dinov2Config c;
  GAPS_ASSIGN_OR_RETURN(const std::string model_type, config_value<std::string>(j, "model_type", "dinov2"));
  if (model_type != "dinov2") {
    return absl::UnimplementedError(
        absl::StrCat("backbone model_type '", model_type, "' is not supported (only 'dinov2')"));
  }
  GAPS_ASSIGN_OR_RETURN(c.hidden_size, config_value<int64_t>(j, "hidden_size", c.hidden_size));
  GAPS_ASSIGN_OR_RETURN(c.num_hidden_layers, config_value<int64_t>(j, "num_hidden_layers", c.num_hidden_layers));
  GAPS_ASSIGN_OR_RETURN(c.num_attention_heads, config_value<int64_t>(j, "num_attention_heads", c.num_attention_heads));
  GAPS_ASSIGN_OR_RETURN(c.num_channels, config_value<int64_t>(j, "num_channels", c.num_channels));
  GAPS_ASSIGN_OR_RETURN(c.mlp_ratio, config_value<double>(j, "mlp_ratio", c.mlp_ratio));
  GAPS_ASSIGN_OR_RETURN(c.layer_norm_eps, config_value<double>(j, "layer_norm_eps", c.layer_norm_eps));
  GAPS_ASSIGN_OR_RETURN(c.qkv_bias, config_value<bool>(j, "qkv_bias", c.qkv_bias));
  GAPS_ASSIGN_OR_RETURN(c.apply_layernorm, config_value<bool>(j, "apply_layernorm", c.apply_layernorm));
  GAPS_ASSIGN_OR_RETURN(c.use_mask_token, config_value<bool>(j, "use_mask_token", c.use_mask_token));
  GAPS_ASSIGN_OR_RETURN(c.reshape_hidden_states,
                        config_value<bool>(j, "reshape_hidden_states", c.reshape_hidden_states));
  GAPS_ASSIGN_OR_RETURN(c.image_size, square_size(j, "image_size", c.image_size));
  GAPS_ASSIGN_OR_RETURN(c.patch_size, square_size(j, "patch_size", c.patch_size));
  GAPS_ASSIGN_OR_RETURN(const std::string hidden_act, config_value<std::string>(j, "hidden_act", "gelu"));
  if (hidden_act != "gelu") {
    return absl::UnimplementedError(
        absl::StrCat("DINOv2 config: hidden_act '", hidden_act, "' is not supported (gelu)"));
  }
  GAPS_ASSIGN_OR_RETURN(const bool swiglu, config_value<bool>(j, "use_swiglu_ffn", false));
  if (swiglu)
    return absl::UnimplementedError("DINOv2 config: use_swiglu_ffn is not supported (the MLP is fc1-gelu-fc2)");
  if (c.hidden_size <= 0 || c.num_attention_heads <= 0 || c.hidden_size % c.num_attention_heads != 0) {
    return absl::InvalidArgumentError("DINOv2 config: hidden_size must be a positive multiple of num_attention_heads");
  }
  if (c.num_hidden_layers <= 0 || c.patch_size <= 0 || c.image_size < c.patch_size || c.mlp_hidden_size() <= 0) {
    return absl::InvalidArgumentError(
        "DINOv2 config: num_hidden_layers, patch_size, image_size or mlp_ratio out of range");
  }
  GAPS_ASSIGN_OR_RETURN(c.out_indices, stage_indices(j, c.num_hidden_layers));
  return c;
}

sdxl::TensorMap rename_legacy_dinov2_names(sdxl::TensorMap tensors) {
  sdxl::TensorMap renamed;
  for (auto& [name, tensor] : tensors) {
    renamed.emplace(absl::StrReplaceAll(name, {{"attention.attention.query", "attention.q_proj"},
                                               {"attention.attention.key", "attention.k_proj"},
                                               {"attention.attention.value", "attention.v_proj"},
                                               {"attention.output.dense", "attention.o_proj"}}),
                    std::move(tensor));
  }
  return renamed;
}

Dinov2Backbone Dinov2Backbone::load(const Dinov2Config& c, sdxl::WeightLoader& w, const std::string& prefix) {
  Dinov2Backbone b;
  b.config_ = c;
  const int64_t d = c.hidden_size;
  const std::string emb = join_name(prefix, "embeddings");
  b.cls_token_ = w.take(join_name(emb, "cls_token"), {1, 1, d});
  // Only masked-image pre-training uses the mask token; it is part of the checkpoint all the same.
  if (c.use_mask_token) (void)w.take(join_name(emb, "mask_token"), {1, d});
  const int64_t grid = c.image_size / c.patch_size;
  b.position_embeddings_ = w.take(join_name(emb, "position_embeddings"), {1, grid * grid + 1, d});
  b.patch_projection_ = sdxl::Conv2d::load(w, join_name(emb, "patch_embeddings.projection"), c.num_channels, d,
                                           c.patch_size, c.patch_size, 0);
  for (int64_t i = 0; i < c.num_hidden_layers; ++i) {
    const std::string p = join_name(prefix, absl::StrCat("encoder.layer.", i));
    Layer l;
    l.norm1 = sdxl::LayerNorm::load(w, join_name(p, "norm1"), d, c.layer_norm_eps);
    l.q_proj = sdxl::Linear::load(w, join_name(p, "attention.q_proj"), d, d, c.qkv_bias);
    l.k_proj = sdxl::Linear::load(w, join_name(p, "attention.k_proj"), d, d, c.qkv_bias);
    l.v_proj = sdxl::Linear::load(w, join_name(p, "attention.v_proj"), d, d, c.qkv_bias);
    l.o_proj = sdxl::Linear::load(w, join_name(p, "attention.o_proj"), d, d);
    l.layer_scale1 = w.take(join_name(p, "layer_scale1.lambda1"), {d});
    l.norm2 = sdxl::LayerNorm::load(w, join_name(p, "norm2"), d, c.layer_norm_eps);
    l.fc1 = sdxl::Linear::load(w, join_name(p, "mlp.fc1"), d, c.mlp_hidden_size());
    l.fc2 = sdxl::Linear::load(w, join_name(p, "mlp.fc2"), c.mlp_hidden_size(), d);
    l.layer_scale2 = w.take(join_name(p, "layer_scale2.lambda1"), {d});
    b.layers_.push_back(std::move(l));
  }
  b.layernorm_ = sdxl::LayerNorm::load(w, join_name(prefix, "layernorm"), d, c.layer_norm_eps);
  return b;
}

at::Tensor Dinov2Backbone::position_embeddings_for(int64_t grid_height, int64_t grid_width) const {
  const int64_t positions = position_embeddings_.size(1) - 1, d = position_embeddings_.size(2);
  const auto side = static_cast<int64_t>(std::sqrt(static_cast<double>(positions)));
  if (grid_height == side && grid_width == side) return position_embeddings_;
  // Resampled in float32 whatever the model's dtype: bicubic in half precision shifts the embeddings.
  const at::Tensor grid =
      position_embeddings_.slice(1, 1).reshape({1, side, side, d}).permute({0, 3, 1, 2}).to(at::kFloat);
  const at::Tensor resampled = at::upsample_bicubic2d(grid, {grid_height, grid_width}, /*align_corners=*/false)
                                   .to(position_embeddings_.scalar_type())
                                   .permute({0, 2, 3, 1})
                                   .reshape({1, -1, d});
  return at::cat({position_embeddings_.slice(1, 0, 1), resampled}, 1);
}

at::Tensor Dinov2Backbone::embed(const at::Tensor& pixel_values) const {
  const at::Tensor patches = patch_projection_(pixel_values.to(cls_token_.scalar_type()));  // B x D x gh x gw
  const int64_t batch = patches.size(0);
  const at::Tensor tokens = at::cat({cls_token_.expand({batch, -1, -1}), patches.flatten(2).transpose(1, 2)}, 1);
  return tokens + position_embeddings_for(patches.size(2), patches.size(3));
}

at::Tensor Dinov2Backbone::layer_forward(const Layer& l, const at::Tensor& x) const {
  const at::Tensor h = l.norm1(x);
  const at::Tensor attended =
      l.o_proj(sdxl::multi_head_attention(l.q_proj(h), l.k_proj(h), l.v_proj(h), config_.num_attention_heads));
  const at::Tensor y = x + attended * l.layer_scale1;
  return y + l.fc2(at::gelu(l.fc1(l.norm2(y)))) * l.layer_scale2;
}

std::vector<at::Tensor> Dinov2Backbone::forward(const at::Tensor& pixel_values) const {
  std::vector<at::Tensor> stages;
  stages.reserve(config_.out_indices.size());
  const auto keep = [&](int64_t stage, const at::Tensor& hidden) {
    for (const int64_t wanted : config_.out_indices) {
      if (wanted == stage) stages.push_back(config_.apply_layernorm ? layernorm_(hidden) : hidden);
    }
  };
  at::Tensor x = embed(pixel_values);
  keep(0, x);
  for (size_t i = 0; i < layers_.size(); ++i) {
    x = layer_forward(layers_[i], x);
    keep(static_cast<int64_t>(i) + 1, x);
  }
  return stages;
}

}  // namespace gaps::depth
