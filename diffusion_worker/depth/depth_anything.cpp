#include "diffusion_worker/depth/depth_anything.h"

#include <cmath>
#include <filesystem>
#include <utility>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/model_folder.h"

namespace gaps::depth {
namespace {

using sdxl::config_value;
using sdxl::join_name;

// The backbone transformers builds when config.json has no backbone_config (DepthAnythingConfig's
// sub-config defaults, Depth-Anything-Small's).
nlohmann::json default_backbone_config() {
  return {{"model_type", "dinov2"},
          {"image_size", 518},
          {"hidden_size", 384},
          {"num_attention_heads", 6},
          {"out_indices", {9, 10, 11, 12}},
          {"reshape_hidden_states", false}};
}

absl::Status refuse_named_backbone(const nlohmann::json& j) {
  if (j.contains("backbone") && !j["backbone"].is_null()) {
    return absl::UnimplementedError(
        absl::StrCat("Depth-Anything config: backbone ", j["backbone"].dump(),
                     " (a backbone by checkpoint name) is not supported; give backbone_config"));
  }
  GAPS_ASSIGN_OR_RETURN(const bool timm, config_value<bool>(j, "use_timm_backbone", false));
  if (timm) return absl::UnimplementedError("Depth-Anything config: use_timm_backbone is not supported");
  return absl::OkStatus();
}

absl::Status check_neck(const DepthAnythingConfig& c) {
  const size_t stages = c.backbone.out_indices.size();
  if (c.neck_hidden_sizes.size() != stages || c.reassemble_factors.size() != stages) {
    return absl::InvalidArgumentError(absl::StrCat(
        "Depth-Anything config: neck_hidden_sizes (", c.neck_hidden_sizes.size(), "), reassemble_factors (",
        c.reassemble_factors.size(), ") and the backbone's out_indices (", stages, ") must have the same length"));
  }
  for (const double factor : c.reassemble_factors) {
    const bool whole = factor >= 1 && factor == std::floor(factor);
    if (factor <= 0 || (factor > 1 && !whole)) {
      return absl::UnimplementedError(absl::StrCat("Depth-Anything config: reassemble factor ", factor,
                                                   " is not supported (a whole number, or below 1)"));
    }
  }
  for (const int64_t size : c.neck_hidden_sizes) {
    if (size <= 0) return absl::InvalidArgumentError("Depth-Anything config: neck_hidden_sizes must be positive");
  }
  const auto n = static_cast<int64_t>(stages);
  if (c.head_in_index < -n || c.head_in_index >= n) {
    return absl::InvalidArgumentError(
        absl::StrCat("Depth-Anything config: head_in_index ", c.head_in_index, " is outside the ", n, " fused maps"));
  }
  if (c.fusion_hidden_size < 2 || c.head_hidden_size <= 0) {
    return absl::InvalidArgumentError("Depth-Anything config: fusion_hidden_size >= 2 and head_hidden_size > 0 needed");
  }
  return absl::OkStatus();
}

at::Tensor relu_conv(const sdxl::Conv2d& conv, const at::Tensor& x) { return conv(at::relu(x)); }

}  // namespace

absl::StatusOr<DepthAnythingConfig> DepthAnythingConfig::from_json(const nlohmann::json& j) {
  DepthAnythingConfig c;
  GAPS_ASSIGN_OR_RETURN(const std::string model_type, config_value<std::string>(j, "model_type", "depth_anything"));
  if (model_type != "depth_anything") {
    return absl::UnimplementedError(
        absl::StrCat("model_type '", model_type, "' is not supported (only 'depth_anything')"));
  }
  GAPS_RETURN_IF_ERROR(refuse_named_backbone(j));
  const bool has_backbone = j.contains("backbone_config") && !j["backbone_config"].is_null();
  if (has_backbone && !j["backbone_config"].is_object()) {
    return absl::InvalidArgumentError("Depth-Anything config: backbone_config is not a JSON object");
  }
  GAPS_ASSIGN_OR_RETURN(c.backbone,
                        Dinov2Config::from_json(has_backbone ? j["backbone_config"] : default_backbone_config()));
  if (c.backbone.num_channels != 3) {
    return absl::UnimplementedError(absl::StrCat("Depth-Anything config: backbone_config.num_channels ",
                                                 c.backbone.num_channels, " is not supported (RGB input)"));
  }
  if (c.backbone.reshape_hidden_states) {
    return absl::UnimplementedError(
        "Depth-Anything config: backbone_config.reshape_hidden_states true is not supported (the neck takes tokens)");
  }
  if (j.contains("patch_size") && !j["patch_size"].is_number_integer()) {
    return absl::UnimplementedError(absl::StrCat("Depth-Anything config: patch_size ", j["patch_size"].dump(),
                                                 " is not supported (a single size)"));
  }
  GAPS_ASSIGN_OR_RETURN(c.patch_size, config_value<int64_t>(j, "patch_size", c.patch_size));
  GAPS_ASSIGN_OR_RETURN(c.reassemble_hidden_size,
                        config_value<int64_t>(j, "reassemble_hidden_size", c.reassemble_hidden_size));
  GAPS_ASSIGN_OR_RETURN(c.fusion_hidden_size, config_value<int64_t>(j, "fusion_hidden_size", c.fusion_hidden_size));
  GAPS_ASSIGN_OR_RETURN(c.head_in_index, config_value<int64_t>(j, "head_in_index", c.head_in_index));
  GAPS_ASSIGN_OR_RETURN(c.head_hidden_size, config_value<int64_t>(j, "head_hidden_size", c.head_hidden_size));
  GAPS_ASSIGN_OR_RETURN(c.reassemble_factors,
                        config_value<std::vector<double>>(j, "reassemble_factors", c.reassemble_factors));
  GAPS_ASSIGN_OR_RETURN(c.neck_hidden_sizes,
                        config_value<std::vector<int64_t>>(j, "neck_hidden_sizes", c.neck_hidden_sizes));
  GAPS_ASSIGN_OR_RETURN(c.max_depth, config_value<double>(j, "max_depth", c.max_depth));
  GAPS_ASSIGN_OR_RETURN(const std::string type, config_value<std::string>(j, "depth_estimation_type", "relative"));
  if (type != "relative" && type != "metric") {
    return absl::UnimplementedError(
        absl::StrCat("Depth-Anything config: depth_estimation_type '", type, "' is not supported (relative, metric)"));
  }
  c.metric = type == "metric";
  if (c.patch_size != c.backbone.patch_size) {
    return absl::UnimplementedError(absl::StrCat("Depth-Anything config: patch_size ", c.patch_size,
                                                 " differs from the backbone's ", c.backbone.patch_size));
  }
  if (c.reassemble_hidden_size != c.backbone.hidden_size) {
    return absl::InvalidArgumentError(
        absl::StrCat("Depth-Anything config: reassemble_hidden_size ", c.reassemble_hidden_size,
                     " differs from the backbone's hidden_size ", c.backbone.hidden_size));
  }
  GAPS_RETURN_IF_ERROR(check_neck(c));
  return c;
}

absl::StatusOr<DepthAnything> DepthAnything::load(const std::string& folder, at::TensorOptions options) {
  if (!std::filesystem::is_directory(folder)) {
    return absl::NotFoundError(absl::StrCat("Depth-Anything folder ", folder, " does not exist"));
  }
  const std::filesystem::path root(folder);
  GAPS_ASSIGN_OR_RETURN(const nlohmann::json config_json, sdxl::read_json_file((root / "config.json").string()));
  auto config = DepthAnythingConfig::from_json(config_json);
  if (!config.ok()) return absl::Status(config.status().code(), absl::StrCat(folder, ": ", config.status().message()));
  GAPS_ASSIGN_OR_RETURN(const nlohmann::json processor_json,
                        sdxl::read_json_file((root / "preprocessor_config.json").string()));
  auto processor = DepthProcessorConfig::from_json(processor_json);
  if (!processor.ok()) {
    return absl::Status(processor.status().code(), absl::StrCat(folder, ": ", processor.status().message()));
  }
  GAPS_ASSIGN_OR_RETURN(sdxl::TensorMap weights, sdxl::read_folder_weights(folder));
  return from_weights(*config, *processor, std::move(weights), options, folder);
}

absl::StatusOr<DepthAnything> DepthAnything::from_weights(const DepthAnythingConfig& config,
                                                          const DepthProcessorConfig& processor,
                                                          sdxl::TensorMap weights, at::TensorOptions options,
                                                          const std::string& source) {
  if (!options.has_dtype()) options = options.dtype(at::kFloat);
  sdxl::WeightLoader w(source, rename_legacy_dinov2_names(std::move(weights)), options);
  DepthAnything model = build(config, processor, w);
  GAPS_RETURN_IF_ERROR(w.finish());
  return model;
}

std::vector<sdxl::TensorSpec> DepthAnything::weight_specs(const DepthAnythingConfig& config) {
  sdxl::WeightLoader w("", {}, at::TensorOptions().device(at::kMeta));
  (void)build(config, DepthProcessorConfig{}, w);
  return w.requested();
}

DepthAnything DepthAnything::build(const DepthAnythingConfig& c, const DepthProcessorConfig& processor,
                                   sdxl::WeightLoader& w) {
  DepthAnything m(processor);
  m.config_ = c;
  m.backbone_ = Dinov2Backbone::load(c.backbone, w, "backbone");
  const int64_t fusion = c.fusion_hidden_size;
  for (size_t i = 0; i < c.neck_hidden_sizes.size(); ++i) {
    const int64_t channels = c.neck_hidden_sizes[i];
    const double factor = c.reassemble_factors[i];
    const std::string p = absl::StrCat("neck.reassemble_stage.layers.", i);
    Reassemble r;
    r.projection = sdxl::Conv2d::load(w, join_name(p, "projection"), c.reassemble_hidden_size, channels, 1);
    if (factor > 1) {
      r.factor_up = static_cast<int64_t>(factor);
      r.upsample_weight = w.take(join_name(p, "resize.weight"), {channels, channels, r.factor_up, r.factor_up});
      r.upsample_bias = w.take(join_name(p, "resize.bias"), {channels});
    } else if (factor < 1) {
      r.factor_down = static_cast<int64_t>(1.0 / factor);  // Python's int() truncation
      r.downsample = sdxl::Conv2d::load(w, join_name(p, "resize"), channels, channels, 3, r.factor_down, 1);
    }
    m.reassemble_.push_back(std::move(r));
    m.neck_convs_.push_back(sdxl::Conv2d::load(w, absl::StrCat("neck.convs.", i), channels, fusion, 3, 1, 1,
                                               /*with_bias=*/false));
  }
  for (size_t i = 0; i < c.neck_hidden_sizes.size(); ++i) {
    const std::string p = absl::StrCat("neck.fusion_stage.layers.", i);
    const auto unit = [&](const std::string& name) {
      return ResidualUnit{sdxl::Conv2d::load(w, join_name(p, name + ".convolution1"), fusion, fusion, 3),
                          sdxl::Conv2d::load(w, join_name(p, name + ".convolution2"), fusion, fusion, 3)};
    };
    // The coarsest map's layer has nothing to fuse, so its residual_layer1 goes unused, as in transformers.
    m.fusion_.push_back({unit("residual_layer1"), unit("residual_layer2"),
                         sdxl::Conv2d::load(w, join_name(p, "projection"), fusion, fusion, 1)});
  }
  m.head_conv1_ = sdxl::Conv2d::load(w, "head.conv1", fusion, fusion / 2, 3);
  m.head_conv2_ = sdxl::Conv2d::load(w, "head.conv2", fusion / 2, c.head_hidden_size, 3);
  m.head_conv3_ = sdxl::Conv2d::load(w, "head.conv3", c.head_hidden_size, 1, 1);
  return m;
}

at::Tensor DepthAnything::ResidualUnit::operator()(const at::Tensor& x) const {
  return x + relu_conv(conv2, relu_conv(conv1, x));
}

at::Tensor DepthAnything::reassemble(const Reassemble& layer, const at::Tensor& tokens, int64_t grid_height,
                                     int64_t grid_width) const {
  const at::Tensor patches = tokens.slice(1, 1);  // the CLS token is dropped (readout "ignore")
  const at::Tensor map =
      patches.reshape({patches.size(0), grid_height, grid_width, patches.size(2)}).permute({0, 3, 1, 2}).contiguous();
  const at::Tensor projected = layer.projection(map);
  if (layer.factor_up > 1) {
    return at::conv_transpose2d(projected, layer.upsample_weight, layer.upsample_bias,
                                {layer.factor_up, layer.factor_up});
  }
  return layer.factor_down > 1 ? layer.downsample(projected) : projected;
}

at::Tensor DepthAnything::fuse(const Fusion& layer, const at::Tensor& fused, const at::Tensor& feature,
                               at::IntArrayRef size) const {
  at::Tensor x = fused;
  if (feature.defined()) {
    at::Tensor skip = feature;
    if (skip.sizes() != x.sizes()) {
      skip = at::upsample_bilinear2d(skip, {x.size(2), x.size(3)}, /*align_corners=*/false);
    }
    x = x + layer.residual1(skip);
  }
  x = layer.residual2(x);
  x = at::upsample_bilinear2d(x, size, /*align_corners=*/true);
  return layer.projection(x);
}

at::Tensor DepthAnything::head(const at::Tensor& features, int64_t grid_height, int64_t grid_width) const {
  at::Tensor x = head_conv1_(features);
  x = at::upsample_bilinear2d(x, {grid_height * config_.patch_size, grid_width * config_.patch_size},
                              /*align_corners=*/true);
  x = head_conv3_(at::relu(head_conv2_(x)));
  x = config_.metric ? at::sigmoid(x) : at::relu(x);
  return (x * config_.max_depth).squeeze(1);
}

std::vector<at::Tensor> DepthAnything::backbone_features(const at::Tensor& pixel_values) const {
  return backbone_.forward(pixel_values.to(head_conv1_.weight.device()));
}

at::Tensor DepthAnything::forward(const at::Tensor& pixel_values) const {
  const int64_t grid_height = pixel_values.size(2) / config_.patch_size;
  const int64_t grid_width = pixel_values.size(3) / config_.patch_size;
  const std::vector<at::Tensor> stages = backbone_features(pixel_values);
  std::vector<at::Tensor> maps;
  for (size_t i = 0; i < stages.size(); ++i) {
    maps.push_back(neck_convs_[i](reassemble(reassemble_[i], stages[i], grid_height, grid_width)));
  }
  // Coarse to fine: each fused map is upsampled to the next finer map's size (the finest one doubles).
  std::vector<at::Tensor> fused;
  for (size_t k = 0; k < maps.size(); ++k) {
    const at::Tensor& map = maps[maps.size() - 1 - k];
    std::vector<int64_t> size;
    if (k + 1 < maps.size()) {
      const at::Tensor& finer = maps[maps.size() - 2 - k];
      size = {finer.size(2), finer.size(3)};
    } else {
      size = {2 * map.size(2), 2 * map.size(3)};
    }
    fused.push_back(k == 0 ? fuse(fusion_[k], map, at::Tensor(), size) : fuse(fusion_[k], fused.back(), map, size));
  }
  const auto n = static_cast<int64_t>(fused.size());
  return head(fused[(config_.head_in_index + n) % n], grid_height, grid_width);
}

absl::StatusOr<at::Tensor> DepthAnything::estimate_depth(const at::Tensor& image) const {
  GAPS_ASSIGN_OR_RETURN(const at::Tensor pixel_values, processor_.preprocess(image));
  if (pixel_values.size(2) < config_.patch_size || pixel_values.size(3) < config_.patch_size) {
    return absl::InvalidArgumentError(absl::StrCat("image of ", image.size(0), " x ", image.size(1),
                                                   " pixels gives no full ", config_.patch_size, "-pixel patch"));
  }
  const at::Tensor depth = forward(pixel_values);
  return processor_.postprocess(depth[0], image.size(0), image.size(1)).cpu();
}

}  // namespace gaps::depth
