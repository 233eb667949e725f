#pragma once
// diffusers UNet2DConditionModel as SDXL configures it: DownBlock2D / CrossAttnDownBlock2D,
// UNetMidBlock2DCrossAttn, CrossAttnUpBlock2D / UpBlock2D, Transformer2DModel with BasicTransformerBlocks
// (self-attention, cross-attention, GEGLU feed-forward), sinusoidal time embedding and the "text_time"
// added conditioning (pooled text embedding + original size / crop / target size features).
//
// Extension points for the conditioning that comes later: ControlNet residuals enter through
// UNetInputs (added to the skip connections and the mid block's output), and every attention layer can be
// given an AttentionProcessor (IP-Adapter's decoupled cross-attention) or have its projections wrapped
// (LoRA) through for_each_attention().
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include <nlohmann/json.hpp>
#include "absl/status/statusor.h"
#include "diffusion_worker/sdxl/layers.h"

namespace gaps::sdxl {

// Every default is the one diffusers' UNet2DConditionModel takes for a key its config.json leaves out
// (Stable Diffusion 1.x's layout); from_json keeps a member's value for an absent key, so these are the
// only defaults. Per-block lists given as one number hold that number for every block.
struct UNetConfig {
  static constexpr int64_t kAttentionHeads = 8;     // per block (attention_head_dim when num_attention_heads is absent)
  static constexpr int64_t kTransformerLayers = 1;  // per block

  int64_t in_channels = 4, out_channels = 4, layers_per_block = 2, norm_num_groups = 32, cross_attention_dim = 1280;
  std::vector<int64_t> block_out_channels = {320, 640, 1280, 1280};
  std::vector<std::string> down_block_types = {"CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D",
                                               "DownBlock2D"};
  std::vector<std::string> up_block_types = {"UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D",
                                             "CrossAttnUpBlock2D"};
  std::vector<int64_t> num_attention_heads = std::vector<int64_t>(4, kAttentionHeads);
  std::vector<int64_t> transformer_layers_per_block = std::vector<int64_t>(4, kTransformerLayers);
  // Per up block; the reversed transformer_layers_per_block when absent.
  std::vector<int64_t> reverse_transformer_layers_per_block = std::vector<int64_t>(4, kTransformerLayers);
  double norm_eps = 1e-5;
  bool flip_sin_to_cos = true, use_linear_projection = false;
  double freq_shift = 0;
  std::string addition_embed_type;  // "text_time" or empty (none)
  // Both only with "text_time", which needs them (diffusers has no default); 0 = absent.
  int64_t addition_time_embed_dim = 0, projection_class_embeddings_input_dim = 0;
  // with_up_blocks = false reads the input half only (a ControlNet's config has no up blocks).
  static absl::StatusOr<UNetConfig> from_json(const nlohmann::json& config, bool with_up_blocks = true);
};

struct UNetInputs {
  at::Tensor sample;                 // B x C x h x w latents
  at::Tensor timestep;               // scalar or B
  at::Tensor encoder_hidden_states;  // B x T x cross_attention_dim
  at::Tensor text_embeds;            // B x P pooled text embedding ("text_time")
  at::Tensor time_ids;               // B x 6: original (h, w), crop (top, left), target (h, w)
  // ControlNet: one residual per skip connection (conv_in, then each resnet/attention and downsampler
  // output, in order) and one for the mid block; empty = none.
  std::vector<at::Tensor> down_block_residuals;
  at::Tensor mid_block_residual;
};

// The UNet's input half: embedding, conv_in, down blocks and mid block (what a ControlNet copies).
struct UNetEncoding {
  at::Tensor emb;                 // time embedding plus the added (text_time) embedding
  std::vector<at::Tensor> skips;  // the skip connections, in UNetInputs::down_block_residuals order
  at::Tensor mid;                 // the mid block's output
};

class UNet2DCondition {
 public:
  static absl::StatusOr<UNet2DCondition> load(const UNetConfig& config, TensorMap weights, at::TensorOptions options,
                                              const std::string& source);
  // Every tensor the config needs (name, shape), without loading anything.
  static std::vector<TensorSpec> weight_specs(const UNetConfig& config);
  // Only the input half (encode() works, forward() does not), its tensors taken from w under the UNet's
  // names; the caller runs w.finish(). A ControlNet stores this half under the same names.
  static absl::StatusOr<UNet2DCondition> load_input_half(const UNetConfig& config, WeightLoader& w,
                                                         const std::string& source);
  // The predicted noise (or v), B x out_channels x h x w.
  at::Tensor forward(const UNetInputs& inputs) const;
  // The input half on inputs' sample, timestep, context and added conditioning (residuals unused);
  // conv_in_addition (when defined) is added to conv_in's output before the down blocks (ControlNet's
  // conditioning embedding).
  UNetEncoding encode(const UNetInputs& inputs, const at::Tensor& conv_in_addition = {}) const;

  const UNetConfig& config() const { return config_; }
  // Visits every transformer attention layer with its diffusers name (e.g.
  // "down_blocks.1.attentions.0.transformer_blocks.0.attn2").
  void for_each_attention(const std::function<void(const std::string&, Attention&)>& visit);

 private:
  struct TransformerBlock {
    LayerNorm norm1, norm2, norm3;
    Attention attn1, attn2;
    // GEGLU: ff.net.0.proj's two halves as two projections, whose outputs are contiguous: GELU and the product
    // then run as vectorised kernels, where the halves of one output (strided views) did not (~12 % of an
    // img2img call's GPU time on an H200 at 504 x 384, batch 8).
    Linear ff_hidden, ff_gate, ff_out;
  };
  struct Transformer2D {
    std::string name;
    GroupNorm norm;
    Linear proj_in_linear, proj_out_linear;
    Conv2d proj_in_conv, proj_out_conv;
    std::vector<TransformerBlock> blocks;
  };
  struct Block {
    std::vector<ResnetBlock> resnets;
    std::vector<Transformer2D> attentions;  // empty, or one per resnet
    std::optional<Downsample> down;
    std::optional<Upsample> up;
  };

  static absl::StatusOr<UNet2DCondition> build(const UNetConfig& config, WeightLoader& w, const std::string& source,
                                               bool with_up_blocks = true);
  Transformer2D load_transformer(WeightLoader& w, const std::string& prefix, int64_t channels, int64_t heads,
                                 int64_t layers) const;
  at::Tensor transformer_forward(const Transformer2D& t, const at::Tensor& x, const at::Tensor& context) const;
  at::Tensor block_forward(const TransformerBlock& b, const at::Tensor& x, const at::Tensor& context) const;
  at::Tensor embedding(const UNetInputs& in, int64_t batch) const;

  UNetConfig config_;
  Conv2d conv_in_, conv_out_;
  TimestepEmbedding time_embedding_, add_embedding_;
  std::vector<Block> down_, up_;
  ResnetBlock mid_resnet_in_, mid_resnet_out_;
  Transformer2D mid_attention_;
  GroupNorm norm_out_;
};

}  // namespace gaps::sdxl
