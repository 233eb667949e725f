#include "diffusion_worker/depth/depth_processor.h"

#include <cmath>
#include <string>
#include <vector>

#include <ATen/ATen.h>
#include "absl/strings/str_cat.h"
#include "common/status_macros.h"
#include "diffusion_worker/sdxl/model_folder.h"

namespace gaps::depth {
namespace {

using sdxl::config_value;

constexpr int kBicubic = 3;  // PIL.Image.Resampling.BICUBIC, the code the processor's `resample` stores

// image_mean / image_std: three values, or one for every channel.
absl::StatusOr<std::array<float, 3>> per_channel(const nlohmann::json& config, const std::string& key,
                                                 const std::array<float, 3>& fallback) {
  if (!config.contains(key) || config[key].is_null()) return fallback;
  const nlohmann::json& value = config[key];
  if (value.is_number()) {
    const float v = value.get<float>();
    return std::array<float, 3>{v, v, v};
  }
  if (value.is_array() && value.size() == 3 && value[0].is_number() && value[1].is_number() && value[2].is_number()) {
    return std::array<float, 3>{value[0].get<float>(), value[1].get<float>(), value[2].get<float>()};
  }
  return absl::InvalidArgumentError(
      absl::StrCat("preprocessor config: ", key, " ", value.dump(), " is not one value or three"));
}

absl::Status refuse_if_set(const nlohmann::json& config, const std::string& key, const std::string& why) {
  GAPS_ASSIGN_OR_RETURN(const bool set, config_value<bool>(config, key, false));
  if (set) return absl::UnimplementedError(absl::StrCat("preprocessor config: ", key, " is not supported (", why, ")"));
  return absl::OkStatus();
}

// DPT's constrain_to_multiple_of without bounds: Python's round() rounds halves to even, as nearbyint
// does in the default rounding mode.
int64_t nearest_multiple(double value, int64_t multiple) {
  return static_cast<int64_t>(std::nearbyint(value / static_cast<double>(multiple))) * multiple;
}

}  // namespace

absl::StatusOr<DepthProcessorConfig> DepthProcessorConfig::from_json(const nlohmann::json& j) {
  DepthProcessorConfig c;
  GAPS_ASSIGN_OR_RETURN(const std::string type,
                        config_value<std::string>(j, "image_processor_type", "DPTImageProcessor"));
  if (type != "DPTImageProcessor" && type != "DPTImageProcessorFast") {
    return absl::UnimplementedError(
        absl::StrCat("preprocessor config: image_processor_type '", type, "' is not supported (DPTImageProcessor)"));
  }
  GAPS_ASSIGN_OR_RETURN(c.do_resize, config_value<bool>(j, "do_resize", c.do_resize));
  GAPS_ASSIGN_OR_RETURN(c.do_rescale, config_value<bool>(j, "do_rescale", c.do_rescale));
  GAPS_ASSIGN_OR_RETURN(c.do_normalize, config_value<bool>(j, "do_normalize", c.do_normalize));
  GAPS_ASSIGN_OR_RETURN(c.keep_aspect_ratio, config_value<bool>(j, "keep_aspect_ratio", c.keep_aspect_ratio));
  GAPS_ASSIGN_OR_RETURN(c.ensure_multiple_of, config_value<int64_t>(j, "ensure_multiple_of", c.ensure_multiple_of));
  GAPS_ASSIGN_OR_RETURN(c.rescale_factor, config_value<double>(j, "rescale_factor", c.rescale_factor));
  GAPS_ASSIGN_OR_RETURN(c.image_mean, per_channel(j, "image_mean", c.image_mean));
  GAPS_ASSIGN_OR_RETURN(c.image_std, per_channel(j, "image_std", c.image_std));
  if (j.contains("size") && !j["size"].is_null()) {
    const nlohmann::json& size = j["size"];
    if (!size.is_object() || !size.contains("height") || !size.contains("width") || size.size() != 2) {
      return absl::UnimplementedError(
          absl::StrCat("preprocessor config: size ", size.dump(), " is not supported (only {height, width})"));
    }
    GAPS_ASSIGN_OR_RETURN(c.height, config_value<int64_t>(size, "height", c.height));
    GAPS_ASSIGN_OR_RETURN(c.width, config_value<int64_t>(size, "width", c.width));
  }
  GAPS_ASSIGN_OR_RETURN(const int resample, config_value<int>(j, "resample", kBicubic));
  if (resample != kBicubic) {
    return absl::UnimplementedError(
        absl::StrCat("preprocessor config: resample ", resample, " is not supported (only 3, bicubic)"));
  }
  GAPS_RETURN_IF_ERROR(refuse_if_set(j, "do_pad", "inputs are resized to the model's multiple instead"));
  GAPS_RETURN_IF_ERROR(refuse_if_set(j, "do_center_crop", "the depth must cover the whole image"));
  if (c.height <= 0 || c.width <= 0 || c.ensure_multiple_of <= 0 || c.rescale_factor <= 0) {
    return absl::InvalidArgumentError(
        "preprocessor config: size, ensure_multiple_of and rescale_factor must be positive");
  }
  for (const float s : c.image_std) {
    if (!(s > 0)) return absl::InvalidArgumentError("preprocessor config: image_std must be positive");
  }
  return c;
}

std::pair<int64_t, int64_t> DepthProcessor::input_size(int64_t height, int64_t width) const {
  if (!config_.do_resize) return {height, width};
  double scale_height = static_cast<double>(config_.height) / static_cast<double>(height);
  double scale_width = static_cast<double>(config_.width) / static_cast<double>(width);
  if (config_.keep_aspect_ratio) {
    // The side whose scale is closer to one decides, so the image is scaled as little as possible.
    if (std::abs(1 - scale_width) < std::abs(1 - scale_height)) {
      scale_height = scale_width;
    } else {
      scale_width = scale_height;
    }
  }
  return {nearest_multiple(scale_height * static_cast<double>(height), config_.ensure_multiple_of),
          nearest_multiple(scale_width * static_cast<double>(width), config_.ensure_multiple_of)};
}

absl::StatusOr<at::Tensor> DepthProcessor::preprocess(const at::Tensor& image) const {
  if (image.dim() != 3 || image.size(2) != 3 || image.size(0) < 1 || image.size(1) < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("depth input must be an H x W x 3 image, got ", image.dim(), " dimensions"));
  }
  if (image.scalar_type() != at::kByte && !at::isFloatingType(image.scalar_type())) {
    return absl::InvalidArgumentError("depth input must be uint8 or floating point in [0, 1]");
  }
  const at::Tensor bytes = image.scalar_type() == at::kByte
                               ? image.cpu()
                               : image.cpu().to(at::kFloat).clamp(0, 1).mul(255).round().to(at::kByte);
  const auto [height, width] = input_size(image.size(0), image.size(1));
  if (height <= 0 || width <= 0) {
    return absl::InvalidArgumentError(absl::StrCat("image of ", image.size(0), " x ", image.size(1),
                                                   " pixels is too small for the depth model's input"));
  }
  at::Tensor x = bytes.permute({2, 0, 1}).unsqueeze(0);  // 1 x 3 x H x W viewing the H x W x 3 pixels
  if (height != image.size(0) || width != image.size(1)) {
    // The same kernel as torchvision's resize of a uint8 tensor (antialiased bicubic, in 8 bits).
    x = at::_upsample_bicubic2d_aa(x, {height, width}, /*align_corners=*/false);
  }
  const auto channel_tensor = [](const std::array<float, 3>& values) {
    return at::tensor(std::vector<float>(values.begin(), values.end()), at::kFloat).view({-1, 1, 1});
  };
  at::Tensor pixels;
  if (config_.do_normalize) {
    // Rescaling folded into the mean and std (in float32), as the processor fuses the two.
    at::Tensor mean = channel_tensor(config_.image_mean), std = channel_tensor(config_.image_std);
    if (config_.do_rescale) {
      mean = mean * (1.0 / config_.rescale_factor);
      std = std * (1.0 / config_.rescale_factor);
    }
    pixels = x.to(at::kFloat).sub(mean).div(std);
  } else if (config_.do_rescale) {
    pixels = x.to(at::kFloat) * config_.rescale_factor;
  } else {
    pixels = x.to(at::kFloat);
  }
  return pixels.contiguous();
}

at::Tensor DepthProcessor::postprocess(const at::Tensor& depth, int64_t height, int64_t width) const {
  const at::Tensor map = depth.to(at::kFloat).reshape({1, 1, depth.size(-2), depth.size(-1)});
  return at::upsample_bicubic2d(map, {height, width}, /*align_corners=*/false).reshape({height, width});
}

}  // namespace gaps::depth
