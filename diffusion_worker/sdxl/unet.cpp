#include "diffusion_worker/sdxl/unet.h"

#include <utility>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/model_folder.h"

namespace gaps::sdxl {
namespace {

constexpr double kTransformerNormEps = 1e-6;  // Transformer2DModel's group norm

// A per-block list in the config may also be given as one number for all blocks.
absl::StatusOr<std::vector<int64_t>> per_block(const nlohmann::json& j, const std::string& key, size_t blocks,
                                               std::vector<int64_t> fallback) {
  if (!j.contains(key) || j[key].is_null()) return fallback;
  if (j[key].is_number_integer()) return std::vector<int64_t>(blocks, j[key].get<int64_t>());
  GAPS_ASSIGN_OR_RETURN(auto list, config_value<std::vector<int64_t>>(j, key, {}));
  if (list.size() != blocks) {
    return absl::InvalidArgumentError(
        absl::StrCat("UNet config: ", key, " has ", list.size(), " entries for ", blocks, " blocks"));
  }
  return list;
}

bool has_cross_attention(const std::string& block_type) { return block_type.rfind("CrossAttn", 0) == 0; }

// Options of diffusers' UNet2DConditionModel this implementation does not have: each must be absent, null or
// at its default value (the value that SD 1.x/2.x and SDXL checkpoints use), else loading fails naming it.
absl::Status reject_unsupported_options(const nlohmann::json& j) {
  const std::vector<std::pair<std::string, nlohmann::json>> defaults = {{"act_fn", "silu"},
                                                                        {"center_input_sample", false},
                                                                        {"dual_cross_attention", false},
                                                                        {"mid_block_scale_factor", 1},
                                                                        {"downsample_padding", 1},
                                                                        {"attention_type", "default"},
                                                                        {"resnet_skip_time_act", false},
                                                                        {"resnet_out_scale_factor", 1},
                                                                        {"conv_in_kernel", 3},
                                                                        {"conv_out_kernel", 3},
                                                                        {"class_embeddings_concat", false},
                                                                        {"mid_block_only_cross_attention", false}};
  for (const auto& [key, value] : defaults) {
    if (j.contains(key) && !j[key].is_null() && j[key] != value) {
      return absl::UnimplementedError(
          absl::StrCat("UNet config: ", key, " = ", j[key].dump(), " is not supported (only ", value.dump(), ")"));
    }
  }
  for (const char* key :
       {"num_class_embeds", "cross_attention_norm", "time_embedding_act_fn", "timestep_post_act", "encoder_hid_dim"}) {
    if (j.contains(key) && !j[key].is_null())
      return absl::UnimplementedError(absl::StrCat("UNet config: ", key, " is not supported"));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<UNetConfig> UNetConfig::from_json(const nlohmann::json& j, bool with_up_blocks) {
  UNetConfig c;
  GAPS_RETURN_IF_ERROR(reject_unsupported_options(j));
  GAPS_ASSIGN_OR_RETURN(c.in_channels, config_value(j, "in_channels", c.in_channels));
  GAPS_ASSIGN_OR_RETURN(c.out_channels, config_value(j, "out_channels", c.out_channels));
  GAPS_ASSIGN_OR_RETURN(c.layers_per_block, config_value(j, "layers_per_block", c.layers_per_block));
  GAPS_ASSIGN_OR_RETURN(c.norm_num_groups, config_value(j, "norm_num_groups", c.norm_num_groups));
  GAPS_ASSIGN_OR_RETURN(c.norm_eps, config_value(j, "norm_eps", c.norm_eps));
  if (j.contains("cross_attention_dim") && !j["cross_attention_dim"].is_null() &&
      !j["cross_attention_dim"].is_number_integer()) {
    return absl::UnimplementedError("UNet config: per-block cross_attention_dim is not supported");
  }
  GAPS_ASSIGN_OR_RETURN(c.cross_attention_dim, config_value(j, "cross_attention_dim", c.cross_attention_dim));
  GAPS_ASSIGN_OR_RETURN(c.block_out_channels, config_value(j, "block_out_channels", c.block_out_channels));
  GAPS_ASSIGN_OR_RETURN(c.down_block_types, config_value(j, "down_block_types", c.down_block_types));
  GAPS_ASSIGN_OR_RETURN(c.up_block_types, config_value(j, "up_block_types", c.up_block_types));
  GAPS_ASSIGN_OR_RETURN(c.flip_sin_to_cos, config_value(j, "flip_sin_to_cos", c.flip_sin_to_cos));
  GAPS_ASSIGN_OR_RETURN(c.freq_shift, config_value(j, "freq_shift", c.freq_shift));
  GAPS_ASSIGN_OR_RETURN(c.use_linear_projection, config_value(j, "use_linear_projection", c.use_linear_projection));
  GAPS_ASSIGN_OR_RETURN(c.addition_embed_type, config_value(j, "addition_embed_type", c.addition_embed_type));
  GAPS_ASSIGN_OR_RETURN(c.addition_time_embed_dim,
                        config_value(j, "addition_time_embed_dim", c.addition_time_embed_dim));
  GAPS_ASSIGN_OR_RETURN(
      c.projection_class_embeddings_input_dim,
      config_value(j, "projection_class_embeddings_input_dim", c.projection_class_embeddings_input_dim));
  const size_t n = c.block_out_channels.size();
  if (!with_up_blocks) c.up_block_types.clear();
  if (n == 0 || c.down_block_types.size() != n || (with_up_blocks && c.up_block_types.size() != n)) {
    return absl::InvalidArgumentError("UNet config: block_out_channels, down_block_types and up_block_types disagree");
  }
  for (const auto& t : c.down_block_types) {
    if (t != "DownBlock2D" && t != "CrossAttnDownBlock2D")
      return absl::UnimplementedError("UNet down block type " + t + " is not supported");
  }
  for (const auto& t : c.up_block_types) {
    if (t != "UpBlock2D" && t != "CrossAttnUpBlock2D")
      return absl::UnimplementedError("UNet up block type " + t + " is not supported");
  }
  // diffusers reads attention_head_dim as the number of heads when num_attention_heads is absent.
  const std::string heads_key = j.contains("num_attention_heads") && !j["num_attention_heads"].is_null()
                                    ? "num_attention_heads"
                                    : "attention_head_dim";
  GAPS_ASSIGN_OR_RETURN(c.num_attention_heads, per_block(j, heads_key, n, std::vector<int64_t>(n, kAttentionHeads)));
  GAPS_ASSIGN_OR_RETURN(c.transformer_layers_per_block,
                        per_block(j, "transformer_layers_per_block", n, std::vector<int64_t>(n, kTransformerLayers)));
  std::vector<int64_t> reversed(c.transformer_layers_per_block.rbegin(), c.transformer_layers_per_block.rend());
  GAPS_ASSIGN_OR_RETURN(c.reverse_transformer_layers_per_block,
                        per_block(j, "reverse_transformer_layers_per_block", n, reversed));
  GAPS_ASSIGN_OR_RETURN(auto mid_type, config_value<std::string>(j, "mid_block_type", "UNetMidBlock2DCrossAttn"));
  if (mid_type != "UNetMidBlock2DCrossAttn")
    return absl::UnimplementedError("UNet mid block type " + mid_type + " is not supported");
  if (!c.addition_embed_type.empty() && c.addition_embed_type != "text_time") {
    return absl::UnimplementedError("UNet addition_embed_type " + c.addition_embed_type + " is not supported");
  }
  if (c.addition_embed_type == "text_time" &&
      (c.addition_time_embed_dim < 1 || c.projection_class_embeddings_input_dim < 1)) {
    return absl::InvalidArgumentError(
        "UNet config: addition_embed_type text_time needs addition_time_embed_dim and "
        "projection_class_embeddings_input_dim");
  }
  for (const char* key : {"class_embed_type", "encoder_hid_dim_type", "time_cond_proj_dim", "time_embedding_dim"}) {
    if (j.contains(key) && !j[key].is_null())
      return absl::UnimplementedError(absl::StrCat("UNet config: ", key, " is not supported"));
  }
  GAPS_ASSIGN_OR_RETURN(auto scale_shift, config_value<std::string>(j, "resnet_time_scale_shift", "default"));
  GAPS_ASSIGN_OR_RETURN(auto time_embedding_type, config_value<std::string>(j, "time_embedding_type", "positional"));
  GAPS_ASSIGN_OR_RETURN(auto upcast, config_value<bool>(j, "upcast_attention", false));
  GAPS_ASSIGN_OR_RETURN(auto only_cross, config_value<bool>(j, "only_cross_attention", false));
  if (scale_shift != "default" || time_embedding_type != "positional" || upcast || only_cross) {
    return absl::UnimplementedError(
        "UNet config: only resnet_time_scale_shift 'default', positional time embedding, no attention upcast and "
        "no only_cross_attention are supported");
  }
  return c;
}

UNet2DCondition::Transformer2D UNet2DCondition::load_transformer(WeightLoader& w, const std::string& prefix,
                                                                 int64_t channels, int64_t heads,
                                                                 int64_t layers) const {
  const UNetConfig& c = config_;
  Transformer2D t;
  t.name = prefix;
  t.norm = GroupNorm::load(w, join_name(prefix, "norm"), c.norm_num_groups, channels, kTransformerNormEps);
  if (c.use_linear_projection) {
    t.proj_in_linear = Linear::load(w, join_name(prefix, "proj_in"), channels, channels);
    t.proj_out_linear = Linear::load(w, join_name(prefix, "proj_out"), channels, channels);
  } else {
    t.proj_in_conv = Conv2d::load(w, join_name(prefix, "proj_in"), channels, channels, 1);
    t.proj_out_conv = Conv2d::load(w, join_name(prefix, "proj_out"), channels, channels, 1);
  }
  const int64_t dim_head = channels / heads, inner = 4 * channels;
  for (int64_t i = 0; i < layers; ++i) {
    const std::string p = absl::StrCat(prefix, ".transformer_blocks.", i);
    const Linear geglu = Linear::load(w, p + ".ff.net.0.proj", channels, 2 * inner);
    t.blocks.push_back({LayerNorm::load(w, p + ".norm1", channels, 1e-5),
                        LayerNorm::load(w, p + ".norm2", channels, 1e-5),
                        LayerNorm::load(w, p + ".norm3", channels, 1e-5),
                        Attention::load(w, p + ".attn1", channels, channels, heads, dim_head, false),
                        Attention::load(w, p + ".attn2", channels, c.cross_attention_dim, heads, dim_head, false),
                        output_rows(geglu, 0, inner), output_rows(geglu, inner, 2 * inner),
                        Linear::load(w, p + ".ff.net.2", inner, channels)});
  }
  return t;
}

absl::StatusOr<UNet2DCondition> UNet2DCondition::load(const UNetConfig& c, TensorMap weights, at::TensorOptions options,
                                                      const std::string& source) {
  WeightLoader w(source, std::move(weights), options);
  GAPS_ASSIGN_OR_RETURN(UNet2DCondition u, build(c, w, source));
  GAPS_RETURN_IF_ERROR(w.finish());
  return u;
}

absl::StatusOr<UNet2DCondition> UNet2DCondition::load_input_half(const UNetConfig& c, WeightLoader& w,
                                                                 const std::string& source) {
  return build(c, w, source, /*with_up_blocks=*/false);
}

std::vector<TensorSpec> UNet2DCondition::weight_specs(const UNetConfig& c) {
  WeightLoader w("", {}, at::TensorOptions().device(at::kMeta));
  (void)build(c, w, "");
  return w.requested();
}

absl::StatusOr<UNet2DCondition> UNet2DCondition::build(const UNetConfig& c, WeightLoader& w, const std::string& source,
                                                       bool with_up_blocks) {
  UNet2DCondition u;
  u.config_ = c;
  const auto& ch = c.block_out_channels;
  const int64_t n = static_cast<int64_t>(ch.size()), g = c.norm_num_groups, temb = 4 * ch[0];
  for (int64_t i = 0; i < n; ++i) {
    if (ch[i] % c.num_attention_heads[i] != 0) {
      return absl::InvalidArgumentError(absl::StrCat(source, ": block ", i, " channels not divisible by its heads"));
    }
  }
  u.conv_in_ = Conv2d::load(w, "conv_in", c.in_channels, ch[0], 3);
  u.time_embedding_ = TimestepEmbedding::load(w, "time_embedding", ch[0], temb);
  if (c.addition_embed_type == "text_time") {
    u.add_embedding_ = TimestepEmbedding::load(w, "add_embedding", c.projection_class_embeddings_input_dim, temb);
  }
  int64_t in = ch[0];
  for (int64_t i = 0; i < n; ++i) {
    const std::string p = absl::StrCat("down_blocks.", i);
    Block b;
    for (int64_t r = 0; r < c.layers_per_block; ++r) {
      b.resnets.push_back(
          ResnetBlock::load(w, absl::StrCat(p, ".resnets.", r), r == 0 ? in : ch[i], ch[i], temb, g, c.norm_eps));
      if (has_cross_attention(c.down_block_types[i])) {
        b.attentions.push_back(u.load_transformer(w, absl::StrCat(p, ".attentions.", r), ch[i],
                                                  c.num_attention_heads[i], c.transformer_layers_per_block[i]));
      }
    }
    if (i + 1 < n) b.down = Downsample::load(w, p + ".downsamplers.0", ch[i], false);
    u.down_.push_back(std::move(b));
    in = ch[i];
  }
  u.mid_resnet_in_ = ResnetBlock::load(w, "mid_block.resnets.0", ch.back(), ch.back(), temb, g, c.norm_eps);
  u.mid_attention_ = u.load_transformer(w, "mid_block.attentions.0", ch.back(), c.num_attention_heads.back(),
                                        c.transformer_layers_per_block.back());
  u.mid_resnet_out_ = ResnetBlock::load(w, "mid_block.resnets.1", ch.back(), ch.back(), temb, g, c.norm_eps);
  if (!with_up_blocks) return u;
  int64_t prev = ch.back();
  for (int64_t i = 0; i < n; ++i) {
    const int64_t out = ch[n - 1 - i], skip_in = ch[std::max<int64_t>(n - 2 - i, 0)];
    const std::string p = absl::StrCat("up_blocks.", i);
    Block b;
    for (int64_t r = 0; r < c.layers_per_block + 1; ++r) {
      const int64_t skip = r == c.layers_per_block ? skip_in : out;
      const int64_t res_in = (r == 0 ? prev : out) + skip;
      b.resnets.push_back(ResnetBlock::load(w, absl::StrCat(p, ".resnets.", r), res_in, out, temb, g, c.norm_eps));
      if (has_cross_attention(c.up_block_types[i])) {
        b.attentions.push_back(u.load_transformer(w, absl::StrCat(p, ".attentions.", r), out,
                                                  c.num_attention_heads[n - 1 - i],
                                                  c.reverse_transformer_layers_per_block[i]));
      }
    }
    if (i + 1 < n) b.up = Upsample::load(w, p + ".upsamplers.0", out);
    u.up_.push_back(std::move(b));
    prev = out;
  }
  u.norm_out_ = GroupNorm::load(w, "conv_norm_out", g, ch[0], c.norm_eps);
  u.conv_out_ = Conv2d::load(w, "conv_out", ch[0], c.out_channels, 3);
  return u;
}

at::Tensor UNet2DCondition::block_forward(const TransformerBlock& b, const at::Tensor& x,
                                          const at::Tensor& context) const {
  const at::Tensor n1 = b.norm1(x);
  at::Tensor h = x + b.attn1(n1, n1);
  h = h + b.attn2(b.norm2(h), context);
  const at::Tensor n3 = b.norm3(h);
  return h + b.ff_out(b.ff_hidden(n3) * at::gelu(b.ff_gate(n3)));
}

at::Tensor UNet2DCondition::transformer_forward(const Transformer2D& t, const at::Tensor& x,
                                                const at::Tensor& context) const {
  const int64_t b = x.size(0), c = x.size(1), h = x.size(2), w = x.size(3);
  at::Tensor y = t.norm(x);
  if (!config_.use_linear_projection) y = t.proj_in_conv(y);
  y = y.permute({0, 2, 3, 1}).reshape({b, h * w, c});
  if (config_.use_linear_projection) y = t.proj_in_linear(y);
  for (const auto& block : t.blocks) y = block_forward(block, y, context);
  if (config_.use_linear_projection) y = t.proj_out_linear(y);
  y = y.reshape({b, h, w, c}).permute({0, 3, 1, 2}).contiguous(t.norm.memory_format());
  if (!config_.use_linear_projection) y = t.proj_out_conv(y);
  return y + x;
}

at::Tensor UNet2DCondition::embedding(const UNetInputs& in, int64_t batch) const {
  at::Tensor t = in.timestep.to(in.sample.device());
  if (t.dim() == 0) t = t.unsqueeze(0);
  t = t.expand({batch});
  const at::Tensor features =
      timestep_features(t, config_.block_out_channels[0], config_.flip_sin_to_cos, config_.freq_shift);
  at::Tensor emb = time_embedding_(features.to(in.sample.scalar_type()));
  if (config_.addition_embed_type == "text_time") {
    const at::Tensor time_ids = in.time_ids.to(in.sample.device()).reshape({-1});
    const at::Tensor time_features =
        timestep_features(time_ids, config_.addition_time_embed_dim, config_.flip_sin_to_cos, config_.freq_shift)
            .reshape({batch, -1});
    const at::Tensor add = at::cat({in.text_embeds.to(in.sample.device(), at::kFloat), time_features}, -1);
    emb = emb + add_embedding_(add.to(in.sample.scalar_type()));
  }
  return emb;
}

UNetEncoding UNet2DCondition::encode(const UNetInputs& in, const at::Tensor& conv_in_addition) const {
  UNetEncoding out;
  out.emb = embedding(in, in.sample.size(0));
  const at::Tensor& context = in.encoder_hidden_states;
  at::Tensor h = conv_in_(in.sample);
  if (conv_in_addition.defined()) h = h + conv_in_addition;
  out.skips.push_back(h);
  for (const Block& b : down_) {
    for (size_t r = 0; r < b.resnets.size(); ++r) {
      h = b.resnets[r](h, out.emb);
      if (!b.attentions.empty()) h = transformer_forward(b.attentions[r], h, context);
      out.skips.push_back(h);
    }
    if (b.down) {
      h = (*b.down)(h);
      out.skips.push_back(h);
    }
  }
  out.mid = mid_resnet_out_(transformer_forward(mid_attention_, mid_resnet_in_(h, out.emb), context), out.emb);
  return out;
}

at::Tensor UNet2DCondition::forward(const UNetInputs& in) const {
  TORCH_CHECK(!up_.empty(), "UNet: forward() on a model loaded as its input half only");
  UNetEncoding enc = encode(in);
  std::vector<at::Tensor>& skips = enc.skips;
  if (!in.down_block_residuals.empty()) {
    TORCH_CHECK(in.down_block_residuals.size() == skips.size(), "UNet: ", in.down_block_residuals.size(),
                " down-block residuals given for ", skips.size(), " skip connections");
    for (size_t i = 0; i < skips.size(); ++i) skips[i] = skips[i] + in.down_block_residuals[i];
  }
  at::Tensor h = enc.mid;
  if (in.mid_block_residual.defined()) h = h + in.mid_block_residual;
  for (const Block& b : up_) {
    for (size_t r = 0; r < b.resnets.size(); ++r) {
      h = b.resnets[r](at::cat({h, skips.back()}, 1), enc.emb);
      skips.pop_back();
      if (!b.attentions.empty()) h = transformer_forward(b.attentions[r], h, in.encoder_hidden_states);
    }
    // Upsample to the next skip's size, which also covers latents not divisible by 2^blocks.
    if (b.up) h = (*b.up)(h, {skips.back().size(2), skips.back().size(3)});
  }
  return conv_out_(norm_out_.with_silu(h));
}

void UNet2DCondition::for_each_attention(const std::function<void(const std::string&, Attention&)>& visit) {
  const auto visit_transformer = [&](Transformer2D& t) {
    for (size_t i = 0; i < t.blocks.size(); ++i) {
      visit(absl::StrCat(t.name, ".transformer_blocks.", i, ".attn1"), t.blocks[i].attn1);
      visit(absl::StrCat(t.name, ".transformer_blocks.", i, ".attn2"), t.blocks[i].attn2);
    }
  };
  for (auto& b : down_)
    for (auto& t : b.attentions) visit_transformer(t);
  visit_transformer(mid_attention_);
  for (auto& b : up_)
    for (auto& t : b.attentions) visit_transformer(t);
}

}  // namespace gaps::sdxl
