#pragma once
// transformers CLIPTextModel / CLIPTextModelWithProjection, the two text encoders of SDXL. SDXL conditions
// on the penultimate layer's hidden states of both and on the second one's projected pooled output.
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include <nlohmann/json.hpp>
#include "absl/status/statusor.h"
#include "diffusion_worker/sdxl/clip_encoder.h"
#include "diffusion_worker/sdxl/layers.h"

namespace gaps::sdxl {

struct ClipTextConfig : ClipEncoderConfig {
  int64_t vocab_size = 49408, max_position_embeddings = 77, projection_dim = 0, eos_token_id = 2;
  static absl::StatusOr<ClipTextConfig> from_json(const nlohmann::json& config);
};

struct ClipTextOutput {
  at::Tensor penultimate;        // B x T x D, hidden states before the last layer (hidden_states[-2])
  at::Tensor last_hidden_state;  // B x T x D, after the final layer norm
  at::Tensor pooled;             // B x D, last_hidden_state at the end-of-text token
  at::Tensor text_embeds;        // B x P, text_projection(pooled); undefined without a projection
};

class ClipTextEncoder {
 public:
  // with_projection: CLIPTextModelWithProjection (takes text_projection.weight). Checkpoints with or
  // without the "text_model." prefix are accepted.
  static absl::StatusOr<ClipTextEncoder> load(const ClipTextConfig& config, bool with_projection, TensorMap weights,
                                              at::TensorOptions options, const std::string& source);
  static std::vector<TensorSpec> weight_specs(const ClipTextConfig& config, bool with_projection);
  // input_ids: B x T int64 (T <= max_position_embeddings).
  ClipTextOutput forward(const at::Tensor& input_ids) const;
  const ClipTextConfig& config() const { return config_; }

 private:
  static absl::StatusOr<ClipTextEncoder> build(const ClipTextConfig& config, bool with_projection, WeightLoader& w,
                                               const std::string& source);

  ClipTextConfig config_;
  at::Tensor token_embedding, position_embedding;
  ClipEncoder encoder_;
  LayerNorm final_layer_norm_;
  bool with_projection_ = false;
  Linear text_projection_;
};

}  // namespace gaps::sdxl
