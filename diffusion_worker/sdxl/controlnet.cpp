#include "diffusion_worker/sdxl/controlnet.h"

#include <filesystem>
#include <utility>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/model_folder.h"

namespace gaps::sdxl {

absl::StatusOr<ControlNetConfig> ControlNetConfig::from_json(const nlohmann::json& j) {
  ControlNetConfig c;
  GAPS_ASSIGN_OR_RETURN(c.unet, UNetConfig::from_json(j, /*with_up_blocks=*/false));
  GAPS_ASSIGN_OR_RETURN(c.conditioning_channels, config_value<int64_t>(j, "conditioning_channels", 3));
  GAPS_ASSIGN_OR_RETURN(
      c.conditioning_embedding_out_channels,
      config_value<std::vector<int64_t>>(j, "conditioning_embedding_out_channels", {16, 32, 96, 256}));
  if (c.conditioning_embedding_out_channels.empty() || c.conditioning_channels < 1) {
    return absl::InvalidArgumentError("ControlNet config: conditioning_embedding_out_channels must not be empty");
  }
  GAPS_ASSIGN_OR_RETURN(auto order, config_value<std::string>(j, "controlnet_conditioning_channel_order", "rgb"));
  if (order != "rgb" && order != "bgr") {
    return absl::InvalidArgumentError("ControlNet config: controlnet_conditioning_channel_order '" + order +
                                      "' is not rgb or bgr");
  }
  c.bgr = order == "bgr";
  GAPS_ASSIGN_OR_RETURN(auto global_pool, config_value<bool>(j, "global_pool_conditions", false));
  if (global_pool) {
    return absl::UnimplementedError(
        "ControlNet config: global_pool_conditions (shuffle-style ControlNets) is not supported");
  }
  GAPS_ASSIGN_OR_RETURN(auto act, config_value<std::string>(j, "act_fn", "silu"));
  if (act != "silu") return absl::UnimplementedError("ControlNet config: act_fn '" + act + "' is not supported");
  if (j.contains("num_class_embeds") && !j["num_class_embeds"].is_null()) {
    return absl::UnimplementedError("ControlNet config: num_class_embeds (class embeddings) is not supported");
  }
  return c;
}

absl::StatusOr<ControlNet> ControlNet::load(const ControlNetConfig& c, TensorMap weights, at::TensorOptions options,
                                            const std::string& source) {
  WeightLoader w(source, std::move(weights), options);
  ControlNet net;
  net.config_ = c;
  GAPS_ASSIGN_OR_RETURN(net.trunk_, UNet2DCondition::load_input_half(c.unet, w, source));
  const auto& levels = c.conditioning_embedding_out_channels;
  const auto& ch = c.unet.block_out_channels;
  net.cond_in_ = Conv2d::load(w, "controlnet_cond_embedding.conv_in", c.conditioning_channels, levels[0], 3);
  for (size_t i = 0; i + 1 < levels.size(); ++i) {
    const std::string p = "controlnet_cond_embedding.blocks.";
    net.cond_blocks_.push_back(Conv2d::load(w, absl::StrCat(p, 2 * i), levels[i], levels[i], 3));
    net.cond_blocks_.push_back(Conv2d::load(w, absl::StrCat(p, 2 * i + 1), levels[i], levels[i + 1], 3, /*stride=*/2));
  }
  net.cond_out_ = Conv2d::load(w, "controlnet_cond_embedding.conv_out", levels.back(), ch[0], 3);
  // One zero convolution per skip connection: conv_in's, then per block its layers' and its downsampler's.
  std::vector<int64_t> skip_channels{ch[0]};
  for (size_t i = 0; i < ch.size(); ++i) {
    for (int64_t r = 0; r < c.unet.layers_per_block; ++r) skip_channels.push_back(ch[i]);
    if (i + 1 < ch.size()) skip_channels.push_back(ch[i]);
  }
  for (size_t i = 0; i < skip_channels.size(); ++i) {
    net.zero_convs_.push_back(
        Conv2d::load(w, absl::StrCat("controlnet_down_blocks.", i), skip_channels[i], skip_channels[i], 1));
  }
  net.zero_conv_mid_ = Conv2d::load(w, "controlnet_mid_block", ch.back(), ch.back(), 1);
  GAPS_RETURN_IF_ERROR(w.finish());
  return net;
}

absl::StatusOr<ControlNet> ControlNet::load_folder(const std::string& dir, at::TensorOptions options,
                                                   const std::string& variant) {
  GAPS_ASSIGN_OR_RETURN(nlohmann::json json, read_json_file((std::filesystem::path(dir) / "config.json").string()));
  const std::string cls = json.value("_class_name", "");
  if (cls != "ControlNetModel") {
    return absl::InvalidArgumentError(absl::StrCat(dir, "/config.json describes '", cls, "', not a ControlNetModel"));
  }
  auto config = ControlNetConfig::from_json(json);
  if (!config.ok()) return absl::Status(config.status().code(), absl::StrCat(dir, ": ", config.status().message()));
  GAPS_ASSIGN_OR_RETURN(TensorMap weights, read_folder_weights(dir, variant));
  return load(*config, std::move(weights), options, dir);
}

absl::Status ControlNet::check_compatible(const UNetConfig& u) const {
  const UNetConfig& c = config_.unet;
  std::vector<std::string> diffs;
  const auto differ = [&](bool different, const char* what) {
    if (different) diffs.push_back(what);
  };
  differ(c.in_channels != u.in_channels, "in_channels");
  differ(c.block_out_channels != u.block_out_channels, "block_out_channels");
  differ(c.layers_per_block != u.layers_per_block, "layers_per_block");
  differ(c.cross_attention_dim != u.cross_attention_dim, "cross_attention_dim");
  differ(c.addition_embed_type != u.addition_embed_type, "addition_embed_type");
  differ(c.addition_time_embed_dim != u.addition_time_embed_dim, "addition_time_embed_dim");
  differ(c.projection_class_embeddings_input_dim != u.projection_class_embeddings_input_dim,
         "projection_class_embeddings_input_dim");
  if (diffs.empty()) return absl::OkStatus();
  return absl::InvalidArgumentError(
      absl::StrCat("the ControlNet does not fit the UNet: its ", absl::StrJoin(diffs, ", "), " differ"));
}

ControlNetResiduals ControlNet::forward(const UNetInputs& in, const at::Tensor& image, const at::Tensor& scale) const {
  const int64_t f = config_.downscale();
  TORCH_CHECK(image.dim() == 4 && image.size(0) == in.sample.size(0) &&
                  image.size(1) == config_.conditioning_channels && image.size(2) == in.sample.size(2) * f &&
                  image.size(3) == in.sample.size(3) * f,
              "ControlNet: conditioning image ", image.sizes(), " does not fit latents ", in.sample.sizes(), " (needs ",
              config_.conditioning_channels, " channels at ", f, "x the latent size)");
  at::Tensor e = at::silu(cond_in_(config_.bgr ? image.flip({1}) : image));
  for (const Conv2d& conv : cond_blocks_) e = at::silu(conv(e));
  const UNetEncoding enc = trunk_->encode(in, cond_out_(e));
  const at::Tensor s = scale.to(enc.mid.device(), enc.mid.scalar_type()).reshape({-1, 1, 1, 1});
  ControlNetResiduals out;
  for (size_t i = 0; i < enc.skips.size(); ++i) out.down.push_back(zero_convs_[i](enc.skips[i]) * s);
  out.mid = zero_conv_mid_(enc.mid) * s;
  return out;
}

}  // namespace gaps::sdxl
