#pragma once
// Depth-Anything's image processing as transformers' DPTImageProcessor does it (the torchvision backend
// that AutoImageProcessor picks): resize to the configured size, optionally keeping the aspect ratio and
// rounding both sides to a multiple (14 for Depth-Anything), bicubic with antialiasing on the 8-bit image;
// rescale and normalise; and the predicted depth resampled back to the image size (bicubic, as
// post_process_depth_estimation does).
#include <array>
#include <utility>

#include <ATen/Tensor.h>
#include <nlohmann/json.hpp>
#include "absl/status/statusor.h"

namespace gaps::depth {

// preprocessor_config.json. Absent keys take DPTImageProcessor's defaults; options that change the
// result and are not implemented (padding, centre crop, a resampling filter other than bicubic) are
// refused by name.
struct DepthProcessorConfig {
  bool do_resize = true, do_rescale = true, do_normalize = true, keep_aspect_ratio = false;
  int64_t height = 384, width = 384, ensure_multiple_of = 1;
  double rescale_factor = 1.0 / 255.0;
  std::array<float, 3> image_mean = {0.5f, 0.5f, 0.5f}, image_std = {0.5f, 0.5f, 0.5f};
  static absl::StatusOr<DepthProcessorConfig> from_json(const nlohmann::json& config);
};

class DepthProcessor {
 public:
  explicit DepthProcessor(DepthProcessorConfig config) : config_(config) {}

  // The model input size for an image of height x width (DPT's get_resize_output_image_size: scale as
  // little as possible when keeping the aspect ratio; Python's round-half-to-even to the multiple).
  std::pair<int64_t, int64_t> input_size(int64_t height, int64_t width) const;

  // image: H x W x 3, uint8, or float in [0, 1] (quantised to 8 bits first: the processor works on the
  // 8-bit image, which is exact for photos decoded from 8-bit files). Returns 1 x 3 x h x w float32
  // pixel_values on the CPU.
  absl::StatusOr<at::Tensor> preprocess(const at::Tensor& image) const;

  // depth: h x w (or 1 x h x w) predicted depth; returns height x width float32 on the depth's device.
  at::Tensor postprocess(const at::Tensor& depth, int64_t height, int64_t width) const;

  const DepthProcessorConfig& config() const { return config_; }

 private:
  DepthProcessorConfig config_;
};

}  // namespace gaps::depth
