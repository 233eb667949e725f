#include "diffusion_worker/sdxl/ip_adapter.h"

#include <algorithm>
#include <set>
#include <utility>

#include <ATen/ATen.h>
#include <c10/core/InferenceMode.h>
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"

namespace gaps::sdxl {
namespace {

// diffusers' ImageProjection always makes 4 tokens from a "proj.weight" checkpoint.
constexpr int64_t kImageTokens = 4;

// The UNet's cross-attention layers in diffusers' attn_processors order: its modules as registered
// (down_blocks, up_blocks, mid_block), where for_each_attention visits down, mid, up.
std::vector<std::pair<std::string, Attention*>> cross_attention_layers(UNet2DCondition& unet) {
  std::vector<std::pair<std::string, Attention*>> layers;
  unet.for_each_attention([&](const std::string& name, Attention& attn) {
    if (absl::EndsWith(name, ".attn2")) layers.emplace_back(name, &attn);
  });
  const auto rank = [](const std::string& name) {
    return absl::StartsWith(name, "down_blocks.") ? 0 : absl::StartsWith(name, "up_blocks.") ? 1 : 2;
  };
  std::stable_sort(layers.begin(), layers.end(),
                   [&](const auto& a, const auto& b) { return rank(a.first) < rank(b.first); });
  return layers;
}

// The layer numbers n of the file's "ip_adapter.<n>." tensors.
absl::StatusOr<std::set<int64_t>> layer_numbers(const TensorMap& weights, const std::string& source) {
  std::set<int64_t> numbers;
  for (const auto& [name, tensor] : weights) {
    if (!absl::StartsWith(name, "ip_adapter.")) continue;
    const std::string rest = name.substr(11);
    int64_t n = 0;
    if (!absl::SimpleAtoi(rest.substr(0, rest.find('.')), &n)) {
      return absl::InvalidArgumentError(absl::StrCat(source, ": tensor '", name, "' is not ip_adapter.<layer>.<name>"));
    }
    numbers.insert(n);
  }
  return numbers;
}

}  // namespace

at::Tensor ImageProjection::operator()(const at::Tensor& embeds) const {
  const at::Tensor x = image_embeds(embeds.to(image_embeds.weight.device(), image_embeds.weight.scalar_type()));
  return norm(x.reshape({embeds.size(0), num_tokens, -1}));
}

void ImagePrompt::set(const at::Tensor& tokens, const at::Tensor& scales) {
  // The buffers are made and refilled as inference tensors, inside or outside a caller's InferenceMode.
  c10::InferenceMode inference;
  Buffers& slot = buffers_[tokens.sizes().vec()];
  const at::Tensor scale_view = scales.to(tokens.options()).view({-1, 1, 1});
  if (!slot.tokens.defined()) {
    slot.tokens = tokens.clone();
    slot.scales = scale_view.clone();
  } else {
    slot.tokens.copy_(tokens);
    slot.scales.copy_(scale_view);
  }
  current_ = &slot;
  text_only_ = false;
}

const at::Tensor& ImagePrompt::tokens() const {
  static const at::Tensor kNone;
  return current_ != nullptr ? current_->tokens : kNone;
}

const at::Tensor& ImagePrompt::scales() const {
  static const at::Tensor kNone;
  return current_ != nullptr ? current_->scales : kNone;
}

at::Tensor DecoupledCrossAttention::operator()(const Attention& attn, const at::Tensor& x,
                                               const at::Tensor& context) const {
  if (prompt_->text_only()) return attn.to_out(attn.attend(attn.to_q(x), attn.to_k(context), attn.to_v(context)));
  const at::Tensor& tokens = prompt_->tokens();
  TORCH_CHECK(tokens.defined(), "IP-Adapter: the UNet ran without an image prompt (set_image_prompt)");
  TORCH_CHECK(tokens.size(0) == x.size(0), "IP-Adapter: image prompt for ", tokens.size(0), " images, UNet batch ",
              x.size(0));
  const at::Tensor q = attn.to_q(x);
  const at::Tensor text = attn.attend(q, attn.to_k(context), attn.to_v(context));
  const at::Tensor image = attn.attend(q, to_k_ip_(tokens), to_v_ip_(tokens));
  return attn.to_out(text + prompt_->scales() * image);
}

absl::StatusOr<std::unique_ptr<IpAdapter>> IpAdapter::load(const std::string& path, UNet2DCondition& unet,
                                                           at::TensorOptions options) {
  GAPS_ASSIGN_OR_RETURN(TensorMap weights, read_safetensors(path));
  return load(std::move(weights), unet, options, path);
}

absl::StatusOr<std::unique_ptr<IpAdapter>> IpAdapter::load(TensorMap weights, UNet2DCondition& unet,
                                                           at::TensorOptions options, const std::string& source) {
  for (const char* other : {"image_proj.latents", "image_proj.proj.0.weight", "image_proj.proj.3.weight",
                            "image_proj.perceiver_resampler.proj_in.weight"}) {
    if (weights.count(other)) {
      return absl::UnimplementedError(
          absl::StrCat(source, ": holds ", other,
                       ", an IP-Adapter Plus / Full Face / FaceID checkpoint; only the "
                       "plain IP-Adapter (image_proj.proj + image_proj.norm) is supported"));
    }
  }
  const auto layers = cross_attention_layers(unet);
  GAPS_ASSIGN_OR_RETURN(const std::set<int64_t> numbers, layer_numbers(weights, source));
  if (numbers.size() != layers.size()) {
    return absl::InvalidArgumentError(absl::StrCat(source, ": IP-Adapter weights for ", numbers.size(),
                                                   " cross-attention layers, the UNet has ", layers.size()));
  }
  const auto proj = weights.find("image_proj.proj.weight");
  if (proj == weights.end() || proj->second.dim() != 2) {
    return absl::InvalidArgumentError(absl::StrCat(source,
                                                   ": image_proj.proj.weight (tokens x cross_attention_dim, "
                                                   "image embedding size) is missing or not a matrix"));
  }
  const int64_t cross = unet.config().cross_attention_dim, embed_dim = proj->second.size(1);

  WeightLoader w(source, std::move(weights), options);
  auto adapter = std::unique_ptr<IpAdapter>(new IpAdapter());
  adapter->projection_ = {Linear::load(w, "image_proj.proj", embed_dim, kImageTokens * cross),
                          LayerNorm::load(w, "image_proj.norm", cross, 1e-5), kImageTokens};
  std::vector<std::shared_ptr<DecoupledCrossAttention>> processors;
  for (size_t i = 0; i < layers.size(); ++i) {
    const Attention& attn = *layers[i].second;
    const std::string prefix = absl::StrCat("ip_adapter.", 2 * i + 1, ".");
    const int64_t inner = attn.to_k.weight.size(0);
    processors.push_back(std::make_shared<DecoupledCrossAttention>(
        Linear::load(w, prefix + "to_k_ip", cross, inner, /*with_bias=*/false),
        Linear::load(w, prefix + "to_v_ip", cross, inner, /*with_bias=*/false), adapter->prompt_));
  }
  GAPS_RETURN_IF_ERROR(w.finish());
  for (size_t i = 0; i < layers.size(); ++i) layers[i].second->set_processor(processors[i]);
  adapter->num_layers_ = static_cast<int64_t>(layers.size());
  return adapter;
}

}  // namespace gaps::sdxl
