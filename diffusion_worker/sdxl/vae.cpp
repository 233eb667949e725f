#include "diffusion_worker/sdxl/vae.h"

#include <utility>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/model_folder.h"

namespace gaps::sdxl {
namespace {
constexpr double kVaeEps = 1e-6;  // diffusers' encoder/decoder blocks use 1e-6 throughout
}

absl::StatusOr<VaeConfig> VaeConfig::from_json(const nlohmann::json& j) {
  VaeConfig c;
  GAPS_ASSIGN_OR_RETURN(c.in_channels, config_value<int64_t>(j, "in_channels", 3));
  GAPS_ASSIGN_OR_RETURN(c.out_channels, config_value<int64_t>(j, "out_channels", 3));
  GAPS_ASSIGN_OR_RETURN(c.latent_channels, config_value<int64_t>(j, "latent_channels", 4));
  GAPS_ASSIGN_OR_RETURN(c.layers_per_block, config_value<int64_t>(j, "layers_per_block", 1));
  GAPS_ASSIGN_OR_RETURN(c.norm_num_groups, config_value<int64_t>(j, "norm_num_groups", 32));
  GAPS_ASSIGN_OR_RETURN(c.block_out_channels, config_value<std::vector<int64_t>>(j, "block_out_channels", {64}));
  GAPS_ASSIGN_OR_RETURN(c.scaling_factor, config_value<double>(j, "scaling_factor", 0.18215));
  GAPS_ASSIGN_OR_RETURN(c.use_quant_conv, config_value<bool>(j, "use_quant_conv", true));
  GAPS_ASSIGN_OR_RETURN(c.use_post_quant_conv, config_value<bool>(j, "use_post_quant_conv", true));
  GAPS_ASSIGN_OR_RETURN(c.mid_block_add_attention, config_value<bool>(j, "mid_block_add_attention", true));
  GAPS_ASSIGN_OR_RETURN(auto down, config_value<std::vector<std::string>>(j, "down_block_types", {}));
  GAPS_ASSIGN_OR_RETURN(auto up, config_value<std::vector<std::string>>(j, "up_block_types", {}));
  for (const auto& t : down) {
    if (t != "DownEncoderBlock2D")
      return absl::UnimplementedError(absl::StrCat("VAE down block type ", t, " is not supported"));
  }
  for (const auto& t : up) {
    if (t != "UpDecoderBlock2D")
      return absl::UnimplementedError(absl::StrCat("VAE up block type ", t, " is not supported"));
  }
  if (c.block_out_channels.empty() || down.size() != c.block_out_channels.size() || up.size() != down.size()) {
    return absl::InvalidArgumentError("VAE config: block_out_channels, down_block_types and up_block_types disagree");
  }
  if (j.contains("latents_mean") && !j["latents_mean"].is_null()) {
    return absl::UnimplementedError("VAE config: latents_mean/latents_std normalisation is not supported");
  }
  if (j.contains("shift_factor") && !j["shift_factor"].is_null()) {
    return absl::UnimplementedError("VAE config: shift_factor is not supported");
  }
  return c;
}

VaeAttention VaeAttention::load(WeightLoader& w, const std::string& prefix, int64_t channels, int64_t groups) {
  return {GroupNorm::load(w, join_name(prefix, "group_norm"), groups, channels, kVaeEps),
          Attention::load(w, prefix, channels, channels, 1, channels, /*qkv_bias=*/true)};
}

at::Tensor VaeAttention::operator()(const at::Tensor& x) const {
  const int64_t b = x.size(0), c = x.size(1), h = x.size(2), wd = x.size(3);
  // Pixels as tokens: a view for channels-last activations, a copy for NCHW ones.
  at::Tensor tokens = group_norm(x).permute({0, 2, 3, 1}).reshape({b, h * wd, c});
  at::Tensor out = attn(tokens, tokens);
  return out.reshape({b, h, wd, c}).permute({0, 3, 1, 2}).contiguous(group_norm.memory_format()) + x;
}

VaeMidBlock VaeMidBlock::load(WeightLoader& w, const std::string& prefix, int64_t channels, int64_t groups,
                              bool with_attention) {
  VaeMidBlock m;
  m.resnet_in = ResnetBlock::load(w, join_name(prefix, "resnets.0"), channels, channels, 0, groups, kVaeEps);
  if (with_attention) m.attention = VaeAttention::load(w, join_name(prefix, "attentions.0"), channels, groups);
  m.resnet_out = ResnetBlock::load(w, join_name(prefix, "resnets.1"), channels, channels, 0, groups, kVaeEps);
  return m;
}

at::Tensor VaeMidBlock::operator()(const at::Tensor& x) const {
  at::Tensor h = resnet_in(x, {});
  if (attention) h = (*attention)(h);
  return resnet_out(h, {});
}

absl::StatusOr<AutoencoderKL> AutoencoderKL::load(const VaeConfig& c, TensorMap weights, at::TensorOptions options,
                                                  const std::string& source) {
  WeightLoader w(source, std::move(weights), options);
  AutoencoderKL vae = build(c, w);
  GAPS_RETURN_IF_ERROR(w.finish());
  return vae;
}

std::vector<TensorSpec> AutoencoderKL::weight_specs(const VaeConfig& c) {
  WeightLoader w("", {}, at::TensorOptions().device(at::kMeta));
  build(c, w);
  return w.requested();
}

AutoencoderKL AutoencoderKL::build(const VaeConfig& c, WeightLoader& w) {
  AutoencoderKL vae;
  vae.config_ = c;
  const auto& ch = c.block_out_channels;
  const int64_t g = c.norm_num_groups, n = static_cast<int64_t>(ch.size()), L = c.latent_channels;

  vae.enc_conv_in = Conv2d::load(w, "encoder.conv_in", c.in_channels, ch[0], 3);
  int64_t in = ch[0];
  for (int64_t i = 0; i < n; ++i) {
    const std::string p = absl::StrCat("encoder.down_blocks.", i);
    std::vector<ResnetBlock> resnets;
    for (int64_t r = 0; r < c.layers_per_block; ++r) {
      resnets.push_back(
          ResnetBlock::load(w, absl::StrCat(p, ".resnets.", r), r == 0 ? in : ch[i], ch[i], 0, g, kVaeEps));
    }
    vae.enc_resnets.push_back(std::move(resnets));
    vae.enc_down.push_back(
        i + 1 < n ? std::optional<Downsample>(Downsample::load(w, p + ".downsamplers.0", ch[i], true)) : std::nullopt);
    in = ch[i];
  }
  vae.enc_mid = VaeMidBlock::load(w, "encoder.mid_block", ch.back(), g, c.mid_block_add_attention);
  vae.enc_norm_out = GroupNorm::load(w, "encoder.conv_norm_out", g, ch.back(), kVaeEps);
  vae.enc_conv_out = Conv2d::load(w, "encoder.conv_out", ch.back(), 2 * L, 3);
  if (c.use_quant_conv) vae.quant_conv = Conv2d::load(w, "quant_conv", 2 * L, 2 * L, 1);
  if (c.use_post_quant_conv) vae.post_quant_conv = Conv2d::load(w, "post_quant_conv", L, L, 1);

  vae.dec_conv_in = Conv2d::load(w, "decoder.conv_in", L, ch.back(), 3);
  vae.dec_mid = VaeMidBlock::load(w, "decoder.mid_block", ch.back(), g, c.mid_block_add_attention);
  int64_t prev = ch.back();
  for (int64_t i = 0; i < n; ++i) {
    const int64_t out = ch[n - 1 - i];
    const std::string p = absl::StrCat("decoder.up_blocks.", i);
    std::vector<ResnetBlock> resnets;
    for (int64_t r = 0; r < c.layers_per_block + 1; ++r) {
      resnets.push_back(ResnetBlock::load(w, absl::StrCat(p, ".resnets.", r), r == 0 ? prev : out, out, 0, g, kVaeEps));
    }
    vae.dec_resnets.push_back(std::move(resnets));
    vae.dec_up.push_back(i + 1 < n ? std::optional<Upsample>(Upsample::load(w, p + ".upsamplers.0", out))
                                   : std::nullopt);
    prev = out;
  }
  vae.dec_norm_out = GroupNorm::load(w, "decoder.conv_norm_out", g, ch[0], kVaeEps);
  vae.dec_conv_out = Conv2d::load(w, "decoder.conv_out", ch[0], c.out_channels, 3);
  return vae;
}

at::Tensor AutoencoderKL::encode_moments(const at::Tensor& images) const {
  at::Tensor h = enc_conv_in(images);
  for (size_t i = 0; i < enc_resnets.size(); ++i) {
    for (const auto& r : enc_resnets[i]) h = r(h, {});
    if (enc_down[i]) h = (*enc_down[i])(h);
  }
  h = (*enc_mid)(h);
  h = enc_conv_out(enc_norm_out.with_silu(h));
  return config_.use_quant_conv ? quant_conv(h) : h;
}

at::Tensor AutoencoderKL::sample_latents(const at::Tensor& moments, std::optional<at::Generator> generator) const {
  const auto parts = moments.chunk(2, 1);
  const at::Tensor std = at::exp(0.5 * at::clamp(parts[1], -30.0, 20.0));
  // Drawn on the CPU in float32 like diffusers' randn_tensor, so a seed gives the same latents anywhere.
  const at::Tensor noise =
      at::randn(parts[0].sizes(), generator, at::TensorOptions().dtype(at::kFloat)).to(moments.options());
  return parts[0] + std * noise;
}

at::Tensor AutoencoderKL::decode(const at::Tensor& latents) const {
  at::Tensor h = dec_conv_in(config_.use_post_quant_conv ? post_quant_conv(latents) : latents);
  h = (*dec_mid)(h);
  for (size_t i = 0; i < dec_resnets.size(); ++i) {
    for (const auto& r : dec_resnets[i]) h = r(h, {});
    if (dec_up[i]) h = (*dec_up[i])(h);
  }
  return dec_conv_out(dec_norm_out.with_silu(h));
}

}  // namespace gaps::sdxl
