#pragma once
// The transformer trunk shared by CLIP's text and vision towers (transformers CLIPEncoder): pre-norm
// layers of multi-head self-attention and a two-layer MLP, with the keys both towers' configs use.
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include <nlohmann/json.hpp>
#include "absl/status/status.h"
#include "diffusion_worker/sdxl/layers.h"

namespace gaps::sdxl {

struct ClipEncoderConfig {
  int64_t hidden_size = 768, intermediate_size = 3072, num_hidden_layers = 12, num_attention_heads = 12;
  std::string hidden_act = "quick_gelu";
  double layer_norm_eps = 1e-5;
  // Reads the keys above (defaults when absent); an unsupported activation or a hidden size the heads do
  // not divide is an error naming `what` ("CLIP text config").
  absl::Status read_json(const nlohmann::json& config, const std::string& what);
};

class ClipEncoder {
 public:
  // Takes "<prefix>layers.<i>.{layer_norm1,self_attn.{q,k,v,out}_proj,layer_norm2,mlp.fc1,mlp.fc2}".
  static ClipEncoder load(WeightLoader& w, const std::string& prefix, const ClipEncoderConfig& config);
  // x: B x T x hidden_size through every layer (causal self-attention for the text tower). When
  // penultimate is given it receives the last layer's input (transformers' hidden_states[-2]).
  at::Tensor forward(at::Tensor x, bool causal, at::Tensor* penultimate = nullptr) const;

 private:
  struct Layer {
    LayerNorm layer_norm1, layer_norm2;
    Linear q_proj, k_proj, v_proj, out_proj, fc1, fc2;
  };
  at::Tensor layer_forward(const Layer& layer, const at::Tensor& x, bool causal) const;
  at::Tensor activation(const at::Tensor& x) const;

  ClipEncoderConfig config_;
  std::vector<Layer> layers_;
};

}  // namespace gaps::sdxl
