#include "diffusion_worker/sdxl/clip_text_encoder.h"

#include <utility>

#include <ATen/ATen.h>
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/model_folder.h"

namespace gaps::sdxl {

absl::StatusOr<ClipTextConfig> ClipTextConfig::from_json(const nlohmann::json& j) {
  ClipTextConfig c;
  GAPS_RETURN_IF_ERROR(c.read_json(j, "CLIP text config"));
  GAPS_ASSIGN_OR_RETURN(c.vocab_size, config_value<int64_t>(j, "vocab_size", c.vocab_size));
  GAPS_ASSIGN_OR_RETURN(c.max_position_embeddings,
                        config_value<int64_t>(j, "max_position_embeddings", c.max_position_embeddings));
  GAPS_ASSIGN_OR_RETURN(c.projection_dim, config_value<int64_t>(j, "projection_dim", c.projection_dim));
  GAPS_ASSIGN_OR_RETURN(c.eos_token_id, config_value<int64_t>(j, "eos_token_id", c.eos_token_id));
  if (c.num_hidden_layers < 2) {
    return absl::InvalidArgumentError("CLIP text config: needs >= 2 layers (SDXL reads the penultimate one)");
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
  e.encoder_ = ClipEncoder::load(w, "encoder.", c);
  e.final_layer_norm_ = LayerNorm::load(w, "final_layer_norm", d, c.layer_norm_eps);
  e.with_projection_ = with_projection;
  if (with_projection) {
    if (c.projection_dim <= 0)
      return absl::InvalidArgumentError(absl::StrCat(source, ": projection_dim missing from the config"));
    e.text_projection_ = Linear::load(w, "text_projection", d, c.projection_dim, /*with_bias=*/false);
  }
  return e;
}

ClipTextOutput ClipTextEncoder::forward(const at::Tensor& input_ids) const {
  const int64_t t = input_ids.size(1);
  const at::Tensor ids = input_ids.to(token_embedding.device());
  at::Tensor x = at::embedding(token_embedding, ids) + position_embedding.slice(0, 0, t).unsqueeze(0);
  ClipTextOutput out;
  out.last_hidden_state = final_layer_norm_(encoder_.forward(x, /*causal=*/true, &out.penultimate));
  // The pooled token: the first end-of-text token (the legacy eos id 2 meant "highest id" instead).
  const at::Tensor eos_pos =
      config_.eos_token_id == 2 ? ids.argmax(-1) : (ids == config_.eos_token_id).to(at::kInt).argmax(-1);
  const at::Tensor flat_index = at::arange(ids.size(0), ids.options()) * t + eos_pos.to(at::kLong);
  out.pooled = out.last_hidden_state.reshape({-1, out.last_hidden_state.size(2)}).index_select(0, flat_index);
  if (with_projection_) out.text_embeds = text_projection_(out.pooled);
  return out;
}

}  // namespace gaps::sdxl
