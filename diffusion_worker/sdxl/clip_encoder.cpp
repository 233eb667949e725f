#include "diffusion_worker/sdxl/clip_encoder.h"

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/model_folder.h"

namespace gaps::sdxl {

absl::Status ClipEncoderConfig::read_json(const nlohmann::json& j, const std::string& what) {
  GAPS_ASSIGN_OR_RETURN(hidden_size, config_value<int64_t>(j, "hidden_size", hidden_size));
  GAPS_ASSIGN_OR_RETURN(intermediate_size, config_value<int64_t>(j, "intermediate_size", intermediate_size));
  GAPS_ASSIGN_OR_RETURN(num_hidden_layers, config_value<int64_t>(j, "num_hidden_layers", num_hidden_layers));
  GAPS_ASSIGN_OR_RETURN(num_attention_heads, config_value<int64_t>(j, "num_attention_heads", num_attention_heads));
  GAPS_ASSIGN_OR_RETURN(hidden_act, config_value<std::string>(j, "hidden_act", hidden_act));
  GAPS_ASSIGN_OR_RETURN(layer_norm_eps, config_value<double>(j, "layer_norm_eps", layer_norm_eps));
  if (hidden_act != "quick_gelu" && hidden_act != "gelu") {
    return absl::UnimplementedError(absl::StrCat(what, ": hidden_act '", hidden_act, "' is not supported"));
  }
  if (num_hidden_layers < 1 || num_attention_heads < 1 || hidden_size % num_attention_heads != 0) {
    return absl::InvalidArgumentError(absl::StrCat(what, ": needs >= 1 layer and hidden_size divisible by the heads"));
  }
  return absl::OkStatus();
}

ClipEncoder ClipEncoder::load(WeightLoader& w, const std::string& prefix, const ClipEncoderConfig& c) {
  ClipEncoder e;
  e.config_ = c;
  const int64_t d = c.hidden_size;
  for (int64_t i = 0; i < c.num_hidden_layers; ++i) {
    const std::string p = absl::StrCat(prefix, "layers.", i, ".");
    e.layers_.push_back({LayerNorm::load(w, p + "layer_norm1", d, c.layer_norm_eps),
                         LayerNorm::load(w, p + "layer_norm2", d, c.layer_norm_eps),
                         Linear::load(w, p + "self_attn.q_proj", d, d), Linear::load(w, p + "self_attn.k_proj", d, d),
                         Linear::load(w, p + "self_attn.v_proj", d, d), Linear::load(w, p + "self_attn.out_proj", d, d),
                         Linear::load(w, p + "mlp.fc1", d, c.intermediate_size),
                         Linear::load(w, p + "mlp.fc2", c.intermediate_size, d)});
  }
  return e;
}

at::Tensor ClipEncoder::activation(const at::Tensor& x) const {
  return config_.hidden_act == "gelu" ? at::gelu(x) : x * at::sigmoid(1.702 * x);
}

at::Tensor ClipEncoder::layer_forward(const Layer& l, const at::Tensor& x, bool causal) const {
  const at::Tensor h = l.layer_norm1(x);
  at::Tensor out =
      x + l.out_proj(multi_head_attention(l.q_proj(h), l.k_proj(h), l.v_proj(h), config_.num_attention_heads, causal));
  return out + l.fc2(activation(l.fc1(l.layer_norm2(out))));
}

at::Tensor ClipEncoder::forward(at::Tensor x, bool causal, at::Tensor* penultimate) const {
  for (size_t i = 0; i < layers_.size(); ++i) {
    if (penultimate != nullptr && i + 1 == layers_.size()) *penultimate = x;
    x = layer_forward(layers_[i], x, causal);
  }
  return x;
}

}  // namespace gaps::sdxl
