#pragma once
// transformers' DINOv2 vision transformer as Depth-Anything's backbone (Dinov2Backbone): 14x14 patch
// embeddings, a CLS token, position embeddings resampled (bicubic) to the input's patch grid, pre-norm
// layers with layer scale, and the final layer norm applied to the hidden states of the chosen stages.
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include <nlohmann/json.hpp>
#include "absl/status/statusor.h"
#include "diffusion_worker/sdxl/layers.h"

namespace gaps::depth {

// Dinov2Config, the options that shape the forward. Unsupported options are refused by name.
struct Dinov2Config {
  int64_t hidden_size = 768, num_hidden_layers = 12, num_attention_heads = 12, num_channels = 3;
  int64_t image_size = 224, patch_size = 14;  // square sizes only
  double mlp_ratio = 4.0, layer_norm_eps = 1e-6;
  bool qkv_bias = true, apply_layernorm = true, use_mask_token = true;
  // Whether transformers' backbone returns B x C x h x w maps instead of token sequences (this backbone
  // always returns tokens; Depth-Anything needs tokens and refuses configs asking for maps).
  bool reshape_hidden_states = true;
  // Stages whose hidden states the backbone returns: 0 is the embeddings, i the output of layer i.
  std::vector<int64_t> out_indices;
  // Dinov2Config's own defaults fill absent keys (transformers does the same for a backbone_config dict).
  static absl::StatusOr<Dinov2Config> from_json(const nlohmann::json& config);
  int64_t mlp_hidden_size() const { return static_cast<int64_t>(hidden_size * mlp_ratio); }
};

class Dinov2Backbone {
 public:
  // Takes the backbone's tensors from w under prefix ("backbone"), by their current transformers names
  // (attention.q_proj ...); see rename_legacy_dinov2_names for older checkpoints.
  static Dinov2Backbone load(const Dinov2Config& config, sdxl::WeightLoader& w, const std::string& prefix);

  // pixel_values: B x C x H x W (any size of at least one patch; the grid is H / patch x W / patch).
  // Returns, per out_indices entry, the B x (1 + patches) x hidden_size hidden states of that stage, CLS
  // token first, after the final layer norm when apply_layernorm.
  std::vector<at::Tensor> forward(const at::Tensor& pixel_values) const;

  const Dinov2Config& config() const { return config_; }

 private:
  struct Layer {
    sdxl::LayerNorm norm1, norm2;
    sdxl::Linear q_proj, k_proj, v_proj, o_proj, fc1, fc2;
    at::Tensor layer_scale1, layer_scale2;
  };
  at::Tensor embed(const at::Tensor& pixel_values) const;
  at::Tensor position_embeddings_for(int64_t grid_height, int64_t grid_width) const;
  at::Tensor layer_forward(const Layer& layer, const at::Tensor& x) const;

  Dinov2Config config_;
  at::Tensor cls_token_, position_embeddings_;
  sdxl::Conv2d patch_projection_;
  std::vector<Layer> layers_;
  sdxl::LayerNorm layernorm_;
};

// Checkpoints written by transformers (save_pretrained keeps the published layout) name the attention
// projections attention.attention.{query,key,value} and attention.output.dense; the modules call them
// attention.{q,k,v,o}_proj. Returns the map with the former renamed to the latter.
sdxl::TensorMap rename_legacy_dinov2_names(sdxl::TensorMap tensors);

}  // namespace gaps::depth
