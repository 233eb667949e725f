#include "diffusion_worker/sdxl/clip_text_encoder.h"

#include <utility>

#include <ATen/ATen.h>
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "diffusion_worker/sdxl/model_folder.h"
#include "gs_trainer/status_macros.h"

namespace gaps::sdxl {

absl::StatusOr<ClipTextConfig> ClipTextConfig::from_json(const nlohmann::json& j) {
  ClipTextConfig c;
  GAPS_ASSIGN_OR_RETURN(c.vocab_size, config_value<int64_t>(j, "vocab_size", c.vocab_size));
  GAPS_ASSIGN_OR_RETURN(c.hidden_size, config_value<int64_t>(j, "hidden_size", c.hidden_size));
  GAPS_ASSIGN_OR_RETURN(c.intermediate_size, config_value<int64_t>(j, "intermediate_size", c.intermediate_size));
  GAPS_ASSIGN_OR_RETURN(c.num_hidden_layers, config_value<int64_t>(j, "num_hidden_layers", c.num_hidden_layers));
  GAPS_ASSIGN_OR_RETURN(c.num_attention_heads, config_value<int64_t>(j, "num_attention_heads", c.num_attention_heads));
  GAPS_ASSIGN_OR_RETURN(c.max_position_embeddings,
                        config_value<int64_t>(j, "max_position_embeddings", c.max_position_embeddings));
  GAPS_ASSIGN_OR_RETURN(c.projection_dim, config_value<int64_t>(j, "projection_dim", c.projection_dim));
  GAPS_ASSIGN_OR_RETURN(c.eos_token_id, config_value<int64_t>(j, "eos_token_id", c.eos_token_id));
  GAPS_ASSIGN_OR_RETURN(c.hidden_act, config_value<std::string>(j, "hidden_act", c.hidden_act));
  GAPS_ASSIGN_OR_RETURN(c.layer_norm_eps, config_value<double>(j, "layer_norm_eps", c.layer_norm_eps));
  if (c.hidden_act != "quick_gelu" && c.hidden_act != "gelu") {
    return absl::UnimplementedError(absl::StrCat("CLIP text config: hidden_act '", c.hidden_act, "' is not supported"));
  }
  if (c.num_hidden_layers < 2 || c.hidden_size % c.num_attention_heads != 0) {
    return absl::InvalidArgumentError("CLIP text config: needs >= 2 layers and hidden_size divisible by the heads");
  }
  return c;
}

absl::StatusOr<ClipTextEncoder> ClipTextEncoder::load(const ClipTextConfig& c, bool with_projection, TensorMap weights,
                                                      at::TensorOptions options, const std::string& source) {
  // Older transformers checkpoints prefix the text tower with "text_model."; newer ones do not.
  TensorMap renamed;
  for (auto& [name, tensor] : weights) {
    renamed.emplace(absl::StartsWith(name, "text_model.") ? name.substr(11) : name, tensor);
  }
  renamed.erase("embeddings.position_ids");  // a buffer some checkpoints carry, not a weight
  WeightLoader w(source, std::move(renamed), options);
  GAPS_ASSIGN_OR_RETURN(ClipTextEncoder e, build(c, with_projection, w, source));
  GAPS_RETURN_IF_ERROR(w.finish());
  return e;
}

std::vector<TensorSpec> ClipTextEncoder::weight_specs(const ClipTextConfig& c, bool with_projection) {
  WeightLoader w("", {}, at::TensorOptions().device(at::kMeta));
  (void)build(c, with_projection, w, "");
  return w.requested();
}

absl::StatusOr<ClipTextEncoder> ClipTextEncoder::build(const ClipTextConfig& c, bool with_projection, WeightLoader& w,
                                                       const std::string& source) {
  ClipTextEncoder e;
  e.config_ = c;
  const int64_t d = c.hidden_size;
  e.token_embedding = w.take("embeddings.token_embedding.weight", {c.vocab_size, d});
  e.position_embedding = w.take("embeddings.position_embedding.weight", {c.max_position_embeddings, d});
  for (int64_t i = 0; i < c.num_hidden_layers; ++i) {
    const std::string p = absl::StrCat("encoder.layers.", i, ".");
    e.layers_.push_back({LayerNorm::load(w, p + "layer_norm1", d, c.layer_norm_eps),
                         LayerNorm::load(w, p + "layer_norm2", d, c.layer_norm_eps),
                         Linear::load(w, p + "self_attn.q_proj", d, d), Linear::load(w, p + "self_attn.k_proj", d, d),
                         Linear::load(w, p + "self_attn.v_proj", d, d), Linear::load(w, p + "self_attn.out_proj", d, d),
                         Linear::load(w, p + "mlp.fc1", d, c.intermediate_size),
                         Linear::load(w, p + "mlp.fc2", c.intermediate_size, d)});
  }
  e.final_layer_norm_ = LayerNorm::load(w, "final_layer_norm", d, c.layer_norm_eps);
  e.with_projection_ = with_projection;
  if (with_projection) {
    if (c.projection_dim <= 0) return absl::InvalidArgumentError(absl::StrCat(source, ": projection_dim missing from the config"));
    e.text_projection_ = Linear::load(w, "text_projection", d, c.projection_dim, /*with_bias=*/false);
  }
  return e;
}

at::Tensor ClipTextEncoder::activation(const at::Tensor& x) const {
  return config_.hidden_act == "gelu" ? at::gelu(x) : x * at::sigmoid(1.702 * x);
}

at::Tensor ClipTextEncoder::layer_forward(const Layer& l, const at::Tensor& x) const {
  const at::Tensor h = l.layer_norm1(x);
  at::Tensor out = x + l.out_proj(multi_head_attention(l.q_proj(h), l.k_proj(h), l.v_proj(h),
                                                       config_.num_attention_heads, /*causal=*/true));
  return out + l.fc2(activation(l.fc1(l.layer_norm2(out))));
}

ClipTextOutput ClipTextEncoder::forward(const at::Tensor& input_ids) const {
  const int64_t t = input_ids.size(1);
  const at::Tensor ids = input_ids.to(token_embedding.device());
  at::Tensor x = at::embedding(token_embedding, ids) + position_embedding.slice(0, 0, t).unsqueeze(0);
  ClipTextOutput out;
  for (size_t i = 0; i < layers_.size(); ++i) {
    if (i + 1 == layers_.size()) out.penultimate = x;
    x = layer_forward(layers_[i], x);
  }
  out.last_hidden_state = final_layer_norm_(x);
  // The pooled token: the first end-of-text token (the legacy eos id 2 meant "highest id" instead).
  const at::Tensor eos_pos = config_.eos_token_id == 2 ? ids.argmax(-1)
                                                       : (ids == config_.eos_token_id).to(at::kInt).argmax(-1);
  const at::Tensor flat_index = at::arange(ids.size(0), ids.options()) * t + eos_pos.to(at::kLong);
  out.pooled = out.last_hidden_state.reshape({-1, out.last_hidden_state.size(2)}).index_select(0, flat_index);
  if (with_projection_) out.text_embeds = text_projection_(out.pooled);
  return out;
}

}  // namespace gaps::sdxl
