#pragma once
// diffusers AutoencoderKL (the SDXL VAE): encoder to the latent distribution's moments, decoder back to
// images in [-1, 1]; latents are scaled by the config's scaling_factor at the pipeline's boundary.
#include <optional>
#include <string>
#include <vector>

#include <ATen/Tensor.h>
#include <nlohmann/json.hpp>
#include "absl/status/statusor.h"
#include "diffusion_worker/sdxl/layers.h"

namespace gaps::sdxl {

struct VaeConfig {
  int64_t in_channels = 3, out_channels = 3, latent_channels = 4, layers_per_block = 2, norm_num_groups = 32;
  std::vector<int64_t> block_out_channels;
  double scaling_factor = 0.18215;
  bool use_quant_conv = true, use_post_quant_conv = true, mid_block_add_attention = true;
  static absl::StatusOr<VaeConfig> from_json(const nlohmann::json& config);
};

// The VAE's attention (single head over all pixels, group norm in front, residual around it).
struct VaeAttention {
  GroupNorm group_norm;
  Attention attn;
  static VaeAttention load(WeightLoader& w, const std::string& prefix, int64_t channels, int64_t groups);
  at::Tensor operator()(const at::Tensor& x) const;
};

struct VaeMidBlock {
  ResnetBlock resnet_in, resnet_out;
  std::optional<VaeAttention> attention;
  static VaeMidBlock load(WeightLoader& w, const std::string& prefix, int64_t channels, int64_t groups,
                          bool with_attention);
  at::Tensor operator()(const at::Tensor& x) const;
};

class AutoencoderKL {
 public:
  // Builds from the config and takes every tensor of weights; mismatches are one error naming them.
  static absl::StatusOr<AutoencoderKL> load(const VaeConfig& config, TensorMap weights, at::TensorOptions options,
                                            const std::string& source);

  static std::vector<TensorSpec> weight_specs(const VaeConfig& config);

  // images B x 3 x H x W in [-1, 1] -> moments B x 2L x H/f x W/f (mean, then log-variance).
  at::Tensor encode_moments(const at::Tensor& images) const;
  // A draw from the latent distribution (mean + std * N(0, 1) from generator), unscaled.
  at::Tensor sample_latents(const at::Tensor& moments, std::optional<at::Generator> generator) const;
  // unscaled latents -> images in [-1, 1] (not clamped).
  at::Tensor decode(const at::Tensor& latents) const;

  const VaeConfig& config() const { return config_; }
  at::ScalarType dtype() const { return enc_conv_in.weight.scalar_type(); }
  // Spatial down-sampling factor of the latents (2^(blocks - 1)).
  int64_t scale_factor() const { return int64_t{1} << (config_.block_out_channels.size() - 1); }

 private:
  static AutoencoderKL build(const VaeConfig& config, WeightLoader& w);

  VaeConfig config_;
  Conv2d enc_conv_in, enc_conv_out, quant_conv, post_quant_conv, dec_conv_in, dec_conv_out;
  std::vector<std::vector<ResnetBlock>> enc_resnets, dec_resnets;
  std::vector<std::optional<Downsample>> enc_down;
  std::vector<std::optional<Upsample>> dec_up;
  std::optional<VaeMidBlock> enc_mid, dec_mid;
  GroupNorm enc_norm_out, dec_norm_out;
};

}  // namespace gaps::sdxl
