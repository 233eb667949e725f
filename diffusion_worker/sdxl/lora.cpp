#include "diffusion_worker/sdxl/lora.h"

#include <algorithm>
#include <cmath>
#include <map>

#include <ATen/ATen.h>
#include <ATen/CPUGeneratorImpl.h>
#include <c10/core/InferenceMode.h>
#include <nlohmann/json.hpp>
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/status_macros.h"

namespace gaps::sdxl {
namespace {

constexpr char kUnetPrefix[] = "unet.";
constexpr char kDownSuffix[] = ".lora_A.weight";
constexpr char kUpSuffix[] = ".lora_B.weight";
constexpr char kMetadataKey[] = "lora_adapter_metadata";
const char* const kProjections[] = {"to_q", "to_k", "to_v", "to_out.0"};

// Every attention projection of unet, self- and cross-attention, by its diffusers name (valid while unet is
// not moved).
std::map<std::string, Linear*> projection_layers(UNet2DCondition& unet) {
  std::map<std::string, Linear*> layers;
  unet.for_each_attention([&](const std::string& name, Attention& a) {
    Linear* projections[] = {&a.to_q, &a.to_k, &a.to_v, &a.to_out};
    for (int i = 0; i < 4; ++i) layers[absl::StrCat(name, ".", kProjections[i])] = projections[i];
  });
  return layers;
}

// The paper (sec. lora) adapts the cross-attention blocks, diffusers' attn2; attn1 is self-attention.
bool in_cross_attention(const std::string& module) { return absl::StrContains(module, ".attn2."); }

// The adapter ranks and alphas of a LoRA file's metadata (diffusers' PEFT LoraConfig, keys "unet.*").
struct AlphaRule {
  bool from_metadata = false;
  double alpha = 0;
  std::map<std::string, double> pattern;  // module name (or a suffix of it) -> alpha
  double alpha_for(const std::string& module, int64_t rank) const {
    if (!from_metadata) return static_cast<double>(rank);
    for (const auto& [key, value] : pattern) {
      if (module == key || absl::EndsWith(module, absl::StrCat(".", key))) return value;
    }
    return alpha;
  }
};

absl::StatusOr<AlphaRule> alpha_rule(const SafetensorsMetadata& metadata, const std::string& source) {
  AlphaRule rule;
  const auto it = metadata.find(kMetadataKey);
  if (it == metadata.end()) return rule;
  const auto fail = [&](const std::string& what) {
    return absl::InvalidArgumentError(absl::StrCat("LoRA file ", source, ": ", kMetadataKey, " ", what));
  };
  nlohmann::json config;
  try {
    config = nlohmann::json::parse(it->second);
  } catch (const std::exception& e) {
    return fail(absl::StrCat("is not valid JSON: ", e.what()));
  }
  if (!config.is_object()) return fail("is not a JSON object");
  for (const char* unsupported : {"unet.use_dora", "unet.use_rslora", "unet.lora_bias"}) {
    if (config.contains(unsupported) && config[unsupported].is_boolean() && config[unsupported].get<bool>()) {
      return fail(absl::StrCat("sets ", unsupported, ", which is not supported"));
    }
  }
  if (!config.contains("unet.lora_alpha")) return rule;
  if (!config["unet.lora_alpha"].is_number()) return fail("has a non-numeric unet.lora_alpha");
  rule.from_metadata = true;
  rule.alpha = config["unet.lora_alpha"].get<double>();
  if (config.contains("unet.alpha_pattern") && config["unet.alpha_pattern"].is_object()) {
    for (const auto& [key, value] : config["unet.alpha_pattern"].items()) {
      if (!value.is_number()) return fail(absl::StrCat("has a non-numeric alpha for ", key));
      rule.pattern[key] = value.get<double>();
    }
  }
  return rule;
}

// Why a key cannot be a UNet LoRA tensor of the supported format, or empty when it may be one.
std::string refusal(const std::string& key) {
  if (absl::StartsWith(key, "text_encoder")) return "adapts a text encoder (only UNet LoRA is supported)";
  if (absl::StartsWith(key, "lora_unet_") || absl::StartsWith(key, "lora_te")) {
    return "is kohya-style (lora_unet_*/lora_down/lora_up; only diffusers' PEFT format is supported)";
  }
  if (absl::StrContains(key, "lora_magnitude_vector")) return "is a DoRA magnitude (DoRA is not supported)";
  if (!absl::StartsWith(key, kUnetPrefix)) return "does not start with 'unet.'";
  if (!absl::EndsWith(key, kDownSuffix) && !absl::EndsWith(key, kUpSuffix)) {
    return "is neither lora_A.weight nor lora_B.weight";
  }
  return "";
}

std::string module_of(const std::string& key) {
  const size_t suffix = absl::EndsWith(key, kDownSuffix) ? sizeof(kDownSuffix) - 1 : sizeof(kUpSuffix) - 1;
  return key.substr(sizeof(kUnetPrefix) - 1, key.size() - (sizeof(kUnetPrefix) - 1) - suffix);
}

at::TensorOptions adapter_options(const Linear& layer) {
  return at::TensorOptions().dtype(at::kFloat).device(layer.weight.device());
}

std::string shape_text(at::IntArrayRef shape) { return absl::StrCat("[", absl::StrJoin(shape, ", "), "]"); }

}  // namespace

absl::StatusOr<UNetLora> UNetLora::create(UNet2DCondition& unet, const LoraConfig& config, uint64_t seed) {
  if (config.rank <= 0)
    return absl::InvalidArgumentError(absl::StrCat("LoRA rank must be positive, got ", config.rank));
  if (config.targets.empty()) return absl::InvalidArgumentError("LoRA needs at least one target projection");
  for (const auto& target : config.targets) {
    if (std::find(std::begin(kProjections), std::end(kProjections), target) == std::end(kProjections)) {
      return absl::InvalidArgumentError(
          absl::StrCat("LoRA target '", target, "' is not an attention projection (to_q, to_k, to_v, to_out.0)"));
    }
  }
  at::Generator generator = at::make_generator<at::CPUGeneratorImpl>(seed);
  UNetLora lora;
  for (const auto& [module, layer] : projection_layers(unet)) {
    const bool targeted = std::any_of(config.targets.begin(), config.targets.end(), [&](const std::string& t) {
      return absl::EndsWith(module, absl::StrCat(".", t));
    });
    if (!targeted || !in_cross_attention(module)) continue;
    const int64_t out = layer->weight.size(0), in = layer->weight.size(1);
    const double bound = 1.0 / std::sqrt(static_cast<double>(in));
    const at::TensorOptions options = adapter_options(*layer);
    Adapter a;
    a.module = module;
    a.down = at::empty({config.rank, in}, at::kFloat).uniform_(-bound, bound, generator).to(options);
    a.up = at::zeros({out, config.rank}, options);
    a.alpha = config.alpha;
    lora.adapters_.push_back(std::move(a));
  }
  if (lora.adapters_.empty()) return absl::InvalidArgumentError("the UNet has no cross-attention layers to adapt");
  lora.attach_to(unet);
  return lora;
}

absl::StatusOr<UNetLora> UNetLora::load(const std::string& path, UNet2DCondition& unet) {
  auto tensors = read_safetensors(path);
  if (!tensors.ok()) return tensors.status();
  auto metadata = read_safetensors_metadata(path);
  if (!metadata.ok()) return metadata.status();
  return from_tensors(*tensors, *metadata, unet, path);
}

absl::StatusOr<UNetLora> UNetLora::from_tensors(const TensorMap& tensors, const SafetensorsMetadata& metadata,
                                                UNet2DCondition& unet, const std::string& source) {
  auto rule = alpha_rule(metadata, source);
  if (!rule.ok()) return rule.status();
  const auto layers = projection_layers(unet);
  std::vector<std::string> problems;
  std::map<std::string, std::pair<at::Tensor, at::Tensor>> pairs;  // module -> (down, up)
  for (const auto& [key, tensor] : tensors) {
    const std::string why = refusal(key);
    if (!why.empty()) {
      problems.push_back(absl::StrCat("tensor '", key, "' ", why));
      continue;
    }
    const std::string module = module_of(key);
    if (layers.count(module) == 0) {
      problems.push_back(absl::StrCat("tensor '", key, "': the UNet has no attention projection '", module, "'"));
      continue;
    }
    (absl::EndsWith(key, kDownSuffix) ? pairs[module].first : pairs[module].second) = tensor;
  }
  UNetLora lora;
  for (const auto& [module, pair] : pairs) {
    const auto& [down, up] = pair;
    const std::string prefix = absl::StrCat(kUnetPrefix, module);
    if (!down.defined() || !up.defined()) {
      problems.push_back(absl::StrCat("missing '", prefix, down.defined() ? kUpSuffix : kDownSuffix, "'"));
      continue;
    }
    const Linear& layer = *layers.at(module);
    const int64_t out = layer.weight.size(0), in = layer.weight.size(1);
    const int64_t rank = down.dim() == 2 ? down.size(0) : -1;
    if (rank <= 0 || down.size(1) != in) {
      problems.push_back(absl::StrCat("mis-shaped '", prefix, kDownSuffix, "': ", shape_text(down.sizes()),
                                      ", expected [rank, ", in, "]"));
      continue;
    }
    if (up.dim() != 2 || up.size(0) != out || up.size(1) != rank) {
      problems.push_back(absl::StrCat("mis-shaped '", prefix, kUpSuffix, "': ", shape_text(up.sizes()), ", expected [",
                                      out, ", ", rank, "]"));
      continue;
    }
    const at::TensorOptions options = adapter_options(layer);
    lora.adapters_.push_back({module, down.to(options, /*non_blocking=*/false, /*copy=*/true),
                              up.to(options, /*non_blocking=*/false, /*copy=*/true), rule->alpha_for(module, rank)});
  }
  if (!problems.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("LoRA file ", source, ": ", absl::StrJoin(problems, "; ")));
  }
  if (lora.adapters_.empty())
    return absl::InvalidArgumentError(absl::StrCat("LoRA file ", source, " holds no adapters"));
  lora.attach_to(unet);
  return lora;
}

DecodedSafetensors UNetLora::as_safetensors() const {
  DecodedSafetensors out;
  nlohmann::json targets = nlohmann::json::array(), rank_pattern = nlohmann::json::object(),
                 alpha_pattern = nlohmann::json::object();
  const int64_t rank = adapters_.empty() ? 0 : adapters_.front().down.size(0);
  const double alpha = adapters_.empty() ? 0 : adapters_.front().alpha;
  for (const auto& a : adapters_) {
    out.tensors[absl::StrCat(kUnetPrefix, a.module, kDownSuffix)] = a.down.detach().to(at::kCPU, at::kFloat);
    out.tensors[absl::StrCat(kUnetPrefix, a.module, kUpSuffix)] = a.up.detach().to(at::kCPU, at::kFloat);
    targets.push_back(a.module);
    if (a.down.size(0) != rank) rank_pattern[a.module] = a.down.size(0);
    if (a.alpha != alpha) alpha_pattern[a.module] = a.alpha;
  }
  const nlohmann::json config = {{"unet.r", rank},
                                 {"unet.lora_alpha", alpha},
                                 {"unet.target_modules", targets},
                                 {"unet.rank_pattern", rank_pattern},
                                 {"unet.alpha_pattern", alpha_pattern},
                                 {"unet.init_lora_weights", true}};
  out.metadata = {{"format", "pt"}, {kMetadataKey, config.dump(2)}};
  return out;
}

absl::Status UNetLora::save(const std::string& path) const {
  const DecodedSafetensors file = as_safetensors();
  return write_safetensors(path, file.tensors, file.metadata);
}

absl::StatusOr<std::string> UNetLora::to_bytes() const {
  const DecodedSafetensors file = as_safetensors();
  return encode_safetensors(file.tensors, file.metadata);
}

absl::StatusOr<UNetLora> UNetLora::from_bytes(std::string bytes, UNet2DCondition& unet, const std::string& source) {
  GAPS_ASSIGN_OR_RETURN(const DecodedSafetensors file, decode_safetensors(std::move(bytes), source));
  return from_tensors(file.tensors, file.metadata, unet, source);
}

std::vector<at::Tensor> UNetLora::parameters() const {
  std::vector<at::Tensor> params;
  for (const auto& a : adapters_) {
    params.push_back(a.down);
    params.push_back(a.up);
  }
  return params;
}

void UNetLora::attach_to(UNet2DCondition& unet) const {
  const auto layers = projection_layers(unet);
  for (const auto& a : adapters_) {
    Linear& layer = *layers.at(a.module);
    layer.lora_down = a.down;
    layer.lora_up = a.up;
    layer.lora_scale = a.scale();
  }
}

namespace {

// A host copy of `weight`, page-locked when it lives on a GPU (its copies back then run at the bus's speed).
at::Tensor host_copy(const at::Tensor& weight) {
  at::Tensor copy = at::empty(weight.sizes(), weight.options().device(at::kCPU).pinned_memory(weight.is_cuda()));
  copy.copy_(weight);
  return copy;
}

}  // namespace

void UNetLora::merge_into(UNet2DCondition& unet, BaseCopies* base_copies) {
  if (merged()) return;
  // In place, so that anything holding the weight tensors (a captured CUDA graph) sees the merged values.
  c10::InferenceMode inference;
  const auto layers = projection_layers(unet);
  for (const auto& a : adapters_) {
    Linear& layer = *layers.at(a.module);
    at::Tensor base;
    if (base_copies != nullptr) {
      at::Tensor& kept = (*base_copies)[a.module];
      if (!kept.defined()) kept = host_copy(layer.weight);
      base = kept;
    } else {
      base = host_copy(layer.weight);
    }
    base_weights_[a.module] = base;
    layer.weight.add_(at::matmul(a.up, a.down).to(layer.weight.scalar_type()), a.scale());
    layer.lora_down = at::Tensor();
    layer.lora_up = at::Tensor();
  }
}

void UNetLora::unmerge_from(UNet2DCondition& unet) {
  c10::InferenceMode inference;
  const auto layers = projection_layers(unet);
  // Synchronous: the next user of the weights may run on another stream (a graph's replay).
  for (const auto& [module, weight] : base_weights_) layers.at(module)->weight.copy_(weight);
  base_weights_.clear();
}

void UNetLora::detach_from(UNet2DCondition& unet) const {
  const auto layers = projection_layers(unet);
  for (const auto& a : adapters_) {
    Linear& layer = *layers.at(a.module);
    layer.lora_down = at::Tensor();
    layer.lora_up = at::Tensor();
  }
}

}  // namespace gaps::sdxl
